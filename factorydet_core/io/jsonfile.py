"""Reading a JSON record (a data set's manifest, the simulator's truth) with one-line errors, and
writing one whole or not at all.

``json.loads`` on a hostile file fails in several ways: a ``RecursionError`` (a traceback) for
deeply nested brackets, ``UnicodeDecodeError`` for bytes that are not UTF-8, and gigabytes of
objects for a file of hundreds of MB. ``read_json`` turns each into an ``InputError`` naming the
file, and refuses files above ``MAX_JSON_BYTES`` before reading them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.types import InputError

MAX_JSON_BYTES = 64 * 2**20
"""Largest JSON record read (64 MiB): parsed, JSON takes up to about 20 times its size, so this
keeps a record within the byte budget of one read (``io.limits.MAX_READ_BYTES``). A simulated
data set's manifest and truth take tens to hundreds of KB."""


def read_json(path: str | os.PathLike, *, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """The parsed contents of the JSON file at ``path``.

    Args:
        what: what the file is, for the messages ("manifest", "truth record").
        max_bytes: refuse larger files without reading them.

    Raises:
        InputError: the file cannot be read, is larger than ``max_bytes``, is not UTF-8, is not
            JSON or is nested too deeply, in one line naming the file.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size <= max_bytes:
            return json.loads(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    except RecursionError:
        raise InputError(f"{path}: malformed {what}: nested too deeply") from None
    except ValueError as exc:  # json.JSONDecodeError, UnicodeDecodeError
        reason = " ".join(str(exc).split())[:200]
        raise InputError(f"{path}: malformed {what} ({type(exc).__name__}: {reason})") from None
    raise InputError(f"{path}: a {what} of {size} bytes, more than the {max_bytes} bytes allowed")


def write_json(path: str | os.PathLike, value: Any) -> None:
    """``value`` as indented JSON at ``path`` (its folder made if missing), written whole or not at
    all: a run stopped while writing leaves the previous file (``io.atomic``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(value, indent=2) + "\n")
