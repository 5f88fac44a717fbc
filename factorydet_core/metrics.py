"""Measuring proposals against reference boxes and instances (truth comes from the caller)."""

from __future__ import annotations

import warnings

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.scoring import operating_thresholds
from factorydet_core.proposals.candidates import point_sets
from factorydet_core.types import InputError, MergedCloud, Proposals, Segmentation, check_threshold_objective


def proposal_point_lists(segmentation: Segmentation, proposals: Proposals) -> list[np.ndarray]:
    """Point indices (into the segmented cloud) of every proposal."""
    return point_sets(segmentation.patch_ids, proposals.patch_sets)


def best_box_iou(reference_boxes: np.ndarray, proposal_boxes: np.ndarray) -> np.ndarray:
    """(R,) the highest 3D IoU of each reference box with any proposal box (0 without proposals)."""
    iou = box_iou_3d(reference_boxes, proposal_boxes)
    return iou.max(axis=1) if iou.shape[1] else np.zeros(len(reference_boxes))


def best_point_iou(cloud: MergedCloud, instance_ids: np.ndarray, point_lists: list[np.ndarray]) -> np.ndarray:
    """(R,) the highest point-set IoU of each instance (its points in ``cloud``, by
    ``cloud.point_instance_ids``) with any proposal's point set: segmentation quality without boxes."""
    best = np.zeros(len(instance_ids))
    if not point_lists:
        return best
    row_of = {int(i): r for r, i in enumerate(instance_ids)}
    sizes = np.array([np.sum(cloud.point_instance_ids == i) for i in instance_ids])
    for points in point_lists:
        ids, counts = np.unique(cloud.point_instance_ids[points], return_counts=True)
        for inst, inter in zip(ids.tolist(), counts.tolist()):
            r = row_of.get(inst)
            if r is not None:
                best[r] = max(best[r], inter / (sizes[r] + len(points) - inter))
    return best


def recall_table(
    class_ids: np.ndarray, hit_mask: np.ndarray, class_names: tuple[str, ...]
) -> dict[str, dict[str, float | int]]:
    """Per-class ``{"num": n, "recall": r}`` and an ``"all"`` row."""
    table: dict[str, dict[str, float | int]] = {}
    for c, name in enumerate(class_names):
        mask = class_ids == c
        if mask.any():
            table[name] = {"num": int(mask.sum()), "recall": round(float(hit_mask[mask].mean()), 3)}
    table["all"] = {
        "num": int(len(hit_mask)),
        "recall": round(float(hit_mask.mean()), 3) if len(hit_mask) else float("nan"),
    }
    return table


