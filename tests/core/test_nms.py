import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import box_iou_3d
from factorydet_core.nms import nms_3d
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
