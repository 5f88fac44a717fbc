"""Object proposals from segments: aggregated Fisher vectors and oriented boxes (paper section 3.4).

A proposal's feature is the weighted mean of the Fisher vectors of the voxels its points occupy
(Eq. 7; weights = the proposal's points in each voxel by default, or 1 per voxel), renormalised per
channel across the Gaussians. The alternative ``feature="direct"`` computes the 3DmFV of the
proposal's own points scaled into the unit sphere instead, and ``feature="none"`` computes none, for
back halves that read the point sets' points (the learned box head).
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import scipy.sparse

from factorydet_core.boxes import complete_hidden_side, fit_boxes, heading_gap, scene_heading
from factorydet_core.proposals.features import NUM_CHANNELS, NUM_GAUSSIANS, fisher_vectors, to_unit_sphere
from factorydet_core.types import InputError, Proposals, Segmentation, VoxelGrid

Weighting = Literal["points", "uniform"]
FeatureKind = Literal["aggregated", "direct", "none"]


def candidate_patch_sets(
    segmentation: Segmentation, *, include_history: bool = True, include_patches: bool = False
) -> tuple[list[tuple[int, ...]], list[int]]:
    """Patch sets to turn into proposals, each once: the final segments (level 0), the unions of the
    merge history (level 1) and, optionally, single patches (level 2)."""
    seen: dict[tuple[int, ...], int] = {}
    groups: dict[int, list[int]] = {}
    structure = segmentation.patch_is_structure
    for patch, seg in enumerate(segmentation.patch_segment_ids.tolist()):
        if not structure[patch]:
            groups.setdefault(seg, []).append(patch)
    for seg in sorted(groups):
        seen.setdefault(tuple(groups[seg]), 0)
    if include_history:
        for union in segmentation.merge_history:
            seen.setdefault(tuple(union), 1)
    if include_patches:
        for patch in np.flatnonzero(~structure).tolist():
            seen.setdefault((patch,), 2)
    return list(seen), list(seen.values())


def snap_to_floor(
    boxes: np.ndarray, floor_plane: np.ndarray | None, ground_snap_m: float = 0.15
) -> np.ndarray:
    """Extend (M, 7) boxes whose bottom is within ``ground_snap_m`` above the floor plane (a, b, c, d)
    down to it: floor removal cut their lowest points. No change without a (finite) plane."""
    boxes = np.array(boxes, np.float64).reshape(-1, 7)
    if floor_plane is None or not np.all(np.isfinite(floor_plane)):
        return boxes
    a, b, c, d = floor_plane
    floor_z = -(a * boxes[:, 0] + b * boxes[:, 1] + d) / c
    bottom, top = boxes[:, 2] - boxes[:, 5] / 2, boxes[:, 2] + boxes[:, 5] / 2
    snap = (bottom - floor_z <= ground_snap_m) & (bottom > floor_z)
    bottom = np.where(snap, floor_z, bottom)
    boxes[:, 2], boxes[:, 5] = (bottom + top) / 2, top - bottom
    return boxes


def point_sets(patch_ids: np.ndarray, patch_sets: list[tuple[int, ...]] | tuple) -> list[np.ndarray]:
    """Point indices of each set of patches (``patch_ids`` is the (N,) patch of every point): a
    set's points patch after patch in the set's order, each patch's in increasing index. All sets
    are gathered at once (a frame has some 10,000 sets: one concatenation each cost more)."""
    if not len(patch_sets):
        return []
    num_patches = int(patch_ids.max()) + 1 if len(patch_ids) else 0
    order = np.argsort(patch_ids, kind="stable")
    sizes = np.bincount(patch_ids, minlength=num_patches)
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    set_lengths, patches = _flatten(patch_sets)
    # Each (set, patch) pair's run of points, laid end to end: position k of the run of pair j
    # is order[starts[patch j] + k].
    run_lengths = sizes[patches].astype(np.int64)
    run_ends = np.cumsum(run_lengths)
    total = int(run_ends[-1]) if len(run_ends) else 0
    within = np.arange(total) - np.repeat(run_ends - run_lengths, run_lengths)
    gathered = order[np.repeat(starts[patches], run_lengths) + within]
    # Where each set's points end: the end of its last pair's run.
    set_ends = np.concatenate([[0], run_ends])[np.cumsum(set_lengths)]
    return np.split(gathered, set_ends[:-1])


def _flatten(sets) -> tuple[np.ndarray, np.ndarray]:
    """``(lengths, flat)``: (S,) the size of each of S sets of indices and all their indices, set
    after set."""
    lengths = np.array([len(s) for s in sets], np.int64)
    return lengths, np.fromiter((i for s in sets for i in s), np.int64, int(lengths.sum()))


def _set_sums(values: np.ndarray, sets: list[tuple[int, ...]]) -> np.ndarray:
    """(S,) int64 the sum of (P,) integer ``values`` over each of S sets of indices."""
    lengths, flat = _flatten(sets)
    running = np.concatenate([[0], np.cumsum(np.asarray(values, np.int64)[flat])])
    ends = np.cumsum(lengths)
    return running[ends] - running[ends - lengths]


def _fitted_and_view_boxes(
    points: np.ndarray, point_lists: list[np.ndarray], heading: float | None = None
) -> np.ndarray:
    """(M, 2, 7) for each of the M point sets: the L-shape box of its points, and their box headed
    along the viewing direction from the vehicle origin (right for round objects, whose one-sided
    view gives the L-shape search nothing to hold on to); with ``heading``, (M, 3, 7): also their
    box at that heading."""
    # The mean as each set's own array computes it, so the headings (and boxes) do not depend on
    # how many sets are fitted together.
    view_headings = np.array([np.arctan2(*points[idx][:, 1::-1].mean(axis=0)) for idx in point_lists])
    num_sets = len(point_lists)
    headings = [np.full(num_sets, np.nan), view_headings]
    if heading is not None:
        headings.append(np.full(num_sets, float(heading)))
    boxes = fit_boxes(points, list(point_lists) * len(headings), np.concatenate(headings))
    return boxes.reshape(len(headings), num_sets, 7).transpose(1, 0, 2)


# Boxes within this angle of the scene's heading are aligned with it already.
ALIGNED_TOLERANCE_RAD = np.radians(3.0)


def _misaligned(boxes: np.ndarray, heading: float) -> np.ndarray:
    """Indices of (M, 7) boxes more than ALIGNED_TOLERANCE_RAD off ``heading`` (modulo 90 degrees):
    the ones that also get a box at the scene's heading."""
    return np.flatnonzero(heading_gap(boxes[:, 6], heading) > ALIGNED_TOLERANCE_RAD)


