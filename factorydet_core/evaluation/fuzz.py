"""A fuzzing campaign: mutated files through every reader, label importer, checkpoint loader and
the session database, each case in a guarded child process.

A case takes a small valid file of one *target* (a point-cloud format, a label format, one of a
checkpoint's three files, a session database), mutates it (bytes: truncation, flipped bytes, a
word set to an extreme value, a chunk cut or repeated; or structure: a JSON field, an array, a
tensor, a token, a table row set to something hostile) and hands it to the entry point a user's
command would call. Its outcome is one of ``OUTCOMES``:

- ``ok``: a valid result; ``input_error``: a one-line ``InputError`` (the wanted refusal);
- ``traceback``: any other exception, or an ``InputError`` spanning lines;
- ``signal``: the child died (SIGSEGV, an abort); ``timeout``: no answer within the case's time;
- ``memory``: the case used more than ``memory_limit_mb`` over the worker's start-up size.

The last four are failures. Memory is measured from outside, so that a reader that catches a
``MemoryError`` and reports it as bad input cannot hide a bomb: a watchdog thread in the parent
reads the worker's resident size every ``WATCHDOG_INTERVAL_S`` and kills it above the limit; the
worker's peak resident size (VmHWM, reset per case) is checked after each case; and an
``InputError`` (or any exception) that mentions or stems from a ``MemoryError`` counts as
``memory``. The worker's address space is capped too, but only as a guard of the machine, at
``ADDRESS_SPACE_FACTOR`` times the limit over its start-up size.

Cases run one after another in a worker process started with ``spawn``; a worker that dies, hangs
or is killed is replaced and the next case goes on. The campaign is deterministic for a seed.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import re
import shutil
import signal
import sqlite3
import statistics
import tempfile
import threading
import time
import traceback
import zipfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.types import InputError

OUTCOMES = ("ok", "input_error", "traceback", "signal", "memory", "timeout")
FAILURES = ("traceback", "signal", "memory", "timeout")

WATCHDOG_INTERVAL_S = 0.02
"""How often the parent reads a running case's resident size."""

ADDRESS_SPACE_FACTOR = 4
"""The worker's address space is capped at start-up + this x ``memory_limit_mb``: a guard of the
machine, not the measurement (a capped allocation raises a ``MemoryError`` the case may catch)."""

WORKER_START_S = 300.0
"""How long a new worker may take to import everything before its first case."""

CLOUD_TARGETS = (
    "ply",
    "ply-ascii",
    "pcd",
    "pcd-ascii",
    "txt",
    "csv",
    "pts",
    "las",
    "laz",
    "bin",
    "npy",
    "npz",
)
LABEL_TARGETS = ("labels-json", "labels-kitti", "labels-npz")
CHECKPOINT_TARGETS = ("checkpoint-pt", "checkpoint-note", "checkpoint-boxq")
SESSION_TARGETS = ("session-db",)
TARGETS = CLOUD_TARGETS + LABEL_TARGETS + CHECKPOINT_TARGETS + SESSION_TARGETS

_TEXT_TARGETS = {
    "ply-ascii",
    "pcd-ascii",
    "txt",
    "csv",
    "pts",
    "labels-json",
    "labels-kitti",
    "checkpoint-note",
}
_NPZ_TARGETS = {"npz", "labels-npz", "checkpoint-boxq"}
_JSON_TARGETS = {"labels-json", "checkpoint-note"}

EXTREME_NUMBERS = (
    "0", "-1", "1e308", "-1e308", "1e-320", "nan", "inf", "-inf", "1e20", "2147483648",
    "99999999999999999999999", "1.7", "-0", "",
)  # fmt: skip
"""Tokens a text mutation puts in place of a number."""

EXTREME_WORDS = (
    b"\x00" * 8, b"\xff" * 8, b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80", b"\xff\xff\xff\xff\xff\xff\xff\x7f",
    np.float32(np.nan).tobytes(), np.float64(1e300).tobytes(), np.float32(-1.0).tobytes(),
    np.int64(10**12).tobytes(), np.int32(-1).tobytes(),
)  # fmt: skip
"""Byte patterns a word mutation writes over a file (counts, sizes and offsets at their extremes)."""


@dataclasses.dataclass(frozen=True)
class FuzzCase:
    """One mutated input: its target, what was done to it and the file to hand over."""

    index: int
    target: str
    mutation: str
    path: str


@dataclasses.dataclass(frozen=True)
class CaseResult:
    case: FuzzCase
    outcome: str
    detail: str
    peak_mb: float
    seconds: float


# -- seed files


def _seed_frame():
    """A small frame with a few labelled boxes (300 points; coordinates and intensities)."""
    from factorydet_core.types import BoxLabels, Frame  # noqa: F401 - documents what read_frame returns

    rng = np.random.default_rng(0)
    points = rng.uniform([-5, -5, 0], [5, 5, 2], (300, 3))
    return {
        "points": points,
        "intensity": rng.uniform(0, 1, 300).astype(np.float32),
        "colors": rng.integers(0, 256, (300, 3), dtype=np.uint8),
        "boxes": np.array([[1.0, 2.0, 0.5, 1.2, 0.8, 1.0, 0.3], [-2.0, 0.0, 0.4, 0.5, 0.5, 0.8, 0.0]]),
        "labels": np.array(["box", "barrel"]),
    }


