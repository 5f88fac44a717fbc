"""What belongs to one browser: who they are, what they selected, where they are in the review
queue, their own panels and highlights.

The scene and the session are shared by every browser; a selection, a camera, a review cursor and
an undo stack (by author name) are each browser's own. Every edit goes through the session
database, which commits it before the call returns, so an edit the panel acknowledges is stored;
an edit made against a label or verdict someone else has changed since is refused and the person
is told (``EditConflictError``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import viser

from factorydet_core import colors
from factorydet_core.editing import box_of_points, box_to_pose, camera_for_box, split_in_two
from factorydet_core.geometry import box_wireframe_segments
from factorydet_core.session import EditConflictError, SessionError

from .state import AppState

HIGHLIGHT_RGB = (255, 215, 0)
REVIEW_RGB = (255, 0, 200)
DIM_FACTOR = 0.25


class ClientView:
    """One browser's selection, review cursor and panels.

    Args:
        client: the viser client.
        state: the shared app state.
        scene_points: returns the shown scan's ``(points (N, 3), colours (N, 3))`` for the dimmed
            copy this client sees while reviewing.
        drawn_result: returns ``(ProposalResult | None, frame_index)`` currently drawn.
    """

    def __init__(
        self,
        client: viser.ClientHandle,
        state: AppState,
        scene_points: Callable[[], tuple[np.ndarray, np.ndarray]],
        drawn_result: Callable[[], tuple],
    ) -> None:
        self.client = client
        self.state = state
        self._scene_points = scene_points
        self.drawn_result = drawn_result
        self.lock = threading.RLock()
        self.author = f"reviewer-{client.client_id}"
        self.selected_label_id: int | None = None
        self.selected_patch_ids: set[int] = set()
        self.selected_frame: int | None = None
        self.object_class = state.dataset.class_names[0]
        # Review: filters, the item shown, whether the scene is dimmed around it.
        self.filter_class: str | None = None
        self.filter_frame: int | None = None
        self.pending_only = True
        self.current_item_id: int | None = None
        self.dim = True
        self._dimmed = False
        self.queue: list[dict] = []
        self.panels: list = []
        self.gizmo: viser.TransformControlsHandle | None = None
        self.suspect_index = -1
        self.closed = False  # set when the browser disconnects: nothing is sent to it after that

    # -- messages

    def notify(self, title: str, body: str, error: bool = False) -> None:
        if self.closed:
            return
        self.client.add_notification(
            title, body, auto_close_seconds=6.0 if not error else 12.0, color="red" if error else None
        )

    def _guarded(self, action: Callable[[], object], what: str) -> object | None:
        """Run an edit; a conflict or a refused edit becomes a notification, not a crash."""
        try:
            result = action()
        except EditConflictError as exc:
            self.notify(f"{what}: someone else got there first", str(exc), error=True)
            self.state.session_changed()
            return None
        except SessionError as exc:
            self.notify(f"{what}: not done", str(exc), error=True)
            return None
        self.state.session_changed()
        return result

    # -- selection

    def selected_label(self):
        if self.selected_label_id is None or self.state.db is None:
            return None
        label = self.state.db.label(self.selected_label_id)
        return None if label.deleted else label

    def select_label(self, label_id: int | None) -> None:
        with self.lock:
            self.selected_label_id = label_id
            self.selected_patch_ids = set()
        self.refresh()

    def select_patches(self, patch_ids, add: bool = False) -> None:
        """Select the segment made of ``patch_ids`` of the drawn result (``add``: extend it)."""
        result, frame_index = self.drawn_result()
        with self.lock:
            if not add or self.selected_frame != frame_index:
                self.selected_patch_ids = set()
            self.selected_patch_ids |= {int(p) for p in patch_ids}
            self.selected_frame = frame_index
            self.selected_label_id = None
        self.refresh()

    def clear_selection(self) -> None:
        with self.lock:
            self.selected_label_id = None
            self.selected_patch_ids = set()
        self.refresh()

    def selected_points(self) -> np.ndarray:
        """(K, 3) points of the selected segment in the drawn result."""
        result, frame_index = self.drawn_result()
        with self.lock:
            patch_ids = set(self.selected_patch_ids)
            frame = self.selected_frame
        if result is None or not patch_ids or frame != frame_index:
            return np.zeros((0, 3))
        mask = np.isin(result.segmentation.patch_ids, list(patch_ids))
        return result.cloud.points[mask]

    # -- label edits

    def set_class(self, class_name: str) -> None:
        label = self.selected_label()
        if label is None:
            self.notify("Set class", "Select a label first (click its box).")
            return
        self._guarded(
            lambda: self.state.db.update_label(
                label.id, self.author, expected_version=label.version, class_name=class_name
            ),
            "Set class",
        )

    def apply_box(self, box) -> None:
        label = self.selected_label()
        if label is None:
            return
        self._guarded(
            lambda: self.state.db.update_label(
                label.id, self.author, expected_version=label.version, box=box
            ),
            "Move box",
        )

    def delete_selected(self) -> None:
        label = self.selected_label()
        if label is None:
            self.notify("Delete", "Select a label first (click its box).")
            return
        if self._guarded(
            lambda: self.state.db.delete_labels([label.id], self.author, {label.id: label.version}), "Delete"
        ):
            self.select_label(None)

    def label_segment(self, class_name: str, split: bool = False) -> None:
        """A new label (two with ``split``) boxing the selected segment's points."""
        points = self.selected_points()
        frame_index = self.selected_frame
        if len(points) < 3 or frame_index is None:
            self.notify("Label segment", "Select a segment first: click its points (shift-click adds one).")
            return
        parts = [points] if not split else [points[split_in_two(points) == k] for k in (0, 1)]

        def add():
            return [
                self.state.db.add_label(frame_index, box_of_points(part), class_name, self.author)
                for part in parts
            ]

        added = self._guarded(add, "Label segment")
        if added:
            self.select_label(added[-1].id)

    def undo(self, redo: bool = False) -> None:
        edit = self._guarded(
            lambda: self.state.db.redo(self.author) if redo else self.state.db.undo(self.author),
            "Redo" if redo else "Undo",
        )
        if edit is None:
            self.notify("Redo" if redo else "Undo", "Nothing to " + ("redo." if redo else "undo."))
        else:
            self.notify("Redone" if redo else "Undone", edit.summary)

    # -- review queue

    def load_queue(self) -> list[dict]:
        if self.state.db is None:
            return []
        with self.lock:
            filter_class, filter_frame, pending = self.filter_class, self.filter_frame, self.pending_only
        queue = self.state.db.review_queue(
            predicted_class=filter_class, frame_index=filter_frame, pending_only=False
        )
        if pending:
            queue = [q for q in queue if q["verdict"] in (None, "skip") or q["id"] == self.current_item_id]
        with self.lock:
            self.queue = queue
        return queue

    def current_item(self) -> dict | None:
        with self.lock:
            return next((q for q in self.queue if q["id"] == self.current_item_id), None)

    def go_to(self, item: dict | None) -> None:
        """Show a queue item: its frame, the camera on it, its box highlighted in a dimmed scene."""
        with self.lock:
            self.current_item_id = None if item is None else item["id"]
        if item is None:
            self.refresh()
            return
        self.state.set_frame(item["frame_index"])
        position, look_at = camera_for_box(item["box"])
        with self.client.atomic():
            self.client.camera.position = tuple(position)
            self.client.camera.look_at = tuple(look_at)  # after position: setting it moves look_at
        self.refresh()

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

    def verdict(self, verdict: str, class_name: str | None = None, advance: bool = True) -> None:
        """The verdict on the shown item, then (with ``advance``) the next pending one."""
        item = self.current_item()
        if item is None:
            self.step(0)
            item = self.current_item()
            if item is None:
                self.notify("Review", "The queue is empty: train a model from the Training panel first.")
                return
        done = self._guarded(
            lambda: self.state.db.review(
                [item["id"]],
                verdict,
                self.author,
                class_name=class_name,
                expected={item["id"]: item["verdict"]},
            ),
            "Review",
        )
        if done is None:
            self.load_queue()
            return
        queue = self.load_queue()
        if not advance:
            self.refresh()
            return
        ids = [q["id"] for q in queue]
        k = ids.index(item["id"]) if item["id"] in ids else -1
        later = [q for q in queue[k + 1 :] if q["verdict"] in (None, "skip")]
        self.go_to(later[0] if later else None)

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
        done = self._guarded(
            lambda: self.state.db.review(
                [q["id"] for q in items],
                verdict,
                self.author,
                class_name=class_name,
                expected={q["id"]: q["verdict"] for q in items},
            ),
            "Batch",
        )
        self.load_queue()
        self.refresh()
        return len(items) if done is not None else 0

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
        position, look_at = camera_for_box(suspect["box"])
        with self.client.atomic():
            self.client.camera.position = tuple(position)
            self.client.camera.look_at = tuple(look_at)
        self.select_label(suspect["label_id"])

    # -- drawing this browser's overlays

    def refresh(self) -> None:
        """Bring this browser's panels and highlights up to date."""
        if self.closed:
            return
        self._draw_highlights()
        for panel in self.panels:
            panel.refresh(self)

    def _draw_highlights(self) -> None:
        scene = self.client.scene
        label = self.selected_label()
        boxes = []
        if label is not None and label.frame_index == self.state.frame_index:
            boxes.append((np.asarray(label.box), HIGHLIGHT_RGB, "/client/selected_box"))
        else:
            scene.remove_by_name("/client/selected_box")
        item = self.current_item()
        if item is not None and item["frame_index"] == self.state.frame_index:
            boxes.append((np.asarray(item["box"]), REVIEW_RGB, "/client/review_box"))
        else:
            scene.remove_by_name("/client/review_box")
        for box, rgb, name in boxes:
            segments = box_wireframe_segments(box[None]).astype(np.float32).reshape(-1, 2, 3)
            scene.add_line_segments(
                name, points=segments, colors=np.array(rgb, np.uint8), thickness=5.0, thickness_units="screen"
            )
        self._draw_gizmo(label)
        points = self.selected_points()
        if len(points):
            scene.add_point_cloud(
                "/client/selected_points", points=points, colors=np.array(HIGHLIGHT_RGB, np.uint8),
                point_size=self.state.point_size * 1.6, point_shape="square",
            )  # fmt: skip
        else:
            scene.remove_by_name("/client/selected_points")
        dim = self.dim and item is not None
        if dim:
            scene_points, scene_colors = self._scene_points()
            # The same node name as the shared scan shadows it for this browser only.
            scene.add_point_cloud(
                "/scan", points=scene_points, colors=(scene_colors * DIM_FACTOR).astype(np.uint8),
                point_size=self.state.point_size, point_shape="square", precision="float32",
            )  # fmt: skip
            self._dimmed = True
        elif self._dimmed:
            scene.remove_by_name("/scan")
            self._dimmed = False

    def _draw_gizmo(self, label) -> None:
        if label is None or label.frame_index != self.state.frame_index:
            if self.gizmo is not None:
                self.gizmo.remove()
                self.gizmo = None
            return
        position, wxyz = box_to_pose(label.box)
        if self.gizmo is None:
            self.gizmo = self.client.scene.add_transform_controls(
                "/client/gizmo", scale=1.5, disable_sliders=True, depth_test=False
            )

            @self.gizmo.on_update
            def _(event) -> None:
                if getattr(event, "phase", "end") != "end":
                    return
                from factorydet_core.editing import pose_to_box

                current = self.selected_label()
                if current is not None:
                    self.apply_box(pose_to_box(self.gizmo.position, self.gizmo.wxyz, current.box[3:6]))

        self.gizmo.position = tuple(position)
        self.gizmo.wxyz = tuple(wxyz)


def class_color_hex(class_names: tuple[str, ...], name: str) -> str:
    """The class colour as ``#rrggbb`` (for the panels' markdown)."""
    rgb = colors.class_colors(class_names)[class_names.index(name)]
    return "#" + "".join(f"{int(v):02x}" for v in rgb)
