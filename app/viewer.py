"""The app: a viser server with the frame and display panels around one data set."""

from __future__ import annotations

import threading

import numpy as np
import viser

from factorydet_core.dataset import Dataset
from factorydet_core.inspect import (
    describe_detection,
    describe_patch,
    describe_proposal,
    description_markdown,
    detection_markdown,
    nearest_point_on_ray,
    ray_box_distances,
)

from .layers import LayerView
from .panels.detections_panel import build_detections_panel
from .panels.display_panel import build_display_panel
from .panels.frame_panel import build_frame_panel
from .panels.metrics_panel import build_metrics_panel
from .panels.pipeline_panel import build_pipeline_panel
from .scene import SceneView
from .state import AppState
from .worker import PipelineWorker


class FactorydetApp:
    """Builds the GUI on ``server`` and keeps the scene in step with the state.

    Args:
        server: a running viser server (the caller owns it and stops it).
        dataset: the data set to show.
        title: shown in the status line; the data set's name by default.
        calibrate: refine the sensor extrinsics by ICP (once, in the background) for multi-sensor data.
        model: a ``DetectionModel``; without one the app shows the front half only.
        model_name: how the model is named in the panel.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        dataset: Dataset,
        title: str | None = None,
        calibrate: bool = True,
        model=None,
        model_name: str = "",
    ) -> None:
        self.server = server
        self.state = AppState(dataset, title, model=model, model_name=model_name)
        if not calibrate:
            self.state.use_refined_extrinsics = False
        self.scene = SceneView(server)
        self.layers = LayerView(server)
        self._layers_key: tuple | None = None
        self._draw_lock = threading.Lock()  # one redraw at a time; the last one wins
        server.gui.configure_theme(control_width="medium", dark_mode=False)
        server.gui.add_markdown("### factorydet")
        self.frame_panel = build_frame_panel(server, self.state)
        self.display_panel = build_display_panel(server, self.state)
        self.pipeline_panel = build_pipeline_panel(server, self.state)
        self.detections_panel = build_detections_panel(server, self.state)
        self.metrics_panel = build_metrics_panel(server, self.state)
        self._detections_key: tuple | None = None
        self._drawn: tuple | None = None
        self.worker = PipelineWorker(self.state, calibrate=calibrate)
        self.state.on_change(self.redraw)
        server.scene.on_click()(self._on_click)
        server.initial_camera.position = (-10.0, -10.0, 11.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self.redraw()

    def redraw(self) -> None:
        """Bring the scene and the panels up to date with the state."""
        with self._draw_lock:
            with self.state.lock:
                key = (
                    self.state.frame_index,
                    self.state.color_mode,
                    self.state.show_boxes,
                    self.state.max_height,
                )
                point_size = self.state.point_size
                frame = self.state.frame
            if key != self._drawn:
                self.scene.draw(
                    frame, color_mode=key[1], point_size=point_size, show_boxes=key[2], max_height=key[3]
                )
                self._drawn = key
            else:
                self.scene.set_point_size(point_size)
            with self.state.lock:
                result = self.state.pipeline_result
                result_frame = self.state.pipeline_result_key[0] if result is not None else None
                layers = dict(self.state.layers)
                max_height = self.state.max_height
            if result is not None:
                layers_key = (id(result), max_height)
                if layers_key != self._layers_key:
                    self.layers.draw(result, result_frame, layers, point_size, max_height)
                    self._layers_key = layers_key
                else:
                    self.layers.set_visibility(layers)
                    self.layers.set_point_size(point_size)
            with self.state.lock:
                detections = self.state.detections
                detection_result = self.state.detection_result
                detection_frame = self.state.detection_frame_index
                detections_key = (
                    id(detections),
                    layers["detections"],
                    self.state.show_suppressed,
                    self.state.color_by_match,
                )
            if detections_key != self._detections_key:
                labels = self.state.dataset.frame(detection_frame).labels if detections is not None else None
                self.layers.draw_detections(detections, *detections_key[1:], labels)
                self.layers.detection_source = (detection_result, detection_frame)
                self._detections_key = detections_key
            self.frame_panel.refresh(self.state)
            self.display_panel.refresh(self.state)
            self.pipeline_panel.refresh(self.state)
            self.detections_panel.refresh(self.state)
            self.metrics_panel.refresh(self.state)
        self.worker.maybe_request()

    def _on_click(self, event: viser.SceneClickEvent) -> None:
        """A click picks the nearest detection box under the cursor, else the nearest proposal box,
        else the nearest patch point."""
        with self._draw_lock:  # the drawn result and its box ids belong together
            result, proposal_ids, frame_index = (
                self.layers.drawn_result,
                self.layers.proposal_ids,
                self.layers.drawn_frame_index,
            )
            detections, detection_ids = self.layers.shown_detections, self.layers.shown_detection_ids
            detection_result, detection_frame = self.layers.detection_source
        if result is None:
            return
        origin, direction = np.asarray(event.ray_origin), np.asarray(event.ray_direction)
        if detections is not None and detection_result is not None and len(detection_ids):
            distances = ray_box_distances(origin, direction, detections.boxes[detection_ids])
            if np.isfinite(distances).any():
                # The detections and the proposals they index come from the same result.
                k = int(detection_ids[int(np.argmin(distances))])
                frame = self.state.dataset.frame(detection_frame)
                info = describe_detection(detections, k, detection_result.proposal.proposals, frame)
                self.state.set_selection(detection_markdown(info))
                return
        with self.state.lock:
            layers = dict(self.state.layers)
            max_height = self.state.max_height
        frame = self.state.dataset.frame(frame_index)
        origin, direction = np.asarray(event.ray_origin), np.asarray(event.ray_direction)
        info = None
        if layers["proposals"] and len(proposal_ids):
            distances = ray_box_distances(origin, direction, result.proposals.boxes[proposal_ids])
            if np.isfinite(distances).any():
                info = describe_proposal(result, frame, int(proposal_ids[int(np.argmin(distances))]))
        if info is None and (layers["patches"] or layers["segments"]):
            shown = np.flatnonzero(result.cloud.below(max_height))
            hit = nearest_point_on_ray(result.cloud.points[shown], origin, direction, max_distance=0.15)
            if hit is not None:
                info = describe_patch(result, frame, int(result.segmentation.patch_ids[shown[hit]]))
        self.state.set_selection(description_markdown(info) if info else "_Nothing under the cursor._")

    def close(self) -> None:
        """Stop the background worker (the caller stops the server)."""
        self.worker.stop()


def serve(
    dataset: Dataset,
    host: str = "127.0.0.1",
    port: int = 8080,
    title: str | None = None,
    model=None,
    model_name: str = "",
) -> None:
    """Serve the app until interrupted."""
    server = viser.ViserServer(host=host, port=port, label="factorydet")
    app = FactorydetApp(server, dataset, title, model=model, model_name=model_name)
    actual_port = server.get_port()
    print(
        f"factorydet: serving {app.state.title} at http://{host}:{actual_port}  (Ctrl+C to stop)", flush=True
    )
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(
            "factorydet: warning: viser has no authentication; anyone who reaches this address can edit",
            flush=True,
        )
    try:
        server.sleep_forever()
    except KeyboardInterrupt:
        pass
    finally:
        app.worker.stop()
        server.stop()
