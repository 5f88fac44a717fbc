"""One owner of the thread pools: every pool gets the same count, from the argument or the
environment, and OpenMP's idle threads sleep."""

import os
import subprocess
import sys

import pytest

from factorydet_core.threads import THREADS_ENV, available_cores, thread_budget
from factorydet_core.types import InputError

PROBE = """
from factorydet_core.threads import configure_threads
import sys, os
count = configure_threads({arg})
import numba, torch
from threadpoolctl import threadpool_info
print(count, numba.get_num_threads(), torch.get_num_threads(), os.environ["OMP_WAIT_POLICY"],
      sorted({{p["num_threads"] for p in threadpool_info()}}))
"""


def _probe(arg: str, env: dict[str, str]) -> list[str]:
    clean = {
        k: v for k, v in os.environ.items() if k not in (THREADS_ENV, "OMP_NUM_THREADS", "OMP_WAIT_POLICY")
    }
    done = subprocess.run(
        [sys.executable, "-c", PROBE.format(arg=arg)], env={**clean, **env}, capture_output=True, text=True,
        timeout=120, check=True,
    )  # fmt: skip
    return done.stdout.strip().split(maxsplit=4)


def test_every_pool_gets_the_environments_count_and_sleeps_when_idle():
    count, numba_threads, torch_threads, policy, pools = _probe("None", {THREADS_ENV: "1"})
    assert (count, numba_threads, torch_threads, policy) == ("1", "1", "1", "PASSIVE")
    assert pools == "[1]"  # BLAS and OpenMP pools loaded so far


def test_the_argument_beats_the_environment_and_a_set_policy_is_kept():
    count, _, torch_threads, policy, _ = _probe("2", {THREADS_ENV: "1", "OMP_WAIT_POLICY": "ACTIVE"})
    assert (count, torch_threads, policy) == ("2", "2", "ACTIVE")


def test_budget_order_and_bad_values(monkeypatch):
    monkeypatch.delenv(THREADS_ENV, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert thread_budget() == available_cores()
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert thread_budget() == 3
    monkeypatch.setenv(THREADS_ENV, "2")
    assert thread_budget() == 2 and thread_budget(5) == 5
    monkeypatch.setenv(THREADS_ENV, "many")
    with pytest.raises(InputError, match=THREADS_ENV):
        thread_budget()
    with pytest.raises(InputError, match="threads must be"):
        thread_budget(0)
