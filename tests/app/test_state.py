import threading

import numpy as np
import pytest

from app.state import AppState, select_with
from factorydet_core.io.dataset import open_dataset
from tests.app.polling import wait


def test_frame_changes_are_clamped_counted_and_announced(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    seen = []
    state.on_change(lambda: seen.append(state.frame_index))
    state.step_frame(+1)
    state.set_frame(99)
    state.step_frame(+1)  # already at the last frame: no change
    state.set_frame(-5)
    assert seen == [1, 2, 0] and state.num_frame_changes == 3
    assert state.frame.name == "frame_00000"


def test_display_settings_are_validated(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    assert state.color_mode == "sensor"
    state.set_display(color_mode="class", point_size=0.1, show_boxes=False, max_height=3.0)
    assert (state.color_mode, state.point_size, state.show_boxes, state.max_height) == (
        "class",
        0.1,
        False,
        3.0,
    )
    with pytest.raises(ValueError, match="unknown colour mode"):
        state.set_display(color_mode="rainbow")


def test_real_files_open_in_their_own_colours():
    from app.scene import point_colors
    from tests.conftest import SHARED_REAL

    path = SHARED_REAL / "scannet_scene0000_00.npz"
    if not path.exists():
        pytest.skip(f"{SHARED_REAL} is not beside the repository")
    state = AppState(open_dataset(path))
    assert state.color_mode == "rgb" and state.dataset.num_frames == 1
    frame = state.frame
    assert (point_colors(frame, frame.points, "rgb") == frame.colors).all()
    by_class = point_colors(frame, frame.points, "class")
    assert by_class.shape == (frame.num_points, 3) and len(np.unique(by_class, axis=0)) > 5


def test_rgb_mode_falls_back_to_height_without_colours(small_dataset_dir):
    from app.scene import point_colors
    from factorydet_core.colors import colors_by_height

    frame = open_dataset(small_dataset_dir).frame(0)
    z = frame.points[:, 2]
    assert (point_colors(frame, frame.points, "rgb") == colors_by_height(z)).all()


def test_class_and_annotated_colours_follow_the_sessions_labels(small_dataset_dir):
    from app.scene import point_colors
    from factorydet_core.colors import colors_by_class

    frame = open_dataset(small_dataset_dir).frame(0)
    points = np.array([[0.0, 0.0, 0.5], [5.0, 0.0, 0.5], [5.1, 0.0, 0.5], [20.0, 0.0, 0.5]], np.float32)
    boxes = np.array([[0.0, 0.0, 0.5, 1, 1, 1, 0], [5.0, 0.0, 0.5, 1, 1, 1, 0]], np.float64)
    by_class = point_colors(frame, points, "class", (boxes, np.array([3, 0])))
    expected = colors_by_class(np.array([3, 0, 0, -1]), frame.class_names)
    assert (by_class == expected).all()
    labelled = point_colors(frame, points, "annotated", (boxes, np.array([3, 0])))
    assert (labelled[:3] == labelled[0]).all() and not (labelled[3] == labelled[0]).all()


@pytest.mark.slow
def test_detection_filters_refilter_and_feed_the_metrics(small_dataset_dir, tiny_model_path):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.detection.scoring import select_detections
    from factorydet_core.evaluation.diagnostics import describe_detection, detection_markdown

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    state = AppState(dataset, model=model, model_name="tiny")
    assert state.layers["detections"] and not state.layers["proposals"]
    result = Detector("agv", model=model).detect(dataset.frame(0))
    state.set_detection_result((0, state.params, False), result, "done")
    assert state.pipeline_result is result.proposal and state.metrics["num_frames"] == 1
    state.set_detection_filter(score_threshold=0.05, nms_iou=0.25)
    low = state.detections
    assert (low.scores >= 0.05).all() and len(low) == (result.candidates.scores >= 0.05).sum()
    state.set_detection_filter(nms_iou=0.95)
    assert state.detections.kept_mask.sum() >= low.kept_mask.sum()
    assert state.metrics["score_threshold"] == 0.05
    # The kinds of errors are counted at the same operating point as the table.
    errors = state.metrics["errors"]
    assert errors["f1"] == pytest.approx(state.metrics["f1"], abs=1e-3)
    assert errors["num_detections"] == state.metrics["num_detections"]
    # Box voting: the model's IoU by default; 0 switches it off, and the kept boxes are then the
    # candidates' own.
    assert state.vote_iou == (model.vote_iou or 0.0)
    state.set_detection_filter(nms_iou=0.25, vote_iou=0.0)
    plain = state.detections
    unvoted = select_detections(result.candidates, 0.05, 0.25, vote_iou=None)
    np.testing.assert_array_equal(plain.boxes, unvoted.boxes)
    state.set_detection_filter(vote_iou=0.1)
    voted = state.detections
    np.testing.assert_array_equal(voted.kept_mask, plain.kept_mask)  # voting moves boxes only
    np.testing.assert_array_equal(
        voted.boxes, select_detections(result.candidates, 0.05, 0.25, vote_iou=0.1).boxes
    )
    with pytest.raises(ValueError):
        state.set_detection_filter(vote_iou=1.5)
    # A suppressed detection's description names who suppressed it.
    suppressed = np.flatnonzero(~low.kept_mask)
    if len(suppressed):
        info = describe_detection(low, int(suppressed[0]), result.proposal.proposals, dataset.frame(0))
        assert "suppressed by" in info
        assert detection_markdown(info).startswith("**Detection:")
    kept = int(np.flatnonzero(low.kept_mask)[0])
    info = describe_detection(low, kept, result.proposal.proposals, dataset.frame(0))
    assert info["proposal"].startswith(f"#{int(low.proposal_ids[kept])}")


def test_per_class_thresholds_until_the_slider_moves(small_dataset_dir, tiny_model_path):
    import dataclasses

    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel

    dataset = open_dataset(small_dataset_dir)
    # (the tiny model may have tuned a threshold or two: this test sets its own)
    base = dataclasses.replace(DetectionModel.load(tiny_model_path), class_score_thresholds=None)
    assert not AppState(dataset, model=base, model_name="tiny").use_class_thresholds
    result = Detector("agv", model=base).detect(dataset.frame(0))
    scores, classes = result.candidates.scores, result.candidates.class_ids
    top_class = int(np.bincount(classes).argmax())
    names = base.class_names
    # The most frequent class needs a score above every candidate's; the others pass at 0.
    tuned = {name: (1.0 if c == top_class else 0.0) for c, name in enumerate(names)}
    model = dataclasses.replace(base, class_score_thresholds=tuned)
    state = AppState(dataset, model=model, model_name="tuned")
    assert state.use_class_thresholds
    state.set_detection_result((0, state.params, False), result, "done")
    shown = state.detections
    assert not (shown.class_ids == top_class).any() and len(shown) == (classes != top_class).sum()
    assert state.metrics["class_score_thresholds"][names[top_class]] == 1.0
    # Moving the score slider sets one threshold for every class.
    state.set_detection_filter(score_threshold=0.05)
    assert not state.use_class_thresholds and "class_score_thresholds" not in state.metrics
    assert len(state.detections) == (scores >= 0.05).sum()
    state.set_detection_filter(use_class_thresholds=True)
    assert state.use_class_thresholds and len(state.detections) == len(shown)
    # A model without them cannot switch them on.
    state.set_model(base, "tiny")
    state.set_detection_filter(use_class_thresholds=True)
    assert not state.use_class_thresholds


def test_session_labels_drive_the_view_and_a_model_switch_resets_detections(
    small_dataset_dir, tiny_model_path, tmp_path
):
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.store import SessionDB, open_session

    dataset = open_dataset(small_dataset_dir)
    read_only = AppState(dataset)
    boxes, class_ids, ids = read_only.frame_labels()
    assert len(boxes) == len(dataset.frame(0).labels) and (ids == -1).all() and not read_only.editable

    db = SessionDB(open_session("s", tmp_path), dataset)
    state = AppState(dataset, db=db)
    assert state.editable
    label = db.labels(0)[0]
    db.delete_labels([label.id], "ann")
    seen = []
    state.on_change(lambda: seen.append(state.revision))
    state.session_changed()
    boxes, _, ids = state.frame_labels()
    assert seen == [1] and label.id not in ids.tolist() and len(boxes) == len(dataset.frame(0).labels) - 1

    key = state.pipeline_key()
    model = DetectionModel.load(tiny_model_path)
    state.set_model(model, "tiny")
    assert state.pipeline_key() != key and state.model_name == "tiny"
    assert state.detections is None and state.frame_detections == {} and state.metrics is None
    assert state.score_threshold == model.score_threshold


def test_each_view_has_its_own_frame_display_and_thresholds(small_dataset_dir, tiny_model_path, tmp_path):
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.store import SessionDB, open_session

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    db = SessionDB(open_session("s", tmp_path), dataset)
    first = AppState(dataset, model=model, model_name="tiny", db=db)
    first.set_frame(2)
    first.set_display(color_mode="height", point_size=0.1, points_drawn=20_000)
    first.set_detection_filter(score_threshold=0.3, nms_iou=0.4)
    second = first.shared.new_view()  # a new browser: the defaults
    like = first.shared.new_view(like=first)  # one that starts like the first
    assert (second.frame_index, second.point_size, second.nms_iou, second.points_drawn) == (
        0, 0.04, model.nms_iou, None
    )  # fmt: skip
    assert (like.frame_index, like.color_mode, like.score_threshold, like.nms_iou) == (2, "height", 0.3, 0.4)
    assert like.points_drawn == 20_000
    seen = {view: [] for view in (first, second, like)}
    for view in seen:
        view.on_change(lambda view=view: seen[view].append(view.frame_index))

    second.set_frame(1)  # one browser's change redraws that browser alone
    second.set_display(show_boxes=False)
    assert seen == {first: [], second: [1, 1], like: []}
    assert first.frame_index == 2 and first.show_boxes and not second.show_boxes

    first.shared.set_params(merge_threshold=0.5)  # the front half's parameters are everyone's
    db.delete_labels([db.labels(0)[0].id], "ann")
    first.session_changed()  # as is the session
    assert all(len(frames) >= 2 for frames in (seen[first], seen[like])) and len(seen[second]) == 4
    assert first.params is second.params and first.revision == second.revision == 1
    other = DetectionModel.load(tiny_model_path)
    second.set_model(other, "other")  # and the model: every view takes its thresholds
    assert all(view.model is other and view.nms_iou == other.nms_iou for view in seen)


def test_the_selection_key_of_partial_class_thresholds_finds_itself(small_dataset_dir, tiny_model_path):
    import dataclasses

    from app.state import select_with
    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel

    dataset = open_dataset(small_dataset_dir)
    model = dataclasses.replace(DetectionModel.load(tiny_model_path), class_score_thresholds={"truck": 0.9})
    state = AppState(dataset, model=model, model_name="partial")
    key = ("shown", *state.selection_args())
    # Every class but trucks keeps the global threshold; the key holds no NaN, so it finds itself.
    assert key == ("shown", *state.selection_args()) and {key: 1}.get(("shown", *state.selection_args()))
    per_class = key[3]
    assert per_class[model.class_names.index("truck")] == 0.9 and per_class.count(None) == len(per_class) - 1
    candidates = Detector("agv", model=model).detect(dataset.frame(0)).candidates
    shown = select_with(candidates, "shown", key[1:])
    trucks = shown.class_ids == model.class_names.index("truck")
    assert (shown.scores[trucks] >= 0.9).all() and (shown.scores >= state.score_threshold).all()


def test_the_metrics_are_measured_again_only_when_what_they_measure_changed(
    small_dataset_dir, tiny_model_path, tmp_path
):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.store import SessionDB, open_session

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    db = SessionDB(open_session("s", tmp_path), dataset)
    state = AppState(dataset, model=model, model_name="tiny", db=db)
    results = [Detector("agv", model=model).detect(dataset.frame(i)) for i in (0, 1)]
    state.set_detection_result((0, state.params, False), results[0], "done")
    state.set_detection_filter(score_threshold=0.05)
    first = state.metrics
    # A write that moves no label (a verdict of background, say): the same metrics, not measured again.
    state.session_changed()
    assert state.metrics is first
    # Another frame: measured again, over both frames; back to the first frame with the same
    # detections (the worker's cache): the frame is shown, the metrics stay.
    state.set_detection_result((1, state.params, False), results[1], "done")
    both = state.metrics
    assert both is not first and both["num_frames"] == 2
    state.set_detection_result((0, state.params, False), results[0], "done (from the cache)")
    assert state.metrics is both and state.detection_frame_index == 0
    shown = select_with(results[0].candidates, "shown", state.selection_args())
    np.testing.assert_array_equal(state.detections.boxes, shown.boxes)
    # A label deleted: measured again against the labels left (one reference fewer).
    label = db.labels(0)[0]
    db.delete_labels([label.id], "ann")
    state.session_changed()
    assert state.metrics is not both
    assert state.metrics["num_reference"] == both["num_reference"] - 1
    # Labels changed by another process (no session_changed here): the frame viewed again is
    # measured against them.
    db.delete_labels([db.labels(1)[0].id], "cli")
    before = state.metrics
    state.set_detection_result((1, state.params, False), results[1], "done (from the cache)")
    assert state.metrics is not before
    assert state.metrics["num_reference"] == before["num_reference"] - 1
    # The frame's detections computed again (another result): measured again too.
    again = Detector("agv", model=model).detect(dataset.frame(0))
    before = state.metrics
    state.set_detection_result((0, state.params, False), again, "done")
    assert state.metrics is not before and state.metrics["num_frames"] == 2


@pytest.fixture
def measured(small_dataset_dir, tiny_model_path, tmp_path):
    """A view with a session, its first frame's detections shown and its metrics measured:
    ``(state, db, metrics)``."""
    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.store import SessionDB, open_session

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    db = SessionDB(open_session("s", tmp_path), dataset)
    state = AppState(dataset, model=model, model_name="tiny", db=db)
    state.set_detection_result(
        (0, state.params, False), Detector("agv", model=model).detect(dataset.frame(0)), "done"
    )
    return state, db, state.metrics


def _on_the_metrics_thread(monkeypatch, before=lambda: None):
    """``state._measure`` patched to call ``before()`` first when run on the background thread."""
    import app.state as state_module

    measure = state_module._measure

    def patched(inputs, *args):
        if threading.current_thread().name == "factorydet-metrics":
            before()
        return measure(inputs, *args)

    monkeypatch.setattr(state_module, "_measure", patched)


def _held(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """The background measurement held until released: ``(measuring, release)``."""
    measuring, release = threading.Event(), threading.Event()

    def hold():
        measuring.set()
        assert release.wait(30)

    _on_the_metrics_thread(monkeypatch, hold)
    return measuring, release


def test_an_edit_returns_before_the_metrics_are_measured_again_on_the_background_thread(
    measured, monkeypatch
):
    state, db, before = measured
    # The measurement held back until the edit has returned (as a slow one is on a busy machine).
    measuring, release = _held(monkeypatch)
    redrawn = threading.Event()
    state.on_change(redrawn.set)
    db.delete_labels([db.labels(0)[0].id], "ann")
    state.session_changed()
    assert measuring.wait(30)
    # The edit has returned; the view shows the metrics it had, said to be out of date.
    assert state.shown_metrics() == (before, True)
    redrawn.clear()
    release.set()
    assert redrawn.wait(30)  # the new metrics came, and the view was redrawn for them
    after, stale = state.shown_metrics()
    assert not stale and after["num_reference"] == before["num_reference"] - 1


def test_a_run_of_edits_is_measured_once_after_a_quiet_period(measured, monkeypatch):
    """Edits in quick succession (a reviewer's verdicts) are measured once, after the last of
    them, not alongside each: the background thread waits until no request came for
    ``QUIET_SECONDS``."""
    import time

    state, db, before = measured
    runner = state.shared.metrics_runner
    runner.QUIET_SECONDS = 2.0  # (long against three edits, on a loaded machine too)
    started: list[float] = []
    _on_the_metrics_thread(monkeypatch, lambda: started.append(time.monotonic()))
    last = 0.0
    for _ in range(3):
        db.delete_labels([db.labels(0)[0].id], "ann")
        last = time.monotonic()
        state.session_changed()
    assert wait(lambda: not state.shown_metrics()[1], 30)
    assert len(started) == 1 and started[0] - last >= 2.0
    assert state.shown_metrics()[0]["num_reference"] == before["num_reference"] - 3


def test_reading_the_metrics_measures_them_at_once_and_a_superseded_measurement_is_dropped(
    measured, monkeypatch
):
    state, db, before = measured
    measuring, release = _held(monkeypatch)
    state.shared.metrics_runner.IDLE_SECONDS = 0.01  # its thread ends once idle (joined below)
    db.delete_labels([db.labels(0)[0].id], "ann")
    state.session_changed()
    assert measuring.wait(30)
    # A reader that needs the figures gets them measured now, while the background thread is held.
    now = state.metrics
    assert now["num_reference"] == before["num_reference"] - 1 and state.shown_metrics() == (now, False)
    thread = state.shared.metrics_runner.thread
    release.set()
    thread.join(30)  # the held measurement finished: it must not replace the newer one
    assert not thread.is_alive()
    assert state.metrics is now


def test_a_measurement_that_fails_leaves_the_background_thread_measuring_the_next_one(
    measured, monkeypatch, capsys
):
    state, db, before = measured
    failed = threading.Event()

    def fail_once():
        if not failed.is_set():
            failed.set()
            raise RuntimeError("a measurement gone wrong")

    _on_the_metrics_thread(monkeypatch, fail_once)
    db.delete_labels([db.labels(0)[0].id], "ann")
    state.session_changed()
    thread = state.shared.metrics_runner.thread
    assert failed.wait(30)
    db.delete_labels([db.labels(0)[0].id], "ann")  # the next change is measured on the same thread
    state.session_changed()
    assert wait(lambda: not state.shown_metrics()[1], 30) and state.shared.metrics_runner.thread is thread
    after, stale = state.shown_metrics()
    assert not stale and after["num_reference"] == before["num_reference"] - 2
    assert "a measurement gone wrong" in capsys.readouterr().err


def test_points_drawn_is_a_budget_or_all_and_other_settings_leave_it_alone(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    assert state.points_drawn is None  # every point, until someone asks for fewer
    state.set_display(points_drawn=20_000)
    state.set_display(point_size=0.1)  # another setting leaves the budget as it was
    assert state.points_drawn == 20_000
    state.set_display(points_drawn=None)
    assert state.points_drawn is None
    with pytest.raises(ValueError, match="at least 1"):
        state.set_display(points_drawn=0)
    # A refused call changes nothing, the settings that were fine included.
    with pytest.raises(ValueError, match="unknown colour mode"):
        state.set_display(points_drawn=5_000, color_mode="rainbow")
    assert state.points_drawn is None


def _random_frames(rng: np.random.Generator, num_frames: int, num_classes: int) -> list[dict]:
    """Metrics entries as ``AppState._update_metrics`` builds them: detections, references near
    some of them, and candidates."""

    def boxes(n: int) -> np.ndarray:
        return np.column_stack(
            [
                rng.uniform(-5, 5, (n, 2)),
                rng.uniform(0, 1, n),
                rng.uniform(0.3, 1.5, (n, 3)),
                rng.uniform(-3, 3, n),
            ]
        )

    frames = []
    for index in range(num_frames):
        detections = boxes(12)
        references = detections[:6] + rng.normal(0, 0.05, (6, 7))
        references[:, 3:6] = np.abs(references[:, 3:6])
        candidates = np.concatenate([detections, boxes(20)])
        frames.append(
            {
                "frame_index": index,
                "boxes": detections,
                "class_ids": rng.integers(0, num_classes, 12),
                "scores": rng.uniform(0, 1, 12),
                "reference_boxes": references,
                "reference_class_ids": rng.integers(0, num_classes, 6),
                "ignore_boxes": np.zeros((0, 7)),
                "candidate_boxes": candidates,
                "candidate_class_ids": rng.integers(0, num_classes, 32),
                "candidate_scores": rng.uniform(0, 1, 32),
            }
        )
    return frames


def test_a_measurement_matches_again_only_the_frames_whose_arrays_changed(monkeypatch):
    import app.state as state_module
    from factorydet_core.metrics import detection_metrics, error_breakdown

    classes = ("a", "b", "c")
    frames = _random_frames(np.random.default_rng(0), 5, len(classes))
    per_class = np.array([0.3, np.nan, 0.6])
    calls, counted = [], []
    matches, counts = state_module.frame_matches, state_module.frame_error_counts
    monkeypatch.setattr(
        state_module,
        "frame_matches",
        lambda frame, *a: calls.append(frame["frame_index"]) or matches(frame, *a),
    )
    monkeypatch.setattr(
        state_module,
        "frame_error_counts",
        lambda frame, *a: counted.append(frame["frame_index"]) or counts(frame, *a),
    )

    def plain(frames: list[dict], score_threshold: float) -> dict:
        metrics = detection_metrics(frames, classes, 0.6, score_threshold, per_class)
        metrics["errors"] = error_breakdown(frames, classes, 0.6, score_threshold, per_class)
        return {**metrics, "num_frames": len(frames)}

    memo: dict = {}
    assert state_module._measure((frames, classes, 0.5, per_class), memo) == plain(frames, 0.5)
    assert sorted(calls) == sorted(counted) == [0, 1, 2, 3, 4]
    # One frame's labels changed (its reference arrays replaced, as a label edit does), one no
    # longer viewed: only the changed one is matched again, and the figures are as measured afresh.
    calls.clear()
    counted.clear()
    edited = [dict(f) for f in frames[:4]]
    edited[2]["reference_boxes"] = edited[2]["reference_boxes"][1:]
    edited[2]["reference_class_ids"] = edited[2]["reference_class_ids"][1:]
    assert state_module._measure((edited, classes, 0.5, per_class), memo) == plain(edited, 0.5)
    assert calls == counted == [2] and sorted(memo) == [0, 1, 2, 3]
    # Another operating point: the matches stand, the errors are counted again, as measured afresh.
    calls.clear()
    counted.clear()
    assert state_module._measure((edited, classes, 0.2, per_class), memo) == plain(edited, 0.2)
    assert calls == [] and sorted(counted) == [0, 1, 2, 3]
