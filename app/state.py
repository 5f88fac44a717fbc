"""State shared by every browser connected to the app, behind one lock.

viser runs callbacks on a thread pool, so every read-modify-write of this state happens under
``lock``. No viser import here: the state is unit-testable without a server.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from factorydet_core.colors import COLOR_MODES
from factorydet_core.dataset import Dataset
from factorydet_core.types import Frame


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

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until ``predicate()`` holds (checked under the lock) or ``timeout`` seconds pass."""
        with self.lock:
            return self.changed.wait_for(predicate, timeout)
