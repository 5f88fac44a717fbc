import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import box_iou_3d, rectangle_corners
from factorydet_core.detection.groups import (
    ANCHORS_PER_SIZE,
    DESCRIPTOR_NAMES,
    GROW_VARIANTS,
    OPTION_KINDS,
    BoxSizePrior,
    ProposalGroups,
    _size_modes,
    describe_point_sets,
    flatten_sets,
    rank_within_sets,
)
from factorydet_core.detection.scoring import score_groups, select_detections
from factorydet_core.types import InputError

CLASSES = ("small", "long")
PRIOR = BoxSizePrior(np.array([[0.6, 0.6, 0.9], [4.0, 2.0, 2.5]]))


def groups_of(group_ids, num_features=None) -> ProposalGroups:
    group_ids = np.asarray(group_ids)
    num = int(group_ids.max()) + 1
    reps = np.array([np.flatnonzero(group_ids == g)[0] for g in range(num)])
    return ProposalGroups(
        group_ids, reps, np.zeros((num, 20, 5, 5, 5), np.float32), np.zeros((num, len(DESCRIPTOR_NAMES)))
    )


def test_prior_from_boxes_uses_sorted_horizontal_sizes():
    boxes = np.array([[0, 0, 0, 1, 2, 3, 0], [0, 0, 0, 2, 1, 5, 0], [0, 0, 0, 9, 9, 9, 0]], float)
    prior = BoxSizePrior.from_boxes(boxes, np.array([0, 0, 1]), 3)
    np.testing.assert_allclose(prior.sizes[0], [2, 1, 4])
    assert np.isnan(prior.sizes[2]).all()
    again = BoxSizePrior.from_json(prior.to_json())
    np.testing.assert_allclose(again.sizes, prior.sizes)


def test_grow_extends_away_from_the_viewpoint_and_up():
    # A 1 m long visible face of a truck, 10 m ahead (along +x) and facing the vehicle.
    face = np.array([[10.0, 0.0, 0.5, 1.0, 0.2, 1.0, np.pi / 2]])  # dx along y, dy along x
    grown = PRIOR.grow(face, 1)[0]
    assert sorted(grown[3:5]) == pytest.approx([2.0, 4.0])
    assert grown[5] == pytest.approx(2.5)
    assert grown[2] - grown[5] / 2 == pytest.approx(0.0)  # the bottom stays put
    assert grown[0] > 10.0  # the hidden side is behind the face
    # Boxes already larger than the class are left alone.
    big = np.array([[0, 5, 2, 6, 3, 4, 0.0]])
    np.testing.assert_allclose(PRIOR.grow(big, 1), big)


def test_grow_splits_the_growth_of_an_axis_across_the_line_of_sight():
    # The visible top of a cone 5 m ahead: 0.2 m wide across the line of sight, 0.1 m deep.
    top = np.array([[5.0, 0.0, 0.3, 0.1, 0.2, 0.6, 0.0]])
    grown = PRIOR.grow(top, 0, size=np.array([0.4, 0.4, 0.6]))[0]
    assert grown[3:5] == pytest.approx([0.4, 0.4])
    assert grown[1] == pytest.approx(0.0)  # across the line of sight: both sides alike
    assert grown[0] == pytest.approx(5.15)  # along it: only away from the viewer
    # An axis at 60 degrees to the line of sight moves by half of the one-sided shift.
    oblique = np.array([[5.0, 0.0, 0.3, 0.2, 0.4, 0.6, np.pi / 3]])
    moved = PRIOR.grow(oblique, 0, size=np.array([0.4, 0.4, 0.6]))[0]
    np.testing.assert_allclose(moved[:2], [5.0 + 0.05 * np.cos(np.pi / 3), 0.05 * np.sin(np.pi / 3)])


