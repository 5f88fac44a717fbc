"""The caps every reader checks before it allocates: points per file, bytes per read, inflation.

A header states how many points follow; a corrupt or hostile one can claim billions in a few
bytes, and a compressed member of a few MB can inflate to gigabytes. Each reader works out, from
the header alone, what the read will hold at its peak and compares it with these caps first, so
that a bad file gives a one-line ``InputError`` instead of gigabytes of allocation:

- ``MAX_POINTS``: points per file (``FACTORYDET_MAX_POINTS`` or ``max_points=``).
- ``MAX_READ_BYTES``: bytes one read may allocate, the decoded arrays and every conversion copy
  up to the finished ``Frame`` together (``FACTORYDET_MAX_READ_BYTES`` or ``max_read_bytes=``).
- ``MAX_INFLATION`` / ``MIN_INFLATE_ALLOWANCE``: compressed data (``.npz`` deflate members, LAZ
  point records) may inflate to at most ``max(MIN_INFLATE_ALLOWANCE, MAX_INFLATION x compressed
  size)``. Real point clouds compress 1.3-8x; runs of zeros compress about 1000x.
"""

from __future__ import annotations

import os
import re

from factorydet_core.types import InputError

MAX_POINTS = 50_000_000
"""Default cap on the points of one file (the default ``MAX_READ_BYTES`` reads about as many)."""

MAX_POINTS_ENV = "FACTORYDET_MAX_POINTS"
"""Environment variable that replaces ``MAX_POINTS`` (a positive integer)."""

MAX_READ_BYTES = 8_000_000_000
"""Default byte budget of one read (8 GB): the decoded arrays plus the conversion copies up to the
``Frame``, at their peak, as estimated before anything is allocated. A 5-million-point scan with
colours and intensity is estimated at 0.72-0.92 GB in every format (its measured peak resident size
is 0.24-0.64 GB), so the default reads about ``MAX_POINTS`` points on a machine with the memory for
them. Hostile files never get near it: their claimed sizes are checked against the file's length,
and compressed data against ``MAX_INFLATION``; a machine with less memory lowers it with
``FACTORYDET_MAX_READ_BYTES``."""

MAX_READ_BYTES_ENV = "FACTORYDET_MAX_READ_BYTES"
"""Environment variable that replaces ``MAX_READ_BYTES``: bytes, optionally with a decimal unit
(``4000000000``, ``4e9``, ``4G``, ``4GB``, ``500M``)."""

FRAME_BYTES_PER_POINT = 128
"""Bytes a point costs from the decoded records to the finished ``Frame``, at the peak: float64
coordinates and their float32 copy, colours, intensity, instance and sensor ids and the temporaries
of the checks. Measured with tracemalloc over every format, with and without colours, intensity,
boxes and recentring: at most 102 bytes a point beyond the decoded records (an ASCII PLY with
colours); ``tests/core/io/test_reader_limits.py`` checks that every reader's estimate covers its
measured peak."""

MAX_INFLATION = 100
"""Compressed data may inflate at most this many times. Measured: the nine shared real ``.npz``
scenes (``shared/data/real``) inflate 1.3-1.5x and their LAZ copies 1.9-7.6x; a 5-million-point
scan inflates 1.6x as ``.npz`` and 2.6x as LAZ. Zero-filled members inflate about 1000x."""

MIN_INFLATE_ALLOWANCE = 64 * 2**20
"""Inflated bytes always allowed whatever the ratio (64 MiB), so small, very regular files read."""


def _positive(text: str | None, value: int | None, env: str, arg: str, default: int, units: bool) -> int:
    """``value`` if given, else the environment variable ``env`` (``text``), else ``default``."""
    if value is None:
        text = (text or "").strip()
        if not text:
            return default
        value = _parse_size(text) if units else _parse_int(text)
        if value is None:
            kind = "a positive number of bytes (e.g. 4000000000 or 4G)" if units else "a positive integer"
            raise InputError(f"{env} must be {kind}, got {text!r}")
        where = env
    else:
        where = arg
    if value < 1:
        raise InputError(f"{where} must be a positive integer, got {value}")
    return int(value)


