"""The app: a viser server with the frame and display panels around one data set."""

from __future__ import annotations

import threading

import viser

from factorydet_core.dataset import Dataset

from .panels.display_panel import build_display_panel
from .panels.frame_panel import build_frame_panel
from .scene import SceneView
from .state import AppState


class FactorydetApp:
    """Builds the GUI on ``server`` and keeps the scene in step with the state.

    Args:
        server: a running viser server (the caller owns it and stops it).
        dataset: the data set to show.
    """

    def __init__(self, server: viser.ViserServer, dataset: Dataset, title: str | None = None) -> None:
        self.server = server
        self.state = AppState(dataset, title)
        self.scene = SceneView(server)
        self._draw_lock = threading.Lock()  # one redraw at a time; the last one wins
        server.gui.configure_theme(control_width="medium", dark_mode=False)
        server.gui.add_markdown("### factorydet")
        self.frame_panel = build_frame_panel(server, self.state)
        self.display_panel = build_display_panel(server, self.state)
        self._drawn: tuple | None = None
        self.state.on_change(self.redraw)
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
            self.frame_panel.refresh(self.state)
            self.display_panel.refresh(self.state)


def serve(dataset: Dataset, host: str = "127.0.0.1", port: int = 8080, title: str | None = None) -> None:
    """Serve the app until interrupted."""
    server = viser.ViserServer(host=host, port=port, label="factorydet")
    app = FactorydetApp(server, dataset, title)
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
        server.stop()
