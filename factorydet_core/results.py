"""Measuring a trained detector the way the paper does: recognition accuracy (its Table 2),
detection precision, recall, F-score and AP per class (its Table 3), the precision-recall curve
(its Fig. 6), against the annotations and, on simulated data, against the full hidden truth; the
baseline on the same proposals; and the report that puts them beside the paper's figures."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from .baseline import BaselineClassifier
from .bench import save_figure
from .dataset import Dataset, annotation_min_points, open_dataset
from .detection import select_detections
from .detector import Detector, params_for
from .evaluation import (
    FALSE_POSITIVE_KINDS,
    MISS_KINDS,
    detection_metrics,
    error_breakdown,
    recognition_accuracy,
)
from .model import DEFAULT_MODEL, PAPER_MODEL, DetectionModel
from .training import FrameProposals, collect_proposals, group_labels
from .types import Detections, InputError

PAPER_TABLE2 = {"mean": 99.84}
"""Recognition accuracy (%) of Negin et al. 2020, Table 2: only the average is quoted here (the
per-class figures are not available to this project, so the report leaves them blank)."""

PAPER_TABLE3 = {
    "ours": {"barrel": 0.038, "truck": 0.258, "total": 0.793},
    "baseline_3d_dpm": {"total": 0.417},
}
"""Detection F-scores at IoU 0.6 from Negin et al. 2020, Table 3, as quoted in the issue."""

Progress = Callable[[str, int, int], None]


def resolve_model(spec: str | os.PathLike, root: str | os.PathLike | None = None) -> Path:
    """A checkpoint path from "default" (the shipped model), "paper" (the shipped checkpoint of the
    paper's pipeline, ``model.PAPER_MODEL``), a ``.pt`` path, or a session name (its latest model)."""
    from .session import latest_model, open_session

    if str(spec) == "default":
        path = DEFAULT_MODEL
    elif str(spec) == "paper":
        path = PAPER_MODEL
    elif str(spec).endswith(".pt"):
        path = Path(spec)
    else:
        path = latest_model(open_session(str(spec), root))
        if path is None:
            raise InputError(f"session {spec!r} has no trained model; run factorydet train first")
    if not path.is_file():
        raise InputError(f"{path}: no such checkpoint")
    return path


def detector_for(model: DetectionModel | None, dataset: Dataset, calibrate: bool = True) -> Detector:
    """A detector with the front-half settings the model was trained with, calibrated on the data
    set's first frame when it has several sensors. The model's classes must be the data set's."""
    if model is not None and tuple(model.class_names) != tuple(dataset.class_names):
        raise InputError(
            f"the model's classes {list(model.class_names)} differ from the data set's "
            f"{list(dataset.class_names)}"
        )
    params = params_for(model.front_end if model is not None else None, dataset.num_sensors)
    detector = Detector(params, model=model)
    if calibrate and dataset.num_sensors > 1:
        detector.calibrate(dataset.frame(0))
    return detector


def reference_boxes(dataset: Dataset, frame_index: int, use_truth: bool, min_points: int | None = None):
    """(boxes, class_ids) of a frame: its annotations, or every instance of the truth with at
    least ``min_points`` points (simulated data sets only; ``None``: the data set's annotation
    policy, ``dataset.annotation_min_points``; only the truth reads it)."""
    if not use_truth:
        frame = dataset.frame(frame_index)
        return np.array(frame.labels.boxes), np.array(frame.labels.class_ids)
    from .sim.truth import read_frame_truth

    if min_points is None:
        min_points = annotation_min_points(dataset)

    truth = read_frame_truth(dataset.path, frame_index)
    keep = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= min_points)
    return truth.instance_boxes[keep], truth.instance_class_ids[keep]


def ignored_boxes(dataset: Dataset, frame_index: int, min_points: int | None = None) -> np.ndarray:
    """(Q, 7) truth boxes of the frame's objects that are seen (some points) but fall below the
    annotation policy: not references, and detections on them are neither right nor wrong
    (``evaluation.IGNORE_IOU``; KITTI's "DontCare"). Empty for data sets without a truth."""
    from .sim.truth import read_frame_truth

    if not (Path(dataset.path) / "truth").is_dir():
        return np.zeros((0, 7))
    if min_points is None:
        min_points = annotation_min_points(dataset)
    truth = read_frame_truth(dataset.path, frame_index)
    sparse = (truth.instance_class_ids >= 0) & (truth.instance_num_points < (min_points or 0))
    return truth.instance_boxes[sparse & (truth.instance_num_points > 0)]


