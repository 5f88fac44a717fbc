"""The demo session: a small simulated factory a new user can open at once."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

from factorydet_core.session.store import Session, open_session

DEMO_SESSION = "demo"
DEMO_CONFIG = {"num_frames": 12, "seed": 0}
"""``SimConfig`` fields of the demo data set `make app` builds: seeded, twelve frames, a few
seconds on a laptop."""


def simulate_into(session: Session, config, progress: Callable[[int, int], None] | None = None) -> Path:
    """Simulate a data set into the session's ``data/`` folder, replacing any earlier one.

    Args:
        config: a ``sim.simulate.SimConfig`` or a dict of its fields.
    """
    from factorydet_core.sim.simulate import (  # open3d: imported only when simulating
        SimConfig,
        simulate_dataset,
    )

    if isinstance(config, dict):
        config = SimConfig(**config)
    tmp = session.path / "data.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    simulate_dataset(tmp, config, progress)
    if session.data_dir.exists():
        shutil.rmtree(session.data_dir)
    os.replace(tmp, session.data_dir)
    return session.data_dir


def ensure_demo(
    root: str | os.PathLike | None = None, progress: Callable[[int, int], None] | None = None
) -> Session:
    """The demo session, simulated first if it is missing or incomplete."""
    session = open_session(DEMO_SESSION, root)
    if not session.has_data:
        simulate_into(session, DEMO_CONFIG, progress)
    return session
