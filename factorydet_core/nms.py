"""3D non-maximum suppression on oriented boxes (paper §3.6)."""

from __future__ import annotations

import numpy as np

from .boxes import box_iou_3d
from .types import InputError, check_array


def nms_3d(
    boxes: np.ndarray,
    scores: np.ndarray,
    iou_threshold: float = 0.25,
    class_ids: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy 3D NMS: visit boxes by decreasing score, keep a box unless a kept box overlaps it.

    A box is suppressed when its exact oriented 3D IoU (``boxes.box_iou_3d``) with a kept, higher
    scored box is strictly greater than ``iou_threshold``.

    Args:
        boxes: (M, 7) boxes.
        scores: (M,) scores; ties keep the lower index first.
        iou_threshold: suppression threshold in [0, 1].
        class_ids: (M,) optional; when given only boxes of the same class suppress each other.

    Returns:
        ``(keep_ids, suppressed_by)``: (K,) indices of kept boxes by decreasing score, and (M,) the
        index of the kept box that suppressed each box (-1 for kept boxes).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float64)
    check_array(scores, (len(boxes),), name="scores", finite=True)
    if not 0.0 <= iou_threshold <= 1.0:
        raise InputError(f"iou_threshold must lie in [0, 1], got {iou_threshold}")
    if class_ids is not None:
        class_ids = np.asarray(class_ids)
        check_array(class_ids, (len(boxes),), name="class_ids")
    suppressed_by = np.full(len(boxes), -1, np.int64)
    if not len(boxes):
        return np.zeros(0, np.int64), suppressed_by
    order = np.lexsort((np.arange(len(boxes)), -scores))
    overlap = box_iou_3d(boxes[order], boxes[order]) > iou_threshold
    if class_ids is not None:
        overlap &= class_ids[order][:, None] == class_ids[order][None, :]
    alive = np.ones(len(order), bool)
    keep = []
    for rank in range(len(order)):
        if not alive[rank]:
            continue
        keep.append(rank)
        hit = overlap[rank] & alive
        hit[: rank + 1] = False
        suppressed_by[order[hit]] = order[rank]
        alive &= ~hit
    return order[np.array(keep, np.int64)], suppressed_by
