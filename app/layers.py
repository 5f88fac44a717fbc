"""Drawing the detection layers: merged cloud, voxels, patches, segments and proposal boxes.

A new result sends the shown layers; a hidden layer is sent the first time it is shown, and
after that toggling it only flips its node's visibility.
"""

from __future__ import annotations

import numpy as np
import viser

from factorydet_core import colors
from factorydet_core.detection.detector import ProposalResult
from factorydet_core.geometry import box_dashed_segments, box_wireframe_segments
from factorydet_core.metrics import match_detections
from factorydet_core.proposals.voxels import voxel_colors
from factorydet_core.types import Detections

from .state import LAYERS

PROPOSAL_RGB = (255, 140, 0)
SUPPRESSED_RGB = (160, 160, 160)
MATCH_RGB = {"tp": (30, 170, 60), "fp": (220, 40, 40), "missed": (40, 90, 230)}
DRAWN_LAYERS: tuple[str, ...] = tuple(name for name in LAYERS if name != "detections")
"""The layers ``LayerView.draw`` draws from a proposal result (the detections are drawn apart)."""
MAX_LABELS = 60  # text sprites are one node each; beyond this the view is unreadable anyway


def _wireframes(boxes: np.ndarray, rgb: np.ndarray, dashed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(S, 2, 3) segments and (S, 2, 3) colours of boxes with one (K, 3) colour each; ``dashed``
    for the model's boxes (labels are solid, ``scene``)."""
    if not len(boxes):
        return np.zeros((0, 2, 3), np.float32), np.zeros((0, 2, 3), np.uint8)
    draw = box_dashed_segments if dashed else box_wireframe_segments
    segments = draw(boxes).astype(np.float32).reshape(-1, 2, 3)
    per_box = len(segments) // len(boxes)
    return segments, np.repeat(np.asarray(rgb, np.uint8), per_box, axis=0)[:, None].repeat(2, axis=1)


def shown_proposal_ids(result: ProposalResult) -> np.ndarray:
    """Proposals drawn as boxes: the final segments with their fitted boxes. The other levels and
    completed boxes are in the result (and the CLI's JSON) but would bury the view."""
    proposals = result.proposals
    return np.flatnonzero((proposals.level == 0) & (proposals.box_kind == 0))


class LayerView:
    """Owns the scene nodes under ``/pipeline``."""

    def __init__(self, server: viser.ViserServer | viser.ClientHandle) -> None:
        self.server = server  # a browser's client: each browser draws its own view
        self.nodes: dict[str, object] = {}  # the layers sent (``DRAWN_LAYERS``), shown or hidden
        # (result, point size, max height, max points) of the last draw: what a hidden layer is
        # drawn from when it is shown.
        self._source: tuple | None = None
        self.drawn_result: ProposalResult | None = None
        self.drawn_frame_index = 0
        self.drawn: tuple[ProposalResult | None, int] = (None, 0)  # the two above, set as one
        self.proposal_ids = np.zeros(0, np.int64)
        # (the result drawn, its voxels' colours): the result itself, not its id, which a freed
        # result's successor can take
        self._voxel_colors: tuple[object, np.ndarray] | None = None
        self.detection_nodes: list = []
        self.detection_source: tuple = (None, 0)  # (DetectionResult, frame index) of the shown detections
        self.shown_detections: Detections | None = None
        self.shown_detection_ids = np.zeros(0, np.int64)

    def draw(
        self,
        result: ProposalResult,
        frame_index: int,
        layers: dict[str, bool],
        point_size: float,
        max_height: float,
        max_points: int | None = None,
    ) -> None:
        """Replace every layer with ``result``'s (computed for ``frame_index``): the shown layers
        are sent now, a hidden one when it is first shown (``set_visibility``); the point layers
        draw at most ``max_points`` points each below ``max_height`` (``colors.thin_for_display``:
        clicks still pick from every point).

        Hidden layers are not sent: four point clouds of a frame's size that nobody looks at made
        every frame change (a review verdict's, say) megabytes larger for the browser to decode."""
        with self.server.atomic():
            for node in self.nodes.values():
                node.remove()
            self.nodes = {}
            self._source = (result, point_size, max_height, max_points)
            if result.voxel_colors is not None:  # the worker's
                self._voxel_colors = (result, result.voxel_colors)
            elif self._voxel_colors is not None and self._voxel_colors[0] is not result:
                self._voxel_colors = None  # another frame's (computed when the layer is sent)
            self.proposal_ids = shown_proposal_ids(result)
            for name in DRAWN_LAYERS:
                if layers[name]:
                    self._send(name)
        self.drawn_result = result
        self.drawn_frame_index = frame_index
        self.drawn = (result, frame_index)

    def _send(self, name: str) -> None:
        """Send layer ``name`` (one of ``DRAWN_LAYERS``) of the result last drawn, shown."""
        result, point_size, max_height, max_points = self._source
        scene = self.server.scene
        if name == "merged":
            merged = result.merged
            low = colors.thin_for_display(merged.below(max_height), max_points)
            self.nodes[name] = scene.add_point_cloud(
                "/pipeline/merged",
                points=merged.points[low],
                colors=colors.colors_by_sensor(merged.sensor_ids[low], len(merged.T_vehicle_sensor)),
                point_size=point_size,
                point_shape="square",
                precision="float32",
            )
        elif name == "voxels":
            if self._voxel_colors is None or self._voxel_colors[0] is not result:
                # Once per result: moving the height slider must not redo the projection.
                self._voxel_colors = (
                    result,
                    voxel_colors(result.cloud, result.grid, result.voxel_features),
                )
            low = colors.thin_for_display(result.grid.below(max_height), max_points)
            self.nodes[name] = scene.add_point_cloud(
                "/pipeline/voxels",
                points=result.grid.centres[low].astype(np.float32),
                colors=self._voxel_colors[1][low],
                point_size=result.grid.voxel_size * 0.8,
                point_shape="square",
                precision="float32",
            )
        elif name in ("patches", "segments"):
            ids = result.segmentation.patch_ids if name == "patches" else result.segmentation.segment_ids
            # (one choice of points for both: a point keeps its place when the layer changes)
            low = colors.thin_for_display(result.cloud.below(max_height), max_points)
            self.nodes[name] = scene.add_point_cloud(
                f"/pipeline/{name}",
                points=result.cloud.points[low],
                colors=colors.colors_by_id(ids[low], seed=1 if name == "segments" else 0),
                point_size=point_size,
                point_shape="square",
                precision="float32",
            )
        elif name == "proposals":
            boxes = result.proposals.boxes[self.proposal_ids]
            segments = box_wireframe_segments(boxes).astype(np.float32) if len(boxes) else np.zeros((0, 2, 3))
            self.nodes[name] = scene.add_line_segments(
                "/pipeline/proposals",
                points=segments.astype(np.float32).reshape(-1, 2, 3),
                colors=np.array(PROPOSAL_RGB, np.uint8),
                thickness=1.5,
                thickness_units="screen",
            )
        else:
            raise ValueError(f"unknown layer {name!r}; choose from {DRAWN_LAYERS}")

    def set_visibility(self, layers: dict[str, bool]) -> None:
        """Show or hide the layers as ``layers`` says; a layer shown for the first time since
        the last ``draw`` is sent now."""
        with self.server.atomic():
            for name in DRAWN_LAYERS:
                node = self.nodes.get(name)
                if node is not None:
                    if node.visible != layers[name]:
                        node.visible = layers[name]
                elif layers[name] and self._source is not None:
                    self._send(name)

    def set_point_size(self, point_size: float) -> None:
        if self._source is not None:
            self._source = (self._source[0], float(point_size), *self._source[2:])
        for name in ("merged", "patches", "segments"):
            node = self.nodes.get(name)
            if node is not None and node.point_size != point_size:
                node.point_size = point_size

    def draw_detections(
        self,
        detections: Detections | None,
        visible: bool,
        show_suppressed: bool,
        color_by_match: bool,
        labels: tuple[np.ndarray, np.ndarray] | None,
        names: bool = True,
    ) -> None:
        """Replace the detection boxes: kept ones coloured by class (or by match against
        ``labels``, ``(boxes (R, 7), class_ids (R,))``: true positive, false positive, missed
        label), with a class-and-score label when ``names``; suppressed ones grey when asked."""
        with self.server.atomic():
            for node in self.detection_nodes:
                node.remove()
            self.detection_nodes = []
            self.shown_detections = detections
            self.shown_detection_ids = np.zeros(0, np.int64)
            if detections is None or not visible:
                return
            kept = np.flatnonzero(detections.kept_mask)
            rgb = colors.class_colors(detections.class_names)[detections.class_ids[kept]]
            missed = np.zeros((0, 7))
            if color_by_match and labels is not None:
                label_boxes, label_class_ids = labels
                tp, matched = match_detections(
                    detections.boxes[kept], detections.class_ids[kept], detections.scores[kept],
                    label_boxes, label_class_ids, 0.6,
                )  # fmt: skip
                rgb = np.where(tp[:, None], MATCH_RGB["tp"], MATCH_RGB["fp"])
                missed = label_boxes[np.setdiff1d(np.arange(len(label_boxes)), matched[matched >= 0])]
            # Dashed: a detection is the model's, a label (solid) a person's, in the same colours.
            self._add_boxes("/pipeline/detections", detections.boxes[kept], rgb, 3.0, dashed=True)
            for n, k in enumerate(kept[:MAX_LABELS] if names else ()):
                box = detections.boxes[k]
                self.detection_nodes.append(
                    self.server.scene.add_label(
                        f"/pipeline/detection_labels/{n}",
                        f"{detections.class_names[int(detections.class_ids[k])]} {detections.scores[k]:.2f}",
                        position=(float(box[0]), float(box[1]), float(box[2] + box[5] / 2 + 0.1)),
                        font_screen_scale=0.7,
                    )
                )
            shown = kept
            if show_suppressed:
                suppressed = np.flatnonzero(~detections.kept_mask)
                grey = np.tile(SUPPRESSED_RGB, (len(suppressed), 1))
                self._add_boxes("/pipeline/suppressed", detections.boxes[suppressed], grey, 1.0)
                shown = np.concatenate([kept, suppressed])
            if len(missed):
                self._add_boxes(
                    "/pipeline/missed", missed, np.tile(MATCH_RGB["missed"], (len(missed), 1)), 2.0
                )
            self.shown_detection_ids = shown

    def _add_boxes(
        self, name: str, boxes: np.ndarray, rgb: np.ndarray, thickness: float, dashed: bool = False
    ) -> None:
        """Draw (K, 7) boxes as wireframes, one (K, 3) colour each, as one detection node."""
        segments, segment_rgb = _wireframes(boxes, rgb, dashed)
        self.detection_nodes.append(
            self.server.scene.add_line_segments(
                name, points=segments, colors=segment_rgb, thickness=thickness, thickness_units="screen"
            )
        )
