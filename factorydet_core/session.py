"""Working sessions under ``sessions/``. This is the only module that writes there.

A session is a folder ``sessions/NAME/``; for now it holds the data set it works on
(``data/``). Later issues add its database, models and caches.
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

from .dataset import MANIFEST
from .sim.simulate import SimConfig, simulate_dataset
from .types import InputError

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")

DEMO_SESSION = "demo"
DEMO_CONFIG = SimConfig(num_frames=12, seed=0)
"""The demo data set `make app` builds: seeded, twelve frames, a few seconds on a laptop."""


class SessionError(InputError):
    """A bad session name or a session that cannot be opened."""


def default_root() -> Path:
    """``$FACTORYDET_SESSIONS`` if set, else ``sessions/`` in the working directory."""
    return Path(os.environ.get("FACTORYDET_SESSIONS", "sessions"))


def validate_name(name: str) -> str:
    """Return ``name`` if it is a safe folder name: letters, digits, ``_ . -``, no path parts."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name) or ".." in name:
        raise SessionError(
            f"invalid session name {name!r}: use 1-64 letters, digits, '_', '.', '-',"
            " starting with a letter or digit"
        )
    return name


@dataclasses.dataclass(frozen=True)
class Session:
    """A session folder."""

    name: str
    root: Path

    @property
    def path(self) -> Path:
        return self.root / self.name

    @property
    def data_dir(self) -> Path:
        return self.path / "data"

    @property
    def has_data(self) -> bool:
        return (self.data_dir / MANIFEST).is_file()


def open_session(name: str, root: str | os.PathLike | None = None) -> Session:
    """The session ``name`` under ``root`` (created lazily when something is written)."""
    root_path = Path(root) if root is not None else default_root()
    return Session(validate_name(name), root_path)


def simulate_into(
    session: Session, config: SimConfig, progress: Callable[[int, int], None] | None = None
) -> Path:
    """Simulate a data set into the session's ``data/`` folder, replacing any earlier one."""
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