def _write_cloud_seeds(folder: Path) -> dict[str, Path]:
    from factorydet_core.io.npz import save_npz
    from factorydet_core.io.readers import read_frame, write_frame

    scene = _seed_frame()
    base = folder / "scene.npz"
    save_npz(base, scene)
    frame = read_frame(base)
    seeds = {}
    for target, suffix in (
        ("ply", ".ply"), ("pcd", ".pcd"), ("txt", ".txt"), ("csv", ".csv"), ("pts", ".pts"), ("las", ".las"),
        ("laz", ".laz"), ("bin", ".bin"), ("npy", ".npy"), ("npz", ".npz"),
    ):  # fmt: skip
        path = folder / f"seed_{target}{suffix}"
        write_frame(path, frame)
        seeds[target] = path
    points = scene["points"][:50]
    ply = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x", "property float y",
           "property float z", "end_header"] + [f"{x:.4f} {y:.4f} {z:.4f}" for x, y, z in points]  # fmt: skip
    seeds["ply-ascii"] = folder / "seed_ascii.ply"
    seeds["ply-ascii"].write_text("\n".join(ply) + "\n")
    pcd = ["# .PCD v0.7", "VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1",
           f"WIDTH {len(points)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(points)}",
           "DATA ascii"] + [f"{x:.4f} {y:.4f} {z:.4f}" for x, y, z in points]  # fmt: skip
    seeds["pcd-ascii"] = folder / "seed_ascii.pcd"
    seeds["pcd-ascii"].write_text("\n".join(pcd) + "\n")
    return seeds


def _write_session_seeds(folder: Path) -> tuple[dict[str, Path], Path, Path]:
    """Label files exported from a pristine two-frame session, the session's root and its data set,
    and (``session-db``) the database of a second session that has every kind of row: labels, a
    few edits (add, update, delete), a training run with a queue of mined negatives and verdicts."""
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.session.labels_io import export_labels
    from factorydet_core.session.store import SessionDB, open_session
    from factorydet_core.sim.simulate import SimConfig, simulate_dataset

    data = simulate_dataset(folder / "data", SimConfig(num_frames=2, seed=3, points_per_frame=4000))
    root = folder / "sessions"
    db = SessionDB(open_session("pristine", root), open_dataset(data))
    db.ensure_frames([0, 1])
    seeds = {}
    for target, fmt, out in (
        ("labels-json", "json", folder / "labels.json"),
        ("labels-kitti", "kitti", folder / "kitti"),
        ("labels-npz", "npz", folder / "npz"),
    ):
        written = export_labels(db, fmt, out)
        seeds[target] = out if fmt == "json" else written[0]
    seeds["session-db"] = _worked_session(SessionDB(open_session("worked", root), open_dataset(data)), data)
    return seeds, root, data


SEED_AUTHOR = "fuzz"
"""Who made the seed session's edits and verdicts (the session-db runner undoes the last one)."""


