import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.nms import nms_3d, vote_boxes
from factorydet_core.types import InputError

BOX = np.array([0, 0, 0.5, 2, 1, 1, 0.3])


def test_identical_boxes_keep_the_best():
    keep, by = nms_3d(np.stack([BOX, BOX, BOX]), np.array([0.2, 0.9, 0.5]), 0.5)
    assert keep.tolist() == [1]
    assert by.tolist() == [1, -1, 1]


def test_disjoint_boxes_all_kept_by_score():
    boxes = np.stack([BOX, BOX + [5, 0, 0, 0, 0, 0, 0], BOX + [0, 5, 0, 0, 0, 0, 0]])
    keep, by = nms_3d(boxes, np.array([0.1, 0.3, 0.2]), 0.0)
    assert keep.tolist() == [1, 2, 0]
    assert (by == -1).all()


def test_rotated_box_threshold_is_strict():
    turned = BOX + [0, 0, 0, 0, 0, 0, np.pi / 2]  # IoU 1/3 with BOX
    boxes = np.stack([BOX, turned])
    assert nms_3d(boxes, np.array([1.0, 0.5]), 0.3)[0].tolist() == [0]
    assert nms_3d(boxes, np.array([1.0, 0.5]), 0.34)[0].tolist() == [0, 1]
    assert nms_3d(boxes, np.array([1.0, 0.5]), 1 / 3 + 1e-9)[0].tolist() == [0, 1]


def test_nested_box_and_chain():
    inner = np.array([0, 0, 0.5, 1, 0.5, 0.5, 0.3])  # IoU 1/8 with BOX
    boxes = np.stack([BOX, inner])
    assert nms_3d(boxes, np.array([0.5, 1.0]), 0.1)[0].tolist() == [1]
    # A chain a-b-c: b is suppressed by a, so c (which only overlaps b) survives.
    chain = np.stack([BOX, BOX + [1.0, 0, 0, 0, 0, 0, 0], BOX + [2.0, 0, 0, 0, 0, 0, 0]])
    chain[:, 6] = 0
    keep, by = nms_3d(chain, np.array([0.9, 0.8, 0.7]), 0.2)
    assert keep.tolist() == [0, 2] and by.tolist() == [-1, 0, -1]


def test_class_aware_nms_keeps_other_classes():
    boxes = np.stack([BOX, BOX])
    assert nms_3d(boxes, np.array([1.0, 0.5]), 0.5, class_ids=np.array([0, 1]))[0].tolist() == [0, 1]
    assert nms_3d(boxes, np.array([1.0, 0.5]), 0.5, class_ids=np.array([2, 2]))[0].tolist() == [0]


def test_empty_and_bad_input():
    keep, by = nms_3d(np.zeros((0, 7)), np.zeros(0))
    assert keep.shape == (0,) and by.shape == (0,)
    with pytest.raises(InputError):
        nms_3d(np.stack([BOX]), np.array([0.1, 0.2]))
    with pytest.raises(InputError):
        nms_3d(np.stack([BOX]), np.array([0.1]), iou_threshold=1.5)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.05, 0.9))
