"""Data sets: a simulated data set folder, or any single point-cloud file, as a sequence of frames."""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from factorydet_core.io.jsonfile import read_json
from factorydet_core.io.limits import resolve_max_points, resolve_max_read_bytes
from factorydet_core.io.npz import load_npz
from factorydet_core.io.readers import read_frame
from factorydet_core.types import CLASS_NAMES, BoxLabels, Frame, InputError

MANIFEST = "manifest.json"


class Dataset:
    """Frames of one data set, read lazily.

    A folder with a ``manifest.json`` is a simulated (or converted) multi-frame data set; any
    supported point-cloud file opens as a one-frame data set.

    Args:
        path: the data set folder or file.
        max_points: refuse frame files holding more points (``io.limits.resolve_max_points``).
        max_read_bytes: refuse frame files whose read would allocate more bytes
            (``io.limits.resolve_max_read_bytes``).
    """

    def __init__(
        self, path: str | os.PathLike, *, max_points: int | None = None, max_read_bytes: int | None = None
    ) -> None:
        self.path = Path(path)
        self.max_points = resolve_max_points(max_points)
        self.max_read_bytes = resolve_max_read_bytes(max_read_bytes)
        self._hash: str | None = None
        if not self.path.exists():
            raise InputError(f"{self.path}: no such file or folder")
        if self.path.is_dir():
            manifest_path = self.path / MANIFEST
            if not manifest_path.is_file():
                raise InputError(f"{self.path}: not a data set folder (no {MANIFEST})")
            self.manifest = read_json(manifest_path, what="manifest")
            try:
                self.class_names = tuple(self.manifest["classes"])
                self._frame_paths = [self.path / p for p in self.manifest["frames"]]
                self.T_vehicle_sensor = np.array(
                    [s["T_vehicle_sensor"] for s in self.manifest["sensors"]], dtype=np.float64
                ).reshape(-1, 4, 4)
                self.splits = {k: list(v) for k, v in self.manifest.get("splits", {}).items()}
            except (KeyError, TypeError, ValueError, AttributeError, RecursionError) as exc:
                reason = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
                raise InputError(f"{manifest_path}: malformed manifest ({reason})") from None
            if not self._frame_paths:
                # Every consumer starts at frame 0; say so here rather than with an IndexError there.
                raise InputError(f"{self.path}: the data set has no frames ({MANIFEST} lists none)")
            self._single = None
        else:
            self._single = read_frame(
                self.path, max_points=self.max_points, max_read_bytes=self.max_read_bytes
            )
            self.manifest = {"generator": "file", "frames": [self.path.name]}
            self.class_names = self._single.class_names
            self._frame_paths = [self.path]
            self.T_vehicle_sensor = np.asarray(self._single.T_vehicle_sensor)
            self.splits = {"train": [], "test": [0]}

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def num_frames(self) -> int:
        return len(self._frame_paths)

    @property
    def num_sensors(self) -> int:
        return len(self.T_vehicle_sensor)

    def __len__(self) -> int:
        return self.num_frames

    def content_hash(self) -> str:
        """A short SHA-256 of the manifest and every frame file, computed once: a session records it
        so that its labels are never applied to a different data set."""
        if self._hash is None:
            digest = hashlib.sha256()
            manifest = self.path / MANIFEST
            for path in ([manifest] if manifest.is_file() else []) + self._frame_paths:
                digest.update(path.name.encode() + b"\0")
                with open(path, "rb") as f:
                    for block in iter(lambda: f.read(1 << 20), b""):
                        digest.update(block)
            self._hash = digest.hexdigest()[:16]
        return self._hash

    def frame(self, index: int) -> Frame:
        """Frame ``index`` (0-based); frames are cached, so repeated reads are free."""
        self._check_index(index)
        if self._single is not None:
            return self._single
        return self._read_frame(index)

    def frame_labels(self, index: int) -> tuple[str, BoxLabels]:
        """``(name, annotations)`` of frame ``index``, reading only the label arrays of its file:
        what importing a frame's annotations needs, without decompressing its points or taking a
        place in the frames' cache from the frames being viewed."""
        self._check_index(index)
        if self._single is not None:
            return self._single.name, self._single.labels
        path = self._frame_paths[index]
        arrays = self._load(path, LABEL_KEYS)
        with _naming(path):
            labels = _box_labels(arrays)
            labels.check_class_ids(len(self.class_names))  # (as ``Frame`` does, reading a whole frame)
            return path.stem, labels

    def _check_index(self, index: int) -> None:
        if not 0 <= index < self.num_frames:
            raise IndexError(f"{self.name}: frame {index} out of range [0, {self.num_frames})")

    def _load(self, path: Path, keys=None) -> dict[str, np.ndarray]:
        """The arrays ``keys`` (``None``: all) of a frame file, within the data set's caps; every
        failure an ``InputError`` naming the file."""
        try:
            # The arrays and their frozen copies in the Frame.
            _, arrays = load_npz(
                path,
                keys,
                max_points=self.max_points,
                max_read_bytes=self.max_read_bytes,
                conversion_bytes=lambda headers: sum(
                    math.prod(shape) * dtype.itemsize for shape, dtype in headers.values()
                ),
            )
        except FileNotFoundError:
            raise InputError(f"{path}: frame file missing") from None
        except OSError as exc:
            raise InputError(f"{path}: unreadable frame ({type(exc).__name__}: {exc})") from None
        except InputError as exc:
            raise InputError(f"{path}: unreadable frame ({str(exc).removeprefix(f'{path}: ')})") from None
        return arrays

    @lru_cache(maxsize=8)  # noqa: B019 - a data set lives as long as the app; the cache is small.
    def _read_frame(self, index: int) -> Frame:
        path = self._frame_paths[index]
        arrays = self._load(path)
        with _naming(path):
            return Frame(
                name=path.stem,
                points=arrays["points"],
                sensor_ids=arrays["sensor_ids"],
                T_vehicle_sensor=self.T_vehicle_sensor,
                T_world_vehicle=arrays["T_world_vehicle"],
                labels=_box_labels(arrays),
                point_instance_ids=arrays["point_instance_ids"],
                class_names=self.class_names,
            )


