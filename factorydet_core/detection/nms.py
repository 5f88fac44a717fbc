"""3D non-maximum suppression on oriented boxes (paper §3.6)."""

from __future__ import annotations

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.types import InputError, check_array


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


def vote_boxes(
    boxes: np.ndarray,
    scores: np.ndarray,
    keep_ids: np.ndarray,
    iou_threshold: float = 0.4,
    class_ids: np.ndarray | None = None,
) -> np.ndarray:
    """Box voting after NMS: each kept box moved to the weighted mean of the boxes that overlap it.

    The detector's candidates come from discrete box options (the class's size modes placed by
    each point set's fitted box), so the right box of an object often lies between the boxes that
    several point sets chose for it, and NMS keeps only the best scored of them. Voting (as in
    Gidaris and Komodakis's multi-region detector) averages them: every box whose IoU with a kept
    box is at least ``iou_threshold`` (of the same class, with ``class_ids``) votes with the
    weight ``score * IoU``; the kept box itself is one of the voters (IoU 1). The centre is the
    weighted mean of the voters' centres, each size the weighted geometric mean of theirs, taken
    along the kept box's axes (a voter turned by more than 45 degrees from it has its length and
    width swapped); the heading stays the kept box's.

    Args:
        boxes: (M, 7) the voters, the kept boxes among them.
        scores: (M,) their scores (> 0 for a vote to count).
        keep_ids: (K,) indices of the kept boxes in ``boxes``.
        iou_threshold: least IoU of a voter with a kept box, in (0, 1].
        class_ids: (M,) optional; given, only boxes of the kept box's class vote.

    Returns:
        (K, 7) the voted boxes, in the order of ``keep_ids``.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    scores = np.asarray(scores, np.float64)
    check_array(scores, (len(boxes),), name="scores", finite=True)
    keep_ids = np.asarray(keep_ids, np.int64).reshape(-1)
    if len(keep_ids) and (keep_ids.min() < 0 or keep_ids.max() >= len(boxes)):
        raise InputError(f"keep_ids must index the {len(boxes)} boxes")
    if not 0.0 < iou_threshold <= 1.0:
        raise InputError(f"iou_threshold must lie in (0, 1], got {iou_threshold}")
    kept = boxes[keep_ids]
    if not len(keep_ids):
        return kept
    own = (np.arange(len(keep_ids)), keep_ids)  # each kept box's own entry in its row
    iou = box_iou_3d(kept, boxes)
    iou[own] = 1.0  # exact, whatever rounding gives
    weight = np.where(iou >= iou_threshold, np.maximum(scores, 0.0)[None] * iou, 0.0)
    if class_ids is not None:
        class_ids = np.asarray(class_ids)
        check_array(class_ids, (len(boxes),), name="class_ids")
        weight *= class_ids[keep_ids][:, None] == class_ids[None]
    # A kept box of score 0 still votes for itself, so no row is without weight.
    weight[own] = np.maximum(weight[own], 1e-12)
    weight /= weight.sum(axis=1, keepdims=True)
    # Only the voting pairs (a few per kept box) are gathered: (K, M, 3) arrays of every pair would
    # take hundreds of MB when the app shows every candidate.
    rows, voters = np.nonzero(weight)
    pair_weight = weight[rows, voters]
    gap = np.abs((boxes[voters, 6] - kept[rows, 6] + np.pi / 2) % np.pi - np.pi / 2)
    log_sizes = np.log(np.maximum(boxes[voters, 3:6], 1e-9))
    turned = gap > np.pi / 4
    log_sizes[turned] = log_sizes[turned][:, [1, 0, 2]]  # along the kept box's length and width
    voted = kept.copy()
    for axis in range(3):
        voted[:, axis] = np.bincount(rows, pair_weight * boxes[voters, axis], minlength=len(kept))
        voted[:, 3 + axis] = np.exp(np.bincount(rows, pair_weight * log_sizes[:, axis], minlength=len(kept)))
    return voted
