"""Compiled kernels: warming the cache, and calls from several threads at once."""

import threading

import numpy as np

from factorydet_core.boxes import fit_boxes
from factorydet_core.detection.warmup import warm_up


def test_warm_up_compiles_every_kernel_without_error():
    warm_up()  # fails if a kernel's signature drifted from what its wrapper passes


def test_kernels_called_from_several_threads_give_the_single_thread_result():
    # The app calls the library from viser's thread pool; numba's fallback threading layer aborts
    # on concurrent parallel launches, which the shared lock prevents.
    rng = np.random.default_rng(0)
    points = rng.normal(size=(4000, 3))
    lists = [rng.choice(4000, 300, replace=False) for _ in range(200)]
    expected = fit_boxes(points, lists)
    results = [None] * 6

    def work(slot):
        results[slot] = fit_boxes(points, lists)

    threads = [threading.Thread(target=work, args=(slot,)) for slot in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for result in results:
        np.testing.assert_array_equal(result, expected)
