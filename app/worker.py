"""The background worker that runs the detector for the frames the browsers show (the front half,
and the classifier and NMS when the app has a model).

Requests come from view changes (a browser's frame, the shared parameters); a request that arrives
while a frame computes is served next, and a result that no view asks for when it finishes is kept
for later but not shown. The GUI thread never computes.

Results are kept for the last few frames (``CACHED_RESULTS``), and while nothing is asked for the
worker computes each shown frame's next and previous ones ahead (``PREFETCH_OFFSETS``, not while a
training runs): flipping through frames shows a cached frame at once, and an asked-for frame that
is being computed ahead is taken over rather than started again. A computation ahead gives way to
a request for another frame at its next stage.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
import traceback

from factorydet_core.detection.detector import Detector
from factorydet_core.proposals.voxels import voxel_colors
from factorydet_core.session.world import session_world
from factorydet_core.training.loop import cached_calibration

from .state import AppState, SharedState, select_with

CACHED_RESULTS = 3
"""Results kept per browser: its frame's and its next and previous frames' (computed ahead). A result
keeps its voxels' colours, not their 3DmFV, and the proposals' 3DmFV only for a model that reads
them (a box head's detections carry none)."""

PREFETCH_OFFSETS = (1, -1)
"""Frames computed ahead, relative to the shown one, in this order."""

MAX_CACHED_RESULTS = 12
"""Results kept at most, however many browsers are connected (``CACHED_RESULTS`` each)."""


class _GaveWayError(Exception):
    """A computation ahead stops for a request of another frame."""


class PipelineWorker:
    """One daemon thread computing the frame every view (browser) asks for: ``maybe_request(view)``
    after a view's frame or the shared parameters change. Views asking for the same frame share
    one computation; the view that asked last is served first.

    Args:
        shared: the app's shared state (results and progress are written into its views).
        calibrate: refine the extrinsics by ICP once, before the first frame, when the data set has
            several sensors.
    """

    def __init__(self, shared: SharedState, calibrate: bool = True) -> None:
        self.shared = shared
        self.calibrate = calibrate
        self._refined_extrinsics = None
        self._cache: collections.OrderedDict[tuple, tuple] = collections.OrderedDict()
        self._cache_lock = threading.Lock()
        self._ahead_key: tuple | None = None  # what is being computed ahead, if anything
        self._asked: list[AppState] = []  # views in the order they last asked, latest first
        self._pending = False
        self._stopped = False
        self._wake = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="factorydet-pipeline", daemon=True)
        self._thread.start()

    @property
    def idle(self) -> bool:
        """Nothing asked for and nothing computed ahead (every view's neighbouring frames are
        cached or out of range)."""
        with self._wake:
            pending = self._pending
        with self._cache_lock:
            ahead = self._ahead_key is not None
        with self.shared.lock:
            busy = any(view.pipeline_busy for view in self.shared.views)
        return not (pending or ahead or busy)

    def request(self) -> None:
        with self._wake:
            self._pending = True
            self._wake.notify()

    def maybe_request(self, view: AppState) -> None:
        """Request a run when ``view``'s frame or the parameters differ from its last result's
        (and from its last failed run's, which is not retried until something changes). A result
        in the cache is shown at once, on the calling thread."""
        key = view.pipeline_key()
        with view.lock:
            done = key in (view.pipeline_result_key, view.pipeline_failed_key)
            busy = view.pipeline_busy
        if done:
            with self._cache_lock:
                computing_ahead = self._ahead_key is not None
            if busy and computing_ahead:
                # Back to the shown frame from one that was being computed ahead: nothing the user
                # waits for is running.
                view.set_pipeline_progress("showing the current result", 1.0, busy=False)
            return
        with self._wake:
            if view in self._asked:
                self._asked.remove(view)
            self._asked.insert(0, view)
        if self._publish_cached(view, key):
            self.request()  # the worker goes on computing ahead of the new frame
            return
        with self._cache_lock:
            taken_over = key == self._ahead_key
        if taken_over and not busy:  # (setting the progress notifies, which calls this again)
            view.set_pipeline_progress(f"frame {key[0] + 1}: computing (started ahead)", 0.5)
        self.request()

    def cached_frames(self, view: AppState) -> list[int]:
        """The frames whose results are cached for the current parameters and model."""
        current = view.pipeline_key()[1:]
        with self._cache_lock:
            return sorted(key[0] for key in self._cache if key[1:] == current)

    def _served(self) -> list[AppState]:
        """The views the worker computes for: the browsers', or before any browser connects the
        templates (the frame a new browser opens on is then computed ahead of it)."""
        return self.shared.views or self.shared.templates

    def _views(self) -> list[AppState]:
        """``_served``, the latest to ask first."""
        views = self._served()
        with self._wake:
            self._asked = [view for view in self._asked if view in views]
            asked = list(self._asked)
        return asked + [view for view in views if view not in asked]

    def _wanting(self, key: tuple) -> list[AppState]:
        """The views that ask for ``key`` now and do not show it yet (the templates before any
        browser connects)."""
        out = []
        for view in self._served():
            with view.lock:
                if view.pipeline_key() == key and view.pipeline_result_key != key:
                    out.append(view)
        return out

    def _shown_elsewhere(self, key: tuple) -> tuple | None:
        """``(kind, result, status, selections)`` of a view that shows ``key`` already (its cache entry may
        have gone): another browser coming to that frame takes it, nothing is computed again."""
        for view in self.shared.views:
            with view.lock:
                if view.pipeline_result_key != key or view.pipeline_result is None:
                    continue
                detection = view.detection_result
                if detection is not None and detection.proposal is view.pipeline_result:
                    return "detection", detection, view.pipeline_status, dict(view._selections)
                if self.shared.model is None:
                    return "proposal", view.pipeline_result, view.pipeline_status, {}
        return None

    def _voxels_shown(self) -> bool:
        """Whether a view (or a new browser's template) shows the voxels layer."""
        for view in self.shared.views + self.shared.templates:
            with view.lock:
                if view.layers["voxels"]:
                    return True
        return False

    def _selections_ahead(self, candidates) -> dict:
        """``{(kind, *args): Detections}``: each view's (and template's) selection of a frame's
        ``candidates``, shown and for the metrics (``state.select_with``)."""
        views = self.shared.views + self.shared.templates
        wanted = {("shown", *view.selection_args()) for view in views}
        wanted |= {("floor", *view.floor_args()) for view in views}
        return {args: select_with(candidates, args[0], args[1:]) for args in wanted}

    def _release_others(self) -> None:
        """Views that came back to the result they show while another frame computed are not
        busy any more."""
        for view in self.shared.views:
            with view.lock:
                back_to_shown = view.pipeline_busy and view.pipeline_result_key == view.pipeline_key()
            if back_to_shown:
                view.set_pipeline_progress("showing the current result", 1.0, busy=False)

    def _publish_cached(self, view: AppState, key: tuple) -> bool:
        with self._cache_lock:
            entry = self._cache.get(key)
            if entry is not None:
                self._cache.move_to_end(key)
        if entry is None:
            entry = self._shown_elsewhere(key)
            if entry is None:
                return False
            self._remember(key, *entry)
        kind, result, status, selections = entry
        status = f"{status.removesuffix(' (from the cache)')} (from the cache)"
        self._show(view, key, kind, result, status, selections)
        return True

    @staticmethod
    def _show(view: AppState, key: tuple, kind: str, result, status: str, selections: dict) -> None:
        """Make ``result`` (a "detection" or a "proposal" result) ``view``'s shown one."""
        if kind == "detection":
            view.set_detection_result(key, result, status, selections)
        else:
            view.set_pipeline_result(key, result, status)

    def _remember(self, key: tuple, kind: str, result, status: str, selections: dict) -> None:
        """Cache a result; beyond ``MAX_CACHED_RESULTS``, the least recently used one that is not
        a view's frame or its neighbour goes first (one browser flipping through frames does not
        evict another's)."""
        views = self._served()
        wanted = {
            (view.frame_index + offset, *view.pipeline_key()[1:])
            for view in views
            for offset in (0, *PREFETCH_OFFSETS)
        }
        capacity = min(MAX_CACHED_RESULTS, CACHED_RESULTS * max(1, len(views)))
        with self._cache_lock:
            self._cache[key] = (kind, result, status, selections)
            self._cache.move_to_end(key)
            while len(self._cache) > capacity:
                spare = next((k for k in self._cache if k not in wanted), next(iter(self._cache)))
                del self._cache[spare]

    def stop(self, timeout: float | None = None) -> None:
        """Stop the thread after its current frame; with ``timeout``, wait for it that long (a
        computation ahead stops at its next stage)."""
        with self._wake:
            self._stopped = True
            self._wake.notify()
        if timeout is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending or self._stopped)
                if self._stopped:
                    return
                self._pending = False
            for view in self._views():
                key = view.pipeline_key()
                with view.lock:
                    done = key in (view.pipeline_result_key, view.pipeline_failed_key)
                if done or self._publish_cached(view, key):
                    continue
                try:
                    self._compute(key)
                except Exception as exc:  # keep the app alive; show what went wrong
                    traceback.print_exc()
                    for wanting in self._wanting(key):
                        wanting.set_pipeline_failed(key, f"failed: {exc}")
                    self._release_others()
                with self._wake:
                    if self._pending or self._stopped:  # someone asked meanwhile: the latest first
                        break
            else:
                self._compute_ahead()

    def _compute_ahead(self) -> None:
        """Compute each view's neighbouring frames into the cache until a request comes."""
        with self.shared.lock:
            if self.shared.training_busy:
                return
        num_frames = self.shared.dataset.num_frames
        for view in self._views():
            key = view.pipeline_key()
            with view.lock:
                if key != view.pipeline_result_key:
                    continue
            for offset in PREFETCH_OFFSETS:
                index = key[0] + offset
                ahead = (index, *key[1:])
                with self._cache_lock:
                    cached = ahead in self._cache
                if cached or not 0 <= index < num_frames:
                    continue
                with self._wake:
                    if self._pending or self._stopped:
                        return
                with self._cache_lock:
                    self._ahead_key = ahead
                try:
                    self._compute(ahead, ahead=True)
                except _GaveWayError:
                    return
                except Exception:  # the frame's own run, when asked for, reports what went wrong
                    traceback.print_exc()
                    return
                finally:
                    with self._cache_lock:
                        self._ahead_key = None

    def _compute(self, key: tuple, ahead: bool = False) -> None:
        """Compute ``key``'s result into the cache and show it in the views that still ask for it.
        Ahead of a request (``ahead``), progress stays quiet until a view asks for the frame, and
        a request for another frame stops the work at the next stage (``_GaveWayError``)."""
        frame_index, params, use_refined, _ = key
        dataset = self.shared.dataset
        if use_refined and self.calibrate and dataset.num_sensors > 1 and self._refined_extrinsics is None:
            for view in self._wanting(key):
                view.set_pipeline_progress("refining the sensor extrinsics (ICP, once)", 0.02)
            detector = Detector(params)
            if self.shared.db is not None:  # (read back from the session after its first time)
                cached_calibration(self.shared.db, dataset, detector, frame_index)
            else:
                detector.calibrate(dataset.frame(frame_index))
            self._refined_extrinsics = detector.T_vehicle_sensor
        extrinsics = self._refined_extrinsics if use_refined else None
        detector = Detector(params, extrinsics, model=self.shared.model)
        frame = dataset.frame(frame_index)
        history = detector.history(dataset, frame_index)

        def progress(stage: str, fraction: float) -> None:
            wanting = self._wanting(key)
            if ahead and not wanting:
                with self._wake:
                    if self._pending or self._stopped:
                        raise _GaveWayError
                return
            for view in wanting:
                view.set_pipeline_progress(f"frame {frame_index + 1}: {stage} done", fraction)

        if not ahead:
            for view in self._wanting(key):
                view.set_pipeline_progress(f"frame {frame_index + 1}: merging", 0.05)
        if detector.model is not None:
            detection = detector.detect(frame, history, progress=progress)
            result = detection.proposal
        else:
            detection, result = None, detector.propose(frame, history, progress=progress)
        # The voxels layer's colours, computed here in the background rather than when drawing,
        # if a view shows that layer: they take a detection's frame its 3DmFV again (seconds on two
        # cores), for a layer hidden by default; a view that shows it later has them computed when
        # drawn (``layers.LayerView``). The vectors themselves (10 kB a voxel, most of a result)
        # are not kept.
        result = dataclasses.replace(
            result,
            voxel_features=None,
            voxel_colors=(
                voxel_colors(result.cloud, result.grid, result.voxel_features)
                if self._voxels_shown()
                else None
            ),
        )
        if detection is not None:
            detection = dataclasses.replace(detection, proposal=result)
        segmentation = result.segmentation
        status = (
            f"frame {frame_index + 1}: {len(result.proposals):,} proposals, {segmentation.num_segments:,} "
            f"segments, {segmentation.num_patches:,} patches, {result.grid.num_voxels:,} voxels in "
            f"{result.timings_ms['total'] / 1000:.1f} s"
            + (" (refined extrinsics)" if extrinsics is not None else "")
        )
        if detection is not None:
            status += f"; classified and NMS in {detection.timings_ms['total'] / 1000:.1f} s in all"
        kind, kept = ("proposal", result) if detection is None else ("detection", detection)
        # The views' selections of the detections, made here in the background: a frame change
        # then runs no NMS on the GUI's thread.
        selections = {} if detection is None else self._selections_ahead(detection.candidates)
        self._remember(key, kind, kept, status, selections)
        for view in self._wanting(key):
            self._show(view, key, kind, kept, status, selections)
        if not ahead:
            # A view that moved on has a newer request queued, unless it came back to the frame
            # and parameters of the result it shows, which is then current again.
            self._release_others()


