"""Compile every numba kernel once: ``python -m factorydet_core.detection.warmup``."""

from __future__ import annotations


def warm_up() -> None:
    """Compile every kernel into numba's on-disk cache (about half a minute on 2 cores), so that
    the first frame a new install processes does not wait for it; ``make`` runs it after install."""
    import numpy as np

    from factorydet_core.boxes import fit_boxes
    from factorydet_core.detection.box_quality import _best_in_sets, _compile_row_walk, _compile_walk
    from factorydet_core.jit import run_kernel
    from factorydet_core.proposals.features import fisher_vectors
    from factorydet_core.proposals.segment import _absorb_small, merge_patches
    from factorydet_core.proposals.visibility import box_visibility, free_space
    from factorydet_core.types import MergedCloud

    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (12, 3))
    fit_boxes(points, [np.arange(12)])
    fisher_vectors(points, np.zeros(12, np.int64))
    patch_ids, source, target = np.arange(12) % 4, np.arange(11), np.arange(1, 12)
    merge_patches(points, patch_ids, source, target)
    _absorb_small(patch_ids, source, target, min_points=4)
    _best_in_sets(np.array([0, 0, 1]), np.zeros(3), 1)
    for walk in (_compile_walk, _compile_row_walk):
        run_kernel(
            walk, points, np.zeros(1, np.int64), np.full(1, -1, np.int32), np.zeros(2, np.int32),
            np.zeros(1), np.zeros(1), np.zeros(12),
        )  # fmt: skip
    cloud = MergedCloud(points, np.zeros(12, np.int16), np.zeros(12, np.int64), np.eye(4)[None])
    box_visibility(free_space(cloud, radius_m=2.0), np.zeros((1, 7)))


if __name__ == "__main__":
    warm_up()
