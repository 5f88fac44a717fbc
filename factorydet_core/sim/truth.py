"""Reading the simulator's hidden truth. Only benchmarks and tests may import this module."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class FrameTruth:
    """What really is in one simulated frame."""

    T_world_vehicle: np.ndarray
    """(4, 4) true vehicle pose."""
    point_instance_ids: np.ndarray
    """(N,) true instance of every point, 0 for structure."""
    instance_ids: np.ndarray
    """(M,) every visible instance."""
    instance_class_ids: np.ndarray
    """(M,) class id, -1 for clutter."""
    instance_boxes: np.ndarray
    """(M, 7) boxes in the true vehicle frame."""
    instance_num_points: np.ndarray
    annotated_mask: np.ndarray
    """(M,) bool."""


def read_truth(dataset_dir: str | os.PathLike) -> dict:
    """The data set's truth record: true extrinsics and every instance with its class."""
    return json.loads((Path(dataset_dir) / "truth" / "truth.json").read_text())


def read_frame_truth(dataset_dir: str | os.PathLike, frame_index: int) -> FrameTruth:
    with np.load(Path(dataset_dir) / "truth" / f"frame_{frame_index:05d}.npz") as data:
        return FrameTruth(**{field.name: data[field.name] for field in dataclasses.fields(FrameTruth)})
