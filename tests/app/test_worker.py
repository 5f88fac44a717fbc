"""The background worker: latest request wins, failures are shown and not retried in a loop, the
next and previous frames are computed ahead and a cached frame shows at once, and every view
(browser) gets its own frame's result."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest

from app.state import AppState
from app.worker import PipelineWorker
from factorydet_core.detection import detector as detector_module
from factorydet_core.io.dataset import open_dataset

from .polling import wait


def _wire(state: AppState, worker: PipelineWorker) -> None:
    # What the viewer does: every change to a view may ask for a run.
    state.on_change(lambda: worker.maybe_request(state))


def test_a_failing_run_is_reported_once_and_retried_only_after_a_change(small_dataset_dir, monkeypatch):
    calls = []

    def failing_propose(self, frame, history=(), progress=None):
        calls.append(frame.name)
        if progress is not None:
            progress("merge", 0.2)  # progress updates must not re-queue the same run
        raise RuntimeError("boom")

    monkeypatch.setattr(detector_module.Detector, "propose", failing_propose)
    state = AppState(open_dataset(small_dataset_dir))
    worker = PipelineWorker(state.shared, calibrate=False)
    _wire(state, worker)
    try:
        worker.request()
        assert state.wait_for(lambda: state.pipeline_status.startswith("failed"), timeout=20)
        time.sleep(0.5)
        assert calls == ["frame_00000"] and not state.pipeline_busy
        state.set_params(merge_threshold=0.5)  # a change: one new attempt
        assert state.wait_for(lambda: len(calls) == 2, timeout=20)
        time.sleep(0.5)
        assert len(calls) == 2
    finally:
        worker.stop(timeout=120)  # its frame's work must not reach the next test's records


def _record_propose(monkeypatch, hold_frame_1: threading.Event | None = None) -> tuple[list, threading.Event]:
    """Record the frames the detector proposes; with ``hold_frame_1``, frame 1 waits for it (and
    the returned event says it started)."""
    original = detector_module.Detector.propose
    computed, started = [], threading.Event()

    def recording(self, frame, history=(), progress=None):
        computed.append(frame.name)
        if hold_frame_1 is not None and frame.name == "frame_00001":
            started.set()
            hold_frame_1.wait(60)
        return original(self, frame, history, progress)

    monkeypatch.setattr(detector_module.Detector, "propose", recording)
    return computed, started


@contextlib.contextmanager
def _running_worker(dataset_dir, release: threading.Event | None = None):
    """A wired worker whose first frame is shown; stopped (and ``release`` set) on leaving."""
    state = AppState(open_dataset(dataset_dir))
    worker = PipelineWorker(state.shared, calibrate=False)
    _wire(state, worker)
    try:
        worker.request()
        assert state.wait_for(lambda: state.pipeline_result is not None, timeout=120)
        yield state, worker
    finally:
        if release is not None:
            release.set()
        worker.stop(timeout=120)  # its frame's work must not reach the next test's records


def test_coming_back_to_the_shown_frame_clears_the_busy_state(small_dataset_dir, monkeypatch):
    release = threading.Event()
    _record_propose(monkeypatch, hold_frame_1=release)
    with _running_worker(small_dataset_dir, release) as (state, _):
        state.set_frame(1)  # starts the slow run (or takes over the one computed ahead)
        assert state.wait_for(lambda: state.pipeline_busy, timeout=20)
        state.set_frame(0)  # back to the result that is shown
        release.set()
        assert state.wait_for(lambda: not state.pipeline_busy, timeout=120), state.pipeline_status
        assert state.pipeline_result_key[0] == 0


def test_neighbours_are_computed_ahead_and_a_cached_frame_shows_at_once(small_dataset_dir, monkeypatch):
    with _running_worker(small_dataset_dir) as (state, worker):
        assert wait(lambda: 1 in worker.cached_frames(state), timeout=120), worker.cached_frames(state)
        computed, _ = _record_propose(monkeypatch)
        state.set_frame(1)
        # Shown on the calling thread, before this returns: nothing computed it again.
        with state.lock:
            assert state.pipeline_result_key[0] == 1 and not state.pipeline_busy
            assert state.pipeline_status.endswith("(from the cache)")
            shown = state.pipeline_result
        assert "frame_00001" not in computed
        fresh = detector_module.Detector(state.params).propose(state.frame)
        np.testing.assert_array_equal(shown.proposals.boxes, fresh.proposals.boxes)
        # A result keeps neither its voxels' 3DmFV (10 kB a voxel) nor, with the voxels layer
        # hidden (the default), their colours: seconds of a frame's time for a layer nobody shows.
        assert shown.voxel_features is None and shown.voxel_colors is None
        # The new frame's next one is computed ahead in turn.
        assert wait(lambda: 2 in worker.cached_frames(state), timeout=120), worker.cached_frames(state)
        # Other parameters: nothing of the cache applies.
        state.set_params(merge_threshold=0.5)
        assert worker.cached_frames(state) == [] or state.pipeline_busy


def test_a_computation_ahead_gives_way_to_a_request_for_another_frame(small_dataset_dir, monkeypatch):
    release = threading.Event()
    computed, started = _record_propose(monkeypatch, hold_frame_1=release)
    with _running_worker(small_dataset_dir, release) as (state, worker):
        assert started.wait(60)  # frame 1 is being computed ahead
        assert not state.pipeline_busy  # quietly
        state.set_frame(2)  # the small data set's last frame
        release.set()
        assert state.wait_for(lambda: state.pipeline_result_key[0] == 2, timeout=120), state.pipeline_status
        # Frame 1's work stopped at its first stage: it is not cached, and frame 2 ran next.
        assert 1 not in worker.cached_frames(state)
        assert computed[:3] == ["frame_00000", "frame_00001", "frame_00002"]


def test_each_view_gets_its_own_frame_and_views_of_one_frame_share_its_run(small_dataset_dir, monkeypatch):
    computed, _ = _record_propose(monkeypatch)
    state = AppState(open_dataset(small_dataset_dir))
    other, same = state.shared.new_view(), state.shared.new_view()
    worker = PipelineWorker(state.shared, calibrate=False)
    for view in (state, other, same):
        _wire(view, worker)
    try:
        other.set_frame(2)
        worker.request()
        assert state.wait_for(
            lambda: all(view.pipeline_result is not None for view in (state, other, same)), timeout=120
        ), [view.pipeline_status for view in (state, other, same)]
        assert [view.pipeline_result_key[0] for view in (state, other, same)] == [0, 2, 0]
        assert state.pipeline_result is same.pipeline_result  # frame 0 was computed once for both
        assert computed.count("frame_00000") == 1 and computed.count("frame_00002") == 1
        # A view that leaves is no longer served; the others keep their frames.
        other.close()
        assert other not in state.shared.views and state.frame_index == 0
    finally:
        worker.stop(timeout=120)  # its frame's work must not reach the next test's records


def test_a_template_is_computed_only_before_any_browser_and_a_shown_frame_is_not_recomputed(
    small_dataset_dir, monkeypatch
):
    computed, _ = _record_propose(monkeypatch)
    template = AppState(open_dataset(small_dataset_dir), served=False)  # what the app opens with
    shared = template.shared
    worker = PipelineWorker(shared, calibrate=False)
    _wire(template, worker)
    try:
        worker.request()
        assert wait(lambda: {0, 1} <= set(worker.cached_frames(template)), timeout=120)
        view = shared.new_view(like=template)  # a browser comes: frame 0 is there already
        _wire(view, worker)
        worker.maybe_request(view)
        assert view.pipeline_result_key[0] == 0 and computed == ["frame_00000", "frame_00001"]
        view.set_frame(2)
        assert view.wait_for(lambda: view.pipeline_result_key[0] == 2, timeout=120)
        view.set_selection("a patch")
        # Another browser comes to the same frame after its cache entry went: it takes the shown
        # result; nothing is computed again and the first browser's selection stays.
        with worker._cache_lock:
            worker._cache.clear()
        other = shared.new_view(like=view)
        _wire(other, worker)
        worker.maybe_request(other)
        assert other.pipeline_result is view.pipeline_result and computed.count("frame_00002") == 1
        assert view.selection_markdown == "a patch"
        # The template's frame is nobody's now: a change of parameters computes only the browsers'.
        assert wait(lambda: worker.idle, timeout=120)
        del computed[:]
        shared.set_params(merge_threshold=0.5)
        assert wait(lambda: worker.idle and view.pipeline_result_key[1] == shared.params, timeout=120)
        assert computed[0] == "frame_00002" and "frame_00000" not in computed[:2]
    finally:
        worker.stop(timeout=120)  # its frame's work must not reach the next test's records


@pytest.mark.slow
def test_a_cached_frame_shows_its_detections_selected_ahead(small_dataset_dir, tiny_model_path, monkeypatch):
    from app import state as state_module
    from factorydet_core.detection.model import DetectionModel

    model = DetectionModel.load(tiny_model_path)
    state = AppState(open_dataset(small_dataset_dir), model=model, model_name="tiny")
    worker = PipelineWorker(state.shared, calibrate=False)
    _wire(state, worker)
    try:
        worker.request()
        assert wait(lambda: 1 in worker.cached_frames(state), timeout=300), worker.cached_frames(state)
        here, original = [], state_module.select_detections

        def counting(*args, **kwargs):
            if threading.current_thread() is threading.main_thread():
                here.append(1)
            return original(*args, **kwargs)

        monkeypatch.setattr(state_module, "select_detections", counting)
        state.set_frame(1)
        # Shown from the cache with its selections made in the background: no NMS on this thread.
        assert state.detection_frame_index == 1 and here == []
        expected = state_module.select_with(
            state.detection_result.candidates, "shown", state.selection_args()
        )
        np.testing.assert_array_equal(state.detections.boxes, expected.boxes)
        np.testing.assert_array_equal(state.detections.suppressed_by, expected.suppressed_by)
        floor = state.frame_detections[1]["floor"]
        expected_floor = state_module.select_with(
            state.detection_result.candidates, "floor", state.floor_args()
        )
        np.testing.assert_array_equal(floor.boxes, expected_floor.boxes)
        state.set_detection_filter(score_threshold=0.2)  # other sliders: selected now, here
        assert here
    finally:
        worker.stop(timeout=120)


@pytest.mark.parametrize("refined", [True, False])
def test_label_once_registers_with_the_librarys_calibration_unless_the_app_draws_the_nominal_one(
    small_dataset_dir, tmp_path, monkeypatch, refined
):
    from app import worker as worker_module
    from app.worker import place_frames
    from factorydet_core.session.store import SessionDB, open_session

    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    state.shared.use_refined_extrinsics = refined
    state.pipeline_failed_key = ("shown",)  # the first frame is settled: placing starts at once
    asked = []

    def fake_session_world(session, data, T_vehicle_sensor=None, progress=None):
        asked.append(T_vehicle_sensor)
        raise RuntimeError("stop here")

    monkeypatch.setattr(worker_module, "session_world", fake_session_world)
    place_frames(state.shared)
    # None: session_world registers with world.registration_extrinsics (cached with the poses).
    if refined:
        assert asked == [None]
    else:
        np.testing.assert_array_equal(asked[0], dataset.T_vehicle_sensor)
    assert state.shared.world is None and "placing the frames failed" in state.shared.world_status


def test_a_result_keeps_its_voxels_colours_when_a_view_shows_the_voxels_layer(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    state.set_layer("voxels", True)
    worker = PipelineWorker(state.shared, calibrate=False)
    _wire(state, worker)
    try:
        worker.request()
        assert state.wait_for(lambda: state.pipeline_result is not None, timeout=120)
        with state.lock:
            shown = state.pipeline_result
        assert shown.voxel_features is None and shown.voxel_colors.shape == (shown.grid.num_voxels, 3)
    finally:
        worker.stop(timeout=120)


def test_annotations_are_imported_ahead_so_that_no_later_edit_reads_a_frame_file(
    small_dataset_dir, tmp_path, monkeypatch
):
    from app.worker import import_annotations_ahead
    from factorydet_core.session.store import SessionDB, SessionError, open_session

    dataset = open_dataset(small_dataset_dir)
    expected = [len(dataset.frame(f).labels.boxes) for f in range(dataset.num_frames)]
    db = SessionDB(open_session("s", tmp_path), dataset)
    assert import_annotations_ahead(db, dataset.num_frames) == dataset.num_frames
    for read in ("frame", "frame_labels"):
        monkeypatch.setattr(dataset, read, lambda index: pytest.fail(f"frame {index} read again"))
    assert [len(db.labels(f)) for f in range(dataset.num_frames)] == expected
    assert import_annotations_ahead(db, dataset.num_frames) == dataset.num_frames  # nothing to do

    # A frame whose annotations fail is left out; the others are imported (its own use says why).
    other_dataset = open_dataset(small_dataset_dir)
    other = SessionDB(open_session("t", tmp_path), other_dataset)
    annotations = other._annotations

    def damaged(frame_index):
        if frame_index == 1:
            raise SessionError(f"frame {frame_index}: damaged annotation")
        return annotations(frame_index)

    monkeypatch.setattr(other, "_annotations", damaged)
    assert import_annotations_ahead(other, dataset.num_frames, chunk=2) == dataset.num_frames - 1
    for read in ("frame", "frame_labels"):
        monkeypatch.setattr(other_dataset, read, lambda index: pytest.fail(f"frame {index} read again"))
    assert [len(other.labels(f)) for f in range(dataset.num_frames) if f != 1] == [
        n for f, n in enumerate(expected) if f != 1
    ]
    assert import_annotations_ahead(None, dataset.num_frames) == 0
