"""The app's state: what every browser shares (``SharedState``: the data set, the session, the
model, the front half's parameters, training) and what each browser sees its own way
(``AppState``: its frame, display settings, detection thresholds, shown result and metrics).

One lock guards both: viser runs callbacks on a thread pool, so every read-modify-write happens
under ``lock``. A change to a browser's view redraws that browser alone; a change to the shared
state redraws every browser. No viser import here: the state is unit-testable without a server.
"""

from __future__ import annotations

import enum
import threading
import time
import traceback
import typing
from collections.abc import Callable

import numpy as np

from factorydet_core.colors import COLOR_MODES
from factorydet_core.detection.detector import DetectionResult, ProposalResult, params_for
from factorydet_core.detection.scoring import BOX_VOTE_IOU, operating_thresholds, select_detections
from factorydet_core.io.dataset import Dataset
from factorydet_core.metrics import (
    errors_from_counts,
    frame_error_counts,
    frame_matches,
    metrics_from_matches,
    pool_matches,
)
from factorydet_core.proposals.settings import FrontEndParams
from factorydet_core.session.store import label_arrays
from factorydet_core.types import SCORE_FLOOR, Detections, Frame

AP_SCORE_FLOOR = SCORE_FLOOR
"""Detections down to this score feed the metrics panel's PR curve."""

LAYERS: tuple[str, ...] = ("merged", "voxels", "patches", "segments", "proposals", "detections")
"""The detection layers the app can draw, in panel order."""


class Unchanged(enum.Enum):
    """``AppState.set_display``'s "leave as it is" where ``None`` is a value (``points_drawn``)."""

    UNCHANGED = "unchanged"


UNCHANGED = Unchanged.UNCHANGED


def select_with(candidates: Detections, kind: str, args: tuple) -> Detections:
    """A view's selection of a frame's candidates: ``kind`` "shown" with ``AppState.selection_args``
    (suppressed ones included, as ``select_detections`` gives them), or "floor" with
    ``AppState.floor_args`` (the kept ones only, for the metrics)."""
    if kind == "shown":
        score, nms_iou, per_class, vote_iou = args
        return select_detections(
            candidates,
            score,
            nms_iou,
            class_score_thresholds=None
            if per_class is None
            else np.array([np.nan if t is None else t for t in per_class], np.float64),
            vote_iou=vote_iou,
        )
    if kind == "floor":
        floor, nms_iou, vote_iou = args
        selected = select_detections(candidates, floor, nms_iou, vote_iou=vote_iou)
        return selected.subset(selected.kept_mask)
    raise ValueError(f"unknown selection {kind!r}")


def _vote_slider_value(model) -> float:
    """The box voting IoU a model asks for, 0 when it switches voting off (``vote_iou: null``)."""
    if model is None:
        return BOX_VOTE_IOU
    return 0.0 if model.vote_iou is None else float(model.vote_iou)


REFERENCE_KEYS = ("reference_boxes", "reference_class_ids", "ignore_boxes")
"""A viewed frame's metrics entry's keys of what it is measured against (``SharedState.references``)."""


class MetricsRunner:
    """Measures views' metrics again on one background thread, so that a label edit or a review
    verdict returns before the metrics over every frame viewed (which grow with the frames) are
    measured; a view then shows its last metrics, said to be out of date, until the new ones come.
    The thread ends when idle and starts again on the next request.

    A measurement waits until no request has come for ``QUIET_SECONDS``: a run of review verdicts
    or edits is measured once, after it, instead of after each. An Object verdict changes the
    references of every frame that shows its object, and a measurement started at once ran
    alongside the verdict's next item, on the cores that answer it; the metrics panel says its
    figures are out of date meanwhile. The quiet period is the app's, not a view's: while any
    browser keeps editing (or moving a threshold) less than ``QUIET_SECONDS`` apart, every view's
    measurement waits (a reader of ``AppState.metrics`` still measures at once)."""

    IDLE_SECONDS = 30.0
    QUIET_SECONDS = 1.0

    def __init__(self) -> None:
        self._wake = threading.Condition()
        self._pending: dict[int, AppState] = {}  # by id: a view asked for twice is measured once
        self._running = False
        self._last_request = 0.0  # time.monotonic() of the latest request
        self.thread: threading.Thread | None = None  # the last one started

    def request(self, view: AppState) -> None:
        with self._wake:
            self._pending[id(view)] = view
            self._last_request = time.monotonic()
            if not self._running:
                self._running = True
                self.thread = threading.Thread(target=self._run, name="factorydet-metrics", daemon=True)
                self.thread.start()
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                if not self._pending:
                    self._wake.wait(self.IDLE_SECONDS)
                if not self._pending:
                    self._running = False
                    return
                # (a request meanwhile wakes this wait and moves the end of the quiet period)
                while (quiet := self._last_request + self.QUIET_SECONDS - time.monotonic()) > 0:
                    self._wake.wait(quiet)
                view = self._pending.pop(next(iter(self._pending)))
            try:
                view._measure_pending()
            except Exception:  # the thread goes on; a reader of ``metrics`` meets the error
                traceback.print_exc()


