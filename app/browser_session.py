"""One browser's labelling state and actions: what it selected, where it is in the review queue,
its undo author, its class, and every action a person takes (select, edit, label a segment, undo,
review, batch, suspects). ``clients.ClientView`` adds the drawing; this module never imports viser,
so tests drive it in-process.

The session is shared by every browser; a view (``state.AppState``: frame, display, thresholds),
a selection, a camera, a review cursor and an undo stack (by author name) are each browser's own.
Every edit goes through the session database, which commits it before the call returns, so an
edit the panel acknowledges is stored;
an edit made against a label or verdict someone else has changed since is refused and the person
is told (``EditConflictError``).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import secrets
import sqlite3
import threading
from collections.abc import Callable

import numpy as np

from factorydet_core.session.editing import (
    box_of_points,
    camera_view_of_box,
    nudge_box,
    prelabel_frame,
    split_in_two,
)
from factorydet_core.session.labels_io import export_bytes
from factorydet_core.session.review_rank import LearnedOrder, RankedPlaces, place_order
from factorydet_core.session.store import HIDE_LABELLED_IOU, EditConflictError, on_labelled_object
from factorydet_core.session.world import (
    MOVING_CLASSES,
    BestView,
    best_view,
    group_by_place,
    interpolate_boxes,
    not_labelled_yet,
    place_box,
    place_chance,
    spread_session,
)
from factorydet_core.types import PRELABEL_SCORE, InputError

from .state import AppState

NUDGE_M = 0.01
"""How far one keyboard nudge moves the selected box, metres."""
NUDGE_DEG = 1.0
"""How far one keyboard nudge turns it, degrees."""

FAILED = object()
"""What ``BrowserSession._guarded`` returns when the edit was refused (the person has been told)."""


def _coalesced(method):
    """A ``BrowserSession`` action run in one ``coalesced`` block: the browser brought up to date
    once, when it ends."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self.coalesced():
            return method(self, *args, **kwargs)

    return run


def _by_place(queue: list[dict], places: list[list[int]], current_id: int | None) -> list[dict]:
    """One entry per place of ``queue`` (``world.group_by_place``'s order): its best item (the
    shown one, if it is of the place), with ``place_versions`` ({item id: review version} of all
    its items, what its verdict answers), ``place_frames`` and ``place_chance``
    (``world.place_chance``: what orders the places)."""
    out = []
    for members in places:
        items = [queue[k] for k in members]
        shown = next((q for q in items if q["id"] == current_id), items[0])
        out.append(
            {
                **shown,
                "place_versions": {q["id"]: q["review_version"] for q in items},
                "place_frames": sorted({q["frame_index"] for q in items}),
                "place_chance": place_chance([q["score"] for q in items]),
            }
        )
    return out


def _answered(entry: dict) -> dict[int, int]:
    """``{item id: review version}`` a verdict on a queue entry answers: every item of its place
    (one object mined in several frames), else the item alone."""
    return entry.get("place_versions") or {entry["id"]: entry["review_version"]}


