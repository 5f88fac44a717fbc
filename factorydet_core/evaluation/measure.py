"""Metrics of a model on proposals whose references are given: what the app's before/after
table and every benchmark compute. Reading references from a data set (or the simulator's truth)
is ``evaluate.measure``'s job, not this module's."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from factorydet_core.detection.model import DetectionModel
from factorydet_core.detection.scoring import select_detections
from factorydet_core.metrics import (
    detection_metrics,
    error_breakdown,
    recognition_accuracy,
)
from factorydet_core.training.mining import (
    FrameProposals,
    group_labels,
)
from factorydet_core.types import SCORE_FLOOR, Detections


def measure_against(
    model: DetectionModel,
    frames: list[FrameProposals],
    references: dict[int, tuple[np.ndarray, np.ndarray]],
    *,
    ignored: dict[int, np.ndarray] | None = None,
    iou_threshold: float = 0.6,
    ap_score_floor: float = SCORE_FLOOR,
    score_thresholds: Sequence[float] = (),
    candidates: dict[int, Detections] | None = None,
) -> dict:
    """Detection metrics (per class and totals) and recognition accuracy of ``model`` on
    ``frames`` against ``references`` (frame index -> (boxes (R, 7), class_ids (R,)): a data set's
    annotations, a session's corrected labels or, in benchmarks, the truth). With
    ``score_thresholds``, ``operating_points`` lists the total precision, recall and F-score at
    each of them (to choose the operating threshold). ``errors`` sorts the false positives and
    misses at the operating point by kind (``metrics.error_breakdown``).

    Args:
        ignored: frame index -> (Q, 7) boxes of objects below the annotation policy; detections on
            them are left out of the counts (``metrics.IGNORE_IOU``). None: no ignore rule.
        candidates: frame index -> the model's candidates of that frame (``model.candidates``),
            when they were computed already.
    """
    scored, true_ids, predicted_ids = [], [], []
    class_names = model.class_names
    background_id = len(class_names)
    for frame in frames:
        ref_boxes, ref_classes = references[frame.frame_index]
        ignore = np.zeros((0, 7)) if ignored is None else ignored.get(frame.frame_index, np.zeros((0, 7)))
        if candidates is not None and frame.frame_index in candidates:
            frame_candidates = candidates[frame.frame_index]
        else:
            frame_candidates = model.candidates(frame.proposal_boxes, frame.groups)
        probabilities = frame_candidates.probabilities
        detections = select_detections(
            frame_candidates, ap_score_floor, model.nms_iou, vote_iou=model.vote_iou
        )
        kept = detections.subset(detections.kept_mask)
        scored.append(
            {
                "boxes": kept.boxes,
                "class_ids": kept.class_ids,
                "scores": kept.scores,
                "reference_boxes": ref_boxes,
                "reference_class_ids": ref_classes,
                "ignore_boxes": ignore,
                # Before the threshold and NMS, for the kinds of misses (error_breakdown).
                "candidate_boxes": frame_candidates.boxes,
                "candidate_class_ids": frame_candidates.class_ids,
                "candidate_scores": frame_candidates.scores,
            }
        )
        # Table 2: held-out point sets that match a reference, and those overlapping none.
        labels, overlaps_any = group_labels(frame, ref_boxes, ref_classes, background_id, iou_threshold)
        chosen = (labels != background_id) | ~overlaps_any
        true_ids.append(labels[chosen])
        predicted_ids.append(probabilities[chosen].argmax(axis=1))
    metrics = detection_metrics(
        scored, class_names, iou_threshold, model.score_threshold, model.class_thresholds()
    )
    if score_thresholds:
        metrics["operating_points"] = []
        for threshold in score_thresholds:
            at = detection_metrics(scored, class_names, iou_threshold, float(threshold))
            metrics["operating_points"].append(
                {"score_threshold": float(threshold), **{k: at[k] for k in ("precision", "recall", "f1")}}
            )
    metrics["errors"] = error_breakdown(
        scored, class_names, iou_threshold, model.score_threshold, model.class_thresholds()
    )
    metrics["recognition"] = recognition_accuracy(
        np.concatenate(true_ids), np.concatenate(predicted_ids), (*class_names, "background")
    )
    return metrics


def compare_models(
    models: dict[str, DetectionModel],
    frames: Sequence[FrameProposals],
    references: dict[int, tuple[np.ndarray, np.ndarray]],
    iou_threshold: float = 0.6,
) -> dict:
    """Precision, recall and F-score per class and in total of each model on the same frames and
    references (the app's before/after table)."""

    out = {}
    for name, model in models.items():
        metrics = measure_against(model, list(frames), references, iou_threshold=iou_threshold)
        out[name] = {
            "per_class": {
                k: {m: v[m] for m in ("precision", "recall", "f1", "num_reference")}
                for k, v in metrics["per_class"].items()
            },
            "precision": metrics["precision"],
            "recall": metrics["recall"],
            "f1": metrics["f1"],
        }
    return out


def comparison_markdown(table: dict) -> str:
    """A before/after table: one row per class, F-score (precision / recall) per model."""
    names = list(table)
    if not names:
        return "_no models to compare_"
    classes = list(table[names[0]]["per_class"])
    head = "| class | " + " | ".join(names) + " |\n|---|" + "---|" * len(names) + "\n"

    def cell(m: dict) -> str:
        if m["f1"] is None:  # no reference of the class: precision alone is defined
            return f"– ({m['precision']:.2f} / –)"
        return f"{m['f1']:.3f} ({m['precision']:.2f} / {m['recall']:.2f})"

    rows = [
        f"| {c} | " + " | ".join(cell(table[n]["per_class"][c]) for n in names) + " |"
        for c in classes
        if any(table[n]["per_class"][c]["num_reference"] for n in names)
    ]
    rows.append("| **total** | " + " | ".join(cell(table[n]) for n in names) + " |")
    return (
        head + "\n".join(rows) + "\n\nF-score (precision / recall) at IoU 0.6 against the session's labels."
    )