IOU_THRESHOLD = 0.6
"""The metrics panel matches detections to labels at this 3D IoU (the paper's)."""

MEASURED_KEYS = (
    "boxes", "class_ids", "scores", *REFERENCE_KEYS,
    "candidate_boxes", "candidate_class_ids", "candidate_scores",
)  # fmt: skip
"""A viewed frame's metrics entry's arrays: a frame whose arrays are the very ones measured last time
is not matched again (``_measure``)."""


class _FrameMeasure(typing.NamedTuple):
    """A viewed frame's last measurement (``_measure``'s memo): the arrays it matched
    (``MEASURED_KEYS``), their ``frame_matches``, the operating thresholds (C,) its errors were
    counted at and those ``frame_error_counts`` (both ``None`` until counted)."""

    arrays: tuple
    matches: tuple
    thresholds: np.ndarray | None
    counts: tuple | None


def _measure(inputs: tuple, memo: dict | None = None) -> dict:
    """The metrics panel's figures from ``AppState._update_metrics``'s inputs. With ``memo`` (a
    dict kept between calls, by frame index), a frame whose arrays (``MEASURED_KEYS``) and
    operating thresholds are the ones of its last measurement keeps that measurement's matches
    (``frame_matches``, ``frame_error_counts``): an edit changes the references of the frames
    that show its object, and only those are matched again; another operating point counts the
    errors again, on the same matches."""
    scored, class_names, score_threshold, per_class = inputs
    num_classes = len(class_names)
    thresholds = operating_thresholds(num_classes, score_threshold, per_class)
    memo = {} if memo is None else memo
    matches, counts = [], []
    for frame in scored:
        arrays = tuple(frame.get(key) for key in MEASURED_KEYS)
        known = memo.get(frame["frame_index"])
        if known is None or not all(a is b for a, b in zip(known.arrays, arrays)):
            known = _FrameMeasure(arrays, frame_matches(frame, num_classes, IOU_THRESHOLD), None, None)
        if known.thresholds is None or not np.array_equal(known.thresholds, thresholds):
            counted = frame_error_counts(frame, num_classes, IOU_THRESHOLD, thresholds)
            known = known._replace(thresholds=thresholds, counts=counted)  # (the matches stand)
        # (replaced whole: a reader measuring at once and the background thread may share it)
        memo[frame["frame_index"]] = known
        matches.append(known.matches)
        counts.append(known.counts)
    for index in set(memo) - {frame["frame_index"] for frame in scored}:
        memo.pop(index, None)  # a frame no longer viewed
    pooled = pool_matches(matches, num_classes)
    metrics = metrics_from_matches(pooled, class_names, IOU_THRESHOLD, score_threshold, per_class)
    metrics["num_frames"] = len(scored)
    metrics["errors"] = errors_from_counts(counts, class_names, IOU_THRESHOLD)
    return metrics


