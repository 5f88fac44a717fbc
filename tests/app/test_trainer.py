"""The training worker: one job at a time, and free again the moment it says it is done."""

from __future__ import annotations

import dataclasses
import threading

from pytest import approx

from app.state import AppState
from app.trainer import TrainingWorker
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.training.settings import LoopSettings
from tests.app.polling import wait as _wait
from tests.fakes import queue_run


def test_a_job_can_start_as_soon_as_the_last_one_says_done(small_dataset_dir, tmp_path):
    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    trainer = TrainingWorker(state, calibrate=False)
    finish, release, jobs = threading.Event(), threading.Event(), []

    def job(mode, settings):  # stands in for training: says done, then its thread lives on
        jobs.append(mode)
        finish.wait(10)
        trainer._finish(status=f"{mode} done", progress=1.0)
        release.wait(10)

    trainer._train = job
    threads = []
    try:
        assert trainer.start("full")
        threads.append(trainer._thread)
        assert state.training_busy and not trainer.start("full")  # one job at a time
        finish.set()
        assert _wait(lambda: not state.training_busy, 10) and state.training_status == "full done"
        assert threads[0].is_alive()  # the thread outlives its "done"...
        assert trainer.start("next")  # ...and a click right after "done" is not refused as busy
        threads.append(trainer._thread)
        assert _wait(lambda: len(jobs) == 2, 10)
    finally:
        finish.set()
        release.set()
        for thread in threads:
            thread.join(10)


def test_a_job_trains_with_the_method_and_epochs_it_was_started_with(small_dataset_dir, tmp_path):
    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    trainer = TrainingWorker(state, calibrate=False)
    seen = []
    done = threading.Event()

    def job(mode, settings):
        seen.append((mode, settings.method, settings.epochs))
        trainer._finish(status="done", progress=1.0)
        done.set()

    trainer._train = job
    assert trainer.start("full", dataclasses.replace(LoopSettings(), epochs=3, method="box_head"))
    assert done.wait(10)
    trainer.join(10)
    assert seen == [("full", "box_head", 3)]
    assert trainer.settings.method == LoopSettings().method  # the worker's own settings are unchanged


def test_the_app_retrains_through_the_same_function_as_the_command_line(
    small_dataset_dir, tiny_model_path, tmp_path, monkeypatch
):
    from factorydet_core.detection.model import DetectionModel

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    state = AppState(
        dataset, db=SessionDB(open_session("s", tmp_path), dataset), model=model,
        model_name="/a/long/path/to/the/models/tiny.pt",
    )  # fmt: skip
    calls = []

    def retrain_session(db, data, settings, front_end, **options):
        calls.append((data, settings, front_end, options))
        raise RuntimeError("stop here")

    monkeypatch.setattr("app.trainer.retrain_session", retrain_session)
    trainer = TrainingWorker(state, calibrate=False)
    assert trainer.start("full", dataclasses.replace(LoopSettings(), epochs=2))
    trainer.join(10)
    assert state.training_status == "failed: stop here" and not state.training_busy
    [(data, settings, front_end, options)] = calls
    assert data is dataset and settings.epochs == 2 and options["mode"] == "full"
    assert front_end == model.front_end  # the shown model's front half, whole
    # (the before/after table's column, named short enough that the after column fits the panel)
    assert list(options["before"]) == ["before (…/models/tiny.pt)"] and options["calibrate"] is False


def test_carrying_pseudo_labels_waits_for_the_views_world_and_then_uses_it(
    small_dataset_dir, tiny_model_path, tmp_path, monkeypatch
):
    import numpy as np

    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.world import WorldFrames

    dataset = open_dataset(small_dataset_dir)
    state = AppState(
        dataset,
        db=SessionDB(open_session("s", tmp_path), dataset),
        model=DetectionModel.load(tiny_model_path),
        model_name="tiny",
    )
    state.db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {})  # (a round to go on from)
    calls = []

    def retrain_session(db, data, settings, front_end, **options):
        calls.append(options)
        raise RuntimeError("stop here")

    monkeypatch.setattr("app.trainer.retrain_session", retrain_session)
    trainer = TrainingWorker(state, calibrate=False)
    carry = dataclasses.replace(LoopSettings(), pseudo_label_confident=0.6, carry_pseudo_labels=True)
    state.set_world(None, "placing the frames in one world frame: 1/3")
    assert trainer.start("next", carry)
    trainer.join(10)
    # Not placed yet: refused with why, nothing trained (placing them here too would run ICP twice).
    assert not calls and not state.training_busy
    assert "needs the frames placed in one world frame" in state.training_status
    assert "1/3" in state.training_status and "Carry pseudo-labels" in state.training_status
    clouds = tuple(np.zeros((1, 3), np.float32) for _ in range(dataset.num_frames))
    world = WorldFrames(np.stack([np.eye(4)] * dataset.num_frames), np.ones(dataset.num_frames), clouds)
    state.set_world(world, "placed")
    assert trainer.start("next", carry)
    trainer.join(10)
    assert calls[0]["mode"] == "next" and calls[0]["world"] is world  # the view's own, not a second one


