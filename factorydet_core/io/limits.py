"""The cap on points per file that every reader checks before it allocates.

A header states how many points follow; a corrupt or hostile one can claim billions in a few
bytes. Each reader compares the claim with the file's length and with this cap first, so that a
bad file gives a one-line ``InputError`` instead of gigabytes of allocation.
"""

from __future__ import annotations

import os

from factorydet_core.types import InputError

MAX_POINTS = 50_000_000
"""Default cap on the points of one file (a dense 5-million-point scan reads with room to spare).
Raise it per call with ``max_points=`` or for a whole run with ``MAX_POINTS_ENV``."""

MAX_POINTS_ENV = "FACTORYDET_MAX_POINTS"
"""Environment variable that replaces ``MAX_POINTS`` (a positive integer)."""

BYTES_PER_POINT = 64
"""Byte budget of the cap for arrays: the arrays read from one ``.npz`` may take at most
``max_points * BYTES_PER_POINT`` bytes ((N, 3) float64 points take 24 bytes a point)."""


def resolve_max_points(max_points: int | None = None) -> int:
    """The cap in force: ``max_points`` when given, else ``$FACTORYDET_MAX_POINTS``, else ``MAX_POINTS``.

    Raises:
        InputError: the argument or the environment variable is not a positive integer.
    """
    if max_points is None:
        text = os.environ.get(MAX_POINTS_ENV, "").strip()
        if not text:
            return MAX_POINTS
        try:
            max_points = int(text.replace("_", ""))
        except ValueError:
            raise InputError(f"{MAX_POINTS_ENV} must be a positive integer, got {text!r}") from None
        where = MAX_POINTS_ENV
    else:
        where = "max_points"
    if max_points < 1:
        raise InputError(f"{where} must be a positive integer, got {max_points}")
    return int(max_points)


RAISE_HINT = f"raise the limit with max_points= or the {MAX_POINTS_ENV} environment variable"
"""How to lift the cap, appended to every message that refuses a file for its size."""


def too_many_points(
    path: str | os.PathLike, count: int, max_points: int, what: str = "the header"
) -> InputError:
    """The one-line error for a file whose ``what`` declares ``count`` > ``max_points`` points."""
    return InputError(
        f"{path}: {what} declares {count} points, more than the limit of {max_points} points "
        f"per file ({RAISE_HINT})"
    )
