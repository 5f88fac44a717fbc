"""The batch jobs in this process give what the plain commands give: a simulated data set byte
for byte, the evaluation's record figure for figure."""

from __future__ import annotations

import hashlib
from pathlib import Path

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


def test_proposals_through_batch_files_are_the_plain_ones(batch_dataset_dir):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import propose_batch, proposer
    from factorydet_core.training.mining import collect_proposals

    assert proposer(Execution()) is collect_proposals and proposer(None) is collect_proposals
    dataset, detector = open_dataset(batch_dataset_dir), Detector("agv")
    steps = []
    through_files = propose_batch(dataset, [3, 1], detector, Execution(), lambda *step: steps.append(step))
    assert [f.frame_index for f in through_files] == [3, 1]
    assert steps[-1] == ("proposals", 2, 2)
    assert_same_proposals(through_files, collect_proposals(dataset, [3, 1], detector))
