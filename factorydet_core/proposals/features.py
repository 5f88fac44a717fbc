"""3D modified Fisher vectors (3DmFV, Ben-Shabat et al. 2017) of point sets (paper section 3.2).

Each point set (the points of one voxel, or of one segment) is first mapped into [-1, 1]^3. A fixed
grid of 5 x 5 x 5 isotropic Gaussians (centres -0.8 .. 0.8 per axis, equal weights, sigma 0.2)
describes it by 20 statistics per Gaussian:

    [a_max, a_sum, m_max xyz, m_min xyz, m_sum xyz, s_max xyz, s_min xyz, s_sum xyz]

with, for point t and Gaussian k, soft assignment Q_tk = softmax_k(-|p_t - mu_k|^2 / (2 sigma^2)),
D = (p - mu) / sigma, a = (Q - w) / sqrt(w), m = Q D / sqrt(w), s = Q (D^2 - 1) / sqrt(2 w); every
aggregate is divided by the set's point count T. Then a signed square root and an L2 normalisation
of each of the 20 channels across the 125 Gaussians. The result is laid out as (20, 5, 5, 5) with
Gaussian k = i * 25 + j * 5 + l for centres (c_i, c_j, c_l) along (x, y, z).

``fisher_vectors`` is the fast path: one compiled kernel, sets spread over the cores, the soft
assignment factorised per axis (15 exponentials per point instead of 125), every statistic of a set
accumulated in float64 in one pass over its points, and no Python loop over sets.
``fisher_vectors_reference`` is the same maths written literally in float64, one set at a time,
for tests and the speed-up benchmark.
"""

from __future__ import annotations

import numpy as np

from factorydet_core.geometry import group_bounds
from factorydet_core.jit import run_kernel
from factorydet_core.types import InputError, check_array

GRID_SIZE = 5
"""Gaussians per axis."""
NUM_GAUSSIANS = GRID_SIZE**3
NUM_CHANNELS = 20
SIGMA = 0.2
"""Standard deviation of every Gaussian (variance 0.04), in the [-1, 1] cube's units."""
CENTRES = np.linspace(-0.8, 0.8, GRID_SIZE)
"""(5,) Gaussian centres along each axis."""
CHANNEL_NAMES: tuple[str, ...] = (
    "a_max", "a_sum",
    "m_max_x", "m_max_y", "m_max_z", "m_min_x", "m_min_y", "m_min_z", "m_sum_x", "m_sum_y", "m_sum_z",
    "s_max_x", "s_max_y", "s_max_z", "s_min_x", "s_min_y", "s_min_z", "s_sum_x", "s_sum_y", "s_sum_z",
)  # fmt: skip
_EPS = 1e-12


def gaussian_means() -> np.ndarray:
    """(125, 3) float64 Gaussian centres in Gaussian order k = i * 25 + j * 5 + l."""
    grid = np.meshgrid(CENTRES, CENTRES, CENTRES, indexing="ij")
    return np.stack([axis.ravel() for axis in grid], axis=1)


def normalize_fisher_vectors(raw: np.ndarray) -> np.ndarray:
    """Signed square root, then per-channel L2 normalisation across the Gaussians.

    Args:
        raw: (S, 20, 125) or (S, 20, 5, 5, 5) aggregated statistics.

    Returns:
        (S, 20, 5, 5, 5) float32 normalised Fisher vectors.
    """
    raw = np.asarray(raw)
    flat = raw.reshape(len(raw), NUM_CHANNELS, NUM_GAUSSIANS)
    return _signed_sqrt_l2(flat).astype(np.float32).reshape(len(raw), NUM_CHANNELS, *(GRID_SIZE,) * 3)


def _signed_sqrt_l2(flat: np.ndarray) -> np.ndarray:
    """(S, 20, 125) -> signed square root and per-channel L2 normalisation.

    Magnitudes under 1e-12 count as zero. The TF original clamps them to 1e-12 but keeps their sign,
    which turns a channel of underflowed values (exactly 0 in float32, 1e-40 in float64) into
    arbitrary +-1/sqrt(125) entries; zeroing them keeps such channels at 0 in any precision.
    """
    magnitude = np.abs(flat)
    rooted = np.where(magnitude >= _EPS, np.sign(flat) * np.sqrt(magnitude), 0.0)
    norms = np.sqrt(np.maximum((rooted**2).sum(axis=2, keepdims=True), _EPS))
    return rooted / norms