def _worked_session(db, data: Path) -> Path:
    """Fill ``db`` (a ``SessionDB`` on the two-frame data set) with edits, a mined-negative queue
    and verdicts, without training; returns its database file."""
    from factorydet_core.detection.model import DEFAULT_MODEL, DetectionModel
    from factorydet_core.training.mining import TrainingRun

    db.ensure_frames([0, 1])
    name = db.class_names[0]
    added = db.add_label(0, [0.5, 0.5, 0.5, 1.0, 1.0, 1.0, 0.0], name, SEED_AUTHOR)
    db.update_label(added.id, SEED_AUTHOR, box=[0.6, 0.5, 0.5, 1.0, 1.2, 1.0, 0.2])
    spare = db.add_label(1, [2.0, 1.0, 0.5, 0.8, 0.8, 1.0, 0.0], name, SEED_AUTHOR)
    db.delete_labels([spare.id], SEED_AUTHOR)

    # A training run as train_with_mining records one (one round, a few mined negatives); its
    # model is the shipped one, since only the queue's rows are exercised.
    def mined(frame_index: int, group: int, box: list[float], score: float) -> dict:
        return {
            "frame_index": frame_index,
            "group": group,
            "proposal": group,
            "box": box,
            "patch_set": [group],
            "score": score,
            "predicted_class": name,
            "probabilities": [score, 1.0 - score],
            "best_annotated_iou": 0.0,
        }

    items = [
        mined(0, 3, [1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9),
        mined(0, 7, [-2.0, 1.0, 0.4, 0.6, 0.6, 0.8, 0.3], 0.7),
        mined(1, 2, [3.0, -1.0, 0.5, 1.2, 0.8, 1.0, 1.0], 0.6),
        mined(1, 5, [0.0, 0.0, 0.3, 0.4, 0.4, 0.6, 0.0], 0.4),
    ]
    model = DetectionModel.load(DEFAULT_MODEL)
    record = {"round": 0, "num_positives": 5, "num_background": 9, "fit_seconds": 1.0}
    rounds = [{**record, "train_metrics": {"f1": 0.5}, "mined": items}]
    run_id = db.save_training_run(TrainingRun(model, rounds, [model], [0]), str(data), {"seed": "fuzz"})
    queue = db.review_queue(run_id)
    db.review([queue[0]["id"]], "background", SEED_AUTHOR)
    db.review([queue[1]["id"]], "object", SEED_AUTHOR, class_name=name)
    return db.path


def _write_checkpoint_seeds(folder: Path, model: Path) -> dict[str, Path]:
    """The model's three files copied into ``folder``; each checkpoint target mutates one of them."""
    from factorydet_core.detection.model import quality_path

    files = {"checkpoint-pt": model, "checkpoint-note": model.with_suffix(".json"),
             "checkpoint-boxq": quality_path(model)}  # fmt: skip
    missing = [str(p) for p in files.values() if not p.is_file()]
    if missing:
        raise InputError(
            f"fuzz: the checkpoint {model} lacks {', '.join(missing)} (needs a box quality model)"
        )
    seeds = {}
    for target, path in files.items():
        copy = folder / "checkpoint" / path.name
        copy.parent.mkdir(exist_ok=True)
        shutil.copy2(path, copy)
        seeds[target] = copy
    return seeds


# -- mutations


def _mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    if not data:
        return b"\x00", "empty->byte"

    # Headers decide allocations: half the offsets fall in the first 512 bytes.
    def offset() -> int:
        span = min(len(data), 512) if rng.random() < 0.5 else len(data)
        return int(rng.integers(0, span))

    kind = rng.choice(
        ["truncate", "flip", "word", "cut", "repeat", "empty"], p=[0.2, 0.3, 0.3, 0.08, 0.08, 0.04]
    )
    if kind == "truncate":
        at = int(rng.integers(0, len(data)))
        return data[:at], f"truncate@{at}"
    if kind == "flip":
        out = bytearray(data)
        spots = [offset() for _ in range(int(rng.integers(1, 9)))]
        for spot in spots:
            out[spot] = int(rng.integers(0, 256))
        return bytes(out), f"flip{spots}"
    if kind == "word":
        word = EXTREME_WORDS[int(rng.integers(len(EXTREME_WORDS)))]
        at = offset()
        out = data[:at] + word + data[at + len(word) :]
        return out[: max(len(data), at + len(word))], f"word{word.hex()}@{at}"
    if kind in ("cut", "repeat"):
        start = offset()
        stop = min(len(data), start + int(rng.integers(1, 4097)))
        chunk = data[start:stop]
        out = (
            data[:start] + data[stop:]
            if kind == "cut"
            else data[:stop] + chunk * int(rng.integers(1, 50)) + data[stop:]
        )
        return out, f"{kind}[{start}:{stop}]"
    return b"", "empty"


_NUMBER = re.compile(rb"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _mutate_text(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    kind = rng.choice(
        ["number", "bad-utf8", "drop-line", "repeat-line", "nesting"], p=[0.6, 0.1, 0.1, 0.1, 0.1]
    )
    lines = data.split(b"\n")
    if kind == "number":
        matches = list(_NUMBER.finditer(data))
        if matches:
            picks = sorted(
                {int(i) for i in rng.integers(0, len(matches), int(rng.integers(1, 4)))}, reverse=True
            )
            out, changed = data, []
            for pick in picks:  # from the end, so earlier offsets stay valid
                match = matches[pick]
                token = EXTREME_NUMBERS[int(rng.integers(len(EXTREME_NUMBERS)))].encode()
                out = out[: match.start()] + token + out[match.end() :]
                changed.append(f"{match.group().decode()}->{token.decode()}@{match.start()}")
            return out, "number " + ",".join(changed)
    if kind == "bad-utf8":
        at = int(rng.integers(0, len(data) + 1))
        return data[:at] + b"\xff\xfe\xc3(" + data[at:], f"bad-utf8@{at}"
    if kind in ("drop-line", "repeat-line") and len(lines) > 1:
        at = int(rng.integers(len(lines)))
        if kind == "drop-line":
            return b"\n".join(lines[:at] + lines[at + 1 :]), f"drop-line{at}"
        return b"\n".join(
            lines[: at + 1] + [lines[at]] * int(rng.integers(1, 1000)) + lines[at + 1 :]
        ), f"repeat-line{at}"
    depth = int(rng.choice([100, 10_000, 200_000]))
    at = int(rng.integers(0, len(data) + 1))
    return data[:at] + b"[" * depth + b"]" * depth + data[at:], f"nesting{depth}@{at}"


_HOSTILE_VALUES: tuple = (None, -1, 0, 10**12, 2**63, 1e308, -1e308, "x", "", [], {}, True, [1, 2], {"a": 1})


def _json_paths(value, path=()) -> Iterator[tuple]:
    yield path
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _json_paths(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value[:20]):
            yield from _json_paths(item, (*path, index))


def _mutate_json(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    try:
        record = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return _mutate_bytes(data, rng)
    paths = [p for p in _json_paths(record) if p]
    if not paths:
        return _mutate_bytes(data, rng)
    changed = []
    for _ in range(int(rng.integers(1, 3))):
        path = paths[int(rng.integers(len(paths)))]
        parent = record
        try:
            for key in path[:-1]:
                parent = parent[key]
            if rng.random() < 0.15:
                del parent[path[-1]]
                changed.append(f"{'/'.join(map(str, path))} deleted")
                continue
            value = _HOSTILE_VALUES[int(rng.integers(len(_HOSTILE_VALUES)))]
            parent[path[-1]] = value
            changed.append(f"{'/'.join(map(str, path))}={json.dumps(value)}")
        except (KeyError, IndexError, TypeError):
            continue
    return json.dumps(record).encode(), "json " + ",".join(changed)


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def _mutate_npz(path: Path, rng: np.random.Generator) -> str:
    """Rewrite the npz at ``path`` with one member made hostile; returns what was done."""
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    name = sorted(arrays)[int(rng.integers(len(arrays)))]
    array = arrays[name]
    kind = rng.choice(
        ["drop", "empty", "shape", "dtype", "values", "object", "claimed-shape", "bomb"],
        p=[0.12, 0.12, 0.16, 0.14, 0.2, 0.08, 0.1, 0.08],
    )
    members: dict[str, bytes] = {k: _npy_bytes(v) for k, v in arrays.items()}
    if kind == "drop":
        del members[name]
    elif kind == "empty":
        members[name] = _npy_bytes(np.zeros((0,) * max(array.ndim, 1), array.dtype))
    elif kind == "shape":
        flat = array.reshape(-1)
        options = [flat, flat.reshape(1, -1), array[..., None], array.T, flat[:1], flat[:0]]
        members[name] = _npy_bytes(np.ascontiguousarray(options[int(rng.integers(len(options)))]))
    elif kind == "dtype":
        dtype = [np.int8, np.float16, np.bool_, np.uint64, "<U3", np.complex64][int(rng.integers(6))]
        try:
            members[name] = _npy_bytes(array.astype(dtype))
        except (ValueError, TypeError):
            members[name] = _npy_bytes(np.zeros(array.shape, dtype))
    elif kind == "values":
        value = [np.nan, np.inf, -1, 1e300, 2**62, -(2**31)][int(rng.integers(6))]
        changed = np.array(array, copy=True)
        if changed.size and changed.dtype.kind in "iuf":
            flat = changed.reshape(-1)
            spots = rng.integers(0, flat.size, int(rng.integers(1, 5)))
            with np.errstate(all="ignore"):  # wrapping into the array's own dtype is the point
                flat[spots] = np.array(value, np.float64).astype(changed.dtype)
        members[name] = _npy_bytes(changed)
    elif kind == "object":
        members[name] = _npy_bytes(np.array([{"a": 1}, None], dtype=object))
    elif kind == "claimed-shape":
        # A header claiming 10**10 rows over a few bytes of data: a loader that trusts it allocates.
        header = {"descr": "<f8", "fortran_order": False, "shape": (10**10, 3)}
        buffer = __import__("io").BytesIO()
        np.lib.format.write_array_header_1_0(buffer, header)
        members[name] = buffer.getvalue() + b"\x00" * 64
    else:  # a deflate bomb: 2.5 GB of zeros in a few MB
        members = {k: v for k, v in members.items() if k != name}
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
            for key, payload in members.items():
                archive.writestr(f"{key}.npy", payload)
            header = {"descr": "<f8", "fortran_order": False, "shape": (2_500_000_000 // 24, 3)}
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                buffer = __import__("io").BytesIO()
                np.lib.format.write_array_header_1_0(buffer, header)
                member.write(buffer.getvalue())
                zeros = bytes(1 << 24)
                for _ in range(2_500_000_000 // len(zeros)):
                    member.write(zeros)
        return f"npz {name}: bomb"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, payload in members.items():
            archive.writestr(f"{key}.npy", payload)
    return f"npz {name}: {kind}"


class _Hostile:
    """Pickled into a checkpoint: a loader that unpickles arbitrary objects would build it."""

    def __reduce__(self):
        return (print, ("a checkpoint's pickle payload ran",))


def _mutate_state_dict(path: Path, rng: np.random.Generator) -> str:
    import torch

    kind = rng.choice(
        ["tensor", "drop", "extra", "bare", "payload", "not-dict"], p=[0.55, 0.12, 0.08, 0.08, 0.09, 0.08]
    )
    if kind == "bare":
        torch.save(torch.zeros(3), path)
        return "pt: a bare tensor"
    if kind == "payload":
        torch.save({"weights": _Hostile()}, path)
        return "pt: a pickle payload"
    if kind == "not-dict":
        torch.save([1, 2, 3], path)
        return "pt: a list"
    state = torch.load(path, map_location="cpu", weights_only=True)
    names = sorted(state)
    name = names[int(rng.integers(len(names)))]
    if kind == "drop":
        del state[name]
    elif kind == "extra":
        state["extra.weight"] = torch.zeros(2)
    else:
        tensor = state[name]
        options = [
            lambda t: t.reshape(-1),
            lambda t: torch.zeros((*t.shape[:-1], t.shape[-1] + 1) if t.ndim else (2,)),
            lambda t: torch.full_like(t, float("nan")) if t.is_floating_point() else t - 10**6,
            lambda t: t.to(torch.int8),
            lambda t: torch.zeros(0),
            lambda t: torch.full_like(t, 1e30) if t.is_floating_point() else t * 0 + 2**40,
        ]
        choice = int(rng.integers(len(options)))
        state[name] = options[choice](tensor)
        kind = f"tensor {name} #{choice}"
    torch.save(state, path)
    return f"pt: {kind}"


_DB_MUTATIONS = {
    "user_version": 0.1,
    "schema": 0.1,
    "label-row": 0.2,
    "mined-row": 0.22,
    "edit-row": 0.18,
    "review-row": 0.08,
    "drop-table": 0.12,
}
"""Structured mutations of a session database and their probabilities."""

_MINED_VALUES = {
    "box": ("[1,2]", "nan", "[1e999,0,0,1,1,1,0]", "{}", "not json", "null", "[1,2,3,4,5,6,-7]"),
    "patch_set": ("[]", "not json", "[-1]", "[1e30]", "{}", "null"),
    "probabilities": ("[NaN]", "not json", "[]", "{}", "[1e999]"),
    "frame_index": ("x", -1, 10**9, 2**62),
    "score": ("x", -1e308, 1e308, "1e999"),
    "predicted_class": ("zzz", "", 42),
    "review_version": (-1, "x", 2**62),
    "in_background": (2, -1, "x"),
    "run_id": (10**6, -1, "x"),
}
"""Hostile values of the mined-negative columns (JSON columns also get ``_mutate_json``)."""


def _mutate_session_db(path: Path, rng: np.random.Generator) -> str:
    kind = rng.choice(list(_DB_MUTATIONS), p=list(_DB_MUTATIONS.values()))
    connection = sqlite3.connect(path, isolation_level=None)
    try:
        # A damaged file breaks the schema's rules too (CHECK and NOT NULL are not re-checked).
        connection.execute("PRAGMA ignore_check_constraints = ON")
        if kind == "user_version":
            value = int(rng.choice([-1, 0, 2**31 - 1, 99]))
            connection.execute(f"PRAGMA user_version = {value}")
            return f"db: user_version {value}"
        if kind == "schema":
            connection.execute("PRAGMA writable_schema = ON")
            connection.execute(
                "UPDATE sqlite_master SET sql = substr(sql, 1, 20) || ' garbage' WHERE name = 'labels'"
            )
            return "db: damaged schema text"
        if kind == "label-row":
            box = ["[1,2]", "nan", "[1e999,0,0,1,1,1,0]", "{}", "not json", "[1,2,3,4,5,6,7]"][
                int(rng.integers(6))
            ]
            column = ["box", "class_name", "frame_index"][int(rng.integers(3))]
            value = {"box": box, "class_name": "zzz", "frame_index": "x"}[column]
            connection.execute(
                f"UPDATE labels SET {column} = ? WHERE id = (SELECT min(id) FROM labels)", (value,)
            )
            return f"db: labels.{column}={value}"
        if kind == "mined-row":
            # The highest-scored item: the first of the queue, the one the runner reviews.
            ids = [r[0] for r in connection.execute("SELECT id FROM mined_negatives ORDER BY score DESC")]
            row_id = ids[int(rng.integers(len(ids)))] if ids and rng.random() < 0.5 else (ids or [0])[0]
            column = sorted(_MINED_VALUES)[int(rng.integers(len(_MINED_VALUES)))]
            options = _MINED_VALUES[column]
            value = options[int(rng.integers(len(options)))]
            if column in ("box", "patch_set", "probabilities") and rng.random() < 0.5:
                (text,) = connection.execute(
                    f"SELECT {column} FROM mined_negatives WHERE id = ?", (row_id,)
                ).fetchone() or ("[]",)
                data, _ = _mutate_json((text or "[]").encode(), rng)
                value = data.decode("utf-8", "replace")
            connection.execute(f"UPDATE mined_negatives SET {column} = ? WHERE id = ?", (value, row_id))
            return f"db: mined_negatives[{row_id}].{column}={str(value)[:60]}"
        if kind == "edit-row":
            # The latest edit: the one an undo replays.
            column = ["changes", "changes", "changes", "state", "author", "kind"][int(rng.integers(6))]
            row = connection.execute(f"SELECT id, {column} FROM edits ORDER BY id DESC LIMIT 1").fetchone()
            if row is None:
                return "db: no edit to damage"
            if column == "changes":
                value = _mutate_json(str(row[1]).encode(), rng)[0].decode("utf-8", "replace")
                if rng.random() < 0.3:
                    value = ["not json", "[]", "{}", "null", "[{}]", "[1]"][int(rng.integers(6))]
            else:
                value = {"state": "zzz", "author": 42, "kind": "zzz"}[column]
            connection.execute(f"UPDATE edits SET {column} = ? WHERE id = ?", (value, row[0]))
            return f"db: edits[{row[0]}].{column}={str(value)[:60]}"
        if kind == "review-row":
            column = ["verdict", "class_name", "label_id", "negative_id"][int(rng.integers(4))]
            value = {"verdict": "zzz", "class_name": "zzz", "label_id": 10**6, "negative_id": 10**6}[column]
            connection.execute(
                f"UPDATE reviews SET {column} = ? WHERE negative_id = (SELECT max(negative_id) FROM reviews)",
                (value,),
            )
            return f"db: reviews.{column}={value}"
        tables = ["edits", "reviews", "meta", "frames", "mined_negatives", "training_runs"]
        table = tables[int(rng.integers(len(tables)))]
        connection.execute("PRAGMA foreign_keys = OFF")
        connection.execute(f"DROP TABLE IF EXISTS {table}")
        return f"db: dropped {table}"
    finally:
        connection.close()


def make_case(index: int, target: str, seed_path: Path, folder: Path, rng: np.random.Generator) -> FuzzCase:
    """A mutated copy of ``seed_path`` (a file or, for KITTI and npz labels, its folder's file)."""
    case_dir = folder / f"case{index:05d}"
    case_dir.mkdir(parents=True)
    if target in CHECKPOINT_TARGETS:
        for sibling in seed_path.parent.iterdir():
            shutil.copy2(sibling, case_dir / sibling.name)
        path = case_dir / seed_path.name
    else:
        path = case_dir / seed_path.name
        shutil.copy2(seed_path, path)
    structured = rng.random() < 0.5
    if structured and target in _NPZ_TARGETS:
        mutation = _mutate_npz(path, rng)
    elif structured and target == "checkpoint-pt":
        mutation = _mutate_state_dict(path, rng)
    elif structured and target == "session-db":
        mutation = _mutate_session_db(path, rng)
    elif structured and target in _JSON_TARGETS and rng.random() < 0.6:
        data, mutation = _mutate_json(path.read_bytes(), rng)
        path.write_bytes(data)
    elif structured and target in _TEXT_TARGETS:
        data, mutation = _mutate_text(path.read_bytes(), rng)
        path.write_bytes(data)
    else:
        data, mutation = _mutate_bytes(path.read_bytes(), rng)
        path.write_bytes(data)
    if target in CHECKPOINT_TARGETS:
        # Every checkpoint target loads through the .pt's path; the mutated file may be a sibling.
        path = next(p for p in case_dir.iterdir() if p.suffix == ".pt")
    return FuzzCase(index, target, mutation, str(path))


# -- running a case (in the worker)


@dataclasses.dataclass(frozen=True)
class _Context:
    session_root: str
    data: str


def _status_kb(field: str, pid: int | str = "self") -> int | None:
    """A ``/proc/<pid>/status`` field in KB (``VmRSS``, ``VmHWM``, ``VmSize``); ``None`` once the
    process is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def _reset_peak() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM (Linux 4.0+)
    except OSError:
        pass


def run_target(target: str, path: Path, context: _Context) -> None:
    """Hand ``path`` to the entry point a user's command would use for ``target``."""
    if target in CLOUD_TARGETS:
        from factorydet_core.io.readers import read_frame

        read_frame(path)
    elif target in LABEL_TARGETS:
        from factorydet_core.io.dataset import open_dataset
        from factorydet_core.session.labels_io import import_labels
        from factorydet_core.session.store import SessionDB, open_session

        root = Path(tempfile.mkdtemp(prefix="fuzz_session_"))
        try:
            shutil.copytree(Path(context.session_root) / "pristine", root / "s")
            db = SessionDB(open_session("s", root), open_dataset(context.data))
            import_labels(db, path, "fuzz")
        finally:
            shutil.rmtree(root, ignore_errors=True)
    elif target in CHECKPOINT_TARGETS:
        from factorydet_core.detection.model import DetectionModel

        model = DetectionModel.load(path)
        if model.box_quality is not None:  # the compiled tree walk reads the loaded arrays
            features = np.random.default_rng(0).normal(size=(64, model.box_quality.num_features_))
            if not np.isfinite(model.box_quality.predict(features)).all():
                raise RuntimeError("box quality predicted non-finite IoUs")
    elif target in SESSION_TARGETS:
        from factorydet_core.session.store import SessionDB, open_session

        root = Path(tempfile.mkdtemp(prefix="fuzz_db_"))
        try:
            folder = root / "s"
            folder.mkdir()
            shutil.copy2(path, folder / path.name)
            db = SessionDB(open_session("s", root))
            db.labels(0)
            db.edits()
            db.training_runs()
            db.review_progress()
            queue = db.review_queue()
            # Writes, on this copy: undo the seed's last verdict, then give one.
            db.undo(SEED_AUTHOR)
            if queue:
                pending = [item for item in queue if item["verdict"] is None] or queue
                db.review([pending[0]["id"]], "background", "fuzz-runner", override=True)
                db.review_queue()
        finally:
            shutil.rmtree(root, ignore_errors=True)
    else:
        raise ValueError(f"unknown fuzz target {target!r}")


Runner = Callable[[str, Path, object], None]
"""What a case runs: ``runner(target, path, context)``; a module-level function (the worker is
spawned, so it is passed by its qualified name)."""


def _stems_from_memory_error(exc: BaseException) -> bool:
    """Whether ``exc`` is, mentions or was raised from a ``MemoryError`` (a reader that turned
    one into an ``InputError`` must not hide a bomb)."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while link is not None and id(link) not in seen:
        seen.add(id(link))
        if isinstance(link, MemoryError) or "MemoryError" in str(link):
            return True
        link = link.__cause__ or link.__context__
    return False


def _worker(connection, runner: Runner, context: object, memory_limit_mb: float) -> None:
    import resource

    # Warm every import first, so that the limit and the peak measure the case, not the start-up.
    import factorydet_core.detection.model  # noqa: F401
    import factorydet_core.io.readers  # noqa: F401
    import factorydet_core.session.labels_io  # noqa: F401

    size_kb = _status_kb("VmSize") or 0
    limit = int((size_kb + ADDRESS_SPACE_FACTOR * memory_limit_mb * 1024) * 1024)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    for inherited in (soft, hard):  # never raise a cap set from outside (ulimit -v)
        if inherited != resource.RLIM_INFINITY:
            limit = min(limit, inherited)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    rss_kb = _status_kb("VmRSS") or 0
    connection.send(("ready", rss_kb))
    while True:
        try:
            case = connection.recv()
        except EOFError:
            return
        if case is None:
            return
        _reset_peak()
        start = time.perf_counter()
        try:
            runner(case.target, Path(case.path), context)
            outcome, detail = "ok", ""
        except MemoryError as exc:
            outcome, detail = "memory", f"MemoryError: {str(exc)[:200]}"
        except InputError as exc:
            message = str(exc)
            outcome = "input_error" if "\n" not in message.strip() else "traceback"
            detail = message[:300]
            if _stems_from_memory_error(exc):
                outcome = "memory"
        except RecursionError as exc:
            outcome, detail = "traceback", f"RecursionError: {str(exc)[:200]}"
        except Exception as exc:  # noqa: BLE001 - the campaign counts every unexpected exception
            frames = traceback.extract_tb(exc.__traceback__)
            where = f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else "?"
            outcome, detail = "traceback", f"{type(exc).__name__} at {where}: {str(exc)[:200]}"
            if _stems_from_memory_error(exc):
                outcome = "memory"
        seconds = time.perf_counter() - start
        peak_mb = max(0.0, ((_status_kb("VmHWM") or 0) - rss_kb) / 1024)
        if outcome != "memory" and peak_mb > memory_limit_mb:
            outcome, detail = "memory", f"peak {peak_mb:.0f} MB above start-up"
        connection.send((outcome, detail, round(peak_mb, 1), round(seconds, 4)))


class _Watchdog(threading.Thread):
    """Reads a worker's resident size every ``WATCHDOG_INTERVAL_S`` while a case runs and kills
    the worker once it holds more than ``limit_kb`` over ``baseline_kb``."""

    def __init__(self, pid: int, baseline_kb: int, limit_kb: float) -> None:
        super().__init__(daemon=True)
        self.pid, self.baseline_kb, self.limit_kb = pid, baseline_kb, limit_kb
        self.peak_kb = 0
        self.killed_at_kb: int | None = None
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            rss = _status_kb("VmRSS", self.pid)
            if rss is None:
                return  # the worker is gone
            above = rss - self.baseline_kb
            self.peak_kb = max(self.peak_kb, above)
            if above > self.limit_kb:
                self.killed_at_kb = above
                try:
                    os.kill(self.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                return
            self._stop_event.wait(WATCHDOG_INTERVAL_S)

    def stop(self) -> None:
        self._stop_event.set()
        self.join()


class _Worker:
    """A spawned process running cases one after another; replaced when a case kills or hangs it,
    or uses too much memory."""

    def __init__(self, runner: Runner, context: object, memory_limit_mb: float) -> None:
        spawn = multiprocessing.get_context("spawn")
        self.memory_limit_mb = memory_limit_mb
        self.connection, child = spawn.Pipe()
        self.process = spawn.Process(
            target=_worker, args=(child, runner, context, memory_limit_mb), daemon=True
        )
        self.process.start()
        child.close()
        # The start-up (imports) is not part of any case's time or memory.
        try:
            if not self.connection.poll(WORKER_START_S):
                raise EOFError(f"no answer in {WORKER_START_S:g} s")
            _, self.baseline_kb = self.connection.recv()
        except (EOFError, OSError) as exc:
            self.process.kill()
            self.process.join()
            raise RuntimeError(
                f"fuzz: the worker did not start ({exc or 'it died'}; exit code {self.process.exitcode})"
            ) from None

    @property
    def alive(self) -> bool:
        return self.process.is_alive()

    def run(self, case: FuzzCase, timeout_s: float) -> tuple[str, str, float, float]:
        """``(outcome, detail, peak_mb, seconds)``; after ``signal``, ``timeout`` or a ``memory``
        kill the worker is dead (``alive`` is false)."""
        start = time.perf_counter()
        assert self.process.pid is not None
        watchdog = _Watchdog(self.process.pid, self.baseline_kb, self.memory_limit_mb * 1024)
        answer, timed_out = None, False
        try:
            self.connection.send(case)
            watchdog.start()
            if self.connection.poll(timeout_s):
                answer = self.connection.recv()
            else:
                timed_out = True
        except (EOFError, OSError):  # the worker died before or while answering
            pass
        finally:
            if watchdog.ident is not None:  # started
                watchdog.stop()
        seconds = round(time.perf_counter() - start, 4)
        if watchdog.killed_at_kb is not None:
            # Killed for its memory, maybe just after it answered: the worker is gone either way.
            self.process.join()
            above_mb = watchdog.killed_at_kb / 1024
            detail = f"resident {above_mb:.0f} MB above start-up: killed by the watchdog"
            return "memory", detail, round(above_mb, 1), seconds
        if answer is not None:
            return answer
        if timed_out and self.process.is_alive():
            self.process.kill()
        self.process.join()
        if timed_out:
            return "timeout", f"no answer in {timeout_s:g} s", float("nan"), seconds
        code = self.process.exitcode
        how = signal.Signals(-code).name if code is not None and code < 0 else f"exit code {code}"
        return "signal", how, float("nan"), seconds

    def close(self) -> None:
        if self.process.is_alive():
            try:
                self.connection.send(None)
            except OSError:
                pass
            self.process.join(5)
            if self.process.is_alive():
                self.process.kill()


def run_guarded(
    cases: Iterable[FuzzCase],
    runner: Runner,
    context: object = None,
    memory_limit_mb: float = 2048.0,
    timeout_s: float = 60.0,
    on_result: Callable[[CaseResult], None] | None = None,
) -> list[CaseResult]:
    """Each case through ``runner`` in a worker process, classified into ``OUTCOMES``."""
    worker = _Worker(runner, context, memory_limit_mb)
    results = []
    try:
        for case in cases:
            result = CaseResult(case, *worker.run(case, timeout_s))
            if not worker.alive:
                worker = _Worker(runner, context, memory_limit_mb)
            results.append(result)
            if on_result is not None:
                on_result(result)
    finally:
        worker.close()
    return results


# -- the campaign


def fuzz_campaign(
    num_cases: int = 1000,
    seed: int = 0,
    targets: tuple[str, ...] = TARGETS,
    model: str | os.PathLike | None = None,
    memory_limit_mb: float = 2048.0,
    timeout_s: float = 60.0,
    keep: str | os.PathLike | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Run ``num_cases`` mutated inputs spread evenly over ``targets``.

    Args:
        model: the checkpoint the checkpoint targets mutate (default: the shipped paper
            pipeline's, which has a box quality regressor).
        memory_limit_mb: a case holding more than this over the worker's start-up (resident,
            watched every ``WATCHDOG_INTERVAL_S``, and at its peak) fails as ``memory``.
        timeout_s: a case answering later fails as ``timeout``.
        keep: folder to copy the failing cases' files into (to reproduce them).

    Returns:
        The benchmark record: counts per target and outcome, every failure, peak memory and time.
    """
    unknown = sorted(set(targets) - set(TARGETS))
    if unknown:
        raise InputError(f"fuzz: unknown targets {unknown}; choose from {', '.join(TARGETS)}")
    if num_cases < 1:
        raise InputError("fuzz: --cases must be at least 1")
    from factorydet_core.session.models import resolve_model

    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory(prefix="factorydet_fuzz_") as scratch_name:
        scratch = Path(scratch_name)
        seeds_dir = scratch / "seeds"
        seeds_dir.mkdir()
        seeds = _write_cloud_seeds(seeds_dir)
        label_seeds, session_root, data = _write_session_seeds(seeds_dir)
        seeds.update(label_seeds)
        if set(targets) & set(CHECKPOINT_TARGETS):
            seeds.update(_write_checkpoint_seeds(seeds_dir, Path(resolve_model(model or "paper"))))
        context = _Context(str(session_root), str(data))

        def cases() -> Iterator[FuzzCase]:
            for index in range(num_cases):
                target = targets[index % len(targets)]
                yield make_case(index, target, seeds[target], scratch / "cases", rng)

        def finished(result: CaseResult) -> None:
            folder = Path(result.case.path).parent
            if result.outcome in FAILURES and keep is not None:
                name = f"case{result.case.index:05d}_{result.case.target}"
                shutil.copytree(folder, Path(keep) / name, dirs_exist_ok=True)
            shutil.rmtree(folder, ignore_errors=True)
            if progress is not None:
                progress(result.case.index + 1, num_cases)

        results = run_guarded(cases(), run_target, context, memory_limit_mb, timeout_s, finished)
    return _record(results, num_cases, seed, targets, memory_limit_mb, timeout_s, time.perf_counter() - start)


def _record(results, num_cases, seed, targets, memory_limit_mb, timeout_s, seconds) -> dict:
    per_target = {}
    for target in targets:
        rows = [r for r in results if r.case.target == target]
        per_target[target] = {
            "cases": len(rows),
            "outcomes": {o: sum(r.outcome == o for r in rows) for o in OUTCOMES},
        }
    totals = {o: sum(r.outcome == o for r in results) for o in OUTCOMES}
    peaks = [r.peak_mb for r in results if np.isfinite(r.peak_mb)]
    times = [r.seconds for r in results if np.isfinite(r.seconds)]
    return {
        "benchmark": "fuzz",
        "cases": num_cases,
        "seed": seed,
        "memory_limit_mb": memory_limit_mb,
        "timeout_s": timeout_s,
        "totals": totals,
        "num_failures": sum(totals[o] for o in FAILURES),
        "targets": per_target,
        "failures": [
            {
                "index": r.case.index,
                "target": r.case.target,
                "mutation": r.case.mutation,
                "outcome": r.outcome,
                "detail": r.detail,
            }  # fmt: skip
            for r in results
            if r.outcome in FAILURES
        ],
        "max_peak_mb": max(peaks) if peaks else None,
        "median_case_seconds": statistics.median(times) if times else None,
        "max_case_seconds": max(times) if times else None,
        "seconds": round(seconds, 1),
    }


def fuzz_markdown(record: dict) -> str:
    """The campaign's counts as a Markdown table, one row per target."""
    lines = [
        f"Fuzz campaign: {record['cases']} cases, seed {record['seed']}, memory limit "
        f"{record['memory_limit_mb']:.0f} MB, {record['num_failures']} failures; "
        f"peak {record['max_peak_mb']} MB, median {record['median_case_seconds']} s a case.",
        "",
        "| target | cases | " + " | ".join(OUTCOMES) + " |",
        "|---|---:|" + "---:|" * len(OUTCOMES),
    ]
    for target, row in record["targets"].items():
        lines.append(
            f"| {target} | {row['cases']} | " + " | ".join(str(row["outcomes"][o]) for o in OUTCOMES) + " |"
        )
    lines.append(
        "| **total** | "
        + str(record["cases"])
        + " | "
        + " | ".join(str(record["totals"][o]) for o in OUTCOMES)
        + " |"
    )
    if "command" in record:
        lines += ["", f"Command: `{record['command']}`"]
    return "\n".join(lines) + "\n"


def write_fuzz_outputs(record: dict, out: str | os.PathLike) -> None:
    """The JSON at ``out`` and its table beside it (``.md``), each written whole."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps(record, indent=2) + "\n")
    write_text_atomic(out.with_suffix(".md"), fuzz_markdown(record))
