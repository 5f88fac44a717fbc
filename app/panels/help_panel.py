"""Keyboard shortcuts (registered per browser, so each acts on that browser's selection and
review item) and the help panel that lists them."""

from __future__ import annotations

import viser

from ..browser_session import NUDGE_DEG, NUDGE_M
from ..clients import ClientView
from .review_panel import wrong_box

# (key, what it does, the action on a ClientView given the panels' current class)
# No W, A, S, D, Q, E or arrow keys: viser's camera moves on those (with any modifier).
HOTKEYS: tuple[tuple[str, str], ...] = (
    ("B", "review: background"),
    ("O", "review: object of the chosen class"),
    ("R", "review: wrong box (re-box it)"),
    ("X", "review: skip"),
    ("I", "review: look at the item's object in the frame that sees it best"),
    ("N", "review: next item"),
    ("P", "review: previous item"),
    ("U", "next suspect label (one the model contradicts)"),
    ("C", "label: set the chosen class"),
    ("G", "accept the suggested box (the model's, for the object clicked) as a label"),
    ("L", "label the selected segment"),
    ("H", "person or truck selected in another frame: add a keyframe here (boxes between keyframes follow)"),
    ("M", "pre-label this frame: the model's detections wait for your confirmation"),
    ("J", "next pre-label waiting for a confirmation"),
    ("enter", "confirm the selected pre-label (and go to the next)"),
    ("K", "split the selected segment into two labels"),
    ("delete", "delete the selected label"),
    ("Z", "undo your last edit"),
    ("Y", "redo"),
    ("escape", "clear the selection"),
    ("1-7", "choose the class (barrel … truck)"),
    ("T / V / F", "look at the selected box from the top / its side / its front"),
    ("page down / page up", "next / previous frame"),
    ("shift+I / shift+K", "move the selected box 1 cm forward / back along its heading"),
    ("shift+J / shift+L", "move it 1 cm to its left / right"),
    ("shift+Y / shift+H", "move it 1 cm up / down"),
    ("shift+U / shift+O", "turn it 1 degree left / right"),
    ("alt+I / alt+K", "make it 1 cm longer / shorter (about its centre)"),
    ("alt+L / alt+J", "make it 1 cm wider / narrower"),
    ("alt+Y / alt+H", "make it 1 cm taller / lower (its bottom stays)"),
    ("drag a face's ball", "move that face alone (the opposite one stays)"),
)

NUDGES: dict[str, tuple[str, dict]] = {
    "I": ("forward", {"forward": NUDGE_M}),
    "K": ("back", {"forward": -NUDGE_M}),
    "J": ("left", {"left": NUDGE_M}),
    "L": ("right", {"left": -NUDGE_M}),
    "Y": ("up", {"up": NUDGE_M}),
    "H": ("down", {"up": -NUDGE_M}),
    "U": ("turn left", {"yaw_deg": NUDGE_DEG}),
    "O": ("turn right", {"yaw_deg": -NUDGE_DEG}),
}
"""Shift + key: how the selected box moves (``BrowserSession.nudge``)."""

RESIZES: dict[str, tuple[str, dict]] = {
    "I": ("longer", {"longer": NUDGE_M}),
    "K": ("shorter", {"longer": -NUDGE_M}),
    "L": ("wider", {"wider": NUDGE_M}),
    "J": ("narrower", {"wider": -NUDGE_M}),
    "Y": ("taller", {"taller": NUDGE_M}),
    "H": ("lower", {"taller": -NUDGE_M}),
}
"""Alt + key: how the selected box is resized, centimetre steps (``BrowserSession.nudge``)."""


