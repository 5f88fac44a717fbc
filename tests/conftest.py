"""Shared fixtures: small seeded simulated data sets, built once per test session."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from factorydet_core.sim.simulate import SimConfig, simulate_dataset

SHARED_REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


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
