"""Cropping, pruning and floor removal of merged clouds (paper section 3.1, before voxelisation).

Every function takes a ``MergedCloud`` and returns a new one (or a mask); the input is never changed.
"""

from __future__ import annotations

import numpy as np

from factorydet_core.types import InputError, MergedCloud


def crop(
    cloud: MergedCloud,
    *,
    radius: float | None = None,
    box_min: tuple[float, float, float] | None = None,
    box_max: tuple[float, float, float] | None = None,
) -> MergedCloud:
    """Keep the points within ``radius`` metres of the vehicle (horizontal distance) and/or inside an
    axis-aligned box of the vehicle frame.

    Args:
        cloud: points in the vehicle frame.
        radius: horizontal range limit, metres; ``None`` for no limit.
        box_min: (3,) lower corner of the kept box, metres; ``None`` for no lower bound.
        box_max: (3,) upper corner, metres; ``None`` for no upper bound.
    """
    mask = np.ones(cloud.num_points, bool)
    if radius is not None:
        if not radius > 0:
            raise InputError(f"crop: radius must be > 0 m, got {radius}")
        mask &= np.hypot(cloud.points[:, 0], cloud.points[:, 1]) <= radius
    if box_min is not None:
        mask &= (cloud.points >= np.asarray(box_min, np.float32)).all(axis=1)
    if box_max is not None:
        mask &= (cloud.points <= np.asarray(box_max, np.float32)).all(axis=1)
    return cloud.select(mask)


MIN_CELL_M = 0.001
"""The smallest down-sampling cell, metres: below a millimetre every point is its own cell anyway,
and a tiny cell would overflow the cell indices of a far point (the bound of ``prune_m``, and the
finest cell ``cap_points`` prunes with)."""


def prune(cloud: MergedCloud, voxel_size: float) -> MergedCloud:
    """Voxel down-sampling: keep one measured point per ``voxel_size`` cell (the one closest to the
    cell's mean), so that per-point attributes (sensor, instance) stay true.

    Args:
        cloud: the cloud to thin.
        voxel_size: cell edge, metres; 0 keeps every point.
    """
    if voxel_size == 0 or cloud.num_points == 0:
        return cloud
    if not voxel_size > 0:
        raise InputError(f"prune: voxel_size must be >= 0 m, got {voxel_size}")
    cell_ids, counts = _cell_ids(np.floor(cloud.points / voxel_size).astype(np.int64))
    means = np.stack([np.bincount(cell_ids, cloud.points[:, axis], len(counts)) for axis in range(3)], axis=1)
    means /= counts[:, None]
    dist = np.linalg.norm(cloud.points - means[cell_ids], axis=1)
    # For each cell, the point with the smallest distance: sort by (cell, distance), take firsts.
    order = np.lexsort((dist, cell_ids))
    first = np.ones(len(order), bool)
    first[1:] = cell_ids[order][1:] != cell_ids[order][:-1]
    keep = np.zeros(cloud.num_points, bool)
    keep[order[first]] = True
    return cloud.select(keep)


def cap_points(cloud: MergedCloud, max_points: int | None, voxel_size: float) -> MergedCloud:
    """``cloud``, which ``prune`` left at ``voxel_size`` (0: not pruned), pruned again with the
    finest cell from ``voxel_size`` up that leaves at most ``max_points`` points; ``cloud`` itself
    when it has no more than that (or ``max_points`` is ``None``).

    Surfaces hold points by their area, so the cell grows by the square root of the excess at each
    try (at least by 5%); each try thins the previous one's cloud, so a few passes over ever fewer
    points do it.
    """
    if max_points is None or cloud.num_points <= max_points:
        return cloud
    if max_points < 1:
        raise InputError(f"cap_points: max_points must be >= 1, got {max_points}")
    if voxel_size <= 0:
        # Unpruned: start from the spacing of the points spread over the faces of their bounding
        # box (scans are surfaces), where pruning removes little.
        dx, dy, dz = np.maximum(np.ptp(cloud.points, axis=0).astype(np.float64), 1e-3)
        voxel_size = float(np.sqrt((dx * dy + dx * dz + dy * dz) / cloud.num_points))
        cloud = prune(cloud, voxel_size)
    cell = max(voxel_size, MIN_CELL_M)
    while cloud.num_points > max_points:
        cell *= max(1.05, float(np.sqrt(cloud.num_points / max_points)))
        cloud = prune(cloud, cell)
    return cloud