def _same_references(item: dict, references: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
    """Whether a viewed frame's metrics entry (``AppState.frame_detections``) is measured against
    ``references`` (``SharedState.references``) already."""
    return all(
        key in item and np.array_equal(item[key], value) for key, value in zip(REFERENCE_KEYS, references)
    )


class SharedState:
    """What every browser shares, and the views (``AppState``, one per browser) of it.

    Args:
        dataset: the data set shown.
        title: the status line's name; the data set's name by default.
        model: a ``DetectionModel``, or ``None`` for the front half only.
        model_name: how the model is named in the panels.
        db: the session's ``SessionDB``; ``None`` when the app shows a data set without a session
            (labels then come from the data set and cannot be edited).
    """

    def __init__(
        self, dataset: Dataset, title: str | None = None, model=None, model_name: str = "", db=None
    ) -> None:
        self.dataset = dataset
        self.db = db
        self.title = title or dataset.name
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        self.revision = 0  # bumped after every write to the session database
        self.model_revision = 0  # bumped when the shown model changes
        self.model = model
        self.model_name = model_name
        self.training_busy = False
        self.training_status = "idle"
        self.training_progress = 0.0
        self.training_comparison: dict | None = None  # the last run's before/after table
        self.offered_model: str | None = None  # a new run's model the Training panel offers
        self.suspects: list[dict] = []  # labels the shown model contradicts (loop.suspect_labels)
        # The front half's parameters are everyone's: one set of results is computed and cached.
        self.params: FrontEndParams = params_for(model, dataset.num_sensors)
        self.use_refined_extrinsics = dataset.num_sensors > 1
        # Label once: the frames placed in one world frame (``world.session_world``), computed in the
        # background when the app opens a session; ``None`` until then (edits stay in their frame).
        self.world = None
        self.world_status = "" if db is None else "placing the frames in one world frame"
        self._views: list[AppState] = []  # the browsers' views, which the worker serves
        self._templates: list[AppState] = []  # views no browser shows (``AppState``, ``served``)
        self._listeners: list[Callable[[], None]] = []
        self.metrics_runner = MetricsRunner()

    # -- views

    def new_view(self, like: AppState | None = None, served: bool = True) -> AppState:
        """A new browser's view, with ``like``'s frame, display settings and thresholds (the
        defaults without); ``served=False`` for a template (``AppState``)."""
        return AppState(self, like=like, served=served)

    def remove_view(self, view: AppState) -> None:
        """Forget a view (its browser left): the worker no longer computes its frames."""
        with self.lock:
            for views in (self._views, self._templates):
                if view in views:
                    views.remove(view)

    @property
    def views(self) -> list[AppState]:
        """The browsers' views."""
        with self.lock:
            return list(self._views)

    @property
    def templates(self) -> list[AppState]:
        """The views no browser shows (``AppState``'s ``served=False``)."""
        with self.lock:
            return list(self._templates)

    def on_change(self, listener: Callable[[], None]) -> None:
        """Call ``listener`` after every change to the shared state (every view's listeners run too)."""
        self._listeners.append(listener)

    def _notify(self) -> None:
        for listener in self._listeners:
            listener()
        for view in self.views:
            view._notify()

    # -- the session: labels, reviews, training

    @property
    def editable(self) -> bool:
        return self.db is not None

    def frame_labels(self, frame_index: int):
        """``(boxes (R, 7), class_ids (R,), label_ids (R,))`` of a frame: the session's labels, or
        the data set's annotations without a session (ids -1)."""
        index = int(frame_index)
        if self.db is not None:
            return self.db.frame_boxes(index)
        labels = self.dataset.frame(index).labels
        return np.array(labels.boxes), np.array(labels.class_ids), np.full(len(labels), -1)

    def drawn_labels(self, frame_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(boxes (R, 7), class_ids (R,), prelabel_mask (R,))`` of a frame's labels, read at once:
        the mask flags the model's pre-labels nobody has confirmed yet (drawn apart)."""
        if self.db is None:
            boxes, class_ids, _ = self.frame_labels(frame_index)
            return boxes, class_ids, np.zeros(len(boxes), bool)
        labels = self.db.labels(int(frame_index))
        boxes, class_ids, _ = label_arrays(labels, self.db.class_names)
        return boxes, class_ids, np.array([not lab.reviewed for lab in labels], bool)

    def references(self, frame_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a frame's detections are measured against: ``(boxes (R, 7), class_ids (R,),
        ignore_boxes (Q, 7))``, the labels a person made or confirmed, and the model's pre-labels
        nobody has confirmed yet (not truth: a detection on one is not counted either way)."""
        return self.frame_references([frame_index])[int(frame_index)]

    def frame_references(self, frame_indices) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``references`` of several frames, by frame, from one read of the session (every edit
        measures each viewed frame's metrics against its labels again)."""
        frames = sorted({int(i) for i in frame_indices})
        if not frames:
            return {}
        if self.db is None:
            out = {}
            for index in frames:
                boxes, class_ids, _ = self.frame_labels(index)
                out[index] = (boxes, class_ids, np.zeros((0, 7)))
            return out
        names = self.db.class_names
        out = {}
        for index, labels in self.db.frame_labels(frames).items():
            boxes, class_ids, _ = label_arrays([lab for lab in labels if lab.reviewed], names)
            out[index] = (
                boxes,
                class_ids,
                label_arrays([lab for lab in labels if not lab.reviewed], names)[0],
            )
        return out

    def session_changed(self) -> None:
        """Something was written to the session database: every view refreshes, and each view's
        metrics are recomputed against the corrected labels."""
        with self.lock:
            self.revision += 1
            # Every viewed frame's labels in one read (a frame several browsers viewed once).
            read = self.frame_references({index for view in self._views for index in view.frame_detections})
            for view in self._views:
                moved = False
                for index, item in view.frame_detections.items():
                    if not _same_references(item, read[index]):
                        item.update(zip(REFERENCE_KEYS, read[index]))
                        moved = True
                if moved:  # (a verdict of background or skip, say, moves no label: nothing to measure again)
                    view._update_metrics()  # the detections are the same: only what they are measured against
            self.changed.notify_all()
        self._notify()

    def set_world(self, world, status: str) -> None:
        """The frames' world placement (``None`` while it computes or after it failed) and a line
        saying where it stands."""
        with self.lock:
            self.world = world
            self.world_status = status
            self.changed.notify_all()
        self._notify()

    def set_model(self, model, name: str) -> None:
        """Show another model's detections in every browser (the worker recomputes the shown
        frames; each view's thresholds become the model's)."""
        with self.lock:
            self.model = model
            self.model_name = name
            self.model_revision += 1
            if model is not None:
                self.params = params_for(model, self.dataset.num_sensors)
            for view in self._views + self._templates:
                view._take_model(model)
            self.suspects = []  # another model's verdicts on the labels
            self.changed.notify_all()
        self._notify()

    def choose_model(self, model, name: str, path) -> None:
        """Show ``model`` (a checkpoint at ``path``) and remember the choice in the session
        (``SessionDB.set_shown_model``), so that the app shows it again when reopened. The choice
        is stored first: once a browser shows the model, a reopen shows it too."""
        if self.db is not None:
            self.db.set_shown_model(name, path)
        with self.lock:
            self.offered_model = None
        self.set_model(model, name)

    def offer_model(self, choice: str) -> None:
        """Offer a new run's model (its Training panel name) without showing it."""
        with self.lock:
            self.offered_model = choice
            self.changed.notify_all()
        self._notify()

    def set_suspects(self, suspects: list[dict]) -> None:
        with self.lock:
            self.suspects = list(suspects)
            self.changed.notify_all()
        self._notify()

    def set_training(
        self,
        *,
        busy: bool | None = None,
        status: str | None = None,
        progress: float | None = None,
        comparison: dict | None = None,
    ) -> None:
        with self.lock:
            if busy is not None:
                self.training_busy = busy
            if status is not None:
                self.training_status = status
            if progress is not None:
                self.training_progress = float(progress)
            if comparison is not None:
                self.training_comparison = comparison
            self.changed.notify_all()
        self._notify()

    def set_params(self, **changes) -> None:
        """Change front-half parameters (``FrontEndParams`` or ``SegmentationParams`` field names)
        for everyone; the worker recomputes the shown frames."""
        with self.lock:
            self.params = self.params.replace(**changes)
            self.changed.notify_all()
        self._notify()

    def set_use_refined_extrinsics(self, use: bool) -> None:
        with self.lock:
            self.use_refined_extrinsics = bool(use)
            self.changed.notify_all()
        self._notify()

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until ``predicate()`` holds (checked under the lock) or ``timeout`` seconds pass."""
        with self.lock:
            return self.changed.wait_for(predicate, timeout)


def _shared(name: str, doc: str = "") -> property:
    """A read-only view attribute that is the shared state's."""
    return property(lambda view: getattr(view.shared, name), doc=doc or f"The shared state's ``{name}``.")


class AppState:
    """One browser's view of the shared state: which frame it shows and how, its detection
    thresholds, the shown frame's result and the metrics over the frames it viewed. Listeners run
    after every change to this view or to the shared state (under no lock).

    ``AppState(dataset, ...)`` makes a shared state with this as its first view (what a test or a
    single-user tool wants); ``SharedState.new_view`` makes more. A view made with ``served=False``
    is a template: the worker does not compute its frames (no browser shows them), it keeps up
    with model changes, and new views can start ``like`` it.
    """

    def __init__(
        self,
        dataset: Dataset | SharedState,
        title: str | None = None,
        model=None,
        model_name: str = "",
        db=None,
        like: AppState | None = None,
        served: bool = True,
    ) -> None:
        if isinstance(dataset, SharedState):
            self.shared = dataset
        else:
            self.shared = SharedState(dataset, title, model=model, model_name=model_name, db=db)
        with self.shared.lock:  # a model change cannot slip in between reading and joining
            self._init(like, served)

    def _init(self, like: AppState | None, served: bool) -> None:
        """(Under the lock.)"""
        shared = self.shared
        self._listeners: list[Callable[[], None]] = []
        self.frame_index = 0
        self.num_frame_changes = 0
        first = shared.dataset.frame(0)
        self.color_mode = (
            "sensor" if shared.dataset.num_sensors > 1 else ("rgb" if first.colors is not None else "height")
        )
        self.point_size = 0.04
        self.show_boxes = True
        # Names on every box overlap into an unreadable cloud of text at the default view: off, only
        # the selected box is named (each browser's own) and a click on a box describes it.
        self.show_box_names = False
        # The floor grid helps to judge distances; a browser without a graphics card draws its lines,
        # as it does the points, at every render of the scene, so it can be turned off.
        self.show_grid = True
        self.max_height = 6.0  # metres: under the simulated hall's 8 m roof, above its racks
        self.points_drawn: int | None = None  # every point; fewer render faster without a graphics card
        # With a model the detections are what people came for; without, the proposals.
        shown = "detections" if shared.model is not None else "proposals"
        self.layers = {name: name == shown for name in LAYERS}
        # The worker's progress on this view's frame, and the frame's result once computed.
        self.pipeline_status = "waiting"
        self.pipeline_progress = 0.0
        self.pipeline_busy = False
        self.pipeline_result: ProposalResult | None = None
        self.pipeline_result_key: tuple | None = None
        self.pipeline_failed_key: tuple | None = None
        self.num_results = 0
        self.selection_markdown = ""
        # Detection back half: the filters the sliders set, and per-frame results.
        self.show_suppressed = False
        self.color_by_match = False
        self._take_model(shared.model)
        if like is not None:
            self.frame_index = like.frame_index
            for name in (
                "color_mode", "point_size", "show_boxes", "show_box_names", "show_grid", "max_height",
                "points_drawn", "score_threshold", "nms_iou", "vote_iou", "use_class_thresholds",
                "show_suppressed", "color_by_match",
            ):  # fmt: skip
                setattr(self, name, getattr(like, name))
            self.layers = dict(like.layers)
        (shared._views if served else shared._templates).append(self)

    def _take_model(self, model) -> None:
        """The model's thresholds, and no result of another model (under the lock)."""
        self.score_threshold = model.score_threshold if model is not None else 0.5
        self.nms_iou = model.nms_iou if model is not None else 0.25
        # Box voting after NMS: the model's IoU, 0 for off (the slider's bottom).
        self.vote_iou = _vote_slider_value(model)
        # The model's own threshold per class, until someone moves the score slider.
        self.use_class_thresholds = model is not None and model.class_thresholds() is not None
        self.detection_result: DetectionResult | None = None
        self._selections: dict = {}  # the shown frame's selections made ahead, by ("shown"/"floor", *args)
        self.detection_frame_index = 0
        self.detections: Detections | None = None
        self.frame_detections: dict[int, dict] = {}  # frame -> candidates and labels, for metrics
        self._metrics: dict | None = None  # the last measured (``metrics``)
        self._metrics_inputs: tuple | None = None  # what is to be measured next; None: up to date
        self._metrics_memo: dict = {}  # each viewed frame's last matches (``_measure``)

    # The shared state, read through the view (the panels read one object).
    dataset = _shared("dataset")
    db = _shared("db", "The session's ``SessionDB``, ``None`` without a session.")
    title = _shared("title")
    lock = _shared("lock")
    changed = _shared("changed")
    revision = _shared("revision")
    model_revision = _shared("model_revision")
    model = _shared("model")
    model_name = _shared("model_name")
    training_busy = _shared("training_busy")
    training_status = _shared("training_status")
    training_progress = _shared("training_progress")
    training_comparison = _shared("training_comparison")
    offered_model = _shared("offered_model")
    suspects = _shared("suspects")
    params = _shared("params")
    use_refined_extrinsics = _shared("use_refined_extrinsics")
    world = _shared("world")
    world_status = _shared("world_status")
    editable = _shared("editable")

    def on_change(self, listener: Callable[[], None]) -> None:
        self._listeners.append(listener)

    def _notify(self) -> None:
        for listener in self._listeners:
            listener()

    def close(self) -> None:
        """This view's browser left: the shared state forgets it."""
        self.shared.remove_view(self)

    # -- what the shared state does, asked from a view

    def frame_labels(self, frame_index: int | None = None):
        """``SharedState.frame_labels`` of ``frame_index``, this view's frame by default."""
        return self.shared.frame_labels(self.frame_index if frame_index is None else frame_index)

    def drawn_labels(self, frame_index: int):
        return self.shared.drawn_labels(frame_index)

    def references(self, frame_index: int):
        return self.shared.references(frame_index)

    def session_changed(self) -> None:
        self.shared.session_changed()

    def set_world(self, world, status: str) -> None:
        self.shared.set_world(world, status)

    def set_model(self, model, name: str) -> None:
        self.shared.set_model(model, name)

    def choose_model(self, model, name: str, path) -> None:
        self.shared.choose_model(model, name, path)

    def offer_model(self, choice: str) -> None:
        self.shared.offer_model(choice)

    def set_suspects(self, suspects: list[dict]) -> None:
        self.shared.set_suspects(suspects)

    def set_training(self, **changes) -> None:
        self.shared.set_training(**changes)

    def set_params(self, **changes) -> None:
        self.shared.set_params(**changes)

    def set_use_refined_extrinsics(self, use: bool) -> None:
        self.shared.set_use_refined_extrinsics(use)

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        return self.shared.wait_for(predicate, timeout)

    # -- this view

    @property
    def frame(self) -> Frame:
        return self.dataset.frame(self.frame_index)

    def set_frame(self, index: int) -> None:
        """Show frame ``index``, clamped to the data set."""
        index = max(0, min(int(index), self.dataset.num_frames - 1))
        with self.lock:
            if index == self.frame_index:
                return
            self.frame_index = index
            self.num_frame_changes += 1
            self.changed.notify_all()
        self._notify()

    def step_frame(self, delta: int) -> None:
        with self.lock:
            target = self.frame_index + delta
        self.set_frame(target)

    def set_display(
        self,
        *,
        color_mode: str | None = None,
        point_size: float | None = None,
        show_boxes: bool | None = None,
        max_height: float | None = None,
        show_box_names: bool | None = None,
        show_grid: bool | None = None,
        points_drawn: int | None | Unchanged = UNCHANGED,
    ) -> None:
        """Change how the frame is drawn; ``None`` leaves a setting as it is (``points_drawn``:
        the most points of the scan and of each layer drawn, ``None`` for all of them; left as
        it is by ``UNCHANGED``)."""
        # (checked before anything changes: a refused call changes nothing)
        if points_drawn is not UNCHANGED and points_drawn is not None and int(points_drawn) < 1:
            raise ValueError(f"points drawn must be at least 1 (None: all), got {points_drawn}")
        if color_mode is not None and color_mode not in COLOR_MODES:
            raise ValueError(f"unknown colour mode {color_mode!r}; choose from {COLOR_MODES}")
        with self.lock:
            if points_drawn is not UNCHANGED:
                self.points_drawn = None if points_drawn is None else int(points_drawn)
            if color_mode is not None:
                self.color_mode = color_mode
            if point_size is not None:
                self.point_size = float(point_size)
            if show_boxes is not None:
                self.show_boxes = bool(show_boxes)
            if max_height is not None:
                self.max_height = float(max_height)
            if show_box_names is not None:
                self.show_box_names = bool(show_box_names)
            if show_grid is not None:
                self.show_grid = bool(show_grid)
            self.changed.notify_all()
        self._notify()

    def set_layer(self, name: str, visible: bool) -> None:
        """Show or hide one of ``LAYERS``."""
        if name not in LAYERS:
            raise ValueError(f"unknown layer {name!r}; choose from {LAYERS}")
        with self.lock:
            self.layers[name] = bool(visible)
            self.changed.notify_all()
        self._notify()

    def pipeline_key(self) -> tuple:
        """What the current result must have been computed from: frame, front-half parameters,
        extrinsics, and the model."""
        with self.lock:
            return (self.frame_index, self.params, self.use_refined_extrinsics, self.model_revision)

    def set_pipeline_progress(self, status: str, fraction: float, busy: bool = True) -> None:
        with self.lock:
            self.pipeline_status = status
            self.pipeline_progress = float(fraction)
            self.pipeline_busy = busy
            self.changed.notify_all()
        self._notify()

    def set_pipeline_result(self, key: tuple, result: ProposalResult, status: str) -> None:
        with self.lock:
            self._set_result(key, result, status)
        self._notify()

    def _set_result(self, key: tuple, result: ProposalResult, status: str) -> None:
        """(Under the lock.)"""
        self.pipeline_result = result
        self.pipeline_result_key = key
        self.pipeline_status = status
        self.pipeline_progress = 1.0
        self.pipeline_busy = False
        self.selection_markdown = ""
        self.num_results += 1
        self.changed.notify_all()

    def set_detection_result(
        self, key: tuple, result: DetectionResult, status: str, selections: dict | None = None
    ) -> None:
        """A new frame's detections: filter them by the sliders, add the frame to the metrics, and
        make its front half the shown result, all at once.

        Args:
            selections: ``{selection arguments: Detections}`` of ``result`` made ahead (the
                worker's ``selections_ahead``); a view whose sliders ask for one of them runs no NMS.
        """
        selections = selections or {}
        with self.lock:
            # Read under the lock, so an edit's session_changed cannot slip in between.
            boxes, class_ids, ignore_boxes = self.references(key[0])
            self.detection_result = result
            self.detection_frame_index = key[0]
            self._selections = selections
            item = {
                "candidates": result.candidates,
                "reference_boxes": boxes,
                "reference_class_ids": class_ids,
                "ignore_boxes": ignore_boxes,
            }
            floor_args = ("floor", *self.floor_args())
            if floor_args in selections:
                item["floor"], item["floor_key"] = selections[floor_args], floor_args[1:]
            known = self.frame_detections.get(key[0])
            # A frame viewed again (the review queue goes back and forth between frames) with the
            # same detections and references leaves the metrics as they are: only the shown
            # detections change.
            again = (
                known is not None
                and known["candidates"] is result.candidates
                and _same_references(known, (boxes, class_ids, ignore_boxes))
            )
            if again:
                self._select_shown()
            else:
                self.frame_detections[key[0]] = item
                self._refilter()
            self._set_result(key, result.proposal, status)
        self._notify()

    def detections_at(self, min_score: float) -> tuple[int, Detections | None]:
        """``(frame index, detections)`` of the shown frame down to ``min_score`` (one threshold
        for every class, the NMS and voting in force), what pre-labelling takes; ``None`` until the
        frame's detections are computed."""
        with self.lock:
            frame_index, result = self.frame_index, self.detection_result
            if result is None or self.detection_frame_index != frame_index:
                return frame_index, None
            nms_iou, vote_iou = self.nms_iou, self._vote_iou()
        return frame_index, select_detections(result.candidates, float(min_score), nms_iou, vote_iou=vote_iou)

    def class_thresholds(self):
        """(C,) the per-class thresholds in force, or ``None`` (one threshold; under the lock)."""
        if not self.use_class_thresholds or self.model is None:
            return None
        return self.model.class_thresholds()

    def _vote_iou(self) -> float | None:
        """The box voting threshold in force, ``None`` for off (under the lock)."""
        return self.vote_iou if self.vote_iou > 0 else None

    def _refilter(self) -> None:
        """Recompute the shown detections and the metrics (under the lock)."""
        self._select_shown()
        self._update_metrics()

    def selection_args(self) -> tuple:
        """``(score_threshold, nms_iou, per-class thresholds (a tuple, None for a class that keeps
        the global one) or None, vote_iou or None)``: how this view selects the shown detections
        (``select_with``). A key of the selections made ahead: no NaN in it (NaN equals nothing,
        not even itself, so a key holding one never finds its selection)."""
        with self.lock:
            per_class = self.class_thresholds()
            return (
                self.score_threshold,
                self.nms_iou,
                None if per_class is None else tuple(None if np.isnan(t) else float(t) for t in per_class),
                self._vote_iou(),
            )

    def floor_args(self) -> tuple:
        """``(score floor, nms_iou, vote_iou or None)``: how this view selects each viewed frame's
        detections for the metrics (down to the AP floor)."""
        with self.lock:
            return (min(AP_SCORE_FLOOR, self.score_threshold), self.nms_iou, self._vote_iou())

    def _select_shown(self) -> None:
        """The shown frame's detections at the current thresholds (under the lock)."""
        result = self.detection_result
        args = self.selection_args()
        ahead = self._selections.get(("shown", *args))
        if result is None:
            self.detections = None
        else:
            self.detections = ahead if ahead is not None else select_with(result.candidates, "shown", args)

    def _update_metrics(self) -> None:
        """Measure the metrics over the frames viewed again (under the lock), on the background
        thread (``MetricsRunner``): ``metrics`` and ``shown_metrics`` read them. Each frame's
        detections down to the AP floor are kept with the thresholds they were selected at: a label
        edit changes only the references, so it recomputes no NMS (that took seconds per edit)."""
        per_class = self.class_thresholds()
        if self.model is None or not self.frame_detections:
            self._metrics, self._metrics_inputs = None, None
            return
        scored = []
        floor_key = self.floor_args()
        for frame_index, item in self.frame_detections.items():
            if item.get("floor_key") != floor_key:
                item["floor"], item["floor_key"] = (
                    select_with(item["candidates"], "floor", floor_key),
                    floor_key,
                )
            kept = item["floor"]
            scored.append(
                {
                    "frame_index": frame_index,
                    "boxes": kept.boxes,
                    "class_ids": kept.class_ids,
                    "scores": kept.scores,
                    "reference_boxes": item["reference_boxes"],
                    "reference_class_ids": item["reference_class_ids"],
                    "ignore_boxes": item["ignore_boxes"],
                    "candidate_boxes": item["candidates"].boxes,
                    "candidate_class_ids": item["candidates"].class_ids,
                    "candidate_scores": item["candidates"].scores,
                }
            )
        # A new tuple per request: the background thread stores its result only if this very
        # tuple is still the one asked for (``_measure_pending``).
        self._metrics_inputs = (scored, self.model.class_names, self.score_threshold, per_class)
        self.shared.metrics_runner.request(self)

    @property
    def metrics(self) -> dict | None:
        """The metrics over the frames viewed (``metrics.detection_metrics`` with ``num_frames``
        and ``errors``, ``metrics.error_breakdown``), measured now if out of date: a caller that
        must not wait reads ``shown_metrics``."""
        with self.lock:
            if self._metrics_inputs is not None:
                self._metrics, self._metrics_inputs = _measure(self._metrics_inputs, self._metrics_memo), None
            return self._metrics

    def shown_metrics(self) -> tuple[dict | None, bool]:
        """``(the last measured metrics, whether they are out of date)``, without waiting: what the
        metrics panel shows while the background thread measures them again."""
        with self.lock:
            return self._metrics, self._metrics_inputs is not None

    def _measure_pending(self) -> None:
        """Measure what ``_update_metrics`` asked for (on the background thread, not under the
        lock), keep it unless something newer was asked meanwhile, and redraw this view."""
        with self.lock:
            inputs = self._metrics_inputs
        if inputs is None:
            return
        measured = _measure(inputs, self._metrics_memo)
        with self.lock:
            if self._metrics_inputs is not inputs:  # asked again since, or measured by a reader
                return
            self._metrics, self._metrics_inputs = measured, None
        self._notify()

    def set_detection_filter(
        self,
        *,
        score_threshold: float | None = None,
        nms_iou: float | None = None,
        show_suppressed: bool | None = None,
        color_by_match: bool | None = None,
        use_class_thresholds: bool | None = None,
        vote_iou: float | None = None,
    ) -> None:
        """Change the score threshold, NMS IoU, box voting IoU (0: off) or what is shown; the
        detections re-filter at once. A score threshold applies to every class (the model's
        per-class ones are switched off)."""
        if vote_iou is not None and not 0.0 <= float(vote_iou) < 1.0:
            raise ValueError(f"vote_iou must lie in [0, 1), got {vote_iou}")
        with self.lock:
            refilter = False
            if use_class_thresholds is not None:
                wanted = bool(use_class_thresholds) and self.model is not None
                wanted = wanted and self.model.class_thresholds() is not None
                if wanted != self.use_class_thresholds:
                    self.use_class_thresholds, refilter = wanted, True
            if score_threshold is not None and (
                score_threshold != self.score_threshold or self.use_class_thresholds
            ):
                self.score_threshold, refilter = float(score_threshold), True
                self.use_class_thresholds = False
            if nms_iou is not None and nms_iou != self.nms_iou:
                self.nms_iou, refilter = float(nms_iou), True
            if vote_iou is not None and vote_iou != self.vote_iou:
                self.vote_iou, refilter = float(vote_iou), True
            if show_suppressed is not None:
                self.show_suppressed = bool(show_suppressed)
            if color_by_match is not None:
                self.color_by_match = bool(color_by_match)
            if refilter:
                self._refilter()
            self.changed.notify_all()
        self._notify()

    def set_pipeline_failed(self, key: tuple, status: str) -> None:
        """Record a failed run; it is not retried until the frame or the parameters change."""
        with self.lock:
            self.pipeline_failed_key = key
            self.pipeline_status = status
            self.pipeline_progress = 0.0
            self.pipeline_busy = False
            self.changed.notify_all()
        self._notify()

    def set_selection(self, markdown: str) -> None:
        with self.lock:
            self.selection_markdown = markdown
            self.changed.notify_all()
        self._notify()
