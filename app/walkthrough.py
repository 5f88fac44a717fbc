"""``bench walkthrough``: a labeller's edits timed as the browser sees them, by driving the real app
in headless Chromium with the keyboard (and a click to select).

    .venv/bin/python -m app.walkthrough DATA [--repeats 5] [--out docs/bench/walkthrough.json]
        [--readme docs/labelling.md [--readme-block walkthrough]] [--no-retrain] [--points-drawn N]

Each step is a key press (or a click), timed until the server has stored its effect (the label's new version,
polled from the database; for a frame change, its detections drawn into the scene) and until the
page shows it (the selected label's new version in the Labels panel, the new frame number). The
record also gives what one scene change costs this browser to render, and how many renders it
causes (``_render_cost``): in headless Chromium that is software WebGL, which a browser with a GPU
does not pay. Runs in a scratch session on the data set (nothing is written under ``sessions/``),
with the shipped model, label once on (edits reach every frame that shows the object). Prints one
JSON object.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import statistics
import sys
import tempfile
import time
from collections.abc import Callable

import numpy as np
import viser

from factorydet_core.detection.model import DEFAULT_MODEL, DetectionModel
from factorydet_core.evaluation.bench_tables import update_readme
from factorydet_core.evaluation.diagnostics import ray_box_distances
from factorydet_core.evaluation.records import machine_info
from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.editing import BOX_VIEWS, Suggestion, camera_view_of_box
from factorydet_core.session.store import PRELABEL_ORIGIN, VERDICTS, SessionDB, open_session
from factorydet_core.session.world import MOVING_CLASSES

from .panels.training_panel import TrainingPanel
from .screenshots import WEBGL_RENDERER_JS, open_app_page, wait_until
from .viewer import FactorydetApp

TARGET_EDIT_MS = 200.0
"""Issue target: an edit's round trip in the browser."""
TARGET_FRAME_MS = 1000.0
"""Issue target: a cached frame change with its detections."""
TARGET_VERDICT_MS = 500.0
"""Issue target: the review queue's next item shown after a verdict."""
TARGET_NEXT_ROUND_S = 180.0
"""Issue target: a next-round retrain from the app on the demo."""
NUM_VERDICTS = 20
"""Review verdicts given with the keyboard, each timed."""
VERDICT_KEY_CHOICES = "box"
"""The review panel's verdict keys: background, object (of the item's class), skip."""
VERDICT_KEYS = "bxbbx"
"""The verdicts' keys, in turn: background and skip (the labels stay as they are, and so does the
box quality regressor's fit); ``--verdict-keys bobxo`` answers some Object too (labels change)."""