def test_a_cancel_after_the_run_is_stored_does_not_lose_it(
    small_dataset_dir, tiny_model_path, tmp_path, monkeypatch
):
    import types

    from factorydet_core.detection.model import DetectionModel

    dataset = open_dataset(small_dataset_dir)
    model = DetectionModel.load(tiny_model_path)
    state = AppState(
        dataset, db=SessionDB(open_session("s", tmp_path), dataset), model=model, model_name="tiny"
    )
    trainer = TrainingWorker(state, calibrate=False)
    compared = []

    def retrain_session(db, data, settings, front_end, progress, **options):
        progress("round", 1, 1)
        trainer.cancel()  # pressed while the stored run is being measured
        progress("compare", 0, 1)  # must not raise: the run is in the database already
        progress("compare", 1, 2)  # a test frame's proposals: the bar moves on from 0.88
        compared.append((state.training_status, state.training_progress))
        progress("compare", 2, 2)  # all proposed: the models are measured, said plainly
        compared.append((state.training_status, state.training_progress))
        # A fit that found none of the 3 cones its training frames label.
        metrics = {
            "per_class": {"cone": {"num_reference": 3, "ap": 0.0}, "box": {"num_reference": 9, "ap": 0.4}}
        }
        run = types.SimpleNamespace(model=model, rounds=[{"train_metrics": metrics}])
        return types.SimpleNamespace(
            run_id=7, run=run, train_frames=[], comparison={"after (run 7)": {}}, notes=()
        )

    monkeypatch.setattr("app.trainer.retrain_session", retrain_session)
    assert trainer.start("full")
    trainer.join(10)
    assert state.training_status.startswith("run 7 (full) done")
    [(status, fraction), (measuring, last)] = compared
    assert "on the test frames: proposals, frame 1 of 2" in status and abs(fraction - 0.93) < 1e-9
    assert measuring.endswith("measuring before and after on the test frames") and abs(last - 0.98) < 1e-9
    # The class the fit did not learn is said with it.
    assert (
        "finds none of the labelled instances of cone (3)**: it has not learned them" in state.training_status
    )
    # The new model is offered, not shown: people decide from the table.
    assert state.model_name == "tiny" and state.offered_model == "run 7 (full) final"
    assert state.training_comparison == {"after (run 7)": {}}


def test_the_chosen_model_is_what_the_session_shows_again(small_dataset_dir, tiny_model_path, tmp_path):
    import shutil

    from app.cli import session_model
    from factorydet_core.detection.model import DetectionModel
    from tests.fakes import queue_run

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    shipped = DetectionModel.load(tiny_model_path)
    assert session_model(db, shipped, "shipped") == (shipped, "shipped")  # no run yet
    db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {}, kind="full")
    # A session from before the choice was kept shows its latest run, and records it as chosen.
    _, name = session_model(db, shipped, "shipped")
    assert name == "run 1 (full) final" and db.shown_model()[0] == name
    # A newer run is not shown on reopening until someone chooses it.
    db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {}, kind="next")
    assert session_model(db, shipped, "shipped")[1] == "run 1 (full) final"
    state = AppState(dataset, db=db, model=shipped, model_name="shipped")
    path = db.session.path / db.training_runs()[-1]["model_path"]
    state.choose_model(DetectionModel.load(path), "run 2 (next) final", path)
    assert state.model_name == "run 2 (next) final" and state.offered_model is None
    assert session_model(db, shipped, "shipped")[1] == "run 2 (next) final"
    # A new session records the shipped model it opens with: its first run is offered, not shown.
    fresh = SessionDB(open_session("fresh", tmp_path), dataset)
    assert session_model(fresh, shipped, "shipped", tiny_model_path) == (shipped, "shipped")
    fresh.save_training_run(queue_run(tiny_model_path, [[]]), "small", {}, kind="full")
    assert session_model(fresh, shipped, "shipped", tiny_model_path)[1] == "shipped"
    # The record is relative to the session folder: a moved session keeps its choice.
    assert not str(db.meta()["shown_model"]).count(str(tmp_path))
    moved = tmp_path / "moved"
    shutil.copytree(db.session.path, moved / "s")
    assert SessionDB(open_session("s", moved), dataset).shown_model()[1] == moved / "s" / path.relative_to(
        db.session.path
    )


