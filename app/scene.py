"""Scene drawing: the merged scan and the annotated boxes of the shown frame."""

from __future__ import annotations

import collections
import threading

import numpy as np
import viser

from factorydet_core import colors
from factorydet_core.geometry import box_corner_segments, box_wireframe_segments, point_box_ids
from factorydet_core.proposals.merge import merge_frame
from factorydet_core.types import Frame

DIM_FACTOR = 0.25
"""How much of its colour a dimmed scan keeps."""


def point_colors(frame: Frame, points: np.ndarray, mode: str, labels: tuple | None = None) -> np.ndarray:
    """(N, 3) uint8 colours of the frame's merged ``points`` (N, 3) in colour ``mode``.

    Args:
        labels: ``(boxes (R, 7), class_ids (R,))``, the session's labels of the frame: the class
            and annotated modes colour the points inside them (the data set's per-point
            annotations without a session), so that they follow every edit.
    """
    points_z = points[:, 2]
    if mode in ("class", "annotated") and labels is not None:
        box_ids = point_box_ids(points, np.asarray(labels[0], np.float64).reshape(-1, 7))
        if mode == "annotated":
            return colors.colors_by_annotation(box_ids + 1)
        class_ids = np.append(np.asarray(labels[1], np.int64), -1)[box_ids]  # -1 (none) stays -1
        return colors.colors_by_class(class_ids, frame.class_names)
    if mode == "sensor":
        return colors.colors_by_sensor(frame.sensor_ids, frame.num_sensors)
    if mode == "rgb" and frame.colors is not None:
        return np.asarray(frame.colors)
    if mode in ("height", "rgb"):
        return colors.colors_by_height(points_z)
    if mode == "class":
        return colors.colors_by_class(frame.point_class_ids, frame.class_names)
    if mode == "annotated":
        return colors.colors_by_annotation(frame.point_instance_ids)
    raise ValueError(f"unknown colour mode {mode!r}")


GRID_HALF_WIDTH_M = 30.0
"""The floor grid spans this far from the origin in x and y."""


def grid_segments(half_width: float, spacing: float, skip_every: int = 0) -> np.ndarray:
    """Lines of a square grid on the floor (z = 0), ``spacing`` apart, from -``half_width`` to
    ``half_width`` (a multiple of ``spacing``), leaving out every ``skip_every``-th line (drawn by a
    coarser grid); (N, 2, 3)."""
    if not spacing > 0 or not half_width > 0:
        raise ValueError(f"grid spacing and half width must be positive, got {spacing} and {half_width}")
    count = int(round(2 * half_width / spacing))
    ticks = -half_width + spacing * np.arange(count + 1)
    if skip_every:
        ticks = ticks[np.arange(count + 1) % skip_every != 0]
    ends = np.full(len(ticks), half_width)
    along_y = np.stack([np.stack([ticks, -ends], 1), np.stack([ticks, ends], 1)], 1)
    lines = np.concatenate([along_y, along_y[:, :, ::-1]])
    return np.concatenate([lines, np.zeros((*lines.shape[:2], 1))], axis=2).astype(np.float32)


MERGED_FRAMES_KEPT = 4
"""Merged scans a browser's scene keeps: going back to a frame just shown (the review queue moves
between a few frames) merges its sensors again only after this many others."""


