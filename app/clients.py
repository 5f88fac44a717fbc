"""What one browser sees: its own scan, detection layers and panels drawn from its view of the
state (``state.AppState``: its frame, display settings and thresholds), and of its
``BrowserSession``: notifications, its camera, the highlighted boxes and points, the box gizmo
and the dimmed scan while reviewing (viser)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from factorydet_core.colors import thin_for_display
from factorydet_core.geometry import box_wireframe_segments
from factorydet_core.session.editing import (
    BOX_FACES,
    box_face_points,
    box_to_pose,
    camera_for_box,
    pose_to_box,
    resize_box,
)

from .browser_session import BrowserSession
from .layers import LayerView
from .scene import SceneView
from .state import AppState

HIGHLIGHT_RGB = (255, 215, 0)
REVIEW_RGB = (255, 0, 200)


SUGGESTION_RGB = (0, 200, 220)
"""The model's suggested box for the object last clicked (cyan: neither a label nor a detection)."""
AUTHOR_KEY = "factorydet.author"
"""The browser's localStorage key of the name its edits are signed with."""


class ClientView(BrowserSession):
    """One browser: its view of the state drawn in its viser client, and its labelling session.

    Args:
        client: the viser client.
        state: this browser's view (``SharedState.new_view``).
    """

    def __init__(self, client: viser.ClientHandle, state: AppState) -> None:
        self.scene = SceneView(client)
        self.layers = LayerView(client)
        super().__init__(state, drawn_result=lambda: self.layers.drawn)
        self.client = client
        self.panels: list = []  # the labelling panels, refreshed with the selection
        self.view_panels: list = []  # frame, display, pipeline, detections, metrics, training
        self.gizmo: viser.TransformControlsHandle | None = None
        self.handles: dict[str, viser.IcosphereHandle] = {}  # the selected box's resize handles, by face
        self._handles_for: tuple | None = None  # (label id, version) the handles were drawn for
        self.class_dropdowns: list = []  # every dropdown showing object_class
        self._refresh_lock = threading.Lock()  # one refresh at a time (redraw and callback threads)
        self._draw_lock = threading.Lock()  # one redraw at a time; the last one wins
        self._drawn: tuple | None = None
        self._labels_key: tuple | None = None
        self._layers_key: tuple | None = None
        self._detections_key: tuple | None = None
        self._refresh_key: tuple | None = None
        self._batch_lock = threading.Lock()
        self._open_batches = 0
        self.sent_at = 0.0
        self.key_received_at = 0.0  # when the server received this browser's last hotkey or click
        self.closed = False  # set when the browser disconnects: nothing is sent to it after that
        # ``coalesced``: per thread in a block, what it asked for meanwhile (viser runs each key
        # and button on its own pool thread: two keys pressed together are two blocks at once).
        self._coalesce_lock = threading.Lock()
        self._wanted: dict[int, set[str]] = {}
        self._num_refreshes = 0

    def respond(self, action: Callable[[], object]) -> None:
        """Run the action of a key or a click of this browser so that everything it changes
        reaches the browser in one update, its panels brought up to date once (``coalesced``);
        ``key_received_at`` says when it came (the walkthrough times the server's share from it)."""
        self.key_received_at = time.perf_counter()
        with self.coalesced():
            action()

    @contextlib.contextmanager
    def coalesced(self):
        me = threading.get_ident()
        with self._coalesce_lock:
            nested = me in self._wanted  # (the outer block redraws)
            if not nested:
                self._wanted[me] = set()
        if nested:
            yield
            return
        try:
            with self.batched():
                try:
                    yield
                finally:
                    with self._coalesce_lock:
                        wanted = self._wanted.pop(me)
                    refreshes = self._num_refreshes
                    if "redraw" in wanted:
                        self.redraw()
                    if "refresh" in wanted and self._num_refreshes == refreshes:  # (none since)
                        self.refresh()
        finally:
            with self._coalesce_lock:
                self._wanted.pop(me, None)  # (batched() itself failed: the thread is not left marked)

    def _deferred(self, what: str) -> bool:
        """Whether this thread is in a ``coalesced`` block: ``what`` is then done at its end."""
        with self._coalesce_lock:
            wanted = self._wanted.get(threading.get_ident())
            if wanted is None:
                return False
            wanted.add(what)
            return True

    def redraw(self) -> None:
        """Bring this browser's scene and panels up to date with its view and the shared state."""
        if self.closed or self._deferred("redraw"):
            return
        state = self.state
        with self._draw_lock, self.batched():
            with state.lock:
                # Colours from the labels follow every edit: the session's revision is part of the key.
                by_labels = state.color_mode in ("class", "annotated") and state.editable
                key = (
                    state.frame_index,
                    state.color_mode,
                    state.max_height,
                    state.revision if by_labels else None,
                    state.points_drawn,
                )
                labels_key = (state.frame_index, state.revision, state.show_boxes, state.show_box_names)
                point_size = state.point_size
                show_grid = state.show_grid
                frame = state.frame
            self.scene.set_grid_visible(show_grid)
            if key != self._drawn:
                labels = state.frame_labels(key[0])[:2] if by_labels else None
                self.scene.draw(
                    frame, color_mode=key[1], point_size=point_size, max_height=key[2], labels=labels,
                    max_points=key[4],
                )  # fmt: skip
                self._drawn = key
            else:
                self.scene.set_point_size(point_size)
            if labels_key != self._labels_key:
                boxes, class_ids, prelabel_mask = state.drawn_labels(labels_key[0])
                self.scene.draw_labels(
                    boxes, class_ids, state.dataset.class_names, labels_key[2], names=labels_key[3],
                    prelabel_mask=prelabel_mask,
                )  # fmt: skip
                self._labels_key = labels_key
            with state.lock:
                result = state.pipeline_result
                result_frame = state.pipeline_result_key[0] if result is not None else None
                layers = dict(state.layers)
                max_height = state.max_height
                max_points = state.points_drawn
            # Another frame's result (the shown frame's is being computed) is hidden in the same
            # update that draws the new scan: never the old frame's boxes on the new frame's cloud.
            if result is not None:
                layers_stale = result_frame != key[0]
                layers_key = (id(result), max_height, max_points, layers_stale)
                if layers_key != self._layers_key:
                    if layers_stale:
                        self.layers.set_visibility(dict.fromkeys(layers, False))
                    else:
                        self.layers.draw(result, result_frame, layers, point_size, max_height, max_points)
                    self._layers_key = layers_key
                elif not layers_stale:  # (the size first: a layer shown for the first time is sent at it)
                    self.layers.set_point_size(point_size)
                    self.layers.set_visibility(layers)
            with state.lock:
                detection_frame = state.detection_frame_index
                fresh = detection_frame == key[0]
                detections = state.detections if fresh else None
                detection_result = state.detection_result if fresh else None
                detections_key = (
                    id(detections),
                    layers["detections"],
                    state.show_suppressed,
                    state.color_by_match,
                    state.show_box_names,
                )
            if detections_key != self._detections_key:
                labels = None
                if detections is not None:  # what the metrics count as truth (no pre-labels)
                    labels = state.references(detection_frame)[:2]
                self.layers.draw_detections(detections, *detections_key[1:4], labels, names=detections_key[4])
                self.layers.detection_source = (detection_result, detection_frame)
                self._detections_key = detections_key
            for panel in self.view_panels:
                panel.refresh(state)
            with state.lock:
                # (the suspects and the world placement's progress show in the labelling panels)
                refresh_key = (
                    state.revision,
                    state.frame_index,
                    id(self.layers.drawn_result),
                    id(state.suspects),
                    state.world_status,
                )
            if refresh_key != self._refresh_key:
                self._refresh_key = refresh_key
                self.refresh()

    def restore_author(self, timeout: float = 10.0) -> None:
        """Sign edits with the name this browser used before (kept in its localStorage), so that
        a reload keeps its undo stack; a browser new to the app keeps its generated name, stored
        for next time. Run off viser's callback threads: it waits for the browser's answer."""
        try:
            stored = self.client.local_storage.get_item(AUTHOR_KEY, timeout=timeout)
        except (RuntimeError, TimeoutError):  # gone, or storage blocked: the generated name stays
            return
        if stored and self.set_author(stored):
            self.refresh()
        else:
            self.remember_author()

    def remember_author(self) -> None:
        """Keep this browser's author name in its localStorage for the next page load."""
        if not self.closed:
            self.client.local_storage.set_item(AUTHOR_KEY, self.author)

    def download_labels(self, fmt: str) -> None:
        """Send the session's labels in ``fmt`` to this browser as a file download."""
        exported = self.export_labels(fmt)
        if exported is not None and not self.closed:
            name, content = exported
            self.client.send_file_download(name, content, save_immediately=True)
            self.notify("Export labels", f"{name}: {len(content):,} bytes, every frame's labels.")

    @contextlib.contextmanager
    def batched(self):
        with self._batch_lock:
            self._open_batches += 1
        try:
            with self.client.atomic():
                yield
        finally:
            with self._batch_lock:
                self._open_batches -= 1
                if self._open_batches == 0:
                    self.sent_at = time.perf_counter()

    @property
    def sending(self) -> bool:
        """Whether a batch of updates for this browser is still being made (nothing of it is
        sent until it ends, at ``sent_at``, a ``time.perf_counter`` reading)."""
        with self._batch_lock:
            return self._open_batches > 0

    def notify(self, title: str, body: str, error: bool = False) -> None:
        super().notify(title, body, error)
        if self.closed:
            return
        self.client.add_notification(
            title, body, auto_close_seconds=6.0 if not error else 12.0, color="red" if error else None
        )

    def look_at_box(self, box) -> None:
        position, look_at = camera_for_box(box)
        with self.client.atomic():
            self.client.camera.position = tuple(position)
            self.client.camera.look_at = tuple(look_at)  # after position: setting it moves look_at

    def set_camera(self, position, look_at, up) -> None:
        with self.client.atomic():
            self.client.camera.up_direction = tuple(float(v) for v in up)
            self.client.camera.position = tuple(float(v) for v in position)
            self.client.camera.look_at = tuple(float(v) for v in look_at)  # after position: it drags look_at

    def _object_class_shown(self, name: str) -> None:
        with self.lock:
            dropdowns = list(self.class_dropdowns)
        for dropdown in dropdowns:
            if dropdown.value != name:
                dropdown.value = name

    def refresh(self) -> None:
        """Bring this browser's panels and highlights up to date."""
        if self.closed or self._deferred("refresh"):
            return
        with self._refresh_lock, self.batched():
            self._num_refreshes += 1
            self.follow_object()
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
        with self.lock:
            suggested = self.suggestion
        if suggested is not None and suggested[0] == self.state.frame_index:
            boxes.append((np.asarray(suggested[1].box), SUGGESTION_RGB, "/client/suggested_box"))
        else:
            scene.remove_by_name("/client/suggested_box")
        item = self.current_item()
        if item is not None and item["frame_index"] == self.state.frame_index:
            boxes.append((np.asarray(item["box"]), REVIEW_RGB, "/client/review_box"))
        else:
            scene.remove_by_name("/client/review_box")
        if label is not None and label.frame_index == self.state.frame_index:
            box = np.asarray(label.box)
            scene.add_label(
                "/client/selected_name",
                text=label.class_name,
                position=(box[0], box[1], box[2] + box[5] / 2 + 0.1),
            )
        else:
            scene.remove_by_name("/client/selected_name")
        for box, rgb, name in boxes:
            self._draw_box(name, box, rgb)
        self._draw_gizmo(label)
        points = self.selected_points()
        # (a shift-drag over the hall selects most of it: the budget holds for the highlight too)
        points = points[thin_for_display(np.ones(len(points), bool), self.state.points_drawn)]
        if len(points):
            scene.add_point_cloud(
                "/client/selected_points", points=points, colors=np.array(HIGHLIGHT_RGB, np.uint8),
                point_size=self.state.point_size * 1.6, point_shape="square",
            )  # fmt: skip
        else:
            scene.remove_by_name("/client/selected_points")
        self.scene.set_dimmed(self.dim and item is not None)

    def _draw_box(self, name: str, box: np.ndarray, rgb: tuple) -> None:
        """One highlighted (7,) box: a thick wireframe in ``rgb``, this browser's only."""
        segments = box_wireframe_segments(np.asarray(box)[None]).astype(np.float32).reshape(-1, 2, 3)
        self.client.scene.add_line_segments(
            name, points=segments, colors=np.array(rgb, np.uint8), thickness=5.0, thickness_units="screen"
        )

    def _draw_handles(self, label) -> None:
        """A handle on each face of the selected box: dragging one moves that face alone
        (``editing.resize_box``), previewed while dragging and one undoable edit on release."""
        if label is None or label.frame_index != self.state.frame_index:
            for handle in self.handles.values():
                handle.remove()
            self.handles, self._handles_for = {}, None
            return
        if self._handles_for == (label.id, label.version):
            return
        radius = float(np.clip(0.15 * min(label.box[3:6]), 0.03, 0.12))
        for face, point in zip(BOX_FACES, box_face_points(label.box)):
            handle = self.handles.get(face)
            if handle is not None:
                handle.position, handle.radius = tuple(point), radius
                continue
            handle = self.client.scene.add_icosphere(
                f"/client/handles/{face}", radius=radius, color=HIGHLIGHT_RGB, subdivisions=1,
                material="toon3", position=tuple(point), cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
            handle.on_drag("left")(lambda event, face=face: self._drag_face(face, event))
            self.handles[face] = handle
        self._handles_for = (label.id, label.version)

    def _drag_face(self, face: str, event) -> None:
        label = self.selected_label()
        if label is None:
            return
        box = resize_box(label.box, face, event.end_position)
        if event.phase != "end":  # a preview in this browser: the box and its handles follow
            self._draw_box("/client/selected_box", box, HIGHLIGHT_RGB)
            for other, point in zip(BOX_FACES, box_face_points(box)):
                if other in self.handles:
                    self.handles[other].position = tuple(point)
            return
        self.apply_box(tuple(float(v) for v in box))

    def _draw_gizmo(self, label) -> None:
        self._draw_handles(label)
        if label is None or label.frame_index != self.state.frame_index:
            if self.gizmo is not None:
                self.gizmo.remove()
                self.gizmo = None
            return
        position, wxyz = box_to_pose(label.box)
        if self.gizmo is None:
            gizmo = self.client.scene.add_transform_controls(
                # x and y arrows and the ring about z only: boxes stay upright (a tilt was
                # dropped on release); heights change in the Box fields or with shift+Y/H.
                "/client/gizmo", scale=1.5, active_axes=(True, True, False), disable_sliders=True,
                depth_test=False,
            )  # fmt: skip

            @gizmo.on_update
            def _(event) -> None:
                if getattr(event, "phase", "end") != "end":
                    return
                current = self.selected_label()
                if current is not None:
                    self.apply_box(pose_to_box(gizmo.position, gizmo.wxyz, current.box[3:6]))

            self.gizmo = gizmo

        self.gizmo.position = tuple(position)
        self.gizmo.wxyz = tuple(wxyz)
