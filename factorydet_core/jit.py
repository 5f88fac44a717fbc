"""Kernels compiled by numba on first use, and run one at a time.

numba is imported only when a kernel first runs (importing the library stays fast), compiled
kernels are cached on disk beside the module (``cache=True``), and every launch holds one lock: the
app calls the library from several threads, and numba's fallback threading layer (workqueue, where
OpenMP is missing) aborts the process on concurrent parallel launches of any kernel.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable

_lock = threading.Lock()
_compiled: dict[Callable[[], Callable], Callable] = {}


def run_kernel(build: Callable[[], Callable], *args):
    """Call the kernel ``build()`` returns (built once per process) with ``args``."""
    with _lock:
        kernel = _compiled.get(build)
        if kernel is None:
            import numba

            numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
            kernel = _compiled[build] = build()
        with warnings.catch_warnings():
            # numba names every threading layer it could not load (an old TBB, say) on first launch.
            warnings.filterwarnings("ignore", message=".*threading layer.*")
            return kernel(*args)
