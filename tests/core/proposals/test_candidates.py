import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import fit_box
from factorydet_core.proposals.candidates import (
    build_proposals,
    candidate_patch_sets,
    normalize_channels,
    snap_to_floor,
)
from factorydet_core.proposals.features import fisher_vectors, to_unit_sphere
from factorydet_core.proposals.voxels import voxel_fisher_vectors, voxelize
from factorydet_core.types import InputError, MergedCloud, Segmentation

VOXEL = 0.5


def hand_made_case():
    """Three voxels A, B, C of 0.5 m and two patches:

    patch 0: 3 points in A, 1 point in B;  patch 1: 2 points in B, 1 point in C.
    Patch 0 and patch 1 are separate final segments; the merge history holds their union.
    """
    rng = np.random.default_rng(0)
    cells = {"A": (0, 0, 0), "B": (1, 0, 0), "C": (1, 1, 0)}
    layout = [("A", 0), ("A", 0), ("A", 0), ("B", 0), ("B", 1), ("B", 1), ("C", 1)]
    points = np.array(
        [(np.array(cells[c]) + rng.uniform(0.1, 0.9, 3)) * VOXEL for c, _ in layout], np.float32
    )
    patch_ids = np.array([p for _, p in layout])
    segmentation = Segmentation(
        patch_ids=patch_ids,
        segment_ids=patch_ids,
        patch_segment_ids=np.array([0, 1]),
        merge_history=((0, 1),),
    )
    cloud = MergedCloud(
        points=points,
        sensor_ids=np.zeros(len(points), np.int16),
        point_instance_ids=np.zeros(len(points), np.int64),
        T_vehicle_sensor=np.eye(4)[None],
    )
    grid = voxelize(points, VOXEL)
    assert grid.num_voxels == 3
    voxel_of = {
        name: grid.point_voxel_ids[layout.index((name, p))] for name, p in [("A", 0), ("B", 0), ("C", 1)]
    }
    return points, segmentation, grid, voxel_fisher_vectors(cloud, grid), voxel_of


def expected_feature(voxel_features: np.ndarray, weights: dict[int, float]) -> np.ndarray:
    """Per-channel L2 normalisation of the weighted mean of voxel features (Eq. 7), in float64."""
    mean = sum(w * voxel_features[v].astype(np.float64) for v, w in weights.items()) / sum(weights.values())
    flat = mean.reshape(20, 125)
    return (flat / np.linalg.norm(flat, axis=1, keepdims=True)).reshape(20, 5, 5, 5)


def test_aggregated_feature_is_the_normalised_points_weighted_mean_of_voxel_features():
    points, segmentation, grid, voxel_features, v = hand_made_case()
    proposals = build_proposals(
        points, segmentation, grid, voxel_features, min_points=1, complete_boxes=False, include_history=True
    )
    assert proposals.patch_sets == ((0,), (1,), (0, 1))
    np.testing.assert_array_equal(proposals.level, [0, 0, 1])
    np.testing.assert_array_equal(proposals.num_points, [4, 3, 7])
    np.testing.assert_array_equal(proposals.num_voxels, [2, 2, 3])
    assert proposals.features.dtype == np.float32
    expected = [
        expected_feature(voxel_features, {v["A"]: 3, v["B"]: 1}),
        expected_feature(voxel_features, {v["B"]: 2, v["C"]: 1}),
        expected_feature(voxel_features, {v["A"]: 3, v["B"]: 3, v["C"]: 1}),
    ]
    np.testing.assert_allclose(proposals.features, np.stack(expected), atol=1e-6)
    # The weights matter: the unweighted mean is a different vector.
    assert (
        np.abs(proposals.features[0] - expected_feature(voxel_features, {v["A"]: 1, v["B"]: 1})).max() > 1e-3
    )


