"""The Training panel's controls are built from the library's training settings (in-process, a
viser server without a browser)."""

import dataclasses

import pytest
import viser

from app.panels.training_panel import build_training_panel, execution_of, settings_of
from app.state import AppState
from app.trainer import TrainingWorker
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.training.settings import LOOP_CONTROLS, LoopSettings
from factorydet_core.types import InputError


@pytest.fixture
def server():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def test_every_training_setting_has_a_control_showing_the_workers_value(server, small_dataset_dir, tmp_path):
    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    base = dataclasses.replace(LoopSettings(), epochs=7, class_weight=None, visibility=False)
    worker = TrainingWorker(state, settings=base, calibrate=False)
    panel = build_training_panel(server, state, worker)

    assert set(panel.controls) == {c.field for c in LOOP_CONTROLS}
    assert panel.controls["epochs"].value == 7
    assert panel.controls["class_weight"].value == "none"
    assert panel.controls["visibility"].value == "off"
    assert settings_of(panel.controls, LoopSettings()) == base  # what is shown is what trains

    panel.controls["method"].value = "box_head"
    panel.controls["negatives_per_round"].value = 40
    panel.controls["geometry"].value = False
    chosen = settings_of(panel.controls, base)
    assert (chosen.method, chosen.negatives_per_round, chosen.geometry) == ("box_head", 40, False)

    panel.controls["score_threshold"].value = 1.5  # a value typed past the control's bounds
    with pytest.raises(InputError, match="Score threshold"):
        settings_of(panel.controls, base)


def test_the_ray_controls_show_and_give_the_session_s_setting(server, small_dataset_dir, tmp_path):
    from factorydet_core.scale.runner import Execution

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    db.set_execution(3, "auto")
    panel = build_training_panel(server, AppState(dataset, db=db), TrainingWorker(AppState(dataset, db=db)))
    assert (panel.ray_workers.value, panel.ray_address.value) == (3, "auto")
    assert panel.execution() == Execution(workers=3, ray_address="auto")
    panel.ray_workers.value, panel.ray_address.value = 0, "  "
    assert panel.execution() == Execution() and not panel.execution().uses_ray
    for bad in (1.5, -1):  # the control rounds and clamps; a value from elsewhere is checked
        with pytest.raises(InputError, match="whole number"):
            execution_of(bad, "")


def test_the_runs_table_says_how_many_labels_trained_as_ignored_places(
    small_dataset_dir, tiny_model_path, tmp_path
):
    from app.panels.training_panel import runs_markdown
    from app.state import AppState
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.session.store import SessionDB, open_session
    from tests.fakes import queue_run

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("runs", tmp_path), dataset)
    snapshot = db.snapshot_labels(range(dataset.num_frames))
    size = db.snapshot_size(snapshot)
    assert size >= 2
    run = queue_run(tiny_model_path, [[]])
    db.save_training_run(run, "small", {"sparse_labels_ignored": 2}, snapshot_id=snapshot)
    db.save_training_run(run, "small", {"sparse_labels_ignored": 0}, snapshot_id=snapshot)
    rows = runs_markdown(AppState(dataset, db=db)).splitlines()[2:]
    assert f"| {size - 2} (+2 too sparse, ignored) |" in rows[0]
    assert f"| {size} |" in rows[1] and "ignored" not in rows[1]


def test_the_progress_bars_move_without_animating_while_busy(server, small_dataset_dir, tmp_path):
    # A browser without a GPU redraws the page for the bar's animation: headless Chromium spent
    # most of a 2-core machine on it, taken from the training and the frame the bars show.
    from app.panels.frame_panel import build_frame_panel

    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    training = build_training_panel(server, state, TrainingWorker(state, calibrate=False))
    pipeline = build_frame_panel(server, state)  # the frame's computation shows there
    state.set_training(busy=True, status="round 1 of 3: epoch 2 of 20", progress=0.25)
    state.set_pipeline_progress("frame 1: merging", 0.4, busy=True)
    training.refresh(state)
    pipeline.refresh(state)
    assert (training.progress.value, pipeline.progress.value) == (25.0, 40.0)
    assert not training.progress.animated and not pipeline.progress.animated
    assert "epoch 2 of 20" in training.status.content and "⏳" in pipeline.work.content
