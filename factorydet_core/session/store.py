"""Working sessions under ``sessions/``. This is the only module that writes there.

A session is a folder ``sessions/NAME/``:

    data/              the data set it works on (simulated or converted), unless the
                       session refers to a data set elsewhere
    session.db         SQLite (WAL, synchronous=FULL, foreign keys on, versioned schema): the data
                       set reference and hash, the labels of every frame, the edit log that undo
                       and redo walk, the training runs and their rounds, the negatives each round
                       mined and the review verdicts on them
    models/run_NNN/    checkpoints of run NNN: round_R.pt and final.pt, each with its .json note
                       and .boxq.npz box quality arrays, and fold_K.pt, its threshold fold models
    cache/             derived data (proposals, features), deletable at any time

Every write to the database is one transaction committed before the call returns, so an edit the
app acknowledges survives a crash of the process that made it. Writers queue for SQLite's one write
lock (at most ``BUSY_TIMEOUT`` seconds, then ``SessionBusyError``); in WAL mode readers never wait
for them, and a read-only open (``SessionDB(..., readonly=True)``) never writes at all. Every change
of a label or a verdict is versioned: a writer that did not see the latest one is refused
(``EditConflictError``), never silently obeyed. Every row is checked where it is read (``_COLUMNS``,
one place per table), and what undo and redo write back is checked likewise: a damaged or
hand-edited file is a one-line ``SessionError`` naming the table and the row, never a traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import math
import numbers
import os
import re
import shutil
import sqlite3
import tempfile
import threading
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

from factorydet_core.boxes import box_iou_3d
from factorydet_core.io.dataset import MANIFEST, Dataset, open_dataset
from factorydet_core.session.queue import queue_order as order_queue
from factorydet_core.session.queue import review_order_of, unlearned_order
from factorydet_core.settings_check import exception_line, short_repr
from factorydet_core.types import MAX_RAY_WORKERS, QUEUE_ORDERS, REVIEW_ORDERS, InputError

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")

HIDE_LABELLED_IOU = 0.25
"""The review panel's "hide items on labelled objects" filter: items whose box overlaps a label at
this IoU or more (``SessionDB.review_queue``'s ``max_label_iou``). Mined items overlap a label at
most below ``positive_iou`` 0.6; boxes of neighbouring objects rarely reach 0.25."""


def on_labelled_object(label_iou: float | None, max_label_iou: float) -> bool:
    """Whether the labelled-objects filter hides a queue item of this ``label_iou``
    (``SessionDB.label_overlap``; ``None``, an overlap not known, is never hidden)."""
    return label_iou is not None and label_iou >= max_label_iou


class SessionError(InputError):
    """A bad session name or a session that cannot be opened."""


class SessionBusyError(SessionError):
    """Another process held the session database's write lock for longer than ``BUSY_TIMEOUT``."""


BUSY_TIMEOUT = 10.0
"""Seconds a write waits for another process's write transaction before ``SessionBusyError``. Every
transaction here is short (the largest, an import of 10,000 boxes, takes about a second), so a
longer wait means a stuck writer: better a one-line error than a minute of silence."""

MAX_BOX_SIZE = 1000.0
"""Largest box edge accepted, metres: far above any object of a factory hall, so that a data set's
own odd annotation (a 150 m region box) exported from a session imports back."""
MIN_BOX_SIZE = 0.001
"""Smallest box edge kept, metres. A person's box must have edges at least this long (a smaller one
would round to zero in the 6 decimals stored); a data set annotation with a thinner edge (a flat
box, ``dz = 0``) is thickened to it, so that its volume, and every IoU with it, is defined."""
MAX_BOX_DISTANCE = 100_000.0
"""Largest distance of a box centre from the vehicle accepted, metres (far beyond any scan's reach;
it keeps every stored coordinate exact in the float32 of the npz export)."""
MAX_FRAME_INDEX = 2**31 - 1
"""Largest frame index accepted (SQLite stores no integer past 2**63; no data set comes near)."""
MAX_YAW = 1_000.0
"""Largest |yaw| accepted before wrapping, radians. Beyond this a float64 yaw has lost its
fractional part's precision, so the heading it meant is gone."""
MAX_STORED_VALUE = 1e9
"""Largest magnitude of any number of a stored box (``usable_box``): far outside the plausibility
bounds above, yet small enough that volumes and IoUs of such boxes stay finite numbers."""


def _box_values(box, where: str) -> list[float]:
    """``box`` as 7 finite floats; anything but 7 real numbers is refused, not converted (``true``,
    ``"1"`` and complex numbers included: ``float`` would take the first two and numpy would drop
    an imaginary part silently)."""
    try:
        items = list(box)
    except TypeError:
        items = None
    if items is None or not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in items):
        raise SessionError(
            f"{where}: a box is 7 numbers (cx, cy, cz, dx, dy, dz, yaw), got {short_repr(box, 80)}"
        )
    try:
        values = [float(v) for v in items]
    except (OverflowError, ValueError):  # an integer too large for a float
        values = [math.inf]
    if len(values) != 7 or not all(map(math.isfinite, values)):
        raise SessionError(
            f"{where}: a box is 7 finite numbers (cx, cy, cz, dx, dy, dz, yaw), got {short_repr(box, 80)}"
        )
    return values


def _wrapped(values: list[float]) -> list[float]:
    if abs(values[6]) > math.pi:
        values[6] = (values[6] + math.pi) % (2 * math.pi) - math.pi
    return values


def check_box(box, where: str = "box") -> list[float]:
    """``box`` as 7 floats (cx, cy, cz, dx, dy, dz, yaw), yaw wrapped to [-pi, pi] if outside it: the
    check of a box a person or a file gives.

    Raises:
        SessionError: not 7 finite real numbers, a size outside [``MIN_BOX_SIZE``,
            ``MAX_BOX_SIZE``], a centre farther than ``MAX_BOX_DISTANCE`` or a yaw beyond
            ``MAX_YAW``; the message starts with ``where``.
    """
    values = _box_values(box, where)
    if not all(MIN_BOX_SIZE <= v <= MAX_BOX_SIZE for v in values[3:6]):
        raise SessionError(
            f"{where}: box sizes must be positive (at least {MIN_BOX_SIZE:g} m) and at most"
            f" {MAX_BOX_SIZE:g} m, got {values[3:6]}"
        )
    if math.hypot(*values[:3]) > MAX_BOX_DISTANCE:
        raise SessionError(
            f"{where}: box centre {values[:3]} is more than {MAX_BOX_DISTANCE:g} m from the vehicle"
        )
    if abs(values[6]) > MAX_YAW:
        raise SessionError(
            f"{where}: box yaw {values[6]:g} rad is beyond +-{MAX_YAW:g}; give it in [-pi, pi)"
        )
    return _wrapped(values)


def usable_box(box, where: str = "box") -> list[float]:
    """``box`` as 7 floats a session can compute with: the check of the data set's own annotations
    and of every box read back from the database. The data set's boxes are the user's data, so the
    plausibility bounds of ``check_box`` do not apply to them: a 150 m hall outline or a box 20 km
    out is kept as it is. Only what no computation survives is refused.

    Sizes below ``MIN_BOX_SIZE`` (a flat box, ``dz = 0``) are raised to it; yaw is wrapped.

    Raises:
        SessionError: not 7 finite real numbers, a negative size, or a number beyond
            ``MAX_STORED_VALUE``; the message starts with ``where``.
    """
    values = _box_values(box, where)
    if any(v < 0 for v in values[3:6]):
        raise SessionError(f"{where}: box sizes must not be negative, got {values[3:6]}")
    if any(abs(v) > MAX_STORED_VALUE for v in values):
        raise SessionError(f"{where}: a box number beyond +-{MAX_STORED_VALUE:g}, got {short_repr(box, 80)}")
    values[3:6] = [max(v, MIN_BOX_SIZE) for v in values[3:6]]
    return _wrapped(values)


def check_frame_index(value, where: str = "frame index") -> int:
    """``value`` as a frame index: an integer, or a float without a fraction (JSON's ``3.0``).

    Raises:
        SessionError: a bool, a fractional or non-finite float, a string or anything else (``1.7``
            and ``true`` would otherwise be truncated to frame 1), or a negative index.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SessionError(f"{where}: a frame index is an integer, got {short_repr(value)}")
    if not isinstance(value, numbers.Integral) and not (math.isfinite(value) and float(value).is_integer()):
        raise SessionError(f"{where}: a frame index is an integer, got {short_repr(value)}")
    if not 0 <= value <= MAX_FRAME_INDEX:
        raise SessionError(f"{where}: a frame index lies in [0, {MAX_FRAME_INDEX}], got {short_repr(value)}")
    return int(value)


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
        return self.path / "session.db"

    @property
    def cache_dir(self) -> Path:
        return self.path / "cache"

    @property
    def models_dir(self) -> Path:
        return self.path / "models"


def open_session(name: str, root: str | os.PathLike | None = None) -> Session:
    """The session ``name`` under ``root`` (created lazily when something is written)."""
    root_path = Path(root) if root is not None else default_root()
    return Session(validate_name(name), root_path)


# --- Derived caches ---------------------------------------------------------------------------------

_CACHE_KEY_RE = re.compile(r"[A-Za-z0-9_.-]{1,128}")


def _cache_path(session: Session, key: str) -> Path:
    if not _CACHE_KEY_RE.fullmatch(key) or ".." in key:
        raise SessionError(f"invalid cache key {key!r}")
    return session.cache_dir / f"{key}.npz"


def write_cache(session: Session, key: str, arrays: dict) -> Path:
    """Store derived arrays under ``cache/KEY.npz`` (written whole, then renamed into place)."""
    import numpy as np

    path = _cache_path(session, key)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f"{path.stem}.{os.getpid()}.{threading.get_ident()}.partial.npz")
    np.savez(partial, **arrays)
    os.replace(partial, path)
    return path


def read_cache(session: Session, key: str) -> dict | None:
    """The arrays cached under ``key``, or ``None`` when missing or unreadable (then rebuilt)."""
    import numpy as np

    path = _cache_path(session, key)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        path.unlink(missing_ok=True)
        return None


def clear_cache(session: Session) -> None:
    """Delete every derived cache of the session."""
    if session.cache_dir.exists():
        shutil.rmtree(session.cache_dir)


def copy_session(session: Session, root: str | os.PathLike) -> Session:
    """A copy of ``session`` under ``root`` (replacing one of that name there), for benchmarks that
    must not change the session they measure: the database through SQLite's backup (consistent
    while the app writes), the models copied, the data and caches hard-linked where the file system
    allows (every writer replaces those files whole, never writes into them: ``write_cache``),
    copied otherwise."""
    if not session.db_path.is_file():
        raise SessionError(f"session {session.name!r} has no database to copy")
    copy = Session(session.name, Path(root))
    if copy.path.resolve() == session.path.resolve():
        raise SessionError(f"copy_session: {root} is the session's own folder")
    if copy.path.exists():
        shutil.rmtree(copy.path)
    copy.path.mkdir(parents=True)

    def link_or_copy(source: str, target: str) -> None:
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)

    for folder, copy_function in (
        (session.data_dir, link_or_copy),
        (session.cache_dir, link_or_copy),
        (session.models_dir, shutil.copy2),
    ):
        if folder.is_dir():
            target = copy.path / folder.relative_to(session.path)
            partial = shutil.ignore_patterns("*.partial.*")
            shutil.copytree(folder, target, copy_function=copy_function, ignore=partial)
    source_db = sqlite3.connect(f"file:{session.db_path}?mode=ro", uri=True)
    try:
        target_db = sqlite3.connect(copy.db_path)
        try:
            source_db.backup(target_db)
        finally:
            target_db.close()
    finally:
        source_db.close()
    return copy


# --- The session database -------------------------------------------------------------------------

SCHEMA_VERSION = 5
"""The schema this code reads and writes (``PRAGMA user_version``). An older database is migrated
when it is opened for writing (a read-only open reads it as it is); a newer one is refused
untouched."""

_SCHEMA_V1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE frames (frame_index INTEGER PRIMARY KEY, imported TEXT NOT NULL);
CREATE TABLE labels (
    id INTEGER PRIMARY KEY,
    frame_index INTEGER NOT NULL,
    box TEXT NOT NULL,
    class_name TEXT NOT NULL,
    origin TEXT NOT NULL CHECK (origin IN ('dataset', 'user', 'review', 'import')),
    instance_id INTEGER,
    created_by TEXT NOT NULL,
    created TEXT NOT NULL,
    modified_by TEXT NOT NULL,
    modified TEXT NOT NULL,
    version INTEGER NOT NULL DEFAULT 1,
    deleted INTEGER NOT NULL DEFAULT 0 CHECK (deleted IN (0, 1))
);
CREATE INDEX labels_by_frame ON labels (frame_index);
CREATE TABLE edits (
    id INTEGER PRIMARY KEY,
    author TEXT NOT NULL,
    created TEXT NOT NULL,
    kind TEXT NOT NULL,
    summary TEXT NOT NULL,
    changes TEXT NOT NULL,
    state TEXT NOT NULL DEFAULT 'done' CHECK (state IN ('done', 'undone', 'dropped'))
);
CREATE INDEX edits_by_author ON edits (author, state);
CREATE TABLE label_snapshots (
    id INTEGER PRIMARY KEY,
    created TEXT NOT NULL,
    last_edit_id INTEGER,
    num_labels INTEGER NOT NULL,
    labels TEXT NOT NULL
);
CREATE TABLE training_runs (
    id INTEGER PRIMARY KEY,
    created TEXT NOT NULL,
    kind TEXT NOT NULL,
    data TEXT NOT NULL,
    config TEXT NOT NULL,
    train_frames TEXT NOT NULL,
    snapshot_id INTEGER REFERENCES label_snapshots (id),
    model_path TEXT NOT NULL,
    metrics TEXT
);
CREATE TABLE training_rounds (
    run_id INTEGER NOT NULL REFERENCES training_runs (id),
    round INTEGER NOT NULL,
    num_positives INTEGER NOT NULL,
    num_background INTEGER NOT NULL,
    num_false_positives INTEGER,
    fit_seconds REAL NOT NULL,
    train_metrics TEXT NOT NULL,
    model_path TEXT NOT NULL,
    PRIMARY KEY (run_id, round)
);
CREATE TABLE mined_negatives (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES training_runs (id),
    round INTEGER NOT NULL,
    frame_index INTEGER NOT NULL,
    proposal INTEGER NOT NULL,
    box TEXT NOT NULL,
    patch_set TEXT NOT NULL,
    score REAL NOT NULL,
    predicted_class TEXT NOT NULL,
    probabilities TEXT,
    best_annotated_iou REAL NOT NULL
);
CREATE INDEX mined_by_run ON mined_negatives (run_id, frame_index);
CREATE TABLE reviews (
    negative_id INTEGER PRIMARY KEY REFERENCES mined_negatives (id),
    verdict TEXT NOT NULL CHECK (verdict IN ('background', 'object', 'wrong_box', 'skip')),
    class_name TEXT,
    label_id INTEGER REFERENCES labels (id),
    author TEXT NOT NULL,
    created TEXT NOT NULL
)
"""

# Version 2: every verdict is versioned like a label. The version lives on the mined negative,
# whose row is never deleted, so that undoing a verdict (which deletes its row) still moves it on.
_SCHEMA_V2 = """
ALTER TABLE mined_negatives ADD COLUMN review_version INTEGER NOT NULL DEFAULT 0
"""

