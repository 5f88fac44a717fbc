"""Detections: layer toggle, score, NMS and box voting sliders that re-filter at once, and what is
shown."""

from __future__ import annotations

import dataclasses

import viser

from ..state import AppState
from . import from_user, short_name


@dataclasses.dataclass
class DetectionsPanel:
    visible: viser.GuiCheckboxHandle
    show_suppressed: viser.GuiCheckboxHandle
    color_by_match: viser.GuiCheckboxHandle
    score_threshold: viser.GuiSliderHandle
    nms_iou: viser.GuiSliderHandle
    summary: viser.GuiMarkdownHandle
    class_thresholds: viser.GuiCheckboxHandle
    vote_iou: viser.GuiSliderHandle

    def refresh(self, state: AppState) -> None:
        with state.lock:
            visible = state.layers["detections"]
            values = (
                state.show_suppressed,
                state.color_by_match,
                state.score_threshold,
                state.nms_iou,
                state.vote_iou,
            )
            detections, model_name, has_model = state.detections, state.model_name, state.model is not None
            per_class = state.use_class_thresholds
            tuned = None if state.model is None else state.model.class_score_thresholds
        for handle, value in zip(
            (
                self.visible,
                self.show_suppressed,
                self.color_by_match,
                self.score_threshold,
                self.nms_iou,
                self.vote_iou,
                self.class_thresholds,
            ),
            (visible, *values, per_class),
        ):
            if handle.value != value:
                handle.value = value
        if self.class_thresholds.disabled != (not tuned):
            self.class_thresholds.disabled = not tuned
        if not has_model:
            self.summary.content = "_No model: run `factorydet train` or start with the default model._"
        elif detections is None:
            name = short_name(model_name)
            self.summary.content = f"Model `{name}`; waiting for the first frame's detections."
        else:
            kept = int(detections.kept_mask.sum())
            threshold = (
                "per-class thresholds " + ", ".join(f"{c} {t:.2f}" for c, t in tuned.items())
                if per_class and tuned
                else "one score threshold"
            )
            self.summary.content = (
                f"**{kept} detections** shown ({len(detections) - kept} suppressed by NMS)"
                f" · model `{short_name(model_name)}` · {threshold}"
            )


def build_detections_panel(
    server: viser.ViserServer | viser.ClientHandle, state: AppState
) -> DetectionsPanel:
    with state.lock:
        has_model = state.model is not None
        score, nms, vote = state.score_threshold, state.nms_iou, state.vote_iou
        per_class = state.use_class_thresholds
    with server.gui.add_folder("Detections", order=70):
        visible = server.gui.add_checkbox(
            "Detections (after NMS)", initial_value=True, disabled=not has_model
        )
        show_suppressed = server.gui.add_checkbox(
            "Show suppressed", initial_value=False, disabled=not has_model
        )
        color_by_match = server.gui.add_checkbox(
            "Colour by match",
            initial_value=False,
            disabled=not has_model,
            hint="Green: matches an annotation (IoU 0.6); red: matches none; blue: annotation missed",
        )
        class_thresholds = server.gui.add_checkbox(
            "Per-class thresholds",
            initial_value=per_class,
            disabled=not per_class,
            hint="Each class's own score threshold, tuned on the training frames; moving the score "
            "slider sets one threshold for all classes",
        )
        score_threshold = server.gui.add_slider(
            "Score threshold", min=0.05, max=1.0, step=0.05, initial_value=score, disabled=not has_model
        )
        nms_iou = server.gui.add_slider(
            "NMS IoU", min=0.05, max=0.95, step=0.05, initial_value=nms, disabled=not has_model
        )
        vote_iou = server.gui.add_slider(
            "Box voting IoU",
            min=0.0,
            max=0.95,
            step=0.05,
            initial_value=vote,
            disabled=not has_model,
            hint="Each kept box becomes the score x IoU weighted mean of the same-class candidates "
            "overlapping it at least this much; 0 switches voting off",
        )
        summary = server.gui.add_markdown("")

    @visible.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_layer("detections", bool(visible.value))

    @show_suppressed.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(show_suppressed=bool(show_suppressed.value))

    @color_by_match.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(color_by_match=bool(color_by_match.value))

    @class_thresholds.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(use_class_thresholds=bool(class_thresholds.value))

    @score_threshold.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(score_threshold=float(score_threshold.value))

    @nms_iou.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(nms_iou=float(nms_iou.value))

    @vote_iou.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            state.set_detection_filter(vote_iou=float(vote_iou.value))

    panel = DetectionsPanel(
        visible,
        show_suppressed,
        color_by_match,
        score_threshold,
        nms_iou,
        summary,
        class_thresholds,
        vote_iou,
    )
    panel.refresh(state)
    return panel