def test_grow_can_put_the_length_on_the_short_side_and_part_of_it_towards_the_viewer():
    # A forklift's mast seen from the front, 10 m ahead: 1.0 m across the line of sight, 0.1 m deep.
    mast = np.array([[10.0, 0.0, 1.0, 0.1, 1.0, 2.0, 0.0]])
    size = np.array([3.0, 1.2, 2.0])
    lengthwise = PRIOR.grow(mast, 1, size=size)[0]
    assert lengthwise[3:5] == pytest.approx([1.2, 3.0])  # the face grows to the length
    crosswise = PRIOR.grow(mast, 1, size=size, crosswise=True)[0]
    assert crosswise[3:5] == pytest.approx([3.0, 1.2])  # the depth does
    assert crosswise[0] == pytest.approx(10.0 + 2.9 / 2)  # all of it away from the viewer
    shared = PRIOR.grow(mast, 1, size=size, near_share=0.3, crosswise=True)[0]
    # 30% of the 2.9 m growth towards the viewer: the near end 0.87 m before the mast's front.
    assert shared[0] - shared[3] / 2 == pytest.approx(9.95 - 0.3 * 2.9)
    assert shared[0] + shared[3] / 2 == pytest.approx(10.05 + 0.7 * 2.9)
    assert shared[1] == pytest.approx(0.0)
    # Each hypothesis is grown once per variant.
    options, _ = PRIOR.options(mast, 1)
    assert len(options) == 1 + len(GROW_VARIANTS)


def test_score_groups_picks_the_box_closest_to_the_class_size():
    proposal_boxes = np.array(
        [
            [5, 0, 0.45, 0.6, 0.3, 0.9, 0],  # group 0: a half-seen small object
            [5, 0, 0.45, 0.6, 0.6, 0.9, 0],  # group 0: its completed box
            [0, 9, 1, 1.0, 1.0, 2.0, 0],  # group 1
        ]
    )
    groups = groups_of([0, 0, 1])
    probabilities = np.array([[0.8, 0.1, 0.1], [0.1, 0.3, 0.6]], np.float32)
    cands = score_groups(proposal_boxes, groups, probabilities, PRIOR, CLASSES)
    assert cands.class_ids.tolist() == [0, 1]
    np.testing.assert_allclose(cands.scores, [0.8, 0.3])
    assert cands.proposal_ids[0] == 1
    np.testing.assert_allclose(cands.boxes[0], proposal_boxes[1])
    # Without a prior each set keeps its first box.
    plain = score_groups(proposal_boxes, groups, probabilities, None, CLASSES)
    assert plain.proposal_ids.tolist() == [0, 2]
    with pytest.raises(InputError):
        score_groups(proposal_boxes, groups, probabilities[:, :2], PRIOR, CLASSES)


def test_select_detections_thresholds_and_flags_suppressed():
    proposal_boxes = np.array([[0, 0, 0.5, 1, 1, 1, 0], [0.05, 0, 0.5, 1, 1, 1, 0], [5, 0, 0.5, 1, 1, 1, 0]])
    groups = groups_of([0, 1, 2])
    probabilities = np.array([[0.7, 0.1, 0.2], [0.9, 0.0, 0.1], [0.2, 0.4, 0.4]], np.float32)
    cands = score_groups(proposal_boxes, groups, probabilities, None, CLASSES)
    selected = select_detections(cands, score_threshold=0.5, nms_iou=0.25)
    assert selected.scores.tolist() == pytest.approx([0.9, 0.7])
    assert selected.suppressed_by.tolist() == [-1, 0]
    assert selected.proposal_ids.tolist() == [1, 0]
    assert len(select_detections(cands, 0.3, 0.25)) == 3
    assert select_detections(cands, 0.95, 0.25).boxes.shape == (0, 7)
    with pytest.raises(InputError):
        select_detections(cands, 1.5)
    # A threshold per class: the second class's 0.4 passes its own 0.35, class 0 needs 0.8.
    per_class = select_detections(cands, 0.5, 0.25, class_score_thresholds=np.array([0.8, 0.35]))
    assert per_class.scores.tolist() == pytest.approx([0.9, 0.4])
    assert per_class.class_ids.tolist() == [0, 1]
    # NaN falls back to the global threshold.
    fallback = select_detections(cands, 0.5, 0.25, class_score_thresholds=np.array([np.nan, 0.35]))
    assert fallback.scores.tolist() == pytest.approx([0.9, 0.7, 0.4])


