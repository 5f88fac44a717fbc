"""What every benchmark record carries: the machine it ran on, and the frames it ran on."""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.types import InputError

__all__ = [
    "library_version",
    "library_versions",
    "machine_info",
    "mixed_library_note",
    "runs_of_this_library",
    "spread_frames",
]


def machine_info() -> dict:
    """Where a benchmark ran: CPU model, cores, memory, Python and the main libraries."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory_gb = None
    try:
        memory_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    import open3d

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gb": memory_gb,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "open3d": open3d.__version__,
        "os": platform.platform(),
    }


@functools.cache
def library_version() -> str:
    """Which code a run ran: the first 12 hex digits of a SHA-256 over the path and the bytes of
    every module of ``factorydet_core``, in path order. Two runs with one digest ran the same
    library; the packages under it (numpy, torch, ...) are the record's ``machine_info``.

    Any change to a module changes it, even one that cannot change a result (a docstring): it
    tells runs apart that may differ, and says nothing of runs that happen to agree."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py"), key=lambda p: p.relative_to(root).as_posix()):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:12]


def library_versions(runs: Sequence[dict]) -> dict[str, int]:
    """How many of ``runs`` (run records with a ``"library"`` field, ``library_version``) ran
    each version of the library, most first; runs of records from before the field existed
    count as ``"unknown"``."""
    counts: dict[str, int] = {}
    for run in runs:
        key = run.get("library") or "unknown"
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def mixed_library_note(versions: Mapping[str, int], runs: str, effect: str) -> str:
    """A record's sentence for runs of more than one version of the library (``library_versions``:
    ``versions``), "" otherwise: " **{runs} ran N versions of the library** (K of a version not
    kept): {effect}." (``runs``: which runs, "The 6 runs"; ``effect``: what it does to the figures)."""
    if len(versions) < 2:
        return ""
    unknown = versions.get("unknown", 0)
    return (
        f" **{runs} ran {len(versions)} versions of the library**"
        + (f" ({unknown} of a version not kept)" if unknown else "")
        + f": {effect}."
    )


def runs_of_this_library(found: Mapping, benchmark: str, what: str) -> dict:
    """The entries of ``found`` (``{key: [run records]}``, what a resume would read back) all of
    whose runs ran this version of the library (``library_version``); the others are left out, to
    be trained again, with a warning naming how many ``what`` (plural: "runs", "training seeds")
    and which versions they ran."""
    version = library_version()
    other = [key for key, runs in found.items() if any(run.get("library") != version for run in runs)]
    if other:
        ran = library_versions([run for key in other for run in found[key] if run.get("library") != version])
        warnings.warn(
            f"bench {benchmark} --resume: {len(other)} of the earlier record's {what} ran another version "
            f"of the library than this one ({version}): {', '.join(f'{v} ({n})' for v, n in ran.items())}; "
            "they train again (--resume-other-library reads them back, and the record then mixes versions)",
            stacklevel=3,
        )
    return {key: runs for key, runs in found.items() if key not in other}


def spread_frames(frames: Sequence[int], count: int | None) -> list[int]:
    """``count`` frames spread evenly over ``frames`` (all of them for ``None`` or more than there
    are), first and last included: a vehicle's consecutive frames are 1.5 m apart and nearly
    repeat each other, so the first N would see one corner of the hall."""
    frames = [int(i) for i in frames]
    if count is None or count >= len(frames):
        return frames
    if count < 1:
        raise InputError(f"frame count must be >= 1, got {count}")
    picks = np.unique(np.round(np.linspace(0, len(frames) - 1, count)).astype(int))
    return [frames[i] for i in picks]


def changed_fields(mine: dict, theirs: dict) -> list[str]:
    """The keys whose values differ between two mappings (a key one lacks counts as None), sorted."""
    return sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))


def check_same_plan(
    benchmark: str, mine: dict, theirs: dict | None, what: str = "the earlier result"
) -> None:
    """Refuse to resume a benchmark from the record of another plan: ``mine`` and ``theirs`` (the
    plans as JSON) must agree in everything but their ``seeds``, which a resumed run may extend.
    ``what`` names ``theirs`` in the message (a file's path, say).

    Raises:
        InputError: naming the fields that differ (resuming would mix two benchmarks).
    """
    mine, theirs = dict(mine), dict(theirs or {})
    mine.pop("seeds", None), theirs.pop("seeds", None)
    if mine != theirs:
        raise InputError(
            f"bench {benchmark} --resume: {what} ran another plan ({', '.join(changed_fields(mine, theirs))})"
        )