def _parse_int(text: str) -> int | None:
    try:
        return int(text.replace("_", ""))
    except ValueError:
        return None


_SIZE = re.compile(r"(\d+(?:\.\d*)?(?:[eE]\d+)?)\s*([kKmMgGtT]?)[bB]?")
_UNITS = {"": 1, "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12}


def _parse_size(text: str) -> int | None:
    """Bytes from ``"1500000000"``, ``"1.5e9"``, ``"1.5G"`` or ``"1500MB"`` (decimal units)."""
    match = _SIZE.fullmatch(text.replace("_", ""))
    if match is None:
        return None
    return int(float(match.group(1)) * _UNITS[match.group(2).lower()])


def resolve_max_points(max_points: int | None = None) -> int:
    """The cap in force: ``max_points`` when given, else ``$FACTORYDET_MAX_POINTS``, else ``MAX_POINTS``.

    Raises:
        InputError: the argument or the environment variable is not a positive integer.
    """
    text = os.environ.get(MAX_POINTS_ENV)
    return _positive(text, max_points, MAX_POINTS_ENV, "max_points", MAX_POINTS, units=False)


def resolve_max_read_bytes(max_read_bytes: int | None = None) -> int:
    """The byte budget in force: ``max_read_bytes`` when given, else ``$FACTORYDET_MAX_READ_BYTES``,
    else ``MAX_READ_BYTES``.

    Raises:
        InputError: the argument or the environment variable is not a positive size.
    """
    text = os.environ.get(MAX_READ_BYTES_ENV)
    return _positive(text, max_read_bytes, MAX_READ_BYTES_ENV, "max_read_bytes", MAX_READ_BYTES, units=True)


RAISE_HINT = f"raise the limit with max_points= or the {MAX_POINTS_ENV} environment variable"
"""How to lift the points cap, appended to every message that refuses a file for its points."""

RAISE_BYTES_HINT = f"raise the limit with max_read_bytes= or the {MAX_READ_BYTES_ENV} environment variable"
"""How to lift the byte budget, appended to every message that refuses a file for its bytes."""


def too_many_points(
    path: str | os.PathLike, count: int, max_points: int, what: str = "the header"
) -> InputError:
    """The one-line error for a file whose ``what`` declares ``count`` > ``max_points`` points."""
    return InputError(
        f"{path}: {what} declares {count} points, more than the limit of {max_points} points "
        f"per file ({RAISE_HINT})"
    )


def _mb(num_bytes: int) -> str:
    return f"{num_bytes / 1e6:.0f} MB" if num_bytes >= 10**6 else f"{num_bytes} bytes"


def check_read_bytes(path: str | os.PathLike, needed: int, max_read_bytes: int, what: str) -> None:
    """Refuse a read that would allocate more than the budget; call it before allocating.

    Args:
        path: the file, for the message.
        needed: the read's peak bytes, worked out from the header (``what`` says what they are).
        max_read_bytes: from ``resolve_max_read_bytes``.

    Raises:
        InputError: ``needed`` > ``max_read_bytes``, in one line.
    """
    if needed > max_read_bytes:
        raise InputError(
            f"{path}: reading {what} needs about {_mb(needed)}, more than the {_mb(max_read_bytes)} "
            f"allowed for one read ({RAISE_BYTES_HINT})"
        )


def inflate_allowance(compressed: int) -> int:
    """The most bytes ``compressed`` bytes of deflate or LAZ data may inflate to."""
    return max(MIN_INFLATE_ALLOWANCE, MAX_INFLATION * max(int(compressed), 0))


def check_inflation(path: str | os.PathLike, inflated: int, compressed: int, what: str) -> None:
    """Refuse compressed data that claims to inflate beyond ``inflate_allowance``.

    Raises:
        InputError: a compression bomb or a corrupt size, in one line.
    """
    if inflated > inflate_allowance(compressed):
        raise InputError(
            f"{path}: {what} claim {inflated} bytes inflated from {compressed} compressed bytes, more "
            f"than {MAX_INFLATION}x (a compression bomb or a corrupt size; real point clouds compress "
            "less than 10x)"
        )