def fit_baseline(
    frames: list[FrameProposals], class_names: tuple[str, ...], positive_iou: float = 0.6
) -> BaselineClassifier:
    """The baseline, trained on every point set of the training frames (positives by the
    annotations, everything else background) and on the annotated instances' own points."""
    if not frames:
        raise InputError("the baseline needs training frames (the data set has no train split)")
    baseline = BaselineClassifier(class_names=class_names)
    background_id = len(class_names)
    descriptors = [f.annotation_descriptors for f in frames]
    labels = [f.annotation_class_ids for f in frames]
    for frame in frames:
        frame_labels, _ = group_labels(
            frame, frame.label_boxes, frame.label_class_ids, background_id, positive_iou
        )
        descriptors.append(frame.groups.descriptors)
        labels.append(frame_labels)
    return baseline.fit(np.concatenate(descriptors), np.concatenate(labels))


def baseline_model(
    model: DetectionModel, frames: list[FrameProposals], positive_iou: float = 0.6
) -> DetectionModel:
    """``model`` with the baseline classifier fitted on the training ``frames`` in place of its
    own, and, when ``model`` has per-class thresholds, the baseline's own tuned on the same frames
    (``evaluation.tune_class_thresholds``; the deep classifier's would not fit its scores)."""
    from .training import score_frames, with_tuned_thresholds

    out = dataclasses.replace(
        model, classifier=fit_baseline(frames, model.class_names, positive_iou), class_score_thresholds=None
    )
    if model.class_score_thresholds is None:
        return out
    return with_tuned_thresholds(out, score_frames(out, frames, 0.05), positive_iou)


def measure(
    model: DetectionModel,
    dataset: Dataset | None,
    frames: list[FrameProposals],
    *,
    iou_threshold: float = 0.6,
    use_truth: bool = False,
    ap_score_floor: float = 0.05,
    references: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    score_thresholds: Sequence[float] = (),
    ignored: dict[int, np.ndarray] | None = None,
    candidates: dict[int, Detections] | None = None,
) -> dict:
    """Detection metrics (per class and totals) and recognition accuracy of ``model`` on
    ``frames``, against the annotations, the full truth, or ``references`` (frame index ->
    (boxes (R, 7), class_ids (R,)), e.g. a session's corrected labels; ``dataset`` may then be
    ``None``). With ``score_thresholds``, ``operating_points`` lists the total precision, recall
    and F-score at each of them (to choose the operating threshold). ``errors`` sorts the false
    positives and misses at the operating point by kind (``evaluation.error_breakdown``).

    Args:
        ignored: frame index -> (Q, 7) boxes of objects below the annotation policy; detections on
            them are left out of the counts (``evaluation.IGNORE_IOU``). With ``use_truth`` and no
            ``references`` they are read from the truth (``ignored_boxes``); ``{}`` turns that off.
        candidates: frame index -> the model's candidates of that frame (``model.candidates``),
            when they were computed already.
    """
    scored, true_ids, predicted_ids = [], [], []
    class_names = model.class_names
    background_id = len(class_names)
    for frame in frames:
        if references is not None:
            ref_boxes, ref_classes = references[frame.frame_index]
        else:
            ref_boxes, ref_classes = reference_boxes(dataset, frame.frame_index, use_truth)
        if ignored is not None:
            ignore = ignored.get(frame.frame_index, np.zeros((0, 7)))
        elif use_truth and references is None:
            ignore = ignored_boxes(dataset, frame.frame_index)
        else:
            ignore = np.zeros((0, 7))
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


