"""Display settings: colour mode, point size, points drawn, box visibility and the floor grid."""

from __future__ import annotations

import dataclasses

import viser

from factorydet_core.colors import COLOR_MODES

from ..state import AppState
from . import from_user

_MODE_LABELS = {
    "sensor": "Sensor",
    "height": "Height",
    "class": "Class",
    "annotated": "Annotated / not",
    "rgb": "Colour (RGB)",
}


POINTS_DRAWN_CHOICES = (None, 160_000, 80_000, 40_000, 20_000, 10_000)
"""The "Points drawn" choices (None: every point). A browser without a graphics card renders
points in software, in time that grows with their number."""


def points_drawn_options(*budgets: int | None) -> tuple[str, ...]:
    """The drop-down's texts: the usual choices and ``budgets`` (one set by code or on the
    command line), all first, then from most to fewest points."""
    ordered = sorted({*POINTS_DRAWN_CHOICES, *budgets}, key=lambda n: -1 if n is None else -n)
    return tuple(points_drawn_label(n) for n in ordered)


def points_drawn_label(max_points: int | None) -> str:
    """The "Points drawn" drop-down's text for a budget (None: every point)."""
    return "All" if max_points is None else f"{max_points:,}"


def points_drawn_value(label: str) -> int | None:
    """The budget a "Points drawn" text stands for (``points_drawn_label``'s inverse)."""
    return None if label == "All" else int(label.replace(",", ""))


@dataclasses.dataclass
class DisplayPanel:
    color_mode: viser.GuiDropdownHandle
    point_size: viser.GuiSliderHandle
    show_boxes: viser.GuiCheckboxHandle
    max_height: viser.GuiSliderHandle
    show_box_names: viser.GuiCheckboxHandle
    points_drawn: viser.GuiDropdownHandle
    show_grid: viser.GuiCheckboxHandle

    def refresh(self, state: AppState) -> None:
        """Show the state's display settings (another client or the code may have changed them)."""
        with state.lock:
            mode, size, boxes, height = state.color_mode, state.point_size, state.show_boxes, state.max_height
            names, points_drawn = state.show_box_names, points_drawn_label(state.points_drawn)
            grid = state.show_grid
        if self.show_box_names.value != names:
            self.show_box_names.value = names
        if self.show_grid.value != grid:
            self.show_grid.value = grid
        if self.color_mode.value != _MODE_LABELS[mode]:
            self.color_mode.value = _MODE_LABELS[mode]
        if self.point_size.value != size:
            self.point_size.value = size
        if self.show_boxes.value != boxes:
            self.show_boxes.value = boxes
        if self.max_height.value != height:
            self.max_height.value = height
        if self.points_drawn.value != points_drawn:
            if points_drawn not in self.points_drawn.options:  # (set by code to a budget not offered)
                offered = [points_drawn_value(text) for text in self.points_drawn.options]
                self.points_drawn.options = points_drawn_options(*offered, points_drawn_value(points_drawn))
            self.points_drawn.value = points_drawn


def build_display_panel(server: viser.ViserServer | viser.ClientHandle, state: AppState) -> DisplayPanel:
    labels = [_MODE_LABELS[m] for m in COLOR_MODES]
    with server.gui.add_folder("Display", order=50):
        color_mode = server.gui.add_dropdown(
            "Colour by", labels, initial_value=_MODE_LABELS[state.color_mode]
        )
        point_size = server.gui.add_slider(
            "Point size (m)", min=0.005, max=0.2, step=0.005, initial_value=state.point_size
        )
        show_boxes = server.gui.add_checkbox("Show boxes", initial_value=state.show_boxes)
        show_box_names = server.gui.add_checkbox(
            "Box names",
            initial_value=state.show_box_names,
            hint="Every label's class and every detection's class and score over its box; off, only the "
            "selected box is named",
        )
        max_height = server.gui.add_slider(
            "Hide above (m)",
            min=0.5,
            max=50.0,
            step=0.5,
            initial_value=state.max_height,
            hint="Hide points higher than this, to look under the roof",
        )
        points_drawn = server.gui.add_dropdown(
            "Points drawn",
            points_drawn_options(state.points_drawn),
            initial_value=points_drawn_label(state.points_drawn),
            hint="Draw at most this many points of the scan and of each layer, spread over the whole "
            "cloud. A browser without a graphics card renders points in software: fewer points show "
            "every change sooner. Clicks still pick from every point",
        )
        show_grid = server.gui.add_checkbox(
            "Floor grid",
            initial_value=state.show_grid,
            hint="Lines on the floor every metre, darker every 5 m. A browser without a graphics card "
            "draws them, like the points, at every render of the scene",
        )

    @color_mode.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(color_mode=COLOR_MODES[labels.index(color_mode.value)])

    @point_size.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(point_size=float(point_size.value))

    @show_boxes.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(show_boxes=bool(show_boxes.value))

    @show_box_names.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(show_box_names=bool(show_box_names.value))

    @max_height.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(max_height=float(max_height.value))

    @points_drawn.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(points_drawn=points_drawn_value(points_drawn.value))

    @show_grid.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        state.set_display(show_grid=bool(show_grid.value))

    return DisplayPanel(
        color_mode, point_size, show_boxes, max_height, show_box_names, points_drawn, show_grid
    )