# Version 3: pre-labels and interpolated boxes. A label made by the model ('model') waits for a
# person to confirm it (``reviewed`` 0; its ``score`` kept to sort the queue by); a moving object's
# box between two keyframes is computed ('interpolated'). SQLite cannot widen a CHECK in place: the
# table is rebuilt (with foreign keys off, checked before the migration commits).
_SCHEMA_V3 = """
CREATE TABLE labels_v3 (
    id INTEGER PRIMARY KEY,
    frame_index INTEGER NOT NULL,
    box TEXT NOT NULL,
    class_name TEXT NOT NULL,
    origin TEXT NOT NULL
        CHECK (origin IN ('dataset', 'user', 'review', 'import', 'model', 'interpolated')),
    instance_id INTEGER,
    created_by TEXT NOT NULL,
    created TEXT NOT NULL,
    modified_by TEXT NOT NULL,
    modified TEXT NOT NULL,
    version INTEGER NOT NULL DEFAULT 1,
    deleted INTEGER NOT NULL DEFAULT 0 CHECK (deleted IN (0, 1)),
    reviewed INTEGER NOT NULL DEFAULT 1 CHECK (reviewed IN (0, 1)),
    score REAL
);
INSERT INTO labels_v3 (id, frame_index, box, class_name, origin, instance_id, created_by, created,
    modified_by, modified, version, deleted)
    SELECT id, frame_index, box, class_name, origin, instance_id, created_by, created, modified_by,
    modified, version, deleted FROM labels;
DROP TABLE labels;
ALTER TABLE labels_v3 RENAME TO labels;
CREATE INDEX labels_by_frame ON labels (frame_index);
CREATE INDEX labels_by_instance ON labels (instance_id)
"""

# Version 4: a run's queue may hold false positives beyond its mined negatives, for review alone
# (``LoopSettings.review_extra``): they never went to the background, and a later run must not put
# them there unless a verdict says so. Every row stored before was a mined negative.
_SCHEMA_V4 = """
ALTER TABLE mined_negatives ADD COLUMN in_background INTEGER NOT NULL DEFAULT 1
    CHECK (in_background IN (0, 1))
"""

_TABLES = frozenset(
    {"meta", "frames", "labels", "edits", "label_snapshots", "training_runs", "training_rounds"}
    | {"mined_negatives", "reviews"}
)
"""The tables of every schema version: a database lacking one is refused."""

# Version 5: a label whose box is the model's own (``MODEL_BOX_ORIGINS``) becomes the person's
# (origin 'user') when they move its box; before, it kept its origin. Labels of those origins whose
# box an edit in force changed are the person's: read from the edit log.
_SCHEMA_V5 = """
UPDATE labels SET origin = 'user'
    WHERE origin IN ('review', 'model') AND reviewed = 1 AND id IN (
        SELECT json_extract(change.value, '$.key')
        FROM edits, json_each(edits.changes) AS change
        WHERE edits.state = 'done'
            AND json_extract(change.value, '$.table') = 'labels'
            AND json_extract(change.value, '$.before') IS NOT NULL
            AND json_extract(change.value, '$.after') IS NOT NULL
            AND json_extract(change.value, '$.before.box') != json_extract(change.value, '$.after.box'))
"""

_MIGRATIONS: dict[int, str] = {1: _SCHEMA_V1, 2: _SCHEMA_V2, 3: _SCHEMA_V3, 4: _SCHEMA_V4, 5: _SCHEMA_V5}
"""Script that takes a database from version ``v - 1`` to ``v``."""

VERDICTS = ("background", "object", "wrong_box", "skip")
"""Review verdicts on a mined negative: confirmed background, a real object of a class (it becomes
a label), a real object whose segment is wrong (to be boxed by hand), or not decided now."""
DECIDED = ("background", "object", "wrong_box")
ORIGINS = ("dataset", "user", "review", "import", "model", "interpolated")
"""Where a label comes from: the data set's annotation, drawn by hand, a mined negative confirmed as
an object, a file imported, the model's detection (a pre-label: unreviewed until a person confirms
or edits it), or a moving object's box computed between two of its keyframes (``world``)."""
PRELABEL_ORIGIN = "model"
COMPUTED_ORIGINS = ("interpolated",)
"""Origins of boxes the session computes from others: an edit of one makes it a person's."""
MODEL_BOX_ORIGINS = ("review", PRELABEL_ORIGIN)
"""Origins of labels whose box is the model's own, as a person accepted it: a reviewer's Object
verdict keeps the mined box, a confirmed pre-label the detection's. A person who moves such a box
makes it theirs (origin 'user'); training can let these teach their class alone
(``LoopSettings.model_box_targets``)."""
SAME_OBJECT_IOU = 0.25
"""Label once never adds a label where another label overlaps the object's box this much: that
object is labelled there already (the data set's label of it, say, under its own id)."""


def labelled_there(box, other_boxes) -> bool:
    """Whether any of ``other_boxes`` (R, 7) overlaps ``box`` (7,) by ``SAME_OBJECT_IOU`` or more:
    the one rule label once uses to keep from labelling an object twice in a frame."""
    import numpy as np

    other_boxes = np.asarray(other_boxes, np.float64).reshape(-1, 7)
    if not len(other_boxes):
        return False
    return bool(box_iou_3d(np.asarray(box, np.float64).reshape(1, 7), other_boxes).max() >= SAME_OBJECT_IOU)


def label_arrays(labels, class_names) -> tuple:
    """``(boxes (R, 7), class_ids (R,), label_ids (R,))`` of ``Label``s, class ids indexing
    ``class_names`` (label id -1: not stored yet, see ``Label.id``)."""
    import numpy as np

    return (
        np.array([lab.box for lab in labels], np.float64).reshape(-1, 7),
        np.array([class_names.index(lab.class_name) for lab in labels], np.int64),
        np.array([-1 if lab.id is None else lab.id for lab in labels], np.int64),
    )


NEW_OBJECT_ID = 1 << 32
"""The first instance id given to an object labelled in the session (the data set's own ids,
which frames not imported yet may still bring, stay below it)."""


class EditConflictError(SessionError):
    """An edit made against a state that someone else has changed since: reload and try again.

    Args:
        message: one line, naming what was refused and why.
        conflicts: per refused item, ``{"id": ..., "reason": ...}`` (a review of several items).
    """

    def __init__(self, message: str, conflicts: list[dict] | None = None) -> None:
        super().__init__(message)
        self.conflicts = list(conflicts or [])


def _by_a_person(content: dict, before: dict | None = None) -> dict:
    """What a person's edit makes of a label's ``content`` (``before`` it: the stored one): a
    pre-label reviewed; a computed (interpolated) box whose box the person moved their own (a
    keyframe), one whose class alone changed still computed; and a box the model gave
    (``MODEL_BOX_ORIGINS``) that the person moved their own too."""
    moved = before is None or content.get("box") != before.get("box")
    taken = content.get("origin") in (*COMPUTED_ORIGINS, *MODEL_BOX_ORIGINS)
    return {**content, "origin": "user" if taken and moved else content.get("origin"), "reviewed": 1}


def _verdict_text(verdict: str, class_name: str | None) -> str:
    return verdict if class_name is None else f"{verdict} ({class_name})"


@dataclasses.dataclass(frozen=True)
class Label:
    """One labelled box of a frame, as stored."""

    id: int | None
    """``None`` only for a data set annotation of a frame whose labels are not stored yet, as a
    read-only open sees them (the first write stores them)."""
    frame_index: int
    box: tuple[float, ...]
    """(7,) (cx, cy, cz, dx, dy, dz, yaw) in the vehicle frame."""
    class_name: str
    origin: str
    """One of ``ORIGINS``."""
    instance_id: int | None
    """The object the label boxes: the data set's instance id for 'dataset' labels, a new id (at or
    above ``NEW_OBJECT_ID``) for an object labelled once in every frame that shows it; every label
    of an object is that object in its frame (``SessionDB.object_labels``). ``None``: this frame
    only."""
    created_by: str
    created: str
    modified_by: str
    modified: str
    version: int
    """Bumped by every change: an edit names the version it was made against."""
    deleted: bool
    reviewed: bool = True
    """False for a pre-label (origin 'model') no person has confirmed or edited yet: training
    ignores its place (neither object nor background) and the metrics do not count it as truth."""
    score: float | None = None
    """The model's score of a pre-label."""


CHECKED_LABELS_KEPT = 20_000
"""How many checked label rows a ``SessionDB`` keeps (``SessionDB._label``): about a kilobyte each
(the labels of a few hundred frames; an export of more passes through and clears them)."""


OVERLAPS_KEPT = 256
"""How many frames' item-to-label overlaps a ``SessionDB`` keeps (``SessionDB.label_overlap``)."""


def _keep(cache: dict, key, value, limit: int) -> None:
    """``cache[key] = value``, the cache emptied first when it holds ``limit`` entries (entries of
    rows and labels that changed since pile up; a full one is refilled by the next reads)."""
    if len(cache) >= limit:
        cache.clear()
    cache[key] = value


class LabelBatch(list):
    """Labels added together, with the id of the edit that added them."""

    def __init__(self, labels, edit_id: int | None) -> None:
        super().__init__(labels)
        self.edit_id = edit_id


@dataclasses.dataclass(frozen=True)
class Edit:
    """One entry of the edit log."""

    id: int
    author: str
    created: str
    kind: str
    summary: str
    state: str
    """'done', 'undone', or 'dropped' (undone, then superseded by a newer edit of its author)."""
    label_versions: dict[int, tuple[int, int]] = dataclasses.field(default_factory=dict)
    """For an edit just undone or redone: each label it changed, ``id -> (version before, version
    after)``, so that a browser follows its own undo without taking in anyone else's change."""


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")


def _box_json(box, where: str = "box") -> str:
    """A box a person or a file gives (``check_box``), as stored."""
    return json.dumps([round(v, 6) for v in check_box(box, where)])


def _usable_box_json(box, where: str = "box") -> str:
    """A data set annotation (``usable_box``), as stored."""
    return json.dumps([round(v, 6) for v in usable_box(box, where)])


def _loads(text, what: str):
    """A JSON field of the database; a damaged one is a one-line ``SessionError`` naming it."""
    try:
        return json.loads(text)
    except (TypeError, ValueError, RecursionError):
        raise SessionError(
            f"the session database is damaged: {what} is not valid JSON ({short_repr(text, 60)})"
        ) from None


# --- Every row read from the database is checked, column by column --------------------------------
# Each checker takes a column's value as SQLite returns it and gives it back as the code uses it
# (JSON decoded, a box checked), or raises ``ValueError`` with the reason. SQLite keeps whatever a
# damaged or hand-edited file holds ('abc' in a REAL column, '[1,2]' as a box), so a row is checked
# where it is read, before anything computes with it: one-line error, never a traceback later.


def _integer(value) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"{short_repr(value)} is not an integer")
    return value


def _flag(value) -> int:
    if _integer(value) not in (0, 1):
        raise ValueError(f"{value} is not 0 or 1")
    return value


