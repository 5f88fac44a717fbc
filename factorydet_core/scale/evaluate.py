"""Evaluation as a batch: each frame measured on a worker (``EvaluateJob``), the metrics pooled by
the driver from the frames' files (``evaluate_batch``). Apart from ``jobs`` because it reads the
simulator's truth, which the app never imports."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.evaluate import (
    detector_for,
    evaluation_result,
    ignored_boxes,
    reference_boxes,
    test_frames,
)
from factorydet_core.evaluation.measure import RECORD_KEYS, frame_record, metrics_of
from factorydet_core.io.dataset import Dataset, open_dataset
from factorydet_core.io.npz import load_npz, save_npz
from factorydet_core.scale.jobs import ModelJob
from factorydet_core.scale.runner import Execution, frame_path, run_frames
from factorydet_core.training.mining import collect_proposals
from factorydet_core.types import InputError

SHARED_RECORD_KEYS = (
    "boxes",
    "class_ids",
    "scores",
    "candidate_boxes",
    "candidate_class_ids",
    "candidate_scores",
)
"""The parts of ``measure.frame_record`` that do not depend on the references: written once per
frame; the rest once per reference, as ``"<reference>.<key>"``."""


@dataclasses.dataclass
class EvaluateJob(ModelJob):
    """Propose, classify and box a frame, and keep what ``evaluate`` pools over frames: its
    detections and candidates, and against each reference (the annotations; on simulated data the
    truth, with the ignore boxes of objects below the annotation policy) the reference boxes and
    the point sets' true and predicted classes (``measure.frame_record``).

    Args:
        data, model_path, T_vehicle_sensor: as ``ModelJob``'s.
        iou_threshold: the IoU a detection must reach (it labels the point sets for Table 2).
    """

    iou_threshold: float = 0.6
    kind: str = "evaluate"

    def describe(self) -> dict:
        # The operating point is the model's own: as a DetectJob's with no thresholds of its own.
        return {**self.model_identity(), "score_threshold": None, "nms_iou": None,
                "iou_threshold": self.iou_threshold}  # fmt: skip

    @property
    def references(self) -> tuple[str, ...]:
        simulated = (Path(self.data) / "truth").is_dir()
        return ("annotations", "truth") if simulated else ("annotations",)

    def load(self) -> tuple[Dataset, DetectionModel, Detector]:
        return self.open_model()

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        dataset, model, detector = self.loaded()
        (frame,) = collect_proposals(dataset, [frame_index], detector)
        candidates = model.candidates(frame.proposal_boxes, frame.groups)
        arrays: dict[str, np.ndarray] = {}
        for reference in self.references:
            use_truth = reference == "truth"
            boxes, class_ids = reference_boxes(dataset, frame_index, use_truth)
            ignore = ignored_boxes(dataset, frame_index) if use_truth else None
            record = frame_record(
                model, frame, candidates, boxes, class_ids, ignore, iou_threshold=self.iou_threshold
            )
            for key, value in record.items():
                arrays[key if key in SHARED_RECORD_KEYS else f"{reference}.{key}"] = value
        save_npz(out_path, arrays)
        return {"num_candidates": len(candidates.scores), "num_detections": len(arrays["scores"])}


def read_records(
    out_dir: str | os.PathLike, frames: Sequence[int], reference: str, with_ignore: bool = True
) -> Iterator[dict[str, np.ndarray]]:
    """An evaluate job's ``measure.frame_record`` of each frame against ``reference``, read one
    file at a time (``with_ignore`` False drops the ignore boxes: every detection counts)."""
    own = [f"{reference}.{key}" for key in RECORD_KEYS if key not in SHARED_RECORD_KEYS]
    for i in frames:
        path = frame_path(out_dir, i)
        _, arrays = load_npz(path, (*SHARED_RECORD_KEYS, *own))
        if len(arrays) != len(SHARED_RECORD_KEYS) + len(own):
            raise InputError(f"{path}: not an evaluation file against {reference!r}")
        record = {key.removeprefix(f"{reference}."): value for key, value in arrays.items()}
        if not with_ignore:
            record["ignore_boxes"] = np.zeros((0, 7))
        yield record


def evaluate_batch(
    data: str | os.PathLike,
    model_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    execution: Execution,
    *,
    iou_threshold: float = 0.6,
    max_frames: int | None = None,
    calibrate: bool = True,
    progress: Callable[[int, int], None] | None = None,
    command: str = "",
    score_thresholds: Sequence[float] = (),
) -> dict:
    """``evaluate.evaluate``'s record with the per-frame work done by ``execution`` (this process
    or Ray workers) into ``out_dir`` (one file per frame; a re-run resumes), and the metrics pooled
    here from those files, one reference at a time."""
    start = time.perf_counter()
    dataset = open_dataset(data)
    model = DetectionModel.load(model_path)
    frames = test_frames(dataset, max_frames)
    detector = detector_for(model, dataset, calibrate)
    job = EvaluateJob(str(dataset.path), str(model_path), detector.T_vehicle_sensor, iou_threshold)
    run = run_frames(job, frames, out_dir, execution, progress)
    against = {
        reference: metrics_of(
            read_records(out_dir, frames, reference),
            model,
            iou_threshold=iou_threshold,
            score_thresholds=score_thresholds,
        )
        for reference in job.references
    }
    plain = None
    if "truth" in against:
        plain = metrics_of(
            read_records(out_dir, frames, "truth", with_ignore=False), model, iou_threshold=iou_threshold
        )
    result = evaluation_result(
        against,
        plain,
        command=command,
        data=data,
        model_path=model_path,
        frames=frames,
        iou_threshold=iou_threshold,
    )
    result["batch"] = run.summary()
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result
