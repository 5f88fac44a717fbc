"""The fuzzing campaign: its guard classifies crashes, hangs and memory bombs, and a short campaign
over every target finds no failure (the long one is ``factorydet bench fuzz``)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.evaluation.fuzz import (
    FAILURES,
    TARGETS,
    FuzzCase,
    fuzz_campaign,
    fuzz_markdown,
    make_case,
    run_guarded,
)
from factorydet_core.types import InputError


def misbehave(target: str, path: Path, context: object) -> None:
    """A runner that does what a broken loader might (the worker imports it by name)."""
    if target == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    elif target == "hang":
        time.sleep(60)
    elif target == "bomb":
        np.ones(3 * 2**30 // 8)  # 3 GB, over the 512 MB limit below
    elif target == "greedy":
        block = np.ones(700 * 2**20 // 8)  # 700 MB touched, under the address cap, over the limit
        del block
    elif target == "swallowed":
        # A reader's catch-all that turns the capped allocation's MemoryError into bad input.
        try:
            np.ones(3 * 2**30 // 8)
        except MemoryError as exc:
            raise InputError(f"{path}: cannot read: {type(exc).__name__}: {exc}") from None
    elif target == "hoard":
        # Holds 600 MB and waits: only the watchdog sees it before the timeout.
        blocks = [np.ones(60 * 2**20 // 8) for _ in range(10)]
        time.sleep(60)
        del blocks
    elif target == "traceback":
        raise KeyError("boxes")
    elif target == "two-lines":
        raise InputError("first line\nsecond line")
    elif target == "refused":
        raise InputError(f"{path}: not a point cloud")


def test_guard_classifies_every_way_a_case_can_end():
    names = ["ok", "segv", "refused", "hang", "bomb", "traceback", "greedy", "two-lines", "swallowed"]
    names += ["hoard", "ok"]
    cases = [FuzzCase(i, name, "none", f"/nowhere/{i}") for i, name in enumerate(names)]
    # A timeout well above the watchdog's reaction, so that the hoard is told from a hang on a busy
    # machine too (touching 600 MB took 3 s beside two benchmarks, more than 6 s beside three and
    # the fast tests).
    timeout_s = 10
    results = run_guarded(cases, misbehave, memory_limit_mb=512, timeout_s=timeout_s)
    outcomes = [r.outcome for r in results]
    assert outcomes == [
        "ok",
        "signal",
        "input_error",
        "timeout",
        "memory",
        "traceback",
        "memory",
        "traceback",
        "memory",  # an InputError hiding a MemoryError is still a memory bomb
        "memory",  # killed by the watchdog, long before the timeout
        "ok",  # a new worker took over after the crash, the hang and the kills
    ]
    assert results[1].detail == "SIGSEGV"
    assert "KeyError" in results[5].detail
    assert "MemoryError" in results[8].detail
    assert "watchdog" in results[9].detail and results[9].seconds < timeout_s  # before its timeout
    assert 512 < results[9].peak_mb < 1024


def test_mutations_are_deterministic_for_a_seed(tmp_path):
    seed_file = tmp_path / "seed.txt"
    seed_file.write_text("".join(f"{i}.5 {i * 2}.25 {i % 3}.0\n" for i in range(50)))

    def mutate(folder: str) -> list[tuple[str, bytes]]:
        rng = np.random.default_rng(4)
        cases = [make_case(i, "txt", seed_file, tmp_path / folder, rng) for i in range(20)]
        return [(c.mutation, Path(c.path).read_bytes()) for c in cases]

    first, second = mutate("a"), mutate("b")
    assert first == second
    assert len({data for _, data in first}) > 10  # the mutations differ from case to case
    assert all(data != seed_file.read_bytes() for _, data in first)


@pytest.mark.slow
def test_short_campaign_over_every_target_has_no_failure():
    record = fuzz_campaign(num_cases=3 * len(TARGETS), seed=11, memory_limit_mb=2048, timeout_s=60)
    assert sum(row["cases"] for row in record["targets"].values()) == 3 * len(TARGETS)
    assert record["num_failures"] == 0, record["failures"]
    assert sum(record["totals"][o] for o in FAILURES) == 0
    assert record["totals"]["input_error"] > 0  # the mutations do reach the checks
    assert "| **total** |" in fuzz_markdown(record)
