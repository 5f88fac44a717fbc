"""The batch jobs in this process give what the plain commands give: a simulated data set byte
for byte, the evaluation's record figure for figure."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.evaluation.evaluate import evaluate, strip_curves
from factorydet_core.scale.evaluate import evaluate_batch
from factorydet_core.scale.jobs import SimulateJob, simulate_batch
from factorydet_core.scale.runner import Execution, run_frames
from factorydet_core.session.models import resolve_model
from factorydet_core.sim.simulate import SimConfig, simulate_dataset

pytestmark = pytest.mark.slow


def digests(folder: Path) -> dict[str, str]:
    """Every data file of a data set folder by its path (the batch's own job and summary aside)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name not in ("job.json", "summary.json")
    }


def comparable(result: dict) -> dict:
    """An evaluation record without what differs between runs of the same measurement."""
    return {k: v for k, v in strip_curves(result).items() if k not in ("seconds", "command", "batch")}


def test_a_batch_simulation_writes_the_plain_one_s_files(tmp_path):
    config = SimConfig(num_frames=3, seed=4, points_per_frame=6_000)
    simulate_dataset(tmp_path / "plain", config)
    # Interrupted after one frame, then finished: the same files.
    run_frames(SimulateJob(str(tmp_path / "batch"), config), [1], tmp_path / "batch")
    run = simulate_batch(tmp_path / "batch", config, Execution())
    assert run.skipped == (1,) and sorted(run.computed) == [0, 2]
    assert digests(tmp_path / "batch") == digests(tmp_path / "plain")


def test_a_batch_evaluation_matches_the_plain_one(batch_dataset_dir, tmp_path):
    model = resolve_model("default")
    plain = evaluate(batch_dataset_dir, model, calibrate=False, score_thresholds=(0.3,))
    batch = evaluate_batch(
        batch_dataset_dir, model, tmp_path / "out", Execution(), calibrate=False, score_thresholds=(0.3,)
    )
    assert batch["batch"]["num_computed"] == len(plain["frames"]) > 0
    assert comparable(batch) == comparable(plain)
    assert plain["reference"] == "truth" and "truth_without_ignore" in plain
    # Resumed: nothing recomputed, the same figures from the files.
    again = evaluate_batch(
        batch_dataset_dir, model, tmp_path / "out", Execution(), calibrate=False, score_thresholds=(0.3,)
    )
    assert again["batch"]["num_computed"] == 0 and comparable(again) == comparable(plain)


def proposal_arrays(frames) -> dict:
    from factorydet_core.training.mining import proposals_to_arrays

    return proposals_to_arrays(frames)


def assert_same_proposals(first, second) -> None:
    import numpy as np

    a, b = proposal_arrays(first), proposal_arrays(second)
    assert sorted(a) == sorted(b)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_proposals_through_batch_files_are_the_plain_ones(batch_dataset_dir, tmp_path):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import ProposeJob, propose_batch, proposer, resumable_folder
    from factorydet_core.training.loop import proposals_cache_key
    from factorydet_core.training.mining import collect_proposals

    assert proposer(Execution()) is collect_proposals and proposer(None) is collect_proposals
    dataset, detector = open_dataset(batch_dataset_dir), Detector("agv")
    steps = []
    through_files = propose_batch(dataset, [3, 1], detector, Execution(), lambda *step: steps.append(step))
    assert [f.frame_index for f in through_files] == [3, 1]
    assert steps[-1] == ("proposals", 2, 2)
    assert_same_proposals(through_files, collect_proposals(dataset, [3, 1], detector))
    # An interrupted run (here: frame 3 done, then stopped) is resumed by the next one.
    execution = Execution(scratch=str(tmp_path))
    job = ProposeJob(str(dataset.path), detector.params, detector.T_vehicle_sensor)
    with resumable_folder(execution, proposals_cache_key(dataset, detector)) as folder:
        run_frames(job, [3], folder, execution)
    steps.clear()
    resumed = propose_batch(dataset, [3, 1], detector, execution, lambda *step: steps.append(step))
    assert steps[0] == ("proposals", 1, 2)  # frame 3 was there
    assert_same_proposals(resumed, through_files)
    assert not folder.exists()  # removed once read back
    assert (folder.parent.stat().st_mode & 0o777) == 0o700  # this user's alone
    # A folder in use by another run is not shared: the second gets one of its own.
    with resumable_folder(execution, "job") as first, resumable_folder(execution, "job") as second:
        assert first.name == "job" and second != first and second.parent == first.parent
    assert not second.exists()


def assert_same_scores(first: list[dict], second: list[dict]) -> None:
    """Two ``score_frames`` outputs hold the same frames, detections and references."""
    assert [item["frame_index"] for item in first] == [item["frame_index"] for item in second]
    for a, b in zip(first, second):
        for key in ("boxes", "class_ids", "scores", "probabilities", "proposal_ids", "suppressed_by"):
            np.testing.assert_array_equal(
                getattr(a["detections"], key), getattr(b["detections"], key), err_msg=key
            )
        for key in ("reference_boxes", "reference_class_ids", "ignore_boxes"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_mining_rounds_scored_through_batch_files_train_the_plain_run(small_dataset_dir, tmp_path):
    """A training run whose rounds are scored by the batch job (in this process here; the Ray
    path differs only in who runs the job) mines, tunes and records what the plain run does:
    each round's model, saved and loaded by the job, scores every frame as the one in memory."""
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import batch_scorer, scoring
    from factorydet_core.session.store import SessionDB, open_session
    from factorydet_core.training.loop import train_session
    from factorydet_core.training.mining import collect_proposals, score_frames
    from factorydet_core.training.settings import LoopSettings

    with scoring(None) as plain, scoring(Execution()) as here:
        assert plain is score_frames and here is score_frames  # no Ray asked: no files
    dataset = open_dataset(small_dataset_dir)
    frames = collect_proposals(dataset, [0, 1], Detector("agv"))
    # The shipped method (the box head classifying, the box quality regressor boxing): both are
    # saved with each round's model and must load to the same scores.
    settings = LoopSettings(
        epochs=1, rounds=1, initial_negatives=100, negatives_per_round=20, seed=3, quality_trees=30
    )
    runs, steps = [], []
    for name in ("plain", "files"):
        db = SessionDB(open_session(name, tmp_path), dataset)
        score = score_frames
        if name == "files":
            folder = tmp_path / "scores"
            score = batch_scorer(Execution(), folder)
        _, run = train_session(
            db, frames, settings, mode="full",
            progress=(lambda *step: steps.append(step)) if name == "files" else None, score=score,
        )  # fmt: skip
        runs.append(run)
    plain_run, files_run = runs
    assert len(files_run.rounds) == 2
    assert any(r["mined"] for r in plain_run.rounds), "nothing mined: the comparison would be empty"
    for a, b in zip(plain_run.rounds, files_run.rounds):
        assert a["mined"] == b["mined"] and a["train_metrics"] == b["train_metrics"]
    assert plain_run.model.class_score_thresholds == files_run.model.class_score_thresholds
    assert ("score", 2, 2) in steps  # the job's progress, reported as the plain scoring's
    # Each round's files are removed once read; the frames' proposals were written once.
    assert sorted(p.name for p in folder.iterdir()) == ["proposals"]
    assert len(list((folder / "proposals" / "frames").glob("*.npz"))) == 2
    plain_scores = score_frames(plain_run.model, frames, 0.05)
    assert all(len(item["detections"].boxes) for item in plain_scores)
    again = batch_scorer(Execution(), tmp_path / "again")
    assert_same_scores(again(plain_run.model, frames, 0.05), plain_scores)
