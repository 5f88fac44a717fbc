"""Reading the simulator's hidden truth. Only benchmarks and tests may import this module."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from factorydet_core.io.jsonfile import read_json
from factorydet_core.io.npz import load_npz
from factorydet_core.types import InputError


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
    """The data set's truth record: true extrinsics and every instance with its class.

    Raises:
        InputError: the record is missing, unreadable, malformed or not a JSON object.
    """
    path = Path(dataset_dir) / "truth" / "truth.json"
    record = read_json(path, what="truth record")
    if not isinstance(record, dict):
        raise InputError(f"{path}: malformed truth record (not a JSON object)")
    return record


def read_frame_truth(dataset_dir: str | os.PathLike, frame_index: int) -> FrameTruth:
    """The truth of one frame, read through ``io.npz.load_npz`` (its headers checked first).

    Raises:
        InputError: a broken or hostile file, or one lacking an array.
        OSError: the file cannot be opened (``FileNotFoundError`` for a frame without truth).
    """
    path = Path(dataset_dir) / "truth" / f"frame_{frame_index:05d}.npz"
    names = [field.name for field in dataclasses.fields(FrameTruth)]
    _, arrays = load_npz(path, names)
    missing = [name for name in names if name not in arrays]
    if missing:
        raise InputError(f"{path}: the truth lacks the arrays {', '.join(missing)}")
    return FrameTruth(**arrays)