class BrowserSession:
    """One browser's selection, review cursor, undo author and class choice, with every action a
    person takes on them; no viser here (``clients.ClientView`` draws it), so that the labelling
    logic is tested in-process.

    Args:
        state: the shared app state.
        drawn_result: returns ``(ProposalResult | None, frame_index)`` currently drawn.
    """

    def __init__(self, state: AppState, drawn_result: Callable[[], tuple]) -> None:
        self.state = state
        self.drawn_result = drawn_result
        self.lock = threading.RLock()
        # viser numbers browsers from 0 at every start, so the default name must not be the id:
        # a new browser would otherwise inherit (and undo) an earlier person's edits.
        self.author = f"reviewer-{secrets.token_hex(3)}"
        self.selected_label_id: int | None = None
        self.selected_label_version: int | None = None
        self.selected_patch_ids: set[int] = set()
        self.selected_frame: int | None = None
        self.object_class = state.dataset.class_names[0]
        self.suggestion: tuple[int, object] | None = None
        """``(frame_index, editing.Suggestion)``: the model's box for the object last clicked."""
        self.prelabel_score: Callable[[], float] = lambda: PRELABEL_SCORE
        """The lowest score a pre-label takes (the Pre-labels panel's slider, once built)."""
        self.label_once = True
        """Edits apply to the selected object in every frame (label once, ``world``), not to this
        frame's box alone."""
        # Review: filters, the item shown, whether the scene is dimmed around it.
        self.filter_class: str | None = None
        self.filter_frame: int | None = None
        self.pending_only = True
        self.hide_labelled = False
        self.group_places = True
        """One queue entry per place (``world.group_by_place``: an object mined in several frames),
        whose verdict answers all its items; needs the frames placed."""
        self.current_item_id: int | None = None
        self.dim = True
        self.queue: list[dict] = []
        self._queue_read: tuple | None = None  # ((change stamp, class, frame), the session's queue)
        self._places: tuple | None = None  # ((world, item ids read, order), group_by_place's places)
        self._learned: LearnedOrder | None = None  # the learned review order's fits (review_rank)
        self._ordered: tuple | None = None  # ((the read, world, session), places in order, ranked or None)
        self._shown_queue: tuple | None = None  # (everything load_queue's result depends on, it)
        self._best_view: tuple | None = None  # (item id, the placement, best_view's answer)
        self.suspect_index = -1
        self.messages: collections.deque[tuple[str, str, bool]] = collections.deque(maxlen=100)
        """The latest notifications given, ``(title, body, error)``, oldest first."""

    def set_author(self, name: str) -> bool:
        """Sign this browser's edits with ``name`` (letters, digits, space and ``.-_@``, at most 64
        characters; anything else is dropped); False, and nothing changed, for a name left empty."""
        name = "".join(c for c in str(name) if c.isalnum() or c in " .-_@")[:64].strip()
        if not name:
            return False
        with self.lock:
            self.author = name
        return True

    # -- what the browser shows: ``ClientView`` draws these

    def notify(self, title: str, body: str, error: bool = False) -> None:
        """Tell the person something (a refused edit is an error)."""
        self.messages.append((title, body, error))

    def batched(self) -> contextlib.AbstractContextManager:
        """A block whose updates this browser receives at once, after it ends (one render of
        its scene instead of one per update: under software WebGL each costs half a second)."""
        return contextlib.nullcontext()

    def coalesced(self) -> contextlib.AbstractContextManager:
        """A block (``batched``) in which this browser's scene and panels are brought up to date
        once, at its end, however many changes inside ask for it (a verdict writes, moves to
        another frame and shows the next item: three redraws of the same panels otherwise)."""
        return contextlib.nullcontext()

    def look_at_box(self, box) -> None:
        """Put this browser's camera on ``box`` (7,)."""

    def set_camera(self, position, look_at, up) -> None:
        """Put this browser's camera at ``position`` looking at ``look_at`` with ``up`` up."""

    def view_selected(self, view: str) -> None:
        """Look at the selected box from above, its side or its front (``editing.BOX_VIEWS``)."""
        label = self.selected_label()
        if label is None:
            self.notify("Box view", "Select a label first (click its box).")
            return
        self.set_camera(*camera_view_of_box(label.box, view))

    def refresh(self) -> None:
        """Bring this browser's panels and highlights up to date."""

    def _object_class_shown(self, name: str) -> None:
        """Show ``name`` as the chosen class in every panel that shows it."""

    def _guarded(self, action: Callable[[], object], what: str, reload_selection: bool = True) -> object:
        """Run an edit; a conflict, a refused edit or a database failure becomes a notification
        (and ``FAILED`` is returned), never an exception in viser's callback thread.

        Args:
            reload_selection: after a conflict, take in the selected label as it is now (the
                conflict was about it). Off for an undo, whose conflict may be about any label.
        """
        with self.batched():
            return self._guarded_now(action, what, reload_selection)

    def _guarded_now(self, action: Callable[[], object], what: str, reload_selection: bool) -> object:
        try:
            result = action()
        except EditConflictError as exc:
            body = str(exc).removesuffix("; reload and try again")
            if reload_selection:
                body += ". The selection now holds it as it is: make your edit again."
            self.notify(f"{what}: someone else got there first", body, error=True)
            if reload_selection:
                self._reload_selected_version()
            self.state.session_changed()
            return FAILED
        except InputError as exc:  # SessionError included
            self.notify(f"{what}: not done", str(exc), error=True)
            return FAILED
        except sqlite3.Error as exc:
            self.notify(f"{what}: the session database failed", f"{type(exc).__name__}: {exc}", error=True)
            return FAILED
        self.state.session_changed()
        return result

    # -- selection

    def selected_label(self):
        """The selected label as stored now (``None`` if none or deleted)."""
        with self.lock:
            label_id = self.selected_label_id
        if label_id is None or self.state.db is None:
            return None
        label = self.state.db.label(label_id)
        return None if label.deleted else label

    def _reload_selected_version(self) -> None:
        """After a conflict the person sees the label as it is now; their next edit is made
        against that version. A deleted label keeps its version too: were it restored later (an
        undo), an edit from here must be refused, not made unversioned over whatever changed."""
        with self.lock:
            label_id = self.selected_label_id
        label = None
        if label_id is not None and self.state.db is not None:
            try:
                label = self.state.db.label(label_id)
            except InputError:  # gone altogether (another session's database): nothing to edit
                label = None
        with self.lock:
            if self.selected_label_id == label_id:
                self.selected_label_version = None if label is None else label.version

    def select_label(self, label_id: int | None) -> None:
        """Select a label; edits from here on are made against the version selected (or last
        edited by this browser), so someone else's change in between is reported, not overwritten.
        The chosen class becomes the label's own, so that Set class [C] changes nothing until
        another class is picked."""
        label = None
        if label_id is not None and self.state.db is not None:
            label = self.state.db.label(label_id)
        with self.lock:
            self.selected_label_id = label_id
            self.selected_label_version = None if label is None else label.version
            self.selected_patch_ids = set()
            self.suggestion = None
        if label is not None:
            self.set_object_class(label.class_name)
        self.refresh()

    def follow_object(self) -> None:
        """After a frame change, the selected label becomes its object's label in the shown frame
        (label once: the same object stays selected while flipping through frames); with no label
        of it there, the selection stays where it was."""
        with self.lock:
            label_id = self.selected_label_id
        frame_index = self.state.frame_index
        if label_id is None or self.state.db is None:
            return
        label = self.state.db.label(label_id)
        if label.frame_index == frame_index or label.instance_id is None or label.deleted:
            return
        here = [lab for lab in self.state.db.object_labels(label_id) if lab.frame_index == frame_index]
        if here:
            with self.lock:
                if self.selected_label_id == label_id:
                    self.selected_label_id = here[0].id
                    self.selected_label_version = here[0].version

    def select_patches(self, patch_ids, add: bool = False) -> None:
        """Select the segment made of ``patch_ids`` of the drawn result (``add``: extend it)."""
        _, frame_index = self.drawn_result()
        with self.lock:
            if not add or self.selected_frame != frame_index:
                self.selected_patch_ids = set()
            self.selected_patch_ids |= {int(p) for p in patch_ids}
            self.selected_frame = frame_index
            self.selected_label_id = None
            self.selected_label_version = None
            self.suggestion = None
        self.refresh()

    def clear_selection(self) -> None:
        """Nothing selected (Escape): no label, segment or suggestion, and no description of the
        last thing clicked."""
        with self.lock:
            self.selected_label_id = None
            self.selected_label_version = None
            self.selected_patch_ids = set()
            self.suggestion = None
        self.state.set_selection("")
        self.refresh()

    def shown_result(self) -> tuple:
        """``(ProposalResult | None, frame_index)`` drawn, the result ``None`` when it is another
        frame's (hidden while the shown frame's is computed: its points are not the scan drawn)."""
        result, frame_index = self.drawn_result()
        with self.state.lock:
            shown = frame_index == self.state.frame_index
        return (result if shown else None), frame_index

    def selected_points(self) -> np.ndarray:
        """(K, 3) points of the selected segment in the drawn result."""
        result, frame_index = self.shown_result()
        with self.lock:
            patch_ids = set(self.selected_patch_ids)
            frame = self.selected_frame
        if result is None or not patch_ids or frame != frame_index:
            return np.zeros((0, 3))
        mask = np.isin(result.segmentation.patch_ids, list(patch_ids))
        return result.cloud.points[mask]

    # -- label edits

    def _edit_selected(self, what: str, edit: Callable) -> object:
        """Apply ``edit(label_id, expected_version)`` to the selected label."""
        with self.lock:
            label_id, version = self.selected_label_id, self.selected_label_version
        if label_id is None:
            self.notify(what, "Select a label first (click its box).")
            return FAILED
        if version is None:  # never edit unversioned: someone else's change would be overwritten
            self.notify(what, "That label is gone: select a label again.", error=True)
            return FAILED
        result = self._guarded(lambda: edit(label_id, version), what)
        if result is not FAILED and hasattr(result, "version"):
            with self.lock:
                self.selected_label_version = result.version
        return result

    def _world_for(self, class_name: str):
        """The frames' world placement when an edit of a ``class_name`` object is carried to every
        frame (label once on, placed already, a class that stands still), else ``None``."""
        if not self.label_once or class_name in MOVING_CLASSES:
            return None
        with self.state.lock:
            return self.state.world

    def _tracker(self, class_name: str):
        """``keyframes -> {frame: box}`` between them (``world.interpolate_boxes``) when an edit
        of a ``class_name`` object recomputes its boxes between keyframes (label once on, placed
        already, a class that moves), else ``None``."""
        if not self.label_once or class_name not in MOVING_CLASSES:
            return None
        with self.state.lock:
            world = self.state.world
        return None if world is None else (lambda keyframes: interpolate_boxes(world, keyframes))

    def keyframe_here(self) -> None:
        """The selected person or truck, labelled in another frame, gets a box in the shown frame
        too (where the frames' poses carry its box: move it onto the object), and its boxes in
        the frames between its keyframes are computed; one edit."""
        label = self.selected_label()
        frame_index = self.state.frame_index
        if label is None:
            self.notify("Keyframe", "Select a person or truck first (click its box in a frame that has it).")
            return
        if label.class_name not in MOVING_CLASSES:
            self.notify(
                "Keyframe",
                f"A {label.class_name} stands still: with label once it is in every frame that shows it "
                "already. Keyframes are for people and trucks.",
            )
            return
        if label.frame_index == frame_index:
            self.notify("Keyframe", "The object is labelled in this frame already: move its box here.")
            return
        with self.state.lock:
            world = self.state.world
        if world is None:
            self.notify("Keyframe", "The frames are not placed in one world frame yet: wait for it.")
            return
        box = place_box(world, label.frame_index, label.box).boxes[frame_index]
        tracker = self._tracker(label.class_name)
        added = self._edit_selected(
            "Keyframe",
            lambda i, v: self.state.db.add_keyframe(
                i, frame_index, box, self.author, expected_version=v, track=tracker
            ),
        )
        if added is not FAILED:
            self.select_label(added.id)

    def set_class(self, class_name: str) -> None:
        """The selected label's class; with label once, its object's in every frame."""
        db = self.state.db
        if self.label_once:
            edit = lambda i, v: db.update_object(i, self.author, expected_version=v, class_name=class_name)  # noqa: E731
        else:
            edit = lambda i, v: db.update_label(i, self.author, expected_version=v, class_name=class_name)  # noqa: E731
        self._edit_selected("Set class", edit)

    def apply_box(self, box) -> None:
        """The selected label's box; with label once, its object's box in every frame that shows it
        (carried by the frames' poses; a person or a truck moves: its box changes here only)."""
        db = self.state.db

        def edit(label_id: int, version: int):
            label = db.label(label_id)
            world = self._world_for(label.class_name)
            if world is None:  # a moving object's boxes between its keyframes follow, if any
                track = self._tracker(label.class_name)
                return db.update_label(label_id, self.author, expected_version=version, box=box, track=track)
            boxes, show_in = place_box(world, label.frame_index, box).for_store()
            return db.update_object(
                label_id, self.author, expected_version=version, boxes=boxes, show_in=show_in
            )

        self._edit_selected("Move box", edit)

    def nudge(self, **step: float) -> None:
        """Move, turn or resize the selected box by ``step`` (``editing.nudge_box``'s keywords:
        ``forward``, ``left``, ``up`` in metres, ``yaw_deg``, ``longer``, ``wider``, ``taller``);
        one edit (``apply_box``)."""
        label = self.selected_label()
        if label is None:
            self.notify("Move box", "Select a label first (click its box).")
            return
        self.apply_box(tuple(nudge_box(label.box, **step)))

    def delete_selected(self) -> None:
        """Delete the selected label; with label once, its object in every frame."""
        done = self._edit_selected(
            "Delete",
            lambda i, v: self.state.db.delete_labels([i], self.author, {i: v}, whole_objects=self.label_once),
        )
        if done is not FAILED:
            self.select_label(None)

    def suggest(self, frame_index: int, suggestion) -> None:
        """Show the model's box for the object just clicked (``editing.suggest_box``; ``None``:
        none there); Accept [G] makes it a label. The chosen class becomes its class."""
        with self.lock:
            self.suggestion = None if suggestion is None else (int(frame_index), suggestion)
        if suggestion is not None:
            self.set_object_class(suggestion.class_name)
        self.refresh()

    def accept_suggestion(self) -> None:
        """The suggested box becomes a label of the chosen class (in every frame that shows it,
        with label once), and is selected."""
        with self.lock:
            suggested = self.suggestion
            class_name = self.object_class
        if suggested is None:
            self.notify("Accept box", "Click an object first: the model's box for it is suggested.")
            return
        frame_index, suggestion = suggested
        if frame_index != self.state.frame_index:
            self.notify("Accept box", "The suggested box is another frame's: click the object in this one.")
            return
        added = self._guarded(
            lambda: self._add_object(frame_index, np.asarray(suggestion.box), class_name), "Accept box"
        )
        if added is not FAILED and added:
            here = [lab for lab in added if lab.frame_index == frame_index]
            self.select_label((here or added)[-1].id)

    # -- pre-labels: the model's detections, confirmed (or fixed, or deleted) one by one

    def prelabel_frame(self, min_score: float) -> None:
        """The shown frame's detections scoring ``min_score`` or more become pre-labels
        (``editing.prelabel_frame``, one undoable edit), and the first of them is selected."""
        frame_index, detections = self.state.detections_at(min_score)
        if detections is None:
            self.notify("Pre-label", "This frame's detections are not computed yet: wait for them.")
            return
        db, author = self.state.db, self.author
        added = self._guarded(
            lambda: prelabel_frame(db, frame_index, detections, author, min_score), "Pre-label"
        )
        if added is FAILED:
            return
        if not added:
            self.notify("Pre-label", f"No new detection scores {min_score:.2f} or more here: nothing added.")
            return
        self.notify(
            "Pre-label",
            f"{len(added)} pre-label(s) added (corner brackets). Confirm [Enter] each one that is right, "
            "fix or delete the others; Undo [Z] takes them all back.",
        )
        self.select_label(added[0].id)

    def next_prelabel(self, delta: int = 1) -> None:
        """Select the next pre-label nobody has confirmed (frame by frame, the model's most
        confident first) and put the camera on it."""
        queue = self.state.db.unreviewed_labels() if self.state.db is not None else []
        if not queue:
            self.notify("Pre-labels", "None waits for a confirmation.")
            return
        with self.lock:
            current = self.selected_label_id
        ids = [lab.id for lab in queue]
        if current in ids:
            position = (ids.index(current) + delta) % len(queue)
        else:  # from the shown frame on
            after = [k for k, lab in enumerate(queue) if lab.frame_index >= self.state.frame_index]
            position = after[0] if after and delta > 0 else (0 if delta > 0 else len(queue) - 1)
        label = queue[position]
        self.state.set_frame(label.frame_index)
        self.look_at_box(label.box)
        self.select_label(label.id)

    def confirm_selected(self) -> None:
        """The selected pre-label is right as it is: confirmed, and the next one selected."""
        label = self.selected_label()
        if label is None or label.reviewed:
            self.notify("Confirm", "Select a pre-label first (corner brackets; Next pre-label [J]).")
            return
        done = self._edit_selected(
            "Confirm", lambda i, v: self.state.db.confirm_labels([i], self.author, {i: v})
        )
        if done is not FAILED:
            self._reload_selected_version()  # (the confirmation moved it on: edits go on from there)
            self.next_prelabel()

    def confirm_frame(self) -> None:
        """Every pre-label of the shown frame is right: all confirmed, one edit."""
        frame_index = self.state.frame_index
        waiting = [lab for lab in self.state.db.labels(frame_index) if not lab.reviewed]
        if not waiting:
            self.notify("Confirm", "No pre-label waits in this frame.")
            return
        self._guarded(
            lambda: self.state.db.confirm_labels(
                [lab.id for lab in waiting], self.author, {lab.id: lab.version for lab in waiting}
            ),
            "Confirm",
            reload_selection=False,
        )
        self._reload_selected_version()

    def _placer(self, class_name: str | None):
        """``place(frame_index, box) -> ({frame: box}, frames that show it)`` for an 'object'
        verdict when label once applies to ``class_name`` (``SessionDB.review``), else ``None``."""
        world = None if class_name is None else self._world_for(class_name)
        if world is None:
            return None

        return lambda frame_index, box: place_box(world, frame_index, box).for_store()

    def _add_object(self, frame_index: int, box: np.ndarray, class_name: str):
        """A new label, placed in every frame that shows it when label once applies (one edit)."""
        world = self._world_for(class_name)
        if world is None:
            return self.state.db.add_labels([(frame_index, box, class_name)], self.author, "user")
        items = [(f, b, class_name) for f, b in place_box(world, frame_index, box).boxes_by_frame().items()]
        return self.state.db.add_labels(
            items,
            self.author,
            "user",
            as_object=True,
            # Not where the object is labelled already (the data set's label of it, say).
            screen=lambda current: not_labelled_yet(items, current, keep_frame=frame_index),
            summary=f"add a {class_name} in the frames that show it",
        )

    def label_segment(self, class_name: str, split: bool = False) -> None:
        """A new label (two with ``split``, as one edit) boxing the selected segment's points."""
        points = self.selected_points()
        with self.lock:
            frame_index = self.selected_frame
        if len(points) < 3 or frame_index is None:
            self.notify("Label segment", "Select a segment first: click its points (shift-click adds one).")
            return

        def add():
            parts = [points] if not split else [points[split_in_two(points) == k] for k in (0, 1)]
            boxes = [box_of_points(part) for part in parts]  # all boxes first: nothing half-written
            if split:  # (two new objects, one edit: each is placed in every frame once it is moved)
                return self.state.db.add_labels(
                    [(frame_index, b, class_name) for b in boxes], self.author, "user"
                )
            return self._add_object(frame_index, boxes[0], class_name)

        added = self._guarded(add, "Split segment" if split else "Label segment")
        if added is not FAILED and added:
            here = [lab for lab in added if lab.frame_index == frame_index]
            self.select_label((here or added)[-1].id)

    def spread_labels(self) -> None:
        """Label once what is labelled per frame: every object that stands still gets a label in
        each frame that shows it and has none (``world.spread_session``), as one undoable edit."""
        with self.state.lock:
            world = self.state.world
        if world is None:
            self.notify(
                "Label every frame", "The frames are not placed in one world frame yet: try again shortly."
            )
            return
        added = self._guarded(lambda: spread_session(self.state.db, world, self.author), "Label every frame")
        if added is FAILED:
            return
        objects = len({lab.instance_id for lab in added})
        if added:
            self.notify(
                "Label every frame",
                f"{len(added)} label(s) added to {objects} object(s); Undo [Z] takes them back.",
            )
        else:
            self.notify("Label every frame", "Every object is labelled in every frame that shows it already.")

    def export_labels(self, fmt: str) -> tuple[str, bytes] | None:
        """The session's labels of every frame as ``(file name, bytes)`` for a download (the same
        export as ``factorydet labels export``; KITTI and npz as a ZIP), else ``None`` (told why)."""
        if self.state.db is None:
            self.notify(
                "Export labels", "This data set is open without a session: there is nothing to export."
            )
            return None
        exported = self._guarded(
            lambda: export_bytes(self.state.db, fmt), "Export labels", reload_selection=False
        )
        return None if exported is FAILED else exported

    def undo(self, redo: bool = False) -> None:
        """Undo (redo) this browser's latest edit. The selection follows the undo only where the
        undo moved it on from the version this browser had: a change someone else made to the
        selected label in between is still refused at the next edit, not taken in silently."""
        what = "Redo" if redo else "Undo"
        edit = self._guarded(
            lambda: self.state.db.redo(self.author) if redo else self.state.db.undo(self.author),
            what,
            reload_selection=False,
        )
        if edit is FAILED:
            return
        if edit is not None:
            with self.lock:
                versions = edit.label_versions.get(self.selected_label_id)
                if versions is not None and versions[0] == self.selected_label_version:
                    self.selected_label_version = versions[1]
        if edit is None:
            self.notify(what, "Nothing to " + ("redo." if redo else "undo."))
        else:
            self.notify("Redone" if redo else "Undone", edit.summary)

    # -- review queue

    def load_queue(self) -> list[dict]:
        """The review queue as this browser's filters show it (``queue``). The session's queue is
        read again only after a write to the session (by anyone: ``SessionDB.change_stamp``) or
        another filter, and grouped by place again only when other items are shown (a verdict's
        refreshes read and group once, not once each; a mined item never changes, so its place
        depends on the items and the world alone)."""
        if self.state.db is None:
            return []
        with self.lock:
            filter_class, filter_frame, pending = self.filter_class, self.filter_frame, self.pending_only
            hide_labelled, current_id, group = self.hide_labelled, self.current_item_id, self.group_places
        with self.state.lock:
            world = self.state.world
        stamp = self.state.db.change_stamp()
        read_key = (stamp, filter_class, filter_frame)
        shown_key = (read_key, pending, hide_labelled, current_id, group, id(world))
        shown = self._shown_queue
        if shown is not None and shown[0] == shown_key:
            with self.lock:
                self.queue = shown[1]
            return shown[1]
        cached = self._queue_read
        if cached is not None and cached[0] == read_key:
            queue = cached[1]
        else:
            queue = self.state.db.review_queue(
                predicted_class=filter_class, frame_index=filter_frame, pending_only=False
            )
            self._queue_read = (read_key, queue)
        read = queue
        # The shown item stays, though a verdict just took it out of the filter (the panel still
        # shows it, with its verdict, until Next).
        if pending:
            queue = [q for q in queue if q["verdict"] in (None, "skip") or q["id"] == current_id]
        if hide_labelled:
            queue = [
                q
                for q in queue
                if not on_labelled_object(q["label_iou"], HIDE_LABELLED_IOU) or q["id"] == current_id
            ]
        if group and world is not None and queue:
            # The places of the whole queue read, grouped once and then filtered: a run's items
            # do not change, and grouped after the filters, a class order's turns would be worked
            # out again on what is left and move places ahead of the shown one.
            # The places' order depends on the read (its items and verdicts), the placement and
            # the session alone: the next item shown after a verdict orders them once, not twice.
            ordered_key = (read_key, id(world), id(self.state.db))
            if self._ordered is None or self._ordered[0] != ordered_key:
                self._ordered = (ordered_key, *self._order_places(read, world))
            _, ordered, ranked = self._ordered
            learned = ranked is not None
            kept = {q["id"] for q in queue}
            places = [[k for k in place if read[k]["id"] in kept] for place in ordered]
            queue = _by_place(read, [place for place in places if place], current_id)
            if learned:  # what the item's text says of the order (still learning, or a chance)
                for entry in queue:
                    entry["place_useful"] = ranked.useful.get(entry["id"])
                    entry["learned_from"] = ranked.num_answers
        self._shown_queue = (shown_key, queue)
        with self.lock:
            self.queue = queue
        return queue

    def _order_places(self, read: list[dict], world) -> tuple[list[list[int]], RankedPlaces | None]:
        """The places of the session's queue ``read`` (positions in it) in its run's review order,
        and the learned order's ``RankedPlaces`` (``None`` for another order)."""
        run_id = read[0]["run_id"]
        # A learned order: the cut's order until there are verdicts to learn from.
        order, learned = place_order(self.state.db, run_id)
        places_key = (id(world), tuple(q["id"] for q in read), order)
        cached = self._places
        if cached is None or cached[0] != places_key:
            cached = self._places = (places_key, group_by_place(world, read, order=order))
        if not learned:
            return cached[1], None
        # Answered places first, then the pending ones likeliest to give a label: the one just
        # answered keeps its place before the next, refitted every few verdicts.
        ranker = self._learned
        if ranker is None or ranker.world is not world or ranker.db is not self.state.db:
            ranker = self._learned = LearnedOrder(self.state.db, world, self.state.dataset.class_names)
        ranked = ranker.ranked(run_id, read, cached[1])
        return ranked.places, ranked

    def current_item(self) -> dict | None:
        with self.lock:
            return next((q for q in self.queue if q["id"] == self.current_item_id), None)

    def go_to(self, item: dict | None) -> None:
        """Show a queue item: its frame, the camera on it, its box highlighted in a dimmed scene;
        the chosen class becomes its predicted one (what Object [O] labels it unless another is
        picked)."""
        with self.lock:
            self.current_item_id = None if item is None else item["id"]
        if item is None:
            self.refresh()
            return
        self.set_object_class(item.get("predicted_class"))
        self.state.set_frame(item["frame_index"])
        self.look_at_box(item["box"])
        self.refresh()

    def best_view(self, item: dict | None) -> BestView | None:
        """Where the frames see a queue item's object best (``world.best_view``); ``None`` before
        the frames are placed, for an item predicted a person or truck (the frames' poses carry a
        box to where a moving object no longer is), or when the item's own frame sees it best.
        Cached per item and placement."""
        if item is None or item.get("predicted_class") in MOVING_CLASSES:
            return None
        with self.state.lock:
            world = self.state.world
        if world is None:
            return None
        cached = self._best_view
        if cached is None or cached[0] != item["id"] or cached[1] is not world:
            cached = self._best_view = (item["id"], world, best_view(world, item["frame_index"], item["box"]))
        return cached[2]

    def look_where_seen_best(self) -> None:
        """Show the review item's object in the frame that sees it best (``best_view``), the
        camera on its box there; the item stays the one a verdict answers."""
        item = self.current_item()
        if item is None:
            self.notify("Review", "No queue item shown: press Next [N] first.")
            return
        view = self.best_view(item)
        if view is None:
            self.notify(
                "Review",
                "No other frame sees this item's place better (or the frames are not placed yet, or it "
                "is predicted a person or truck, which move between frames).",
            )
            return
        self.state.set_frame(view.frame_index)
        self.look_at_box(view.box)
        self.notify(
            "Seen best",
            f"Frame {view.frame_index + 1}: {view.num_points} points in the item's box there, "
            f"{view.num_points_here} in frame "
            f"{item['frame_index'] + 1}. A verdict still answers the item (Object labels it in every "
            "frame that shows it; Wrong box, then draw its box here).",
        )
        self.refresh()

    @_coalesced
    def step(self, delta: int) -> None:
        queue = self.load_queue()
        if not queue:
            self.go_to(None)
            return
        ids = [q["id"] for q in queue]
        with self.lock:
            current = self.current_item_id
        k = ids.index(current) + delta if current in ids else 0
        self.go_to(queue[max(0, min(k, len(queue) - 1))])

    @_coalesced
    def verdict(self, verdict: str, class_name: str | None = None, advance: bool = True) -> None:
        """The verdict on the shown item, then (with ``advance``) the next pending one."""
        item = self.current_item()
        if item is None:
            # Nothing is shown yet: show the first item, and let the person look before judging.
            self.step(0)
            if self.current_item() is None:
                self.notify("Review", "The queue is empty: train a model from the Training panel first.")
            return
        versions = _answered(item)
        done = self._guarded(
            lambda: self.state.db.review(
                list(versions),
                verdict,
                self.author,
                class_name=class_name,
                expected_versions=versions,
                place=self._placer(class_name),
                one_object=len(versions) > 1,
            ),
            "Review",
        )
        if done is FAILED:
            self.load_queue()
            self.refresh()
            return
        queue = self.load_queue()
        if not advance:
            self.refresh()
            return
        ids = [q["id"] for q in queue]
        k = ids.index(item["id"]) if item["id"] in ids else -1
        # Unreviewed ones first, after this one and then from the start (a learned order puts
        # the places skipped last, the one just skipped among them); then those skipped.
        rest = queue[k + 1 :] + queue[: max(k, 0)]
        later = [q for q in rest if q["verdict"] is None] or [q for q in rest if q["verdict"] == "skip"]
        self.go_to(later[0] if later else None)

    @_coalesced
    def batch_verdict(self, verdict: str, class_name: str | None = None) -> int:
        """One verdict on every pending item of the current filter, as one undoable edit."""
        with self.lock:
            pending_only = self.pending_only
            self.pending_only = True
        queue = self.load_queue()
        with self.lock:
            self.pending_only = pending_only
        items = [q for q in queue if q["verdict"] in (None, "skip")]
        if not items:
            self.notify("Batch", "No pending items in the current filter.")
            return 0
        versions = {}
        for q in items:
            versions.update(_answered(q))
        done = self._guarded(
            lambda: self.state.db.review(
                list(versions),
                verdict,
                self.author,
                class_name=class_name,
                expected_versions=versions,
                place=self._placer(class_name),
            ),
            "Batch",
        )
        self.load_queue()
        self.refresh()
        return len(items) if done is not FAILED else 0

    def set_object_class(self, name: str | None) -> None:
        """The class the Labels and Review panels (and the O, C, L, K keys) use: one per browser,
        shown in both panels' dropdowns. A name that is no object class of the data set
        ("background", none) leaves it as it is."""
        if name not in self.state.dataset.class_names:
            return
        with self.lock:
            self.object_class = name
        self._object_class_shown(name)

    def current_suspect(self) -> dict | None:
        suspects = self.state.suspects
        with self.lock:
            index = self.suspect_index
        return suspects[index] if 0 <= index < len(suspects) else None

    def next_suspect(self, delta: int = 1) -> None:
        """Select the next label the model contradicts and put the camera on it."""
        suspects = self.state.suspects
        if not suspects:
            self.notify("Suspect labels", "None listed: press Find suspect labels (needs a model).")
            return
        with self.lock:
            self.suspect_index = (self.suspect_index + delta) % len(suspects)
            suspect = suspects[self.suspect_index]
        self.state.set_frame(suspect["frame_index"])
        self.look_at_box(suspect["box"])
        self.select_label(suspect["label_id"])
        # What the model says it is: Set class [C] takes it unless another class is picked.
        self.set_object_class(suspect.get("predicted_class"))