def test_kept_detections_are_voted_on_by_the_candidates_that_overlap_them():
    # Two point sets of one object whose boxes straddle it, and a weak third one.
    proposal_boxes = np.array(
        [[0, 0, 0.5, 1, 1, 1, 0], [0.2, 0, 0.5, 1, 1, 1, 0], [0.1, 0.1, 0.5, 1, 1, 1, 0]]
    )
    groups = groups_of([0, 1, 2])
    probabilities = np.array([[0.9, 0.0, 0.1], [0.8, 0.0, 0.2], [0.2, 0.0, 0.8]], np.float32)
    cands = score_groups(proposal_boxes, groups, probabilities, None, CLASSES)
    plain = select_detections(cands, 0.5, 0.25, vote_iou=None)
    voted = select_detections(cands, 0.5, 0.25)
    np.testing.assert_array_equal(plain.boxes, cands.boxes[[0, 1]])  # by score; 1 suppressed by 0
    assert voted.suppressed_by.tolist() == [-1, 0]
    assert 0.0 < voted.boxes[0, 0] < 0.2 and voted.boxes[0, 1] > 0.0  # moved toward the voters
    np.testing.assert_array_equal(voted.boxes[1], plain.boxes[1])  # suppressed ones keep theirs
    # The weak candidate (0.2) votes at any operating threshold: a detection's box does not depend
    # on the threshold that shows it.
    low = select_detections(cands, 0.05, 0.25)
    np.testing.assert_allclose(low.boxes[0], voted.boxes[0])


def test_descriptors_of_a_flat_and_a_linear_set():
    rng = np.random.default_rng(0)
    plane = np.column_stack([rng.uniform(0, 2, 200), rng.uniform(0, 2, 200), np.zeros(200)])
    line = np.column_stack([rng.uniform(0, 3, 200), np.zeros(200), np.zeros(200)])
    points = np.concatenate([plane, line])
    boxes = np.array([[1, 1, 0, 2, 2, 0.02, 0], [1.5, 0, 0, 3, 0.02, 0.02, 0]])
    d = describe_point_sets(points, [np.arange(200), np.arange(200, 400)], boxes, np.array([100, 15]))
    names = list(DESCRIPTOR_NAMES)
    assert d[0, names.index("planarity")] > 0.8
    assert d[1, names.index("linearity")] > 0.9
    assert d[0, names.index("length_m")] == pytest.approx(2.0)


