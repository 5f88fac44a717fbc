import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.proposals.features import (
    CENTRES,
    NUM_CHANNELS,
    NUM_GAUSSIANS,
    SIGMA,
    fisher_vectors,
    fisher_vectors_reference,
    gaussian_means,
    normalize_fisher_vectors,
    to_unit_sphere,
)
from factorydet_core.types import InputError

# Coordinates where the formulas have their edge cases: the cube's faces, the Gaussian centres, and
# centre +- sigma (|D| = 1, where D^2 - 1 cancels).
SPECIAL_COORDS = np.unique(
    np.round(np.concatenate([[-1.0, 1.0], CENTRES, CENTRES + SIGMA, CENTRES - SIGMA]), 9)
)


def channel_norms(features: np.ndarray) -> np.ndarray:
    """(S, 20) L2 norm of each channel across the 125 Gaussians."""
    return np.linalg.norm(features.reshape(len(features), NUM_CHANNELS, NUM_GAUSSIANS), axis=2)


def assert_unit_or_zero_channels(features: np.ndarray, atol: float = 1e-5) -> None:
    norms = channel_norms(features)
    assert (np.isclose(norms, 1.0, atol=atol) | np.isclose(norms, 0.0, atol=atol)).all(), norms


def mixed_sets(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Many sets (about 6k points): single points, small and medium random sets, one set of more than
    2048 points, and special coordinates sprinkled over all of them; rows shuffled."""
    sizes = [1] * 25 + rng.integers(2, 40, 80).tolist() + rng.integers(100, 500, 6).tolist() + [2100]
    rng.shuffle(sizes)
    set_ids = np.repeat(np.arange(len(sizes)), sizes)
    points = rng.uniform(-1, 1, (len(set_ids), 3))
    special = rng.random(len(points)) < 0.2
    points[special] = rng.choice(SPECIAL_COORDS, (special.sum(), 3))
    # Some single-point sets sit exactly on a special point (the whole point, not single coordinates).
    singles = np.flatnonzero(np.bincount(set_ids) == 1)
    for set_id, coords in zip(
        singles[:10],
        [
            (-1, -1, -1),
            (1, 1, 1),
            (0, 0, 0),
            (-0.8, 0.4, 0.8),
            (-0.6, 0.6, 1.0),
            (-1, 0.2, 0.6),
            (0.8, -0.8, -1),
            (0.6, -0.2, 0.0),
            (0.4, 0.4, 0.4),
            (1, -1, 0.2),
        ],
    ):
        points[set_ids == set_id] = coords
    order = rng.permutation(len(points))
    return points[order].astype(np.float32), set_ids[order]


def test_fast_path_matches_the_float64_reference():
    points, set_ids = mixed_sets(np.random.default_rng(3))
    assert len(points) > 2048 and np.bincount(set_ids).max() > 2048 and np.bincount(set_ids).min() == 1
    fast = fisher_vectors(points, set_ids)
    reference = fisher_vectors_reference(points, set_ids)
    assert fast.dtype == np.float32 and fast.shape == (set_ids.max() + 1, 20, 5, 5, 5)
    assert np.abs(fast - reference).max() < 1e-5


def test_fast_path_matches_the_reference_on_the_special_lattice():
    # One single-point set per lattice point of special coordinates (every |D| = 1 and D = 0 case).
    lattice = np.stack(np.meshgrid(SPECIAL_COORDS, SPECIAL_COORDS, SPECIAL_COORDS), -1).reshape(-1, 3)
    set_ids = np.arange(len(lattice))
    points = lattice.astype(np.float32)
    assert np.abs(fisher_vectors(points, set_ids) - fisher_vectors_reference(points, set_ids)).max() < 1e-5


def test_sets_are_independent_of_their_neighbours_in_the_chunking():
    rng = np.random.default_rng(5)
    big = rng.uniform(-1, 1, (2300, 3)).astype(np.float32)  # more than one 2048-point chunk
    small = rng.uniform(-1, 1, (1500, 3)).astype(np.float32)
    small_ids = rng.integers(0, 300, 1500)
    small_ids = np.unique(small_ids, return_inverse=True)[1]
    num_small = small_ids.max() + 1
    alone_big = fisher_vectors(big, np.zeros(len(big), np.int64))
    alone_small = fisher_vectors(small, small_ids)
    together = fisher_vectors(
        np.concatenate([small, big]), np.concatenate([small_ids, np.full(len(big), num_small)])
    )
    np.testing.assert_allclose(together[:num_small], alone_small, atol=1e-6)
    np.testing.assert_allclose(together[num_small], alone_big[0], atol=1e-6)


@st.composite
def sets_and_permutation(draw):
    """Random continuous points (so no exactly mirror-symmetric sets), set structure and a permutation
    chosen by hypothesis."""
    num_points = draw(st.integers(1, 80))
    num_sets = draw(st.integers(1, min(num_points, 6)))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    set_ids = np.concatenate([np.arange(num_sets), rng.integers(0, num_sets, num_points - num_sets)])
    points = rng.uniform(-1.2, 1.2, (num_points, 3)).astype(np.float32)
    permutation = np.array(draw(st.permutations(range(num_points))), dtype=np.int64)
    return points, set_ids, permutation


@given(sets_and_permutation())
@settings(max_examples=60, deadline=None)
def test_features_do_not_depend_on_point_order(data):
    points, set_ids, permutation = data
    original = fisher_vectors(points, set_ids)
    permuted = fisher_vectors(points[permutation], set_ids[permutation])
    assert np.abs(original - permuted).max() < 1e-5


def test_every_channel_has_unit_or_zero_norm():
    points, set_ids = mixed_sets(np.random.default_rng(4))
    features = fisher_vectors(points, set_ids)
    assert np.isfinite(features).all()
    assert_unit_or_zero_channels(features)
    # Channels are normalised, not all zero: most of them carry information.
    assert (channel_norms(features) > 0.5).mean() > 0.5


def test_raw_aggregates_are_returned_unnormalised():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (50, 3)).astype(np.float32)
    set_ids = np.repeat([0, 1], 25)
    raw = fisher_vectors(points, set_ids, normalize=False)
    assert raw.shape == (2, 20, 5, 5, 5)
    np.testing.assert_allclose(normalize_fisher_vectors(raw), fisher_vectors(points, set_ids), atol=1e-6)
    # a_sum = (sum_t Q_tk - T w) / (T sqrt w) sums to 0 over the Gaussians (soft assignments sum to 1).
    np.testing.assert_allclose(raw[:, 1].reshape(2, -1).sum(axis=1), 0.0, atol=1e-5)


def test_zero_sets_give_an_empty_result():
    points = np.zeros((0, 3), np.float32)
    assert fisher_vectors(points, np.zeros(0, np.int64)).shape == (0, 20, 5, 5, 5)
    assert fisher_vectors(points, np.zeros(0, np.int64), num_sets=0).shape == (0, 20, 5, 5, 5)
    assert fisher_vectors_reference(points, np.zeros(0, np.int64)).shape == (0, 20, 5, 5, 5)


@pytest.mark.parametrize(
    ("points", "set_ids", "num_sets", "match"),
    [
        (np.array([[0.0, np.nan, 0.0]], np.float32), np.array([0]), None, "NaN"),
        (np.array([[0.0, np.inf, 0.0]], np.float32), np.array([0]), None, "NaN or Inf"),
        (np.zeros((2, 3), np.float32), np.array([0, -1]), None, ">= 0"),
        (np.zeros((2, 3), np.float32), np.array([0, 2]), None, "at least one point"),  # set 1 is empty
        (np.zeros((2, 3), np.float32), np.array([0, 0]), 2, "at least one point"),
        (np.zeros((2, 3), np.float32), np.array([0, 3]), 2, "< num_sets"),
        (np.zeros((2, 2), np.float32), np.array([0, 0]), None, "shape"),
        (np.zeros((2, 3), np.float32), np.array([0, 0, 0]), None, "shape"),
        (np.zeros(3, np.float32), np.array([0]), None, "shape"),
    ],
)
def test_bad_input_raises_input_error(points, set_ids, num_sets, match):
    with pytest.raises(InputError, match=match):
        fisher_vectors(points, set_ids, num_sets)
    with pytest.raises(InputError, match=match):
        fisher_vectors_reference(points, set_ids, num_sets)
    with pytest.raises(InputError, match=match):
        to_unit_sphere(points, set_ids, num_sets)


def test_gaussian_means_follow_the_documented_order():
    means = gaussian_means()
    assert means.shape == (125, 3)
    for i, j, k in [(0, 0, 0), (1, 2, 3), (4, 0, 2), (4, 4, 4)]:
        np.testing.assert_allclose(means[i * 25 + j * 5 + k], [CENTRES[i], CENTRES[j], CENTRES[k]])
    np.testing.assert_allclose(CENTRES, [-0.8, -0.4, 0.0, 0.4, 0.8], atol=1e-12)
    assert len(np.unique(means, axis=0)) == 125


def test_a_single_point_is_assigned_to_its_nearest_gaussian():
    # The point sits on Gaussian (i, j, l) = (1, 3, 4); its a_max channel peaks there.
    point = np.array([[CENTRES[1], CENTRES[3], CENTRES[4]]], np.float32)
    features = fisher_vectors(point, np.array([0]))
    a_max = features[0, 0].reshape(-1)
    assert int(np.argmax(a_max)) == 1 * 25 + 3 * 5 + 4


def test_normalize_takes_the_signed_root_and_normalises_each_channel():
    raw = np.zeros((1, 20, 125))
    raw[0, 0, 0], raw[0, 0, 1] = 4.0, -9.0  # roots 2 and -3
    raw[0, 1, 7] = 1e-14  # below the 1e-12 threshold: counts as zero
    raw[0, 2, :] = 1.0
    out = normalize_fisher_vectors(raw)
    assert out.shape == (1, 20, 5, 5, 5) and out.dtype == np.float32
    flat = out.reshape(20, 125)
    np.testing.assert_allclose(flat[0, :2], np.array([2.0, -3.0]) / np.sqrt(13.0), rtol=1e-6)
    assert not flat[0, 2:].any()
    assert not flat[1].any()
    np.testing.assert_allclose(flat[2], 1 / np.sqrt(125), rtol=1e-6)
    assert not flat[3:].any()
    np.testing.assert_array_equal(normalize_fisher_vectors(raw.reshape(1, 20, 5, 5, 5)), out)


def test_to_unit_sphere_centres_and_scales_each_set():
    rng = np.random.default_rng(1)
    points = np.concatenate(
        [rng.normal(10.0, 3.0, (40, 3)), rng.normal(-5.0, 0.01, (30, 3)), [[7.0, 8.0, 9.0]]]
    )
    set_ids = np.repeat([0, 1, 2], [40, 30, 1])
    unit = to_unit_sphere(points, set_ids)
    assert unit.dtype == np.float32 and unit.shape == points.shape
    for s in (0, 1):
        chosen = unit[set_ids == s].astype(np.float64)
        assert np.linalg.norm(chosen, axis=1).max() == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose((chosen.min(0) + chosen.max(0)) / 2, 0.0, atol=1e-6)
    np.testing.assert_array_equal(unit[set_ids == 2], 0.0)
    # Shape is preserved: distance ratios within a set do not change.
    before, after = points[set_ids == 0], unit[set_ids == 0].astype(np.float64)
    ratios = np.linalg.norm(after[1:] - after[:-1], axis=1) / np.linalg.norm(before[1:] - before[:-1], axis=1)
    np.testing.assert_allclose(ratios, ratios[0], rtol=1e-5)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_large_sets_keep_reference_accuracy(seed):
    # a_sum = sum Q - T w cancels over thousands of points; float32 sums broke the 1e-5 bound here.
    points = np.random.default_rng(seed).uniform(-1, 1, (3000, 3)).astype(np.float32)
    set_ids = np.zeros(len(points), np.int64)
    assert np.abs(fisher_vectors(points, set_ids) - fisher_vectors_reference(points, set_ids)).max() < 1e-5


def test_symmetric_sets_match_the_reference_in_any_point_order():
    # Sums of a symmetric set are exactly 0; the signed square root must not amplify rounding there.
    corners = np.array([[x, y, z] for x in (-0.3, 0.3) for y in (-0.3, 0.3) for z in (-0.3, 0.3)], np.float32)
    set_ids = np.zeros(8, np.int64)
    reference = fisher_vectors_reference(corners, set_ids)
    rng = np.random.default_rng(0)
    for _ in range(5):
        shuffled = corners[rng.permutation(8)]
        assert np.abs(fisher_vectors(shuffled, set_ids) - reference).max() < 1e-5
