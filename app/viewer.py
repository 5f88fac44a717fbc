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
from .keyboard import route_dropdown_keys_to_hotkeys
from .panels.detections_panel import build_detections_panel
from .panels.display_panel import build_display_panel
from .panels.frame_panel import build_frame_panel
from .panels.help_panel import build_help_panel, register_hotkeys
from .panels.labels_panel import build_labels_panel
from .panels.metrics_panel import build_metrics_panel
from .panels.pipeline_panel import build_pipeline_panel
from .panels.review_panel import build_review_panel
from .panels.training_panel import build_training_panel
from .state import SharedState
from .trainer import TrainingWorker
from .worker import PipelineWorker, place_frames


class FactorydetApp:
    """Serves one data set (and session): each browser that connects gets its own view of it
    (frame, display settings, thresholds: ``clients.ClientView``), drawn in its own scene and
    panels; the data set, session, model, front-half parameters and training are shared.

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
        points_drawn: int | None = None,
    ) -> None:
        self.server = server
        # Compile the library's numba kernels (or load them from numba's disk cache, about a
        # second) before any client connects: compiling holds the interpreter for seconds at a
        # time, during which the server could not send a new browser its controls.
        warm_up()
        self.shared = SharedState(dataset, title, model=model, model_name=model_name, db=db)
        if not calibrate:
            self.shared.use_refined_extrinsics = False
        self.state = self.shared.new_view(served=False)
        """The view no browser owns (a template): each new browser starts like it (its frame,
        display settings and thresholds), and the worker computes its frame before the first
        browser connects."""
        self.state.set_display(points_drawn=points_drawn)  # (every browser's, reloads too)
        server.gui.configure_theme(control_width="medium", dark_mode=False)
        self.trainer = TrainingWorker(self.shared, training, calibrate=calibrate)
        self.clients: dict[int, ClientView] = {}
        self._clients_lock = threading.Lock()
        self.worker = PipelineWorker(self.shared, calibrate=calibrate)
        if db is not None:
            threading.Thread(
                target=place_frames,
                args=(self.shared,),
                name="factorydet-world",
                daemon=True,
            ).start()
        self.state.on_change(lambda: self.worker.maybe_request(self.state))
        server.scene.on_click()(self._on_click)
        server.scene.on_click(modifier="shift")(lambda event: self._on_click(event, add=True))
        server.scene.on_rect_select(modifier="shift")(self._on_rect_select)
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        server.initial_camera.position = (-10.0, -10.0, 11.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self.worker.maybe_request(self.state)

    # -- browsers

    @property
    def views(self) -> list[ClientView]:
        """The connected browsers."""
        with self._clients_lock:
            return list(self.clients.values())

    def _on_connect(self, client: viser.ClientHandle) -> None:
        """A new browser gets its own view (like ``state``), scene and panels."""
        state = self.shared.new_view(like=self.state)
        view = ClientView(client, state)
        # Registered before it is built: a browser that leaves meanwhile (a reload) is found
        # and closed by the disconnect callback, which viser may run on another thread.
        with self._clients_lock:
            self.clients[client.client_id] = view
        try:
            self._build(view)
        except Exception:
            self._forget(client.client_id)
            raise
        if client.client_id not in self.server.get_clients():  # it left while being built
            self._forget(client.client_id)

    def _build(self, view: ClientView) -> None:
        client, state = view.client, view.state
        client.gui.add_markdown("### factorydet", order=0)
        view.view_panels = [
            build_frame_panel(client, state),
            build_display_panel(client, state),
            build_pipeline_panel(client, state),
            build_detections_panel(client, state),
            build_metrics_panel(client, state),
        ]
        if self.shared.editable:
            view.view_panels.append(build_training_panel(client, state, self.trainer))
            labels_panel = build_labels_panel(view)
            review_panel = build_review_panel(view, self.trainer.find_suspects)
            view.panels = [labels_panel, review_panel]
            register_hotkeys(view, labels_panel, review_panel)
            route_dropdown_keys_to_hotkeys(client)
            build_help_panel(view)

        def redraw() -> None:
            view.redraw()
            self.worker.maybe_request(state)

        state.on_change(redraw)
        redraw()
        if self.shared.editable:
            threading.Thread(target=view.restore_author, name="factorydet-author", daemon=True).start()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        self._forget(client.client_id)

    def _forget(self, client_id: int) -> None:
        """A browser left: nothing is drawn for it and the worker no longer computes its frames."""
        with self._clients_lock:
            view = self.clients.pop(client_id, None)
        if view is not None:
            view.closed = True
            view.state.close()

    def client_view(self, client_id: int) -> ClientView | None:
        with self._clients_lock:
            return self.clients.get(client_id)

    def _on_click(self, event: viser.SceneClickEvent, add: bool = False) -> None:
        """A click picks the nearest label box under the cursor (it becomes the browser's
        selection), else the nearest detection box, else the nearest proposal box, else the nearest
        patch point (whose segment becomes the browser's selection; shift-click adds it). What it
        changes reaches the browser in one update, as a key's does (``ClientView.respond``)."""
        view = self.client_view(event.client_id)
        if view is not None:
            view.respond(lambda: self._click(view, event, add))

    def _click(self, view: ClientView, event: viser.SceneClickEvent, add: bool) -> None:
        state = view.state
        origin, direction = np.asarray(event.ray_origin), np.asarray(event.ray_direction)
        with state.lock:
            show_labels, shown_frame = state.show_boxes, state.frame_index
        if state.editable and show_labels and not add:
            boxes, _, label_ids = state.frame_labels(shown_frame)
            distances = ray_box_distances(origin, direction, boxes) if len(boxes) else np.zeros(0)
            if np.isfinite(distances).any():
                view.select_label(int(label_ids[int(np.argmin(distances))]))
                return
        layers = view.layers
        with view._draw_lock:  # the drawn result and its box ids belong together
            result, proposal_ids, frame_index = (
                layers.drawn_result,
                layers.proposal_ids,
                layers.drawn_frame_index,
            )
            detections, detection_ids = layers.shown_detections, layers.shown_detection_ids
            detection_result, detection_frame = layers.detection_source
        if result is None:
            return
        if frame_index != shown_frame:
            # Another frame's result (hidden): its points are not the scan drawn.
            state.set_selection("_This frame's segments are still being computed: click again in a moment._")
            return
        if detections is not None and detection_result is not None and len(detection_ids):
            distances = ray_box_distances(origin, direction, detections.boxes[detection_ids])
            if np.isfinite(distances).any():
                # The detections and the proposals they index come from the same result.
                k = int(detection_ids[int(np.argmin(distances))])
                frame = state.dataset.frame(detection_frame)
                with state.lock:
                    exponent = getattr(state.model, "probability_exponent", 1.0)
                info = describe_detection(detections, k, detection_result.proposal.proposals, frame, exponent)
                state.set_selection(detection_markdown(info))
                if state.editable and not add:
                    view.suggest(
                        detection_frame, suggestion_of(detections, k, detection_result.proposal.proposals)
                    )
                return
        with state.lock:
            shown_layers = dict(state.layers)
            max_height = state.max_height
        frame = state.dataset.frame(frame_index)
        info = None
        if shown_layers["proposals"] and len(proposal_ids):
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
                view.select_patches(segment_patch_ids(result, patch_id), add=add)
                same_cloud = detection_result is not None and detection_result.proposal is result
                if same_cloud and state.editable and not add:
                    view.suggest(frame_index, suggest_box(detection_result, point))
        if info is None and not add:
            view.clear_selection()
        state.set_selection(description_markdown(info) if info else "_Nothing under the cursor._")

    def _on_rect_select(self, event: viser.SceneRectSelectEvent) -> None:
        """Shift-drag: the patches of the points inside the rectangle become the selection (one
        update, as a click's)."""
        view = self.client_view(event.client_id)
        if view is not None:
            view.respond(lambda: self._rect_select(view, event))

    def _rect_select(self, view: ClientView, event: viser.SceneRectSelectEvent) -> None:
        result, _ = view.shown_result()
        if result is None:
            return
        camera = event.client.camera
        with view.state.lock:
            max_height = view.state.max_height
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
    points_drawn: int | None = None,
) -> None:
    """Serve the app until interrupted (``points_drawn``: every browser's Display > Points drawn
    to begin with; None, all)."""
    server = viser.ViserServer(host=host, port=port, label="factorydet")
    app = FactorydetApp(
        server, dataset, title, model=model, model_name=model_name, db=db, points_drawn=points_drawn
    )
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
