"""The batch runner in this process: outputs per frame, resuming, refusing to mix jobs."""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.scale import runner
from factorydet_core.scale.jobs import DetectJob, read_detections
from factorydet_core.scale.runner import JOB_FILE, SUMMARY_FILE, Execution, frame_path, run_frames
from factorydet_core.types import InputError

from .conftest import same_outputs

pytestmark = pytest.mark.slow


def test_a_run_writes_one_file_per_frame_and_a_rerun_skips_them(detect_job, tmp_path):
    progress = []
    run = run_frames(detect_job, [0, 2], tmp_path / "out", progress=lambda d, n: progress.append((d, n)))
    assert run.computed == (0, 2) and run.skipped == ()
    assert progress[0] == (0, 2) and progress[-1] == (2, 2)
    detections = read_detections(frame_path(tmp_path / "out", 2))
    assert detections["boxes"].shape[1] == 7 and len(detections["scores"]) == len(detections["boxes"])
    summary = json.loads((tmp_path / "out" / SUMMARY_FILE).read_text())
    assert summary["num_computed"] == 2 and summary["execution"]["ray"] is False

    before = frame_path(tmp_path / "out", 0).stat().st_mtime_ns
    again = run_frames(detect_job, [0, 1, 2], tmp_path / "out")
    assert again.skipped == (0, 2) and again.computed == (1,)
    assert frame_path(tmp_path / "out", 0).stat().st_mtime_ns == before  # not rewritten


def test_a_resumed_run_matches_one_run_through(detect_job, tmp_path):
    run_frames(detect_job, [1], tmp_path / "resumed")
    run_frames(detect_job, [0, 1, 2], tmp_path / "resumed")
    run_frames(detect_job, [0, 1, 2], tmp_path / "whole")
    same_outputs(tmp_path / "resumed", tmp_path / "whole", [0, 1, 2])


def test_a_folder_of_another_job_or_of_other_files_is_refused(detect_job, batch_dataset_dir, tmp_path):
    run_frames(detect_job, [0], tmp_path / "out")
    other = DetectJob(detect_job.data, detect_job.model_path, score_threshold=0.9)
    with pytest.raises(InputError, match="another job.*score_threshold"):
        run_frames(other, [0], tmp_path / "out")
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not a batch output folder"):
        run_frames(detect_job, [0], tmp_path / "stuff")
    with pytest.raises(InputError, match="twice"):
        run_frames(detect_job, [0, 0], tmp_path / "new")
    assert json.loads((tmp_path / "out" / JOB_FILE).read_text())["score_threshold"] is None


def test_a_job_travels_without_its_loaded_model(detect_job, tmp_path):
    run_frames(detect_job, [0], tmp_path / "out")  # sets the job up
    assert detect_job._loaded is not None
    copy = pickle.loads(pickle.dumps(detect_job))
    assert copy._loaded is None and copy.describe() == detect_job.describe()
    assert len(pickle.dumps(detect_job)) < 10_000


def test_execution_settings_are_checked():
    assert not Execution().uses_ray
    assert Execution(workers=2).uses_ray and Execution(ray_address="auto").uses_ray
    for bad in ({"workers": 0}, {"workers": True}, {"threads": 0}, {"ray_address": " "}):
        with pytest.raises(InputError):
            Execution(**bad)


def test_threshold_changes_what_is_written(detect_job, tmp_path):
    run_frames(detect_job, [0], tmp_path / "model")
    strict = DetectJob(detect_job.data, detect_job.model_path, score_threshold=0.99)
    run_frames(strict, [0], tmp_path / "strict")
    loose = read_detections(frame_path(tmp_path / "model", 0))
    tight = read_detections(frame_path(tmp_path / "strict", 0))
    assert len(tight["scores"]) < len(loose["scores"])
    assert np.all(tight["scores"] >= 0.99)


class _Failing:
    """A job whose frames fail as a worker's would on a node without the data set."""

    kind = "failing"

    def describe(self) -> dict:
        return {}

    def setup(self) -> None:
        pass

    def run(self, frame_index, out_path):
        raise RuntimeError("worker crashed") from InputError(f"frame {frame_index}: no such file")


def test_a_worker_s_input_error_comes_out_as_one_line(tmp_path):
    with pytest.raises(InputError, match="frame 0: no such file"):
        run_frames(_Failing(), [0], tmp_path / "out")


def test_half_written_files_of_a_killed_writer_are_cleared_and_paths_made_absolute(
    detect_job, tmp_path, monkeypatch
):
    run_frames(detect_job, [0], tmp_path / "out")
    stale = tmp_path / "out" / "frames" / ".frame_00001.tmp123-4-abcd.npz"
    stale.write_bytes(b"half")
    monkeypatch.chdir(tmp_path)
    run = run_frames(detect_job, [0, 1], "out")
    assert run.out_dir == (tmp_path / "out").resolve() and run.computed == (1,)
    assert not stale.exists()


def test_a_missing_scratch_folder_is_refused(tmp_path):
    with pytest.raises(InputError, match="scratch"):
        with Execution(workers=1, scratch=str(tmp_path / "nowhere")).scratch_folder("x"):
            pass


@pytest.mark.skipif(runner._malloc_trim is None, reason="the C library is not glibc: nothing to trim")
def test_the_freed_heap_goes_back_to_the_system():
    def rss_mb() -> float:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

    # 200 MB of 100 kB arrays (below glibc's mmap threshold: on the heap), all freed but the last,
    # which pins the top of the heap so that free() alone cannot shrink it.
    blocks = [np.ones(100_000 // 8) for _ in range(2000)]
    last = blocks[-1]
    del blocks
    before = rss_mb()
    runner.release_free_heap()
    assert before - rss_mb() > 100
    assert last.sum() == len(last)
