"""Screenshots for the README's walkthrough, taken by driving the real app in headless Chromium:
train from the Training panel, review a few mined negatives with the review panel's buttons, train
the next round, and capture the review queue and the before/after table.

    .venv/bin/python -m app.screenshots DATA --out docs/img

Runs in a scratch session (nothing is written under ``sessions/``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import viser

from factorydet_core.detection.model import DEFAULT_MODEL, DetectionModel
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.training.settings import LoopSettings

from .viewer import FactorydetApp

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--headless", "--no-sandbox", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # WebGL through ANGLE on EGL: on a machine without a GPU, Mesa's llvmpipe, still software on
    # the CPU but rendering the app's scene in about half the time of Chromium's own SwiftShader
    # (what --disable-gpu or no GL flag gives) and showing a scene change several times sooner.
    # Where Mesa's EGL is missing, Chromium falls back to SwiftShader; WEBGL_RENDERER_JS says
    # which one drew.
    "--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist",
]  # fmt: skip
"""Headless Chromium's flags, for the browser tests, the walkthrough and the screenshots."""

WEBGL_RENDERER_JS = """() => {
  const gl = document.createElement('canvas').getContext('webgl2');
  if (!gl) return null;
  const info = gl.getExtension('WEBGL_debug_renderer_info');
  return info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}"""
"""What renders the page's WebGL (``page.evaluate``): 'ANGLE (Mesa/X.org, llvmpipe ...)', ..."""


def wait_until(predicate, timeout: float, what: str, poll: float = 0.2) -> None:
    """Poll ``predicate`` every ``poll`` seconds until it holds; ``TimeoutError`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll)
    raise TimeoutError(f"timed out waiting for {what}")


_HIDE_WEBGL_NOTICE = """
for (const el of document.querySelectorAll('[class*="Notification-root"], [role="alert"]')) {
  if (el.innerText.includes('Software WebGL')) el.style.display = 'none';
}
"""
"""The headless browser renders WebGL in software and viser says so; the notice would cover the
screenshots' scene."""


def open_app_page(pw, app: FactorydetApp, width: int, height: int, init_script: str | None = None) -> tuple:
    """Headless Chromium on ``app``'s page, once it is connected: ``(browser, page, the page's
    ClientView)``; ``init_script`` runs in the page before the app's own scripts."""
    browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
    context = browser.new_context(viewport={"width": width, "height": height})
    if init_script is not None:
        context.add_init_script(init_script)
    page = context.new_page()
    page.goto(f"http://127.0.0.1:{app.server.get_port()}/")
    page.wait_for_selector("canvas[data-engine]", timeout=60_000)
    wait_until(lambda: app.clients, 60, "the browser")
    return browser, page, next(iter(app.clients.values()))


def take(data: str, out: str, epochs: int = 5, reviews: int = 6) -> list[Path]:
    from playwright.sync_api import sync_playwright

    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    dataset = open_dataset(data)
    with tempfile.TemporaryDirectory() as root:
        db = SessionDB(open_session("walkthrough", root), dataset)
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        model = DetectionModel.load(DEFAULT_MODEL) if DEFAULT_MODEL.is_file() else None
        app = FactorydetApp(
            server, dataset, model=model, model_name="shipped default", db=db,
            training=LoopSettings(epochs=epochs, rounds=0),
        )  # fmt: skip
        shots = []
        try:
            with sync_playwright() as pw:
                browser, page, view = open_app_page(pw, app, 1500, 1200)
                for folder in ("Display", "Detection layers", "Detections"):
                    # Fold the viewing panels so the labelling ones fit on the page.
                    title = page.get_by_text(folder, exact=True).first
                    if title.count():
                        title.click()
                page.get_by_text("Training", exact=True).first.click()
                page.get_by_role("button", name="Train", exact=True).click()
                wait_until(lambda: app.state.training_busy, 30, "training to start")
                wait_until(lambda: not app.state.training_busy, 3600, "the first training run")
                page.get_by_text("Training", exact=True).first.click()  # fold it again
                page.get_by_text("Labels", exact=True).first.click()  # fold: the queue fits
                page.get_by_role("button", name="Next [N]").click()
                wait_until(lambda: view.current_item_id is not None, 30, "the first queue item")
                time.sleep(3)  # the dimmed scene and the camera move reach the canvas
                page.evaluate(_HIDE_WEBGL_NOTICE)
                page.get_by_text("Review queue", exact=True).first.scroll_into_view_if_needed()
                shots.append(out_dir / "review_queue.png")
                page.screenshot(path=str(shots[-1]))
                for _ in range(reviews):
                    page.get_by_role("button", name="Background [B]").click()
                    time.sleep(0.5)
                page.get_by_text("Training", exact=True).first.click()
                page.get_by_role("button", name="Train", exact=True).click()
                wait_until(lambda: app.state.training_busy, 30, "training to start")
                wait_until(lambda: not app.state.training_busy, 3600, "the next round")
                page.get_by_text("Review queue", exact=True).first.click()  # fold it
                page.get_by_text("Frame", exact=True).first.click()  # fold: the table fits
                page.get_by_text("Before / after", exact=False).first.wait_for(timeout=30_000)
                time.sleep(2)
                page.evaluate(_HIDE_WEBGL_NOTICE)
                page.get_by_text("Before / after", exact=False).first.scroll_into_view_if_needed()
                shots.append(out_dir / "before_after.png")
                page.screenshot(path=str(shots[-1]))
                browser.close()
        finally:
            app.close()
            app.trainer.join(120)
            server.stop()
    return shots


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="a simulated data set folder (e.g. sessions/demo/data)")
    parser.add_argument("--out", default="docs/img")
    parser.add_argument("--epochs", type=int, default=5)
    args = parser.parse_args()
    for path in take(args.data, args.out, args.epochs):
        print(path)


if __name__ == "__main__":
    main()