def test_uniform_weighting_gives_every_voxel_the_same_weight():
    points, segmentation, grid, voxel_features, v = hand_made_case()
    proposals = build_proposals(
        points, segmentation, grid, voxel_features, min_points=1, complete_boxes=False, weighting="uniform"
    )
    np.testing.assert_allclose(
        proposals.features[2], expected_feature(voxel_features, {v["A"]: 1, v["B"]: 1, v["C"]: 1}), atol=1e-6
    )


def test_direct_feature_is_the_fisher_vector_of_the_proposals_points():
    points, segmentation, grid, voxel_features, _ = hand_made_case()
    proposals = build_proposals(
        points, segmentation, grid, voxel_features, min_points=1, complete_boxes=False, feature="direct"
    )
    assert proposals.features.shape == (3, 20, 5, 5, 5)
    members = [np.flatnonzero(segmentation.patch_ids == 0), np.flatnonzero(segmentation.patch_ids == 1)]
    for index, chosen in enumerate([members[0], members[1], np.concatenate(members)]):
        ids = np.zeros(len(chosen), np.int64)
        expected = fisher_vectors(to_unit_sphere(points[chosen], ids), ids)[0]
        np.testing.assert_allclose(proposals.features[index], expected, atol=1e-5)
    # Direct features do not read the voxels' (the detector then skips computing them).
    without = build_proposals(
        points, segmentation, grid, None, min_points=1, complete_boxes=False, feature="direct"
    )
    np.testing.assert_array_equal(without.features, proposals.features)
    with pytest.raises(InputError, match="voxel features"):
        build_proposals(points, segmentation, grid, None, min_points=1, feature="aggregated")


def test_feature_none_gives_the_same_proposals_without_their_3dmfv():
    points, segmentation, grid, voxel_features, _ = hand_made_case()
    direct = build_proposals(points, segmentation, grid, None, min_points=1, feature="direct")
    none = build_proposals(points, segmentation, grid, None, min_points=1, feature="none")
    assert none.features is None and direct.features is not None
    assert none.patch_sets == direct.patch_sets
    np.testing.assert_array_equal(none.boxes, direct.boxes)
    np.testing.assert_array_equal(none.box_kind, direct.box_kind)
    np.testing.assert_array_equal(none.num_voxels, direct.num_voxels)
    empty = build_proposals(points, segmentation, grid, None, min_points=100, feature="none")
    assert len(empty) == 0 and empty.features is None
    with pytest.raises(InputError, match="'none'"):
        build_proposals(points, segmentation, grid, None, min_points=1, feature="raw")


def test_boxes_are_fitted_to_the_proposals_points():
    points, segmentation, grid, voxel_features, _ = hand_made_case()
    proposals = build_proposals(
        points, segmentation, grid, voxel_features, min_points=1, complete_boxes=False
    )
    np.testing.assert_allclose(proposals.boxes[0], fit_box(points[segmentation.patch_ids == 0]))
    np.testing.assert_allclose(proposals.boxes[2], fit_box(points))


def test_min_points_and_completion():
    points, segmentation, grid, voxel_features, _ = hand_made_case()
    only_big = build_proposals(points, segmentation, grid, voxel_features, min_points=4, complete_boxes=False)
    assert only_big.patch_sets == ((0,), (0, 1))
    none = build_proposals(points, segmentation, grid, voxel_features, min_points=8)
    assert len(none) == 0 and none.features.shape == (0, 20, 5, 5, 5) and none.boxes.shape == (0, 7)
    completed = build_proposals(
        points, segmentation, grid, voxel_features, min_points=1, complete_boxes=True, align_to_scene=False
    )
    assert completed.scene_heading is None
    extra = completed.box_kind > 0
    # Every candidate gets a view-completed box; narrow ones also their own box completed.
    assert (completed.box_kind == 2).sum() == 3 and (completed.box_kind == 1).sum() >= 1
    assert extra.sum() == len(completed) - 3
    np.testing.assert_allclose(completed.boxes[extra, 3], completed.boxes[extra, 4])
    # A completed proposal repeats its segment's patches and feature.
    originals = [completed.patch_sets.index(completed.patch_sets[i]) for i in np.flatnonzero(extra)]
    assert all(completed.box_kind[i] == 0 for i in originals)
    np.testing.assert_array_equal(completed.features[extra], completed.features[originals])