def _completable(boxes: np.ndarray, min_completion_ratio: float) -> np.ndarray:
    """Indices of boxes narrow enough that completing them behind the visible side changes them."""
    return np.flatnonzero(boxes[:, 4] < min_completion_ratio * boxes[:, 3])


def box_hypotheses(
    points: np.ndarray,
    floor_plane: np.ndarray | None = None,
    *,
    ground_snap_m: float = 0.15,
    complete_boxes: bool = True,
    min_completion_ratio: float = 0.9,
    heading: float | None = None,
) -> np.ndarray:
    """(K, 7) the boxes ``build_proposals`` proposes for one point set: fitted, fitted and completed
    behind (when narrow), view-headed and completed behind, and with the scene's ``heading`` (when
    the fitted box is off it) the box at that heading and the same completed (when narrow); each
    snapped to the floor."""
    boxes = snap_to_floor(
        _fitted_and_view_boxes(points, [np.arange(len(points))], heading)[0], floor_plane, ground_snap_m
    )
    if not complete_boxes:
        return boxes[:1]
    out = [boxes[:1], complete_hidden_side(boxes[:1][_completable(boxes[:1], min_completion_ratio)])]
    out.append(complete_hidden_side(boxes[1:2]))
    if heading is not None and len(_misaligned(boxes[:1], heading)):
        aligned = boxes[2:3]
        out += [aligned, complete_hidden_side(aligned[_completable(aligned, min_completion_ratio)])]
    return np.concatenate(out)


def normalize_channels(features: np.ndarray) -> np.ndarray:
    """Per-channel L2 normalisation across the Gaussians of (M, 20, 5, 5, 5) features."""
    # float32 throughout: a channel's 125 squares sum to well within float32's precision, and
    # copies to float64 of thousands of proposals' features cost more than the rest of the stage.
    flat = np.asarray(features, np.float32).reshape(len(features), NUM_CHANNELS, NUM_GAUSSIANS)
    norms = np.sqrt(np.maximum(np.einsum("mcg,mcg->mc", flat, flat), 1e-12))[..., None]
    return (flat / norms).reshape(features.shape)