def _wait(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    wait_until(predicate, timeout, what, poll=0.005)  # finely: it times what it waits for


def _timed(view, action: Callable[[], None], stored: Callable[[], bool], shown: Shows) -> tuple[float, ...]:
    """Milliseconds from ``action`` (a key press) until the server has ``stored`` its effect
    (polled) and until the page has ``shown`` it (polled by the test driver), the server's own
    share: from receiving the key to having sent the browser ``view`` everything it changed (the
    end of its batch of updates), and in the page's own clock, from the key until its text changed
    and until that change was drawn (``Shows.in_page``). The rest is the browser's: delivering the
    key, rendering, showing."""
    shown.watch()
    start = time.perf_counter()
    action()
    _wait(stored, 60, "the edit stored")
    stored_at = time.perf_counter()
    _wait(lambda: not view.sending and view.key_received_at > start, 60, "the updates sent")
    sent_at = max(view.sent_at, view.key_received_at)
    shown()
    end = time.perf_counter()
    server = sent_at - view.key_received_at
    seen, painted = shown.in_page()
    return 1000.0 * (stored_at - start), 1000.0 * server, 1000.0 * (end - start), seen, painted


VISER_HEARTBEAT_MS = 1000.0
"""viser's client renders the scene once a second when idle: a page never settles for longer."""
TIMES = ("stored", "server", "shown", "page_seen", "page")
"""A step's times (``_timed``): stored, the server's share, shown (polled), and in the page's own
clock the text changed and the change drawn."""
FEW_POINTS = 1_000
"""Points drawn while the walkthrough times a render of the scene with (almost) no scan."""
BURST_GAP_MS = 20.0
"""Draw calls less than this far apart belong to one render of the scene."""

DRAW_LOG = """
window.__factorydetDraws = [];
for (const proto of [WebGL2RenderingContext.prototype, WebGLRenderingContext.prototype]) {
  for (const name of ['drawArrays', 'drawElements', 'drawArraysInstanced', 'drawElementsInstanced']) {
    const original = proto[name];
    if (!original) continue;
    proto[name] = function (...args) {
      window.__factorydetDraws.push(performance.now());
      return original.apply(this, args);
    };
  }
}
"""
"""An init script that logs the time of every WebGL draw call (a render of the scene is a burst)."""

PAGE_CLOCK = """
window.__factorydetInput = null;
window.__factorydetSettleMs = 0;
window.__factorydetSettled = () => new Promise((resolve) => {
  const start = performance.now();
  const check = () => {
    const draws = window.__factorydetDraws || [];
    const idle = performance.now() - (draws.length ? draws[draws.length - 1] : -Infinity);
    if (idle >= window.__factorydetSettleMs || performance.now() - start > 5000) resolve(idle);
    else setTimeout(check, Math.max(5, window.__factorydetSettleMs - idle));
  };
  check();
});
for (const type of ['keydown', 'pointerdown']) {
  window.addEventListener(type, (event) => { window.__factorydetInput = event.timeStamp; }, true);
}
window.__factorydetWatch = (pattern, exclude) => new Promise((resolve) => {
  const regex = new RegExp(pattern, 'g');
  const shows = () => {
    for (const match of (document.body ? document.body.innerText : '').matchAll(regex)) {
      if (match.length < 2 || !exclude.includes(Number(match[1]))) return true;
    }
    return false;
  };
  if (shows()) throw new Error('the page shows ' + pattern + ' before the key');
  const observer = new MutationObserver(() => {
    if (window.__factorydetInput === null || !shows()) return;
    observer.disconnect();
    const seen = performance.now();
    const input = window.__factorydetInput;
    // The frame that paints the change starts at the first animation frame; the second starts
    // once that one is drawn.
    requestAnimationFrame(() => requestAnimationFrame(() => resolve(
      {input: input, seen: seen, painted: performance.now()})));
  });
  observer.observe(document.body, {subtree: true, childList: true, characterData: true, attributes: true});
});
"""
"""An init script that times, in the page's own clock, a key press or click (the input event's
time) until the page's text shows its effect (``Shows``: the DOM mutation, then two animation
frames, the first of which draws it): what a person at this browser waits, without the test
driver's polling (Playwright checks a locator at growing intervals, 20, 50, 100, 100 and 500 ms,
which adds up to the next check's time to every wait). With ``__factorydetSettleMs`` set, a
watch starts once the page has drawn nothing for that long (``DRAW_LOG``'s draw calls; at most
5 s): viser keeps rendering for a quarter of a second after every scene change, and a key pressed
meanwhile waits for the render in flight."""


class Shows:
    """What the page shows once a step is done: ``text`` (polled with Playwright, as a person
    reads it) and ``pattern``, a regular expression of it the page watches for in its own clock
    (``PAGE_CLOCK``; with a group, a number ``exclude`` leaves out: what was shown before)."""

    def __init__(self, page, text: str | Callable[[], str], pattern: str, exclude=()) -> None:
        self.page, self.text, self.pattern, self.exclude = page, text, pattern, [int(n) for n in exclude]

    def watch(self) -> None:
        """Start watching, before the key (once the page has settled, with a settle time set)."""
        self.page.evaluate(
            "async ([pattern, exclude]) => { await window.__factorydetSettled();"
            " window.__factorydetInput = null;"
            " window.__factorydetShown = window.__factorydetWatch(pattern, exclude); }",
            [self.pattern, self.exclude],
        )

    def __call__(self) -> None:
        text = self.text() if callable(self.text) else self.text
        self.page.get_by_text(text, exact=False).first.wait_for(timeout=30_000)

    def in_page(self, timeout_ms: float = 30_000.0) -> tuple[float, float]:
        """Milliseconds from the key (or click) until the page's text changed, and until the frame
        after it began (the change drawn), in the page's clock. Raises (the page's error) when
        the pattern has not shown within ``timeout_ms`` of this call: the polled text showed, so a
        pattern that does not match it is the walkthrough's mistake."""
        times = self.page.evaluate(
            "([pattern, ms]) => Promise.race([window.__factorydetShown, new Promise((_, reject) =>"
            " setTimeout(() => reject(new Error(`the page never matched ${pattern}`)), ms))])",
            [self.pattern, float(timeout_ms)],
        )
        return times["seen"] - times["input"], times["painted"] - times["input"]


def shows_text(page, text: str) -> Shows:
    """``Shows`` of a text known before the key."""
    return Shows(page, text, re.escape(text))


def _scene_render_ms(page, view, seconds: float = 5.0) -> float | None:
    """Median milliseconds between renders of the app's scene while the camera moves (a render
    per move asked for): what one render costs this browser (software WebGL headless)."""
    camera = view.client.camera
    position = tuple(camera.position)
    page.evaluate("window.__factorydetDraws = []")
    start, k = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        camera.position = (position[0] + 0.01 * (k % 2), position[1], position[2])
        k += 1
        time.sleep(0.05)
    camera.position = position
    renders = _render_starts(page.evaluate("window.__factorydetDraws"))
    return round(float(np.median(np.diff(renders))), 1) if len(renders) > 2 else None


def _shadow_cost(page, view, pairs: int = 6, seconds: float = 4.0) -> dict:
    """One render of the scene with viser's default shadows on and with them off (the app's
    scene), in turns in the same page, the order alternating, after 12 s of camera moves that let
    viser's adaptive resolution settle: what the shadows the app turns off would cost this
    browser. Leaves them off, and the page settled. Returns ``scene_render_ms_shadows_on`` and
    ``_off`` (``pairs`` turns each, ms, None for a turn with too few renders to time), their
    medians, and the median and count of the paired differences (on minus off) of the pairs
    timed on both sides (None without one)."""
    for _ in range(3):
        _scene_render_ms(page, view, seconds)
    on, off = [], []
    for k in range(pairs):
        for shadows in (True, False) if k % 2 == 0 else (False, True):
            view.client.scene.configure_default_lights(enabled=True, cast_shadow=shadows)
            time.sleep(1.5)
            (on if shadows else off).append(_scene_render_ms(page, view, seconds))
    view.client.scene.configure_default_lights(enabled=True, cast_shadow=False)
    time.sleep(1.5)  # the lit materials made again without shadows, before the first key is timed
    _scene_render_ms(page, view, 1.0)
    differences = [a - b for a, b in zip(on, off) if a is not None and b is not None]

    def median(values: list) -> float | None:
        timed = [value for value in values if value is not None]
        return round(statistics.median(timed), 1) if timed else None

    return {
        "scene_render_ms_shadows_on": on,
        "scene_render_ms_shadows_off": off,
        "shadows_on_median_ms": median(on),
        "shadows_off_median_ms": median(off),
        "shadows_paired_difference_median_ms": median(differences),
        "shadows_pairs": len(differences),
        "shadows_slower_pairs": sum(d > 0 for d in differences),
    }


def _render_starts(draws: list[float]) -> list[float]:
    """The page times at which renders of the scene began: the first draw call of each burst
    (``DRAW_LOG``'s times, in order; a render's calls come less than ``BURST_GAP_MS`` apart)."""
    return [t for k, t in enumerate(draws) if k == 0 or t - draws[k - 1] > BURST_GAP_MS]


def _renders_since(page, since_ms: float, window_ms: float) -> int:
    """How many renders of the scene the page began in the ``window_ms`` after page time
    ``since_ms``."""
    starts = _render_starts(page.evaluate("window.__factorydetDraws"))
    return sum(since_ms <= t < since_ms + window_ms for t in starts)


def _render_cost(page, view, repeats: int = 5, window_s: float = 1.0) -> dict:
    """What one scene change costs this browser: a notification's round trip alone, and with a
    small scene change in the same update (the page renders the whole scene again before it shows
    the notification; in headless Chromium that is software WebGL). Also how many renders the
    page begins in the ``window_s`` after each (viser renders on a 1 s heartbeat when idle, and
    for a quarter of a second after each scene change), and in as long a time with nothing sent."""
    alone, with_scene = [], []
    renders: dict[str, list[int]] = {"idle": [], "alone": [], "scene": []}
    for k in range(repeats):
        page.evaluate("window.__factorydetDraws = []")
        since = page.evaluate("performance.now()")
        time.sleep(window_s)
        renders["idle"].append(_renders_since(page, since, 1000.0 * window_s))
        for scene_change, into in ((False, alone), (True, with_scene)):
            page.evaluate("window.__factorydetDraws = []")
            since = page.evaluate("performance.now()")
            start = time.perf_counter()
            if scene_change:
                view.client.scene.add_box(
                    "/client/probe",
                    color=(0, 0, 0),
                    dimensions=(0.01, 0.01, 0.01),
                    position=(float(k), 0.0, -5.0),
                )
            view.client.add_notification("probe", f"probe {k} {scene_change}", auto_close_seconds=0.5)
            page.get_by_text(f"probe {k} {scene_change}", exact=False).first.wait_for(timeout=30_000)
            into.append(1000.0 * (time.perf_counter() - start))
            time.sleep(max(0.0, window_s - (time.perf_counter() - start)))
            renders["scene" if scene_change else "alone"].append(
                _renders_since(page, since, 1000.0 * window_s)
            )
            time.sleep(0.3)
    view.client.scene.remove_by_name("/client/probe")
    return {
        "notification_alone_median_ms": round(statistics.median(alone), 1),
        "with_a_scene_change_median_ms": round(statistics.median(with_scene), 1),
        "render_window_s": window_s,
        "renders_idle_median": float(statistics.median(renders["idle"])),
        "renders_after_a_notification_median": float(statistics.median(renders["alone"])),
        "renders_after_a_scene_change_median": float(statistics.median(renders["scene"])),
        "renders": renders,
    }


def _select_by_click(page, view, label_id: int, note, shows, progress=None) -> None:
    """Select the label ``label_id`` (selected now) again by a click, timed: the camera on one of
    its box views (``editing.BOX_VIEWS``: the box in the middle of the page's canvas), Escape, then
    a click there; the camera as it was afterwards."""
    # The first of the box views whose line of sight meets this label before any other (an
    # object stacked on it would take the click from above).
    boxes, _, label_ids = view.state.db.frame_boxes(view.state.frame_index)
    label_box = view.state.db.label(label_id).box
    for box_view in BOX_VIEWS:
        eye, centre, _ = camera_view_of_box(label_box, box_view)
        distances = ray_box_distances(eye, (centre - eye) / np.linalg.norm(centre - eye), boxes)
        if label_ids[int(np.argmin(distances))] == label_id:
            break
    else:
        if progress is not None:
            progress(f"label {label_id}: every box view of it is blocked by another box, no click this round")
        return
    camera = view.client.camera
    position, look_at, up = tuple(camera.position), tuple(camera.look_at), tuple(camera.up_direction)
    reported = camera.update_timestamp
    view.view_selected(box_view)
    try:
        page.keyboard.press("Escape")
        _wait(lambda: view.selected_label_id is None, 30, "nothing selected")
        page.get_by_text(f"Label #{label_id}:", exact=False).first.wait_for(state="hidden", timeout=30_000)
        # A click is cast from the camera the page has: the page must have taken the new view (the
        # server's camera changes when it is set; the timestamp only when the page reports back).
        _wait(
            lambda: camera.update_timestamp > reported and np.allclose(camera.position, eye, atol=0.01),
            30,
            "the page's camera on the label",
        )
        time.sleep(1.0)  # the page draws the new view before the click
        size = page.locator("canvas[data-engine]").bounding_box()
        x, y = size["x"] + size["width"] / 2, size["y"] + size["height"] / 2
        note(
            "select a label (click)",
            _timed(
                view,
                # (the mouse itself: a locator's click first waits for the canvas to hold still
                # over two animation frames, renders a key press does not wait for)
                lambda: page.mouse.click(x, y),
                lambda: view.selected_label_id == label_id,
                shows(f"Label #{label_id}:"),
            ),
        )
    finally:
        view.set_camera(position, look_at, up)
    time.sleep(1.0)  # the page draws the view as it was before the next key


def _prelabels(app, page, view, note, shows, open_folder: bool = True) -> None:
    """Pre-label the shown frame (M) and confirm the first pre-label (Enter), each timed; the
    frame and the camera as they were afterwards (Confirm moves on to the next pre-label and puts
    the camera on it, maybe in another frame). ``open_folder``: open the Pre-labels folder first
    (its count is what the page shows). A frame pre-labelled already (the rounds went round the
    data set) is left as it is: M would add nothing there."""
    db = app.state.db
    frame_index = view.state.frame_index

    def prelabelled() -> bool:  # (one frame's labels: polled while M is timed)
        return any(lab.origin == PRELABEL_ORIGIN for lab in db.labels(frame_index))

    if prelabelled():
        return
    camera = view.client.camera
    position, look_at = tuple(camera.position), tuple(camera.look_at)
    if open_folder:
        page.get_by_text("Pre-labels", exact=True).first.click()
    page.locator("canvas[data-engine]").focus()
    note(
        "pre-label the frame (M)",
        _timed(
            view,
            lambda: page.keyboard.press("m"),
            prelabelled,  # (the frame had no pre-label before)
            Shows(
                page,
                lambda: f"{len(db.unreviewed_labels())} pre-label(s) wait",
                r"(\d+) pre-label\(s\) wait",
                exclude=[len(db.unreviewed_labels())],
            ),
        ),
    )
    unreviewed = db.unreviewed_labels()
    num_waiting = len(unreviewed)
    # (the frame's own, the model's most confident first: the app selects the first it added)
    waiting = [lab for lab in unreviewed if lab.frame_index == frame_index]
    _wait(lambda: view.selected_label_id == waiting[0].id, 30, "the first pre-label selected")
    note(
        "confirm a pre-label (Enter)",
        _timed(
            view,
            lambda: page.keyboard.press("Enter"),
            lambda: db.label(waiting[0].id).reviewed,
            shows(f"{num_waiting - 1} pre-label(s) wait" if num_waiting > 1 else "No pre-label waits"),
        ),
    )
    if view.state.frame_index != frame_index:
        view.state.set_frame(frame_index)
        _wait(lambda: view.layers.detection_source[1] == frame_index, 600, "the frame shown again")
    view.set_camera(position, look_at, tuple(camera.up_direction))
    time.sleep(1.0)  # the page draws the view as it was before the next key


def _train_from_the_page(app, page, timeout: float) -> float:
    """Click Train (the panel's mode: next round, a full run in a session without one) and wait
    until the page shows the run done and its before/after table; returns the seconds."""
    runs = len(app.state.db.training_runs())
    start = time.perf_counter()
    page.get_by_role("button", name="Train", exact=True).click()
    _wait(
        lambda: len(app.state.db.training_runs()) > runs and not app.state.training_busy, timeout, "the run"
    )
    if "done" not in app.state.training_status:
        raise RuntimeError(f"the retrain did not finish: {app.state.training_status}")
    page.get_by_text("done:", exact=False).first.wait_for(timeout=60_000)
    page.get_by_text("Before / after", exact=False).first.wait_for(timeout=60_000)
    return time.perf_counter() - start


def _process_tree(pid: int) -> list[int]:
    """``pid`` and every process below it (Linux ``/proc``; empty where it is missing)."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    found = [pid]
    for task in tasks:
        try:
            children = open(f"/proc/{pid}/task/{task}/children").read().split()
        except OSError:
            continue
        for child in children:
            found += _process_tree(int(child))
    return found


def _cpu_seconds(pids: list[int]) -> float:
    """User and system CPU seconds the processes have used (those gone count 0)."""
    total = 0.0
    for pid in pids:
        try:
            fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _browser_cores(seconds: float = 10.0) -> float | None:
    """Cores the browser (this process's child processes: Playwright's driver and Chromium) uses
    over ``seconds`` with nothing sent to it; ``None`` where ``/proc`` cannot tell."""
    children = _process_tree(os.getpid())[1:]
    if not children:
        return None
    start, before = time.perf_counter(), _cpu_seconds(children)
    time.sleep(seconds)
    return round((_cpu_seconds(children) - before) / (time.perf_counter() - start), 2)


def _num_answered(db) -> int:
    """The latest run's queue items with a verdict, skips included: each verdict given on a
    pending item adds one or more (its place's items)."""
    progress = db.review_progress()
    return sum(progress[verdict] for verdict in VERDICTS)


def check_verdict_keys(keys: str) -> str:
    """``keys`` if every one is a verdict key (``VERDICT_KEY_CHOICES``), else ``ValueError``."""
    if not keys or set(keys) - set(VERDICT_KEY_CHOICES):
        raise ValueError(f"verdict keys must be some of {', '.join(VERDICT_KEY_CHOICES)}, got {keys!r}")
    return keys


def verdict_step(keys: str) -> str:
    """The step's name for review verdicts given with ``keys``: ``review verdict (B / X)``."""
    return "review verdict (" + " / ".join(sorted(set(keys.upper()))) + ")"


def _retrain_and_review(app, page, view, note, shows, progress, verdict_keys: str = VERDICT_KEYS) -> dict:
    """The loop the app exists for, from the page: Train (a full run first, in a session without
    one), ``NUM_VERDICTS`` review verdicts with the keyboard (``verdict_keys`` in turn), each timed,
    then Train again (a next round) until its before/after table shows."""
    db = app.state.db
    out = {"browser_cores_idle": _browser_cores()}
    page.get_by_text("Training", exact=True).first.click()  # the folder starts collapsed
    time.sleep(1.0)  # (opened)
    # What the browser spends with the Training panel open, its bar still (as the app has it) and
    # animated (as it once was): cores a run shown there competes for on the same machine.
    out["browser_cores_training_open"] = _browser_cores()
    (panel,) = [p for p in view.view_panels if isinstance(p, TrainingPanel)]
    panel.progress.animated = True
    time.sleep(1.0)
    out["browser_cores_training_open_animated_bar"] = _browser_cores()
    panel.progress.animated = False
    if not db.training_runs():
        out["full_run_shown_s"] = round(_train_from_the_page(app, page, 3600), 1)
        if progress is not None:
            progress(f"full run from the page: {out['full_run_shown_s']:.0f} s")
    canvas = page.locator("canvas[data-engine]")
    canvas.focus()
    page.keyboard.press("n")
    _wait(lambda: view.current_item_id is not None, 60, "the first queue item")
    for key in itertools.islice(itertools.cycle(verdict_keys), NUM_VERDICTS):
        _wait(lambda: app.worker.idle, 600, "the frames ahead")
        item = view.current_item_id
        num_answered = _num_answered(db)

        def judged(num_answered=num_answered) -> bool:
            # Counted in SQL: polled every few milliseconds in the app's own process, reading
            # the whole queue would take the server's time from the verdict it times.
            return _num_answered(db) > num_answered

        def next_item(item=item) -> str:
            _wait(lambda: view.current_item_id not in (None, item), 30, "the next queue item")
            return f"(#{view.current_item_id}, frame"

        next_item_shown = Shows(page, next_item, r"\(#(\d+), frame", exclude=[item])
        note(
            verdict_step(verdict_keys),
            _timed(view, lambda key=key: page.keyboard.press(key), judged, next_item_shown),
        )
    out["next_round_shown_s"] = round(_train_from_the_page(app, page, 3600), 1)
    if progress is not None:
        progress(f"next round from the page: {out['next_round_shown_s']:.0f} s")
    return out


def run(
    data: str,
    repeats: int = 5,
    progress: Callable[[str], None] | None = None,
    retrain: bool = True,
    points_drawn: int | None = None,
    verdict_keys: str = VERDICT_KEYS,
    shadow_cost: bool = False,
    show_grid: bool = True,
    settle_ms: float = 0.0,
) -> dict:
    """Drive the app through the steps ``repeats`` times; returns the record. Without ``retrain``
    the review verdicts and the retrains are left out (minutes instead of a quarter of an hour);
    ``points_drawn``: the Display panel's "Points drawn" (None: all); ``verdict_keys``: the review
    verdicts' keys, in turn; ``shadow_cost``: also time a render with viser's default shadows on
    and off (``_shadow_cost``, a minute and a half); ``show_grid``: the Display panel's "Floor
    grid"; ``settle_ms``: press each timed key once the page has drawn nothing for this long (a
    labeller who looks at each edit before the next key; 0: as soon as the last step showed)."""
    check_verdict_keys(verdict_keys)
    if not 0 <= settle_ms < VISER_HEARTBEAT_MS:
        raise ValueError(f"settle_ms must lie in [0, {VISER_HEARTBEAT_MS:.0f}), got {settle_ms!r}")
    from playwright.sync_api import sync_playwright

    dataset = open_dataset(data)
    steps: dict[str, dict[str, list[float]]] = {}
    render: dict = {}
    retrained: dict = {}

    def note(step: str, times: tuple[float, ...]) -> None:
        record = steps.setdefault(step, {name: [] for name in TIMES})
        for name, value in zip(TIMES, times):
            record[name].append(round(value, 1))
        if progress is not None:
            progress(
                f"{step}: stored after {times[0]:.0f} ms, the server's share {times[1]:.0f} ms,"
                f" shown after {times[2]:.0f} ms (polled), drawn after {times[4]:.0f} ms (the page's clock)"
            )

    with tempfile.TemporaryDirectory() as root:
        db = SessionDB(open_session("walkthrough", root), dataset)
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        model = DetectionModel.load(DEFAULT_MODEL) if DEFAULT_MODEL.is_file() else None
        app = FactorydetApp(server, dataset, model=model, model_name="shipped default", db=db)
        try:
            with sync_playwright() as pw:
                browser, page, view = open_app_page(pw, app, 1400, 1400, init_script=DRAW_LOG + PAGE_CLOCK)
                webgl_renderer = page.evaluate(WEBGL_RENDERER_JS)
                page.evaluate("ms => { window.__factorydetSettleMs = ms; }", float(settle_ms))
                _wait(lambda: app.state.world is not None, 600, "the frames placed in one world frame")
                _wait(lambda: view.layers.detection_source[0] is not None, 600, "the first detections")
                if points_drawn is not None:
                    view.state.set_display(points_drawn=points_drawn)
                    _wait(
                        lambda: 0 < view.scene.num_points_shown <= points_drawn,
                        60,
                        "the scan drawn with fewer points",
                    )
                if not show_grid:
                    view.state.set_display(show_grid=False)
                    _wait(lambda: not view.scene.grid_visible, 60, "the floor grid hidden")
                points_shown = view.scene.num_points_shown
                canvas = page.locator("canvas[data-engine]")
                canvas.click(position={"x": 5, "y": 5})  # keys go to the page, not a panel
                _wait(lambda: app.worker.idle, 600, "the frames ahead")
                render.update(_render_cost(page, view))
                render["scene_render_ms"] = _scene_render_ms(page, view)
                if points_shown > FEW_POINTS:
                    # The same with a handful of points: what a render costs this browser whatever
                    # the scan (the boxes, the grid, the page), then the scan as it was.
                    view.state.set_display(points_drawn=FEW_POINTS)
                    # (the scan had more: this holds only once the smaller one is drawn)
                    _wait(lambda: 0 < view.scene.num_points_shown <= FEW_POINTS, 60, "a handful of points")
                    time.sleep(1.0)  # the page takes the smaller scan in before the camera moves
                    render["few_points"] = FEW_POINTS
                    render["scene_render_ms_few_points"] = _scene_render_ms(page, view)
                    view.state.set_display(points_drawn=points_drawn)
                    _wait(lambda: view.scene.num_points_shown == points_shown, 60, "the scan drawn again")
                    time.sleep(1.0)  # ... and the whole scan again before the first key
                if shadow_cost:
                    render["shadows"] = _shadow_cost(page, view)

                def shows(text: str) -> Shows:
                    return shows_text(page, text)

                for k in range(repeats):
                    frame_index = view.state.frame_index
                    label = next(  # an object that stands still: its edits reach every frame showing it
                        lab
                        for lab in db.labels(frame_index)
                        if lab.instance_id is not None
                        and lab.class_name not in MOVING_CLASSES
                        and lab.reviewed  # (not a pre-label of an earlier round: an edit confirms it)
                    )
                    view.select_label(label.id)
                    page.get_by_text(f"Label #{label.id}:", exact=False).first.wait_for(timeout=30_000)
                    # Timed once the frames ahead are computed: on two cores an edit would share
                    # them with that work.
                    _wait(lambda: app.worker.idle, 600, "the frames ahead")
                    version = label.version
                    for step, key in (
                        ("nudge (shift+I)", "Shift+I"),
                        ("undo (Z)", "z"),
                        ("redo (Y)", "y"),
                        ("set class (C)", "c"),
                    ):
                        if key == "c":
                            name = "cone" if db.label(label.id).class_name != "cone" else "barrel"
                            page.keyboard.press(str(dataset.class_names.index(name) + 1))
                            _wait(lambda name=name: view.object_class == name, 30, "the class key")
                        version += 1
                        note(
                            step,
                            _timed(
                                view,
                                lambda key=key: page.keyboard.press(key),
                                lambda version=version, label_id=label.id: (
                                    db.label(label_id).version >= version
                                ),
                                shows(f"(version {version})"),
                            ),
                        )
                    _select_by_click(page, view, label.id, note, shows, progress)
                    # The model's box for an object, accepted: the new label is selected in the page.
                    box = tuple(float(v) for v in np.asarray(label.box) + [3.0, 3.0, 0, 0, 0, 0, 0])
                    view.suggest(frame_index, Suggestion(box, "box", 0.9, 1))
                    before = {lab.id for lab in db.labels(frame_index)}

                    def new_ids(frame_index: int = frame_index, before: set = before) -> set:
                        return {lab.id for lab in db.labels(frame_index)} - before

                    accepted = Shows(
                        page,
                        lambda new_ids=new_ids: f"Label #{min(new_ids())}:",
                        r"Label #(\d+):",
                        exclude=before,
                    )

                    note(
                        "accept suggested box (G)",
                        _timed(
                            view,
                            lambda: page.keyboard.press("g"),
                            lambda new_ids=new_ids: bool(new_ids()),
                            accepted,
                        ),
                    )
                    _prelabels(app, page, view, note, shows, open_folder=k == 0)
                    # The next frame, computed ahead while this one was shown.
                    target = frame_index + 1
                    if target >= dataset.num_frames:
                        view.state.set_frame(0)
                        continue
                    _wait(
                        lambda t=target: t in app.worker.cached_frames(view.state),
                        600,
                        "the next frame ahead",
                    )
                    note(
                        "frame change with its detections (PageDown)",
                        _timed(
                            view,
                            lambda: page.keyboard.press("PageDown"),
                            lambda t=target: view.layers.detection_source[1] == t,
                            shows(f"{target + 1} / {dataset.num_frames}"),
                        ),
                    )
                    if progress is not None:
                        progress(f"round {k + 1} of {repeats} done")
                if retrain:
                    retrained.update(
                        _retrain_and_review(app, page, view, note, shows, progress, verdict_keys)
                    )
                browser.close()
        finally:
            app.close()
            server.stop()
    return {
        "benchmark": "walkthrough",
        "machine": machine_info(),
        "data": str(data),
        "repeats": int(repeats),
        "label_once": True,
        "points_drawn": points_drawn,
        "points_shown": points_shown,  # of the first frame's scan, after the height cut and the budget
        "show_grid": show_grid,
        "settle_ms": float(settle_ms),
        "webgl_renderer": webgl_renderer,
        "target_edit_ms": TARGET_EDIT_MS,
        "target_frame_ms": TARGET_FRAME_MS,
        "target_verdict_ms": TARGET_VERDICT_MS,
        "num_verdicts": NUM_VERDICTS if retrain else 0,
        "verdict_keys": verdict_keys if retrain else None,
        "browser_render": render,
        "retrain": retrained,
        "target_next_round_s": TARGET_NEXT_ROUND_S,
        "steps": {
            step: {
                "stored_median_ms": round(statistics.median(values["stored"]), 1),
                "server_median_ms": round(statistics.median(values["server"]), 1),
                "server_max_ms": round(max(values["server"]), 1),
                "shown_median_ms": round(statistics.median(values["shown"]), 1),
                "shown_max_ms": round(max(values["shown"]), 1),
                "page_seen_median_ms": round(statistics.median(values["page_seen"]), 1),
                "page_median_ms": round(statistics.median(values["page"]), 1),
                "page_max_ms": round(max(values["page"]), 1),
                "runs": values,
            }
            for step, values in steps.items()
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="a data set folder (e.g. sessions/demo/data)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=None, help="also write the JSON here")
    parser.add_argument("--readme", default=None, help="update the page's walkthrough block (and its record)")
    parser.add_argument(
        "--readme-block",
        default="walkthrough",
        help="the block of --readme to update (default: walkthrough, the whole walkthrough's; another "
        "block may hold the edits alone)",
    )
    parser.add_argument(
        "--no-retrain",
        action="store_true",
        help="leave out the review verdicts and the retrains (edits only)",
    )
    parser.add_argument(
        "--points-drawn",
        type=int,
        default=None,
        help="the Display panel's Points drawn (default: all the points)",
    )
    parser.add_argument(
        "--no-grid",
        action="store_true",
        help="the Display panel's Floor grid off (default: on, as the app starts)",
    )
    parser.add_argument(
        "--shadow-cost",
        action="store_true",
        help="also time a render with viser's default shadows on and off, in turns (they are off in the app)",
    )
    parser.add_argument(
        "--verdict-keys",
        default=VERDICT_KEYS,
        help=f"the review verdicts' keys, in turn (default {VERDICT_KEYS}: background and skip; o answers "
        "Object with the item's class, and the next round fits the box quality regressor again)",
    )
    parser.add_argument(
        "--settle-ms",
        type=float,
        default=0.0,
        help="press each timed key once the page has drawn nothing for this many ms (a labeller who "
        "looks at each edit before the next key; default 0: as soon as the last step showed)",
    )
    args = parser.parse_args(argv)
    if not 0 <= args.settle_ms < VISER_HEARTBEAT_MS:
        parser.error(f"--settle-ms must lie in [0, {VISER_HEARTBEAT_MS:.0f}), got {args.settle_ms}")
    try:
        check_verdict_keys(args.verdict_keys)
    except ValueError as exc:
        parser.error(f"--verdict-keys: {exc}")
    if args.points_drawn is not None and args.points_drawn < 1:
        parser.error(f"--points-drawn must be at least 1, got {args.points_drawn}")
    if args.readme_block != "walkthrough" and not args.readme:
        parser.error("--readme-block names a block of --readme: give the page too")
    if args.no_retrain and args.readme and args.readme_block == "walkthrough":
        parser.error(
            "the walkthrough block records the whole walkthrough: drop --no-retrain or name --readme-block"
        )
    record = run(
        args.data,
        args.repeats,
        progress=lambda line: print(line, file=sys.stderr),
        retrain=not args.no_retrain,
        points_drawn=args.points_drawn,
        verdict_keys=args.verdict_keys,
        shadow_cost=args.shadow_cost,
        show_grid=not args.no_grid,
        settle_ms=args.settle_ms,
    )
    record["command"] = "python -m app.walkthrough " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps(record, indent=2)
    print(text)
    if args.out:
        write_text_atomic(args.out, text + "\n")
    if args.readme:
        update_readme(args.readme, record, name=args.readme_block)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