class SceneView:
    """Owns the scene nodes under ``/scan`` and ``/labels``."""

    def __init__(self, server: viser.ViserServer | viser.ClientHandle) -> None:
        self.server = server  # a browser's client: each browser draws its own view
        self._cloud: viser.PointCloudHandle | None = None
        # What the browser shows of the labels, to send only what an edit changes: per wireframe
        # node (handle, segments, colours), per class name (handle, text, position).
        self._line_nodes: dict[str, tuple] = {}
        self._name_nodes: list[tuple] = []
        # The shown scan's (points, colours) and point size, to send it again dimmed or not.
        self._shown: tuple[np.ndarray, np.ndarray] | None = None
        self._point_size = 0.04
        self.dimmed = False
        # The scan is sent from the redraw and from the selection's refresh (dimming): one at a time.
        self._scan_lock = threading.RLock()
        # By the frame's id, (the frame, its merge): frames are frozen and a data set reads each
        # one into one object, held here so that its id stays its own.
        self._merged: collections.OrderedDict[int, tuple] = collections.OrderedDict()
        server.scene.set_up_direction("+z")
        # The lit-mesh environment map costs seconds under software WebGL and changes nothing for
        # wireframes and points.
        server.scene.configure_environment_map(None)
        # viser's default light casts shadows in three cascades, each drawn again at every render
        # of the scene, and nothing here needs a shadow (the walkthrough's --shadow-cost times
        # what they would cost). The light stays for the lit resize handles.
        server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        # A point cloud that is always there, two points far outside any view: it keeps the
        # browser's compiled point shader alive. Each new scan replaces the node, and with no
        # other point cloud drawn three.js would free the shader with the old scan and compile it
        # again for the new one: under software WebGL that compile was the largest part of a frame
        # change (0.1-0.35 s of the page's main thread).
        server.scene.add_point_cloud(
            "/shader_keeper",
            points=np.full((2, 3), -1.0e4, np.float32),
            colors=np.zeros((2, 3), np.uint8),
            point_size=0.01,
            point_shape="square",
            precision="float32",
        )
        # The floor grid as plain lines: viser's grid is a shader evaluated at every pixel of the
        # plane, which under software WebGL took more time per render than the 80k points did.
        self._grid = [
            server.scene.add_line_segments(name, segments, rgb, thickness=1.0, thickness_units="screen")
            for name, segments, rgb in (
                ("/grid/cells", grid_segments(GRID_HALF_WIDTH_M, 1.0, skip_every=5), (200, 200, 200)),
                ("/grid/sections", grid_segments(GRID_HALF_WIDTH_M, 5.0), (140, 140, 140)),
            )
        ]

    @property
    def grid_visible(self) -> bool:
        """Whether the floor grid is shown."""
        return self._grid[0].visible

    def set_grid_visible(self, visible: bool) -> None:
        """Show or hide the floor grid (viser sends a node's visibility only when it changes)."""
        for handle in self._grid:
            handle.visible = visible

    def draw(
        self,
        frame: Frame,
        *,
        color_mode: str,
        point_size: float,
        max_height: float,
        labels: tuple | None = None,
        max_points: int | None = None,
    ) -> None:
        """Replace the shown scan with ``frame``'s, points above ``max_height`` hidden and at most
        ``max_points`` of the others drawn (``colors.thin_for_display``; ``labels``: the
        session's, for the class and annotated colours, see ``point_colors``)."""
        merged = self._merge(frame)
        rgb = point_colors(frame, merged.points, color_mode, labels)
        keep = colors.thin_for_display(merged.below(max_height), max_points)
        with self._scan_lock:
            self._shown = (merged.points[keep], rgb[keep])
            self._point_size = float(point_size)
            self._send()

    @property
    def num_points_shown(self) -> int:
        """Points of the scan this browser was last sent (after the height cut and the budget)."""
        with self._scan_lock:
            return 0 if self._shown is None else len(self._shown[0])

    def _merge(self, frame: Frame):
        """``merge_frame(frame)``, kept for the last ``MERGED_FRAMES_KEPT`` frames drawn."""
        with self._scan_lock:
            cached = self._merged.get(id(frame))
            if cached is not None and cached[0] is frame:
                self._merged.move_to_end(id(frame))
                return cached[1]
        merged = merge_frame(frame)
        with self._scan_lock:
            self._merged[id(frame)] = (frame, merged)
            while len(self._merged) > MERGED_FRAMES_KEPT:
                self._merged.popitem(last=False)
        return merged

    def _send(self) -> None:
        """(Under ``_scan_lock``.)"""
        points, rgb = self._shown
        if self.dimmed:
            rgb = (rgb * DIM_FACTOR).astype(np.uint8)
        self._cloud = self.server.scene.add_point_cloud(
            "/scan",
            points=points,
            colors=rgb,
            point_size=self._point_size,
            point_shape="square",
            precision="float32",
        )

    def set_dimmed(self, dimmed: bool) -> None:
        """Dim the scan (while reviewing, the item's box stands out) or restore its colours; the
        scan (a megabyte for 80k points) is sent again only when this changes."""
        with self._scan_lock:
            if bool(dimmed) == self.dimmed:
                return
            self.dimmed = bool(dimmed)
            if self._shown is not None:
                self._send()

    def draw_labels(
        self,
        boxes: np.ndarray,
        class_ids: np.ndarray,
        class_names: tuple[str, ...],
        visible: bool,
        names: bool = True,
        prelabel_mask: np.ndarray | None = None,
    ) -> None:
        """Show the label boxes: wireframes in the class colour, the model's pre-labels nobody
        has confirmed (``prelabel_mask``, (R,)) as corner brackets, with the class name on top when
        ``names`` (detections are dashed: ``layers``).

        Only what changed is sent: an edit moves one box, and re-creating every name and both
        wireframe nodes made each edit's update as large as the frame's whole set of labels. (In
        headless Chromium the walkthrough showed no difference: the scene's render is what an
        edit waits for there, ``docs/labelling.md``.)"""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        with self.server.atomic():
            if not visible or not len(boxes):
                self._show_lines({})
                self._show_names([])
                return
            class_rgb = colors.class_colors(class_names)[class_ids]
            pre = np.zeros(len(boxes), bool) if prelabel_mask is None else np.asarray(prelabel_mask, bool)
            lines = {}
            for name, mask, draw, thickness in (
                ("/labels/boxes", ~pre, box_wireframe_segments, 2.0),
                ("/labels/pre_labels", pre, box_corner_segments, 4.0),
            ):
                if not mask.any():
                    continue
                segments = draw(boxes[mask]).astype(np.float32)
                per_box = len(segments) // int(mask.sum())
                rgb = np.repeat(class_rgb[mask], per_box, axis=0)[:, None].repeat(2, axis=1).astype(np.uint8)
                lines[name] = (segments, rgb, thickness)
            self._show_lines(lines)
            if not names:
                self._show_names([])
                return
            tops = boxes[:, :3] + np.c_[np.zeros((len(boxes), 2)), boxes[:, 5] / 2 + 0.1]
            self._show_names(
                [(class_names[c], tuple(float(v) for v in top)) for top, c in zip(tops, class_ids)]
            )

    def _show_lines(self, lines: dict[str, tuple[np.ndarray, np.ndarray, float]]) -> None:
        """The wireframe nodes ``lines`` (name: segments (S, 2, 3), colours (S, 2, 3), thickness):
        a node whose arrays are unchanged is kept, a changed one sent again, a missing one removed."""
        for name in list(self._line_nodes):
            if name not in lines:
                self._line_nodes.pop(name)[0].remove()
        for name, (segments, rgb, thickness) in lines.items():
            shown = self._line_nodes.get(name)
            if shown is not None and np.array_equal(shown[1], segments) and np.array_equal(shown[2], rgb):
                continue
            handle = self.server.scene.add_line_segments(
                name, points=segments, colors=rgb, thickness=thickness, thickness_units="screen"
            )
            self._line_nodes[name] = (handle, segments, rgb)

    def _show_names(self, names: list[tuple[str, tuple[float, float, float]]]) -> None:
        """The class names ``names`` ((text, position) per box, in box order): the i-th name node
        is kept when unchanged, else given the new text or position; extra nodes are removed."""
        while len(self._name_nodes) > len(names):
            self._name_nodes.pop()[0].remove()
        for i, (text, position) in enumerate(names):
            if i == len(self._name_nodes):
                handle = self.server.scene.add_label(f"/labels/name_{i}", text=text, position=position)
                self._name_nodes.append((handle, text, position))
                continue
            handle, shown_text, shown_position = self._name_nodes[i]
            if text != shown_text:
                handle.text = text
            if position != shown_position:
                handle.position = position
            self._name_nodes[i] = (handle, text, position)

    def set_visible(self, visible: bool) -> None:
        """Show or hide the scan and its boxes."""
        nodes = [node for node, *_ in (*self._line_nodes.values(), *self._name_nodes)]
        for node in ([self._cloud] if self._cloud is not None else []) + nodes:
            node.visible = visible

    def set_point_size(self, point_size: float) -> None:
        with self._scan_lock:
            self._point_size = float(point_size)
            if self._cloud is not None and self._cloud.point_size != self._point_size:
                self._cloud.point_size = self._point_size