def _eigen_features_of_one_set(points: np.ndarray) -> np.ndarray:
    """The shape features of one set as the textbook gives them: the reference for the batch."""
    if len(points) < 3:
        return np.zeros(4)
    centred = points - points.mean(axis=0)
    values, vectors = np.linalg.eigh(centred.T @ centred / len(points))
    l3, l2, l1 = np.sqrt(np.maximum(values, 1e-12))
    return np.array([(l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, 1.0 - abs(vectors[2, 0])])


@given(st.integers(0, 2**31 - 1), st.lists(st.integers(0, 60), min_size=0, max_size=12))
@settings(max_examples=40, deadline=None)
def test_eigen_features_of_many_sets_at_once_equal_one_set_at_a_time(seed, sizes):
    from factorydet_core.detection.groups import eigen_features

    rng = np.random.default_rng(seed)
    points = rng.normal(size=(100, 3)) * rng.uniform(0.01, 3.0, size=3) + rng.uniform(-20, 20, size=3)
    point_lists = [rng.choice(100, size, replace=False) for size in sizes]
    batch = eigen_features(points, point_lists)
    assert batch.shape == (len(sizes), 4)
    for row, members in zip(batch, point_lists):
        np.testing.assert_allclose(row, _eigen_features_of_one_set(points[members]), atol=1e-7)


def _truck_boxes() -> tuple[np.ndarray, np.ndarray]:
    """Annotated pallet trucks (2.0 x 0.56 x 1.3) and forklifts (3.3 x 1.4 x 2.4), class 1, and
    one small object, class 0."""
    rng = np.random.default_rng(3)
    small = [[0, 0, 0, 2.0 + rng.normal(0, 0.02), 0.56, 1.3, 0] for _ in range(6)]
    large = [[0, 0, 0, 1.4, 3.3 + rng.normal(0, 0.02), 2.4, 0] for _ in range(4)]
    boxes = np.array(small + large + [[0, 0, 0, 0.6, 0.6, 0.9, 0]], float)
    return boxes, np.array([1] * 10 + [0])


def test_prior_keeps_range_and_one_mode_per_kind():
    boxes, class_ids = _truck_boxes()
    prior = BoxSizePrior.from_boxes(boxes, class_ids, 3)
    modes = prior.modes[1][np.argsort(prior.modes[1][:, 0])]
    np.testing.assert_allclose(modes, [[2.0, 0.56, 1.3], [3.3, 1.4, 2.4]], atol=0.05)
    np.testing.assert_allclose(prior.lower[1], [boxes[:6, 3].min(), 0.56, 1.3])
    np.testing.assert_allclose(prior.upper[1], [boxes[6:10, 4].max(), 1.4, 2.4])
    assert len(prior.modes[2]) == 0 and np.isnan(prior.lower[2]).all()
    again = BoxSizePrior.from_json(json.loads(json.dumps(prior.to_json())))  # as a checkpoint's note
    for got, want in ((again.sizes, prior.sizes), (again.lower, prior.lower), (again.upper, prior.upper)):
        np.testing.assert_array_equal(got, want)  # exactly: the saved model boxes as the one that ran
    for got, want in zip(again.modes, prior.modes):
        np.testing.assert_array_equal(got, want)
    # A checkpoint's prior from before the range: medians only, chosen as before.
    old = BoxSizePrior.from_json(prior.to_json()["median"])
    assert old.lower is None and old.modes is None


def test_options_keep_a_plausible_box_and_grow_a_partial_view_to_the_nearest_kind():
    boxes, class_ids = _truck_boxes()
    prior = BoxSizePrior.from_boxes(boxes, class_ids, 3)
    # A whole forklift, seen well: its own box is inside the range and is kept as it is.
    whole = np.array([[8.0, 0.0, 1.2, 3.25, 1.38, 2.4, 0.0]])
    options, cost = prior.options(whole, 1)
    np.testing.assert_allclose(options[np.argmin(cost)], whole[0])
    # The median alone would have grown it, or picked another size.
    assert prior.range_distance(whole, 1)[0] == 0.0 and prior.distance(whole, 1)[0] > 0.0
    # The visible 0.8 m of a pallet truck: grown to a pallet truck, not to a forklift.
    partial = np.array([[6.0, 0.0, 0.65, 0.8, 0.55, 1.3, 0.0]])
    options, cost = prior.options(partial, 1)
    chosen = options[np.argmin(cost)]
    np.testing.assert_allclose(sorted(chosen[3:5]), [0.56, 2.0], atol=0.06)
    assert chosen[5] == pytest.approx(1.3)
    assert chosen[0] > 6.0  # grown behind the visible end, away from the vehicle at the origin
    # A class never annotated keeps the hypotheses, at no cost.
    options, cost = prior.options(partial, 2)
    np.testing.assert_allclose(options, partial)
    assert (cost == 0).all()


@settings(max_examples=60, deadline=None)
@given(
    centre=st.tuples(*(st.floats(-20, 20),) * 3),
    dims=st.tuples(*(st.floats(0.2, 5.0),) * 3),
    yaw=st.floats(-np.pi, np.pi),
    size=st.tuples(*(st.floats(0.2, 3.0),) * 3),
)
def test_anchored_boxes_share_a_corner_and_a_face_with_their_box(centre, dims, yaw, size):
    box = np.array([[*centre, *dims, yaw]])
    anchored = PRIOR.anchored(box, np.array(size))
    assert anchored.shape == (ANCHORS_PER_SIZE, 7)
    np.testing.assert_allclose(anchored[:, 6], yaw)
    np.testing.assert_allclose(anchored[:, 5], size[2])
    # Length along the box's x axis, then along its y axis.
    np.testing.assert_allclose(anchored[:8, 3:5], np.tile(size[:2], (8, 1)))
    np.testing.assert_allclose(anchored[8:, 3:5], np.tile(size[1::-1], (8, 1)))
    bottom, top = centre[2] - dims[2] / 2, centre[2] + dims[2] / 2
    np.testing.assert_allclose(anchored[0::2, 2] - size[2] / 2, bottom, atol=1e-9)
    np.testing.assert_allclose(anchored[1::2, 2] + size[2] / 2, top, atol=1e-9)
    # Each keeps one of the box's four ground-plane corners as one of its own.
    own = rectangle_corners(box)[0]
    for corners in rectangle_corners(anchored):
        distance = np.linalg.norm(corners[:, None, :] - own[None, :, :], axis=2)
        assert distance.min() < 1e-6
    # A size equal to the box's gives the box back, wherever it is anchored.
    same = PRIOR.anchored(box, np.array(dims))[:8:2]
    np.testing.assert_allclose(box_iou_3d(same, box)[:, 0], 1.0, atol=1e-6)


def test_anchored_options_find_each_object_of_a_flush_stack():
    """Two crates side by side with flush faces make one segment: its fitted box holds each crate
    in a corner, and the anchored options contain both, where growing or the box itself do not."""
    prior = BoxSizePrior.from_boxes(np.array([[0, 0, 0, 1.2, 0.8, 0.6, 0.0]] * 3), np.zeros(3, int), 1)
    crates = np.array([[5.0, -0.6, 0.3, 1.2, 0.8, 0.6, 0.0], [5.0, 0.6, 0.3, 1.2, 0.8, 0.6, 0.0]])
    # Crates turned 90 degrees: their 1.2 m length lies along the world y axis.
    crates[:, 6] = np.pi / 2
    segment = np.array([[5.0, 0.0, 0.3, 0.8, 2.4, 0.6, 0.0]])
    plain, _ = prior.options(segment, 0)
    assert box_iou_3d(plain, crates).max() < 0.6
    options, cost, kinds, sources, _ = prior.option_sources(segment, 0, anchor_boxes=segment)
    assert (kinds == OPTION_KINDS.index("anchored")).sum() == ANCHORS_PER_SIZE
    assert (sources[kinds >= 2] == 0).all()
    np.testing.assert_allclose(box_iou_3d(options, crates).max(axis=0), 1.0, atol=1e-6)
    assert np.isfinite(cost).all()


def test_standing_options_find_an_object_whose_lower_part_is_unseen():
    """A cone beside the vehicle shows only its top, 0.2 m above the floor, seen from both sides
    (its fitted box is centred on it): growing that box away from the viewer and upwards misses
    the cone, the box of the cone's size standing on the floor under it does not."""
    cone = np.array([[0.45, -1.2, 0.32, 0.38, 0.38, 0.64, 0.0]])
    prior = BoxSizePrior.from_boxes(np.repeat(cone, 3, axis=0), np.zeros(3, int), 1)
    visible_top = np.array([[0.46, -1.17, 0.4, 0.23, 0.17, 0.41, 0.0]])
    plain, _ = prior.options(visible_top, 0)
    assert box_iou_3d(plain, cone).max() < 0.6
    options, _, kinds, _, _ = prior.option_sources(visible_top, 0, anchor_boxes=visible_top)
    standing = options[kinds == OPTION_KINDS.index("standing")]
    assert len(standing) == 1
    assert standing[0, 2] - standing[0, 5] / 2 == pytest.approx(0.0)
    assert box_iou_3d(standing, cone)[0, 0] > 0.8
    # A box on a shelf, well above the size's height, gets no standing option.
    on_shelf = visible_top + np.array([0, 0, 1.5, 0, 0, 0, 0])
    assert len(prior.standing(on_shelf, prior.class_modes(0)[0])[0]) == 0


def test_stacked_options_find_the_middle_object_of_a_stack():
    """Three pallets stacked make one segment; its corners hold the bottom and the top pallet, only
    the stacked options the middle one."""
    pallet = np.array([1.2, 0.8, 0.12])
    prior = BoxSizePrior.from_boxes(np.array([[0, 0, 0.06, *pallet, 0.0]] * 3), np.zeros(3, int), 1)
    gap = 0.02
    pallets = np.array([[2.0, -4.5, 0.06 + k * (0.12 + gap), *pallet, 0.0] for k in range(3)])
    stack = np.array([[2.0, -4.5, (3 * 0.12 + 2 * gap) / 2, *pallet[:2], 3 * 0.12 + 2 * gap, 0.0]])
    corners = prior.anchored(stack, pallet)
    found = box_iou_3d(corners, pallets).max(axis=0)
    assert found[0] > 0.99 and found[2] > 0.99 and found[1] < 0.6
    options, _, kinds, _, _ = prior.option_sources(stack, 0, anchor_boxes=stack)
    assert box_iou_3d(options, pallets).max(axis=0).min() > 0.7
    assert box_iou_3d(options[kinds == OPTION_KINDS.index("stacked")], pallets[1:2]).max() > 0.7
    # One pallet is not a stack: no stacked options.
    assert len(prior.stacked(pallets[:1], pallet)[0]) == 0
    # Anchors alone, without hypotheses, still give the placed boxes and a cost for each.
    placed, cost = prior.options(np.zeros((0, 7)), 0, fitted_boxes=np.zeros((0, 7)), anchor_boxes=stack)
    assert len(placed) == (kinds >= 2).sum() and np.isfinite(cost).all()


def test_near_duplicate_size_modes_are_merged():
    rng = np.random.default_rng(0)
    barrels = np.array([0.6, 0.6, 0.9]) * rng.uniform(0.98, 1.02, (60, 3))
    assert len(_size_modes(barrels, 8)) == 1
    crates = np.concatenate([barrels, np.array([1.15, 0.95, 0.5]) * rng.uniform(0.99, 1.01, (30, 3))])
    modes = _size_modes(crates, 8)
    assert len(modes) == 2
    np.testing.assert_allclose(np.sort(modes[:, 0]), [0.6, 1.15], rtol=0.03)


def test_best_option_iou_is_the_bound_of_the_anchored_options():
    from factorydet_core.detection.groups import best_option_iou

    prior = BoxSizePrior.from_boxes(np.array([[0, 0, 0, 1.2, 0.8, 0.6, 0.0]] * 3), np.zeros(3, int), 1)
    crates = np.array([[5.0, -0.6, 0.3, 0.8, 1.2, 0.6, 0.0], [5.0, 0.6, 0.3, 0.8, 1.2, 0.6, 0.0]])
    far = np.array([[-9.0, 9.0, 0.3, 0.8, 1.2, 0.6, 0.0]])
    # One set: the flush pair's box and a view-headed variant of it; nothing near the far crate.
    proposals = np.array([[5.0, 0.0, 0.3, 0.8, 2.4, 0.6, 0.0], [5.0, 0.0, 0.3, 2.4, 0.8, 0.6, np.pi / 2]])
    references = np.concatenate([crates, far])
    best = best_option_iou(references, np.zeros(3, int), proposals, np.zeros(2, int), prior)
    np.testing.assert_allclose(best, [1.0, 1.0, 0.0], atol=1e-6)
    plain = best_option_iou(references, np.zeros(3, int), proposals, np.zeros(2, int), prior, anchored=False)
    assert plain.max() < 0.6


def test_sizes_set_into_the_scene_aligned_box_find_a_round_object_on_a_shelf():
    from factorydet_core.detection.groups import best_option_iou
    from factorydet_core.proposals.candidates import box_hypotheses

    # A standing bobbin on a shelf built along the axes; its neighbours hide all but a quarter of
    # its round side, whose own box runs diagonally. No annotated bobbin had its size.
    rng = np.random.default_rng(0)
    truth = np.array([[2.6, 4.1, 1.79, 0.378, 0.378, 0.37, 0.0]])
    angles = np.radians(rng.uniform(180, 270, 60))
    points = np.column_stack(
        [2.6 + 0.189 * np.cos(angles), 4.1 + 0.189 * np.sin(angles), rng.uniform(1.62, 1.96, 60)]
    )
    sizes = np.array([[0.33, 0.326, 0.326]] * 6 + [[0.454, 0.454, 0.281]] * 6 + [[0.59, 0.59, 0.31]] * 5)
    annotated = np.column_stack([np.zeros((17, 3)), sizes, np.zeros(17)])
    prior = BoxSizePrior.from_boxes(annotated, np.zeros(17, int), 1)
    own = box_hypotheses(points)
    assert abs(own[0, 6]) > np.radians(30)  # the L-shape box is diagonal
    aligned = box_hypotheses(points, heading=0.0)
    np.testing.assert_allclose(aligned[: len(own)], own)
    anchor_mask = np.zeros(len(aligned), bool)
    anchor_mask[[0, len(own)]] = True  # the fitted box and the box at the scene's heading

    def bound(boxes, mask=None):
        return best_option_iou(truth, [0], boxes, np.zeros(len(boxes), int), prior, anchor_mask=mask)[0]

    assert bound(own) < 0.6
    assert bound(aligned, anchor_mask) > 0.65
    # The aligned hypotheses alone, without sizes set into them, fall short.
    assert bound(aligned) < bound(aligned, anchor_mask) - 0.01


def test_a_rare_kind_of_object_keeps_its_size_mode():
    # 28 forklifts and 2 pallet trucks (7 %): the trucks' size must stay an option.
    forklifts = np.tile([0, 0, 1.2, 3.4, 1.3, 2.3, 0.0], (28, 1))
    pallet_trucks = np.tile([0, 0, 0.6, 2.0, 0.6, 1.3, 0.0], (2, 1))
    prior = BoxSizePrior.from_boxes(np.vstack([forklifts, pallet_trucks]), np.zeros(30, int), 1)
    modes = prior.class_modes(0)
    assert len(modes) == 2
    np.testing.assert_allclose(sorted(modes.tolist()), [[2.0, 0.6, 1.3], [3.4, 1.3, 2.3]], atol=1e-9)
    # A single odd box is no mode.
    odd = np.vstack([forklifts, pallet_trucks[:1]])
    assert len(BoxSizePrior.from_boxes(odd, np.zeros(29, int), 1).class_modes(0)) == 1


@given(st.lists(st.tuples(st.integers(0, 5), st.integers(-3, 3)), min_size=1, max_size=60))
def test_rank_within_sets_orders_each_sets_rows_by_key_earlier_first_on_ties(rows):
    owners = np.array([o for o, _ in rows], np.int64)
    key = np.array([k for _, k in rows], np.float64)
    rank = rank_within_sets(owners, key)
    for owner in np.unique(owners):
        mine = np.flatnonzero(owners == owner)
        expected = sorted(mine.tolist(), key=lambda r: (key[r], r))
        assert rank[expected].tolist() == list(range(len(mine)))


def test_flatten_sets_lists_members_set_after_set():
    member_ids, owners, starts = flatten_sets([np.array([4, 2]), np.array([7]), np.array([1, 0, 3])])
    assert member_ids.tolist() == [4, 2, 7, 1, 0, 3]
    assert owners.tolist() == [0, 0, 1, 2, 2, 2] and starts.tolist() == [0, 2, 3]