def _check_sets(local_points: np.ndarray, set_ids: np.ndarray, num_sets: int | None) -> int:
    check_array(local_points, (None, 3), name="local_points", finite=True)
    check_array(set_ids, (len(local_points),), name="set_ids")
    if len(set_ids) and set_ids.min() < 0:
        raise InputError("set_ids: ids must be >= 0")
    num_sets = int(set_ids.max()) + 1 if num_sets is None and len(set_ids) else int(num_sets or 0)
    if len(set_ids) and set_ids.max() >= num_sets:
        raise InputError(f"set_ids: ids must be < num_sets={num_sets}")
    if num_sets and np.bincount(set_ids, minlength=num_sets).min() == 0:
        raise InputError("set_ids: every set needs at least one point")
    return num_sets


def fisher_vectors(
    local_points: np.ndarray,
    set_ids: np.ndarray,
    num_sets: int | None = None,
    *,
    normalize: bool = True,
) -> np.ndarray:
    """3DmFV of many point sets at once.

    Args:
        local_points: (N, 3) points already mapped into the [-1, 1] cube of their set (points outside
            it are allowed; the Gaussians simply see them far away).
        set_ids: (N,) int, the set of each point, in [0, num_sets). Every set needs a point.
        num_sets: number of sets S; ``set_ids.max() + 1`` by default.
        normalize: apply the signed square root and per-channel L2 normalisation.

    Returns:
        (S, 20, 5, 5, 5) float32 Fisher vectors (the raw aggregates when ``normalize`` is False).
    """
    num_sets = _check_sets(local_points, set_ids, num_sets)
    if num_sets == 0:
        return np.zeros((0, NUM_CHANNELS, *(GRID_SIZE,) * 3), np.float32)
    order = np.argsort(set_ids, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(set_ids, minlength=num_sets))]).astype(np.int64)
    out = np.empty((num_sets, NUM_CHANNELS, NUM_GAUSSIANS), np.float32)
    run_kernel(
        _compile_fisher_vectors,
        np.ascontiguousarray(local_points[order], np.float64),
        starts,
        CENTRES.astype(np.float64),
        bool(normalize),
        out,
    )
    return out.reshape(num_sets, NUM_CHANNELS, *(GRID_SIZE,) * 3)


def _compile_fisher_vectors():
    import math

    import numba

    weight = 1.0 / NUM_GAUSSIANS
    # The positive gradient scales 1/sqrt(w) (alpha, mu) and 1/sqrt(2 w) (sigma) commute with max
    # and min, so they and 1/T are applied once per set, not per point.
    channel_scale = np.full(NUM_CHANNELS, 1.0 / np.sqrt(weight))
    channel_scale[11:] = 1.0 / np.sqrt(2.0 * weight)
    # Where each output channel comes from: (statistic 0 max / 1 min / 2 sum, gradient term 0..6)
    # for [a_max, a_sum, m_max xyz, m_min xyz, m_sum xyz, s_max xyz, s_min xyz, s_sum xyz]; the
    # gradient terms are Q, Q D_xyz and Q (D_xyz^2 - 1).
    source = np.array(
        [(0, 0), (2, 0)]
        + [(stat, term) for first in (1, 4) for stat in (0, 1, 2) for term in range(first, first + 3)],
        np.int64,
    )
    num_gaussians, grid, sigma, eps = NUM_GAUSSIANS, GRID_SIZE, SIGMA, _EPS

    @numba.njit(parallel=True, cache=True, nogil=True)
    def fisher(points, starts, centres, normalize, out):
        for s in numba.prange(starts.shape[0] - 1):
            lo, hi = starts[s], starts[s + 1]
            # stats[0] max, stats[1] min, stats[2] sum of the 7 gradient terms per Gaussian, float64:
            # a_sum = sum Q - T w cancels, and sums of symmetric sets are exactly 0, where the signed
            # square root would turn a rounding error into a visible one.
            stats = np.empty((3, 7, num_gaussians))
            stats[0] = -np.inf
            stats[1] = np.inf
            stats[2] = 0.0
            q = np.empty((3, grid))
            d = np.empty((3, grid))
            d2m1 = np.empty((3, grid))
            terms = np.empty(7)
            for t in range(lo, hi):
                # The soft assignment factorises per axis: 15 exponentials per point, not 125.
                for axis in range(3):
                    top = -np.inf
                    for c in range(grid):
                        offset = (points[t, axis] - centres[c]) / sigma
                        d[axis, c] = offset
                        d2m1[axis, c] = offset * offset - 1.0
                        q[axis, c] = -0.5 * offset * offset
                        top = max(top, q[axis, c])
                    total = 0.0
                    for c in range(grid):
                        q[axis, c] = math.exp(q[axis, c] - top)
                        total += q[axis, c]
                    for c in range(grid):
                        q[axis, c] /= total
                for i in range(grid):
                    for j in range(grid):
                        q_ij = q[0, i] * q[1, j]
                        for k in range(grid):
                            g = (i * grid + j) * grid + k
                            assignment = q_ij * q[2, k]
                            terms[0] = assignment
                            terms[1] = assignment * d[0, i]
                            terms[2] = assignment * d[1, j]
                            terms[3] = assignment * d[2, k]
                            terms[4] = assignment * d2m1[0, i]
                            terms[5] = assignment * d2m1[1, j]
                            terms[6] = assignment * d2m1[2, k]
                            for term in range(7):
                                value = terms[term]
                                if value > stats[0, term, g]:
                                    stats[0, term, g] = value
                                if value < stats[1, term, g]:
                                    stats[1, term, g] = value
                                stats[2, term, g] += value
            num_points = hi - lo
            stats[0, 0] -= weight  # a = (Q - w) / sqrt(w): max(a) and sum(a) shift by w and T w
            stats[2, 0] -= num_points * weight
            for channel in range(source.shape[0]):
                scale = channel_scale[channel] / num_points
                stat, term = source[channel, 0], source[channel, 1]
                if not normalize:
                    for g in range(num_gaussians):
                        out[s, channel, g] = stats[stat, term, g] * scale
                    continue
                # Signed square root, then L2 over the Gaussians; magnitudes under eps are 0.
                norm = 0.0
                rooted = np.empty(num_gaussians)
                for g in range(num_gaussians):
                    value = stats[stat, term, g] * scale
                    magnitude = abs(value)
                    rooted[g] = 0.0 if magnitude < eps else math.copysign(math.sqrt(magnitude), value)
                    norm += rooted[g] * rooted[g]
                norm = math.sqrt(max(norm, eps))
                for g in range(num_gaussians):
                    out[s, channel, g] = rooted[g] / norm

    return fisher