def test_bad_arguments_raise():
    points, segmentation, grid, voxel_features, _ = hand_made_case()
    with pytest.raises(InputError, match="weighting"):
        build_proposals(points, segmentation, grid, voxel_features, weighting="median")
    with pytest.raises(InputError, match="feature"):
        build_proposals(points, segmentation, grid, voxel_features, feature="learned")
    with pytest.raises(InputError, match="same cloud"):
        build_proposals(points[:-1], segmentation, grid, voxel_features)
    with pytest.raises(InputError, match="voxel features"):
        build_proposals(points, segmentation, grid, voxel_features[:2])


def test_candidate_patch_sets_levels():
    segmentation = Segmentation(
        patch_ids=np.array([0, 1, 2, 3]),
        segment_ids=np.array([0, 0, 0, 1]),
        patch_segment_ids=np.array([0, 0, 0, 1]),
        merge_history=((0, 1), (0, 1, 2)),
    )
    sets, levels = candidate_patch_sets(segmentation, include_history=True, include_patches=True)
    # Each set once, at its lowest level: (0, 1, 2) is a final segment and (3,) both a segment and a patch.
    assert sets == [(0, 1, 2), (3,), (0, 1), (0,), (1,), (2,)]
    assert levels == [0, 0, 1, 2, 2, 2]
    assert candidate_patch_sets(segmentation, include_history=False)[0] == [(0, 1, 2), (3,)]


def test_snap_to_floor_extends_boxes_just_above_the_floor():
    boxes = np.array([[0, 0, 0.6, 1, 1, 1.0, 0], [0, 0, 1.0, 1, 1, 1.0, 0], [0, 0, 0.4, 1, 1, 1.0, 0]])
    snapped = snap_to_floor(boxes, np.array([0, 0, 1.0, 0.0]))
    np.testing.assert_allclose(snapped[0], [0, 0, 0.55, 1, 1, 1.1, 0])  # bottom 0.1 above: snapped
    np.testing.assert_allclose(snapped[1], boxes[1])  # bottom 0.5 above: kept
    np.testing.assert_allclose(snapped[2], boxes[2])  # already through the floor: kept
    np.testing.assert_allclose(snap_to_floor(boxes, None), boxes)
    np.testing.assert_allclose(snap_to_floor(boxes, np.full(4, np.nan)), boxes)


def test_normalize_channels_gives_unit_channels():
    rng = np.random.default_rng(0)
    features = rng.normal(size=(3, 20, 5, 5, 5))
    features[1, 4] = 0.0
    out = normalize_channels(features)
    norms = np.linalg.norm(out.reshape(3, 20, 125), axis=2)
    expected = np.ones((3, 20))
    expected[1, 4] = 0.0
    np.testing.assert_allclose(norms, expected, atol=1e-6)


@given(
    st.lists(st.integers(0, 6), min_size=0, max_size=40),
    st.lists(st.lists(st.integers(0, 6), max_size=4, unique=True), max_size=12),
)
@settings(max_examples=80, deadline=None)
def test_point_sets_gathers_each_set_patch_after_patch(patch_list, patch_sets):
    from factorydet_core.proposals.candidates import point_sets

    patch_ids = np.array(patch_list, np.int64)
    num_patches = int(patch_ids.max()) + 1 if len(patch_ids) else 0
    patch_sets = [tuple(p for p in s if p < num_patches) for s in patch_sets]
    lists = point_sets(patch_ids, patch_sets)
    assert len(lists) == len(patch_sets)
    for members, patch_set in zip(lists, patch_sets):
        expected = [i for p in patch_set for i in np.flatnonzero(patch_ids == p)]
        np.testing.assert_array_equal(members, np.array(expected, np.int64).reshape(-1))