def evaluate(
    data: str | os.PathLike,
    model_path: str | os.PathLike,
    *,
    iou_threshold: float = 0.6,
    max_frames: int | None = None,
    with_baseline: bool = False,
    max_train_frames: int | None = None,
    calibrate: bool = True,
    progress: Progress | None = None,
    command: str = "",
    score_thresholds: Sequence[float] = (),
) -> dict:
    """Evaluate a checkpoint on the test frames of a data set.

    The top-level ``per_class``, ``f1`` and ``map`` are against the full truth on simulated data
    (the issue's targets) and against the annotations otherwise; both are under ``against``.
    """
    start = time.perf_counter()
    dataset = open_dataset(data)
    model = DetectionModel.load(model_path)
    simulated = (Path(data) / "truth").is_dir()
    test = dataset.splits.get("test") or list(range(dataset.num_frames))
    test = test[:max_frames] if max_frames else test
    detector = detector_for(model, dataset, calibrate)
    frames = collect_proposals(dataset, test, detector, progress)
    # Classified and boxed once, measured against the annotations and the truth.
    candidates = {f.frame_index: model.candidates(f.proposal_boxes, f.groups) for f in frames}
    against = {
        "annotations": measure(
            model, dataset, frames, iou_threshold=iou_threshold, score_thresholds=score_thresholds,
            candidates=candidates,
        )  # fmt: skip
    }
    if simulated:
        against["truth"] = measure(
            model,
            dataset,
            frames,
            iou_threshold=iou_threshold,
            use_truth=True,
            score_thresholds=score_thresholds,
            candidates=candidates,
        )
    headline = against["truth" if simulated else "annotations"]
    result = {
        "benchmark": "evaluate",
        "command": command,
        "data": Path(data).name,
        "model": str(model_path),
        "frames": test,
        "reference": "truth" if simulated else "annotations",
        "iou_threshold": iou_threshold,
        "per_class": {
            k: {m: v[m] for m in ("precision", "recall", "f1", "ap", "num_reference")}
            for k, v in headline["per_class"].items()
        },
        "precision": headline["precision"],
        "recall": headline["recall"],
        "f1": headline["f1"],
        "map": headline["map"],
        "errors": headline["errors"],
        "num_reference": headline["num_reference"],
        "against": against,
    }
    if simulated:
        # The same without the ignore rule: detections on objects below the policy count as false.
        plain = measure(
            model, dataset, frames, iou_threshold=iou_threshold, use_truth=True, ignored={},
            candidates=candidates,
        )  # fmt: skip
        result["truth_without_ignore"] = {k: plain[k] for k in ("precision", "recall", "f1", "map")}
    if with_baseline:
        train = dataset.splits.get("train") or []
        train = train[:max_train_frames] if max_train_frames else train
        train_frames = collect_proposals(dataset, train, detector, progress)
        baseline = baseline_model(model, train_frames)
        result["baseline"] = {
            name: measure(baseline, dataset, frames, iou_threshold=iou_threshold, use_truth=name == "truth")
            for name in against
        }
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result


def strip_curves(metrics: dict) -> dict:
    """``metrics`` without the PR curves (for printing)."""
    out = dict(metrics)
    for key in ("against", "baseline"):
        if key in out:
            out[key] = {k: {m: v for m, v in d.items() if m != "pr_curves"} for k, d in out[key].items()}
    return out


def plot_pr_curves(metrics: dict, png: str | os.PathLike, title: str = "") -> None:
    """Precision against recall per class (the paper's Fig. 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    for name, curve in metrics["pr_curves"].items():
        if name == "all":
            continue
        ap = metrics["per_class"][name]["ap"]
        ax.plot(curve["recall"], curve["precision"], label=f"{name} (AP {ap:.2f})", lw=1.8)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(title or f"Precision-recall at IoU {metrics['iou_threshold']}")
    ax.legend(fontsize=8, loc="upper right")
    save_figure(fig, png)


def frame_list(indices: Sequence[int]) -> str:
    return ", ".join(str(i) for i in indices)


def plot_error_breakdown(errors: dict, png: str | os.PathLike, title: str = "") -> None:
    """Per class, stacked bars of the detections (true positives, then each kind of false
    positive) beside the references (found, then each kind of miss): ``evaluation.error_breakdown``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(errors["per_class"])
    positions = np.arange(len(names))
    found = np.array([errors["per_class"][n]["tp"] for n in names], float)
    fig, ax = plt.subplots(figsize=(8.0, 4.8))
    width = 0.38
    for side, (group, kinds, shades) in enumerate(
        (("false_positives", FALSE_POSITIVE_KINDS, plt.cm.Reds), ("misses", MISS_KINDS, plt.cm.Blues))
    ):
        x = positions + (side - 0.5) * width
        ax.bar(x, found, width, color="#4c9a2a", label="true positives" if side == 0 else None)
        bottom = found.copy()
        for k, kind in enumerate(kinds):
            counts = np.array([errors["per_class"][n][group][kind] for n in names], float)
            label = f"{'FP' if group == 'false_positives' else 'miss'}: {kind.replace('_', ' ')}"
            ax.bar(
                x,
                counts,
                width,
                bottom=bottom,
                color=shades(0.35 + 0.5 * k / max(len(kinds) - 1, 1)),
                label=label,
            )
            bottom += counts
    ax.set_xticks(positions, names)
    ax.set_ylabel("count (left bar: detections; right bar: references)")
    ax.set_title(title or f"Errors at the operating point, IoU {errors['iou_threshold']}")
    ax.legend(fontsize=7, ncol=2, loc="upper right")
    ax.grid(axis="y", alpha=0.3)
    save_figure(fig, png)
