"""Files written whole or not at all: a reader, or a run stopped while writing, never sees half a
file (the old one stays until the new one is complete), and a crash of the machine right after the
write leaves the new file or the old one, never an empty one.

The data go to a hidden temporary file beside the target, unique to the call (process, thread and a
random suffix), so concurrent writers of one target never share it: the last rename wins whole.
The temporary file is flushed to disk before it is renamed onto the target, and the folder after.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import threading
from collections.abc import Iterator
from pathlib import Path


def _temporary_name(path: Path) -> Path:
    """A hidden name beside ``path``, with its suffix, that no other call uses."""
    unique = f"{os.getpid()}-{threading.get_ident()}-{secrets.token_hex(4)}"
    return path.with_name(f".{path.stem}.tmp{unique}{path.suffix}")


def _fsync_file(path: Path) -> None:
    """Flush ``path``'s data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename) to disk, where the file system allows it: the rename
    is atomic either way, so a folder that cannot be synced (EINVAL on some) is no failure."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _naming_target(exc: OSError, path: Path) -> OSError:
    """``exc`` as an error of ``path``: the same type (from the errno), reason and errno."""
    if exc.errno:
        return OSError(exc.errno, exc.strerror or str(exc), str(path))
    return OSError(f"{path}: {exc}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix) and move it onto ``path`` on success.

    The body writes (and closes) the temporary file; it is then synced to disk, renamed onto
    ``path`` and the folder synced. Nothing is left behind on failure.

    Raises:
        OSError: writing, syncing or renaming failed; the error names ``path``, not the hidden
            temporary file, keeps its type and errno (``PermissionError``, ENOSPC, ...), and chains
            the original. Errors of other files in the body pass unchanged.
    """
    path = Path(path)
    tmp = _temporary_name(path)
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        # An error with no file name (ENOSPC in write) or the temporary's is the target's.
        if exc.filename in (None, str(tmp), tmp) or exc.filename2 in (str(tmp), tmp):
            raise _naming_target(exc, path) from exc
        raise
    else:
        _fsync_folder(path.parent)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """``Path(path).write_text(text)``, whole or not at all.

    Raises:
        OSError: the file cannot be written (the error names ``path``).
    """
    with atomic_path(path) as tmp:
        tmp.write_text(text)
