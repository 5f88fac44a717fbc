"""What one browser sees of its ``BrowserSession``: notifications, its camera, its panels, the
highlighted boxes and points, the box gizmo and the dimmed scan while reviewing (viser)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import viser

from factorydet_core.geometry import box_wireframe_segments
from factorydet_core.session.editing import box_to_pose, camera_for_box, pose_to_box

from .browser_session import BrowserSession
from .state import AppState

HIGHLIGHT_RGB = (255, 215, 0)
REVIEW_RGB = (255, 0, 200)
DIM_FACTOR = 0.25


SUGGESTION_RGB = (0, 200, 220)
"""The model's suggested box for the object last clicked (cyan: neither a label nor a detection)."""
AUTHOR_KEY = "factorydet.author"
"""The browser's localStorage key of the name its edits are signed with."""


class ClientView(BrowserSession):
    """One browser's session drawn in its viser client.

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
        super().__init__(state, drawn_result)
        self.client = client
        self._scene_points = scene_points
        self._dimmed: tuple | None = None  # (scan points, point size) this browser has a dimmed copy of
        self.panels: list = []
        self.gizmo: viser.TransformControlsHandle | None = None
        self.class_dropdowns: list = []  # every dropdown showing object_class
        self._refresh_lock = threading.Lock()  # one refresh at a time (redraw and callback threads)
        self.closed = False  # set when the browser disconnects: nothing is sent to it after that

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
        if self.closed:
            return
        with self._refresh_lock:
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
            point_size = self.state.point_size
            # Sent again only for another scan (a frame change, a colour mode) or point size: an
            # 80k-point copy is a megabyte, which every refresh (anyone's edit) would otherwise send.
            dimmed = self._dimmed
            if dimmed is None or dimmed[0] is not scene_points or dimmed[1] != point_size:
                # The same node name as the shared scan shadows it for this browser only.
                scene.add_point_cloud(
                    "/scan", points=scene_points, colors=(scene_colors * DIM_FACTOR).astype(np.uint8),
                    point_size=point_size, point_shape="square", precision="float32",
                )  # fmt: skip
                self._dimmed = (scene_points, point_size)
        elif self._dimmed is not None:
            # Removing this browser's copy would remove the scan from its view altogether: send
            # the undimmed colours under the same name instead.
            scene_points, scene_colors = self._scene_points()
            scene.add_point_cloud(
                "/scan", points=scene_points, colors=scene_colors,
                point_size=self.state.point_size, point_shape="square", precision="float32",
            )  # fmt: skip
            self._dimmed = None

    def _draw_gizmo(self, label) -> None:
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
