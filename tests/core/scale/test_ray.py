"""The batch runner on Ray: the same files as in this process, no frame lost or doubled when a
worker is killed, work spread over a two-node cluster started with ``ray start``.

Every test here starts Ray and so runs in a loopback-only network namespace (``make test-ray``,
part of ``make test``); outside one it is skipped by the conftest's guard.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from factorydet_core.scale.runner import (
    FRAME_ATTEMPTS,
    Execution,
    SetUpOnce,
    done_frames,
    frame_path,
    run_frames,
)
from factorydet_core.types import FrameLostError, InputError

from .conftest import NUM_FRAMES, same_outputs

pytestmark = [pytest.mark.ray, pytest.mark.slow]

RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}


@pytest.fixture
def local_ray():
    """A local Ray of 2 CPUs for one test (a module-wide one would clash with the cluster test's)."""
    import ray

    os.environ.update(RAY_ENV)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_ray_workers_write_the_same_files_as_this_process(detect_job, tmp_path, local_ray):
    frames = list(range(NUM_FRAMES))
    here = run_frames(detect_job, frames, tmp_path / "here")
    on_ray = run_frames(detect_job, frames, tmp_path / "ray", Execution(workers=2))
    assert sorted(on_ray.computed) == frames and on_ray.workers == 2
    assert len(on_ray.worker_pids) == 2 and os.getpid() not in on_ray.worker_pids
    assert here.worker_pids == (os.getpid(),)
    same_outputs(tmp_path / "here", tmp_path / "ray", frames)
    summary = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert summary["execution"] == {"ray": True, "workers": 2, "address": None}


def test_simulation_and_evaluation_on_ray_give_what_this_process_gives(
    batch_dataset_dir, tmp_path, local_ray
):
    from factorydet_core.evaluation.evaluate import evaluate
    from factorydet_core.scale.evaluate import evaluate_batch
    from factorydet_core.scale.jobs import simulate_batch
    from factorydet_core.session.models import resolve_model
    from factorydet_core.sim.simulate import SimConfig, simulate_dataset

    from .test_jobs import comparable, digests

    config = SimConfig(num_frames=4, seed=4, points_per_frame=6_000)
    simulate_dataset(tmp_path / "plain", config)
    run = simulate_batch(tmp_path / "ray", config, Execution(workers=2))
    assert len(run.worker_pids) == 2
    assert digests(tmp_path / "ray") == digests(tmp_path / "plain")

    model = resolve_model("default")
    plain = evaluate(batch_dataset_dir, model, calibrate=False)
    on_ray = evaluate_batch(
        batch_dataset_dir, model, tmp_path / "eval", Execution(workers=2), calibrate=False
    )
    assert on_ray["batch"]["workers"] == 2
    assert comparable(on_ray) == comparable(plain)


def test_training_proposals_on_ray_are_the_plain_ones(batch_dataset_dir, local_ray):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import proposer
    from factorydet_core.training.mining import collect_proposals

    from .test_jobs import assert_same_proposals

    dataset, detector = open_dataset(batch_dataset_dir), Detector("agv")
    on_ray = proposer(Execution(workers=2))(dataset, [0, 2, 4], detector)
    assert_same_proposals(on_ray, collect_proposals(dataset, [0, 2, 4], detector))


def test_a_training_run_on_ray_mines_what_the_plain_one_mines(batch_dataset_dir, tmp_path, local_ray):
    """``train --workers``: the front half and every mining round's scoring run on the workers
    (each round's model loaded once per worker); the run mines and records what the plain one does."""
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.settings import PRESETS
    from factorydet_core.session.store import SessionDB, open_session
    from factorydet_core.training.settings import LoopSettings
    from factorydet_core.workflows import retrain_session

    dataset = open_dataset(batch_dataset_dir)
    settings = LoopSettings(epochs=1, rounds=1, initial_negatives=100, negatives_per_round=20, seed=2)
    runs, steps = {}, []
    for name, execution in (("plain", None), ("ray", Execution(workers=2))):
        db = SessionDB(open_session(name, tmp_path), dataset)
        runs[name] = retrain_session(
            db, dataset, settings, PRESETS["agv"], mode="full", calibrate=False, compare=False,
            max_train_frames=3, execution=execution,
            progress=(lambda *step: steps.append(step)) if execution else None,
        ).run  # fmt: skip
    assert ("score", 3, 3) in steps and ("proposals", 3, 3) in steps  # both ran as batch jobs
    assert len(runs["ray"].rounds) == 2
    assert any(r["mined"] for r in runs["plain"].rounds), "nothing mined: the comparison would be empty"
    for plain, ray_round in zip(runs["plain"].rounds, runs["ray"].rounds):
        assert ray_round["mined"] == plain["mined"] and ray_round["train_metrics"] == plain["train_metrics"]


def test_a_killed_worker_loses_no_frame_and_doubles_none(detect_job, tmp_path, local_ray):
    frames = list(range(NUM_FRAMES))
    killed = []

    def kill_first_worker(row):
        # The first frame's worker already holds its next frame: kill it mid-frame.
        if not killed:
            killed.append(row["pid"])
            os.kill(row["pid"], signal.SIGKILL)

    run = run_frames(detect_job, frames, tmp_path / "ray", Execution(workers=2), on_row=kill_first_worker)
    assert killed and killed[0] in run.worker_pids
    assert len(run.worker_pids) >= 3, "the killed worker's frames were not redone by a new one"
    assert sorted(run.computed) == frames, "a frame was lost or reported twice"
    run_frames(detect_job, frames, tmp_path / "here")
    same_outputs(tmp_path / "here", tmp_path / "ray", frames)
    assert not list((tmp_path / "ray" / "frames").glob("*.tmp*")), "a half-written file was left"


@dataclasses.dataclass
class FailingJob(SetUpOnce):
    """A job whose workers cannot set up (a data set missing on their node), or whose frames fail."""

    in_setup: bool
    kind: str = "failing"

    def describe(self) -> dict:
        return {"in_setup": self.in_setup}

    def load(self) -> int:
        if self.in_setup:
            raise InputError("no data set at /nowhere on this node")
        return 1

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        raise InputError(f"frame {frame_index}: unreadable")


def test_a_worker_s_input_error_ends_the_run_with_its_message(tmp_path, local_ray):
    """Neither restarted nor retried forever: a worker that cannot set up, or a frame that raises,
    ends the run with the worker's own message (the command line prints it in one line)."""
    for in_setup, message in ((True, "no data set at /nowhere"), (False, "unreadable")):
        with pytest.raises(InputError, match=message):
            run_frames(FailingJob(in_setup), range(4), tmp_path / str(in_setup), Execution(workers=2))


@dataclasses.dataclass
class CrashingJob(SetUpOnce):
    """A job whose frame ``crash_on`` kills the process computing it, every time (as running out of
    memory would), leaving a file in ``deaths`` each time; the other frames write their index."""

    crash_on: int
    deaths: str
    kind: str = "crashing"

    def describe(self) -> dict:
        return {"crash_on": self.crash_on}

    def load(self) -> int:
        return 1

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        if frame_index == self.crash_on:
            (Path(self.deaths) / str(os.getpid())).touch()
            os.kill(os.getpid(), signal.SIGKILL)
        out_path.write_text(str(frame_index))
        return {}


def test_a_frame_that_keeps_killing_its_worker_ends_the_run_naming_it(tmp_path, local_ray):
    """Given to a worker ``FRAME_ATTEMPTS`` times, not for ever; the frame handed to the same worker
    after it, computed again with it every time, is not the one named; the other frames are done
    and kept for a re-run."""
    crash_on = 1  # the second worker's first frame: frame 3 is handed to that worker after it
    deaths = tmp_path / "deaths"
    deaths.mkdir()
    named = f"^frame {crash_on}: its Ray worker died {FRAME_ATTEMPTS} times"
    with pytest.raises(FrameLostError, match=named):
        run_frames(CrashingJob(crash_on, str(deaths)), range(8), tmp_path / "out", Execution(workers=2))
    assert len(list(deaths.iterdir())) == FRAME_ATTEMPTS
    done = done_frames(tmp_path / "out", range(8))
    assert crash_on not in done and 0 in done


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def two_node_cluster():
    """Two Ray nodes of one CPU each on this machine, started as a user would (``ray start``)."""
    ray_cli = str(Path(sys.executable).with_name("ray"))
    env = {**os.environ, **RAY_ENV}
    # Ray's sockets live under the temp dir: pytest's tmp_path is too long for AF_UNIX.
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    port = _free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus=1", "--object-store-memory=300000000", "--disable-usage-stats"]
    try:
        subprocess.run(
            [ray_cli, "start", "--head", f"--port={port}", "--node-ip-address=127.0.0.1",
             f"--temp-dir={temp_dir}", "--include-dashboard=false", *common],
            env=env, check=True, capture_output=True, timeout=120,
        )  # fmt: skip
        subprocess.run(
            [ray_cli, "start", f"--address={address}", *common],
            env=env, check=True, capture_output=True, timeout=120,
        )  # fmt: skip
        yield address, env
    finally:
        subprocess.run([ray_cli, "stop", "--force"], env=env, capture_output=True, timeout=120)
        shutil.rmtree(temp_dir, ignore_errors=True)


def test_the_command_line_runs_across_a_two_node_cluster(batch_dataset_dir, tmp_path, two_node_cluster):
    address, env = two_node_cluster
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "app.cli", "detect", str(batch_dataset_dir), "--out", str(out),
        "--ray", address, "--json",
    ]  # fmt: skip
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout)
    assert summary["num_computed"] == NUM_FRAMES and summary["workers"] == 2
    assert summary["num_nodes"] == 2, "the frames did not run on both nodes"
    assert all(frame_path(out, i).is_file() for i in range(NUM_FRAMES))
