"""State shared by every browser connected to the app, behind one lock.

viser runs callbacks on a thread pool, so every read-modify-write of this state happens under
``lock``. No viser import here: the state is unit-testable without a server.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from factorydet_core.colors import COLOR_MODES
from factorydet_core.dataset import Dataset
from factorydet_core.detector import PRESETS, FrontEndParams, ProposalResult
from factorydet_core.types import Frame

LAYERS: tuple[str, ...] = ("merged", "voxels", "patches", "segments", "proposals")
"""The detection layers the app can draw, in panel order."""


class AppState:
    """Which frame is shown and how; listeners run after every change (under no lock)."""

    def __init__(self, dataset: Dataset, title: str | None = None) -> None:
        self.dataset = dataset
        self.title = title or dataset.name
        self.lock = threading.RLock()
        self.frame_index = 0
        first = dataset.frame(0)
        self.color_mode = (
            "sensor" if dataset.num_sensors > 1 else ("rgb" if first.colors is not None else "height")
        )
        self.point_size = 0.04
        self.show_boxes = True
        self.max_height = 6.0  # metres: under the simulated hall's 8 m roof, above its racks
        self.num_frame_changes = 0
        # Detection front half: which layers show, its parameters, and the worker's progress.
        self.layers = {name: name == "proposals" for name in LAYERS}
        self.params: FrontEndParams = PRESETS["agv" if dataset.num_sensors > 1 else "indoor"]
        self.use_refined_extrinsics = dataset.num_sensors > 1
        self.pipeline_status = "waiting"
        self.pipeline_progress = 0.0
        self.pipeline_busy = False
        self.pipeline_result: ProposalResult | None = None
        self.pipeline_result_key: tuple | None = None
        self.pipeline_failed_key: tuple | None = None
        self.num_results = 0
        self.selection_markdown = ""
        self._listeners: list[Callable[[], None]] = []
        self.changed = threading.Condition(self.lock)

    def on_change(self, listener: Callable[[], None]) -> None:
        self._listeners.append(listener)

    def _notify(self) -> None:
        for listener in self._listeners:
            listener()

    @property
    def frame(self) -> Frame:
        return self.dataset.frame(self.frame_index)

    def set_frame(self, index: int) -> None:
        """Show frame ``index``, clamped to the data set."""
        index = max(0, min(int(index), self.dataset.num_frames - 1))
        with self.lock:
            if index == self.frame_index:
                return
            self.frame_index = index
            self.num_frame_changes += 1
            self.changed.notify_all()
        self._notify()

    def step_frame(self, delta: int) -> None:
        with self.lock:
            target = self.frame_index + delta
        self.set_frame(target)

    def set_display(
        self,
        *,
        color_mode: str | None = None,
        point_size: float | None = None,
        show_boxes: bool | None = None,
        max_height: float | None = None,
    ) -> None:
        """Change how the frame is drawn; ``None`` leaves a setting as it is."""
        with self.lock:
            if color_mode is not None:
                if color_mode not in COLOR_MODES:
                    raise ValueError(f"unknown colour mode {color_mode!r}; choose from {COLOR_MODES}")
                self.color_mode = color_mode
            if point_size is not None:
                self.point_size = float(point_size)
            if show_boxes is not None:
                self.show_boxes = bool(show_boxes)
            if max_height is not None:
                self.max_height = float(max_height)
            self.changed.notify_all()
        self._notify()

    def set_layer(self, name: str, visible: bool) -> None:
        """Show or hide one of ``LAYERS``."""
        if name not in LAYERS:
            raise ValueError(f"unknown layer {name!r}; choose from {LAYERS}")
        with self.lock:
            self.layers[name] = bool(visible)
            self.changed.notify_all()
        self._notify()

    def set_params(self, **changes) -> None:
        """Change front-half parameters (``FrontEndParams`` or ``SegmentationParams`` field names);
        the worker recomputes the current frame."""
        with self.lock:
            self.params = self.params.replace(**changes)
            self.changed.notify_all()
        self._notify()

    def set_use_refined_extrinsics(self, use: bool) -> None:
        with self.lock:
            self.use_refined_extrinsics = bool(use)
            self.changed.notify_all()
        self._notify()

    def pipeline_key(self) -> tuple:
        """What the current front-half result must have been computed from."""
        with self.lock:
            return (self.frame_index, self.params, self.use_refined_extrinsics)

    def set_pipeline_progress(self, status: str, fraction: float, busy: bool = True) -> None:
        with self.lock:
            self.pipeline_status = status
            self.pipeline_progress = float(fraction)
            self.pipeline_busy = busy
            self.changed.notify_all()
        self._notify()

    def set_pipeline_result(self, key: tuple, result: ProposalResult, status: str) -> None:
        with self.lock:
            self.pipeline_result = result
            self.pipeline_result_key = key
            self.pipeline_status = status
            self.pipeline_progress = 1.0
            self.pipeline_busy = False
            self.selection_markdown = ""
            self.num_results += 1
            self.changed.notify_all()
        self._notify()

    def set_pipeline_failed(self, key: tuple, status: str) -> None:
        """Record a failed run; it is not retried until the frame or the parameters change."""
        with self.lock:
            self.pipeline_failed_key = key
            self.pipeline_status = status
            self.pipeline_progress = 0.0
            self.pipeline_busy = False
            self.changed.notify_all()
        self._notify()

    def set_selection(self, markdown: str) -> None:
        with self.lock:
            self.selection_markdown = markdown
            self.changed.notify_all()
        self._notify()

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until ``predicate()`` holds (checked under the lock) or ``timeout`` seconds pass."""
        with self.lock:
            return self.changed.wait_for(predicate, timeout)