def _real(value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{short_repr(value)} is not a finite number")
    return float(value)


def _text(value) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{short_repr(value)} is not text")
    return value


def _frame(value) -> int:
    try:
        return check_frame_index(value)
    except SessionError as exc:
        raise ValueError(str(exc)) from None


def _optional(check: Callable) -> Callable:
    return lambda value: None if value is None else check(value)


def _choice(options: tuple) -> Callable:
    def check(value):
        if isinstance(value, bool) or value not in options:
            raise ValueError(f"{short_repr(value)} is not one of {', '.join(map(str, options))}")
        return value

    return check


def _json(value):
    """A JSON column (text); a list given as it is (a box inside an edit or a snapshot)."""
    if isinstance(value, (list, dict)):
        return value
    try:
        return json.loads(_text(value))
    except RecursionError:
        raise ValueError("is JSON nested too deeply") from None
    except ValueError:
        raise ValueError(f"{short_repr(value)} is not valid JSON") from None


def _json_of(kind: type, item: Callable | None = None) -> Callable:
    """A JSON column holding a ``kind`` (list or dict), each list item checked by ``item``."""

    def check(value):
        decoded = _json(value)
        if not isinstance(decoded, kind):
            raise ValueError(f"{short_repr(value)} is not a JSON {kind.__name__}")
        if item is not None:
            decoded = [item(v) for v in decoded]
        return decoded

    return check


def _stored_box(value) -> tuple[float, ...]:
    try:
        return tuple(usable_box(_json_of(list)(value), "box"))
    except SessionError as exc:
        raise ValueError(str(exc).removeprefix("box: ")) from None


_STATES = ("done", "undone", "dropped")
_COLUMNS: dict[str, dict[str, Callable]] = {
    "meta": {"key": _text, "value": _text},
    "frames": {"frame_index": _frame, "imported": _text},
    "labels": {
        "id": _integer,
        "frame_index": _frame,
        "box": _stored_box,
        "class_name": _text,
        "origin": _choice(ORIGINS),
        "instance_id": _optional(_integer),
        "created_by": _text,
        "created": _text,
        "modified_by": _text,
        "modified": _text,
        "version": _integer,
        "deleted": _flag,
        "reviewed": _flag,
        "score": _optional(_real),
    },
    "edits": {
        "id": _integer,
        "author": _text,
        "created": _text,
        "kind": _text,
        "summary": _text,
        "changes": _json_of(list),
        "state": _choice(_STATES),
    },
    "label_snapshots": {
        "id": _integer,
        "created": _text,
        "last_edit_id": _optional(_integer),
        "num_labels": _integer,
        "labels": _json_of(dict),
    },
    "training_runs": {
        "id": _integer,
        "created": _text,
        "kind": _text,
        "data": _text,
        "config": _json_of(dict),
        "train_frames": _json_of(list, _frame),
        "snapshot_id": _optional(_integer),
        "model_path": _text,
        "metrics": _optional(_json_of(dict)),
    },
    "training_rounds": {
        "run_id": _integer,
        "round": _integer,
        "num_positives": _integer,
        "num_background": _integer,
        "num_false_positives": _optional(_integer),
        "fit_seconds": _real,
        "train_metrics": _json_of(dict),
        "model_path": _text,
    },
    "mined_negatives": {
        "id": _integer,
        "run_id": _integer,
        "round": _integer,
        "frame_index": _frame,
        "proposal": _integer,
        "box": _stored_box,
        "patch_set": _json_of(list, _integer),
        "score": _real,
        "predicted_class": _text,
        "probabilities": _optional(_json_of(list, _real)),
        "best_annotated_iou": _real,
        "review_version": _integer,
        "in_background": _flag,
    },
    "reviews": {
        "negative_id": _integer,
        "verdict": _choice(VERDICTS),
        "class_name": _optional(_text),
        "label_id": _optional(_integer),
        "author": _text,
        "created": _text,
    },
}
"""Per table, per column: how a value read back is checked (and decoded). The one place that says
what a table's rows may hold; ``_row`` applies it."""
_ROW_ID = {"meta": "key", "frames": "frame_index", "reviews": "negative_id", "training_rounds": "run_id"}
"""The column naming a row in error messages (``id`` where not listed)."""

_VERDICT_COLUMNS = {
    "id": "negative_id",
    "verdict": "verdict",
    "verdict_class": "class_name",
    "label_id": "label_id",
    "reviewer": "author",
    "reviewed": "created",
}
"""The review queue's names for the columns of ``reviews`` it joins to each mined negative."""
_SNAPSHOT_LABEL = ("id", "frame_index", "box", "class_name", "origin", "instance_id", "reviewed")
"""The columns of ``labels`` a label snapshot keeps of each label (a snapshot taken before schema 3
has no ``reviewed``: every label of it was a person's)."""


def _table_columns(db: sqlite3.Connection, table: str) -> set[str]:
    """The columns ``table`` has in this database (an older schema, read as it is, has fewer)."""
    return {r[1] for r in db.execute(f"PRAGMA table_info({table})")}


def _row(table: str, row: sqlite3.Row | dict, where: str | None = None) -> dict:
    """A row of ``table`` (all its columns or some) as a dict, each column checked and decoded
    (``_COLUMNS``); columns of other tables are left as they are.

    Args:
        where: what names the row in an error (default: "TABLE row ID", by its ``_ROW_ID`` column).

    Raises:
        SessionError: one line naming the table, the row and the column.
    """
    out = dict(row)
    checks = _COLUMNS[table]
    for column, value in out.items():
        if column in checks:
            try:
                out[column] = checks[column](value)
            except (TypeError, ValueError) as exc:
                if where is None:
                    where = f"{table} row {short_repr(out.get(_ROW_ID.get(table, 'id')), 24)}"
                raise SessionError(f"the session database is damaged: {where}, {column}: {exc}") from None
    return out


def _label(row: sqlite3.Row | dict) -> Label:
    """A stored label, checked (``_row``): a damaged row is a one-line ``SessionError``."""
    checked = _row("labels", row)
    fields = {f.name: checked[f.name] for f in dataclasses.fields(Label) if f.name in checked}
    # (a database of schema 2 or older, read as it is, has no ``reviewed`` or ``score``)
    return Label(
        **fields | {"deleted": bool(checked["deleted"]), "reviewed": bool(checked.get("reviewed", 1))}
    )


# What an edit changes, per table: undo and redo compare and write only these columns.
_CONTENT = {
    "labels": ("frame_index", "box", "class_name", "deleted", "origin", "reviewed"),
    "reviews": ("verdict", "class_name", "label_id"),
}
_LATER_CONTENT = {"labels": frozenset({"origin", "reviewed"}), "reviews": frozenset()}
"""Columns an edit logged by an older schema does not name: undo and redo leave them as they are."""


def _same_content(current: dict | None, expected: dict | None) -> bool:
    """Whether a row's content is what an edit expects, on the columns the edit names."""
    if current is None or expected is None:
        return current is expected
    return {k: current.get(k) for k in expected} == expected


_KEYS = {"labels": "id", "reviews": "negative_id"}


def _is_busy(exc: Exception) -> bool:
    return isinstance(exc, sqlite3.OperationalError) and any(
        word in str(exc) for word in ("database is locked", "database table is locked", "busy")
    )


def _connect_readonly(path: Path, timeout: float) -> sqlite3.Connection:
    """A connection that cannot write: opened ``mode=ro``, with ``query_only`` on as well.

    Reading a WAL database needs its ``-shm`` file, which SQLite creates beside it. In a folder
    nobody can write (a read-only mount, a folder made immutable) that fails, and the database is
    then opened ``immutable=1``: safe, since no writer can work there either (a writer needs the
    ``-wal`` and ``-shm`` files too), so the file cannot change under the reader.
    """
    uri = path.resolve().as_uri()
    connection = _open_uri(f"{uri}?mode=ro", timeout)
    try:
        connection.execute("PRAGMA user_version").fetchone()  # opens the WAL index, if it can
    except sqlite3.OperationalError as exc:
        connection.close()
        if "unable to open" not in str(exc) or not _frozen_folder(path):
            raise
        connection = _open_uri(f"{uri}?mode=ro&immutable=1", timeout)
    return connection


def _open_uri(uri: str, timeout: float) -> sqlite3.Connection:
    connection = sqlite3.connect(
        uri, uri=True, timeout=timeout, isolation_level=None, check_same_thread=False
    )
    connection.execute("PRAGMA query_only = ON")
    return connection


def _frozen_folder(path: Path) -> bool:
    """Whether a read of the database at ``path`` failed only for want of a ``-shm`` file in a
    folder nobody can write, so that an immutable open reads exactly what is stored.

    Raises:
        SessionError: a ``-wal`` file holds changes not yet in the database: an immutable open
            would not see them, and reading them needs the ``-shm`` file that cannot be made.
    """
    if Path(f"{path}-shm").exists() or os.access(path.parent, os.W_OK):
        return False
    wal = Path(f"{path}-wal")
    if wal.exists() and wal.stat().st_size > 0:
        raise SessionError(
            f"{path}: cannot read the session database: {wal.name} holds changes not yet written into"
            f" it and its folder is not writable (SQLite needs to create {path.name}-shm there);"
            " make the folder writable to read it"
        )
    return True


def check_database(path: str | os.PathLike, timeout: float | None = None) -> int:
    """Check an existing session database without writing to it.

    Returns:
        Its schema version (0 for an empty file).

    Raises:
        SessionError: the file is not an SQLite database, is damaged, is not a factorydet session,
            or was written by a newer version of factorydet.
        SessionBusyError: another process kept it locked (only a database not in WAL mode can).
    """
    path = Path(path)
    timeout = BUSY_TIMEOUT if timeout is None else timeout
    connection = None
    try:
        connection = _connect_readonly(path, timeout)
        version = connection.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            raise SessionError(
                f"{path}: session database schema {version} is newer than this factorydet's "
                f"({SCHEMA_VERSION}); upgrade factorydet. The file was not modified."
            )
        if version < 0:
            raise SessionError(f"{path}: session database schema {version} is not valid; it was not modified")
        check = connection.execute("PRAGMA quick_check").fetchone()[0]
        if check != "ok":
            reason = " ".join(check.split())[:200]  # quick_check lists problems a line each
            raise SessionError(f"{path}: the session database is damaged ({reason}); it was not modified")
        tables = {r[0] for r in connection.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if version == 0 and tables:
            raise SessionError(f"{path}: an SQLite file that is not a factorydet session database")
        missing = _TABLES - tables
        if version >= 1 and missing:
            raise SessionError(
                f"{path}: the session database lacks the tables {sorted(missing)}; it was not modified"
            )
    except (sqlite3.Error, UnicodeDecodeError) as exc:
        if _is_busy(exc):
            raise SessionBusyError(
                f"{path}: another process has kept the session database locked for over {timeout:g} s;"
                " try again when it is done"
            ) from None
        if isinstance(exc, sqlite3.OperationalError) and "unable to open" in str(exc):
            readable = "" if os.access(path, os.R_OK) else "; the file is not readable by you"
            raise SessionError(f"{path}: cannot open the session database ({exc}{readable})") from None
        raise SessionError(
            f"{path}: not a readable session database ({exception_line(exc)}); it was not modified"
        ) from None
    finally:
        if connection is not None:
            connection.close()
    return version


def _imported_frames(db: sqlite3.Connection) -> set[int]:
    """The frames whose labels are stored (``frames``, checked)."""
    return {_row("frames", r)["frame_index"] for r in db.execute("SELECT frame_index FROM frames")}


class SessionDB:
    """The session database: labels, edits, reviews, training runs.

    Every method is one transaction, committed before it returns. Methods may be called from any
    thread; each call uses its own connection, and SQLite serialises the writers.

    Args:
        session: the session folder (``open_session``).
        dataset: the data set the labels belong to. The first open records its reference and
            content hash; a later open with a different data set is refused. Needed to import the
            data set's annotations as the first labels of each frame.
        data_ref: how to name the data set in the record (default: its path).
        readonly: open for reading only (``queue``, ``labels export``): nothing is ever written,
            not even a migration or the data set record, so a read-only file or a busy writer does
            not stop it. Frames whose labels were never stored read as the data set's annotations.
        timeout: seconds a write waits for another process's write before ``SessionBusyError``
            (default ``BUSY_TIMEOUT``).
    """

    def __init__(
        self,
        session: Session,
        dataset=None,
        data_ref: str | None = None,
        *,
        readonly: bool = False,
        timeout: float | None = None,
    ) -> None:
        self.session = session
        self.dataset = dataset
        self.path = session.db_path
        self.readonly = readonly
        self.timeout = float(BUSY_TIMEOUT if timeout is None else timeout)
        # (run id, {mined negative id: (its checked columns, the names of its list columns)}): a
        # run's mined negatives are written once, with the run, and then only their review
        # version changes, so the queue of a run is checked once, not at every read after every
        # verdict (``_queue_rows``).
        self._mined_checked: tuple[int | None, dict[int, tuple[dict, list[str]]]] = (None, {})
        # ((run, order), {item id: position}): a class order's positions in a run's whole queue.
        self._queue_positions: tuple[tuple | None, dict[int, int]] = (None, {})
        # {(row's values, the session's classes): Label}: checking a stored label is pure Python
        # per row, and the app reads every shown frame's labels again after each edit; a row
        # read again unchanged (every column the same) is the same label, checked once.
        self._checked_labels: dict[tuple, Label] = {}
        # {(items' boxes, labels' boxes) as bytes: each item's highest IoU} (``label_overlap``).
        self._overlaps: dict[tuple[bytes, bytes], list[float]] = {}
        if readonly:
            if not self.path.is_file():
                raise SessionError(f"session {session.name!r} has no database ({self.path}) to read")
            self.schema_version = check_database(self.path, self.timeout)
            if self.schema_version == 0:
                raise SessionError(f"{self.path}: an empty session database; nothing to read")
        else:
            version = check_database(self.path, self.timeout) if self.path.exists() else 0
            session.path.mkdir(parents=True, exist_ok=True)
            self._migrate(version)
            self.schema_version = SCHEMA_VERSION
        if dataset is not None:
            self._bind(dataset, data_ref or str(dataset.path))

    # -- connections

    def _connect(self, foreign_keys: bool = True) -> sqlite3.Connection:
        if self.readonly:
            connection = _connect_readonly(self.path, self.timeout)
        else:
            connection = sqlite3.connect(
                self.path, timeout=self.timeout, isolation_level=None, check_same_thread=False
            )
            connection.execute("PRAGMA synchronous = FULL")
        connection.row_factory = sqlite3.Row
        # Off only for a migration that rebuilds a table, said explicitly: some SQLite builds
        # switch foreign keys on by default.
        connection.execute(f"PRAGMA foreign_keys = {'ON' if foreign_keys else 'OFF'}")
        return connection

    def _failure(self, exc: Exception) -> SessionError:
        """A database error as the one-line error a person reads."""
        if isinstance(exc, UnicodeDecodeError):
            return SessionError(f"{self.path}: the session database is damaged (a text value is not UTF-8)")
        if _is_busy(exc):
            return SessionBusyError(
                f"session {self.session.name!r} is busy: another process has held its database for over"
                f" {self.timeout:g} s; try again when it is done"
            )
        return SessionError(f"{self.path}: the session database failed ({exception_line(exc)})")

    @contextlib.contextmanager
    def _write(self, foreign_keys: bool = True) -> Iterator[sqlite3.Connection]:
        """A write transaction (taken at once, so two writers never deadlock), committed on success.

        Whatever the body reads and then writes is one atomic step: no other writer runs between.
        ``foreign_keys=False`` only for a migration that rebuilds a table (checked before it commits).
        """
        if self.readonly:
            raise SessionError(f"session {self.session.name!r} was opened read-only")
        try:
            connection = self._connect(foreign_keys)
            try:
                connection.execute("BEGIN IMMEDIATE")
                try:
                    yield connection
                except BaseException:
                    if connection.in_transaction:
                        connection.execute("ROLLBACK")
                    raise
                connection.execute("COMMIT")
            finally:
                connection.close()
        except (sqlite3.Error, UnicodeDecodeError) as exc:  # a text value that is not UTF-8: damage
            raise self._failure(exc) from None

    @contextlib.contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """A read transaction: one consistent state, however many statements (WAL: never waits)."""
        try:
            connection = self._connect()
            try:
                connection.execute("BEGIN")
                yield connection
                connection.execute("COMMIT")
            finally:
                connection.close()
        except (sqlite3.Error, UnicodeDecodeError) as exc:  # a text value that is not UTF-8: damage
            raise self._failure(exc) from None

    def _migrate(self, version: int) -> None:
        """WAL mode if the database is not in it yet, then the schema brought up to date."""
        try:
            connection = self._connect()
            try:
                # Outside a transaction: the journal mode cannot change inside one. Only switched
                # when needed, since switching waits for every other connection to close.
                if connection.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                    connection.execute("PRAGMA journal_mode = WAL")
            finally:
                connection.close()
        except (sqlite3.Error, UnicodeDecodeError) as exc:  # a text value that is not UTF-8: damage
            raise self._failure(exc) from None
        if version >= SCHEMA_VERSION:
            return
        with self._write(foreign_keys=False) as db:  # SQLite's way to rebuild a referenced table
            # Read again inside the lock: another process may have migrated it meanwhile.
            version = db.execute("PRAGMA user_version").fetchone()[0]
            for target in range(version + 1, SCHEMA_VERSION + 1):
                for statement in _MIGRATIONS[target].split(";"):
                    if statement.strip():
                        db.execute(statement)
                if target == 1:
                    db.execute("INSERT INTO meta VALUES ('created', ?)", (_now(),))
                db.execute(f"PRAGMA user_version = {target}")
            broken = db.execute("PRAGMA foreign_key_check").fetchall()
            if broken:
                raise SessionError(
                    f"{self.path}: the session database is damaged ({len(broken)} row(s) refer to rows"
                    " that do not exist); it was not migrated"
                )

    def _bind(self, dataset, data_ref: str) -> None:
        """Record the data set on the first open; refuse another data set on a later one. Only the
        first open writes (a read-only open never does)."""
        digest = dataset.content_hash()
        meta = self.meta()
        if "data_hash" not in meta and not self.readonly:
            with self._write() as db:
                meta = dict(db.execute("SELECT key, value FROM meta").fetchall())
                if "data_hash" not in meta:
                    db.executemany(
                        "INSERT INTO meta VALUES (?, ?)",
                        [
                            ("data", data_ref),
                            ("data_hash", digest),
                            ("class_names", json.dumps(list(dataset.class_names))),
                            ("num_frames", str(dataset.num_frames)),
                        ],
                    )
                    return
        if "data_hash" in meta and meta["data_hash"] != digest:
            raise SessionError(
                f"session {self.session.name!r} was made on the data set {meta.get('data')} "
                f"(hash {meta['data_hash']}); {data_ref} (hash {digest}) differs. "
                "Open it with its own data set or start a new session."
            )

    def check_writable(self) -> None:
        """Refuse, now and in one line, a session this process cannot write: what a long job (a
        training run, minutes of proposals and fitting) calls first, rather than losing its
        result at the end. Writes nothing but the folders a run makes anyway.

        Raises:
            SessionError: the database, or the folders a run writes (``models/``, ``cache/``),
                cannot be written (a read-only file, folder or mount; a read-only open).
            SessionBusyError: another process held the write lock for over the timeout.
        """
        if self.readonly:
            raise SessionError(f"session {self.session.name!r} was opened read-only")
        for folder in (self.session.path, self.session.models_dir, self.session.cache_dir):
            try:
                folder.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryFile(dir=folder):
                    pass
            except OSError as exc:
                raise SessionError(
                    f"session {self.session.name!r} cannot be written: cannot write in {folder}"
                    f" ({exc.strerror or exception_line(exc)})"
                ) from None
        try:
            with self._write() as db:
                # A write statement that changes nothing: a read-only file refuses it all the same.
                db.execute("UPDATE meta SET value = value WHERE 0")
        except SessionBusyError:
            raise
        except SessionError as exc:
            raise SessionError(f"session {self.session.name!r} cannot be written: {exc}") from None

    # -- metadata

    def meta(self) -> dict[str, str]:
        """The data set reference and hash, the creation time."""
        with self._read() as db:
            rows = [_row("meta", r) for r in db.execute("SELECT key, value FROM meta")]
        return {r["key"]: r["value"] for r in rows}

    def set_shown_model(self, name: str, path: str | os.PathLike) -> None:
        """Record the model people chose to show (the app's **Show this model**): the app shows it
        again when it reopens the session, and a retrain never replaces it by itself. ``path`` is
        kept relative to the session folder when it lies inside it (a copied session keeps it)."""
        path = Path(path)
        with contextlib.suppress(ValueError):
            path = path.resolve().relative_to(self.session.path.resolve())
        value = json.dumps({"name": str(name), "path": str(path)})
        with self._write() as db:
            db.execute("INSERT OR REPLACE INTO meta VALUES ('shown_model', ?)", (value,))

    def shown_model(self) -> tuple[str, Path] | None:
        """``(name, checkpoint path)`` of the model last chosen to be shown (``set_shown_model``),
        or ``None`` if none was."""
        raw = self.meta().get("shown_model")
        if raw is None:
            return None
        value = _loads(raw, "meta 'shown_model'")
        if not isinstance(value, dict) or not all(isinstance(value.get(k), str) for k in ("name", "path")):
            raise SessionError(
                f"the session database is damaged: meta 'shown_model' is {short_repr(raw, 60)}"
            )
        path = Path(value["path"])
        return value["name"], path if path.is_absolute() else self.session.path / path

    def set_execution(self, workers: int | None, ray_address: str | None) -> None:
        """Record where the session's retraining proposes its frames (the app's Training panel):
        ``workers`` Ray workers (``None``: this process) on the Ray at ``ray_address`` (``None``: a
        local one). The app reads it back when it reopens the session."""
        if workers is not None and (
            isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_RAY_WORKERS
        ):
            raise SessionError(
                f"Ray workers must be a whole number in [1, {MAX_RAY_WORKERS}], got {short_repr(workers)}"
            )
        if ray_address is not None and (not isinstance(ray_address, str) or not ray_address.strip()):
            raise SessionError(f"a Ray address must be text, got {short_repr(ray_address)}")
        value = json.dumps({"workers": workers, "ray_address": ray_address})
        with self._write() as db:
            db.execute("INSERT OR REPLACE INTO meta VALUES ('execution', ?)", (value,))

    def execution(self) -> dict:
        """``{"workers": int | None, "ray_address": str | None}`` as ``set_execution`` stored it;
        both ``None`` (this process) when it never was."""
        raw = self.meta().get("execution")
        if raw is None:
            return {"workers": None, "ray_address": None}
        value = _loads(raw, "meta 'execution'")
        workers = value.get("workers") if isinstance(value, dict) else "?"
        address = value.get("ray_address") if isinstance(value, dict) else "?"
        if not (workers is None or (isinstance(workers, int) and 1 <= workers <= MAX_RAY_WORKERS)) or not (
            address is None or isinstance(address, str)
        ):
            raise SessionError(f"the session database is damaged: meta 'execution' is {short_repr(raw, 60)}")
        return {"workers": workers, "ray_address": address}

    @property
    def class_names(self) -> tuple[str, ...]:
        if self.dataset is not None:
            return tuple(self.dataset.class_names)
        names = _loads(self.meta().get("class_names", "[]"), "the class names")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise SessionError(f"the session database is damaged: class names {short_repr(names, 60)}")
        return tuple(names)

    def _check_class(self, class_name: str, names: tuple[str, ...] | None = None) -> str:
        """``class_name`` if it is one of the session's classes: a session's labels only ever have
        its classes (a data set without classes takes no labels at all)."""
        names = self.class_names if names is None else names
        if class_name not in names:
            choose = f"choose from {', '.join(names)}" if names else "the data set names no classes"
            raise SessionError(f"unknown class {short_repr(class_name)}; {choose}")
        return class_name

    def _label(self, row: sqlite3.Row | dict, names: tuple[str, ...]) -> Label:
        """A stored label, checked (``_label``), whose class must be one of ``names``, the
        session's: one of another class can only be damage. A row read before with every column
        the same is the label checked then (a damaged row is never kept: it is refused each time)."""
        key = (tuple(row), tuple(row.keys()), tuple(names)) if isinstance(row, sqlite3.Row) else None
        if key is not None:
            known = self._checked_labels.get(key)
            if known is not None:
                return known
        label = _label(row)
        if label.class_name not in names:
            raise SessionError(
                f"the session database is damaged: labels row {label.id}, class_name:"
                f" {short_repr(label.class_name)} is not one of the session's classes {list(names)}"
            )
        if key is not None:
            _keep(self._checked_labels, key, label, CHECKED_LABELS_KEPT)
        return label

    def _check_frame(self, frame_index: int, where: str = "frame index") -> int:
        index = check_frame_index(frame_index, where)
        if self.dataset is not None and not index < self.dataset.num_frames:
            raise SessionError(f"frame {frame_index} out of range [0, {self.dataset.num_frames})")
        return index

    # -- labels

    def _import_frame(
        self,
        db: sqlite3.Connection,
        frame_index: int,
        annotations: list[tuple[str, str, int]] | None = None,
    ) -> None:
        """The data set's annotations become the frame's first labels (once per session);
        ``annotations``: ``_annotations(frame_index)`` read already (outside the transaction)."""
        if db.execute("SELECT 1 FROM frames WHERE frame_index = ?", (frame_index,)).fetchone():
            return
        if annotations is None:
            annotations = self._annotations(frame_index)
        now = _now()
        db.executemany(
            "INSERT INTO labels (frame_index, box, class_name, origin, instance_id, created_by, created,"
            " modified_by, modified) VALUES (?, ?, ?, 'dataset', ?, 'dataset', ?, 'dataset', ?)",
            [(frame_index, box, name, instance_id, now, now) for box, name, instance_id in annotations],
        )
        db.execute("INSERT INTO frames VALUES (?, ?)", (frame_index, now))

    def _annotations(self, frame_index: int) -> list[tuple[str, str, int]]:
        """``(box JSON, class_name, instance_id)`` of the data set's annotations of a frame.

        They are the user's data: kept as they are, past the bounds a person's box is held to,
        only made usable (``usable_box``: a flat box thickened to ``MIN_BOX_SIZE``).

        Raises:
            SessionError: an annotation no computation can use (a negative size, a number beyond
                ``MAX_STORED_VALUE``), naming the data set, the frame and the box. (The data set
                reader has refused non-finite numbers and class ids out of range already.)
        """
        if self.dataset is None:
            raise SessionError(
                f"frame {frame_index} has no labels yet and no data set is open to import them"
            )
        # The label arrays alone: importing ahead reads every frame, and a whole frame would take
        # a place in the data set's frame cache from the frames being viewed.
        name, labels = self.dataset.frame_labels(frame_index)
        names = self.dataset.class_names
        out = []
        for k, (box, c, i) in enumerate(zip(labels.boxes, labels.class_ids, labels.instance_ids)):
            where = f"{self.dataset.path}: frame {frame_index} ({name}), annotation {k}"
            out.append((_usable_box_json(box, where), str(names[int(c)]), int(i)))
        return out

    def ensure_frames(self, frame_indices) -> None:
        """Import the data set's annotations of any of ``frame_indices`` not imported yet (a
        read-only open never writes: it reads such frames from the data set instead)."""
        if self.readonly:
            return
        todo = {self._check_frame(i) for i in frame_indices}
        with self._read() as db:
            todo -= _imported_frames(db)
        if todo:
            # The frame files are read before the write transaction: other writers (a person's
            # edit) do not wait for them.
            annotations = {index: self._annotations(index) for index in sorted(todo)}
            with self._write() as db:
                for index in sorted(todo):
                    self._import_frame(db, index, annotations[index])

    def _stored_labels(self, frames: list[int], include_deleted: bool) -> dict[int, list[Label]]:
        """The stored labels of those of ``frames`` whose labels were imported, in one read."""
        out: dict[int, list[Label]] = {}
        names = self.class_names
        with self._read() as db:
            imported = _imported_frames(db)
            wanted = [f for f in frames if f in imported]
            for f in wanted:
                out[f] = []
            query = "SELECT * FROM labels WHERE frame_index IN (SELECT value FROM json_each(?))"
            if not include_deleted:
                query += " AND deleted = 0"
            for row in db.execute(query + " ORDER BY id", (json.dumps(wanted),)):
                label = self._label(row, names)
                out[label.frame_index].append(label)
        return out

    def frame_labels(self, frame_indices, include_deleted: bool = False) -> dict[int, list[Label]]:
        """The labels of several frames, in creation order, all read in one transaction (one
        consistent state however many frames: what an export writes)."""
        frames = sorted({self._check_frame(i) for i in frame_indices})
        out = self._stored_labels(frames, include_deleted)
        missing = [f for f in frames if f not in out]
        if missing and self.readonly:
            # What the first write will store, read without writing (ids come with the store).
            for f in missing:
                out[f] = [
                    Label(None, f, tuple(json.loads(box)), name, "dataset", instance_id,
                          "dataset", "", "dataset", "", 0, False)
                    for box, name, instance_id in self._annotations(f)
                ]  # fmt: skip
        elif missing:
            self.ensure_frames(missing)
            out.update(self._stored_labels(missing, include_deleted))
        return {f: out[f] for f in frames}

    def labels(self, frame_index: int, include_deleted: bool = False) -> list[Label]:
        """The frame's labels, in creation order."""
        return next(iter(self.frame_labels([frame_index], include_deleted).values()))

    def label(self, label_id: int) -> Label:
        with self._read() as db:
            row = db.execute("SELECT * FROM labels WHERE id = ?", (int(label_id),)).fetchone()
        if row is None:
            raise SessionError(f"no label {label_id}")
        return self._label(row, self.class_names)

    def frame_boxes(self, frame_index: int, reviewed: bool | None = None) -> tuple:
        """The frame's labels as arrays: ``(boxes (R, 7), class_ids (R,), label_ids (R,))``, class
        ids indexing ``class_names`` (label id -1: not stored yet, see ``Label.id``).

        Args:
            reviewed: ``True``: only the labels a person made or confirmed (the truth metrics and
                training count); ``False``: only the unreviewed pre-labels; ``None``: all.
        """
        labels = self.labels(frame_index)  # every class checked to be one of the session's
        if reviewed is not None:
            labels = [lab for lab in labels if lab.reviewed == reviewed]
        return label_arrays(labels, self.class_names)

    def _edit(self, db: sqlite3.Connection, author: str, kind: str, summary: str, changes: list) -> int:
        """Log an edit made in ``db``'s transaction; a new edit drops its author's redo stack."""
        db.execute("UPDATE edits SET state = 'dropped' WHERE author = ? AND state = 'undone'", (author,))
        return int(
            db.execute(
                "INSERT INTO edits (author, created, kind, summary, changes) VALUES (?, ?, ?, ?, ?)",
                (author, _now(), kind, summary, json.dumps(changes)),
            ).lastrowid
        )

    @staticmethod
    def _content(db: sqlite3.Connection, table: str, key: int) -> dict | None:
        """What an edit changes of a row (``_CONTENT``), checked, as stored (undo compares it)."""
        columns = ", ".join(_CONTENT[table])
        row = db.execute(f"SELECT {columns} FROM {table} WHERE {_KEYS[table]} = ?", (key,)).fetchone()
        if row is None:
            return None
        _row(table, row, where=f"{table} row {key}")
        return dict(row)

    @staticmethod
    def _store(db: sqlite3.Connection, table: str, key: int, content: dict | None, author: str) -> None:
        """Write ``content`` to a row (``None``: delete it); labels are never deleted, only flagged."""
        if table == "labels":
            columns = [c for c in _CONTENT["labels"] if c in content]  # an older edit names fewer
            db.execute(
                f"UPDATE labels SET {', '.join(f'{c} = ?' for c in columns)},"
                " version = version + 1, modified_by = ?, modified = ? WHERE id = ?",
                (*(content[c] for c in columns), author, _now(), key),
            )
        else:
            if content is None:
                db.execute("DELETE FROM reviews WHERE negative_id = ?", (key,))
            else:
                db.execute(
                    "INSERT OR REPLACE INTO reviews VALUES (?, ?, ?, ?, ?, ?)",
                    (key, content["verdict"], content["class_name"], content["label_id"], author, _now()),
                )
            db.execute("UPDATE mined_negatives SET review_version = review_version + 1 WHERE id = ?", (key,))

    def _change(self, db, table: str, key: int, after: dict | None, author: str) -> dict:
        before = self._content(db, table, key)
        self._store(db, table, key, after, author)
        return {"table": table, "key": key, "before": before, "after": after}

    def _object_id(self, db, label_id: int) -> int:
        """The instance id of the object label ``label_id`` boxes; a label of one frame only is
        given a new one (it becomes an object), in the writing transaction."""
        row = db.execute("SELECT instance_id FROM labels WHERE id = ?", (int(label_id),)).fetchone()
        if row["instance_id"] is not None:
            return int(row["instance_id"])
        instance_id = self._new_object_id(db)
        db.execute("UPDATE labels SET instance_id = ? WHERE id = ?", (instance_id, int(label_id)))
        return instance_id

    @staticmethod
    def _object_label_in(db, instance_id: int, frame_index: int) -> sqlite3.Row | None:
        """The live label of object ``instance_id`` in a frame (``id``, ``origin``), if any."""
        return db.execute(
            "SELECT id, origin FROM labels WHERE instance_id = ? AND frame_index = ? AND deleted = 0",
            (instance_id, frame_index),
        ).fetchone()

    @staticmethod
    def _new_object_id(db) -> int:
        """An instance id no label has (``NEW_OBJECT_ID`` or above), read in the writing transaction."""
        row = db.execute("SELECT MAX(instance_id) FROM labels").fetchone()
        return max(NEW_OBJECT_ID, (row[0] or 0) + 1)

    def _insert_labels(
        self,
        db,
        items: list[tuple],
        origin: str,
        author: str,
        instance_id: int | None = None,
        scores: list[float | None] | None = None,
    ) -> tuple[list[int], list[dict]]:
        """Insert labels ``(frame_index, box JSON, class_name[, instance_id])``, of object
        ``instance_id`` where an item names none; returns their ids and changes. Labels of origin
        'model' are pre-labels (unreviewed), with the model's ``scores``.

        Each is logged as created deleted, then undeleted (version 2): undo simply flags it again.
        """
        now = _now()
        reviewed = int(origin != PRELABEL_ORIGIN)
        ids, changes = [], []
        for k, item in enumerate(items):
            frame_index, box, class_name = item[:3]
            object_id = item[3] if len(item) > 3 and item[3] is not None else instance_id
            score = None if scores is None else scores[k]
            label_id = db.execute(
                "INSERT INTO labels (frame_index, box, class_name, origin, instance_id, created_by, created,"
                " modified_by, modified, version, deleted, reviewed, score)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, 2, 0, ?, ?)",
                (frame_index, box, class_name, origin, object_id, author, now, author, now, reviewed, score),
            ).lastrowid
            ids.append(int(label_id))
            before = {
                "frame_index": frame_index, "box": box, "class_name": class_name, "deleted": 1,
                "origin": origin, "reviewed": reviewed,
            }  # fmt: skip
            changes.append(
                {"table": "labels", "key": int(label_id), "before": before, "after": {**before, "deleted": 0}}
            )
        return ids, changes

    def _insert_label(
        self, db, frame_index: int, box, class_name: str, origin: str, author: str, where: str = "box"
    ) -> tuple[int, dict]:
        ids, changes = self._insert_labels(
            db, [(frame_index, _box_json(box, where), class_name)], origin, author
        )
        return ids[0], changes[0]

    def _locked_label(self, db, label_id: int, expected_version: int | None) -> sqlite3.Row:
        row = db.execute("SELECT * FROM labels WHERE id = ?", (int(label_id),)).fetchone()
        if row is None:
            raise SessionError(f"no label {label_id}")
        self._label(row, self.class_names)  # checked; the row itself is what the edit compares
        if expected_version is not None and row["version"] != expected_version:
            raise EditConflictError(
                f"label {label_id} was changed by {row['modified_by']} at {row['modified']} "
                f"(version {row['version']}, you edited version {expected_version}); reload and try again"
            )
        return row

    def add_label(self, frame_index: int, box, class_name: str, author: str, origin: str = "user") -> Label:
        """A new label; returns it as stored."""
        return self.add_labels(
            [(frame_index, box, class_name)],
            author,
            origin,
            summary=f"add {class_name} to frame {frame_index}",
        )[0]

    def add_labels(
        self,
        items,
        author: str,
        origin: str = "import",
        *,
        screen: Callable[[dict[int, list[Label]]], list[int]] | None = None,
        summary: str | None = None,
        as_object: bool = False,
        scores=None,
    ) -> LabelBatch:
        """Several new labels as one undoable edit (returned with its ``edit_id``).

        Args:
            items: ``(frame_index, box, class_name)`` triples, or with a fourth item, the instance
                id of the object the label boxes (``world.spread_objects``: the data set's objects
                carried into more frames).
            as_object: the items are one object in several frames (label once,
                ``world.place_box``): they share a new instance id.
            scores: per item, the model's score of a pre-label (origin 'model').
            screen: called with the current labels of the items' frames, inside the transaction that
                writes, and returns the positions in ``items`` to add (an import leaves out the boxes
                that repeat a label). Checking and writing in one transaction is what keeps two
                imports of one file at the same time from both adding its boxes.
            summary: the edit log's line (default: "<origin>: add N label(s)").
        """
        if origin not in ORIGINS:
            raise SessionError(f"unknown label origin {origin!r}")
        names = self.class_names
        rows = [
            (
                self._check_frame(item[0]),
                _box_json(item[1]),
                self._check_class(item[2], names),
                None if len(item) < 4 or item[3] is None else int(item[3]),
            )
            for item in items
        ]
        scores = [None] * len(rows) if scores is None else [float(v) for v in scores]
        if len(scores) != len(rows):
            raise SessionError(f"{len(scores)} scores for {len(rows)} labels")
        rows = [(*row, score) for row, score in zip(rows, scores)]
        if not rows:
            return LabelBatch([], None)
        frames = sorted({row[0] for row in rows})
        with self._write() as db:
            for index in frames:
                self._import_frame(db, index)
            if screen is not None:
                current: dict[int, list[Label]] = {f: [] for f in frames}
                for row in db.execute(
                    "SELECT * FROM labels WHERE deleted = 0"
                    " AND frame_index IN (SELECT value FROM json_each(?)) ORDER BY id",
                    (json.dumps(frames),),
                ):
                    label = self._label(row, names)
                    current[label.frame_index].append(label)
                rows = [rows[k] for k in screen(current)]
                if not rows:
                    return LabelBatch([], None)
            instance_id = self._new_object_id(db) if as_object else None
            ids, changes = self._insert_labels(
                db, [row[:4] for row in rows], origin, author, instance_id, [row[4] for row in rows]
            )
            edit_id = self._edit(db, author, "add", summary or f"{origin}: add {len(ids)} label(s)", changes)
            wanted = set(ids)
            added = [
                self._label(r, names)
                for r in db.execute(
                    "SELECT * FROM labels WHERE id BETWEEN ? AND ? ORDER BY id", (min(ids), max(ids))
                )
                if r["id"] in wanted
            ]
        return LabelBatch(added, edit_id)

    def update_label(
        self,
        label_id: int,
        author: str,
        *,
        expected_version: int | None = None,
        box=None,
        class_name: str | None = None,
        track: Callable[[dict], dict] | None = None,
    ) -> Label:
        """Change a label's box and/or class.

        Args:
            expected_version: the version the change was made against; if the label has changed
                since, ``EditConflictError`` is raised and nothing is written.
            track: for a moving object's label, ``keyframes -> {frame: box}`` of the frames between
                them (``world.interpolate_boxes``): the label becomes a keyframe (an interpolated
                one too) and the object's computed boxes follow, in the same edit.
        """
        if class_name is not None:
            self._check_class(class_name)
        with self._write() as db:
            row = self._locked_label(db, label_id, expected_version)
            if row["deleted"]:
                raise EditConflictError(
                    f"label {label_id} was deleted by {row['modified_by']} at {row['modified']}"
                )
            content = self._content(db, "labels", int(label_id))
            after = _by_a_person(
                {
                    **content,
                    "box": row["box"] if box is None else _box_json(box),
                    "class_name": row["class_name"] if class_name is None else class_name,
                },
                content,
            )
            what = "box" if class_name is None else ("class" if box is None else "box and class")
            changes = [self._change(db, "labels", int(label_id), after, author)]
            if track is not None and row["instance_id"] is not None:
                changes += self._retrack(db, row["instance_id"], track, author, class_name)
            self._edit(db, author, "update", f"change the {what} of label {label_id}", changes)
        return self.label(label_id)

    def _retrack(
        self,
        db,
        instance_id: int,
        track: Callable[[dict], dict],
        author: str,
        class_name: str | None = None,
    ) -> list[dict]:
        """A moving object's computed boxes (origin 'interpolated') brought in line with its
        keyframes (its other live labels a person made or confirmed): each frame
        ``track(keyframes)`` gives gets its box (a new label where the object has none, no other
        label overlaps it, ``SAME_OBJECT_IOU``, and no person deleted it), and computed boxes
        outside them are deleted. Their class is ``class_name`` (default: the first keyframe's).
        Returns the changes."""
        span = db.execute(
            "SELECT MIN(frame_index), MAX(frame_index) FROM labels WHERE instance_id = ? AND deleted = 0",
            (instance_id,),
        ).fetchone()
        if span[0] is None:
            return []
        # The data set's own labels of the object in the frames between come in first: they are
        # keyframes, not places for a computed box.
        for frame_index in range(int(span[0]), int(span[1]) + 1):
            self._import_frame(db, frame_index)
        rows = db.execute(
            "SELECT * FROM labels WHERE instance_id = ? ORDER BY frame_index, id", (instance_id,)
        ).fetchall()
        members = [m for m in rows if not m["deleted"]]
        # Where a person deleted the object's box (a delete of a computed box makes it theirs,
        # ``delete_labels``), it stays out: the object is hidden there.
        deleted_in = {m["frame_index"] for m in rows if m["deleted"] and m["origin"] not in COMPUTED_ORIGINS}
        keys = [m for m in members if m["origin"] not in COMPUTED_ORIGINS and m["reviewed"]]
        keyframes = {m["frame_index"]: json.loads(m["box"]) for m in keys}
        if not keyframes:
            return []
        class_name = class_name or keys[0]["class_name"]
        taken = {m["frame_index"] for m in members if m["origin"] not in COMPUTED_ORIGINS}
        wanted = {
            self._check_frame(f): _box_json(b, f"box of frame {f}")
            for f, b in track(keyframes).items()
            if int(f) not in taken and int(f) not in deleted_in
        }
        changes = []
        for member in members:
            if member["origin"] not in COMPUTED_ORIGINS:
                continue
            content = self._content(db, "labels", int(member["id"]))
            box = wanted.pop(member["frame_index"], None)
            after = (
                {**content, "deleted": 1}
                if box is None
                else {**content, "box": box, "class_name": class_name}
            )
            if after != content:
                changes.append(self._change(db, "labels", int(member["id"]), after, author))
        items = []
        for frame_index, box in sorted(wanted.items()):
            self._import_frame(db, frame_index)
            if not self._overlapped(db, frame_index, box, instance_id):
                items.append((frame_index, box, class_name))
        if items:
            changes += self._insert_labels(db, items, "interpolated", author, instance_id)[1]
        return changes

    def add_keyframe(
        self,
        label_id: int,
        frame_index: int,
        box,
        author: str,
        *,
        expected_version: int | None = None,
        track: Callable[[dict], dict] | None = None,
    ) -> Label:
        """A moving object (person, truck) labelled in one more frame: a keyframe of the object
        label ``label_id`` boxes, with its class, and (given ``track``, see ``update_label``) its
        boxes in the frames between its keyframes computed; one edit. Returns the new label.

        Raises:
            EditConflictError: the label changed since ``expected_version`` or was deleted, or the
                object is labelled in that frame already (move that label instead).
        """
        frame_index = self._check_frame(frame_index)
        box_json = _box_json(box)
        names = self.class_names
        with self._write() as db:
            row = self._locked_label(db, label_id, expected_version)
            if row["deleted"]:
                raise EditConflictError(
                    f"label {label_id} was deleted by {row['modified_by']} at {row['modified']}"
                )
            self._import_frame(db, frame_index)
            changes = []
            source = self._content(db, "labels", int(label_id))
            if not source["reviewed"]:  # a pre-label carried to another frame: a person's choice
                changes.append(
                    self._change(db, "labels", int(label_id), _by_a_person(source, source), author)
                )
            instance_id = self._object_id(db, label_id)
            there = self._object_label_in(db, instance_id, frame_index)
            if there is not None and there["origin"] not in COMPUTED_ORIGINS:
                raise EditConflictError(
                    f"the object is labelled in frame {frame_index} already (label {there['id']}):"
                    " move that one"
                )
            if there is not None:  # a computed box there becomes the keyframe
                content = self._content(db, "labels", int(there["id"]))
                after = _by_a_person({**content, "box": box_json})
                changes.append(self._change(db, "labels", int(there["id"]), after, author))
                new_id = int(there["id"])
            else:
                ids, inserted = self._insert_labels(
                    db, [(frame_index, box_json, row["class_name"])], "user", author, instance_id
                )
                changes += inserted
                new_id = ids[0]
            if track is not None:
                changes += self._retrack(db, instance_id, track, author)
            self._edit(
                db,
                author,
                "add",
                f"add a keyframe of label {label_id}'s object in frame {frame_index}",
                changes,
            )
            return self._label(db.execute("SELECT * FROM labels WHERE id = ?", (new_id,)).fetchone(), names)

    @staticmethod
    def _overlapped(db, frame_index: int, box_json: str, instance_id: int | None) -> bool:
        """Whether a live label of another object in the frame overlaps the box (IoU at least
        ``SAME_OBJECT_IOU``): the object is labelled there already, under another id."""
        others = [
            json.loads(r["box"])
            for r in db.execute(
                "SELECT box, instance_id FROM labels WHERE frame_index = ? AND deleted = 0", (frame_index,)
            )
            if instance_id is None or r["instance_id"] != instance_id
        ]
        return labelled_there(json.loads(box_json), others)

    @staticmethod
    def _members(db, row) -> list[sqlite3.Row]:
        """The live labels of the object ``row`` boxes, in frame order (``row`` alone without one)."""
        if row["instance_id"] is None:
            return [row]
        return db.execute(
            "SELECT * FROM labels WHERE instance_id = ? AND deleted = 0 ORDER BY frame_index, id",
            (row["instance_id"],),
        ).fetchall()

    def object_labels(self, label_id: int) -> list[Label]:
        """Every live label of the object label ``label_id`` boxes, in frame order (the label alone
        when it has no instance id: a box of this frame only)."""
        names = self.class_names
        with self._read() as db:
            row = db.execute("SELECT * FROM labels WHERE id = ?", (int(label_id),)).fetchone()
            if row is None:
                raise SessionError(f"no label {label_id}")
            return [self._label(r, names) for r in self._members(db, row)]

    def update_object(
        self,
        label_id: int,
        author: str,
        *,
        expected_version: int | None = None,
        boxes: dict | None = None,
        show_in=None,
        class_name: str | None = None,
        origin: str = "user",
    ) -> Label:
        """Change an object in every frame at once, as one undoable edit (label once).

        Args:
            label_id: the label the person edited; the change applies to every live label of its
                object (``object_labels``).
            expected_version: the version of ``label_id`` the change was made against
                (``EditConflictError`` if it changed since; nothing is written).
            boxes: ``{frame_index: box}``, the object's box in each frame (``world.Placement``):
                each of its labels in these frames takes its frame's box, the others keep theirs.
                A label of this frame only becomes an object (undo leaves it that id: an object of
                one label is a label of one frame).
            show_in: the frames among ``boxes`` that show the object (default: all of them): each
                without a label of it gets one (``origin``), unless another label there overlaps
                the box (IoU ``SAME_OBJECT_IOU`` or more: the object is labelled there already).
                Decided here, in the writing transaction, so labels added meanwhile count.
            class_name: the class of all its labels (``None``: each keeps its own).

        Returns:
            ``label_id`` as stored after the change.
        """
        names = self.class_names
        if class_name is not None:
            self._check_class(class_name, names)
        wanted = {self._check_frame(f): _box_json(b, f"box of frame {f}") for f, b in (boxes or {}).items()}
        with self._write() as db:
            row = self._locked_label(db, label_id, expected_version)
            if row["deleted"]:
                raise EditConflictError(
                    f"label {label_id} was deleted by {row['modified_by']} at {row['modified']}"
                )
            instance_id = row["instance_id"]
            if instance_id is None and set(wanted) - {row["frame_index"]}:
                instance_id = self._object_id(db, label_id)
                row = db.execute("SELECT * FROM labels WHERE id = ?", (int(label_id),)).fetchone()
            for index in sorted(set(wanted)):  # the data set's own labels of the object come first
                self._import_frame(db, index)
            members = self._members(db, row)
            changes = []
            new_class = row["class_name"] if class_name is None else class_name
            for member in members:
                content = self._content(db, "labels", int(member["id"]))
                after = {
                    **content,
                    "box": wanted.get(member["frame_index"], member["box"]),
                    # A box move leaves each frame's class as it is; a class change sets them all.
                    "class_name": member["class_name"] if class_name is None else class_name,
                }
                if after != content:
                    after = _by_a_person(after, content)
                    changes.append(self._change(db, "labels", int(member["id"]), after, author))
            shown = set(wanted) if show_in is None else {int(f) for f in show_in} & set(wanted)
            changes += self._add_to_frames(db, instance_id, wanted, shown, new_class, origin, author)
            if not changes:
                return self._label(row, names)
            what = "box" if class_name is None else ("class" if not wanted else "box and class")
            where = f"label {label_id}" if len(changes) == 1 else f"an object in {len(changes)} frames"
            self._edit(db, author, "update", f"change the {what} of {where}", changes)
        return self.label(label_id)

    def delete_labels(
        self,
        label_ids,
        author: str,
        expected_versions: dict[int, int] | None = None,
        whole_objects: bool = False,
    ) -> int:
        """Delete labels (they stay in the database, flagged, so undo can restore them).

        Args:
            expected_versions: ``{label id: version}`` the deletion was made against.
            whole_objects: delete every live label of each one's object too (label once).

        Returns:
            The edit id.
        """
        expected_versions = expected_versions or {}
        with self._write() as db:
            if whole_objects:
                ids = []
                for label_id in label_ids:
                    row = self._locked_label(db, label_id, expected_versions.get(int(label_id)))
                    ids += [int(label_id)] + [
                        int(m["id"]) for m in self._members(db, row) if int(m["id"]) != int(label_id)
                    ]
                label_ids = list(dict.fromkeys(ids))
            changes = []
            for label_id in label_ids:
                row = self._locked_label(db, label_id, expected_versions.get(int(label_id)))
                if row["deleted"]:
                    raise EditConflictError(f"label {label_id} is already deleted (by {row['modified_by']})")
                content = self._content(db, "labels", int(label_id))
                # A person deleting a computed box says the object is not there: theirs, kept out.
                origin = "user" if content["origin"] in COMPUTED_ORIGINS else content["origin"]
                after = {**content, "deleted": 1, "origin": origin}
                changes.append(self._change(db, "labels", int(label_id), after, author))
            if not changes:
                raise SessionError("no labels to delete")
            return self._edit(db, author, "delete", f"delete {len(changes)} label(s)", changes)

    # -- pre-labels (the model's boxes, waiting for a person)

    def confirm_labels(self, label_ids, author: str, expected_versions: dict[int, int] | None = None) -> int:
        """A person confirms pre-labels as they are (one undoable edit); returns the edit id.

        Raises:
            EditConflictError: one was changed since the version given, deleted, or confirmed
                already; nothing is written.
        """
        expected_versions = expected_versions or {}
        with self._write() as db:
            changes = []
            for label_id in dict.fromkeys(int(i) for i in label_ids):
                row = self._locked_label(db, label_id, expected_versions.get(label_id))
                if row["deleted"]:
                    raise EditConflictError(f"label {label_id} was deleted by {row['modified_by']}")
                content = self._content(db, "labels", label_id)
                if content["reviewed"]:
                    raise EditConflictError(
                        f"label {label_id} is confirmed already (by {row['modified_by']})"
                    )
                # (confirmed as it is: the box stays the model's)
                changes.append(self._change(db, "labels", label_id, _by_a_person(content, content), author))
            if not changes:
                raise SessionError("no pre-labels to confirm")
            return self._edit(db, author, "confirm", f"confirm {len(changes)} pre-label(s)", changes)

    def unreviewed_labels(self) -> list[Label]:
        """The live pre-labels no person has confirmed or edited yet: frame by frame, the model's
        most confident first (the queue a person confirms them from)."""
        names = self.class_names
        with self._read() as db:
            # (a schema 2 database or older, read as it is, has no pre-labels)
            if "reviewed" not in _table_columns(db, "labels"):
                return []
            rows = db.execute(
                "SELECT * FROM labels WHERE deleted = 0 AND reviewed = 0 ORDER BY frame_index, score DESC, id"
            ).fetchall()
            return [self._label(r, names) for r in rows]

    # -- undo and redo

    def _replay(self, author: str, undo: bool) -> Edit | None:
        state, order, new_state = ("done", "DESC", "undone") if undo else ("undone", "ASC", "done")
        names = self.class_names
        with self._write() as db:
            row = db.execute(
                f"SELECT * FROM edits WHERE author = ? AND state = ? ORDER BY id {order} LIMIT 1",
                (author, state),
            ).fetchone()
            if row is None:
                return None
            edit = _row("edits", row)
            changes = self._changes(edit, names)
            versions: dict[int, tuple[int, int]] = {}
            for change in reversed(changes) if undo else changes:
                expected, target = (
                    (change["after"], change["before"]) if undo else (change["before"], change["after"])
                )
                current = self._content(db, change["table"], change["key"])
                if not _same_content(current, expected):
                    raise EditConflictError(
                        f"cannot {'undo' if undo else 'redo'} '{edit['summary']}': "
                        f"{change['table'][:-1]} {change['key']} has been changed since"
                    )
                if change["table"] == "labels":
                    version = db.execute("SELECT version FROM labels WHERE id = ?", (change["key"],))
                    before = _row("labels", version.fetchone(), f"labels row {change['key']}")["version"]
                    versions[change["key"]] = (versions.get(change["key"], (before,))[0], before + 1)
                self._store(db, change["table"], change["key"], target, author)
            db.execute("UPDATE edits SET state = ? WHERE id = ?", (new_state, edit["id"]))
            return dataclasses.replace(self._edit_of(edit, new_state), label_versions=versions)

    def _changes(self, edit: dict, names: tuple[str, ...]) -> list[dict]:
        """An edit's changes (its ``changes`` column, decoded), every one checked as what undo and
        redo compare and write back: the table, the key, and the content on both sides, column
        by column as the table's rows are (``_COLUMNS``), classes among the session's ``names``.

        Raises:
            SessionError: one line naming the edit and the change.
        """
        for k, change in enumerate(edit["changes"]):
            place = f"edits row {edit['id']}, change {k}"
            where = f"the session database is damaged: {place}"
            if not isinstance(change, dict) or set(change) != {"table", "key", "before", "after"}:
                raise SessionError(f"{where} is {short_repr(change, 60)}, not a change of a row")
            table = change["table"]
            if table not in _CONTENT:
                raise SessionError(
                    f"{where} names the table {short_repr(table, 30)}, not one an edit changes"
                )
            try:
                _integer(change["key"])
            except ValueError as exc:
                raise SessionError(f"{where}: key {exc}") from None
            for side in ("before", "after"):
                content = change[side]
                if content is None and table == "reviews":  # no verdict on that side
                    continue
                if not isinstance(content, dict) or not (
                    set(_CONTENT[table]) - _LATER_CONTENT[table] <= set(content) <= set(_CONTENT[table])
                ):
                    raise SessionError(f"{where}, {side}: {short_repr(content, 60)} is not a {table} row")
                _row(table, content, where=f"{place}, {side} ({table} row {change['key']})")
                frame = content.get("frame_index")
                if frame is not None and self.dataset is not None and frame >= self.dataset.num_frames:
                    raise SessionError(
                        f"{where}, {side}: frame {frame} is not one of the data set's "
                        f"{self.dataset.num_frames} frames"
                    )
                if content["class_name"] is not None and content["class_name"] not in names:
                    raise SessionError(
                        f"{where}, {side}: class {short_repr(content['class_name'])} is not one of the"
                        f" session's {list(names)}"
                    )
        return edit["changes"]

    @staticmethod
    def _edit_of(row: dict, state: str | None = None) -> Edit:
        return Edit(
            row["id"], row["author"], row["created"], row["kind"], row["summary"], state or row["state"]
        )

    def undo(self, author: str) -> Edit | None:
        """Undo ``author``'s latest edit that is not undone; ``None`` if there is none.

        Raises:
            EditConflictError: something it changed was changed again since (by anyone).
        """
        return self._replay(author, undo=True)

    def redo(self, author: str) -> Edit | None:
        """Redo ``author``'s most recently undone edit; ``None`` if there is none."""
        return self._replay(author, undo=False)

    def edits(self, author: str | None = None, limit: int = 50) -> list[Edit]:
        """The edit log, newest first."""
        query, args = "SELECT * FROM edits", []
        if author is not None:
            query, args = query + " WHERE author = ?", [author]
        with self._read() as db:
            rows = db.execute(query + " ORDER BY id DESC LIMIT ?", [*args, limit]).fetchall()
        return [self._edit_of(_row("edits", r)) for r in rows]

    def can_undo(self, author: str) -> tuple[bool, bool]:
        """Whether ``author`` has an edit to undo, and one to redo."""
        with self._read() as db:
            states = {
                r[0] for r in db.execute("SELECT DISTINCT state FROM edits WHERE author = ?", (author,))
            }
        return "done" in states, "undone" in states

    # -- label snapshots (what a training run learnt from)

    def snapshot_labels(self, frame_indices) -> int:
        """Store the current labels of ``frame_indices``; returns the snapshot id."""
        self.ensure_frames(frame_indices)
        frames = sorted({int(i) for i in frame_indices})
        with self._write() as db:
            rows = db.execute(
                f"SELECT {', '.join(_SNAPSHOT_LABEL)} FROM labels WHERE deleted = 0"
                f" AND frame_index IN ({','.join('?' * len(frames))}) ORDER BY id",
                frames,
            ).fetchall()
            labels = [_row("labels", r) for r in rows]
            for label in labels:
                label["box"] = list(label["box"])  # stored as JSON
            last_edit = db.execute("SELECT MAX(id) FROM edits").fetchone()[0]
            return int(
                db.execute(
                    "INSERT INTO label_snapshots (created, last_edit_id, num_labels, labels)"
                    " VALUES (?, ?, ?, ?)",
                    (_now(), last_edit, len(labels), json.dumps({"frames": frames, "labels": labels})),
                ).lastrowid
            )

    def snapshot_size(self, snapshot_id: int) -> int:
        """How many labels a snapshot holds."""
        with self._read() as db:
            row = db.execute(
                "SELECT id, num_labels FROM label_snapshots WHERE id = ?", (int(snapshot_id),)
            ).fetchone()
        if row is None:
            raise SessionError(f"no label snapshot {snapshot_id}")
        return _row("label_snapshots", row)["num_labels"]

    def snapshot(self, snapshot_id: int) -> dict:
        """A stored snapshot: ``created``, ``last_edit_id``, ``frames`` and ``labels``."""
        with self._read() as db:
            row = db.execute("SELECT * FROM label_snapshots WHERE id = ?", (int(snapshot_id),)).fetchone()
        if row is None:
            raise SessionError(f"no label snapshot {snapshot_id}")
        snapshot = _row("label_snapshots", row)
        stored = snapshot["labels"]
        try:
            frames = _json_of(list, _frame)(stored.get("frames"))
            labels = _json_of(list)(stored.get("labels"))
        except ValueError as exc:
            raise SessionError(
                f"the session database is damaged: label_snapshots row {snapshot_id}, labels: {exc}"
            ) from None
        for k, label in enumerate(labels):
            if not isinstance(label, dict) or not set(_SNAPSHOT_LABEL) - {"reviewed"} <= set(label) <= set(
                _SNAPSHOT_LABEL
            ):
                raise SessionError(
                    f"the session database is damaged: label_snapshots row {snapshot_id}, labels:"
                    f" {short_repr(label, 60)} is not a label"
                )
            _row("labels", label, where=f"label_snapshots row {snapshot_id}, label {k}")
        return {
            "id": snapshot["id"],
            "created": snapshot["created"],
            "last_edit_id": snapshot["last_edit_id"],
            "frames": frames,
            "labels": labels,
        }

    # -- training runs

    def _run_dir(self, run_id: int) -> Path:
        """Run ``run_id``'s checkpoint folder, ``models/run_NNN/``."""
        return self.session.models_dir / f"run_{int(run_id):03d}"

    def fold_model_paths(self, run_id: int) -> list[Path]:
        """The checkpoints of run ``run_id``'s threshold fold models (``fold_K.pt``, in fold
        order; none for a run without threshold folds)."""
        run_dir = self._run_dir(run_id)
        folds = {}
        for path in run_dir.glob("fold_*.pt"):
            match = re.fullmatch(r"fold_(\d+)\.pt", path.name)
            if match:  # (anything else there is not one of ours)
                folds[int(match.group(1))] = path
        return [folds[k] for k in sorted(folds)]

    def save_training_run(
        self, run, data: str, config: dict, *, kind: str = "mining", snapshot_id: int | None = None
    ) -> int:
        """Store a ``mining.TrainingRun``: a checkpoint per round under ``models/run_NNN/``, the
        final one as ``final.pt``, its threshold fold models as ``fold_K.pt``, and the rounds and
        mined negatives in the database.

        Args:
            kind: 'mining' (blind, from the labels), 'retrain', or whatever the caller names it.
            snapshot_id: the label snapshot the run was trained on (``snapshot_labels``).

        Returns:
            The run id.
        """
        with self._write() as db:
            # The row first: its id names the checkpoint folder, so two runs never share one.
            run_id = int(
                db.execute(
                    "INSERT INTO training_runs (created, kind, data, config, train_frames, snapshot_id,"
                    " model_path) VALUES (?, ?, ?, ?, ?, ?, '')",
                    (_now(), kind, data, json.dumps(config), json.dumps(run.train_frames), snapshot_id),
                ).lastrowid
            )
        # Checkpoints are written outside the transaction (they take seconds); the run only points
        # at its final model once every file is in place.
        run_dir = self._run_dir(run_id)
        note = {"data": data, "train_frames": run.train_frames, "config": config, "run_id": run_id}
        paths = []
        for record, model in zip(run.rounds, run.models):
            path = run_dir / f"round_{record['round']}.pt"
            model.save(path, {**note, "round": record["round"], "train_metrics": record["train_metrics"]})
            paths.append(path)
        # The last round's threshold fold models: a next round goes on from them (each never saw
        # the frames its fold scores). Written before final.pt, which says the run is complete.
        for k, fold in enumerate(getattr(run, "fold_models", ())):
            fold_note = {**note, "fold": k, "fold_frames": [int(i) for i in fold.frame_indices]}
            fold.classifier.save(run_dir / f"fold_{k}.pt", fold_note)
        final = run_dir / "final.pt"
        run.model.save(
            final,
            {
                **note,
                "round": run.rounds[-1]["round"],
                "rounds": len(run.rounds),
                "rounds_record": rounds_record(run),
            },
        )
        with self._write() as db:
            for record, path in zip(run.rounds, paths):
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
                        str(path.relative_to(self.session.path)),
                    ),
                )
                # The mined negatives (background from now on), then the false positives queued
                # for review alone (``LoopSettings.review_extra``).
                rows = [(m, 1) for m in record["mined"]] + [(m, 0) for m in record.get("queued", [])]
                db.executemany(
                    "INSERT INTO mined_negatives (run_id, round, frame_index, proposal, box, patch_set,"
                    " score, predicted_class, probabilities, best_annotated_iou, in_background)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
                            json.dumps(m.get("probabilities"))
                            if m.get("probabilities") is not None
                            else None,
                            m["best_annotated_iou"],
                            in_background,
                        )
                        for m, in_background in rows
                    ],
                )
            db.execute(
                "UPDATE training_runs SET model_path = ? WHERE id = ?",
                (str(final.relative_to(self.session.path)), run_id),
            )
        return run_id

    def set_run_metrics(self, run_id: int, metrics: dict) -> None:
        """Attach test-frame metrics (e.g. the before/after table) to a run."""
        with self._write() as db:
            db.execute(
                "UPDATE training_runs SET metrics = ? WHERE id = ?", (json.dumps(metrics), int(run_id))
            )

    def training_runs(self) -> list[dict]:
        """Every finished training run with its rounds, oldest first."""
        with self._read() as db:
            runs = [
                _row("training_runs", r)
                for r in db.execute("SELECT * FROM training_runs WHERE model_path != '' ORDER BY id")
            ]
            for run in runs:
                run["rounds"] = [
                    _row(
                        "training_rounds",
                        r,
                        f"training_rounds row ({run['id']}, {short_repr(r['round'], 20)})",
                    )
                    for r in db.execute(
                        "SELECT * FROM training_rounds WHERE run_id = ? ORDER BY round", (run["id"],)
                    )
                ]
        return runs

    def hold_score(self, run_id: int) -> float | None:
        """The score at or above which run ``run_id`` held its mined negatives out of the
        background until reviewed (``LoopSettings.hold_confident``; ``None``: it held none)."""
        hold = self._run_settings(run_id).get("hold_confident")
        return None if hold is None else float(hold)

    def pseudo_label_score(self, run_id: int) -> float | None:
        """The score at or above which run ``run_id`` took its mined negatives off the labels for
        labels of their predicted class until reviewed (``LoopSettings.pseudo_label_confident``;
        ``None``: none)."""
        score = self._run_settings(run_id).get("pseudo_label_confident")
        return None if score is None else float(score)

    def review_order(self, run_id: int | None = None) -> str:
        """How run ``run_id`` (the latest by default) orders its review queue
        (``LoopSettings.review_order``, else the order that cut its mined negatives,
        ``LoopSettings.queue_order``; "score" for runs from before either was a setting, and when
        there is no run)."""
        return self.orders(run_id)[0]

    def cut_order(self, run_id: int | None = None) -> str:
        """The order run ``run_id`` (the latest by default) cut its mined negatives in
        (``LoopSettings.queue_order``; "score" for runs from before it was a setting): its review
        queue's order by item when the review order is "learned" (which orders places,
        ``session.review_rank``), and the places' order until it has enough verdicts."""
        return self.orders(run_id)[1]

    def orders(self, run_id: int | None = None) -> tuple[str, str]:
        """``(review_order, cut_order)`` of run ``run_id`` (the latest by default), from one read
        of its settings: what a queue read needs both of (``session.queue.unlearned_order``)."""
        if run_id is None:
            run_id = self.latest_run_id()
            if run_id is None:
                return "score", "score"
        settings = self._run_settings(run_id)
        review = review_order_of(settings) or "score"
        if review not in REVIEW_ORDERS:
            raise SessionError(f"training run {run_id}: unknown review order {short_repr(review, 40)}")
        cut = settings.get("queue_order") or "score"
        if cut not in QUEUE_ORDERS:
            raise SessionError(f"training run {run_id}: unknown queue order {short_repr(cut, 40)}")
        return str(review), str(cut)

    def run_config(self, run_id: int) -> dict:
        """Run ``run_id``'s config as ``train_session`` stored it (one row read, where
        ``training_runs`` reads every run with its rounds)."""
        with self._read() as db:
            row = db.execute("SELECT id, config FROM training_runs WHERE id = ?", (int(run_id),)).fetchone()
        if row is None:
            raise SessionError(f"no training run {run_id}")
        return _row("training_runs", row)["config"]

    def _run_settings(self, run_id: int) -> dict:
        """Run ``run_id``'s ``LoopSettings`` as stored in its config (``{}`` for a run without)."""
        settings = self.run_config(run_id).get("settings") or {}
        if not isinstance(settings, dict):
            raise SessionError(
                f"training run {run_id}: its settings are {short_repr(settings, 40)}, not a mapping"
            )
        return settings

    def change_stamp(self) -> tuple:
        """A value that changes with every edit to the session's labels and verdicts and every
        training run, by this process or another (a new edit, an undo or redo, a run; not the
        import of a frame's annotations, which a first read makes): the newest edit, the edits
        undone (a redo stack) and the newest run, which together say what the edit log holds.
        Cheap to read: what a cache of views derived from the session is keyed on.

        Two more parts keep it from coming back to an earlier value while the session moved on:
        the newest finished run (a run's row is written before its model, and only a finished run
        has a queue) and the sum of the verdicts' versions (an undo then a redo leaves the edit log
        as it was, but every verdict it touched has a new version)."""
        versions = "(SELECT SUM(review_version) FROM mined_negatives)" if self.schema_version > 1 else "NULL"
        with self._read() as db:
            return tuple(
                db.execute(
                    "SELECT (SELECT MAX(id) FROM edits),"
                    " (SELECT group_concat(id) FROM"
                    " (SELECT id FROM edits WHERE state = 'undone' ORDER BY id)),"
                    " (SELECT MAX(id) FROM training_runs),"
                    " (SELECT MAX(id) FROM training_runs WHERE model_path != ''),"
                    f" {versions}"
                ).fetchone()
            )

    def latest_run_id(self) -> int | None:
        with self._read() as db:
            return db.execute("SELECT MAX(id) FROM training_runs WHERE model_path != ''").fetchone()[0]

    # -- the review queue

    def review_queue(
        self,
        run_id: int | None = None,
        *,
        predicted_class: str | None = None,
        frame_index: int | None = None,
        pending_only: bool = False,
        max_label_iou: float | None = None,
    ) -> list[dict]:
        """Negatives mined by a run (the latest by default), and the false positives it queued for
        review alone (``in_background`` 0: ``LoopSettings.review_extra``), in its review order
        (``queue_order``: highest score first, or the predicted classes taking turns), each with its
        verdict (``None`` if unreviewed), the verdict's class, label and reviewer, and
        ``label_iou``: its box's highest IoU with the frame's current labels (``label_overlap``).

        Args:
            max_label_iou: leave out items whose box overlaps a current label at this IoU or more
                (``None``: keep all). Such an item is a part, a duplicate or a loose box of an
                object already labelled: it is trained as background whatever its verdict, so a
                reviewer's time is better spent on the items that overlap no label, where the
                unlabelled objects are.
        """
        if max_label_iou is not None and not 0.0 < max_label_iou <= 1.0:
            raise InputError(f"max_label_iou must lie in (0, 1], got {max_label_iou}")
        if run_id is None:
            run_id = self.latest_run_id()
        out = self._queue_rows(run_id, predicted_class, frame_index, pending_only)
        if out:
            order = unlearned_order(*self.orders(run_id))
            if order != "score":
                out = self._in_queue_order(run_id, order, out)
        label_iou = self.label_overlap(out)
        for item, iou in zip(out, label_iou):
            item["label_iou"] = iou
        if max_label_iou is not None:
            out = [item for item in out if not on_labelled_object(item["label_iou"], max_label_iou)]
        return out

    def _in_queue_order(self, run_id: int, order: str, items: list[dict]) -> list[dict]:
        """``items`` of run ``run_id``'s queue in ``order`` (``session.queue``), each at its
        position in the whole queue: a filter or a verdict given leaves the rest where they were."""
        cached_run, position = self._queue_positions
        if cached_run != (run_id, order):  # a run's mined negatives never change once it is stored
            with self._read() as db:
                rows = db.execute(
                    "SELECT id, predicted_class, score FROM mined_negatives WHERE run_id = ?"
                    " ORDER BY score DESC, id",
                    (int(run_id),),
                ).fetchall()
            ranked = order_queue([r["score"] for r in rows], [r["predicted_class"] for r in rows], order)
            position = {int(rows[k]["id"]): p for p, k in enumerate(ranked.tolist())}
            self._queue_positions = ((run_id, order), position)
        return sorted(items, key=lambda item: position[int(item["id"])])

    def _queue_rows(
        self, run_id: int | None, predicted_class: str | None, frame_index: int | None, pending_only: bool
    ) -> list[dict]:
        """``review_queue``'s rows as stored, without the overlap with the labels.

        A run's mined negatives never change once it is stored but for their review version: a
        read that meets a row for the first time reads and checks its rows whole (``_row``, row by
        row in queue order) and keeps them (``_mined_checked``); a read that knows every row asks
        SQLite only for each row's version and joined verdict (the review panel reads the queue
        after every verdict, and decoding a thousand rows' boxes each time was most of a
        verdict's time)."""
        if run_id is None:
            run_id = self.latest_run_id()
        checked_run, checked = self._mined_checked
        if checked_run != run_id:
            checked = {}
        where, args = " WHERE m.run_id = ?", [run_id]
        if predicted_class is not None:
            where, args = where + " AND m.predicted_class = ?", [*args, predicted_class]
        if frame_index is not None:
            where, args = where + " AND m.frame_index = ?", [*args, int(frame_index)]
        if pending_only:
            where += " AND (r.verdict IS NULL OR r.verdict = 'skip')"
        joined = (
            " r.verdict, r.class_name AS verdict_class, r.label_id, r.author AS reviewer,"
            " r.created AS reviewed FROM mined_negatives m LEFT JOIN reviews r ON r.negative_id = m.id"
            f"{where} ORDER BY m.score DESC, m.id"
        )
        with self._read() as db:
            versioned = "review_version" in _table_columns(db, "mined_negatives")
            version = "m.review_version" if versioned else "NULL AS review_version"
            rows = db.execute(f"SELECT m.id, {version},{joined}", args).fetchall()
            whole = any(r["id"] not in checked for r in rows)
            if whole:
                rows = db.execute(f"SELECT m.*,{joined}", args).fetchall()
        check_version = _COLUMNS["mined_negatives"]["review_version"]
        out = []
        for r in rows:
            if whole and r["id"] not in checked:
                item = _row("mined_negatives", r)  # its columns checked in order, the verdict's left
                known = {k: item[k] for k in r.keys() if k == "id" or k not in _VERDICT_COLUMNS}
                checked[known["id"]] = (known, [k for k, v in known.items() if isinstance(v, list)])
            known, lists = checked[r["id"]]
            item = dict(known)
            for key in lists:  # copied: a caller may change the item it got, not the next caller's
                item[key] = list(item[key])
            if versioned:
                try:
                    item["review_version"] = check_version(r["review_version"])
                except (TypeError, ValueError):  # (``_row`` names the row and the column)
                    _row("mined_negatives", {"id": item["id"], "review_version": r["review_version"]})
            for alias in _VERDICT_COLUMNS:
                if alias != "id":
                    item[alias] = r[alias]
            if item["reviewed"] is not None or item["verdict"] is not None:  # the joined verdict
                _row("reviews", {column: item[alias] for alias, column in _VERDICT_COLUMNS.items()})
            item.setdefault("review_version", 0)  # a schema 1 database, read-only: not versioned yet
            item.setdefault("in_background", 1)  # before schema 4, every item was a mined negative
            out.append(item)
        self._mined_checked = (run_id, checked)
        return out

    def label_overlap(self, items: list[dict]) -> list[float | None]:
        """Each item's (a dict with ``frame_index`` and ``box``) highest box IoU with the current
        labels of its frame (0 when it overlaps none; ``None`` for a frame whose labels were never
        imported, when no data set is open to import them)."""
        import numpy as np

        by_frame: dict[int, list[int]] = {}
        for i, item in enumerate(items):
            by_frame.setdefault(int(item["frame_index"]), []).append(i)
        readable = set(by_frame)
        if self.dataset is None:
            with self._read() as db:
                readable &= _imported_frames(db)
        out: list[float | None] = [None] * len(items)
        labels = self.frame_labels(sorted(readable))  # every frame's in one read
        for index, positions in by_frame.items():
            if index not in readable:
                continue
            boxes = label_arrays(labels[index], self.class_names)[0]
            iou = np.zeros(len(positions))
            if len(boxes):
                item_boxes = np.array([items[i]["box"] for i in positions], np.float64).reshape(-1, 7)
                # The queue is read again after every verdict, and its items and (mostly) the
                # labels are the ones of the last read: rotated-box IoU is what that read cost.
                key = (item_boxes.tobytes(), np.ascontiguousarray(boxes, np.float64).tobytes())
                iou = self._overlaps.get(key)
                if iou is None:
                    iou = box_iou_3d(item_boxes, boxes).max(axis=1).tolist()
                    _keep(self._overlaps, key, iou, OVERLAPS_KEPT)
            for i, value in zip(positions, iou):
                out[i] = round(float(value), 4)
        return out

    def review_progress(self, run_id: int | None = None) -> dict:
        """Counts of a run's queue: ``total``, ``reviewed`` (a decided verdict) and per verdict.
        Reads the verdicts alone (a damaged row elsewhere is ``review_queue``'s to report)."""
        if run_id is None:
            run_id = self.latest_run_id()
        # Counted in SQL: every panel refresh asks, and a run's queue holds thousands of items.
        with self._read() as db:
            rows = db.execute(
                "SELECT r.verdict, COUNT(*), MIN(r.negative_id) FROM mined_negatives m"
                " LEFT JOIN reviews r ON r.negative_id = m.id WHERE m.run_id = ? GROUP BY r.verdict",
                (run_id,),
            ).fetchall()
        by_verdict = {
            (
                None
                if verdict is None
                else _row("reviews", {"verdict": verdict}, f"reviews row {row}")["verdict"]
            ): int(n)
            for verdict, n, row in rows
        }  # (a verdict that is none of VERDICTS is damage, named as such)
        counts = {v: by_verdict.get(v, 0) for v in VERDICTS}
        return {
            "total": sum(by_verdict.values()),
            "reviewed": sum(counts[v] for v in DECIDED),
            **counts,
        }

    def review(
        self,
        negative_ids,
        verdict: str,
        author: str,
        *,
        class_name: str | None = None,
        expected_versions: dict[int, int] | None = None,
        expected: dict[int, str | None] | None = None,
        override: bool = False,
        place: Callable[[int, tuple], tuple[dict, list]] | None = None,
        one_object: bool = False,
    ) -> int:
        """Give one verdict on mined negatives, as one undoable edit.

        'object' makes each a label of ``class_name`` (origin 'review', the mined box); a later
        different verdict on it deletes that label again. An item that already has this verdict is
        left as it is.

        Every verdict is versioned (the queue item's ``review_version``), so a reviewer who did not
        see the latest verdict on an item is refused, not obeyed. Per item:

        - with ``expected_versions`` (what the app sends): refused if its verdict changed since that
          version, by anyone, an undo included;
        - with ``expected`` (the verdict seen, ``None`` for unreviewed): refused if it differs;
        - without either (the command line, a script): refused if someone else gave it a decided
          verdict (background, object, wrong box), unless ``override``. A skip is no decision.

        With ``place`` (label once: ``place(frame_index, box) -> ({frame: box}, frames that show
        it)``), an 'object' label is the object in every frame that shows it (labels of origin
        'review' sharing its instance id, never where another label overlaps the box), and a
        later different verdict deletes them with it.

        With ``one_object`` the items are one place of the queue (``world.group_by_place``: one
        object mined in several frames): an 'object' verdict labels it as one object, each item
        taking the object's label in its frame where the first item's placement put one.

        Raises:
            EditConflictError: naming every refused item (also in its ``conflicts``); then nothing
                at all is written.

        Returns:
            The edit id.
        """
        if verdict not in VERDICTS:
            raise SessionError(f"unknown verdict {verdict!r}; choose from {', '.join(VERDICTS)}")
        if verdict == "object":
            if class_name is None:
                raise SessionError("an 'object' verdict needs a class")
            self._check_class(class_name)
        elif class_name is not None:
            raise SessionError(f"a {verdict!r} verdict takes no class")
        ids = list(dict.fromkeys(int(i) for i in negative_ids))
        if not ids:
            raise SessionError("no mined negatives to review")
        expected_versions = expected_versions or {}
        with self._write() as db:
            changes, conflicts = [], []
            object_id = None  # one_object: the instance the first 'object' item labelled
            for negative_id in ids:
                # Labels this call changed already (a place's shared label, deleted or restored by
                # an earlier item of it): not someone else's edit, and not to change twice.
                touched = {c["key"] for c in changes if c["table"] == "labels"}
                item = db.execute("SELECT * FROM mined_negatives WHERE id = ?", (negative_id,)).fetchone()
                if item is None:
                    raise SessionError(f"no mined negative {negative_id}")
                item = _row("mined_negatives", item)
                row = db.execute("SELECT * FROM reviews WHERE negative_id = ?", (negative_id,)).fetchone()
                row = None if row is None else _row("reviews", row)
                current = self._content(db, "reviews", negative_id)
                if negative_id in expected_versions:
                    stale = item["review_version"] != expected_versions[negative_id]
                elif expected is not None and negative_id in expected:
                    stale = (row["verdict"] if row else None) != expected[negative_id]
                else:
                    stale = False
                    if row is not None and row["author"] != author and row["verdict"] in DECIDED:
                        if not override and (row["verdict"], row["class_name"]) != (verdict, class_name):
                            given = f"{_verdict_text(row['verdict'], row['class_name'])} by {row['author']}"
                            reason = f"mined negative {negative_id} already has the verdict {given}"
                            conflicts.append({"id": negative_id, "reason": reason})
                            continue
                if stale:
                    given = "no verdict" if row is None else _verdict_text(row["verdict"], row["class_name"])
                    by = "" if row is None else f" by {row['author']}"
                    reason = f"mined negative {negative_id} was given {given}{by} since you loaded it"
                    conflicts.append({"id": negative_id, "reason": reason})
                    continue
                label_id = current["label_id"] if current else None
                label = None if label_id is None else self._content(db, "labels", label_id)
                if label is not None and label_id not in touched:
                    made = {
                        "class_name": current["class_name"],
                        "deleted": 0 if current["verdict"] == "object" else 1,
                    }
                    if {k: label[k] for k in made} != made:
                        reason = (
                            f"label {label_id}, made by the verdict on mined negative {negative_id}, was"
                            " edited since; change or delete it in the Labels panel"
                        )
                        conflicts.append({"id": negative_id, "reason": reason})
                        continue
                if row is not None and (row["verdict"], row["class_name"]) == (verdict, class_name):
                    continue  # already so: nothing to change, nothing for anyone's undo to trip on
                if label is not None and label_id in touched:
                    pass  # an earlier item of the same place brought its shared label where it belongs
                elif label is not None:
                    wanted = {**label, "deleted": 0 if verdict == "object" else 1}
                    if verdict == "object":
                        wanted["class_name"] = class_name
                    if wanted != label:
                        changes.append(self._change(db, "labels", label_id, wanted, author))
                    if verdict != "object":
                        changes += self._delete_review_siblings(db, label_id, author)
                elif verdict == "object":
                    self._import_frame(db, self._check_frame(item["frame_index"]))
                    there = None
                    if one_object and object_id is not None:
                        there = self._object_label_in(db, object_id, item["frame_index"])
                    if there is not None:  # the place's object is labelled in this frame already
                        label_id = int(there["id"])
                    else:
                        label_id, change = self._insert_label(
                            db, item["frame_index"], item["box"], class_name, "review", author,
                            where=f"mined negative {negative_id}",
                        )  # fmt: skip
                        changes.append(change)
                        if one_object and object_id is not None:
                            db.execute(
                                "UPDATE labels SET instance_id = ? WHERE id = ?", (object_id, label_id)
                            )
                # (the place's first object item places it; the later ones link or join it)
                if verdict == "object" and place is not None and object_id is None:
                    changes += self._place_review_label(db, label_id, class_name, place, author)
                if verdict == "object" and one_object and object_id is None and label_id is not None:
                    object_id = self._object_id(db, label_id)
                after = {"verdict": verdict, "class_name": class_name, "label_id": label_id}
                changes.append(self._change(db, "reviews", negative_id, after, author))
            if conflicts:
                # Raised inside the transaction: what the loop wrote for the other items is rolled back.
                shown = "; ".join(c["reason"] for c in conflicts[:5])
                more = f"; and {len(conflicts) - 5} more" if len(conflicts) > 5 else ""
                hint = (
                    " (pass --override to replace another reviewer's verdict)"
                    if any("already has" in c["reason"] for c in conflicts)
                    else "; reload and try again"
                )
                raise EditConflictError(
                    f"{len(conflicts)} of {len(ids)} item(s) refused, nothing written: {shown}{more}{hint}",
                    conflicts,
                )
            what = _verdict_text(verdict, class_name)
            return self._edit(db, author, "review", f"review {len(ids)} mined negative(s) as {what}", changes)

    def _place_review_label(
        self, db, label_id: int, class_name: str, place: Callable, author: str
    ) -> list[dict]:
        """Label once for an 'object' verdict: the label's object added to the frames ``place``
        says show it and that have no label of it (nor one overlapping it); the changes."""
        instance_id = self._object_id(db, label_id)
        row = db.execute("SELECT * FROM labels WHERE id = ?", (label_id,)).fetchone()
        boxes, show_in = place(row["frame_index"], tuple(json.loads(row["box"])))
        wanted = {self._check_frame(f): _box_json(boxes[f], f"box of frame {f}") for f in show_in}
        return self._add_to_frames(db, instance_id, wanted, set(wanted), class_name, "review", author)

    def _add_to_frames(
        self, db, instance_id: int, boxes: dict, frames: set, class_name: str, origin: str, author: str
    ) -> list[dict]:
        """Label once: object ``instance_id`` added to each of ``frames`` (box JSON from ``boxes``)
        that has no live label of it nor another label overlapping the box (``_overlapped``); the
        frames are imported first, so that the data set's labels there count. Returns the changes."""
        for frame_index in sorted(frames):
            self._import_frame(db, frame_index)
        labelled = {
            r[0]
            for r in db.execute(
                "SELECT frame_index FROM labels WHERE instance_id = ? AND deleted = 0", (instance_id,)
            )
        }
        items = [
            (f, boxes[f], class_name)
            for f in sorted(set(frames) - labelled)
            if not self._overlapped(db, f, boxes[f], instance_id)
        ]
        return self._insert_labels(db, items, origin, author, instance_id)[1] if items else []

    def _delete_review_siblings(self, db, label_id: int, author: str) -> list[dict]:
        """The other live labels of a verdict's label's object, deleted (the verdict is no longer
        'object', so the object it made is none); the changes. Those a person moved since are
        theirs (origin 'user') but still the verdict's object, as the verdict's own label is; a
        data set's or an imported label never joins a verdict's object."""
        row = db.execute("SELECT instance_id FROM labels WHERE id = ?", (label_id,)).fetchone()
        if row is None or row["instance_id"] is None:
            return []
        siblings = db.execute(
            "SELECT id FROM labels WHERE instance_id = ? AND id != ? AND deleted = 0"
            " AND origin NOT IN ('dataset', 'import')",
            (row["instance_id"], label_id),
        ).fetchall()
        changes = []
        for sibling in siblings:
            after = {**self._content(db, "labels", int(sibling["id"])), "deleted": 1}
            changes.append(self._change(db, "labels", int(sibling["id"]), after, author))
        return changes

    def mined_patch_sets(
        self,
        below_score: float | None = None,
        at_least_score: float | None = None,
        undecided_only: bool = False,
    ) -> dict[int, list[tuple[int, ...]]]:
        """Point sets of every negative mined in the session (all runs), by frame: the background
        a next round starts from. Not the false positives queued for review alone
        (``LoopSettings.review_extra``): a verdict decides those (``reviewed_patch_sets``).

        Args:
            below_score, at_least_score: only those the model scored below / at least this when
                it mined them (``LoopSettings.hold_confident``: confident ones are held).
            undecided_only: only those without a verdict other than skip.
        """
        out: dict[int, dict[tuple[int, ...], None]] = {}
        for row in self._mined_rows("patch_set", below_score, at_least_score, undecided_only):
            out.setdefault(row["frame_index"], {})[tuple(row["patch_set"])] = None  # distinct, in order
        return {frame: list(sets) for frame, sets in out.items()}

    def _mined_rows(
        self,
        column: str,
        below_score: float | None = None,
        at_least_score: float | None = None,
        undecided_only: bool = False,
    ) -> list[dict]:
        """Every mined negative's id, frame index and ``column`` (checked, ``_row``), in the order
        they were mined, filtered as ``mined_patch_sets`` says."""
        query = f"SELECT id, frame_index, {column} FROM mined_negatives m WHERE 1"
        if self.schema_version > 3:  # (before, every row was a mined negative)
            query += " AND in_background = 1"
        values: list = []
        if below_score is not None:
            query, values = query + " AND score < ?", [*values, float(below_score)]
        if at_least_score is not None:
            query, values = query + " AND score >= ?", [*values, float(at_least_score)]
        if undecided_only:
            # Decided when this row, or a row of the same point set mined by another run, has a
            # verdict: a set mined twice is one thing to decide.
            query += (
                " AND NOT EXISTS (SELECT 1 FROM reviews r JOIN mined_negatives o ON o.id = r.negative_id"
                " WHERE o.frame_index = m.frame_index AND o.patch_set = m.patch_set AND r.verdict != 'skip')"
            )
        with self._read() as db:
            return [_row("mined_negatives", r) for r in db.execute(query + " ORDER BY id", values)]

    def held_places(
        self,
        at_least_score: float,
        max_label_iou: float = HIDE_LABELLED_IOU,
        below_score: float | None = None,
    ) -> dict:
        """Boxes of the mined negatives held until reviewed (``LoopSettings.hold_places``), by
        frame: those the model scored at least ``at_least_score`` (and below ``below_score``,
        where the pseudo-labels start: ``pseudo_labels``) when it mined them, with no verdict
        other than skip, and off every current label (box IoU below ``max_label_iou``: a held
        box on a labelled object is a part or a loose box of it, a negative like any other).

        Returns:
            Frame index -> (K, 7) boxes; frames without any are left out.
        """
        import numpy as np

        out: dict[int, list] = {}
        for item in self._mined_off_labels("box", at_least_score, max_label_iou, below_score):
            out.setdefault(item["frame_index"], []).append(item["box"])
        return {frame: np.asarray(boxes, np.float64).reshape(-1, 7) for frame, boxes in out.items()}

    def pseudo_labels(self, at_least_score: float, max_label_iou: float = HIDE_LABELLED_IOU) -> dict:
        """The mined negatives that teach their predicted class until reviewed
        (``LoopSettings.pseudo_label_confident``), by frame: those the model scored at least
        ``at_least_score`` when it mined them, with no verdict other than skip (on any row of
        their point set), and off every current label (box IoU below ``max_label_iou``, as
        ``held_places``); one per point set, and none that overlaps a more confident one at
        ``max_label_iou`` or more (another set of the same object).

        Returns:
            Frame index -> ``(patch_sets, boxes, class_ids)``, most confident first: K point
            sets (each a tuple of patch ids), (K, 7) boxes and (K,) predicted class ids; frames
            without any are left out.
        """
        import numpy as np

        items = self._mined_off_labels(
            "box, patch_set, predicted_class, score", at_least_score, max_label_iou
        )
        names = list(self.class_names)
        out: dict[int, list[dict]] = {}
        # Most confident first; a set mined again by a later run, or another set on the same
        # object (IoU ``max_label_iou`` or more with a pseudo-label kept), is one label, not two.
        for item in sorted(items, key=lambda m: -float(m["score"])):
            if item["predicted_class"] not in names:  # (a class the session no longer has teaches nothing)
                continue
            kept = out.setdefault(item["frame_index"], [])
            if any(tuple(k["patch_set"]) == tuple(item["patch_set"]) for k in kept):
                continue
            if kept and on_labelled_object(
                float(box_iou_3d(np.asarray([item["box"]]), np.asarray([k["box"] for k in kept])).max()),
                max_label_iou,
            ):
                continue
            kept.append(item)
        out = {frame: rows for frame, rows in out.items() if rows}
        return {
            frame: (
                [tuple(item["patch_set"]) for item in rows],
                np.asarray([item["box"] for item in rows], np.float64).reshape(-1, 7),
                np.asarray([names.index(item["predicted_class"]) for item in rows], np.int64),
            )
            for frame, rows in out.items()
        }

    def _mined_off_labels(
        self,
        columns: str,
        at_least_score: float,
        max_label_iou: float,
        below_score: float | None = None,
    ) -> list[dict]:
        """The undecided mined negatives scored at least ``at_least_score`` (and below
        ``below_score``) whose box is off every current label (``on_labelled_object``)."""
        items = self._mined_rows(columns, below_score, at_least_score, undecided_only=True)
        overlaps = self.label_overlap(items)
        return [
            item for item, overlap in zip(items, overlaps) if not on_labelled_object(overlap, max_label_iou)
        ]

    def rejected_boxes(self, frame_indices) -> dict:
        """Per frame, the boxes where a person said there is no object to label: mined negatives
        answered Background, and labels deleted (what a carried pseudo-label stays off,
        ``training.loop.session_pseudo_labels``).

        Returns:
            Frame index -> (K, 7) boxes, for each of ``frame_indices`` (none: (0, 7)).
        """
        import numpy as np

        frames = sorted({self._check_frame(i) for i in frame_indices})
        out: dict[int, list] = {f: [] for f in frames}
        with self._read() as db:
            rows = db.execute(
                "SELECT m.frame_index, m.box FROM reviews r JOIN mined_negatives m ON m.id = r.negative_id"
                " WHERE r.verdict = 'background' AND m.frame_index IN (SELECT value FROM json_each(?))",
                (json.dumps(frames),),
            ).fetchall()
        for row in rows:
            item = _row("mined_negatives", row)
            out[item["frame_index"]].append(item["box"])
        for f, labels in self._stored_labels(frames, include_deleted=True).items():
            out[f].extend(label.box for label in labels if label.deleted)
        return {f: np.asarray(boxes, np.float64).reshape(-1, 7) for f, boxes in out.items()}

    def reviewed_patch_sets(self) -> dict[str, dict[int, list[tuple[int, ...]]]]:
        """Point sets of every reviewed negative by verdict and frame: what the next training run
        must treat as background ('background'), and must not mine again (all decided ones)."""
        out: dict[str, dict[int, list[tuple[int, ...]]]] = {v: {} for v in DECIDED}
        with self._read() as db:
            rows = db.execute(
                "SELECT m.id, m.frame_index, m.patch_set, r.verdict FROM reviews r"
                " JOIN mined_negatives m ON m.id = r.negative_id WHERE r.verdict != 'skip'"
            ).fetchall()
        for row in rows:
            item = _row("mined_negatives", row)
            verdict = _row("reviews", {"negative_id": item["id"], "verdict": item["verdict"]})["verdict"]
            out[verdict].setdefault(item["frame_index"], []).append(tuple(item["patch_set"]))
        return out


