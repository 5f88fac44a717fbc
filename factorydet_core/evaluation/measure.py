"""Metrics of a model on proposals whose references are given: what the app's before/after
table and every benchmark compute. Reading references from a data set (or the simulator's truth)
is ``evaluate.measure``'s job, not this module's."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

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

RECORD_KEYS = (
    "boxes",
    "class_ids",
    "scores",
    "reference_boxes",
    "reference_class_ids",
    "ignore_boxes",
    "candidate_boxes",
    "candidate_class_ids",
    "candidate_scores",
    "true_ids",
    "predicted_ids",
)
"""The arrays of ``frame_record``: ``metrics.detection_metrics``' and ``metrics.error_breakdown``'s
per-frame input, and the point sets' true and predicted class ids (Table 2)."""


def frame_record(
    model: DetectionModel,
    frame: FrameProposals,
    candidates: Detections,
    reference_boxes: np.ndarray,
    reference_class_ids: np.ndarray,
    ignore_boxes: np.ndarray | None = None,
    *,
    iou_threshold: float = 0.6,
    ap_score_floor: float = SCORE_FLOOR,
) -> dict[str, np.ndarray]:
    """One frame's share of ``measure_against``: its detections at the AP floor after NMS (K),
    its references (R, 7) and ignore boxes (Q, 7), its candidates before the threshold and NMS
    (M), and the class ids of its held-out point sets (N: those matching a reference, and those
    overlapping none), true and predicted. A batch computes these on its workers; ``metrics_of``
    pools them."""
    background_id = len(model.class_names)
    detections = select_detections(candidates, ap_score_floor, model.nms_iou, vote_iou=model.vote_iou)
    kept = detections.subset(detections.kept_mask)
    labels, overlaps_any = group_labels(
        frame, reference_boxes, reference_class_ids, background_id, iou_threshold
    )
    chosen = (labels != background_id) | ~overlaps_any
    return {
        "boxes": kept.boxes,
        "class_ids": kept.class_ids,
        "scores": kept.scores,
        "reference_boxes": np.asarray(reference_boxes, np.float64).reshape(-1, 7),
        "reference_class_ids": np.asarray(reference_class_ids, np.int64),
        "ignore_boxes": np.zeros((0, 7)) if ignore_boxes is None else np.asarray(ignore_boxes, np.float64),
        # Before the threshold and NMS, for the kinds of misses (error_breakdown).
        "candidate_boxes": candidates.boxes,
        "candidate_class_ids": candidates.class_ids,
        "candidate_scores": candidates.scores,
        "true_ids": labels[chosen],
        "predicted_ids": candidates.probabilities[chosen].argmax(axis=1),
    }


def metrics_of(
    records: Iterable[dict[str, np.ndarray]],
    model: DetectionModel,
    *,
    iou_threshold: float = 0.6,
    score_thresholds: Sequence[float] = (),
) -> dict:
    """``measure_against``'s metrics from its frames' ``frame_record``s."""
    scored = list(records)
    class_names = model.class_names
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
    true_ids = [r["true_ids"] for r in scored]
    predicted_ids = [r["predicted_ids"] for r in scored]
    metrics["recognition"] = recognition_accuracy(
        np.concatenate(true_ids) if true_ids else np.zeros(0, np.int64),
        np.concatenate(predicted_ids) if predicted_ids else np.zeros(0, np.int64),
        (*class_names, "background"),
    )
    return metrics


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
    records = []
    for frame in frames:
        ref_boxes, ref_classes = references[frame.frame_index]
        ignore = None if ignored is None else ignored.get(frame.frame_index)
        if candidates is not None and frame.frame_index in candidates:
            frame_candidates = candidates[frame.frame_index]
        else:
            frame_candidates = model.candidates(frame.proposal_boxes, frame.groups)
        records.append(
            frame_record(
                model,
                frame,
                frame_candidates,
                ref_boxes,
                ref_classes,
                ignore,
                iou_threshold=iou_threshold,
                ap_score_floor=ap_score_floor,
            )  # fmt: skip
        )
    return metrics_of(records, model, iou_threshold=iou_threshold, score_thresholds=score_thresholds)


