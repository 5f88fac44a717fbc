"""Fixing labels (one panel per browser): the selected label or segment, its class, delete, a new
label from a segment (or two, split), the box's numbers, undo and redo."""

from __future__ import annotations

import dataclasses

import numpy as np
import viser

from factorydet_core.evaluation.diagnostics import describe_label
from factorydet_core.session.labels_io import FORMATS as EXPORT_FORMATS
from factorydet_core.session.store import COMPUTED_ORIGINS
from factorydet_core.session.world import MOVING_CLASSES
from factorydet_core.types import PRELABEL_SCORE

from ..clients import ClientView
from . import from_user


@dataclasses.dataclass
class LabelsPanel:
    author: viser.GuiTextHandle
    selection: viser.GuiMarkdownHandle
    label_once: viser.GuiCheckboxHandle
    world_status: viser.GuiMarkdownHandle
    spread: viser.GuiButtonHandle
    accept: viser.GuiButtonHandle
    class_name: viser.GuiDropdownHandle
    set_class: viser.GuiButtonHandle
    delete: viser.GuiButtonHandle
    keyframe: viser.GuiButtonHandle
    label_segment: viser.GuiButtonHandle
    split_segment: viser.GuiButtonHandle
    centre: viser.GuiVector3Handle
    size: viser.GuiVector3Handle
    yaw_deg: viser.GuiNumberHandle
    apply_box: viser.GuiButtonHandle
    undo: viser.GuiButtonHandle
    redo: viser.GuiButtonHandle
    min_score: viser.GuiSliderHandle
    prelabel: viser.GuiButtonHandle
    prelabel_status: viser.GuiMarkdownHandle
    next_prelabel: viser.GuiButtonHandle
    confirm: viser.GuiButtonHandle
    confirm_frame: viser.GuiButtonHandle
    _shown: tuple | None = None
    _shown_author: str | None = None

    def refresh(self, view: ClientView) -> None:
        state = view.state
        # The field follows the name when the server changed it (read back from the browser's
        # storage), not whenever they differ: a refresh from another thread between a typed name's
        # arrival and its callback would put the old name back, and the callback would read that.
        if view.author != self._shown_author:
            self._shown_author = view.author
            self.author.value = view.author
        label = view.selected_label()
        points = view.selected_points()
        if not state.editable:
            text = "_This data set is open without a session: labels are read-only._"
        elif label is not None:
            text = describe_label(label, state.db.labels(label.frame_index))
            members = state.db.object_labels(label.id)
            frames = [lab.frame_index + 1 for lab in members]
            if len(frames) > 1:
                text += f"\n\nThe same object is labelled in {len(frames)} frames ({_spans(frames)})."
            computed = [lab.frame_index + 1 for lab in members if lab.origin in COMPUTED_ORIGINS]
            if computed:
                keyframes = sorted(set(frames) - set(computed))
                text += (
                    f" Keyframes: {_spans(keyframes)}; computed between them: {_spans(computed)}"
                    " (moving a computed box makes it a keyframe)."
                )
            elif label.class_name in MOVING_CLASSES:
                text += (
                    "\n\nA moving object: select it, go to another frame and press **Keyframe here [H]**;"
                    " the frames between keyframes get computed boxes."
                )
        elif len(points):
            text = (
                f"**Segment** of {len(view.selected_patch_ids)} patch(es), {len(points):,} points. "
                "**Label segment** boxes it as a new label of the class above; **Split** makes two."
            )
        else:
            text = (
                "_Click a label box to select it; click points to select their segment "
                "(shift-click adds another; shift-drag selects a rectangle)._"
            )
        with view.lock:
            suggested = view.suggestion
        if suggested is not None and label is None and state.editable:
            suggestion = suggested[1]
            size = " x ".join(f"{v:.2f}" for v in suggestion.box[3:6])
            text += (
                f"\n\n**Suggested box** (cyan): {suggestion.class_name}, score {suggestion.score:.2f},"
                f" {size} m. **Accept suggested box [G]** labels it as the class above."
            )
        self.selection.content = text
        self.accept.disabled = suggested is None or not state.editable
        for button in (self.set_class, self.delete, self.apply_box):
            button.disabled = label is None
        self.keyframe.disabled = label is None or label.class_name not in MOVING_CLASSES
        for button in (self.label_segment, self.split_segment):
            button.disabled = not len(points)
        # Fill the Box fields only when another label or version is shown: a refresh caused by
        # someone else's edit must not overwrite numbers the person is typing.
        shown = None if label is None else (label.id, label.version)
        if label is not None and shown != self._shown:
            self._shown = shown
            box = np.asarray(label.box)
            values = (
                tuple(np.round(box[:3], 3)),
                tuple(np.round(box[3:6], 3)),
                round(float(np.degrees(box[6])), 1),
            )
            for handle, value in zip((self.centre, self.size, self.yaw_deg), values):
                if handle.value != value:
                    handle.value = value
        with state.lock:
            world_status = state.world_status
        self.world_status.content = f"_{world_status}_" if world_status else ""
        self.spread.disabled = state.world is None or not state.editable
        if state.db is not None:
            can_undo, can_redo = state.db.can_undo(view.author)
            self.undo.disabled, self.redo.disabled = not can_undo, not can_redo
            waiting = state.db.unreviewed_labels()
            here = sum(lab.frame_index == state.frame_index for lab in waiting)
            self.prelabel_status.content = (
                f"{len(waiting)} pre-label(s) wait for a confirmation, {here} in this frame."
                if waiting
                else "_No pre-label waits for a confirmation._"
            )
            self.next_prelabel.disabled = not waiting
            self.confirm_frame.disabled = not here
            self.confirm.disabled = label is None or label.reviewed
        with state.lock:
            ready = state.detection_result is not None and state.detection_frame_index == state.frame_index
        self.prelabel.disabled = not ready or not state.editable