# --- Module-level helpers over a session's database -----------------------------------------------


def rounds_record(run) -> list[dict]:
    """Per round of a training run: sizes, times and the training-frame F-score (no mined lists)."""
    return [
        {
            "round": r["round"],
            "num_positives": r["num_positives"],
            "num_background": r["num_background"],
            "fit_seconds": r["fit_seconds"],
            "score_seconds": r.get("score_seconds"),
            "box_quality_seconds": r.get("box_quality_seconds"),
            "box_quality_wait_seconds": r.get("box_quality_wait_seconds"),
            # (the threshold fold models' fits, in the last round: not part of its scoring)
            "folds_fit_seconds": (r.get("threshold_folds") or {}).get("fit_seconds"),
            "box_quality": r.get("box_quality"),
            "epochs": r.get("epochs"),
            "continued": r.get("continued"),
            "recalibrated": r.get("recalibrated"),
            "num_mined": len(r["mined"]),
            "num_queued": len(r.get("queued", [])),
            "train_f1": r["train_metrics"]["f1"],
        }
        for r in run.rounds
    ]


def save_training_run(session: Session, run, data: str, config: dict, dataset=None, **kwargs) -> int:
    """``SessionDB(session, dataset).save_training_run(...)``."""
    return SessionDB(session, dataset).save_training_run(run, data, config, **kwargs)


