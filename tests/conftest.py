"""Shared fixtures: small seeded simulated data sets, built once per test session."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.sim.simulate import SimConfig, simulate_dataset
from factorydet_core.threads import THREADS_ENV, available_cores, configure_threads

# The library's thread pools sized once, as the command line does (a test process beside a browser
# or an app server would otherwise oversubscribe the cores). Under pytest-xdist the workers share
# the cores, so each takes its share (the controller's OMP_NUM_THREADS, which they inherit, would
# give each all of them); FACTORYDET_THREADS still decides when it is set.
_NUM_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_SHARED = _NUM_WORKERS > 1 and not os.environ.get(THREADS_ENV)
configure_threads(max(1, available_cores() // _NUM_WORKERS) if _SHARED else None)

SHARED_REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def pytest_runtest_setup(item: pytest.Item) -> None:
    # Ray binds its ports on every interface unless the namespace has only loopback.
    if item.get_closest_marker("ray") is not None:
        from factorydet_core.scale.netns import loopback_only

        if not loopback_only():
            pytest.skip(
                "starts Ray: runs in a loopback-only network namespace (make test-ray, part of make test)"
            )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def default_dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The issue's reference data set: default settings, 5 frames, seed 1."""
    return simulate_dataset(tmp_path_factory.mktemp("sim_default"), SimConfig(num_frames=5, seed=1))


@pytest.fixture(scope="session")
def small_dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A light data set (3 frames of about 20k points) for tests that only need a valid one."""
    return simulate_dataset(
        tmp_path_factory.mktemp("sim_small"), SimConfig(num_frames=3, seed=7, points_per_frame=20_000)
    )


@pytest.fixture(scope="session")
def tiny_model_path(small_dataset_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A quickly trained detection model (two frames, a few epochs): a real checkpoint whose
    quality does not matter, for tests of the plumbing around it."""
    from factorydet_core.detection.classifier import ProposalClassifier
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.settings import front_end_params
    from factorydet_core.training.mining import collect_proposals, train_with_mining

    dataset = open_dataset(small_dataset_dir)
    frames = collect_proposals(dataset, [0, 1], Detector("agv"))
    run = train_with_mining(
        frames,
        ProposalClassifier(width=0.0625, epochs=3, num_threads=1),
        rounds=0,
        initial_negatives=200,
    )
    run.model.front_end = front_end_params("agv")
    return run.model.save(tmp_path_factory.mktemp("model") / "tiny.pt", {"rounds": 1})
