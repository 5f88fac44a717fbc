"""Frame navigation: slider, previous/next buttons, the status line, and the progress of the
frame's computation (the front half and the detections), where a labeller waiting for it looks."""

from __future__ import annotations

import dataclasses

import numpy as np
import viser

from ..state import AppState
from . import from_user


@dataclasses.dataclass
class FramePanel:
    slider: viser.GuiSliderHandle
    previous: viser.GuiButtonHandle
    next: viser.GuiButtonHandle
    status: viser.GuiMarkdownHandle
    progress: viser.GuiProgressBarHandle
    work: viser.GuiMarkdownHandle

    def refresh(self, state: AppState) -> None:
        """Show the state's frame in the slider and the status line, and its computation's
        progress and status."""
        with state.lock:
            index, frame = state.frame_index, state.frame
            work, fraction, busy = state.pipeline_status, state.pipeline_progress, state.pipeline_busy
        # The slider counts frames from 1, as the status line does.
        if self.slider.value != index + 1:
            self.slider.value = index + 1
        self.previous.disabled = index == 0
        self.next.disabled = index >= state.dataset.num_frames - 1
        _, class_ids, _ = state.frame_labels(index)
        what = "labels in the session" if state.editable else "annotated instances"
        self.status.content = status_markdown(
            state.title, index, state.dataset.num_frames, frame, class_ids, what
        )
        self.progress.value = round(100 * fraction, 1)
        self.work.content = f"{'⏳ ' if busy else ''}{work}"


def status_markdown(
    dataset_name: str, index: int, num_frames: int, frame, class_ids=None, what: str = "annotated instances"
) -> str:
    class_ids = frame.labels.class_ids if class_ids is None else np.asarray(class_ids)
    per_class = np.bincount(class_ids, minlength=len(frame.class_names)) if len(class_ids) else []
    counts = ", ".join(f"{name} {n}" for name, n in zip(frame.class_names, per_class) if n) or "none"
    return (
        f"**{dataset_name}** · frame **{index + 1} / {num_frames}** (`{frame.name}`)  \n"
        f"{frame.num_points:,} points · {frame.num_sensors} sensors  \n"
        f"{len(class_ids)} {what}: {counts}"
    )


def build_frame_panel(server: viser.ViserServer | viser.ClientHandle, state: AppState) -> FramePanel:
    num_frames = state.dataset.num_frames
    with server.gui.add_folder("Frame", order=10):
        slider = server.gui.add_slider(
            "Frame", min=1, max=max(num_frames, 2), step=1, initial_value=1, disabled=num_frames <= 1
        )
        with server.gui.add_folder("Step", expand_by_default=True):
            previous = server.gui.add_button("Previous frame", icon=viser.Icon.ARROW_LEFT, disabled=True)
            next_ = server.gui.add_button("Next frame", icon=viser.Icon.ARROW_RIGHT, disabled=num_frames <= 1)
        status = server.gui.add_markdown("")
        # Not animated while busy either (the status says so): the stripes' animation costs a browser
        # without a GPU cores the frame's own computation needs (see the Training panel's bar).
        progress = server.gui.add_progress_bar(0.0, animated=False)
        work = server.gui.add_markdown("")

    @slider.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_frame(int(slider.value) - 1)

    @previous.on_click
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.step_frame(-1)

    @next_.on_click
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.step_frame(+1)

    panel = FramePanel(slider, previous, next_, status, progress, work)
    panel.refresh(state)
    return panel