def compare_models(
    models: dict[str, DetectionModel],
    frames: Sequence[FrameProposals],
    references: dict[int, tuple[np.ndarray, np.ndarray]],
    iou_threshold: float = 0.6,
    ignored: dict[int, np.ndarray] | None = None,
) -> dict:
    """Precision, recall and F-score per class and in total of each model on the same frames and
    references (the app's before/after table); detections on ``ignored`` boxes (frame index ->
    (Q, 7)) count neither way."""

    out = {}
    for name, model in models.items():
        metrics = measure_against(
            model, list(frames), references, iou_threshold=iou_threshold, ignored=ignored
        )
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
    first, last = table[names[0]]["per_class"], table[names[-1]]["per_class"]
    lost = [
        f"\n\n**{names[-1]} finds none of the {last[c]['num_reference']} labelled instances of {c}; "
        f"{names[0]} finds {first[c]['recall']:.0%} of them.** "
        "A model that has lost a class sends its unlabelled objects to the background when it mines, "
        "and the review queue, whose classes take turns by the predicted class, does not show them: "
        "keep the shown model, or label more of the class and train again."
        for c in lost_classes(table)
    ]
    before_f1, after_f1 = table[names[0]]["f1"], table[names[-1]]["f1"]
    worse = (
        [
            f"\n\n**{names[-1]} scores a lower total F-score than {names[0]} on these frames "
            f"({after_f1:.3f} against {before_f1:.3f})**: keep the shown model unless the classes "
            "above say otherwise."
        ]
        if len(names) > 1 and before_f1 is not None and after_f1 is not None and after_f1 < before_f1
        else []
    )
    return (
        head
        + "\n".join(rows)
        + "\n\nF-score (precision / recall) at IoU 0.6 against the session's labels."
        + "".join(worse)
        + "".join(lost)
    )


def lost_classes(table: dict) -> list[str]:
    """The classes the last model of a ``compare_models`` table (the new one) finds no instance of
    while its first (the shown one) finds some, on the same labelled frames. A fit can lose a
    whole class to a neighbour (cones taken for barrels), and mining then makes the loss last: the
    class's unlabelled objects come as false positives of the other class and go to the
    background (``docs/review-loop.md``, *Ten training seeds*)."""
    names = list(table)
    if len(names) < 2:
        return []
    first, last = table[names[0]]["per_class"], table[names[-1]]["per_class"]
    return [
        c
        for c, m in last.items()
        if m["num_reference"] and not m["recall"] and c in first and (first[c]["recall"] or 0) > 0
    ]


def unlearned_classes(train_metrics: dict) -> dict[str, int]:
    """The classes a model finds none of on its own training frames, at any score it reports
    (their AP there is 0, down to the mining's score floor), though the frames label some:
    class -> its number of labels there. ``train_metrics`` is a training round's record
    (``train_with_mining``'s ``train_metrics``).

    Such a fit has not learned the class: too few epochs for a class with few examples (``bench
    hitl``'s 5-epoch first fit of seed 7 found neither cones nor pallets on its training frames,
    ``docs/review-loop.md``), and mining then sends the class's unlabelled objects to the background
    as false positives of another class."""
    return {
        c: int(m["num_reference"])
        for c, m in train_metrics.get("per_class", {}).items()
        if m.get("num_reference") and not m.get("ap")
    }


def unlearned_text(train_metrics: dict) -> str:
    """A sentence naming ``unlearned_classes`` and what to do ("" when there are none)."""
    missing = unlearned_classes(train_metrics)
    if not missing:
        return ""
    named = " or ".join(f"{c} ({n})" for c, n in missing.items())
    return (
        f"**On its own training frames the model finds none of the labelled instances of {named}**: "
        "it has not learned them. Train with more epochs, or label more of them; mining with this "
        "model sends their unlabelled objects to the background."
    )