def _spans(numbers: list[int]) -> str:
    """``[1, 2, 3, 5]`` as "1-3, 5"."""
    spans: list[list[int]] = []
    for n in sorted(set(numbers)):
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def build_labels_panel(view: ClientView) -> LabelsPanel:
    gui = view.client.gui
    names = list(view.state.dataset.class_names)
    with gui.add_folder("Labels", order=30):
        author = gui.add_text(
            "Your name", initial_value=view.author, hint="Edits and reviews are signed with it"
        )
        selection = gui.add_markdown("")
        label_once = gui.add_checkbox(
            "Label once, every frame",
            initial_value=view.label_once,
            hint="A new label, a class, a box move or a delete applies to the object in every frame that "
            "shows it (people and trucks move: their boxes stay per frame). Off: this frame only.",
        )
        world_status = gui.add_markdown("")
        spread = gui.add_button(
            "Label every frame that shows them",
            hint="Each labelled object that stands still gets a label in every frame whose points show it "
            "and that has none (one edit: Undo takes it back)",
        )
        class_name = gui.add_dropdown("Class", names, initial_value=view.object_class)
        set_class = gui.add_button("Set class [C]", hint="Give the selected label the class above")
        delete = gui.add_button("Delete label [Delete]", color="red")
        accept = gui.add_button(
            "Accept suggested box [G]",
            hint="Click an object's points or detection: the model's box for it is suggested (cyan); "
            "this makes it a label of the class above",
        )
        label_segment = gui.add_button("Label segment [L]", hint="A new label boxing the selected segment")
        keyframe = gui.add_button(
            "Keyframe here [H]",
            hint="The selected person or truck, labelled in another frame, gets a box in this frame; the "
            "frames between its keyframes get computed boxes",
        )
        split_segment = gui.add_button("Split segment into two [K]")
        with gui.add_folder("Box", expand_by_default=False):
            # Millimetres and tenths of a degree: the numbers a labeller checks a box with.
            centre = gui.add_vector3("Centre (m)", initial_value=(0.0, 0.0, 0.0), step=0.001)
            size = gui.add_vector3(
                "Size (m)", initial_value=(1.0, 1.0, 1.0), min=(0.02, 0.02, 0.02), step=0.001
            )
            yaw_deg = gui.add_number("Yaw (deg)", initial_value=0.0, step=0.1)
            apply_box = gui.add_button("Apply box", hint="Or drag the gizmo on the selected box")
            box_view = gui.add_button_group("View it from", ("top [T]", "side [V]", "front [F]"))
        with gui.add_folder("Pre-labels", expand_by_default=False):
            min_score = gui.add_slider(
                "Lowest score", min=0.05, max=1.0, step=0.05, initial_value=PRELABEL_SCORE,
                hint="Detections scoring this much or more become pre-labels",
            )  # fmt: skip
            prelabel = gui.add_button(
                "Pre-label this frame [M]",
                hint="The model's detections of this frame become labels waiting for your confirmation "
                "(drawn as corner brackets; training and metrics leave them out until confirmed)",
            )
            prelabel_status = gui.add_markdown("")
            next_prelabel = gui.add_button("Next pre-label [J]")
            confirm = gui.add_button("Confirm [Enter]", hint="The selected pre-label is right as it is")
            confirm_frame = gui.add_button("Confirm all in this frame")
        undo = gui.add_button("Undo [Z]")
        redo = gui.add_button("Redo [Y]")
        with gui.add_folder("Export", expand_by_default=False):
            export_format = gui.add_dropdown(
                "Format", list(EXPORT_FORMATS), initial_value="json",
                hint="JSON boxes; KITTI label files or npz scenes with per-point labels (as a ZIP)",
            )  # fmt: skip
            export = gui.add_button(
                "Download labels", hint="Every frame's labels, as `factorydet labels export`"
            )
    panel = LabelsPanel(
        author, selection, label_once, world_status, spread, accept, class_name, set_class, delete,
        keyframe, label_segment, split_segment, centre, size, yaw_deg, apply_box, undo, redo, min_score,
        prelabel, prelabel_status, next_prelabel, confirm, confirm_frame,
    )  # fmt: skip

    panel._shown_author = view.author

    @author.on_update
    def _(event: viser.GuiEvent) -> None:
        if not from_user(event):
            return
        if view.set_author(author.value):
            view.remember_author()
            view.refresh()
        else:  # an empty name: the field shows the one edits are still signed with
            author.value = view.author

    view.class_dropdowns.append(class_name)

    @label_once.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            view.label_once = bool(label_once.value)

    @class_name.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            view.set_object_class(class_name.value)

    spread.on_click(lambda _: view.spread_labels())
    accept.on_click(lambda _: view.accept_suggestion())
    set_class.on_click(lambda _: view.set_class(class_name.value))
    delete.on_click(lambda _: view.delete_selected())
    label_segment.on_click(lambda _: view.label_segment(class_name.value))
    keyframe.on_click(lambda _: view.keyframe_here())
    split_segment.on_click(lambda _: view.label_segment(class_name.value, split=True))
    export.on_click(lambda _: view.download_labels(export_format.value))
    prelabel.on_click(lambda _: view.prelabel_frame(float(min_score.value)))
    next_prelabel.on_click(lambda _: view.next_prelabel())
    confirm.on_click(lambda _: view.confirm_selected())
    confirm_frame.on_click(lambda _: view.confirm_frame())
    view.prelabel_score = lambda: float(min_score.value)
    undo.on_click(lambda _: view.undo())
    redo.on_click(lambda _: view.undo(redo=True))

    box_view.on_click(lambda _: view.view_selected(box_view.value.split(" ")[0]))

    @apply_box.on_click
    def _(_) -> None:
        view.apply_box([*centre.value, *size.value, float(np.radians(yaw_deg.value))])

    return panel
