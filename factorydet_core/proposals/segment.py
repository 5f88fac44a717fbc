"""Over-segmentation into local patches by l0 cut pursuit, then merging into object segments
(paper section 3.3).

1. Local geometric features per point (``pgeof``: linearity, planarity, scattering, verticality,
   from the k nearest neighbours).
2. A k-nearest-neighbour graph; edges longer than ``max_edge_m`` are dropped, so objects separated
   by a gap are never in one patch (far from the viewpoint the limit may grow with range,
   ``max_edge_per_range``, as a scanner's returns spread).
3. The l0 (Potts) partition of the features on that graph (``cut-pursuit-py``). Its
   ``reg_strength`` argument is ignored by the library, so the regularisation is folded into the edge
   weights: w_uv = reg / (1 + d_uv / mean d).
4. Patches with fewer than ``min_patch_points`` points join the neighbour they share most edges with.
5. Adjacent patches merge, strongest contact first, while their contact strength (edges between them
   over the smaller patch's boundary edges) is at least ``merge_threshold`` and their union still
   fits an object (``max_object_size_m``). Every union formed along the way is kept in
   ``merge_history``: intermediate unions are proposals too, because the right level of merging
   differs between a forklift and a box on a pallet.
6. More candidates from diversity: the same merging with smaller size limits
   (``proposal_scales_m`` on the longest side, ``proposal_sizes_m`` on side and height: crate-sized
   passes that cannot join a crate to the one it stands on before its own faces are joined), and
   cut pursuits on the graph of patches at coarser regularisations (``patch_regularizations``).
   Surfaces bigger than any object (walls, rack beams) are found by a first, geometry-only cut
   pursuit and kept out of all of this (``structure_size_m``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from factorydet_core.geometry import group_bounds
from factorydet_core.jit import run_kernel
from factorydet_core.proposals.cut_pursuit import cut_pursuit
from factorydet_core.settings_check import Setting, short_repr
from factorydet_core.types import InputError, Segmentation, check_array

MAX_EXTRA_PASSES = 16
"""The most entries of ``proposal_scales_m``, ``proposal_sizes_m`` and ``patch_regularizations``:
each is one more merge pass or cut pursuit per frame (the defaults have 2, 5 and 3)."""

_SETTINGS: dict[str, Setting] = {
    # Neighbour counts: the k-NN search holds max(k_features, k_graph) + 1 neighbours per point and
    # the cut pursuit k_graph edges per point. Measured on 100,000 points: 3 s and 0.24 GB at the
    # defaults, 8 s and 0.35 GB at k_features 200, 5 s and 0.46 GB at k_graph 100.
    "k_features": Setting(int, 1, 200),
    "k_graph": Setting(int, 1, 100),
    "max_edge_m": Setting(float, 0.0, 10.0, low_open=True),
    # 1 m per metre of range is already far beyond any scanner's beam spread (0.02 for the AGV's).
    "max_edge_per_range": Setting(float, 0.0, 1.0),
    # The edge weights are float32: keep them far from overflowing (the presets use 0.05 to 1).
    "regularization": Setting(float, 0.0, 100.0, low_open=True),
    "spatial_weight": Setting(float, 0.0, 100.0),
    "min_patch_points": Setting(int, 1, 1_000_000),
    "merge_threshold": Setting(float, 0.0, 1.0),
    "convexity": Setting(bool),
    "split_structure": Setting(bool),
    "smooth_angle_deg": Setting(float, 0.0, 90.0),
    "step_m": Setting(float, 0.0, 10.0),
}
"""The scalar settings of ``SegmentationParams`` and what each may hold."""

_OBJECT_LENGTH = Setting(float, 0.0, 100.0, low_open=True)
"""A size limit of a merged segment, metres: objects are metres long, not hundreds."""
_STRUCTURE_LENGTH = Setting(float, 0.0, 1000.0, low_open=True)
"""A size of structure (walls, racks), metres: up to the largest hall the crop lets in."""


@dataclasses.dataclass(frozen=True)
class SegmentationParams:
    """Settings of ``segment``; the defaults were picked with ``factorydet bench pipeline``."""

    k_features: int = 20
    """Neighbours for the local geometric features."""
    k_graph: int = 10
    """Neighbours per point in the adjacency graph."""
    max_edge_m: float = 0.3
    """Graph edges longer than this are cut: a gap this wide always separates segments."""
    max_edge_per_range: float = 0.0
    """Besides ``max_edge_m``, an edge may be this long per metre of horizontal distance of its
    nearer end from the viewpoint (the vehicle frame's origin). A scanning sensor's returns spread
    with range: the AGV's beams are 1.2 degrees apart vertically, 0.31 m at 15 m, so a fixed
    0.3 m limit cut far objects into slices (a forklift at 15 m into its mast and its body).
    0 keeps one limit everywhere (static scans without a viewpoint)."""
    regularization: float = 0.05
    """Cut-pursuit regularisation (lambda): larger gives fewer, bigger patches."""
    spatial_weight: float = 3.0
    """Weight of the xyz coordinates (per metre) next to the geometric features in the data term;
    > 0 keeps patches compact."""
    min_patch_points: int = 3
    """Smaller patches are absorbed by their best-connected neighbour. Keep it small: absorbing
    10-point patches put crates' corners into their neighbours (measured: patch purity fell)."""
    merge_threshold: float = 0.15
    """Least contact strength (in [0, 1]) for two adjacent patches to merge."""
    max_object_size_m: tuple[float, float] = (4.0, 3.2)
    """(longest horizontal side, height) of a merged segment, metres; the side is measured on the
    axis-aligned bounding box with 20 % slack for yawed objects (see ``merge_patches``)."""
    convexity: bool = False
    """Merge only across convex or smooth connections (LCCP, Stein et al. 2014): faces of one object
    meet at convex edges, an object and what it stands on or leans against at concave ones. Off by
    default: on the simulator it did not raise recall (stacked crates are flush, and beams meet
    crates where the patches are not planar enough to judge)."""
    smooth_angle_deg: float = 10.0
    """Near-parallel patches (normals within this angle) count as one smooth surface..."""
    step_m: float = 0.03
    """...unless their planes are offset by more than this (the step between two crates' fronts)."""
    patch_regularizations: tuple[float, ...] = (0.1, 0.3, 1.0)
    """Cut pursuits on the graph of patches at these regularisations; their groups of patches are
    proposals too (a coarser, feature-driven hierarchy next to the greedy contact merging)."""
    proposal_scales_m: tuple[float, ...] = (1.0, 2.0)
    """Extra merge passes with these smaller longest-side limits, whose unions are proposals too:
    the greedy order that builds a forklift can swallow a crate into its neighbour first."""
    proposal_sizes_m: tuple[tuple[float, float], ...] = (
        (0.7, 0.45),
        (1.0, 0.45),
        (1.0, 0.6),
        (1.3, 0.45),
        (1.3, 0.75),
    )
    """Extra merge passes limited to these (longest side, height) sizes, metres, whose unions are
    proposals too. The contact order joins a crate's front face to the crate below before its top;
    a pass that cannot grow taller than one crate forms the crate alone (measured with
    ``factorydet bench pipeline``: box proposal recall rose about 1.6-fold on the simulator)."""
    structure_size_m: tuple[float, float] | None = (5.0, 3.5)
    """A first, geometry-only cut pursuit marks surfaces whose (horizontal diagonal, height) exceeds
    this as structure (walls, rack beams and posts): cut off from everything else, never merged,
    never proposed. ``None`` skips that pass."""
    split_structure: bool = False
    """Also split structure into patches with the second, feature-and-position cut pursuit (the
    structure takes no part in merging or proposals either way). False keeps each piece of
    structure one patch per connected part of the first pass's surfaces and runs the second cut
    pursuit on the other points alone: a third of an AGV frame's points are structure, and that
    pass was a third of the segmentation's time (``bench detect --compare-set
    split_structure=true`` runs the earlier way)."""

    def __post_init__(self) -> None:
        # Every value is checked whatever built it (a checkpoint's note, a run's record in the
        # session database, ``--set``, code): a neighbour count of 1e8 would allocate gigabytes in
        # the k-NN search before anything else noticed. Checked values are kept as plain Python
        # numbers and tuples, so settings read back from JSON compare equal to the originals.
        def keep(name: str, value: object) -> None:
            object.__setattr__(self, name, value)

        for name, setting in _SETTINGS.items():
            keep(name, setting.check(f"segmentation: {name}", getattr(self, name)))
        name = "segmentation: max_object_size_m"
        keep("max_object_size_m", _OBJECT_LENGTH.check_tuple(name, self.max_object_size_m, length=2))
        if self.structure_size_m is not None:
            name = "segmentation: structure_size_m"
            keep("structure_size_m", _STRUCTURE_LENGTH.check_tuple(name, self.structure_size_m, length=2))
        # Each entry of these is one more merge pass or cut pursuit over the whole frame.
        name = "segmentation: proposal_scales_m"
        scales = _OBJECT_LENGTH.check_tuple(name, self.proposal_scales_m, max_length=MAX_EXTRA_PASSES)
        keep("proposal_scales_m", scales)
        name = "segmentation: patch_regularizations"
        regularization = _SETTINGS["regularization"]
        keep(
            "patch_regularizations",
            regularization.check_tuple(name, self.patch_regularizations, max_length=MAX_EXTRA_PASSES),
        )
        name = "segmentation: proposal_sizes_m"
        sizes = self.proposal_sizes_m
        if not isinstance(sizes, (list, tuple)) or len(sizes) > MAX_EXTRA_PASSES:
            raise InputError(
                f"{name} must be a list of at most {MAX_EXTRA_PASSES} (side, height) pairs in metres,"
                f" got {short_repr(sizes)}"
            )
        keep(
            "proposal_sizes_m",
            tuple(_OBJECT_LENGTH.check_tuple(f"{name}[{i}]", pair, length=2) for i, pair in enumerate(sizes)),
        )


def point_features(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local geometric features and the neighbour lists they came from.

    Args:
        points: (N, 3) float32 points.
        k: neighbours per point (excluding the point itself).

    Returns:
        ``(features, neighbours, sq_distances)``: (N, 4) float32 [linearity, planarity, scattering,
        verticality], (N, k) uint32 neighbour indices sorted by distance, (N, k) float32 squared
        distances.
    """
    import pgeof

    xyz = np.ascontiguousarray(points, dtype=np.float32)
    k_eff = min(k, len(xyz) - 1)
    neighbours, sq_distances = pgeof.knn_search(xyz, xyz, k_eff + 1)
    # The first neighbour of a point is itself, except for duplicated points; drop column 0.
    neighbours, sq_distances = neighbours[:, 1:], sq_distances[:, 1:]
    with_self = np.concatenate([np.arange(len(xyz), dtype=np.uint32)[:, None], neighbours], axis=1)
    pointers = np.arange(0, with_self.size + 1, k_eff + 1, dtype=np.uint32)
    geof = pgeof.compute_features(xyz, np.ascontiguousarray(with_self.ravel()), pointers, k_min=3)
    return np.ascontiguousarray(geof[:, :4]), neighbours, sq_distances


def knn_edges(
    neighbours: np.ndarray, sq_distances: np.ndarray, k: int, max_edge_m: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected kNN graph: ``(source, target, length)`` with source < target, each edge once.

    ``max_edge_m`` is one limit, or (N,) one per point; an edge is kept when it is no longer than
    the smaller limit of its two ends (so the graph does not depend on which end found the other).
    """
    k = min(k, neighbours.shape[1])
    num_points = len(neighbours)
    source = np.repeat(np.arange(num_points, dtype=np.int64), k)
    target = neighbours[:, :k].astype(np.int64).ravel()
    length = np.sqrt(sq_distances[:, :k].astype(np.float64)).ravel()
    limit = np.asarray(max_edge_m, np.float64)
    if limit.ndim:
        limit = np.minimum(limit[source], limit[target])
    keep = (length <= limit) & (source != target)
    lo, hi = np.minimum(source, target)[keep], np.maximum(source, target)[keep]
    key, first = np.unique(lo * num_points + hi, return_index=True)
    return key // num_points, key % num_points, length[keep][first]


def _relabel(labels: np.ndarray) -> np.ndarray:
    return np.unique(labels, return_inverse=True)[1].reshape(-1).astype(np.int64)


def _split_disconnected(labels: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Make every label a connected set of the graph (a label split in pieces becomes several)."""
    num = len(labels)
    same = labels[source] == labels[target]
    graph = scipy.sparse.coo_matrix(
        (np.ones(same.sum()), (source[same], target[same])), shape=(num, num)
    ).tocsr()
    _, components = scipy.sparse.csgraph.connected_components(graph, directed=False)
    return _relabel(components)


def _patch_adjacency(
    patch_ids: np.ndarray, source: np.ndarray, target: np.ndarray, num_patches: int
) -> scipy.sparse.csr_matrix:
    """(P, P) symmetric matrix of the number of graph edges between two patches."""
    a, b = patch_ids[source], patch_ids[target]
    cross = a != b
    matrix = scipy.sparse.coo_matrix(
        (np.ones(cross.sum()), (a[cross], b[cross])), shape=(num_patches, num_patches)
    ).tocsr()
    return (matrix + matrix.T).tocsr()


def _absorb_small(
    patch_ids: np.ndarray, source: np.ndarray, target: np.ndarray, min_points: int
) -> np.ndarray:
    """Patches under ``min_points`` join the neighbour with the most shared edges (repeatedly)."""
    for _ in range(10):
        num = int(patch_ids.max()) + 1
        sizes = np.bincount(patch_ids, minlength=num)
        small = sizes < min_points
        if not small.any():
            break
        adjacency = _patch_adjacency(patch_ids, source, target, num)
        adjacency.sort_indices()
        mapping, changed = run_kernel(
            _compile_absorb,
            adjacency.indptr.astype(np.int64),
            adjacency.indices.astype(np.int64),
            adjacency.data.astype(np.float64),
            small,
        )
        if not changed:
            break
        # Resolve chains (a -> b -> c).
        for _ in range(num):
            nxt = mapping[mapping]
            if np.array_equal(nxt, mapping):
                break
            mapping = nxt
        patch_ids = _relabel(mapping[patch_ids])
    return patch_ids


def _compile_absorb():
    import numba

    @numba.njit(cache=True, nogil=True)
    def absorb(indptr, neighbours, counts, small):
        """One round: each small patch, in order, maps to its best neighbour's current target."""
        mapping = np.arange(len(small))
        changed = False
        for patch in range(len(small)):
            if not small[patch] or indptr[patch] == indptr[patch + 1]:
                continue  # isolated: stays (and is dropped later as too small for a proposal)
            # Prefer a neighbour that is not small itself, then the most shared edges; the first
            # (lowest id) of equals.
            best = -1
            best_big, best_count = False, -1.0
            for e in range(indptr[patch], indptr[patch + 1]):
                big = not small[neighbours[e]]
                if best < 0 or (big and not best_big) or (big == best_big and counts[e] > best_count):
                    best, best_big, best_count = neighbours[e], big, counts[e]
            if mapping[best] != patch:
                mapping[patch] = mapping[best]
                changed = True
        return mapping, changed

    return absorb


def _cut_pursuit(
    values: np.ndarray, source: np.ndarray, target: np.ndarray, length: np.ndarray, regularization: float
) -> np.ndarray:
    """l0 cut pursuit of (N, D) ``values`` on the point graph; lambda folded into the edge weights
    lambda / (1 + d / mean d)."""
    mean_length = max(float(length.mean()), 1e-6)
    return _cut_pursuit_weighted(values, source, target, regularization / (1.0 + length / mean_length))


def _cut_pursuit_weighted(
    values: np.ndarray, source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """(N,) component of each node of the l0 cut pursuit with the given edge weights (in a helper
    process: ``cut_pursuit`` says why)."""
    return cut_pursuit(values, weights, source, target)


def _oversized(points: np.ndarray, labels: np.ndarray, size: tuple[float, float]) -> np.ndarray:
    """(L,) bool: labels whose points span more than ``size`` = (horizontal, height) metres."""
    num = int(labels.max()) + 1
    lo, hi = group_bounds(points, labels, num)
    extent = hi - lo
    return (np.hypot(extent[:, 0], extent[:, 1]) > size[0]) | (extent[:, 2] > size[1])


def edge_limits(points: np.ndarray, params: SegmentationParams) -> float | np.ndarray:
    """The graph's edge length limit: ``max_edge_m``, or (N,) per point
    max(``max_edge_m``, ``max_edge_per_range`` x horizontal distance from the origin)."""
    if params.max_edge_per_range <= 0:
        return float(params.max_edge_m)
    distance = np.hypot(points[:, 0], points[:, 1]).astype(np.float64)
    return np.maximum(params.max_edge_m, params.max_edge_per_range * distance)


def over_segment(
    points: np.ndarray, params: SegmentationParams = SegmentationParams()
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """Cut-pursuit patches.

    Args:
        points: (N, 3) points (pruned, floor removed).
        params: segmentation settings.

    Returns:
        ``(patch_ids, structure_mask, (source, target, length), values)``: (N,) int64 patch of each
        point, (N,) bool True on structure points (see ``structure_size_m``), the graph, and the
        (N, D) float32 values the cut pursuit partitioned.
    """
    check_array(points, (None, 3), name="segment points", finite=True)
    num_points = len(points)
    if num_points == 0:
        empty = np.zeros(0, np.int64)
        return empty, np.zeros(0, bool), (empty, empty, np.zeros(0)), np.zeros((0, 4), np.float32)
    if num_points < 4:  # too few for local features: one patch per connected group
        source, target = np.triu_indices(num_points, 1)
        length = np.linalg.norm(points[source] - points[target], axis=1)
        limit = np.broadcast_to(edge_limits(points, params), (num_points,))
        keep = length <= np.minimum(limit[source], limit[target])
        source, target, length = source[keep], target[keep], length[keep]
        patch_ids = _split_disconnected(np.zeros(num_points, np.int64), source, target)
        return (
            patch_ids,
            np.zeros(num_points, bool),
            (source, target, length),
            np.zeros((num_points, 4), np.float32),
        )
    features, neighbours, sq_distances = point_features(points, max(params.k_features, params.k_graph))
    source, target, length = knn_edges(neighbours, sq_distances, params.k_graph, edge_limits(points, params))
    geometric = features * np.array([1.0, 1.0, 1.0, 2.0], np.float32)  # verticality counts double (SPG)
    structure_mask = np.zeros(num_points, bool)
    if params.structure_size_m is not None and len(source):
        # Pass 1, geometry only: surfaces far bigger than any object (walls, rack beams and posts)
        # are structure. Cutting them out first keeps objects resting on them separate.
        first = _split_disconnected(
            _cut_pursuit(geometric, source, target, length, params.regularization), source, target
        )
        structure_mask = _oversized(points, first, params.structure_size_m)[first]
        keep = structure_mask[source] == structure_mask[target]
        source, target, length = source[keep], target[keep], length[keep]
    values = geometric
    if params.spatial_weight > 0:
        centred = (points - points.mean(axis=0)) * params.spatial_weight
        values = np.concatenate([values, centred.astype(np.float32)], axis=1)
    if structure_mask.any() and not params.split_structure:
        # Pass 2 on the other points alone; the structure keeps pass 1's surfaces as patches.
        labels = first.copy()
        others = np.flatnonzero(~structure_mask)
        on_others = ~structure_mask[source]  # no edge joins structure to the rest any more
        if len(others):
            index = np.full(num_points, -1, np.int64)
            index[others] = np.arange(len(others))
            others_source, others_target = index[source[on_others]], index[target[on_others]]
            labels[others] = num_points + (
                _cut_pursuit(
                    values[others], others_source, others_target, length[on_others], params.regularization
                )
                if on_others.any()
                else np.arange(len(others))
            )
    elif len(source):
        labels = _cut_pursuit(values, source, target, length, params.regularization)
    else:
        labels = np.arange(num_points)
    patch_ids = _split_disconnected(labels, source, target)
    patch_ids = _absorb_small(patch_ids, source, target, params.min_patch_points)
    return patch_ids, structure_mask, (source, target, length), values


def merge_patches(
    points: np.ndarray,
    patch_ids: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    params: SegmentationParams = SegmentationParams(),
) -> tuple[np.ndarray, tuple[tuple[int, ...], ...]]:
    """Greedy merging of adjacent patches into object segments.

    Args:
        points: (N, 3) points.
        patch_ids: (N,) patch of each point, in [0, P).
        source, target: (E,) the point graph's edges.
        params: ``merge_threshold`` and ``max_object_size_m`` are used.

    Returns:
        ``(patch_segment_ids, history)``: (P,) segment of each patch, and the patch sets of every
        union formed, in merge order.
    """
    num_patches = int(patch_ids.max()) + 1 if len(patch_ids) else 0
    if num_patches == 0:
        return np.zeros(0, np.int64), ()
    return _merge(*_merge_inputs(points, patch_ids, source, target, num_patches), params)


def _merge_inputs(
    points: np.ndarray, patch_ids: np.ndarray, source: np.ndarray, target: np.ndarray, num_patches: int
) -> tuple[scipy.sparse.csr_matrix, np.ndarray, np.ndarray]:
    """What ``_merge`` starts from: the patches' (P, P) adjacency, indices sorted, and their
    (P, 3) lower and upper bounds."""
    adjacency = _patch_adjacency(patch_ids, source, target, num_patches)
    adjacency.sort_indices()
    return (adjacency, *group_bounds(points, patch_ids, num_patches))


def _merge(
    adjacency: scipy.sparse.csr_matrix, lo: np.ndarray, hi: np.ndarray, params: SegmentationParams
) -> tuple[np.ndarray, tuple[tuple[int, ...], ...]]:
    """``merge_patches`` of P patches given their (P, P) adjacency (``_patch_adjacency``, indices
    sorted) and (P, 3) bounds, which every merge pass of a frame shares (none is changed: the
    kernel grows copies of the bounds as it merges)."""
    num_patches = adjacency.shape[0]
    max_side, max_height = params.max_object_size_m
    root_of, history_members, history_ends = run_kernel(
        _compile_merge,
        num_patches,
        adjacency.indptr.astype(np.int64),
        adjacency.indices.astype(np.int64),
        adjacency.data.astype(np.float64),
        lo.copy(),
        hi.copy(),
        # The horizontal test uses the axis-aligned bounding box of the union, which over-estimates
        # a yawed object's longest side (by up to sqrt(2) for a square at 45 degrees); 20 % slack
        # covers the usual yaws of elongated objects without admitting much larger unions.
        float(max_side) * 1.2,
        float(max_height),
        float(params.merge_threshold),
    )
    starts = np.concatenate([[0], history_ends[:-1]])
    history = tuple(tuple(history_members[a:b].tolist()) for a, b in zip(starts, history_ends))
    return _relabel(root_of), history


def _compile_merge():
    import heapq

    import numba
    from numba import types
    from numba.typed import Dict, List

    @numba.njit(cache=True, nogil=True)
    def merge(num_patches, indptr, neighbours, counts, lo, hi, max_side, max_height, threshold):
        # Union-find over patches; each root keeps its members, bounds, boundary (its inter-patch
        # edges) and edge counts to the other roots.
        parent = np.arange(num_patches)
        boundary = np.zeros(num_patches)
        links = List()
        members = List()
        heap = []
        for a in range(num_patches):
            row = Dict.empty(types.int64, types.float64)
            for e in range(indptr[a], indptr[a + 1]):
                row[neighbours[e]] = counts[e]
                boundary[a] += counts[e]
            links.append(row)
            own = List.empty_list(types.int64)
            own.append(a)
            members.append(own)
        for a in range(num_patches):
            for b, count in links[a].items():
                if a < b:
                    heap.append((-(count / max(min(boundary[a], boundary[b]), 1.0)), a, b))
        heapq.heapify(heap)
        history_members = List.empty_list(types.int64)
        history_ends = List.empty_list(types.int64)
        while len(heap):
            neg_strength, a, b = heapq.heappop(heap)
            if parent[a] != a or parent[b] != b or b not in links[a]:
                continue  # stale entry
            if -neg_strength != links[a][b] / max(min(boundary[a], boundary[b]), 1.0):
                continue  # a newer entry for this pair is in the heap
            if -neg_strength < threshold:
                break
            union_lo = np.minimum(lo[a], lo[b])
            union_hi = np.maximum(hi[a], hi[b])
            if max(union_hi[0] - union_lo[0], union_hi[1] - union_lo[1]) > max_side:
                continue
            if union_hi[2] - union_lo[2] > max_height:
                continue
            # Merge b into a.
            parent[b] = a
            members[a].extend(members[b])
            members[b] = List.empty_list(types.int64)
            lo[a], hi[a] = union_lo, union_hi
            shared = links[a].pop(b)
            links[b].pop(a)
            boundary[a] = boundary[a] + boundary[b] - 2 * shared
            for other, count in links[b].items():
                links[other].pop(b)
                total = links[a].get(other, 0.0) + count
                links[a][other] = total
                links[other][a] = total
            links[b] = Dict.empty(types.int64, types.float64)
            for other, count in links[a].items():
                strength = count / max(min(boundary[a], boundary[other]), 1.0)
                heapq.heappush(heap, (-strength, min(a, other), max(a, other)))
            union = np.empty(len(members[a]), np.int64)
            for i in range(len(union)):
                union[i] = members[a][i]
            union.sort()
            history_members.extend(union)
            history_ends.append(len(history_members))
        root_of = np.arange(num_patches)
        for root in range(num_patches):
            if parent[root] == root:
                for patch in members[root]:
                    root_of[patch] = root
        return root_of, np.asarray(history_members), np.asarray(history_ends)

    return merge


def _mergeable_connections(
    points: np.ndarray,
    patch_ids: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    params: SegmentationParams,
    viewpoint: np.ndarray | None = None,
) -> np.ndarray:
    """(E,) bool: graph edges between patches whose connection is convex or smooth (LCCP).

    Each patch gets its centroid and plane normal (smallest principal axis, turned out of the
    visible surface: up for near-horizontal patches, towards the viewpoint, the vehicle at the
    origin by default, for the others). For neighbours with unit offset
    d = (c_a - c_b) / |c_a - c_b|, the connection is convex when (n_a - n_b) . d > 0 (with a small
    margin), smooth when the normals are within
    ``smooth_angle_deg`` and the planes less than ``step_m`` apart. Patches of fewer than 5 points or
    without a dominant plane are not judged (their edges stay). Edges inside a patch always stay.
    """
    num_patches = int(patch_ids.max()) + 1
    sizes = np.bincount(patch_ids, minlength=num_patches).astype(np.float64)
    xyz = points.astype(np.float64)
    centroids = np.zeros((num_patches, 3))
    np.add.at(centroids, patch_ids, xyz)
    centroids /= np.maximum(sizes, 1)[:, None]
    offsets = xyz - centroids[patch_ids]
    covariance = np.zeros((num_patches, 3, 3))
    np.add.at(covariance, patch_ids, offsets[:, :, None] * offsets[:, None, :])
    covariance /= np.maximum(sizes, 1)[:, None, None]
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)  # ascending
    normals = eigenvectors[:, :, 0]
    # Outward normals: a sensor looks down on the tops it sees, so near-horizontal surfaces face +z;
    # the other surfaces face the viewpoint (in the ground plane).
    view = np.zeros(2) if viewpoint is None else np.asarray(viewpoint, np.float64)[:2]
    towards = np.einsum("pd,pd->p", normals[:, :2], view - centroids[:, :2])
    horizontal = np.abs(normals[:, 2]) > np.cos(np.radians(45.0))
    flip = np.where(horizontal, normals[:, 2] < 0, towards < 0)
    normals *= np.where(flip, -1.0, 1.0)[:, None]
    # A plane is dominant when the smallest spread is well below the middle one.
    planar = (sizes >= 5) & (eigenvalues[:, 0] < 0.1 * np.maximum(eigenvalues[:, 1], 1e-12))

    a, b = patch_ids[source], patch_ids[target]
    across = a != b
    judged = across & planar[a] & planar[b]
    d = centroids[a] - centroids[b]
    d /= np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    convex = np.einsum("ed,ed->e", normals[a] - normals[b], d) > 0.05
    parallel = np.einsum("ed,ed->e", normals[a], normals[b]) > np.cos(np.radians(params.smooth_angle_deg))
    step = np.abs(np.einsum("ed,ed->e", normals[a], centroids[b] - centroids[a]))
    smooth = parallel & (step < params.step_m)
    return ~judged | convex | smooth


def _coarser_partitions(
    points: np.ndarray,
    values: np.ndarray,
    patch_ids: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    patch_is_structure: np.ndarray,
    params: SegmentationParams,
) -> tuple[tuple[int, ...], ...]:
    """Groups of patches from cut pursuits on the patch graph (a node per patch valued by its mean
    point values, an edge per adjacency weighted by its point-graph edge count) at each of
    ``params.patch_regularizations``; groups of 2+ patches that still fit an object."""
    num_patches = len(patch_is_structure)
    sizes = np.bincount(patch_ids, minlength=num_patches).astype(np.float64)
    means = np.column_stack(
        [np.bincount(patch_ids, values[:, d].astype(np.float64), num_patches) for d in range(values.shape[1])]
    )
    means /= np.maximum(sizes, 1)[:, None]
    adjacency = _patch_adjacency(patch_ids, source, target, num_patches).tocoo()
    upper = adjacency.row < adjacency.col
    patch_source, patch_target = adjacency.row[upper], adjacency.col[upper]
    counts = adjacency.data[upper].astype(np.float64)
    if not len(counts):
        return ()
    lo, hi = group_bounds(points, patch_ids, num_patches)
    max_side, max_height = params.max_object_size_m
    groups: list[tuple[int, ...]] = []
    contact = counts / counts.mean()  # stronger contact, dearer cut
    for regularization in params.patch_regularizations:
        labels = _cut_pursuit_weighted(means, patch_source, patch_target, regularization * contact)
        labels = _split_disconnected(labels, patch_source, patch_target)
        objects = np.flatnonzero(~patch_is_structure)
        by_label = objects[np.argsort(labels[objects], kind="stable")]  # ascending patch ids per label
        ends = np.cumsum(np.bincount(labels[objects]))
        for members in np.split(by_label, ends[:-1]):
            if len(members) < 2:
                continue
            extent = hi[members].max(axis=0) - lo[members].min(axis=0)
            if max(extent[:2]) <= max_side * 1.2 and extent[2] <= max_height:
                groups.append(tuple(members.tolist()))
    return tuple(groups)


def segment(points: np.ndarray, params: SegmentationParams = SegmentationParams()) -> Segmentation:
    """Patches and merged segments of a cloud.

    Args:
        points: (N, 3) points of the pruned, floor-free cloud.
        params: segmentation settings.

    Returns:
        The segmentation: per-point patch and segment ids, and the merge history.
    """
    patch_ids, structure_mask, (source, target, _), values = over_segment(points, params)
    num_patches = int(patch_ids.max()) + 1 if len(patch_ids) else 0
    patch_is_structure = np.zeros(num_patches, bool)
    if num_patches:
        np.logical_or.at(patch_is_structure, patch_ids, structure_mask)
    # Structure patches take no part in merging: drop their edges.
    keep = ~patch_is_structure[patch_ids[source]] & ~patch_is_structure[patch_ids[target]]
    if params.convexity and num_patches > 1:
        keep &= _mergeable_connections(points, patch_ids, source, target, params)
    if num_patches:
        # Every merge pass starts from the same patches: their adjacency and bounds once.
        inputs = _merge_inputs(points, patch_ids, source[keep], target[keep], num_patches)
        patch_segment_ids, history = _merge(*inputs, params)
        passes = [(scale, params.max_object_size_m[1]) for scale in params.proposal_scales_m]
        for size in passes + list(params.proposal_sizes_m):
            history = history + _merge(*inputs, dataclasses.replace(params, max_object_size_m=size))[1]
    else:
        patch_segment_ids, history = np.zeros(0, np.int64), ()
    if params.patch_regularizations and num_patches > 1:
        history = history + _coarser_partitions(
            points, values, patch_ids, source[keep], target[keep], patch_is_structure, params
        )
    segment_ids = patch_segment_ids[patch_ids] if len(patch_ids) else np.zeros(0, np.int64)
    return Segmentation(
        patch_ids=patch_ids,
        segment_ids=segment_ids,
        patch_segment_ids=patch_segment_ids,
        merge_history=history,
        patch_is_structure=patch_is_structure,
    )