def training_runs(session: Session) -> list[dict]:
    """Every training run of the session with its rounds, oldest first."""
    if not session.db_path.is_file():
        return []
    return SessionDB(session, readonly=True).training_runs()


def latest_model(session: Session) -> Path | None:
    """The final checkpoint of the session's last training run, if any."""
    runs = training_runs(session)
    return session.path / runs[-1]["model_path"] if runs else None


def mined_negatives(
    session: Session, run_id: int | None = None, frame_index: int | None = None
) -> list[dict]:
    """The review queue of a run (the last by default), in its queue order (``SessionDB.review_queue``)."""
    if not session.db_path.is_file():
        return []
    return SessionDB(session, readonly=True).review_queue(run_id, frame_index=frame_index)


def session_data(session: Session) -> Path | None:
    """The data set a session labels: its own ``data/`` folder, else the one its database
    recorded when it was made on a data set outside its folder; ``None`` when it has neither."""
    if session.has_data:
        return session.data_dir
    if session.db_path.is_file():
        recorded = SessionDB(session, readonly=True).meta().get("data")
        return None if recorded is None else Path(recorded)
    return None


def open_session_data(
    name: str,
    root: str | os.PathLike | None = None,
    data: str | os.PathLike | None = None,
    *,
    readonly: bool = False,
) -> tuple[SessionDB, Dataset]:
    """A session's database and the data set it labels: ``data`` if given, else
    ``session_data``'s. What ``factorydet train``, ``review``, ``labels`` and the app open.

    Args:
        readonly: open it read-only (``queue``, ``labels export``), if it exists; a session without
            a database yet is created as usual, since there is nothing to read without writing.

    Raises:
        SessionError: when the session has no data set and ``data`` is not given.
    """
    session = open_session(name, root)
    data = data if data is not None else session_data(session)
    if data is None:
        raise SessionError(f"session {name!r} has no data set; pass --data DIR or FILE")
    dataset = open_dataset(data)
    return SessionDB(session, dataset, readonly=readonly and session.db_path.is_file()), dataset
