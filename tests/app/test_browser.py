"""The app in headless Chromium: controls present, frame navigation reaches the server, canvas drawn."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
import viser
from PIL import Image

from app.screenshots import WEBGL_RENDERER_JS
from app.viewer import FactorydetApp
from factorydet_core.io.dataset import open_dataset
from tests.app.polling import wait as _wait

pytestmark = pytest.mark.browser


@pytest.fixture
def app(small_dataset_dir):
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    # The ICP calibration has its own tests; here it would only slow the first result down.
    app = FactorydetApp(server, open_dataset(small_dataset_dir), calibrate=False)
    yield app
    app.close()
    server.stop()


@pytest.fixture
def page(app, browser):
    context = browser.new_context(viewport={"width": 1100, "height": 700})
    yield context.new_page()
    context.close()  # before server.stop(), which otherwise waits for the socket


def test_the_browser_draws_webgl_through_egl_not_swiftshader(browser):
    # Set-up, not the app: without Mesa's EGL Chromium falls back to SwiftShader, which renders the
    # scene about twice as slowly as Mesa's llvmpipe (here, no GPU), and every browser figure of
    # docs/labelling.md would move.
    context = browser.new_context()
    try:
        renderer = context.new_page().evaluate(WEBGL_RENDERER_JS)
    finally:
        context.close()
    assert renderer is not None and "SwiftShader" not in renderer, renderer


def _view(app):
    """The one connected browser's ``ClientView`` (its own view, scene and layers)."""
    assert _wait(lambda: len(app.views) == 1, 30), "the browser never connected"
    return app.views[0]


