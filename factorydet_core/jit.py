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


def warm_up() -> None:
    """Compile every kernel into numba's on-disk cache (about half a minute on 2 cores), so that
    the first frame a new install processes does not wait for it; ``make`` runs it after install."""
    import numpy as np

    from .box_quality import _compile_walk
    from .boxes import fit_boxes
    from .features import fisher_vectors
    from .segment import _absorb_small, merge_patches
    from .types import MergedCloud
    from .visibility import box_visibility, free_space

    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (12, 3))
    fit_boxes(points, [np.arange(12)])
    fisher_vectors(points, np.zeros(12, np.int64))
    patch_ids, source, target = np.arange(12) % 4, np.arange(11), np.arange(1, 12)
    merge_patches(points, patch_ids, source, target)
    _absorb_small(patch_ids, source, target, min_points=4)
    run_kernel(
        _compile_walk, points, np.zeros(1, np.int64), np.full(1, -1, np.int32), np.zeros((1, 2), np.int32),
        np.zeros(1), np.zeros(1), 0.0,
    )  # fmt: skip
    cloud = MergedCloud(points, np.zeros(12, np.int16), np.zeros(12, np.int64), np.eye(4)[None])
    box_visibility(free_space(cloud, radius_m=2.0), np.zeros((1, 7)))


if __name__ == "__main__":
    warm_up()