def test_the_time_left_counts_the_epochs_of_this_round_and_of_the_rounds_after_it():
    from app.trainer import epochs_left, time_left_text

    full = LoopSettings(epochs=20, round_epochs=5, rounds=2, threshold_folds=0)
    assert epochs_left("full", full, 0, 4, 20) == 16 + 2 * 5
    assert epochs_left("full", full, 2, 5, 5) == 0
    assert epochs_left("full", dataclasses.replace(full, round_epochs=0), 1, 10, 20) == 10 + 20
    assert epochs_left("next", full, 0, 2, 5) == 3
    # The threshold fold models' epochs after the last round (training.loop.fold_fit_epochs).
    assert epochs_left("full", full, 2, 5, 5, fold_epochs=20) == 20
    assert epochs_left("next", full, 0, 2, 5, fold_epochs=5) == 3 + 5
    assert time_left_text(12) == "about 10 s" and time_left_text(1) == "about 5 s"
    assert time_left_text(200) == "about 3 min"


def _reports_of(
    small_dataset_dir, tmp_path, monkeypatch, seconds_per_reading: int, reports, **settings
) -> list:
    """``(status, progress)`` pairs a full run shows while the given ``reports`` (``(what, done,
    total)`` progress calls) come in, the clock moving ``seconds_per_reading`` at each reading."""
    dataset = open_dataset(small_dataset_dir)
    state = AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset))
    trainer = TrainingWorker(state, calibrate=False)
    shown = []
    real_set = state.set_training

    def set_training(**changes):
        shown.append((changes.get("status"), changes.get("progress")))
        real_set(**changes)

    monkeypatch.setattr(state, "set_training", set_training)
    clock = iter(range(0, 10_000, seconds_per_reading))
    monkeypatch.setattr("app.trainer._clock", lambda: float(next(clock)))

    def retrain_session(db, data, settings, front_end, progress, **options):
        for report in reports:
            progress(*report)
        raise RuntimeError("stop here")

    monkeypatch.setattr("app.trainer.retrain_session", retrain_session)
    # (A session without a run trains in full: no mining round here.)
    assert trainer.start("full", dataclasses.replace(LoopSettings(), rounds=0, **settings))
    trainer.join(10)
    return shown


def test_the_training_status_gives_the_fitting_time_left(small_dataset_dir, tmp_path, monkeypatch):
    reports = [("fit", epoch, 5) for epoch in (1, 2, 3)]
    shown = _reports_of(small_dataset_dir, tmp_path, monkeypatch, 10, reports, threshold_folds=0)
    fits = [s for s, _ in shown if s and s.startswith("round 1 of 1")]
    # Ten seconds an epoch: after epoch 2, three are left (30 s); after epoch 3, two (20 s).
    assert fits == ["round 1 of 1: epoch 1 of 5", "round 1 of 1: epoch 2 of 5 · about 30 s of fitting left",
                    "round 1 of 1: epoch 3 of 5 · about 20 s of fitting left"]  # fmt: skip
    # With the default threshold folds, the fold models' epochs after the round count too: two of
    # the run's epochs (20 on half the frames each) after its own three.
    shown = _reports_of(small_dataset_dir, tmp_path, monkeypatch, 10, reports, epochs=5)
    fits = [s for s, _ in shown if s and s.startswith("round 1 of 1")]
    assert fits[1] == "round 1 of 1: epoch 2 of 5 · about 80 s of fitting left"  # (3 + 5) x 10 s


def test_proposals_and_scoring_move_the_bar_and_say_the_time_left(small_dataset_dir, tmp_path, monkeypatch):
    reports = [("proposals", frame, 8) for frame in range(4)] + [("fit", 5, 5)]
    reports += [("score", frame, 10) for frame in range(3)]
    shown = _reports_of(small_dataset_dir, tmp_path, monkeypatch, 4, reports, threshold_folds=0)
    proposals = [(s, p) for s, p in shown if s and s.startswith("proposals")]
    # Four seconds a frame: after frame 1, seven are left (28 s).
    assert proposals[0][0] == "proposals: frame 0 of 8"
    assert proposals[1][0] == "proposals: frame 1 of 8 · about 30 s left"
    scoring = [(s, p) for s, p in shown if s and "scoring" in s]
    assert scoring[0][0] == "round 1 of 1: scoring frame 1 of 10"
    assert scoring[2][0] == "round 1 of 1: scoring frame 3 of 10 · about 30 s left"  # 8 x 4 s
    fitted = [p for s, p in shown if s and "epoch 5 of 5" in s][0]
    progress = [p for _, p in scoring]
    assert fitted <= progress[0] < progress[1] < progress[2] < 0.1 + 0.75  # the bar moves while scoring


