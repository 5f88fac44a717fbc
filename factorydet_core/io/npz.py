"""A byte-reproducible ``.npz`` writer and a guarded ``.npz`` / ``.npy`` loader.

``numpy.savez_compressed`` stamps each member with the current time, so two runs with the same
seed would give different bytes. This writer uses a fixed timestamp and a fixed member order.

``numpy.load`` trusts an array's header: a member whose header claims 10**10 rows allocates them
before it finds the data missing, and a deflate bomb of a few MB inflates to gigabytes.
``load_npz`` reads each member's header first and refuses, with a one-line ``InputError``, an
array larger than its member's declared size or than the points cap, members inflating more than
``io.limits.MAX_INFLATION`` times their compressed size, arrays (with what the caller says its
conversion of them will take) above the byte budget of one read (``io.limits``), and object arrays
(pickles).
"""

from __future__ import annotations

import io
import math
import os
import zipfile
from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import BinaryIO

import numpy as np

from factorydet_core.io.atomic import atomic_path
from factorydet_core.io.limits import (
    check_inflation,
    check_read_bytes,
    resolve_max_points,
    resolve_max_read_bytes,
    too_many_points,
)
from factorydet_core.types import InputError

_EPOCH = (1980, 1, 1, 0, 0, 0)


def save_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as a compressed ``.npz`` that ``numpy.load`` reads, atomically."""
    with (
        atomic_path(path) as tmp,
        zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as archive,
    ):
        for key in arrays:
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asarray(arrays[key]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, buffer.getvalue())


def read_npy_header(handle: BinaryIO) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` of the ``.npy`` header at the handle's position, which is left at the data.

    Raises:
        ValueError: bad magic bytes, an unsupported format version or a malformed header.
    """
    version = np.lib.format.read_magic(handle)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(handle)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
    else:  # 3.0 only differs by utf-8 field names, which no point array of ours has
        raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    return tuple(int(n) for n in shape), np.dtype(dtype)


def check_npy_array(
    path: str | os.PathLike,
    name: str,
    shape: tuple[int, ...],
    dtype: np.dtype,
    available: int,
    max_points: int,
) -> int:
    """Check an array's header before it is read; returns its size in bytes.

    Args:
        path: the file, for the message.
        name: what the array is, for the message (``"the array"``, ``"member 'points'"``).
        shape, dtype: from ``read_npy_header``.
        available: bytes of data the file (or zip member) holds after the header.
        max_points: the points cap on the array's rows.

    Raises:
        InputError: an object (pickled) array, a header claiming more bytes than follow, or more
            rows than the cap.
    """
    if dtype.hasobject:
        raise InputError(f"{path}: {name} holds Python objects (a pickle), which are not read")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > available:
        raise InputError(
            f"{path}: {name} declares shape {shape} {dtype} ({nbytes} bytes) but only {available} "
            "bytes follow (truncated or corrupt)"
        )
    rows = shape[0] if shape else 1
    if rows > max_points:
        raise too_many_points(path, rows, max_points, f"{name} of shape {shape}")
    return nbytes


NpyHeaders = Mapping[str, tuple[tuple[int, ...], np.dtype]]
"""``{array name: (shape, dtype)}`` of the arrays ``load_npz`` is about to read."""


def load_npz(
    path: str | os.PathLike,
    keys: Collection[str] | None = None,
    *,
    max_points: int | None = None,
    max_read_bytes: int | None = None,
    conversion_bytes: Callable[[NpyHeaders], int] | None = None,
) -> tuple[list[str], dict[str, np.ndarray]]:
    """Read the arrays of an ``.npz`` after checking every header against its member and the caps.

    Args:
        path: the archive.
        keys: the arrays to read (those present); ``None`` reads all.
        max_points: the points cap on every array's rows (``io.limits.resolve_max_points``).
        max_read_bytes: the byte budget (``io.limits.resolve_max_read_bytes``): the arrays read
            plus ``conversion_bytes`` of their headers must fit in it.
        conversion_bytes: what the caller will allocate turning the arrays into its result, from
            their shapes and dtypes (``None``: nothing).

    Returns:
        ``(names of all arrays in the archive, {name: array} of those read)``.

    Raises:
        InputError: not a zip, a broken member, an object array, a lying header, a deflate bomb or
            arrays above a cap, in one line naming the file.
        OSError: the file cannot be opened.
        MemoryError: never turned into an ``InputError``: the caps are meant to prevent it, and a
            caller (or the fuzz harness) must see it if they do not.
    """
    path = Path(path)
    cap = resolve_max_points(max_points)
    budget = resolve_max_read_bytes(max_read_bytes)
    try:
        with zipfile.ZipFile(path) as archive:
            members = {i.filename[:-4]: i for i in archive.infolist() if i.filename.endswith(".npy")}
            wanted = [key for key in (members if keys is None else keys) if key in members]
            # The central directory's sizes first: a deflate bomb is refused before any inflating
            # (compressed sizes beyond the file's are lies, so the file's length bounds them).
            compressed = min(sum(members[key].compress_size for key in wanted), path.stat().st_size)
            inflated = sum(members[key].file_size for key in wanted)
            check_inflation(path, inflated, compressed, "its members")
            headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
            nbytes = 0
            for key in wanted:
                info = members[key]
                with archive.open(info) as member:
                    shape, dtype = read_npy_header(member)
                    # file_size is the member's declared inflated size; the reader stops there.
                    available = info.file_size - member.tell()
                nbytes += check_npy_array(path, f"member {key!r}", shape, dtype, available, cap)
                headers[key] = (shape, dtype)
            extra = conversion_bytes(headers) if conversion_bytes is not None else 0
            check_read_bytes(path, nbytes + extra, budget, f"its arrays ({nbytes} bytes)")
            arrays = {}
            for key in wanted:
                with archive.open(members[key]) as member:
                    arrays[key] = np.lib.format.read_array(member, allow_pickle=False)
    except (InputError, OSError, MemoryError):
        raise
    except Exception as exc:  # zipfile.BadZipFile, zlib.error, EOF in a member, a bad header, ...
        reason = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise InputError(f"{path}: broken .npz archive: {reason}") from None
    return list(members), arrays
