"""The per-frame work of the batch commands, as jobs ``runner.run_frames`` runs anywhere.

A job holds only paths and small arrays until ``setup`` (it travels to Ray workers by pickle) and
writes one ``.npz`` per frame (``runner.frame_path``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

import numpy as np

from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.model import DetectionModel
from factorydet_core.io.dataset import Dataset, open_dataset
from factorydet_core.io.npz import load_npz, save_npz
from factorydet_core.types import InputError

DETECTION_KEYS = ("boxes", "class_ids", "scores", "suppressed_by", "probabilities")
"""What a detect job writes per frame: ``types.Detections``' arrays (vehicle frame), NMS-suppressed
ones included with the index of the detection that suppressed them (-1: kept)."""


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file (a model's identity in a batch job's description)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


@dataclasses.dataclass
class DetectJob:
    """Detect every frame with one model: the front half, the box head, the score threshold, NMS.

    Args:
        data: the data set folder (every worker must see it at this path).
        model_path: the checkpoint (the same).
        T_vehicle_sensor: (S, 4, 4) extrinsics to merge with, calibrated once by the caller
            (``evaluate.detector_for``); ``None``: each frame's own.
        score_threshold, nms_iou: the operating point; ``None``: the model's (with its per-class
            thresholds).
    """

    data: str
    model_path: str
    T_vehicle_sensor: np.ndarray | None = None
    score_threshold: float | None = None
    nms_iou: float | None = None
    kind: str = "detect"

    def __post_init__(self) -> None:
        self._detector: Detector | None = None
        self._dataset: Dataset | None = None

    def __getstate__(self) -> dict:
        # Workers get the settings, never a loaded model or data set.
        return {k: v for k, v in self.__dict__.items() if k not in ("_detector", "_dataset")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._detector = None
        self._dataset = None

    def describe(self) -> dict:
        extrinsics = None if self.T_vehicle_sensor is None else np.asarray(self.T_vehicle_sensor, float)
        return {
            "data": str(Path(self.data).resolve()),
            "model_sha256": file_digest(self.model_path),
            "T_vehicle_sensor_sha256": None
            if extrinsics is None
            else hashlib.sha256(np.ascontiguousarray(extrinsics).tobytes()).hexdigest(),
            "score_threshold": self.score_threshold,
            "nms_iou": self.nms_iou,
        }

    def setup(self) -> None:
        self._dataset = open_dataset(self.data)
        model = DetectionModel.load(self.model_path)
        if tuple(model.class_names) != tuple(self._dataset.class_names):
            raise InputError(
                f"the model's classes {list(model.class_names)} differ from the data set's "
                f"{list(self._dataset.class_names)}"
            )
        self._detector = Detector(params_for(model, self._dataset.num_sensors), self.T_vehicle_sensor, model)

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        if self._detector is None or self._dataset is None:
            self.setup()
        detector, dataset = self._detector, self._dataset
        result = detector.detect(
            dataset.frame(frame_index),
            detector.history(dataset, frame_index),
            score_threshold=self.score_threshold,
            nms_iou=self.nms_iou,
        )
        detections = result.detections
        save_npz(out_path, {key: getattr(detections, key) for key in DETECTION_KEYS})
        return {
            "num_detections": int(detections.kept_mask.sum()),
            "num_suppressed": int((~detections.kept_mask).sum()),
            "total_ms": float(result.timings_ms["total"]),
        }


def read_detections(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A detect job's frame file: ``DETECTION_KEYS`` -> arrays."""
    _, arrays = load_npz(path, DETECTION_KEYS)
    missing = [k for k in DETECTION_KEYS if k not in arrays]
    if missing:
        raise InputError(f"{path}: not a detection file (missing {', '.join(missing)})")
    return arrays