def test_the_fold_models_and_the_regressors_trees_move_the_bar_between_the_last_fit_and_its_scoring(
    small_dataset_dir, tmp_path, monkeypatch
):
    # The last round's fit, its fold models' fits, waiting for the box quality regressor (fitted
    # alongside: its trees reported once the run waits), then its scoring: the bar only moves on.
    reports = [("box quality", 0, 1), ("fit", 5, 5)] + [
        ("threshold folds", epoch, 40) for epoch in (1, 2, 40)
    ]
    reports += [("box quality", 0, 1)] + [("box quality", tree, 500) for tree in (100, 200, 300, 500)]
    reports += [("score", frame, 10) for frame in range(10)]
    shown = _reports_of(small_dataset_dir, tmp_path, monkeypatch, 4, reports, threshold_folds=2)
    folds = [(s, p) for s, p in shown if s and "no model fitted" in s]
    assert folds[0][0] == "tuning the thresholds on frames no model fitted: epoch 1 of 40"
    assert folds[1][0].startswith("tuning the thresholds on frames no model fitted: epoch 2 of 40 · about")
    fitted = [p for s, p in shown if s and "epoch 5 of 5" in s][0]
    said = [(s, p) for s, p in shown if s == "fitting the box quality regressor"]
    assert len(said) == 2 and all(p is None for _, p in said)  # (its start, then the wait's: words alone)
    trees = [(s, p) for s, p in shown if s and s.startswith("fitting the box quality regressor: tree")]
    assert [s for s, _ in trees] == [
        "fitting the box quality regressor: tree 100 of 500",
        "fitting the box quality regressor: tree 200 of 500 · about 10 s left",  # 4 s per 100: 12 s
        "fitting the box quality regressor: tree 300 of 500 · about 10 s left",  # 8 s per 200: 8 s
    ]  # (the last tree is the scoring's start)
    scoring = [p for s, p in shown if s and "scoring" in s]
    bar = [fitted, *(p for _, p in folds), *(p for _, p in trees), *scoring]
    assert bar == sorted(bar) and bar[0] < bar[-1]
    # The round's fit, the wait and its scoring share one half of the fits' part (0.5, 0.3, 0.2 of
    # it), the fold models the other.
    assert fitted == approx(0.1 + 0.75 * 0.5 / 2)
    assert folds[-1][1] == approx(0.1 + 0.75 * (0.5 + 1) / 2)
    assert trees[0][1] == approx(0.1 + 0.75 * (1 + 0.5 + 0.3 * 100 / 500) / 2)
    assert scoring[0] == approx(0.1 + 0.75 * (1 + 0.8) / 2)
    assert scoring[-1] == approx(0.1 + 0.75 * (1 + 0.8 + 0.2 * 9 / 10) / 2)


def test_the_ray_setting_is_the_session_s_and_goes_to_the_retrain(
    small_dataset_dir, tiny_model_path, tmp_path, monkeypatch
):
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.scale.runner import Execution

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    state = AppState(dataset, db=db, model=DetectionModel.load(tiny_model_path), model_name="tiny")
    calls = []

    def retrain_session(db, data, settings, front_end, progress, **options):
        calls.append(options["execution"])
        progress("proposals", 1, 4)
        calls.append(state.training_status)
        raise RuntimeError("stop here")

    monkeypatch.setattr("app.trainer.retrain_session", retrain_session)
    trainer = TrainingWorker(state, calibrate=False)
    assert trainer.execution() == Execution()  # this process until someone chooses Ray
    assert trainer.start("full", execution=Execution(workers=2))
    trainer.join(10)
    assert calls[0] == Execution(workers=2)
    assert calls[1].startswith("proposals: frame 1 of 4 on 2 Ray workers")
    # Kept with the session: a reopened app (a new worker) trains the same way.
    again = TrainingWorker(AppState(dataset, db=SessionDB(open_session("s", tmp_path), dataset)))
    assert again.execution() == Execution(workers=2)
    assert trainer.start("full")
    trainer.join(10)
    assert calls[2] == Execution(workers=2)