def help_markdown(class_names: tuple[str, ...]) -> str:
    rows = "\n".join(f"| `{key}` | {what} |" for key, what in HOTKEYS)
    classes = ", ".join(f"`{i + 1}` {name}" for i, name in enumerate(class_names))
    return (
        "| key | action |\n|---|---|\n" + rows + "\n\n"
        f"Classes: {classes}.  \nMouse: click a box to select it, click points to select their "
        "segment (with a model, its box for the object is suggested in cyan), shift-click to add a "
        "segment, shift-drag to select a rectangle. Drag the gizmo to move or turn the selected box. "
        "Ctrl/Cmd+K lists every command. Keys pressed on a drop-down once it is closed are "
        "these hotkeys (an open drop-down searches its options as you type).  \nSlow to show "
        "changes? Without a graphics card the browser draws points in software: Display > Points "
        "drawn (e.g. 20,000) shows every change sooner."
    )


def register_hotkeys(view: ClientView, labels_panel, review_panel) -> list[viser.CommandHandle]:
    """Register the shortcuts for one browser; returns the command handles."""
    gui = view.client.gui
    names = view.state.dataset.class_names

    def chosen_class() -> str:
        return view.object_class

    actions = {
        "B": ("Review: background", lambda: view.verdict("background")),
        "O": ("Review: object", lambda: view.verdict("object", chosen_class())),
        "R": ("Review: wrong box", lambda: wrong_box(view)),
        "X": ("Review: skip", lambda: view.verdict("skip")),
        "I": ("Review: look where it is seen best", view.look_where_seen_best),
        "N": ("Review: next item", lambda: view.step(1)),
        "P": ("Review: previous item", lambda: view.step(-1)),
        "U": ("Next suspect label", view.next_suspect),
        "C": ("Label: set class", lambda: view.set_class(chosen_class())),
        "G": ("Accept the suggested box", view.accept_suggestion),
        "L": ("Label the selected segment", lambda: view.label_segment(chosen_class())),
        "H": ("Keyframe of the selected person or truck here", view.keyframe_here),
        "M": ("Pre-label this frame", lambda: view.prelabel_frame(view.prelabel_score())),
        "J": ("Next pre-label", view.next_prelabel),
        "enter": ("Confirm the selected pre-label", view.confirm_selected),
        "K": ("Split the selected segment", lambda: view.label_segment(chosen_class(), split=True)),
        "delete": ("Delete the selected label", view.delete_selected),
        "Z": ("Undo", view.undo),
        "Y": ("Redo", lambda: view.undo(redo=True)),
        "escape": ("Clear the selection", view.clear_selection),
        "T": ("View the selected box from the top", lambda: view.view_selected("top")),
        "V": ("View the selected box from its side", lambda: view.view_selected("side")),
        "F": ("View the selected box from its front", lambda: view.view_selected("front")),
        "pagedown": ("Next frame", lambda: view.state.step_frame(1)),
        "pageup": ("Previous frame", lambda: view.state.step_frame(-1)),
    }
    handles = []
    for key, (label, action) in actions.items():
        handle = gui.add_command(label, hotkey=key)
        handle.on_trigger(lambda _event, action=action: view.respond(action))
        handles.append(handle)
    for key, (what, step) in NUDGES.items():
        handle = gui.add_command(f"Box: {what}", hotkey=key, modifier="shift")
        handle.on_trigger(lambda _event, step=step: view.respond(lambda: view.nudge(**step)))
        handles.append(handle)
    for key, (what, step) in RESIZES.items():
        handle = gui.add_command(f"Box: {what}", hotkey=key, modifier="alt")
        handle.on_trigger(lambda _event, step=step: view.respond(lambda: view.nudge(**step)))
        handles.append(handle)
    for i, name in enumerate(names[:9]):

        def choose(_event, name=name) -> None:
            view.set_object_class(name)

        handle = gui.add_command(f"Class: {name}", hotkey=str(i + 1))
        handle.on_trigger(choose)
        handles.append(handle)
    return handles


def build_help_panel(view: ClientView) -> None:
    with view.client.gui.add_folder("Keys", order=90, expand_by_default=False):
        view.client.gui.add_markdown(help_markdown(view.state.dataset.class_names))