@contextlib.contextmanager
def _naming(path: Path):
    """A frame's arrays made into its objects: a missing array or a refused one is an
    ``InputError`` naming the file."""
    try:
        yield
    except KeyError as exc:
        raise InputError(f"{path}: frame lacks the array {exc}") from None
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


LABEL_KEYS = ("label_boxes", "label_class_ids", "label_instance_ids", "label_num_points")
"""A frame file's arrays that hold its annotations."""


def _box_labels(arrays: dict[str, np.ndarray]) -> BoxLabels:
    return BoxLabels(
        boxes=arrays["label_boxes"],
        class_ids=arrays["label_class_ids"],
        instance_ids=arrays["label_instance_ids"],
        num_points=arrays["label_num_points"],
    )


def annotation_min_points(dataset: Dataset, default: int | None = 50) -> int | None:
    """The data set's annotation policy: objects with at least this many points in a frame are
    annotated (the simulator's ``min_annotated_points``; ``default`` when the manifest does not
    say, as for real scans). The truth references of the evaluation (``evaluate.reference_boxes``)
    and the labels of the simulated reviewer and of the full labels of ``bench hitl`` follow it."""
    config = dataset.manifest.get("config", {})
    value = config.get("min_annotated_points") if isinstance(config, dict) else None
    if value is None:
        return default
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        shown = f"{value!r:.60}"
        raise InputError(f"{dataset.path}: malformed manifest (min_annotated_points = {shown})") from None


def open_dataset(
    path: str | os.PathLike, *, max_points: int | None = None, max_read_bytes: int | None = None
) -> Dataset:
    """Open a data set folder or a point-cloud file (``max_points``, ``max_read_bytes``: see ``Dataset``)."""
    return Dataset(path, max_points=max_points, max_read_bytes=max_read_bytes)


__all__ = ["CLASS_NAMES", "Dataset", "annotation_min_points", "open_dataset"]
