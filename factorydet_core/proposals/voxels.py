"""Sparse voxel grid and per-voxel 3DmFV features (paper sections 3.1 and 3.2)."""

from __future__ import annotations

import numpy as np

from factorydet_core.proposals.features import fisher_vectors
from factorydet_core.types import InputError, MergedCloud, VoxelGrid, check_array

DEFAULT_VOXEL_SIZE = 0.2
"""The paper's best cell size (its Fig. 7), metres."""


def voxelize(points: np.ndarray, voxel_size: float = DEFAULT_VOXEL_SIZE) -> VoxelGrid:
    """Sparse grid of the occupied cells.

    Args:
        points: (N, 3) points, metres (a ``MergedCloud.points``).
        voxel_size: cell edge, metres.

    Returns:
        The grid; cell (0, 0, 0) starts at the floor of the points' minimum over ``voxel_size``, so
        the same point always lands in the same cell whatever else is in the cloud.
    """
    check_array(points, (None, 3), name="voxelize points", finite=True)
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InputError(f"voxelize: voxel_size must be a positive number of metres, got {voxel_size}")
    if len(points) == 0:
        return VoxelGrid(
            voxel_size=float(voxel_size),
            origin=np.zeros(3),
            coords=np.zeros((0, 3), np.int32),
            point_voxel_ids=np.zeros(0, np.int64),
            num_points=np.zeros(0, np.int64),
        )
    cells = np.floor(points.astype(np.float64) / voxel_size).astype(np.int64)
    cell_min = cells.min(axis=0)
    coords, point_voxel_ids, counts = np.unique(
        cells - cell_min, axis=0, return_inverse=True, return_counts=True
    )
    return VoxelGrid(
        voxel_size=float(voxel_size),
        origin=cell_min * float(voxel_size),
        coords=coords.astype(np.int32),
        point_voxel_ids=point_voxel_ids.reshape(-1).astype(np.int64),
        num_points=counts.astype(np.int64),
    )


def voxel_local_points(points: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """(N, 3) float32: each point in its voxel's [-1, 1]^3 frame, (p - centre) / (size / 2)."""
    centres = grid.centres[grid.point_voxel_ids]
    return ((points.astype(np.float64) - centres) / (grid.voxel_size / 2)).astype(np.float32)


def voxel_fisher_vectors(cloud: MergedCloud, grid: VoxelGrid) -> np.ndarray:
    """Per-voxel 3DmFV (see ``features``).

    Args:
        cloud: the cloud the grid was built from.
        grid: its voxel grid.

    Returns:
        (V, 20, 5, 5, 5) float32 Fisher vectors, one per occupied voxel. A voxel with a single point
        gets a valid (if uninformative) vector.
    """
    if len(grid.point_voxel_ids) != cloud.num_points:
        raise InputError(
            f"voxel_fisher_vectors: grid was built from {len(grid.point_voxel_ids)} points, "
            f"cloud has {cloud.num_points}"
        )
    return fisher_vectors(voxel_local_points(cloud.points, grid), grid.point_voxel_ids, grid.num_voxels)


def voxel_colors(cloud: MergedCloud, grid: VoxelGrid, voxel_features: np.ndarray | None = None) -> np.ndarray:
    """(V, 3) uint8 colours of the voxels by their 3DmFV (``fisher_vector_colors`` of
    ``voxel_fisher_vectors``, computed unless given): what a viewer keeps of them, 3 bytes a voxel
    instead of 10 kB."""
    if voxel_features is None:
        voxel_features = voxel_fisher_vectors(cloud, grid)
    return fisher_vector_colors(voxel_features)


def fisher_vector_colors(features: np.ndarray, seed: int = 0) -> np.ndarray:
    """(V, 3) uint8 colours: a 3-component PCA projection of (V, 20, 5, 5, 5) features, so that voxels
    with similar local shape get similar colours."""
    if len(features) == 0:
        return np.zeros((0, 3), np.uint8)
    flat = features.reshape(len(features), -1).astype(np.float64)
    flat = flat - flat.mean(axis=0)
    rng = np.random.default_rng(seed)
    if len(flat) > 4000:  # the principal axes of a random subset are as good and much cheaper
        subset = flat[rng.choice(len(flat), 4000, replace=False)]
    else:
        subset = flat
    # Randomised PCA (a range finder with 2 power iterations): a full SVD of a (4000, 2500) matrix
    # takes tens of seconds, this takes milliseconds.
    basis = np.linalg.qr(subset @ rng.standard_normal((subset.shape[1], 10)))[0]
    for _ in range(2):
        basis = np.linalg.qr(subset @ (subset.T @ basis))[0]
    _, _, vt = np.linalg.svd(basis.T @ subset, full_matrices=False)
    projected = flat @ vt[:3].T
    if projected.shape[1] < 3:
        projected = np.pad(projected, ((0, 0), (0, 3 - projected.shape[1])))
    lo, hi = np.percentile(projected, [2, 98], axis=0)
    scaled = np.clip((projected - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return (scaled * 255).astype(np.uint8)
