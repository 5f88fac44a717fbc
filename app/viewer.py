"""The app: a viser server with the frame and display panels around one data set."""

from __future__ import annotations

import threading

import numpy as np
import viser

from factorydet_core.detection.warmup import warm_up
from factorydet_core.evaluation.diagnostics import (
    describe_detection,
    describe_patch,
    describe_proposal,
    description_markdown,
    detection_markdown,
    nearest_point_on_ray,
    ray_box_distances,
    segment_patch_ids,
)
from factorydet_core.io.dataset import Dataset
from factorydet_core.session.editing import points_in_screen_rect, suggest_box, suggestion_of
from factorydet_core.training.settings import LoopSettings

from .clients import ClientView
from .layers import LayerView
from .panels.detections_panel import build_detections_panel
from .panels.display_panel import build_display_panel
from .panels.frame_panel import build_frame_panel
from .panels.help_panel import build_help_panel, register_hotkeys
from .panels.labels_panel import build_labels_panel
from .panels.metrics_panel import build_metrics_panel
from .panels.pipeline_panel import build_pipeline_panel
from .panels.review_panel import build_review_panel
from .panels.training_panel import build_training_panel
from .scene import SceneView
from .state import AppState
from .trainer import TrainingWorker
from .worker import PipelineWorker, place_frames