def match_detections(
    boxes: np.ndarray,
    class_ids: np.ndarray,
    scores: np.ndarray,
    reference_boxes: np.ndarray,
    reference_class_ids: np.ndarray,
    iou_threshold: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching of one frame's detections to reference instances, as in VOC / SUN RGB-D:
    by decreasing score, a detection is a true positive if its best-overlapping reference of the
    same class has IoU >= ``iou_threshold`` and is not matched yet.

    Returns:
        ``(tp_mask, matched_reference_ids)``: (K,) bool, and (K,) the reference each detection
        matched (-1 for false positives).
    """
    if not 0.0 < iou_threshold <= 1.0:
        raise InputError(f"iou_threshold must lie in (0, 1], got {iou_threshold}")
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    matched = np.full(len(boxes), -1, np.int64)
    if not len(boxes) or not len(reference_boxes):
        return matched >= 0, matched
    iou = box_iou_3d(boxes, reference_boxes)
    iou[np.asarray(class_ids)[:, None] != np.asarray(reference_class_ids)[None, :]] = 0.0
    taken = np.zeros(len(reference_boxes), bool)
    for k in np.argsort(-np.asarray(scores), kind="stable"):
        r = int(np.argmax(iou[k]))
        if iou[k, r] >= iou_threshold and not taken[r]:
            taken[r] = True
            matched[k] = r
    return matched >= 0, matched


def average_precision(recall: np.ndarray, precision: np.ndarray) -> float:
    """Area under the interpolated precision-recall curve (all points, VOC 2010 and later)."""
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


IGNORE_IOU = 0.25
"""A detection that matches no reference but overlaps an ignored object (one below the annotation
policy's point count: ``evaluate.ignored_boxes``) at least this much is left out of the counts, as
KITTI's "DontCare" regions and nuScenes' ignored boxes: such objects are real, so a detection on
them is no false positive, and not references, so missing them is no miss."""


def ignored_mask(boxes: np.ndarray, tp_mask: np.ndarray, ignore_boxes: np.ndarray | None) -> np.ndarray:
    """(K,) the false positives among (K, 7) ``boxes`` that lie on one of ``ignore_boxes`` (Q, 7)
    (``IGNORE_IOU``, any class)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    out = np.zeros(len(boxes), bool)
    if ignore_boxes is None or not len(ignore_boxes) or not len(boxes):
        return out
    false = np.flatnonzero(~np.asarray(tp_mask, bool))
    if len(false):
        out[false] = box_iou_3d(boxes[false], ignore_boxes).max(axis=1) >= IGNORE_IOU
    return out


def frame_matches(
    frame: dict, num_classes: int, iou_threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame's part of ``detection_metrics`` (``frame`` as one of its ``frames``): its counted
    detections' (K,) scores, (K,) whether each is a true positive and (K,) classes, and (C,) its
    references per class. ``pool_matches`` of every frame's part is what ``detection_metrics``
    measures (``metrics_from_matches``): a caller that measures the same frames again can keep
    the parts of frames that did not change."""
    tp, _ = match_detections(
        frame["boxes"], frame["class_ids"], frame["scores"], frame["reference_boxes"],
        frame["reference_class_ids"], iou_threshold,
    )  # fmt: skip
    counted = ~ignored_mask(frame["boxes"], tp, frame.get("ignore_boxes"))
    num_reference = np.bincount(np.asarray(frame["reference_class_ids"], np.int64), minlength=num_classes)
    return (
        np.asarray(frame["scores"], np.float64)[counted],
        tp[counted],
        np.asarray(frame["class_ids"], np.int64)[counted],
        num_reference[:num_classes],
    )


def pool_matches(
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], num_classes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Frames' ``frame_matches`` pooled: (K,) scores, (K,) whether each is a true positive, (K,)
    classes, and (C,) the number of references per class."""
    scores = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0)
    tps = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, bool)
    classes = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0, np.int64)
    num_reference = np.zeros(num_classes, np.int64)
    for part in parts:
        num_reference += part[3]
    return scores, tps, classes, num_reference