def place_frames(state: SharedState) -> None:
    """Place the session's frames in one world frame (label once), reporting progress in
    ``state.world_status``; run once on its own thread when the app opens a session. A failure
    leaves labels per frame and says why. The frames are registered with the library's settled
    calibration (``world.registration_extrinsics``), or with the nominal extrinsics when the app
    runs without calibrating: the poses are the vehicle's, whatever the viewer draws with.
    """
    dataset = state.dataset
    # The first frame's detections are what a person waits for: ICP would share the two cores
    # with them, so it starts once a view shows them (or they failed), or after a minute anyway.
    state.wait_for(
        lambda: any(
            view.pipeline_result is not None or view.pipeline_failed_key is not None
            for view in state.views + state.templates
        ),
        60.0,
    )

    last = [0.0]

    def progress(done: int, total: int) -> None:
        # Each report refreshes every browser's panels: at most one a second.
        now = time.monotonic()
        if now - last[0] >= 1.0 or done == total:
            last[0] = now
            state.set_world(None, f"placing the frames in one world frame: {done}/{total}")

    try:
        nominal = None if state.use_refined_extrinsics else dataset.T_vehicle_sensor
        world, from_cache = session_world(state.db.session, dataset, nominal, progress)
    except Exception as exc:  # noqa: BLE001 - a thread of its own: say why, keep labels per frame
        state.set_world(
            None, f"labels stay per frame: placing the frames failed ({type(exc).__name__}: {exc})"
        )
        return
    placed = "placed (poses from the session's cache)" if from_cache else "placed by ICP"
    state.set_world(world, f"{world.num_frames} frames {placed}")
    import_annotations_ahead(state.db, dataset.num_frames)


def import_annotations_ahead(db, num_frames: int, chunk: int = 32) -> int:
    """Import the data set's annotations of every frame not imported yet, ``chunk`` frames per
    write (``SessionDB.ensure_frames``), so that no one waits for them later. With label once, the
    first edit of an object reaches every frame that shows it, and importing those frames then
    (reading each frame file) took half a second of that edit on the demo. A chunk that fails is
    imported frame by frame, and a frame that fails (damaged annotations, a busy database) is
    left as it was: it is imported, or its error raised with its message, when it is used.
    Returns how many frames are imported now."""
    if db is None or db.readonly:
        return 0
    done = 0
    for start in range(0, num_frames, chunk):
        frames = range(start, min(start + chunk, num_frames))
        try:
            db.ensure_frames(frames)
            done += len(frames)
            continue
        except Exception:  # noqa: BLE001 - a thread of its own: frame by frame, below
            pass
        for frame_index in frames:
            try:
                db.ensure_frames([frame_index])
            except Exception:  # noqa: BLE001 - the frame's own use says why
                continue
            done += 1
    return done