def test_kept_boxes_do_not_overlap_and_suppressed_ones_do(seed, threshold):
    rng = np.random.default_rng(seed)
    n = 30
    boxes = np.column_stack(
        [
            rng.uniform(-2, 2, (n, 2)),
            rng.uniform(0, 0.5, n),
            rng.uniform(0.3, 1.5, (n, 3)),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    scores = rng.uniform(size=n)
    keep, by = nms_3d(boxes, scores, threshold)
    iou = box_iou_3d(boxes, boxes)
    kept_iou = iou[np.ix_(keep, keep)] - np.eye(len(keep))
    assert (kept_iou <= threshold + 1e-12).all()
    for i in np.flatnonzero(by >= 0):
        assert iou[i, by[i]] > threshold and scores[by[i]] >= scores[i]
    assert set(keep.tolist()) | set(np.flatnonzero(by >= 0).tolist()) == set(range(n))


def test_a_box_without_voters_is_unchanged_and_a_close_voter_pulls_it_by_its_weight():
    far = BOX + [9, 0, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(vote_boxes(np.stack([BOX, far]), np.array([0.9, 0.8]), [0]), BOX[None])
    shifted = BOX + [0.2, 0, 0, 0.4, 0, 0, 0]  # IoU 2/2.4 with BOX
    voted = vote_boxes(np.stack([BOX, shifted]), np.array([0.5, 0.5]), [0], iou_threshold=0.4)
    # Equal scores: the kept box weighs score x 1, the other score x its IoU with it.
    iou = box_iou_3d(BOX[None], shifted[None])[0, 0]
    weights = np.array([1.0, iou]) / (1.0 + iou)
    np.testing.assert_allclose(voted[0, 0], weights @ [BOX[0], shifted[0]])
    np.testing.assert_allclose(voted[0, 3], np.exp(weights @ np.log([BOX[3], shifted[3]])))
    assert voted[0, 6] == BOX[6]  # the heading is the kept box's
    # Above the threshold, the other box does not vote.
    alone = vote_boxes(np.stack([BOX, shifted]), np.array([0.5, 0.5]), [0], 0.9)
    np.testing.assert_allclose(alone, BOX[None])


def test_only_the_kept_boxes_class_votes():
    shifted = BOX + [0.1, 0, 0, 0, 0, 0, 0]
    boxes, scores = np.stack([BOX, shifted]), np.array([0.9, 0.9])
    np.testing.assert_allclose(vote_boxes(boxes, scores, [0], 0.4, class_ids=np.array([0, 1])), BOX[None])
    assert vote_boxes(boxes, scores, [0], 0.4, class_ids=np.array([1, 1]))[0, 0] > 0.04


@settings(max_examples=60, deadline=None)
@given(
    centre=st.tuples(*[st.floats(-20, 20)] * 3),
    dims=st.tuples(*[st.floats(0.2, 3.0)] * 3),
    yaw=st.floats(-np.pi, np.pi),
    shift=st.tuples(*[st.floats(-50, 50)] * 3),
    scores=st.tuples(*[st.floats(0.05, 1.0)] * 3),
)
def test_voting_sees_one_box_in_its_forms_and_moves_with_the_boxes(centre, dims, yaw, shift, scores):
    box = np.array([*centre, *dims, yaw])
    # The same box turned by 90 degrees with length and width swapped, and turned by 180 degrees.
    turned = np.array([*centre, dims[1], dims[0], dims[2], yaw + np.pi / 2])
    flipped = box + [0, 0, 0, 0, 0, 0, np.pi]
    voters = np.stack([box, turned, flipped])
    voted = vote_boxes(voters, np.array(scores), [0], iou_threshold=0.5)
    np.testing.assert_allclose(voted[0], box, atol=1e-6)
    # Translation equivariance, with a second box that really votes.
    other = box + [0.05 * dims[0], 0, 0.02, 0, 0, 0, 0]
    voters = np.stack([box, other])
    moved = voters + [*shift, 0, 0, 0, 0]
    a = vote_boxes(voters, np.array(scores[:2]), [1], 0.3)
    b = vote_boxes(moved, np.array(scores[:2]), [1], 0.3)
    np.testing.assert_allclose(b[0, :3], a[0, :3] + shift, atol=1e-6)
    np.testing.assert_allclose(b[0, 3:], a[0, 3:], atol=1e-9)
    # The voted centre lies between the voters'.
    assert (a[0, :3] >= voters[:, :3].min(axis=0) - 1e-9).all()
    assert (a[0, :3] <= voters[:, :3].max(axis=0) + 1e-9).all()


def test_voting_rejects_bad_input():
    with pytest.raises(InputError):
        vote_boxes(np.stack([BOX]), np.array([0.5]), [1])
    with pytest.raises(InputError):
        vote_boxes(np.stack([BOX]), np.array([0.5]), [0], iou_threshold=0.0)
    with pytest.raises(InputError):
        vote_boxes(np.stack([BOX]), np.array([np.nan]), [0])
    assert vote_boxes(np.stack([BOX]), np.array([0.5]), []).shape == (0, 7)
