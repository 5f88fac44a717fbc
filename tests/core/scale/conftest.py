"""A small data set and a batch job over it, shared by the runner's tests on both paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from factorydet_core.scale.jobs import DetectJob, read_detections
from factorydet_core.scale.runner import frame_path
from factorydet_core.session.models import resolve_model
from factorydet_core.sim.simulate import SimConfig, simulate_dataset

NUM_FRAMES = 6


@pytest.fixture(scope="session")
def batch_dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six frames of about 15k points: enough work per frame for a worker to be killed mid-run."""
    return simulate_dataset(
        tmp_path_factory.mktemp("sim_batch"),
        SimConfig(num_frames=NUM_FRAMES, seed=5, points_per_frame=15_000),
    )


@pytest.fixture
def detect_job(batch_dataset_dir: Path) -> DetectJob:
    return DetectJob(str(batch_dataset_dir), str(resolve_model("default")))


def same_outputs(first: Path, second: Path, frames) -> None:
    """Every frame's detection file holds the same arrays in both folders."""
    for i in frames:
        a, b = read_detections(frame_path(first, i)), read_detections(frame_path(second, i))
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"frame {i}: {key}")