def _cell_ids(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the id of each of (N, 3) integer cells among the distinct cells in lexicographic order,
    and (C,) each cell's count (``np.unique(cells, axis=0)``'s inverse and counts, computed on one
    integer key per cell: several times faster)."""
    lo = cells.min(axis=0)
    span = cells.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:  # a key would overflow: the slow way
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        return inverse.reshape(-1), counts
    offset = cells - lo
    key = (offset[:, 0] * span[1] + offset[:, 1]) * span[2] + offset[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return inverse.reshape(-1), counts


def floor_mask(
    cloud: MergedCloud,
    *,
    distance_m: float = 0.06,
    max_tilt_deg: float = 10.0,
    search_below_m: float = 0.5,
    ransac_iterations: int = 200,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Find the floor plane (RANSAC among the lowest points, normal near +z).

    Args:
        cloud: points in a z-up frame.
        distance_m: points less than this above the plane are floor, and so is everything below it
            (range noise and reflections through the floor).
        max_tilt_deg: largest accepted angle between the plane normal and +z.
        search_below_m: RANSAC looks at points within this height above the lowest percentile.
        ransac_iterations: plane hypotheses tried.
        seed: RANSAC seed (the same input and seed give the same plane).

    Returns:
        ``(mask, plane)``: (N,) bool, True on floor points, and the plane (4,) as (a, b, c, d) with
        a x + b y + c z + d = 0 and c > 0; an all-False mask and NaNs when no floor is found.
    """
    no_floor = np.zeros(cloud.num_points, bool), np.full(4, np.nan)
    if cloud.num_points < 3:
        return no_floor
    z = cloud.points[:, 2]
    low_points = cloud.points[z <= np.percentile(z, 1) + search_below_m].astype(np.float64)
    if len(low_points) < 3:
        return no_floor
    # RANSAC in numpy with a seeded generator (open3d's segment_plane is not reproducible even when
    # seeded), on at most 20k of the low points; planes tilted more than max_tilt_deg are skipped.
    rng = np.random.default_rng(seed)
    if len(low_points) > 20_000:
        low_points = low_points[rng.choice(len(low_points), 20_000, replace=False)]
    triples = low_points[rng.integers(0, len(low_points), size=(ransac_iterations, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    valid = lengths > 1e-9
    normals = normals[valid] / lengths[valid, None]
    normals *= np.sign(normals[:, 2:3]) + (normals[:, 2:3] == 0)
    level = normals[:, 2] >= np.cos(np.radians(max_tilt_deg))
    normals, anchors = normals[level], triples[valid][level, 0]
    if not len(normals):
        return no_floor
    offsets = -np.einsum("kd,kd->k", normals, anchors)
    inlier_counts = (np.abs(low_points @ normals.T + offsets) <= distance_m).sum(axis=0)
    best = int(np.argmax(inlier_counts))
    inliers = low_points[np.abs(low_points @ normals[best] + offsets[best]) <= distance_m]
    if len(inliers) < 3:
        return no_floor
    # Least-squares refit on the inliers (RANSAC's plane passes through 3 of them).
    centroid = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centroid, full_matrices=False)[2][2]
    normal = normal if normal[2] > 0 else -normal
    if np.degrees(np.arccos(np.clip(normal[2], -1, 1))) > max_tilt_deg:
        return no_floor
    plane = np.append(normal, -normal @ centroid)
    distance = cloud.points.astype(np.float64) @ plane[:3] + plane[3]
    return distance <= distance_m, plane


def remove_floor(cloud: MergedCloud, *, distance_m: float = 0.06) -> MergedCloud:
    """The cloud without its floor points (see ``floor_mask``); unchanged when no floor is found."""
    mask, _ = floor_mask(cloud, distance_m=distance_m)
    return cloud.select(~mask)