def _pooled_matches(
    frames: list[dict], num_classes: int, iou_threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Detections of all ``frames`` pooled (``pool_matches``)."""
    return pool_matches([frame_matches(f, num_classes, iou_threshold) for f in frames], num_classes)


def detection_metrics(
    frames: list[dict],
    class_names: tuple[str, ...],
    iou_threshold: float = 0.6,
    score_threshold: float = 0.5,
    class_score_thresholds: np.ndarray | None = None,
) -> dict:
    """Precision, recall and F1 per class at a score threshold, AP per class and mAP.

    Args:
        frames: one dict per frame with ``boxes`` (K, 7), ``class_ids`` (K,), ``scores`` (K,) of the
            kept detections (scored down to a low threshold, so that AP sees the whole curve), and
            ``reference_boxes`` (R, 7), ``reference_class_ids`` (R,); optionally
            ``ignore_boxes`` (Q, 7): detections on them are not counted (``IGNORE_IOU``).
        class_names: the classes.
        iou_threshold: matching threshold.
        score_threshold: operating point for precision, recall and F1.
        class_score_thresholds: (C,) an operating point per class instead (NaN: ``score_threshold``).

    Returns:
        ``{"per_class": {name: {num_reference, num_detections, tp, precision, recall, f1, ap}},
        "precision", "recall", "f1"`` (pooled over classes)``, "map"`` (mean AP over classes with
        references)``, "pr_curves": {name: {"recall": [...], "precision": [...]}}}`` with the
        classes pooled under "all". Each figure says how many references it rests on
        (``num_reference``); recall, F-score and AP of a class without references are ``None``, and
        so are the totals when no frame has any (with a warning): they are undefined, not 0.
    """
    pooled = _pooled_matches(frames, len(class_names), iou_threshold)
    return _metrics_from_matches(pooled, class_names, iou_threshold, score_threshold, class_score_thresholds)


def metrics_from_matches(
    pooled: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    class_names: tuple[str, ...],
    iou_threshold: float = 0.6,
    score_threshold: float = 0.5,
    class_score_thresholds: np.ndarray | None = None,
) -> dict:
    """``detection_metrics`` from its frames' ``pool_matches`` (matched at ``iou_threshold``)."""
    return _metrics_from_matches(pooled, class_names, iou_threshold, score_threshold, class_score_thresholds)


def _metrics_from_matches(
    pooled: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    class_names: tuple[str, ...],
    iou_threshold: float,
    score_threshold: float,
    class_score_thresholds: np.ndarray | None,
) -> dict:
    """``metrics_from_matches``, called by a public function: its warning names that function's
    caller."""
    scores, tps, classes, num_reference = pooled
    per_class_threshold = operating_thresholds(len(class_names), score_threshold, class_score_thresholds)
    above = scores >= per_class_threshold[classes]

    def prf(tp: int, num_det: int, num_ref: int) -> tuple[float, float | None, float | None]:
        precision = tp / num_det if num_det else 0.0
        if not num_ref:  # recall, and so F, rest on nothing: undefined, not 0
            return precision, None, None
        recall = tp / num_ref
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        return precision, recall, f1

    def rounded(value: float | None) -> float | None:
        return None if value is None else round(value, 4)

    per_class, curves, aps = {}, {}, []
    for c, name in enumerate(class_names):
        mask = classes == c
        order = np.argsort(-scores[mask], kind="stable")
        cum_tp = np.cumsum(tps[mask][order])
        cum_det = np.arange(1, mask.sum() + 1)
        recall = cum_tp / max(num_reference[c], 1)
        precision = cum_tp / np.maximum(cum_det, 1)
        ap = average_precision(recall, precision) if num_reference[c] else float("nan")
        operating = mask & above
        tp = int(tps[operating].sum())
        p, r, f = prf(tp, int(operating.sum()), int(num_reference[c]))
        per_class[name] = {
            "num_reference": int(num_reference[c]),
            "num_detections": int(operating.sum()),
            "tp": tp,
            "precision": round(p, 4),
            "recall": rounded(r),
            "f1": rounded(f),
            "ap": None if np.isnan(ap) else round(ap, 4),
        }
        if num_reference[c]:
            aps.append(ap)
            curves[name] = {"recall": recall.round(4).tolist(), "precision": precision.round(4).tolist()}
    if num_reference.sum():
        order = np.argsort(-scores, kind="stable")
        cum_tp = np.cumsum(tps[order])
        curves["all"] = {
            "recall": (cum_tp / num_reference.sum()).round(4).tolist(),
            "precision": (cum_tp / np.arange(1, len(order) + 1)).round(4).tolist(),
        }
    operating = above
    p, r, f = prf(int(tps[operating].sum()), int(operating.sum()), int(num_reference.sum()))
    if not num_reference.sum():
        warnings.warn(
            "detection metrics without any reference instance: recall, F-score and mAP are undefined",
            stacklevel=3,
        )
    out = {
        "iou_threshold": iou_threshold,
        "score_threshold": score_threshold,
        "per_class": per_class,
        "num_reference": int(num_reference.sum()),
        "num_detections": int(operating.sum()),
        "precision": round(p, 4),
        "recall": rounded(r),
        "f1": rounded(f),
        "map": round(float(np.mean(aps)), 4) if aps else None,
        "pr_curves": curves,
    }
    if class_score_thresholds is not None:
        out["class_score_thresholds"] = {
            name: round(float(t), 4) for name, t in zip(class_names, per_class_threshold)
        }
    return out


CLASS_THRESHOLD_GRID: tuple[float, ...] = tuple(round(0.1 + 0.05 * k, 2) for k in range(17))
"""Score thresholds ``tune_class_thresholds`` chooses among: 0.1 to 0.9 in steps of 0.05."""


def tune_class_thresholds(
    frames: list[dict],
    class_names: tuple[str, ...],
    iou_threshold: float = 0.6,
    grid: tuple[float, ...] = CLASS_THRESHOLD_GRID,
    max_threshold: float = 1.0,
    objective: str = "class",
    untuned_threshold: float | None = None,
) -> np.ndarray:
    """(C,) each class's score threshold of highest F-score on ``frames`` (``detection_metrics``'s
    input, scored down to at least the grid's lowest threshold) among those of ``grid`` up to
    ``max_threshold``; NaN for a class without references or without a true positive at any of them
    (it keeps the global one).

    ``objective`` (``types.THRESHOLD_OBJECTIVES``) says whose F-score: ``"class"``, each class's
    own; ``"total"``, that of all classes' detections pooled (``detection_metrics``'s total), by
    coordinate ascent from the per-class choice: one class's threshold at a time moves to the grid
    value of highest pooled F given the others', until none moves. Lowering a threshold raises the
    pooled F exactly when the share of matches among the detections it adds is above half that F.
    So a class of few, poorly scored objects is held above its own best (up to switching it off:
    above all its scores, where it has no true positive), and a class whose own F is well above the
    pooled one goes below its own best. The classes left NaN stay NaN and count their detections at
    ``untuned_threshold`` (required with ``"total"``).

    Training on the frames its model fitted passes its global threshold as ``max_threshold``: a
    class's threshold may go below it, never above (``train_with_mining``'s ``threshold_folds``
    tunes on out-of-fold scores instead, with no ceiling). Scores on the frames a classifier was
    trained on run higher than on new ones, so thresholds tuned there are too high: raised ones
    (barrels to 0.65, people to 0.55) cost the demo's test frames most of their barrels (total F
    0.209 at one threshold, 0.187 per class), while the lowered truck threshold held on the
    corpus's test frames.

    One threshold for all classes serves them badly: the classifier's probabilities are on
    different scales per class (a well-boxed truck scores 0.3, a barrel 0.7), so any one threshold
    drops the trucks or floods the barrels (``docs/default_model_validation.json``)."""
    check_threshold_objective(objective)
    if objective == "total" and untuned_threshold is None:
        raise InputError('objective "total" needs untuned_threshold (the classes left NaN count there)')
    scores, tps, classes, num_reference = _pooled_matches(frames, len(class_names), iou_threshold)
    thresholds = np.array([t for t in grid if t <= max_threshold + 1e-12], np.float64)
    # (C, G) matches and detections of each class at or above each threshold: both objectives
    # read these counts.
    of_class = classes[None, :] == np.arange(len(class_names))[:, None]  # (C, K)
    above = (scores[:, None] >= thresholds[None, :]).astype(np.int64)  # (K, G)
    tp_curve = (of_class & tps[None, :]).astype(np.int64) @ above
    det_curve = of_class.astype(np.int64) @ above
    best_f = np.zeros(len(class_names))
    chosen = np.full(len(class_names), -1)  # index into thresholds; -1: untuned
    for g in range(len(thresholds)):
        for c in range(len(class_names)):
            tp, num_detections = int(tp_curve[c, g]), int(det_curve[c, g])
            if not tp or not num_reference[c]:
                continue
            f1 = 2 * tp / (num_detections + num_reference[c])  # 2PR / (P + R)
            if f1 > best_f[c] + 1e-12:  # strictly better: ties keep the lower threshold
                best_f[c], chosen[c] = f1, g
    if objective == "total":
        untuned = np.isin(classes, np.flatnonzero(chosen < 0)) & (scores >= untuned_threshold)
        fixed = (int((untuned & tps).sum()), int(untuned.sum()))
        chosen = _pooled_f_choice(tp_curve, det_curve, int(num_reference.sum()), chosen, fixed)
    tuned = np.full(len(class_names), np.nan)
    tuned[chosen >= 0] = thresholds[chosen[chosen >= 0]]
    return tuned


def _pooled_f_choice(
    tp_curve: np.ndarray,
    det_curve: np.ndarray,
    num_references: int,
    chosen: np.ndarray,
    fixed: tuple[int, int],
) -> np.ndarray:
    """``tune_class_thresholds``'s ``"total"`` objective: ``chosen`` (C,), each class's own best
    grid index (-1: untuned, left so), moved class by class to the pooled F's best grid index.

    Args:
        tp_curve, det_curve: (C, G) each class's matches and detections at each grid threshold.
        num_references: the references of all classes.
        fixed: the matches and detections of the untuned classes (at the global threshold)."""
    index = chosen.copy()
    tunable = np.flatnonzero(index >= 0)
    moved = True
    while moved:  # each move raises the pooled F strictly, among finitely many choices: it ends
        moved = False
        for c in tunable:
            others = tunable[tunable != c]
            tp_rest = fixed[0] + int(tp_curve[others, index[others]].sum())
            det_rest = fixed[1] + int(det_curve[others, index[others]].sum())
            pooled = 2 * (tp_rest + tp_curve[c]) / np.maximum(det_rest + det_curve[c] + num_references, 1)
            best = int(np.argmax(pooled))
            if pooled[best] > pooled[index[c]] + 1e-12:  # strictly better: ties stay
                index[c], moved = best, True
    return index


def recognition_accuracy(true_ids: np.ndarray, predicted_ids: np.ndarray, labels: tuple[str, ...]) -> dict:
    """The paper's Table 2: per true class, the fraction of samples classified correctly, their mean
    over classes, and the overall accuracy."""
    true_ids, predicted_ids = np.asarray(true_ids), np.asarray(predicted_ids)
    per_class = {}
    for c, name in enumerate(labels):
        mask = true_ids == c
        if mask.any():
            per_class[name] = {
                "num": int(mask.sum()),
                "accuracy": round(float((predicted_ids[mask] == c).mean()), 4),
            }
    return {
        "per_class": per_class,
        "mean_class_accuracy": round(float(np.mean([v["accuracy"] for v in per_class.values()])), 4)
        if per_class
        else None,
        # The mean is over the classes with samples: say which ones it leaves out.
        "classes_without_samples": [name for name in labels if name not in per_class],
        "overall_accuracy": round(float((true_ids == predicted_ids).mean()), 4) if len(true_ids) else None,
    }


FALSE_POSITIVE_KINDS: tuple[str, ...] = ("duplicate", "localization", "confusion", "part", "background")
"""Why a detection is false (``error_breakdown``), checked in this order: a reference of its class
fits it at the matching IoU but was already matched; one of its class overlaps it, but less; only a
reference of another class overlaps it; none overlaps it, but it lies mostly inside one (a part of
a larger object, such as a person-sized upright of a pallet truck); nothing does. Records written
before ``part`` existed count those under ``background``: read the kinds a record has."""

MISS_KINDS: tuple[str, ...] = ("no_candidate", "below_threshold", "suppressed")
"""Why a reference is missed (``error_breakdown``): no candidate of its class fits it at the
matching IoU, whatever its score (no point set covers it, its point set has a wrong class, or a
wrong box was chosen among the options); some do, but all score below their class's operating
threshold; one scores above it, but NMS suppressed it, the one-to-one matching gave it another
reference, or box voting moved its box below the IoU."""

OVERLAP_IOU = 0.1
"""Least IoU at which ``error_breakdown`` counts a false positive as overlapping a reference."""


def recorded_false_positive_kinds(errors: dict) -> list[str]:
    """The kinds of false positive an ``error_breakdown`` result counts, in
    ``FALSE_POSITIVE_KINDS`` order: records written before ``part`` existed count those false
    positives as background and have no ``part``."""
    return [k for k in FALSE_POSITIVE_KINDS if k in errors["false_positives"]]


PART_FRACTION = 0.5
"""Least share of a false positive's volume inside one reference box at which ``error_breakdown``
counts it as a ``part`` of that object (when no reference overlaps it at ``OVERLAP_IOU``)."""


def _share_inside(boxes: np.ndarray, ref_boxes: np.ndarray, iou: np.ndarray) -> np.ndarray:
    """(N, R) share of each of (N, 7) boxes' volume that lies inside each of (R, 7) reference
    boxes, from their (N, R) IoU: the intersection is IoU (V_a + V_b) / (1 + IoU)."""
    volume = np.prod(boxes[:, 3:6], axis=1)
    ref_volume = np.prod(ref_boxes[:, 3:6], axis=1)
    intersection = iou * (volume[:, None] + ref_volume[None, :]) / (1.0 + iou)
    return np.divide(intersection, volume[:, None], out=np.zeros_like(iou), where=volume[:, None] > 0)


def error_breakdown(
    frames: list[dict],
    class_names: tuple[str, ...],
    iou_threshold: float = 0.6,
    score_threshold: float = 0.5,
    class_score_thresholds: np.ndarray | None = None,
) -> dict:
    """Where a detector's errors come from at its operating point, in the manner of Hoiem et al.'s
    "Diagnosing error in object detectors" (ECCV 2012): each false positive and each missed
    reference is given one kind (``FALSE_POSITIVE_KINDS``, ``MISS_KINDS``).

    Args:
        frames: ``detection_metrics``'s input; for the kinds of misses each frame also holds its
            candidates before the threshold and NMS: ``candidate_boxes`` (M, 7),
            ``candidate_class_ids`` (M,) and ``candidate_scores`` (M,). Without them every miss
            counts as ``no_candidate``.
        class_names, iou_threshold, score_threshold, class_score_thresholds: as for
            ``detection_metrics``; the operating point the errors are counted at.

    Returns:
        ``{"per_class": {name: {"tp", "num_reference", "false_positives": {kind: n}, "misses":
        {kind: n}}},
        "false_positives": {kind: n}, "misses": {kind: n}, "tp", "num_detections",
        "num_reference", "f1", "f1_without": {kind: F}}``: the totals over classes, and the total
        F-score with every false positive of one kind removed, or every miss of one kind found
        (each by one more detection: a found "suppressed" miss whose candidate was already
        counted as a duplicate would add none, so its figure can run slightly low).
    """
    num_classes = len(class_names)
    thresholds = operating_thresholds(num_classes, score_threshold, class_score_thresholds)
    counts = [frame_error_counts(frame, num_classes, iou_threshold, thresholds) for frame in frames]
    return errors_from_counts(counts, class_names, iou_threshold)


def frame_error_counts(
    frame: dict, num_classes: int, iou_threshold: float, thresholds: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's part of ``error_breakdown`` (``frame`` as one of its ``frames``, ``thresholds``
    (C,) each class's operating score, ``operating_thresholds``): ``(tp (C,), false positives
    (C, len(FALSE_POSITIVE_KINDS)), misses (C, len(MISS_KINDS)))`` counted per class and kind.
    ``errors_from_counts`` of every frame's part is ``error_breakdown``'s result."""
    fp = np.zeros((num_classes, len(FALSE_POSITIVE_KINDS)), np.int64)
    missed = np.zeros((num_classes, len(MISS_KINDS)), np.int64)
    tp_per_class = np.zeros(num_classes, np.int64)
    classes = np.asarray(frame["class_ids"], np.int64)
    scores = np.asarray(frame["scores"], np.float64)
    above = scores >= thresholds[classes] if len(classes) else np.zeros(0, bool)
    boxes = np.asarray(frame["boxes"], np.float64).reshape(-1, 7)[above]
    classes, scores = classes[above], scores[above]
    ref_boxes = np.asarray(frame["reference_boxes"], np.float64).reshape(-1, 7)
    ref_classes = np.asarray(frame["reference_class_ids"], np.int64)
    # References of classes the detector does not know are not counted (as detection_metrics).
    known = (ref_classes >= 0) & (ref_classes < num_classes)
    ref_boxes, ref_classes = ref_boxes[known], ref_classes[known]
    tp, matched = match_detections(boxes, classes, scores, ref_boxes, ref_classes, iou_threshold)
    np.add.at(tp_per_class, classes[tp], 1)
    iou = (
        box_iou_3d(boxes, ref_boxes)
        if len(boxes) and len(ref_boxes)
        else np.zeros((len(boxes), len(ref_boxes)))
    )
    same = classes[:, None] == ref_classes[None, :]
    same_iou = np.where(same, iou, 0.0).max(axis=1, initial=0.0)
    other_iou = np.where(same, 0.0, iou).max(axis=1, initial=0.0)
    inside = _share_inside(boxes, ref_boxes, iou).max(axis=1, initial=0.0)
    kind = np.select(
        [
            same_iou >= iou_threshold,
            same_iou >= OVERLAP_IOU,
            other_iou >= OVERLAP_IOU,
            inside >= PART_FRACTION,
        ],
        [0, 1, 2, 3],
        4,
    )
    np.add.at(fp, (classes[~tp], kind[~tp]), 1)
    found = np.zeros(len(ref_boxes), bool)
    found[matched[tp]] = True
    lost = np.flatnonzero(~found)
    if not len(lost):
        return tp_per_class, fp, missed
    candidate_boxes = np.asarray(frame.get("candidate_boxes", np.zeros((0, 7))), np.float64).reshape(-1, 7)
    candidate_classes = np.asarray(frame.get("candidate_class_ids", np.zeros(0)), np.int64)
    candidate_scores = np.asarray(frame.get("candidate_scores", np.zeros(0)), np.float64)
    fits = np.zeros((len(candidate_boxes), len(lost)), bool)
    if len(candidate_boxes):
        fits = box_iou_3d(candidate_boxes, ref_boxes[lost]) >= iou_threshold
        fits &= candidate_classes[:, None] == ref_classes[lost][None, :]
    scored_above = (
        candidate_scores >= thresholds[candidate_classes] if len(candidate_boxes) else np.zeros(0, bool)
    )
    miss_kind = np.where(~fits.any(axis=0), 0, np.where((fits & scored_above[:, None]).any(axis=0), 2, 1))
    np.add.at(missed, (ref_classes[lost], miss_kind), 1)
    return tp_per_class, fp, missed


def errors_from_counts(
    counts: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    class_names: tuple[str, ...],
    iou_threshold: float,
) -> dict:
    """``error_breakdown``'s result from its frames' ``frame_error_counts`` (at ``iou_threshold``)."""
    num_classes = len(class_names)
    tp_per_class = np.zeros(num_classes, np.int64)
    fp = np.zeros((num_classes, len(FALSE_POSITIVE_KINDS)), np.int64)
    missed = np.zeros((num_classes, len(MISS_KINDS)), np.int64)
    for frame_tp, frame_fp, frame_missed in counts:
        tp_per_class += frame_tp
        fp += frame_fp
        missed += frame_missed
    tp_total = int(tp_per_class.sum())
    num_detections = tp_total + int(fp.sum())
    num_reference = tp_total + int(missed.sum())

    def f1(tp: int, detections: int, references: int) -> float:
        return round(2 * tp / (detections + references), 4) if detections + references else 0.0

    fp_totals, miss_totals = fp.sum(axis=0), missed.sum(axis=0)
    f1_without = {
        **{
            k: f1(tp_total, num_detections - int(n), num_reference)
            for k, n in zip(FALSE_POSITIVE_KINDS, fp_totals)
        },
        **{
            k: f1(tp_total + int(n), num_detections + int(n), num_reference)
            for k, n in zip(MISS_KINDS, miss_totals)
        },
    }
    return {
        "iou_threshold": iou_threshold,
        "per_class": {
            name: {
                "tp": int(tp_per_class[c]),
                "num_reference": int(tp_per_class[c] + missed[c].sum()),
                "false_positives": dict(zip(FALSE_POSITIVE_KINDS, fp[c].tolist())),
                "misses": dict(zip(MISS_KINDS, missed[c].tolist())),
            }
            for c, name in enumerate(class_names)
        },
        "false_positives": dict(zip(FALSE_POSITIVE_KINDS, fp_totals.tolist())),
        "misses": dict(zip(MISS_KINDS, miss_totals.tolist())),
        "tp": tp_total,
        "num_detections": num_detections,
        "num_reference": num_reference,
        "f1": f1(tp_total, num_detections, num_reference),
        "f1_without": f1_without,
    }