def _colourful_fraction(png: bytes) -> float:
    """Share of pixels with clearly saturated colour: points coloured by sensor, not the grey grid.

    Only the middle-left part of the canvas counts: the GUI panel (right), viser's notification
    (top left) and the axes gizmo (bottom left) float over the canvas and are colourful themselves.
    """
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    height, width = rgb.shape[:2]
    rgb = rgb[height // 4 : height - 80, 80 : int(width * 0.6)]
    saturation = rgb.max(axis=2) - rgb.min(axis=2)
    return float((saturation > 60).mean())


PROGRAMS_LINKED_JS = """
window.__programsLinked = 0;
for (const proto of [WebGL2RenderingContext.prototype, WebGLRenderingContext.prototype]) {
  const link = proto.linkProgram;
  proto.linkProgram = function (...args) { window.__programsLinked += 1; return link.apply(this, args); };
}
"""
"""Counts the shader programs the page links (a compile of a shader pair each)."""


def _settled(read, quiet: float = 1.0, timeout: float = 30.0):
    """``read()`` once it has stayed the same for ``quiet`` seconds."""
    value, since, start = read(), time.monotonic(), time.monotonic()
    while time.monotonic() - since < quiet and time.monotonic() - start < timeout:
        time.sleep(0.1)
        now = read()
        if now != value:
            value, since = now, time.monotonic()
    return value


def test_app_shows_controls_navigates_frames_and_draws(app, page):
    page.add_init_script(PROGRAMS_LINKED_JS)
    page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
    canvas = page.wait_for_selector("canvas[data-engine]", timeout=30_000)
    assert _wait(lambda: len(app.server.get_clients()) == 1, 30), "the browser never connected"
    view = _view(app)

    # The controls reach a new browser in messages sent after its connection is registered
    # (a fraction of a second later).
    page.get_by_role("button", name="Next frame").wait_for(timeout=30_000)
    for name in ("Next frame", "Previous frame"):
        assert page.get_by_role("button", name=name).count() == 1
    for label in ("Colour by", "Point size (m)", "Show boxes", "Hide above (m)"):
        # (the panels' controls arrive in the same stream of messages, some after the buttons)
        page.get_by_text(label, exact=True).first.wait_for(timeout=30_000)
        assert page.get_by_text(label, exact=True).count() >= 1
    page.get_by_text("frame 1 / 3", exact=False).wait_for(timeout=20_000)
    result = view.state.wait_for(lambda: view.state.pipeline_result, timeout=120)
    assert result is not None and _wait(lambda: view.layers.drawn == (result, 0), 120)
    assert _wait(lambda: _colourful_fraction(canvas.screenshot()) > 0.005, 30), "the 3D canvas stayed blank"
    linked = _settled(lambda: page.evaluate("window.__programsLinked"))

    page.get_by_role("button", name="Next frame").click()
    assert view.state.wait_for(lambda: view.state.frame_index == 1, timeout=20), (
        "the server never saw the click"
    )
    page.get_by_text("frame 2 / 3", exact=False).wait_for(timeout=20_000)

    # Software WebGL draws within seconds; poll until the points show up.
    assert _wait(lambda: view.layers.drawn == (view.state.pipeline_result, 1), 120)
    assert _wait(lambda: _colourful_fraction(canvas.screenshot()) > 0.005, 30), "the 3D canvas stayed blank"
    # The new frame's scan and boxes are drawn with the shaders compiled for the first (a compile
    # took up to a third of a second of the page's main thread under software WebGL).
    assert _settled(lambda: page.evaluate("window.__programsLinked")) == linked > 0

    # The measure is not fooled by the page around the points: hide them and it drops.
    view.scene.set_visible(False)
    view.state.set_layer("proposals", False)  # the orange proposal boxes are colourful too
    assert _wait(lambda: _colourful_fraction(canvas.screenshot()) < 0.001, 30), "hidden points still drawn"


def test_detection_layers_toggle_and_parameters_recompute(app, page):
    page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
    canvas = page.wait_for_selector("canvas[data-engine]", timeout=30_000)
    assert _wait(lambda: len(app.server.get_clients()) == 1, 30), "the browser never connected"
    view = _view(app)
    page.get_by_text("Proposal boxes", exact=True).first.wait_for(timeout=30_000)
    for label in (
        "Proposal boxes",
        "Patches (cut pursuit)",
        "Voxel size (m)",
        "Regularisation",
        "Merge threshold",
    ):
        assert page.get_by_text(label, exact=True).count() >= 1, label

    # The first frame's front half runs in the background; its status line reaches the browser.
    assert view.state.wait_for(lambda: view.state.pipeline_result is not None, timeout=120)
    page.get_by_text("proposals,", exact=False).first.wait_for(timeout=30_000)
    assert view.layers.nodes["proposals"].visible
    assert "patches" not in view.layers.nodes  # a hidden layer is sent when it is first shown

    # Toggle a layer from the browser: the state and the scene node follow.
    page.get_by_label("Patches (cut pursuit)").check()
    assert view.state.wait_for(lambda: view.state.layers["patches"], timeout=20), (
        "toggle never reached the server"
    )
    assert _wait(lambda: getattr(view.layers.nodes.get("patches"), "visible", False), 20)
    assert _wait(lambda: _colourful_fraction(canvas.screenshot()) > 0.005, 30), "patches not drawn"

    # Change a parameter from the browser (keyboard on the merge-threshold slider): the layers
    # recompute for the current frame with the new value, off the GUI thread.
    before = view.state.num_results
    old_threshold = view.state.params.segmentation.merge_threshold
    thumb = page.locator('[role=slider][aria-valuemin="0"][aria-valuemax="1"]')
    thumb.focus()
    thumb.press("ArrowRight")
    expected = round(old_threshold + 0.05, 6)
    assert view.state.wait_for(
        lambda: abs(view.state.params.segmentation.merge_threshold - expected) < 1e-6, timeout=20
    ), "the slider change never reached the server"
    assert view.state.wait_for(lambda: view.state.num_results > before, timeout=120), "no recompute"
    assert (
        view.state.pipeline_result_key[1].segmentation.merge_threshold
        == view.state.params.segmentation.merge_threshold
    )
    assert _wait(lambda: view.layers.drawn_result is view.state.pipeline_result, 30), "new result not drawn"


@pytest.fixture
def app_with_model(small_dataset_dir, tiny_model_path):
    from factorydet_core.detection.model import DetectionModel

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    model = DetectionModel.load(tiny_model_path)
    app = FactorydetApp(
        server, open_dataset(small_dataset_dir), calibrate=False, model=model, model_name="tiny"
    )
    yield app
    app.close()
    server.stop()


def test_detections_layer_and_score_slider(app_with_model, browser):
    app = app_with_model
    context = browser.new_context(viewport={"width": 1100, "height": 900})
    try:
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
        page.wait_for_selector("canvas[data-engine]", timeout=30_000)
        assert _wait(lambda: len(app.server.get_clients()) == 1, 30), "the browser never connected"
        view = _view(app)
        page.get_by_text("Score threshold", exact=True).first.wait_for(timeout=30_000)
        for label in ("Detections (after NMS)", "Show suppressed", "Score threshold", "NMS IoU"):
            assert page.get_by_text(label, exact=True).count() >= 1, label
        assert view.state.wait_for(lambda: view.state.detections is not None, timeout=120), "no detections"
        page.get_by_text("detections** shown", exact=False).or_(
            page.get_by_text("detections shown", exact=False)
        ).first.wait_for(timeout=30_000)
        before = int(view.state.detections.kept_mask.sum())
        text_before = page.get_by_text("suppressed by NMS", exact=False).first.inner_text()
        assert f"{before} detections" in text_before

        # Lower the score threshold from the browser: more candidates pass, so the count changes.
        # The panel re-renders while the frame's work finishes, which can take the focus off the
        # thumb between key presses on a loaded machine: press again (each press only lowers it).
        thumb = page.locator('[role=slider][aria-valuemin="0.05"][aria-valuemax="1"]')
        arrived = False
        for _ in range(3):
            thumb.focus()
            for _ in range(9):
                thumb.press("ArrowLeft")
            arrived = view.state.wait_for(lambda: view.state.score_threshold < 0.1, timeout=30)
            if arrived:
                break
        assert arrived, f"slider never arrived (score threshold {view.state.score_threshold})"
        after = int(view.state.detections.kept_mask.sum())
        assert after != before
        page.get_by_text(f"{after} detections", exact=False).first.wait_for(timeout=20_000)
        assert _wait(lambda: len(view.layers.shown_detection_ids) == after, 20), "scene not re-filtered"
        # The metrics panel has the frame's per-class table.
        assert view.state.metrics is not None and view.state.metrics["num_frames"] == 1
    finally:
        context.close()


def test_another_frames_boxes_are_hidden_the_moment_the_frame_changes(app_with_model, browser, monkeypatch):
    """A frame still being computed shows its scan with no boxes, never the last frame's
    detections and layers on its cloud; a click on it selects nothing of the other frame."""
    import threading
    import types

    from factorydet_core.detection import detector as detector_module

    app = app_with_model
    release = threading.Event()
    original = detector_module.Detector.propose

    def held(self, frame, *args, **kwargs):
        if frame.name == "frame_00002":
            release.wait(120)
        return original(self, frame, *args, **kwargs)

    monkeypatch.setattr(detector_module.Detector, "propose", held)
    context = browser.new_context(viewport={"width": 900, "height": 700})
    try:
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
        page.wait_for_selector("canvas[data-engine]", timeout=30_000)
        view = _view(app)
        assert _wait(
            lambda: view.layers.shown_detections is not None and view.layers.detection_source[1] == 0, 120
        )
        view.state.set_layer("segments", True)
        assert _wait(lambda: "segments" in view.layers.nodes, 20)
        assert view.layers.nodes["segments"].visible
        view.state.set_frame(2)  # not computed ahead (the neighbours of frame 0 are 0 and 1)
        # Hidden with frame 2's scan, while frame 0's are still the result.
        assert _wait(
            lambda: (
                view._drawn is not None
                and view._drawn[0] == 2
                and view.layers.shown_detections is None
                and not view.layers.detection_nodes
                and not view.layers.nodes["segments"].visible
            ),
            20,
        )
        assert view.state.detection_frame_index == 0 and view.state.detections is not None
        # A click straight down onto a point of frame 0's result selects nothing of it.
        point = view.layers.drawn_result.cloud.points[0].astype(np.float64)
        event = types.SimpleNamespace(
            ray_origin=point + (0.0, 0.0, 5.0), ray_direction=np.array([0.0, 0.0, -1.0])
        )
        app._click(view, event, False)
        assert "still being computed" in view.state.selection_markdown
        assert not view.selected_patch_ids
        release.set()
        assert _wait(lambda: view.layers.detection_source[1] == 2 and view.layers.drawn_frame_index == 2, 120)
        assert view.layers.nodes["segments"].visible
    finally:
        release.set()
        context.close()


def test_each_browser_has_its_own_frame_display_and_thresholds(app_with_model, browser):
    """Two browsers on one app: a frame change, a display setting and a threshold in one leave the
    other's as they were; the model and the front half's parameters are shared."""
    app = app_with_model
    contexts = [browser.new_context(viewport={"width": 1000, "height": 700}) for _ in range(2)]
    try:
        pages = [context.new_page() for context in contexts]
        for k, page in enumerate(pages):
            page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
            page.wait_for_selector("canvas[data-engine]", timeout=30_000)
            assert _wait(lambda k=k: len(app.views) == k + 1, 30), "a browser never connected"
            page.get_by_role("button", name="Next frame").wait_for(timeout=30_000)
        first, second = (app.client_view(c) for c in sorted(app.clients))
        assert first.state is not second.state

        pages[0].get_by_role("button", name="Next frame").click()
        assert _wait(lambda: first.state.frame_index == 1, 20), "the click never reached the server"
        pages[0].get_by_text("frame 2 / 3", exact=False).wait_for(timeout=20_000)
        pages[1].get_by_text("frame 1 / 3", exact=False).wait_for(timeout=20_000)
        assert second.state.frame_index == 0
        # Each browser's scene shows its own frame's result.
        assert _wait(
            lambda: first.layers.drawn_frame_index == 1 and first.layers.drawn_result is not None, 120
        )
        assert _wait(
            lambda: second.layers.drawn_frame_index == 0 and second.layers.drawn_result is not None, 120
        )

        for view in (first, second):  # (a hidden layer is not sent: these two are shown)
            view.state.set_layer("merged", True)
            view.state.set_layer("patches", True)
        assert _wait(lambda: all("patches" in view.layers.nodes for view in (first, second)), 20)
        first.state.set_display(point_size=0.1)
        first.state.set_detection_filter(score_threshold=0.05)
        assert second.state.point_size == 0.04 and second.state.score_threshold != 0.05
        assert _wait(lambda: first.layers.nodes["merged"].point_size == 0.1, 20)
        assert second.layers.nodes["merged"].point_size == 0.04
        # A budget of points drawn redraws that browser's scan and layers alone.
        shown_before = second.scene.num_points_shown
        first.state.set_display(points_drawn=1000)
        assert _wait(lambda: 0 < first.scene.num_points_shown <= 1000, 20)
        assert _wait(lambda: len(first.layers.nodes["patches"].points) <= 1000, 20)
        assert second.scene.num_points_shown == shown_before > 1000
        # The floor grid is a display setting of each browser too.
        first.state.set_display(show_grid=False)
        assert _wait(lambda: not first.scene.grid_visible, 20)
        second.redraw()
        assert second.state.show_grid and second.scene.grid_visible
    finally:
        for context in contexts:
            context.close()