def point_set_features(
    points: np.ndarray,
    grid: VoxelGrid,
    voxel_features: np.ndarray,
    point_lists: list[np.ndarray],
    weighting: Weighting = "points",
    feature: FeatureKind = "aggregated",
    set_voxel_counts: scipy.sparse.csr_matrix | None = None,
) -> np.ndarray:
    """(M, 20, 5, 5, 5) features of point sets: the weighted mean of the Fisher vectors of the voxels
    each set occupies, renormalised (Eq. 7), or the 3DmFV of the set's points in the unit sphere.

    Args:
        points: (N, 3) the cloud the grid was built from.
        grid: its voxel grid.
        voxel_features: (V, 20, 5, 5, 5) per-voxel Fisher vectors.
        point_lists: M arrays of point indices.
        weighting: "points" (c_v = the set's points in voxel v) or "uniform" (c_v = 1).
        feature: "aggregated" or "direct".
        set_voxel_counts: (M, V) points of each set in each voxel, when the caller has it.
    """
    num_sets = len(point_lists)
    if feature == "direct":
        set_ids = np.repeat(np.arange(num_sets), [len(p) for p in point_lists])
        all_points = points[np.concatenate(point_lists)] if num_sets else np.zeros((0, 3))
        return fisher_vectors(to_unit_sphere(all_points, set_ids, num_sets), set_ids, num_sets)
    if set_voxel_counts is None:
        rows = np.repeat(np.arange(num_sets), [len(p) for p in point_lists])
        cols = grid.point_voxel_ids[np.concatenate(point_lists)] if num_sets else np.zeros(0, np.int64)
        set_voxel_counts = scipy.sparse.csr_matrix(
            (np.ones(len(rows)), (rows, cols)), shape=(num_sets, grid.num_voxels)
        )
    weights = set_voxel_counts.copy().tocsr()
    if weighting == "uniform":
        weights.data[:] = 1.0
    totals = np.asarray(weights.sum(axis=1)).ravel()
    weights = (scipy.sparse.diags(1.0 / np.maximum(totals, 1e-12)) @ weights).astype(np.float32)
    # A float32 product: each mean has at most a few hundred terms of unit-scale values.
    flat = np.asarray(voxel_features, np.float32).reshape(grid.num_voxels, -1)
    mean = np.asarray(weights @ flat).reshape(num_sets, NUM_CHANNELS, 5, 5, 5)
    return normalize_channels(mean)


