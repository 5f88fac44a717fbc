"""Drawing the detection layers: merged cloud, voxels, patches, segments and proposal boxes.

A new result re-sends every layer once; toggling a layer only flips its node's visibility.
"""

from __future__ import annotations

import numpy as np
import viser

from factorydet_core import colors
from factorydet_core.detector import ProposalResult
from factorydet_core.geometry import box_wireframe_segments
from factorydet_core.voxels import fisher_vector_colors

from .state import LAYERS

PROPOSAL_RGB = (255, 140, 0)


def shown_proposal_ids(result: ProposalResult) -> np.ndarray:
    """Proposals drawn as boxes: the final segments with their fitted boxes. The other levels and
    completed boxes are in the result (and the CLI's JSON) but would bury the view."""
    proposals = result.proposals
    return np.flatnonzero((proposals.level == 0) & (proposals.box_kind == 0))


class LayerView:
    """Owns the scene nodes under ``/pipeline``."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.nodes: dict[str, object] = {}
        self.drawn_result: ProposalResult | None = None
        self.drawn_frame_index = 0
        self.proposal_ids = np.zeros(0, np.int64)
        self._voxel_colors: tuple[int, np.ndarray] | None = None  # (id(result), colours)

    def draw(
        self,
        result: ProposalResult,
        frame_index: int,
        layers: dict[str, bool],
        point_size: float,
        max_height: float,
    ) -> None:
        """Replace every layer with ``result``'s (computed for ``frame_index``); hidden layers are
        sent hidden."""
        cloud = result.cloud
        low = cloud.below(max_height)
        merged = result.merged
        merged_low = merged.below(max_height)
        num_sensors = len(merged.T_vehicle_sensor)
        with self.server.atomic():
            for node in self.nodes.values():
                node.remove()
            self.nodes = {}
            self.nodes["merged"] = self.server.scene.add_point_cloud(
                "/pipeline/merged",
                points=merged.points[merged_low],
                colors=colors.colors_by_sensor(merged.sensor_ids[merged_low], num_sensors),
                point_size=point_size,
                point_shape="square",
                precision="float32",
                visible=layers["merged"],
            )
            if self._voxel_colors is None or self._voxel_colors[0] != id(result):
                # Once per result: moving the height slider must not redo the projection.
                self._voxel_colors = (id(result), fisher_vector_colors(result.voxel_features))
            voxel_low = result.grid.below(max_height)
            self.nodes["voxels"] = self.server.scene.add_point_cloud(
                "/pipeline/voxels",
                points=result.grid.centres[voxel_low].astype(np.float32),
                colors=self._voxel_colors[1][voxel_low],
                point_size=result.grid.voxel_size * 0.8,
                point_shape="square",
                precision="float32",
                visible=layers["voxels"],
            )
            for name, ids in (
                ("patches", result.segmentation.patch_ids),
                ("segments", result.segmentation.segment_ids),
            ):
                self.nodes[name] = self.server.scene.add_point_cloud(
                    f"/pipeline/{name}",
                    points=cloud.points[low],
                    colors=colors.colors_by_id(ids[low], seed=1 if name == "segments" else 0),
                    point_size=point_size,
                    point_shape="square",
                    precision="float32",
                    visible=layers[name],
                )
            self.proposal_ids = shown_proposal_ids(result)
            boxes = result.proposals.boxes[self.proposal_ids]
            segments = box_wireframe_segments(boxes).astype(np.float32) if len(boxes) else np.zeros((0, 2, 3))
            self.nodes["proposals"] = self.server.scene.add_line_segments(
                "/pipeline/proposals",
                points=segments.astype(np.float32).reshape(-1, 2, 3),
                colors=np.array(PROPOSAL_RGB, np.uint8),
                thickness=1.5,
                thickness_units="screen",
                visible=layers["proposals"],
            )
        self.drawn_result = result
        self.drawn_frame_index = frame_index

    def set_visibility(self, layers: dict[str, bool]) -> None:
        for name in LAYERS:
            node = self.nodes.get(name)
            if node is not None and node.visible != layers[name]:
                node.visible = layers[name]

    def set_point_size(self, point_size: float) -> None:
        for name in ("merged", "patches", "segments"):
            node = self.nodes.get(name)
            if node is not None:
                node.point_size = point_size
