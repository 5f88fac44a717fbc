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

``fisher_vectors`` is the fast path: the soft assignment factorises per axis (15 exponentials per
point instead of 125), points are processed in cache-sized chunks aligned to set boundaries, and no
Python loop runs over sets. ``fisher_vectors_reference`` is the same maths written literally in
float64, one set at a time, for tests and the speed-up benchmark.
"""

from __future__ import annotations

import numpy as np
import torch

from .geometry import group_bounds
from .types import InputError, check_array

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
_CHUNK_POINTS = 1024  # keeps the (n, 7, 125) gradient blocks of one chunk in cache (measured best)
# Index views that broadcast a per-axis (n, 5) array onto the (n, 5, 5, 5) Gaussian grid.
_AXIS_VIEWS = (
    (slice(None), slice(None), None, None),
    (slice(None), None, slice(None), None),
    (slice(None), None, None, slice(None)),
)


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
    sorted_ids = set_ids[order]
    points = torch.from_numpy(np.ascontiguousarray(local_points[order], dtype=np.float32))
    counts = np.bincount(set_ids, minlength=num_sets)
    starts = np.concatenate([[0], np.cumsum(counts)])

    # Sums are kept in float64: a_sum = sum Q - T w cancels, and sums of symmetric sets are exactly 0,
    # where the signed square root would turn float32 rounding into a visible error.
    sums = torch.zeros((num_sets, 7, NUM_GAUSSIANS), dtype=torch.float64)
    maxs = torch.empty((num_sets, 7, NUM_GAUSSIANS))
    mins = torch.empty((num_sets, 6, NUM_GAUSSIANS))
    centres = torch.tensor(CENTRES, dtype=torch.float64)
    # Chunks end on set boundaries so that every set is reduced within one chunk.
    boundaries = np.searchsorted(starts, np.arange(0, len(points), _CHUNK_POINTS), side="right") - 1
    set_breaks = np.unique(np.concatenate([boundaries, [num_sets]]))
    with torch.no_grad():
        for first_set, end_set in zip(set_breaks[:-1], set_breaks[1:]):
            lo, hi = int(starts[first_set]), int(starts[end_set])
            chunk = points[lo:hi]
            local_ids = torch.from_numpy(sorted_ids[lo:hi] - first_set)
            num_local = int(end_set - first_set)
            # Per-axis terms (n, 3, 5) in float64: D^2 - 1 cancels near |D| = 1, and the signed
            # square root would turn a float32 rounding error there into a 1e-3 feature error.
            D64 = (chunk[:, :, None].double() - centres) / SIGMA
            q = torch.softmax(-0.5 * D64 * D64, dim=2).float()  # per-axis soft assignment
            D, D2m1 = D64.float(), (D64 * D64 - 1.0).float()
            Q = (q[:, 0, :, None, None] * q[:, 1, None, :, None] * q[:, 2, None, None, :]).reshape(-1, 125)
            grad = torch.empty((len(chunk), 7, NUM_GAUSSIANS))
            grad[:, 0] = Q
            for axis, view in enumerate(_AXIS_VIEWS):
                # D of Gaussian k along an axis depends only on that axis' centre index.
                grad[:, 1 + axis] = Q * D[:, axis][view].expand(-1, 5, 5, 5).reshape(-1, NUM_GAUSSIANS)
                grad[:, 4 + axis] = Q * D2m1[:, axis][view].expand(-1, 5, 5, 5).reshape(-1, NUM_GAUSSIANS)
            index = local_ids[:, None, None].expand_as(grad)
            sums[first_set:end_set].index_add_(0, local_ids, grad.double())
            maxs[first_set:end_set] = torch.full((num_local, 7, NUM_GAUSSIANS), -torch.inf).scatter_reduce_(
                0, index, grad, "amax"
            )
            mins[first_set:end_set] = torch.full((num_local, 6, NUM_GAUSSIANS), torch.inf).scatter_reduce_(
                0, index[:, 1:], grad[:, 1:], "amin"
            )

    # The gradient scales 1/sqrt(w), 1/sqrt(2w) and 1/T are positive, so they commute with max and
    # min and are applied once here; the alpha offset -w becomes -w (max) and -T w (sum).
    weight = 1.0 / NUM_GAUSSIANS
    T64 = torch.from_numpy(counts.astype(np.float64))[:, None, None]
    raw = torch.cat(
        [
            maxs[:, 0:1] - weight,
            (sums[:, 0:1] - T64 * weight).float(),  # cancels: float64 until here
            maxs[:, 1:4],
            mins[:, 0:3],
            sums[:, 1:4].float(),
            maxs[:, 4:7],
            mins[:, 3:6],
            sums[:, 4:7].float(),
        ],
        dim=1,
    )
    # One multiply for the positive scales 1/sqrt(w) (alpha, mu), 1/sqrt(2 w) (sigma) and 1/T.
    channel_scale = torch.full((NUM_CHANNELS,), 1.0 / np.sqrt(weight))
    channel_scale[11:] = 1.0 / np.sqrt(2.0 * weight)
    raw.mul_(channel_scale[None, :, None] / torch.from_numpy(counts.astype(np.float32))[:, None, None])
    if not normalize:
        return raw.numpy().reshape(num_sets, NUM_CHANNELS, *(GRID_SIZE,) * 3)
    # Signed square root and per-channel L2 (as ``normalize_fisher_vectors``), in place and in
    # float32: the raw values already carry their float64-accurate digits.
    tiny = raw.abs() < _EPS
    rooted = torch.copysign(raw.abs().sqrt_(), raw).masked_fill_(tiny, 0.0)
    norms = torch.linalg.vector_norm(rooted, dim=2, keepdim=True).clamp_(min=np.sqrt(_EPS))
    return rooted.div_(norms).numpy().reshape(num_sets, NUM_CHANNELS, *(GRID_SIZE,) * 3)


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