def build_proposals(
    points: np.ndarray,
    segmentation: Segmentation,
    grid: VoxelGrid,
    voxel_features: np.ndarray | None,
    *,
    min_points: int = 30,
    weighting: Weighting = "points",
    feature: FeatureKind = "aggregated",
    include_history: bool = True,
    include_patches: bool = False,
    floor_plane: np.ndarray | None = None,
    ground_snap_m: float = 0.15,
    complete_boxes: bool = True,
    min_completion_ratio: float = 0.9,
    align_to_scene: bool = True,
) -> Proposals:
    """Proposals of a segmented cloud.

    Args:
        points: (N, 3) points the segmentation and the grid were built from.
        segmentation: patches and segments of those points.
        grid: their voxel grid.
        voxel_features: (V, 20, 5, 5, 5) per-voxel Fisher vectors; ``None`` with ``feature``
            "direct" or "none", which do not read them.
        min_points: smaller candidates are dropped.
        weighting: voxel weights of the aggregation, "points" (c_v = points of the proposal in the
            voxel) or "uniform" (c_v = 1).
        feature: "aggregated" (Eq. 7), "direct" (3DmFV of the proposal's points) or "none" (no
            3DmFV: ``Proposals.features`` is ``None``; for back halves that read the points).
        include_history: also propose the intermediate unions of the merge hierarchy.
        include_patches: also propose single patches.
        floor_plane: (4,) floor plane (a, b, c, d); a box whose bottom is within ``ground_snap_m`` of
            it is extended down to the floor, because floor removal cut the object's lowest points.
        ground_snap_m: see ``floor_plane``.
        complete_boxes: also propose each segment with its box completed behind the visible side
            (``boxes.complete_hidden_side``, seen from the vehicle origin), when its footprint is
            narrower than ``min_completion_ratio`` times its length.
        min_completion_ratio: see ``complete_boxes``.
        align_to_scene: with ``complete_boxes``, also propose each point set boxed at the scene's
            heading (``boxes.scene_heading`` of the fitted boxes, weighted by points), completed
            behind when narrow. A round object's own box takes an arbitrary heading, 45 degrees off
            its shelf costs a 0.37 m bobbin a third of its IoU; these boxes (and the class sizes
            set into them) raised the bobbins' ``option_recall`` in ``bench pipeline`` (README).

    Returns:
        The proposals, empty when no candidate has ``min_points`` points.
    """
    if weighting not in ("points", "uniform"):
        raise InputError(f"weighting must be 'points' or 'uniform', got {weighting!r}")
    if feature not in get_args(FeatureKind):
        raise InputError(f"feature must be 'aggregated', 'direct' or 'none', got {feature!r}")
    num_points = len(points)
    if len(segmentation.patch_ids) != num_points or len(grid.point_voxel_ids) != num_points:
        raise InputError("build_proposals: points, segmentation and grid must describe the same cloud")
    if voxel_features is None and feature == "aggregated":
        raise InputError('build_proposals: feature "aggregated" needs the voxel features')
    if voxel_features is not None and len(voxel_features) != grid.num_voxels:
        raise InputError(
            f"build_proposals: {len(voxel_features)} voxel features for {grid.num_voxels} voxels"
        )
    sets, levels = candidate_patch_sets(
        segmentation, include_history=include_history, include_patches=include_patches
    )
    num_patches = segmentation.num_patches
    patch_sizes = np.bincount(segmentation.patch_ids, minlength=num_patches)
    set_sizes = _set_sums(patch_sizes, sets)
    keep = set_sizes >= min_points
    sets = [s for s, k in zip(sets, keep) if k]
    levels = np.array([lv for lv, k in zip(levels, keep) if k], np.int8)
    if not sets:
        return Proposals(
            boxes=np.zeros((0, 7)),
            features=None if feature == "none" else np.zeros((0, NUM_CHANNELS, 5, 5, 5), np.float32),
            patch_sets=(),
            num_points=np.zeros(0, np.int64),
            num_voxels=np.zeros(0, np.int64),
            level=np.zeros(0, np.int8),
        )
    # membership (M, P) @ patch-voxel point counts (P, V) = proposal-voxel point counts (M, V).
    rows = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
    membership = scipy.sparse.csr_matrix(
        (np.ones(len(rows)), (rows, np.concatenate(sets))), shape=(len(sets), num_patches)
    )
    patch_voxel = scipy.sparse.csr_matrix(
        (np.ones(num_points), (segmentation.patch_ids, grid.point_voxel_ids)),
        shape=(num_patches, grid.num_voxels),
    )
    proposal_voxel = (membership @ patch_voxel).tocsr()
    num_voxels = np.diff(proposal_voxel.indptr).astype(np.int64)

    point_lists = point_sets(segmentation.patch_ids, sets)
    features = (
        None
        if feature == "none"
        else point_set_features(points, grid, voxel_features, point_lists, weighting, feature, proposal_voxel)
    )

    fitted_and_view = _fitted_and_view_boxes(points, point_lists).reshape(-1, 2, 7)
    boxes = snap_to_floor(fitted_and_view[:, 0], floor_plane, ground_snap_m)
    num_points_kept = set_sizes[keep]
    # Each candidate box is one of a set's hypotheses: origin is its set, and the set's features,
    # patches and counts are gathered once at the end (copying every set's features per kind of
    # box took a good part of the stage).
    origin = np.arange(len(sets))
    box_kind = np.zeros(len(sets), np.int8)
    heading = None
    if complete_boxes:
        view_boxes = snap_to_floor(fitted_and_view[:, 1], floor_plane, ground_snap_m)
        fitted = boxes
        # (kind, the sets that get one, their boxes, whether to complete them)
        hypotheses = [
            (1, _completable(fitted, min_completion_ratio), fitted, True),
            (2, np.arange(len(sets)), view_boxes, True),
        ]
        if align_to_scene:
            heading = float(scene_heading(fitted, num_points_kept))
            misaligned = _misaligned(fitted, heading)
            aligned = np.zeros_like(fitted)
            if len(misaligned):
                aligned[misaligned] = snap_to_floor(
                    fit_boxes(
                        points, [point_lists[i] for i in misaligned], np.full(len(misaligned), heading)
                    ),
                    floor_plane,
                    ground_snap_m,
                )
            completable = misaligned[_completable(aligned[misaligned], min_completion_ratio)]
            hypotheses += [(3, misaligned, aligned, False), (4, completable, aligned, True)]
        for kind, extra, source, complete in hypotheses:
            added = complete_hidden_side(source[extra]) if complete else source[extra]
            boxes = np.concatenate([boxes, added])
            origin = np.concatenate([origin, extra])
            box_kind = np.concatenate([box_kind, np.full(len(extra), kind, np.int8)])
    # Different candidates often give the same box (a union with a sliver, a completion of an
    # already square box): keep the first of boxes equal to within 2 cm and 2 degrees.
    key = np.column_stack(
        [np.round(boxes[:, :6] / 0.02), np.round(np.mod(boxes[:, 6], np.pi) / np.radians(2.0)) % 90]
    ).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    unique = np.sort(first)
    boxes, box_kind, chosen = boxes[unique], box_kind[unique], origin[unique]
    if features is not None:
        features = features[chosen]
        features.flags.writeable = False  # a fresh array nobody else holds: Proposals need not copy it
    sets = [sets[i] for i in chosen]
    num_points_kept, num_voxels, levels = num_points_kept[chosen], num_voxels[chosen], levels[chosen]
    return Proposals(
        boxes=boxes,
        features=features,
        patch_sets=tuple(sets),
        num_points=num_points_kept,
        num_voxels=num_voxels,
        level=levels,
        box_kind=box_kind,
        scene_heading=heading,
    )