class FactorydetApp:
    """Builds the GUI on ``server`` and keeps the scene in step with the state.

    Args:
        server: a running viser server (the caller owns it and stops it).
        dataset: the data set to show.
        title: shown in the status line; the data set's name by default.
        calibrate: refine the sensor extrinsics by ICP (once, in the background) for multi-sensor data.
        model: a ``DetectionModel``; without one the app shows the front half only.
        model_name: how the model is named in the panel.
        db: the session's ``SessionDB``: labels become editable, the review queue and retraining
            appear. Without one, the data set's annotations are shown read-only.
        training: how the Training panel trains (``settings.LoopSettings``).
    """

    def __init__(
        self,
        server: viser.ViserServer,
        dataset: Dataset,
        title: str | None = None,
        calibrate: bool = True,
        model=None,
        model_name: str = "",
        db=None,
        training: LoopSettings | None = None,
    ) -> None:
        self.server = server
        # Compile the library's numba kernels (or load them from numba's disk cache, about a
        # second) before any client connects: compiling holds the interpreter for seconds at a
        # time, during which the server could not send a new browser its controls.
        warm_up()
        self.state = AppState(dataset, title, model=model, model_name=model_name, db=db)
        if not calibrate:
            self.state.use_refined_extrinsics = False
        self.scene = SceneView(server)
        self.layers = LayerView(server)
        self._layers_key: tuple | None = None
        self._draw_lock = threading.Lock()  # one redraw at a time; the last one wins
        server.gui.configure_theme(control_width="medium", dark_mode=False)
        server.gui.add_markdown("### factorydet", order=0)
        self.frame_panel = build_frame_panel(server, self.state)
        self.display_panel = build_display_panel(server, self.state)
        self.pipeline_panel = build_pipeline_panel(server, self.state)
        self.detections_panel = build_detections_panel(server, self.state)
        self.metrics_panel = build_metrics_panel(server, self.state)
        self.trainer = TrainingWorker(self.state, training, calibrate=calibrate)
        self.training_panel = (
            build_training_panel(server, self.state, self.trainer) if db is not None else None
        )
        self._detections_key: tuple | None = None
        self._drawn: tuple | None = None
        self._labels_key: tuple | None = None
        self.clients: dict[int, ClientView] = {}
        self._clients_lock = threading.Lock()
        self._clients_key: tuple | None = None
        self.worker = PipelineWorker(self.state, calibrate=calibrate)
        if db is not None:
            threading.Thread(
                target=place_frames,
                args=(self.state, lambda: self.worker.refined_extrinsics),
                name="factorydet-world",
                daemon=True,
            ).start()
        self.state.on_change(self.redraw)
        server.scene.on_click()(self._on_click)
        server.scene.on_click(modifier="shift")(lambda event: self._on_click(event, add=True))
        server.scene.on_rect_select(modifier="shift")(self._on_rect_select)
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        server.initial_camera.position = (-10.0, -10.0, 11.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self.redraw()

    def redraw(self) -> None:
        """Bring the scene and the panels up to date with the state."""
        with self._draw_lock:
            with self.state.lock:
                # Colours from the labels follow every edit: the session's revision is part of the key.
                by_labels = self.state.color_mode in ("class", "annotated") and self.state.editable
                key = (
                    self.state.frame_index,
                    self.state.color_mode,
                    self.state.max_height,
                    self.state.revision if by_labels else None,
                )
                labels_key = (
                    self.state.frame_index,
                    self.state.revision,
                    self.state.show_boxes,
                    self.state.show_box_names,
                )
                point_size = self.state.point_size
                frame = self.state.frame
            if key != self._drawn:
                labels = self.state.frame_labels(key[0])[:2] if by_labels else None
                self.scene.draw(
                    frame, color_mode=key[1], point_size=point_size, max_height=key[2], labels=labels
                )
                self._drawn = key
            else:
                self.scene.set_point_size(point_size)
            if labels_key != self._labels_key:
                boxes, class_ids, prelabel_mask = self.state.drawn_labels(labels_key[0])
                self.scene.draw_labels(
                    boxes, class_ids, self.state.dataset.class_names, labels_key[2], names=labels_key[3],
                    prelabel_mask=prelabel_mask,
                )  # fmt: skip
                self._labels_key = labels_key
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
                    self.state.show_box_names,
                )
            if detections_key != self._detections_key:
                labels = None
                if detections is not None:  # what the metrics count as truth (no pre-labels)
                    labels = self.state.references(detection_frame)[:2]
                self.layers.draw_detections(detections, *detections_key[1:4], labels, names=detections_key[4])
                self.layers.detection_source = (detection_result, detection_frame)
                self._detections_key = detections_key
            self.frame_panel.refresh(self.state)
            self.display_panel.refresh(self.state)
            self.pipeline_panel.refresh(self.state)
            self.detections_panel.refresh(self.state)
            self.metrics_panel.refresh(self.state)
            if self.training_panel is not None:
                self.training_panel.refresh(self.state)
            with self.state.lock:
                # (the suspects and the world placement's progress show in each browser's panels)
                clients_key = (
                    self.state.revision,
                    self.state.frame_index,
                    id(self.layers.drawn_result),
                    id(self.state.suspects),
                    self.state.world_status,
                )
            if clients_key != self._clients_key:
                self._clients_key = clients_key
                for view in self._client_views():
                    view.refresh()
        self.worker.maybe_request()

    # -- browsers

    def _client_views(self) -> list[ClientView]:
        with self._clients_lock:
            return list(self.clients.values())

    def _on_connect(self, client: viser.ClientHandle) -> None:
        view = ClientView(
            client,
            self.state,
            scene_points=lambda: self.scene.shown,
            drawn_result=lambda: self.layers.drawn,
        )
        if self.state.editable:
            labels_panel = build_labels_panel(view)
            review_panel = build_review_panel(view, self.trainer.find_suspects)
            view.panels = [labels_panel, review_panel]
            register_hotkeys(view, labels_panel, review_panel)
            build_help_panel(view)
        with self._clients_lock:
            self.clients[client.client_id] = view
        view.refresh()
        if self.state.editable:
            threading.Thread(target=view.restore_author, name="factorydet-author", daemon=True).start()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._clients_lock:
            view = self.clients.pop(client.client_id, None)
        if view is not None:
            view.closed = True

    def client_view(self, client_id: int) -> ClientView | None:
        with self._clients_lock:
            return self.clients.get(client_id)

    def _on_click(self, event: viser.SceneClickEvent, add: bool = False) -> None:
        """A click picks the nearest label box under the cursor (it becomes the browser's
        selection), else the nearest detection box, else the nearest proposal box, else the nearest
        patch point (whose segment becomes the browser's selection; shift-click adds it)."""
        view = self.client_view(event.client_id)
        origin, direction = np.asarray(event.ray_origin), np.asarray(event.ray_direction)
        with self.state.lock:
            show_labels, frame_index = self.state.show_boxes, self.state.frame_index
        if view is not None and self.state.editable and show_labels and not add:
            boxes, _, label_ids = self.state.frame_labels(frame_index)
            distances = ray_box_distances(origin, direction, boxes) if len(boxes) else np.zeros(0)
            if np.isfinite(distances).any():
                view.select_label(int(label_ids[int(np.argmin(distances))]))
                return
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
                with self.state.lock:
                    exponent = getattr(self.state.model, "probability_exponent", 1.0)
                info = describe_detection(detections, k, detection_result.proposal.proposals, frame, exponent)
                self.state.set_selection(detection_markdown(info))
                if view is not None and self.state.editable and not add:
                    view.suggest(
                        detection_frame, suggestion_of(detections, k, detection_result.proposal.proposals)
                    )
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
        if info is None:
            # Points are clickable in every layer: the click selects their segment and, with a
            # model, suggests its box for the object (Accept [G]).
            shown = np.flatnonzero(result.cloud.below(max_height))
            hit = nearest_point_on_ray(result.cloud.points[shown], origin, direction, max_distance=0.15)
            if hit is not None:
                point = int(shown[hit])
                patch_id = int(result.segmentation.patch_ids[point])
                info = describe_patch(result, frame, patch_id)
                if view is not None:
                    view.select_patches(segment_patch_ids(result, patch_id), add=add)
                    same_cloud = detection_result is not None and detection_result.proposal is result
                    if same_cloud and self.state.editable and not add:
                        view.suggest(frame_index, suggest_box(detection_result, point))
        if info is None and view is not None and not add:
            view.clear_selection()
        self.state.set_selection(description_markdown(info) if info else "_Nothing under the cursor._")

    def _on_rect_select(self, event: viser.SceneRectSelectEvent) -> None:
        """Shift-drag: the patches of the points inside the rectangle become the selection."""
        view = self.client_view(event.client_id)
        with self._draw_lock:
            result = self.layers.drawn_result
        if view is None or result is None:
            return
        camera = event.client.camera
        with self.state.lock:
            max_height = self.state.max_height
        shown = np.flatnonzero(result.cloud.below(max_height))
        inside = points_in_screen_rect(
            result.cloud.points[shown], camera.position, camera.wxyz, camera.fov, camera.aspect,
            event.screen_min, event.screen_max,
        )  # fmt: skip
        patch_ids = np.unique(result.segmentation.patch_ids[shown[inside]])
        view.select_patches(patch_ids[patch_ids >= 0])

    def close(self) -> None:
        """Stop the background workers (the caller stops the server)."""
        self.worker.stop()
        self.trainer.cancel()


def serve(
    dataset: Dataset,
    host: str = "127.0.0.1",
    port: int = 8080,
    title: str | None = None,
    model=None,
    model_name: str = "",
    db=None,
) -> None:
    """Serve the app until interrupted."""
    server = viser.ViserServer(host=host, port=port, label="factorydet")
    app = FactorydetApp(server, dataset, title, model=model, model_name=model_name, db=db)
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
        app.close()
        server.stop()