def fisher_vectors_reference(local_points: np.ndarray, set_ids: np.ndarray, num_sets: int | None = None):
    """Float64 3DmFV written straight from the formulas, one set at a time (slow; for tests).

    Same arguments and result layout as ``fisher_vectors``.
    """
    num_sets = _check_sets(local_points, set_ids, num_sets)
    mu = gaussian_means()  # (K, 3)
    w = np.full(NUM_GAUSSIANS, 1.0 / NUM_GAUSSIANS)
    out = np.zeros((num_sets, NUM_CHANNELS, NUM_GAUSSIANS))
    for s in range(num_sets):
        p = local_points[set_ids == s].astype(np.float64)  # (T, 3)
        T = len(p)
        sq = ((p[:, None, :] - mu[None]) ** 2).sum(axis=2)  # (T, K)
        logits = -sq / (2 * SIGMA**2)
        logits -= logits.max(axis=1, keepdims=True)
        Q = np.exp(logits) * w
        Q /= Q.sum(axis=1, keepdims=True)
        D = (p[:, None, :] - mu[None]) / SIGMA  # (T, K, 3)
        a = (Q - w) / np.sqrt(w)
        m = Q[:, :, None] * D / np.sqrt(w)[None, :, None]
        g = Q[:, :, None] * (D**2 - 1) / np.sqrt(2 * w)[None, :, None]
        feats = [a.max(0) / T, a.sum(0) / T]
        feats += list((m.max(0) / T).T) + list((m.min(0) / T).T) + list((m.sum(0) / T).T)
        feats += list((g.max(0) / T).T) + list((g.min(0) / T).T) + list((g.sum(0) / T).T)
        out[s] = np.stack(feats)
    rooted = _signed_sqrt_l2(out)
    return rooted.reshape(num_sets, NUM_CHANNELS, *(GRID_SIZE,) * 3)


def to_unit_sphere(points: np.ndarray, set_ids: np.ndarray, num_sets: int | None = None) -> np.ndarray:
    """Centre each set on its bounding-box centre and scale it so its farthest point lies on the unit
    sphere (the input normalisation of 3DmFV-Net). A single-point set maps to the origin.

    Args:
        points: (N, 3) points.
        set_ids: (N,) set of each point.

    Returns:
        (N, 3) float32 points in the unit ball.
    """
    num_sets = _check_sets(points, set_ids, num_sets)
    points = points.astype(np.float64)
    lo, hi = group_bounds(points, set_ids, num_sets)
    centred = points - ((lo + hi) / 2)[set_ids]
    radius = np.zeros(num_sets)
    np.maximum.at(radius, set_ids, np.linalg.norm(centred, axis=1))
    radius = np.where(radius > 0, radius, 1.0)
    return (centred / radius[set_ids, None]).astype(np.float32)
