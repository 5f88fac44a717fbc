"""Checkpoints on disk: a network's state dict (``NAME.pt``) with a JSON note beside it
(``NAME.json``).

Both are written whole or not at all (``io.atomic``), and read back as untrusted input: a checkpoint
may be hand-edited, cut off, or not ours. Every setting of a note is checked
(``settings_check.Setting``) before any network is built from it, the state dict's archive size is
bounded by the network's own before it is read, and its tensors' names, shapes and dtypes are
compared with the network's before they are loaded. Whatever is wrong is one line of ``InputError``
naming the file; torch reads the weights with ``weights_only=True``, so a crafted file runs no code.
The note, written last, records the size and SHA-256 of the files it belongs with
(``check_checkpoint_files``): files replaced one by one can be of different saves.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from factorydet_core.io.atomic import atomic_path, write_text_atomic
from factorydet_core.io.jsonfile import read_json
from factorydet_core.settings_check import Setting, short_repr
from factorydet_core.types import InputError

BACKGROUND = "background"

MAX_NOTE_BYTES = 16 * 2**20
"""The largest note read: a note holds settings, labels and a history of a few hundred epochs (the
shipped ones are a few kB)."""

MAX_CLASSES = 256
"""The most object classes a model may have: the paper's has 7, and a label file's own classes stay
far below this. It bounds the size of the networks' class layers and of the box quality's one-hot
features a note can ask for."""

MAX_CLASS_NAME_CHARS = 100

STATE_DICT_SLACK_BYTES = 4 * 2**20
"""What a state dict's archive may hold beyond its tensors' bytes: the pickled names and torch's
small records (about 10 kB for the shipped checkpoints)."""

MAX_SEED = 2**63 - 1


def check_class_names(names: object) -> tuple[str, ...]:
    """Class names as a tuple: 1 to ``MAX_CLASSES`` distinct, non-empty texts of at most
    ``MAX_CLASS_NAME_CHARS`` characters, none of them "background" (the extra output column)."""
    if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)):
        raise InputError(f"class_names must be a list of names, got {type(names).__name__}")
    if not 1 <= len(names) <= MAX_CLASSES:
        raise InputError(f"class_names must hold 1 to {MAX_CLASSES} names, got {len(names)}")
    for name in names:
        if not isinstance(name, str) or not 0 < len(name) <= MAX_CLASS_NAME_CHARS:
            raise InputError(
                f"class_names must be texts of 1 to {MAX_CLASS_NAME_CHARS} characters, got {short_repr(name)}"
            )
    if BACKGROUND in names:
        raise InputError(f"class_names must not include {BACKGROUND!r} (the extra output column)")
    if len(set(names)) != len(names):
        raise InputError("class_names must be distinct")
    return tuple(names)


def write_checkpoint(
    network: nn.Module,
    path: str | os.PathLike,
    note: dict,
    companions: Mapping[str, str | os.PathLike] | None = None,
) -> Path:
    """A network's state dict at ``path`` (.pt) and ``note`` as JSON beside it (.json), each written
    whole or not at all.

    The note goes last and records the size and SHA-256 of the weights and of each of
    ``companions`` (role -> a file of the same checkpoint written before it, such as the box quality
    arrays) under ``FILES_KEY``: the files are replaced one by one, so an interrupted save can leave
    new files beside an old note, and ``check_checkpoint_files`` tells. Any ``FILES_KEY`` of
    ``note`` itself (a loaded model's note saved again) is replaced.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(network.state_dict(), tmp)
        files = {"weights": file_record(tmp)}  # the bytes written, whoever replaces the file later
    for role, companion in (companions or {}).items():
        files[role] = file_record(companion)
    write_text_atomic(path.with_suffix(".json"), json.dumps({**note, FILES_KEY: files}, indent=2))
    return path


FILES_KEY = "files"
"""The note's record of the files it was saved with: role -> ``file_record``."""

MAX_CHECKPOINT_FILE_BYTES = 2**31
"""The largest file a note may record (the shipped weights and box quality arrays take under 1 MB
each, the largest networks the note's settings allow some hundred MB): it bounds the hashing a
note can ask for."""


def file_record(path: str | os.PathLike) -> dict[str, object]:
    """The size and SHA-256 of the file at ``path``, as a note records them."""
    path = Path(path)
    return {"bytes": path.stat().st_size, "sha256": _sha256(path)}


def check_checkpoint_files(note: Mapping[str, object], paths: Mapping[str, Path], note_path: Path) -> None:
    """Check that the files of a checkpoint are the ones its note was saved with (``write_checkpoint``).

    Args:
        note: the checkpoint's note; without ``FILES_KEY`` (the shipped checkpoints, those saved
            before the files were recorded) there is nothing to compare and the check passes.
        paths: role -> where that file of the checkpoint is ("weights": the .pt and any
            companions); a role the note records but ``paths`` lacks is refused.
        note_path: the note's file, named in the error.

    Raises:
        InputError: one line naming the note: a malformed record, or a file of another save (or
            missing), which an interrupted save or a copy of only some of the files leaves.
    """
    files = note.get(FILES_KEY)
    if files is None:
        return
    if not isinstance(files, dict) or not all(isinstance(role, str) and role in paths for role in files):
        raise InputError(
            f"{note_path}: {FILES_KEY} must map the checkpoint's files ({', '.join(paths)}) to their"
            f" sizes and hashes, got {short_repr(files)}"
        )
    expected = {}
    for role, record in files.items():
        if not isinstance(record, dict) or set(record) != {"bytes", "sha256"}:
            raise InputError(
                f"{note_path}: {FILES_KEY}[{role!r}] must hold bytes and sha256, got {short_repr(record)}"
            )
        size = Setting(int, 0, MAX_CHECKPOINT_FILE_BYTES).check(
            f"{note_path}: {FILES_KEY}[{role!r}] bytes", record["bytes"]
        )
        digest = record["sha256"]
        if not (
            isinstance(digest, str) and len(digest) == 64 and all(c in "0123456789abcdef" for c in digest)
        ):
            raise InputError(
                f"{note_path}: {FILES_KEY}[{role!r}] sha256 must be 64 hex digits, got {short_repr(digest)}"
            )
        expected[role] = (size, digest)
    # The sizes first: a file of another save is usually told apart without reading it.
    for role, (size, digest) in expected.items():
        path = paths[role]
        try:
            matches = path.stat().st_size == size and _sha256(path) == digest
        except FileNotFoundError:
            matches = False
        except OSError as exc:
            raise InputError(f"{path}: unreadable checkpoint file ({exc.strerror or exc})") from None
        if not matches:
            raise InputError(
                f"{note_path}: the checkpoint's files are from different saves ({path.name} is not the"
                " file this note was saved with, e.g. after an interrupted save): re-export or re-train"
                " the model"
            )


def _sha256(path: Path) -> str:
    """The SHA-256 of a file, read in 1 MB blocks."""
    digest = hashlib.sha256()
    with path.open("rb") as file:
        while block := file.read(2**20):
            digest.update(block)
    return digest.hexdigest()


def read_checkpoint_note(path: str | os.PathLike) -> dict:
    """The JSON note of the checkpoint at ``path``; ``InputError`` if either file is missing or
    the note is not a JSON object (of at most ``MAX_NOTE_BYTES``)."""
    path = Path(path)
    note_path = path.with_suffix(".json")
    if not path.is_file() or not note_path.is_file():
        raise InputError(f"{path}: no checkpoint (needs {path.name} and {note_path.name})")
    note = read_json(note_path, what="checkpoint note", max_bytes=MAX_NOTE_BYTES)
    if not isinstance(note, dict):
        raise InputError(f"{note_path}: malformed checkpoint note (not a JSON object)")
    return note


def read_state_dict(path: str | os.PathLike, expected: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The state dict at ``path``, checked against a network's ``expected`` one (same names,
    shapes and dtypes, finite values) before anything is loaded into it.

    The archive's declared size is compared with the expected tensors' before torch reads it (a
    file can declare gigabytes in a few bytes), and torch unpickles with ``weights_only=True``.

    Raises:
        InputError: one line naming ``path``: empty, not a PyTorch archive, Python objects other
            than tensors, not a state dict, or weights of another network.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"{path}: unreadable checkpoint ({exc.strerror or exc})") from None
    if size == 0:
        raise InputError(f"{path}: empty file, not a checkpoint")
    expected_bytes = sum(t.numel() * t.element_size() for t in expected.values())
    try:
        with zipfile.ZipFile(path) as archive:
            declared = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError, ValueError):  # PyTorch has written zip archives since 1.6
        raise InputError(f"{path}: not a factorydet checkpoint (not a PyTorch archive)") from None
    if declared > expected_bytes + STATE_DICT_SLACK_BYTES:
        raise InputError(
            f"{path}: holds {declared} bytes where this network's weights take {expected_bytes}:"
            " not the weights its note describes"
        )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch's own message advises loading without weights_only: not for a file of unknown origin.
        raise InputError(
            f"{path}: not a factorydet checkpoint (it holds Python objects other than tensors;"
            " refused for safety)"
        ) from None
    except (RuntimeError, OSError, ValueError, KeyError, EOFError, TypeError, AttributeError) as exc:
        raise InputError(f"{path}: unreadable checkpoint ({_first_line(exc)})") from None
    if not isinstance(state, Mapping):
        what = type(state).__name__
        raise InputError(f"{path}: not a factorydet checkpoint (holds a {what}, not a state dict)")
    missing = [name for name in expected if name not in state]
    unexpected = [str(name) for name in state if name not in expected]
    if missing or unexpected:
        what = f"lacks {missing[0]}" if missing else f"has an unexpected {unexpected[0][:80]}"
        raise InputError(
            f"{path}: weights of another network ({what}; {len(missing)} missing, {len(unexpected)}"
            " unexpected): not the weights its note describes"
        )
    for name, want in expected.items():
        tensor = state[name]
        if not isinstance(tensor, torch.Tensor):
            raise InputError(f"{path}: {name} is a {type(tensor).__name__}, not a tensor")
        if tensor.shape != want.shape or tensor.dtype != want.dtype:
            raise InputError(
                f"{path}: {name} is {tuple(tensor.shape)} {tensor.dtype} where the network its note"
                f" describes has {tuple(want.shape)} {want.dtype}"
            )
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise InputError(f"{path}: {name} holds NaN or Inf values")
    return dict(state)


