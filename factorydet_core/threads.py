"""One owner of the thread pools: numba's, torch's, OpenMP's (open3d, torch) and BLAS's.

Each of these libraries sizes its pool to the machine on its own, and OpenMP's threads spin while
they wait for work. On a 2-core machine with one other busy process (the app's server computing a
frame beside a benchmark, two test workers) the pools oversubscribe the cores and the spinning
threads take the cores the working ones need: a 9 s test took over 500 s. ``configure_threads``
gives every pool the same count and makes OpenMP's idle threads sleep instead of spin, so that two
processes share the machine in proportion rather than collapsing.

The count is, in order: the argument (``factorydet --threads N``), ``FACTORYDET_THREADS``,
``OMP_NUM_THREADS`` (what people already set for OpenMP programs), the cores this process may use.
"""

from __future__ import annotations

import os
import sys

from factorydet_core.types import InputError

THREADS_ENV = "FACTORYDET_THREADS"
MAX_THREADS = 256

_POOL_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
"""Read by OpenMP (open3d, torch), MKL, OpenBLAS and numba when they load."""


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which containers and ``taskset`` narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def thread_budget(num_threads: int | None = None) -> int:
    """The thread count every pool gets (see the module's docstring for the order)."""
    source = "--threads"
    if num_threads is None:
        for variable in (THREADS_ENV, "OMP_NUM_THREADS"):
            text = os.environ.get(variable, "").strip()
            if text:
                source = variable
                try:
                    num_threads = int(text)
                except ValueError:
                    raise InputError(f"{variable} must be a whole number of threads, got {text!r}") from None
                break
    if num_threads is None:
        return available_cores()
    if isinstance(num_threads, bool) or not 1 <= int(num_threads) <= MAX_THREADS:
        raise InputError(f"{source}: threads must be in [1, {MAX_THREADS}], got {num_threads!r}")
    return int(num_threads)


def configure_threads(num_threads: int | None = None) -> int:
    """Give every pool ``thread_budget(num_threads)`` threads; returns the count.

    Libraries not loaded yet read the environment when they load; those already loaded are set at
    run time (numba, torch, and BLAS or OpenMP pools through ``threadpoolctl``). OpenMP threads
    wait passively unless ``OMP_WAIT_POLICY`` says otherwise.
    """
    count = thread_budget(num_threads)
    for variable in _POOL_VARIABLES:
        os.environ[variable] = str(count)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
    if "torch" in sys.modules:
        import torch

        torch.set_num_threads(count)
    if "numpy" in sys.modules or "torch" in sys.modules:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # scikit-learn brings it; without it the environment still applies
            return count
        threadpool_limits(count)
    return count
