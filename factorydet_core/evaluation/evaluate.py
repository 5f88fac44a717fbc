"""Measuring a trained detector the way the paper does: recognition accuracy (its Table 2),
detection precision, recall, F-score and AP per class (its Table 3), the precision-recall curve
(its Fig. 6), against the annotations and, on simulated data, against the full hidden truth; the
baseline on the same proposals; and the report that puts them beside the paper's figures."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from factorydet_core.detection.baseline import BaselineClassifier
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.measure import measure_against
from factorydet_core.io.dataset import Dataset, annotation_min_points, open_dataset
from factorydet_core.sim.truth import read_frame_truth
from factorydet_core.training.mining import (
    FrameProposals,
    Progress,
    collect_proposals,
    group_labels,
    score_frames,
    with_tuned_thresholds,
)
from factorydet_core.types import SCORE_FLOOR, InputError

PAPER_TABLE2 = {"mean": 99.84}
"""Recognition accuracy (%) of Negin et al. 2020, Table 2: only the average is quoted here (the
per-class figures are not available to this project, so the report leaves them blank)."""

PAPER_TABLE3 = {
    "ours": {"barrel": 0.038, "truck": 0.258, "total": 0.793},
    "baseline_3d_dpm": {"total": 0.417},
}
"""Detection F-scores at IoU 0.6 from Negin et al. 2020, Table 3, as quoted in the issue."""


def detector_for(model: DetectionModel | None, dataset: Dataset, calibrate: bool = True) -> Detector:
    """A detector with the front-half settings the model was trained with, calibrated on the data
    set's first frame when it has several sensors. The model's classes must be the data set's."""
    if model is not None:
        model.check_classes(dataset.class_names)
    detector = Detector.for_model(model, dataset.num_sensors)
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

    if min_points is None:
        min_points = annotation_min_points(dataset)

    truth = read_frame_truth(dataset.path, frame_index)
    keep = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= min_points)
    return truth.instance_boxes[keep], truth.instance_class_ids[keep]


def ignored_boxes(dataset: Dataset, frame_index: int, min_points: int | None = None) -> np.ndarray:
    """(Q, 7) truth boxes of the frame's objects that are seen (some points) but fall below the
    annotation policy: not references, and detections on them are neither right nor wrong
    (``metrics.IGNORE_IOU``; KITTI's "DontCare"). Empty for data sets without a truth."""

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
    (``metrics.tune_class_thresholds``; the deep classifier's would not fit its scores)."""

    out = dataclasses.replace(
        model, classifier=fit_baseline(frames, model.class_names, positive_iou), class_score_thresholds=None
    )
    if model.class_score_thresholds is None:
        return out
    return with_tuned_thresholds(out, score_frames(out, frames, SCORE_FLOOR), positive_iou)


def measure(
    model: DetectionModel,
    dataset: Dataset | None,
    frames: list[FrameProposals],
    *,
    use_truth: bool = False,
    references: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    ignored: dict[int, np.ndarray] | None = None,
    **kwargs,
) -> dict:
    """``measure.measure_against`` with the references read from ``dataset``: its annotations or,
    with ``use_truth``, the simulator's full truth, whose objects below the annotation policy are
    then ignored (``ignored_boxes``; ``ignored={}`` turns that off). Given ``references``,
    ``dataset`` may be ``None``. ``kwargs`` go to ``measure_against``."""
    if references is None:
        references = {f.frame_index: reference_boxes(dataset, f.frame_index, use_truth) for f in frames}
        if ignored is None and use_truth:
            ignored = {f.frame_index: ignored_boxes(dataset, f.frame_index) for f in frames}
    return measure_against(model, frames, references, ignored=ignored, **kwargs)


def test_frames(dataset: Dataset, max_frames: int | None = None) -> list[int]:
    """The frames ``evaluate`` measures on: the test split (every frame without one), the first
    ``max_frames`` of them when given."""
    test = dataset.splits.get("test") or list(range(dataset.num_frames))
    return test[:max_frames] if max_frames else test


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
    test = test_frames(dataset, max_frames)
    detector = detector_for(model, dataset, calibrate)
    frames = collect_proposals(dataset, test, detector, progress)
    # Classified and boxed once, measured against the annotations and the truth.
    candidates = {f.frame_index: model.candidates(f.proposal_boxes, f.groups) for f in frames}
    against = {
        "annotations": measure(
            model,
            dataset,
            frames,
            iou_threshold=iou_threshold,
            score_thresholds=score_thresholds,
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
    plain = None
    if simulated:
        # The same without the ignore rule: detections on objects below the policy count as false.
        plain = measure(
            model, dataset, frames, iou_threshold=iou_threshold, use_truth=True, ignored={},
            candidates=candidates,
        )  # fmt: skip
    result = evaluation_result(
        against,
        plain,
        command=command,
        data=data,
        model_path=model_path,
        frames=test,
        iou_threshold=iou_threshold,
    )
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


def evaluation_result(
    against: dict[str, dict],
    truth_without_ignore: dict | None,
    *,
    command: str,
    data: str | os.PathLike,
    model_path: str | os.PathLike,
    frames: Sequence[int],
    iou_threshold: float,
) -> dict:
    """``evaluate``'s record from the metrics against each reference (``"annotations"``, and
    ``"truth"`` on simulated data, with and without the ignore rule); a batch evaluation on Ray
    workers (``scale.jobs.evaluate_batch``) builds the same."""
    reference = "truth" if "truth" in against else "annotations"
    headline = against[reference]
    result = {
        "benchmark": "evaluate",
        "command": command,
        "data": Path(data).name,
        "model": str(model_path),
        "frames": list(frames),
        "reference": reference,
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
    if truth_without_ignore is not None:
        result["truth_without_ignore"] = {
            k: truth_without_ignore[k] for k in ("precision", "recall", "f1", "map")
        }
    return result


def strip_curves(metrics: dict) -> dict:
    """``metrics`` without the PR curves (for printing)."""
    out = dict(metrics)
    for key in ("against", "baseline"):
        if key in out:
            out[key] = {k: {m: v for m, v in d.items() if m != "pr_curves"} for k, d in out[key].items()}
    return out


def frame_list(indices: Sequence[int]) -> str:
    return ", ".join(str(i) for i in indices)
