"""A byte-reproducible ``.npz`` writer and a guarded ``.npz`` / ``.npy`` loader.

``numpy.savez_compressed`` stamps each member with the current time, so two runs with the same
seed would give different bytes. This writer uses a fixed timestamp and a fixed member order.

``numpy.load`` trusts an array's header: a member whose header claims 10**10 rows allocates them
before it finds the data missing, and a deflate bomb of a few MB inflates to gigabytes.
``load_npz`` reads each member's header first and refuses, with a one-line ``InputError``, an
array larger than its member's declared size or than the points cap (``io.limits``), and object
arrays (pickles).
"""

from __future__ import annotations

import io
import math
import os
import zipfile
from collections.abc import Collection
from pathlib import Path
from typing import BinaryIO

import numpy as np

from factorydet_core.io.atomic import atomic_path
from factorydet_core.io.limits import BYTES_PER_POINT, RAISE_HINT, resolve_max_points, too_many_points
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
        max_points: the points cap; rows and bytes (``BYTES_PER_POINT`` a point) are checked.

    Raises:
        InputError: an object (pickled) array, a header claiming more bytes than follow, or an
            array above the cap.
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
    if nbytes > max_points * BYTES_PER_POINT:
        raise InputError(
            f"{path}: {name} of shape {shape} {dtype} takes {nbytes} bytes, more than the "
            f"{max_points * BYTES_PER_POINT} bytes allowed for {max_points} points ({RAISE_HINT})"
        )
    return nbytes


def load_npz(
    path: str | os.PathLike, keys: Collection[str] | None = None, *, max_points: int | None = None
) -> tuple[list[str], dict[str, np.ndarray]]:
    """Read the arrays of an ``.npz`` after checking every header against its member and the cap.

    Args:
        path: the archive.
        keys: the arrays to read (those present); ``None`` reads all.
        max_points: the points cap (``io.limits.resolve_max_points``); the arrays read may take
            ``max_points * BYTES_PER_POINT`` bytes together.

    Returns:
        ``(names of all arrays in the archive, {name: array} of those read)``.

    Raises:
        InputError: not a zip, a broken member, an object array, a lying header or an array
            above the cap, in one line naming the file.
        OSError: the file cannot be opened.
    """
    path = Path(path)
    cap = resolve_max_points(max_points)
    try:
        with zipfile.ZipFile(path) as archive:
            members = {i.filename[:-4]: i for i in archive.infolist() if i.filename.endswith(".npy")}
            wanted = [key for key in (members if keys is None else keys) if key in members]
            budget = cap * BYTES_PER_POINT
            for key in wanted:
                info = members[key]
                with archive.open(info) as member:
                    shape, dtype = read_npy_header(member)
                    # file_size is the member's declared inflated size; the reader stops there.
                    available = info.file_size - member.tell()
                budget -= check_npy_array(path, f"member {key!r}", shape, dtype, available, cap)
                if budget < 0:
                    raise InputError(
                        f"{path}: its arrays take more than the {cap * BYTES_PER_POINT} bytes "
                        f"allowed for {cap} points ({RAISE_HINT})"
                    )
            arrays = {}
            for key in wanted:
                with archive.open(members[key]) as member:
                    arrays[key] = np.lib.format.read_array(member, allow_pickle=False)
    except (InputError, OSError):
        raise
    except Exception as exc:  # zipfile.BadZipFile, zlib.error, EOF in a member, a bad header, ...
        reason = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise InputError(f"{path}: broken .npz archive: {reason}") from None
    return list(members), arrays