def load_weights(network: nn.Module, path: str | os.PathLike) -> nn.Module:
    """``network`` with the state dict at ``path`` (``read_state_dict``), in eval mode;
    ``InputError`` if it does not fit."""
    state = read_state_dict(path, network.state_dict())
    try:
        network.load_state_dict(state)
    except RuntimeError as exc:  # read_state_dict compared names and shapes: not expected
        raise InputError(f"{path}: weights do not fit the network ({_first_line(exc)})") from None
    network.eval()
    return network


def check_note_record(meta: Mapping[str, object], class_names: tuple[str, ...], where: str) -> None:
    """Check the informative fields of a note that its model keeps (``labels``, ``history``,
    ``fit_seconds``, ``train_hash``, ``train_counts``), each optional."""
    labels = meta.get("labels")
    if labels is not None and labels != [*class_names, BACKGROUND]:
        raise InputError(f"{where}: labels {labels!r} are not the class names and background"[:200])
    history = meta.get("history", [])
    if not isinstance(history, list) or not all(isinstance(h, dict) for h in history):
        raise InputError(f"{where}: history must be a list of objects")
    Setting(float, low=0.0).check(f"{where}: fit_seconds", meta.get("fit_seconds", 0.0))
    if not isinstance(meta.get("train_hash", ""), str):
        raise InputError(f"{where}: train_hash must be a text")
    counts = meta.get("train_counts", {})
    if not isinstance(counts, dict):
        raise InputError(f"{where}: train_counts must map labels to counts")
    for label, count in counts.items():
        Setting(int, low=0).check(f"{where}: train_counts[{label!r}]", count)


def _first_line(exc: BaseException) -> str:
    """An exception's message cut to one line of at most 200 characters."""
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]
