"""Detection front half: layer toggles, segmentation and voxel parameters, selection (its progress
shows in the Frame panel)."""

from __future__ import annotations

import dataclasses

import viser

from ..state import AppState
from . import from_user

LAYER_LABELS = {
    "merged": "Merged cloud (by sensor)",
    "voxels": "Voxels (Fisher-vector colours)",
    "patches": "Patches (cut pursuit)",
    "segments": "Segments (merged patches)",
    "proposals": "Proposal boxes",
}


@dataclasses.dataclass
class PipelinePanel:
    layer_boxes: dict[str, viser.GuiCheckboxHandle]
    refined: viser.GuiCheckboxHandle
    voxel_size: viser.GuiSliderHandle
    regularization: viser.GuiSliderHandle
    merge_threshold: viser.GuiSliderHandle
    selection: viser.GuiMarkdownHandle

    def refresh(self, state: AppState) -> None:
        """Show the state's layers, parameters and selection."""
        with state.lock:
            layers = dict(state.layers)
            params = state.params
            refined = state.use_refined_extrinsics
            selection = state.selection_markdown
        for name, box in self.layer_boxes.items():
            if box.value != layers[name]:
                box.value = layers[name]
        if self.refined.value != refined:
            self.refined.value = refined
        for handle, value in (
            (self.voxel_size, params.voxel_size_m),
            (self.regularization, params.segmentation.regularization),
            (self.merge_threshold, params.segmentation.merge_threshold),
        ):
            if abs(handle.value - value) > 1e-9:
                handle.value = value
        self.selection.content = selection or "_Click a point (any layer) or a proposal box._"


def build_pipeline_panel(server: viser.ViserServer | viser.ClientHandle, state: AppState) -> PipelinePanel:
    with state.lock:
        params = state.params
        layers = dict(state.layers)
    with server.gui.add_folder("Detection layers", order=60):
        layer_boxes = {
            name: server.gui.add_checkbox(label, initial_value=layers[name])
            for name, label in LAYER_LABELS.items()
        }
        refined = server.gui.add_checkbox(
            "Refined extrinsics (ICP)",
            initial_value=state.use_refined_extrinsics,
            disabled=state.dataset.num_sensors < 2,
            hint="Merge with extrinsics refined by ICP between sensors instead of the nominal ones",
        )
        # (inside: one folder for the front half, fewer folders in the sidebar)
        with server.gui.add_folder("Segmentation"):
            voxel_size = server.gui.add_slider(
                "Voxel size (m)", min=0.05, max=0.5, step=0.05, initial_value=params.voxel_size_m
            )
            regularization = server.gui.add_slider(
                "Regularisation",
                min=0.005,
                max=0.5,
                step=0.005,
                initial_value=params.segmentation.regularization,
                hint="Cut-pursuit lambda: larger gives fewer, bigger patches",
            )
            merge_threshold = server.gui.add_slider(
                "Merge threshold",
                min=0.0,
                max=1.0,
                step=0.05,
                initial_value=params.segmentation.merge_threshold,
                hint="Least contact strength for two adjacent patches to merge into one segment",
            )
        with server.gui.add_folder("Selection"):
            selection = server.gui.add_markdown("")

    for name, box in layer_boxes.items():

        def on_toggle(event: viser.GuiEvent, name: str = name, box: viser.GuiCheckboxHandle = box) -> None:
            if not from_user(event):
                return
            state.set_layer(name, bool(box.value))

        box.on_update(on_toggle)

    @refined.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_use_refined_extrinsics(bool(refined.value))

    @voxel_size.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_params(voxel_size_m=float(voxel_size.value))

    @regularization.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_params(regularization=float(regularization.value))

    @merge_threshold.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_params(merge_threshold=float(merge_threshold.value))

    panel = PipelinePanel(layer_boxes, refined, voxel_size, regularization, merge_threshold, selection)
    panel.refresh(state)
    return panel
