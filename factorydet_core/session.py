"""Working sessions under ``sessions/``. This is the only module that writes there.

A session is a folder ``sessions/NAME/``:

    data/              the data set it works on (simulated or converted)
    session.sqlite     training runs, their rounds and the hard negatives each round mined
    models/run_NNN/    checkpoints of run NNN: round_R.pt (+ .json notes) and final.pt
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import re
import shutil
import sqlite3
from collections.abc import Callable, Iterator
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

    @property
    def db_path(self) -> Path:
        return self.path / "session.sqlite"

    @property
    def models_dir(self) -> Path:
        return self.path / "models"


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


_SCHEMA = """
CREATE TABLE IF NOT EXISTS training_runs (
    id INTEGER PRIMARY KEY,
    created TEXT NOT NULL,
    data TEXT NOT NULL,
    config TEXT NOT NULL,
    train_frames TEXT NOT NULL,
    model_path TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS training_rounds (
    run_id INTEGER NOT NULL REFERENCES training_runs(id),
    round INTEGER NOT NULL,
    num_positives INTEGER NOT NULL,
    num_background INTEGER NOT NULL,
    num_false_positives INTEGER,
    fit_seconds REAL NOT NULL,
    train_metrics TEXT NOT NULL,
    model_path TEXT NOT NULL,
    PRIMARY KEY (run_id, round)
);
CREATE TABLE IF NOT EXISTS mined_negatives (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES training_runs(id),
    round INTEGER NOT NULL,
    frame_index INTEGER NOT NULL,
    proposal INTEGER NOT NULL,
    box TEXT NOT NULL,
    patch_set TEXT NOT NULL,
    score REAL NOT NULL,
    predicted_class TEXT NOT NULL,
    best_annotated_iou REAL NOT NULL,
    review TEXT NOT NULL DEFAULT 'unreviewed'
);
CREATE INDEX IF NOT EXISTS mined_by_frame ON mined_negatives (run_id, frame_index);
"""


@contextlib.contextmanager
def connect(session: Session) -> Iterator[sqlite3.Connection]:
    """The session database (created on first use), committed on success."""
    session.path.mkdir(parents=True, exist_ok=True)
    connection = sqlite3.connect(session.db_path)
    connection.row_factory = sqlite3.Row
    try:
        connection.executescript(_SCHEMA)
        yield connection
        connection.commit()
    finally:
        connection.close()


def rounds_record(run) -> list[dict]:
    """Per round of a training run: sizes, times and the training-frame F-score (no mined lists)."""
    return [
        {
            "round": r["round"],
            "num_positives": r["num_positives"],
            "num_background": r["num_background"],
            "fit_seconds": r["fit_seconds"],
            "score_seconds": r.get("score_seconds"),
            "num_mined": len(r["mined"]),
            "train_f1": r["train_metrics"]["f1"],
        }
        for r in run.rounds
    ]


def save_training_run(session: Session, run, data: str, config: dict) -> int:
    """Store a ``training.TrainingRun``: a checkpoint per round under ``models/run_NNN/``, the final
    one as ``final.pt``, and the rounds and mined negatives in the database.

    Returns:
        The run id.
    """
    with connect(session) as db:
        # The row first: its id names the checkpoint folder, so two runs never share one.
        run_id = int(
            db.execute(
                "INSERT INTO training_runs (created, data, config, train_frames, model_path)"
                " VALUES (?, ?, ?, ?, '')",
                (
                    datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                    data,
                    json.dumps(config),
                    json.dumps(run.train_frames),
                ),
            ).lastrowid
        )
        run_dir = session.models_dir / f"run_{run_id:03d}"
        final = run_dir / "final.pt"
        note = {"data": data, "train_frames": run.train_frames, "config": config, "run_id": run_id}
        for record, model in zip(run.rounds, run.models):
            path = run_dir / f"round_{record['round']}.pt"
            model.save(path, {**note, "round": record["round"], "train_metrics": record["train_metrics"]})
            db.execute(
                "INSERT INTO training_rounds VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    run_id,
                    record["round"],
                    record["num_positives"],
                    record["num_background"],
                    record.get("num_false_positives"),
                    record["fit_seconds"],
                    json.dumps(record["train_metrics"]),
                    str(path.relative_to(session.path)),
                ),
            )
            db.executemany(
                "INSERT INTO mined_negatives (run_id, round, frame_index, proposal, box, patch_set, score,"
                " predicted_class, best_annotated_iou) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (
                        run_id,
                        record["round"],
                        m["frame_index"],
                        m["proposal"],
                        json.dumps(m["box"]),
                        json.dumps(m["patch_set"]),
                        m["score"],
                        m["predicted_class"],
                        m["best_annotated_iou"],
                    )
                    for m in record["mined"]
                ],
            )
        run.model.save(
            final,
            {
                **note,
                "round": run.rounds[-1]["round"],
                "rounds": len(run.rounds),
                "rounds_record": rounds_record(run),
            },
        )
        db.execute(
            "UPDATE training_runs SET model_path = ? WHERE id = ?",
            (str(final.relative_to(session.path)), run_id),
        )
    return run_id


def training_runs(session: Session) -> list[dict]:
    """Every training run of the session with its rounds, oldest first."""
    if not session.db_path.is_file():
        return []
    with connect(session) as db:
        runs = [dict(r) for r in db.execute("SELECT * FROM training_runs ORDER BY id")]
        for run in runs:
            run["rounds"] = [
                {**dict(r), "train_metrics": json.loads(r["train_metrics"])}
                for r in db.execute(
                    "SELECT * FROM training_rounds WHERE run_id = ? ORDER BY round", (run["id"],)
                )
            ]
    return runs


def latest_model(session: Session) -> Path | None:
    """The final checkpoint of the session's last training run, if any."""
    runs = training_runs(session)
    return session.path / runs[-1]["model_path"] if runs else None


def mined_negatives(
    session: Session, run_id: int | None = None, frame_index: int | None = None
) -> list[dict]:
    """The review queue: negatives mined by a run (the last by default), highest score first."""
    if not session.db_path.is_file():
        return []
    with connect(session) as db:
        if run_id is None:
            run_id = db.execute("SELECT MAX(id) FROM training_runs").fetchone()[0]
        query = "SELECT * FROM mined_negatives WHERE run_id = ?"
        args: list = [run_id]
        if frame_index is not None:
            query += " AND frame_index = ?"
            args.append(frame_index)
        rows = db.execute(query + " ORDER BY score DESC", args).fetchall()
    return [{**dict(r), "box": json.loads(r["box"]), "patch_set": json.loads(r["patch_set"])} for r in rows]
