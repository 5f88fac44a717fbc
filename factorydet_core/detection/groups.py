"""The back half of the detector: proposals grouped by point set, classified, boxed by class, and
filtered by score and 3D NMS (paper §3.5, §3.6).

Several proposals share one point set (the same patches with different box hypotheses), and so
share one feature; the classifier sees each point set once. Its predicted class then picks the
box: among the set's hypotheses, and the same boxes grown to the class's typical sizes behind their
visible sides, the least grown one whose size the class's annotations cover (``BoxSizePrior``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.proposals.candidates import point_sets
from factorydet_core.proposals.visibility import FreeSpace
from factorydet_core.types import Proposals, Segmentation

if TYPE_CHECKING:  # box_quality builds on this module
    pass

DESCRIPTOR_NAMES: tuple[str, ...] = (
    "length_m",
    "width_m",
    "height_m",
    "width_over_length",
    "height_over_length",
    "bottom_above_floor_m",
    "top_above_floor_m",
    "linearity",
    "planarity",
    "scattering",
    "verticality",
    "log_num_points",
    "log_points_per_m3",
    "log_num_voxels",
)
"""Hand-made geometric descriptors of a point set, for the non-deep baseline."""


@dataclasses.dataclass(frozen=True)
class ProposalGroups:
    """The distinct point sets of a frame's proposals, with what a classifier reads from them."""

    group_ids: np.ndarray
    """(M,) int64: the point set of each proposal."""
    representatives: np.ndarray
    """(G,) int64: the first proposal of each point set."""
    features: np.ndarray | None
    """(G, 20, 5, 5, 5) float32: the 3DmFV feature of each point set; ``None`` when the proposals
    carry none (``feature`` "none")."""
    descriptors: np.ndarray
    """(G, len(DESCRIPTOR_NAMES)) float32: geometric descriptors of each point set (its fitted box)."""
    anchor_mask: np.ndarray | None = None
    """(M,) bool: the proposals whose boxes class sizes are set into (``Proposals.anchor_mask``);
    ``None``: the first (fitted) box of each set."""
    free_space: FreeSpace | None = None
    """What the frame's rays saw around the vehicle (``visibility.free_space``), for the box
    quality regressor's visibility features; ``None``: not computed."""
    points: np.ndarray | None = None
    """(G, SAMPLED_POINTS, 3) float32: a fixed-size sample of each point set's points in the
    vehicle frame (``sample_point_sets``), what the learned box head reads; ``None``: not kept."""
    fitted_boxes: np.ndarray | None = None
    """(G, 7) the fitted box of each point set (its first proposal's): the box head's canonical
    frame; ``None``: not kept."""

    @property
    def num_groups(self) -> int:
        return len(self.representatives)

    def members(self) -> list[np.ndarray]:
        """Per point set, the indices of its proposals in proposal order (the fitted box first)."""
        order = np.argsort(self.group_ids, kind="stable")
        starts = np.concatenate([[0], np.cumsum(np.bincount(self.group_ids, minlength=self.num_groups))])
        return [order[starts[g] : starts[g + 1]] for g in range(self.num_groups)]


SAMPLED_POINTS = 64
"""Points kept of each point set for the learned box head (``box_head.BoxHead``)."""


def flatten_sets(members: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S point sets' proposal ids listed set after set: ``(member_ids, owners, starts)``, (M,) the
    ids, (M,) the set (0..S-1) of each row and (S,) the row where each set starts."""
    counts = np.array([len(m) for m in members], np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    member_ids = np.concatenate(members).astype(np.int64) if len(members) else np.zeros(0, np.int64)
    return member_ids, np.repeat(np.arange(len(members)), counts), starts


def rank_within_sets(owners: np.ndarray, key: np.ndarray) -> np.ndarray:
    """(R,) each row's rank among the rows of its set (``owners``, (R,)) by increasing ``key``
    (R,), the earlier row first on ties: 0 marks each set's least."""
    order = np.lexsort((key, owners))
    sorted_owners = owners[order]
    starts = np.flatnonzero(np.r_[True, sorted_owners[1:] != sorted_owners[:-1]])
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    return rank


def floor_height(floor_plane: np.ndarray | None) -> float:
    """The floor plane's height at the vehicle origin (0 for ``None``, NaN or a vertical plane)."""
    if floor_plane is not None and np.isfinite(floor_plane).all() and abs(floor_plane[2]) > 1e-6:
        return -float(floor_plane[3]) / float(floor_plane[2])
    return 0.0


def sample_point_sets(
    points: np.ndarray, point_lists: list[np.ndarray], num_samples: int = SAMPLED_POINTS, seed: int = 0
) -> np.ndarray:
    """(M, num_samples, 3) float32: ``num_samples`` points of each of M point sets, drawn without
    replacement from sets that have more and with replacement (all points first) from the others;
    an empty set gives zeros. Seeded: the same sets give the same samples.

    Args:
        points: (N, 3) the cloud.
        point_lists: M arrays of indices into ``points``.
    """
    rng = np.random.default_rng(seed)
    out = np.zeros((len(point_lists), num_samples, 3), np.float32)
    for m, members in enumerate(point_lists):
        count = len(members)
        if not count:
            continue
        if count >= num_samples:
            chosen = members[rng.choice(count, num_samples, replace=False)]
        else:
            extra = rng.integers(0, count, num_samples - count)
            chosen = np.concatenate([members, members[extra]])
        out[m] = points[chosen]
    return out


def eigen_features(points: np.ndarray, point_lists: Sequence[np.ndarray]) -> np.ndarray:
    """(M, 4) linearity, planarity, scattering, verticality of M point sets (Demantke et al.), all
    sets at once (one call per set cost a frame's 2,500 sets 60 ms); zeros for sets of under 3
    points.

    Args:
        points: (N, 3) the cloud.
        point_lists: M arrays of indices into ``points``.
    """
    out = np.zeros((len(point_lists), 4))
    member_ids, owner, _ = flatten_sets(point_lists)
    counts = np.bincount(owner, minlength=len(point_lists)).astype(np.float64)
    enough = counts >= 3
    if not enough.any():
        return out
    own = np.asarray(points, np.float64)[member_ids]
    mean = np.column_stack([np.bincount(owner, own[:, d], len(point_lists)) for d in range(3)])
    mean /= np.maximum(counts, 1)[:, None]
    centred = own - mean[owner]
    covariance = np.empty((len(point_lists), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            covariance[:, i, j] = covariance[:, j, i] = np.bincount(
                owner, centred[:, i] * centred[:, j], len(point_lists)
            )
    values, vectors = np.linalg.eigh(covariance[enough] / counts[enough, None, None])
    l3, l2, l1 = np.sqrt(np.maximum(values, 1e-12)).T  # ascending
    normal_z = vectors[:, 2, 0]
    out[enough] = np.column_stack([(l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, 1.0 - np.abs(normal_z)])
    return out


def group_proposals(
    proposals: Proposals,
    points: np.ndarray,
    segmentation: Segmentation,
    floor_plane: np.ndarray | None = None,
    free_space: FreeSpace | None = None,
) -> ProposalGroups:
    """Group proposals by point set and describe each set.

    Args:
        proposals: the frame's proposals.
        points: (N, 3) the segmented cloud's points.
        segmentation: its segmentation (patch ids).
        floor_plane: (4,) floor plane for the heights above floor (z = 0 when None or NaN).
        free_space: the frame's rays on a grid (``visibility.free_space``), kept with the groups.
    """
    keys = {}
    group_ids = np.array([keys.setdefault(s, len(keys)) for s in proposals.patch_sets], np.int64)
    representatives = np.unique(group_ids, return_index=True)[1].astype(np.int64)  # first of each
    features = None if proposals.features is None else proposals.features[representatives]
    point_lists = point_sets(segmentation.patch_ids, [proposals.patch_sets[i] for i in representatives])
    descriptors = describe_point_sets(
        points,
        point_lists,
        proposals.boxes[representatives],
        proposals.num_voxels[representatives],
        floor_plane,
    )
    return ProposalGroups(
        group_ids,
        representatives,
        features,
        descriptors,
        proposals.anchor_mask,
        free_space,
        sample_point_sets(points, point_lists),
        np.array(proposals.boxes[representatives], np.float64),
    )


def describe_point_sets(
    points: np.ndarray,
    point_lists: list[np.ndarray],
    boxes: np.ndarray,
    num_voxels: np.ndarray,
    floor_plane: np.ndarray | None = None,
) -> np.ndarray:
    """(M, len(DESCRIPTOR_NAMES)) float32 geometric descriptors of M point sets with their boxes.

    Args:
        points: (N, 3) the cloud.
        point_lists: M arrays of point indices.
        boxes: (M, 7) a box of each set.
        num_voxels: (M,) occupied voxels of each set.
        floor_plane: (4,) floor plane for the heights above floor (z = 0 when None or NaN).
    """
    floor_z = floor_height(floor_plane)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    num_points = np.maximum(np.array([len(m) for m in point_lists], np.float64), 1)
    length, width = np.maximum(boxes[:, 3], boxes[:, 4]), np.minimum(boxes[:, 3], boxes[:, 4])
    height = boxes[:, 5]
    volume = np.maximum(length * width * height, 1e-6)
    columns = [
        length,
        width,
        height,
        width / np.maximum(length, 1e-6),
        height / np.maximum(length, 1e-6),
        boxes[:, 2] - height / 2 - floor_z,
        boxes[:, 2] + height / 2 - floor_z,
        *eigen_features(points, point_lists).T,
        np.log(num_points),
        np.log(num_points / volume),
        np.log(np.maximum(np.asarray(num_voxels, np.float64), 1)),
    ]
    descriptors = np.column_stack(columns).astype(np.float32).reshape(len(point_lists), len(DESCRIPTOR_NAMES))
    return descriptors


def _horizontal_sorted_sizes(boxes: np.ndarray) -> np.ndarray:
    """(M, 3) (length, width, height) of (M, 7) boxes, length >= width."""
    return np.column_stack(
        [np.maximum(boxes[:, 3], boxes[:, 4]), np.minimum(boxes[:, 3], boxes[:, 4]), boxes[:, 5]]
    )


def _size_modes(
    sizes: np.ndarray, max_modes: int, min_share: float = 0.05, merge_log_ratio: float = 0.05
) -> np.ndarray:
    """(K, 3) typical sizes of one class: k-means on log sizes (k <= ``max_modes``), seeded at
    evenly spaced quantiles of the volume; clusters holding less than ``min_share`` of the boxes
    (or a single box) are dropped, and modes within ``merge_log_ratio`` of a more frequent one on
    every axis (5%: their options are near duplicates) are merged into it. A class of two kinds
    (pallet trucks and forklifts) gets a mode per kind; a class of one kind whose sizes vary a
    little (the default corpus's barrels, within 7% of each other) gets one or two. At a share of
    0.1 the pallet trucks of the simulator's default corpus (4 of its 55 annotated trucks) had no
    mode, and no option of a pallet truck's point set reached their size."""
    logs = np.log(np.maximum(sizes, 1e-3))
    k = min(max_modes, len(logs))
    order = np.argsort(logs.sum(axis=1), kind="stable")
    centres = logs[order[((np.arange(k) + 0.5) * len(logs) / k).astype(int)]]
    for _ in range(25):
        assign = np.argmin(((logs[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        centres = np.array(
            [logs[assign == j].mean(axis=0) if (assign == j).any() else centres[j] for j in range(k)]
        )
    counts = np.bincount(assign, minlength=k)
    keep = counts >= max(2, min_share * len(logs))
    if not keep.any():
        return np.median(sizes, axis=0)[None]
    kept_centres, kept_counts = centres[keep], counts[keep]
    merged: list[list[int]] = []  # groups of kept modes, each led by its most frequent member
    for j in np.argsort(-kept_counts, kind="stable").tolist():
        for group in merged:
            if np.abs(kept_centres[j] - kept_centres[group[0]]).max() <= merge_log_ratio:
                group.append(j)
                break
        else:
            merged.append([j])
    return np.exp(np.array([np.average(kept_centres[g], axis=0, weights=kept_counts[g]) for g in merged]))


GROW_VARIANTS: tuple[tuple[float, bool], ...] = ((0.0, False), (0.3, True))
"""Each hypothesis is grown to each mode once per ``(near_share, crosswise)`` pair here
(``BoxSizePrior.grow``): away from the viewer with the mode's length on the box's longer side, and
with 30% of the growth towards the viewer and the length on the shorter side (a forklift seen from
the front: ``bench pipeline``'s truck ``option_recall`` on the corpus's 20 test frames rose from
0.883 to 0.922, the other classes unchanged)."""

ANCHORS_PER_SIZE = 16
"""Boxes ``BoxSizePrior.anchored`` sets into each box per size: 2 orientations x 4 corners x
bottom or top."""

OPTION_KINDS: tuple[str, ...] = ("hypothesis", "grown", "anchored", "standing", "stacked")
"""What ``BoxSizePrior.option_sources`` says each option is: a point set's own box hypothesis; the
same grown to a size mode (``grow``); a mode-sized box set into a corner of the fitted box
(``anchored``); a mode-sized box centred on the fitted box and standing on the floor
(``standing``); a mode-sized box one object up from the fitted box's bottom or down from its top
(``stacked``)."""


@dataclasses.dataclass(frozen=True)
class BoxSizePrior:
    """Typical box sizes of each class, from annotated boxes: the median (length, width, height)
    with length >= width, the annotated range, and up to eight modes (size clusters).

    A detection's box is chosen among its point set's box hypotheses and the same boxes grown to
    each mode behind their visible sides (``options``): the least grown one whose size lies in the
    class's annotated range, else the one nearest to that range. Without a range (checkpoints from
    before it was kept) the one nearest to the median.
    """

    sizes: np.ndarray
    """(C, 3) median sizes, metres; NaN rows for classes never seen."""
    lower: np.ndarray | None = None
    """(C, 3) smallest annotated sizes (NaN for classes never seen); ``None``: unknown."""
    upper: np.ndarray | None = None
    """(C, 3) largest annotated sizes."""
    modes: tuple[np.ndarray, ...] | None = None
    """Per class a (K, 3) array of typical sizes (K = 0 for classes never seen)."""

    @classmethod
    def from_boxes(
        cls, boxes: np.ndarray, class_ids: np.ndarray, num_classes: int, max_modes: int = 8
    ) -> BoxSizePrior:
        """The prior of annotated (M, 7) boxes of classes ``class_ids`` (M,), with up to
        ``max_modes`` modes per class. Crates and bobbins come in more sizes than three modes told
        apart (three averaged a 1.15 x 0.95 m and a 1.15 x 0.75 m crate into one mode between
        them); eight, with near-duplicate modes merged (``_size_modes``), put a crate's or a
        bobbin's option within IoU 0.6 more often than five. ``bench pipeline``'s
        ``option_recall`` measures it."""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        class_ids = np.asarray(class_ids)
        dims = _horizontal_sorted_sizes(boxes)
        sizes, lower, upper = (np.full((num_classes, 3), np.nan) for _ in range(3))
        modes = []
        for c in range(num_classes):
            own = dims[class_ids == c]
            if len(own):
                sizes[c], lower[c], upper[c] = np.median(own, axis=0), own.min(axis=0), own.max(axis=0)
                modes.append(_size_modes(own, max_modes))
            else:
                modes.append(np.zeros((0, 3)))
        return cls(sizes, lower, upper, tuple(modes))

    def distance(self, boxes: np.ndarray, class_id: int) -> np.ndarray:
        """(M,) sum of |log| size ratios of (M, 7) boxes to class ``class_id`` (0 is a perfect fit)."""
        prior = self.sizes[class_id]
        if not np.isfinite(prior).all():
            return np.zeros(len(boxes))
        dims = _horizontal_sorted_sizes(np.asarray(boxes, np.float64).reshape(-1, 7))
        return np.abs(np.log(np.maximum(dims, 1e-3) / prior)).sum(axis=1)

    def range_distance(self, boxes: np.ndarray, class_id: int) -> np.ndarray:
        """(M,) sum of |log| ratios of (M, 7) boxes' sizes to the nearest size in the class's
        annotated range (0 inside it)."""
        if self.lower is None or self.upper is None or not np.isfinite(self.lower[class_id]).all():
            return self.distance(boxes, class_id)
        dims = np.maximum(_horizontal_sorted_sizes(np.asarray(boxes, np.float64).reshape(-1, 7)), 1e-3)
        clipped = np.clip(dims, self.lower[class_id], self.upper[class_id])
        return np.abs(np.log(clipped / dims)).sum(axis=1)

    def grow(
        self,
        boxes: np.ndarray,
        class_id: int,
        viewpoint: np.ndarray | None = None,
        size: np.ndarray | None = None,
        near_share: float = 0.0,
        crosswise: bool = False,
    ) -> np.ndarray:
        """(M, 7) boxes grown to at least the class's median size (or ``size``, (3,) length, width,
        height): horizontally towards the hidden side, away from ``viewpoint`` (the vehicle origin
        by default), and upwards (the floor is below).

        A box axis along the line of sight grows only away from the viewer (its near face is the
        seen one); an axis across it grows equally to both sides (both of its ends are seen, the
        visible points of a round object or the top of a cone are narrower than its foot); oblique
        axes in between, by the cosine of their angle to the line of sight. Growing every axis
        wholly to one side put the boxes of cones beside their objects (``option_recall`` in
        ``bench pipeline``; the README gives the figures).

        ``near_share`` of the growth along the line of sight goes towards the viewer instead (0:
        none; 0.5: as much as away): the nearest surface seen is not always the object's near end
        (a forklift seen from the front shows its mast, 0.6 to 1.1 m behind the tips of forks too
        low and thin to return). ``crosswise`` grows the box's shorter side to the size's length
        instead of its longer one: the face seen across a long object's end (that mast, 1.1 m wide
        and 0.15 m deep) is longer than its depth."""
        prior = self.sizes[class_id] if size is None else np.asarray(size, np.float64)
        out = np.array(boxes, np.float64).reshape(-1, 7)
        if not np.isfinite(prior).all():
            return out
        view = np.zeros(2) if viewpoint is None else np.asarray(viewpoint, np.float64)[:2]
        sight = out[:, :2] - view
        sight /= np.maximum(np.linalg.norm(sight, axis=1), 1e-9)[:, None]
        long_is_x = (out[:, 3] >= out[:, 4]) != crosswise
        for axis in (0, 1):  # box x and y
            size_col = 3 + axis
            want = np.where(long_is_x == (axis == 0), prior[0], prior[1])
            grow_by = np.maximum(want - out[:, size_col], 0.0)
            heading = out[:, 6] + axis * np.pi / 2
            direction = np.column_stack([np.cos(heading), np.sin(heading)])
            away = np.einsum("md,md->m", direction, sight)  # cosine to the line of sight
            out[:, :2] += direction * (away * (1.0 - 2.0 * near_share) * grow_by / 2)[:, None]
            out[:, size_col] += grow_by
        grow_z = np.maximum(prior[2] - out[:, 5], 0.0)
        out[:, 2] += grow_z / 2
        out[:, 5] += grow_z
        return out

    def anchored(self, boxes: np.ndarray, size: np.ndarray) -> np.ndarray:
        """Boxes of exactly ``size`` ((3,) length, width, height) set into each of (M, 7) boxes'
        corners: the new box shares one vertical edge's corner of the old box (its 4 corners) and
        its bottom or its top, with its length along the old box's x or y axis. A segment of two
        stacked or side-by-side objects (flush faces leave no gap to cut at) holds each object in
        one of its corners; a segment of one object seen from one side holds it in the corner
        nearest the viewer (the size grows away from the other corners).

        Returns:
            (ANCHORS_PER_SIZE * M, 7), anchor after anchor (M rows each): orientation (length
            along x, then y), then corner (x sign, y sign in (-,-), (-,+), (+,-), (+,+)), then
            bottom before top.
        """
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        size = np.asarray(size, np.float64)
        cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        bottom, top = boxes[:, 2] - boxes[:, 5] / 2, boxes[:, 2] + boxes[:, 5] / 2
        out = []
        for dx, dy in ((size[0], size[1]), (size[1], size[0])):
            for sx in (-1.0, 1.0):
                for sy in (-1.0, 1.0):
                    # Offsets in the box frame that keep corner (sx, sy) where it is.
                    ox, oy = sx * (boxes[:, 3] - dx) / 2, sy * (boxes[:, 4] - dy) / 2
                    for z in (bottom + size[2] / 2, top - size[2] / 2):
                        block = boxes.copy()
                        block[:, 0] += cos * ox - sin * oy
                        block[:, 1] += sin * ox + cos * oy
                        block[:, 2] = z
                        block[:, 3], block[:, 4], block[:, 5] = dx, dy, size[2]
                        out.append(block)
        return np.concatenate(out)

    def standing(self, boxes: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes of ``size`` ((3,) length, width, height) standing on the floor (z = 0, the vehicle
        frame's floor) centred on those of (M, 7) ``boxes`` whose bottom lies below that height;
        horizontally the box keeps its heading and grows to at least ``size`` to both sides (length
        along its longer axis). Objects beside the vehicle lose their lower part to its own blind
        zone, not only their foot to floor removal: a cone's visible top, 0.2 m above the floor, is
        as wide as the view's line of sight is deep, and growing it away from the viewer or upwards
        set the box beside and above the cone (``option_recall`` in ``bench pipeline``).

        Returns:
            ``(standing, rows)``: (K, 7) boxes and (K,) the row of ``boxes`` each stands under.
        """
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        size = np.asarray(size, np.float64)
        rows = np.flatnonzero(boxes[:, 2] - boxes[:, 5] / 2 < size[2])
        out = boxes[rows]
        long_is_x = out[:, 3] >= out[:, 4]
        out[:, 3] = np.maximum(out[:, 3], np.where(long_is_x, size[0], size[1]))
        out[:, 4] = np.maximum(out[:, 4], np.where(long_is_x, size[1], size[0]))
        out[:, 2], out[:, 5] = size[2] / 2, size[2]
        return out, rows

    def stacked(
        self, boxes: np.ndarray, size: np.ndarray, corners: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``anchored`` boxes of ``size`` moved one object height up from the bottom of (M, 7)
        ``boxes`` (the bottom-set ones) or down from their top (the top-set ones), for the boxes at
        least two objects high: the middle objects of a stack of pallets or crates, which no corner
        of the stack's box holds (a stack of three pallets has one, of four two).

        Args:
            corners: ``anchored(boxes, size)`` when the caller has it already (not modified).

        Returns:
            ``(stacked, rows)``: (K, 7) boxes and (K,) the row of ``boxes`` each was set into, in
            ``anchored``'s order with the boxes too low to hold two objects left out.
        """
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        size = np.asarray(size, np.float64)
        if corners is None:
            corners = self.anchored(boxes, size)
        corners = np.array(corners, np.float64).reshape(ANCHORS_PER_SIZE, len(boxes), 7)
        rows = np.tile(np.arange(len(boxes)), (ANCHORS_PER_SIZE, 1))
        # anchored's blocks alternate bottom-set and top-set: move those up, these down.
        corners[0::2, :, 2] += size[2]
        corners[1::2, :, 2] -= size[2]
        tall = np.broadcast_to(boxes[:, 5] >= 2 * size[2] - 1e-6, rows.shape)
        return corners[tall], rows[tall]

    def class_modes(self, class_id: int) -> np.ndarray:
        """(K, 3) the sizes options are grown to for ``class_id``: its modes, else its median."""
        return self.modes[class_id] if self.modes is not None else self.sizes[class_id][None]

    def options(
        self,
        boxes: np.ndarray,
        class_id: int,
        fitted_boxes: np.ndarray | None = None,
        anchor_boxes: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """A point set's box options for class ``class_id`` and the cost of each.

        Args:
            boxes: (M, 7) the set's box hypotheses, the fitted box first.
            fitted_boxes: (M, 7) the fitted box of each box's own set, when ``boxes`` hold the
                hypotheses of several sets at once; ``None``: one set, whose fitted box is
                ``boxes[0]``.
            anchor_boxes: (S, 7) boxes to set boxes of each mode's exact size into
                (``anchored``, ``standing``, ``stacked``), appended after the grown blocks, mode
                after mode; ``None``: none. Their cost's volume ratio is to the anchor box they
                came from.

        Returns:
            ``(options, cost)``: (K, 7) the hypotheses and the same grown to each of the class's
            modes (to its median without modes), block after block, once per ``GROW_VARIANTS``
            entry, then per mode the anchored,
            standing and stacked boxes, and (K,) their cost; the chosen box is the option of least
            cost. The cost is the distance to the class's range (to its median without a range)
            plus a tie-break that prefers the least grown box (0.001 per unit of log volume ratio
            to the fitted box). ``option_sources`` says where each option came from.
        """
        options, cost, _, _, _ = self.option_sources(boxes, class_id, fitted_boxes, anchor_boxes)
        return options, cost

    def option_sources(
        self,
        boxes: np.ndarray,
        class_id: int,
        fitted_boxes: np.ndarray | None = None,
        anchor_boxes: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``options`` with where each option came from.

        Returns:
            ``(options, cost, kinds, sources, modes)``: as ``options``, and per option (K,) its
            kind (an index into ``OPTION_KINDS``), (K,) its source (the row of ``boxes`` for
            hypotheses and grown boxes, of ``anchor_boxes`` for the others) and (K,) the mode it
            was sized to (-1 for hypotheses).
        """
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        rows = np.arange(len(boxes))
        if not np.isfinite(self.sizes[class_id]).all():
            zeros = np.zeros(len(boxes), np.int64)
            return boxes, np.zeros(len(boxes)), zeros, rows, zeros - 1
        modes = self.class_modes(class_id)
        anchors = np.zeros((0, 7)) if anchor_boxes is None else np.asarray(anchor_boxes, np.float64)
        anchors = anchors.reshape(-1, 7)
        anchor_rows = np.arange(len(anchors))
        # (boxes, kind, source rows, mode) blocks, in the documented order.
        blocks = [(boxes, 0, rows, -1)]
        blocks += [
            (self.grow(boxes, class_id, size=m, near_share=share, crosswise=cross), 1, rows, j)
            for share, cross in GROW_VARIANTS
            for j, m in enumerate(modes)
        ]
        if len(anchors):
            for j, m in enumerate(modes):
                corners = self.anchored(anchors, m)
                blocks.append((corners, 2, np.tile(anchor_rows, ANCHORS_PER_SIZE), j))
                standing, standing_rows = self.standing(anchors, m)
                blocks.append((standing, 3, standing_rows, j))
                stacked, stacked_rows = self.stacked(anchors, m, corners)
                blocks.append((stacked, 4, stacked_rows, j))
        options = np.concatenate([b[0] for b in blocks])
        kinds = np.concatenate([np.full(len(b[0]), b[1], np.int64) for b in blocks])
        sources = np.concatenate([b[2] for b in blocks]).astype(np.int64)
        mode_ids = np.concatenate([np.full(len(b[0]), b[3], np.int64) for b in blocks])
        if self.lower is None:
            return options, self.distance(options, class_id), kinds, sources, mode_ids
        if fitted_boxes is None:
            fitted = np.repeat(boxes[:1], len(boxes), axis=0)
        else:
            fitted = np.asarray(fitted_boxes, np.float64).reshape(-1, 7)
        # Each option's volume is compared with its own set's fitted box, or the anchor it came from.
        from_box = kinds < 2
        reference = np.zeros((len(options), 7))
        reference[from_box] = fitted[sources[from_box]]
        reference[~from_box] = anchors[sources[~from_box]]
        volume = np.prod(np.maximum(options[:, 3:6], 1e-3), axis=1)
        reference_volume = np.prod(np.maximum(reference[:, 3:6], 1e-3), axis=1)
        growth = np.abs(np.log(volume / reference_volume))
        cost = self.range_distance(options, class_id) + 1e-3 * growth
        return options, cost, kinds, sources, mode_ids

    def to_json(self) -> dict:
        def rows(array):
            # Whole floats (JSON keeps every bit): the saved model boxes as the one that ran.
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in array]

        out = {"median": rows(self.sizes)}
        if self.lower is not None and self.upper is not None:
            out["lower"], out["upper"] = rows(self.lower), rows(self.upper)
        if self.modes is not None:
            out["modes"] = [rows(m) for m in self.modes]
        return out

    @classmethod
    def from_json(cls, data: list | dict) -> BoxSizePrior:
        """From ``to_json``; a plain list of rows is a checkpoint's medians from before the range."""

        def array(rows):
            return np.array([[np.nan if v is None else v for v in row] for row in rows], np.float64)

        if isinstance(data, list):
            return cls(array(data))
        modes = data.get("modes")
        return cls(
            array(data["median"]),
            array(data["lower"]) if "lower" in data else None,
            array(data["upper"]) if "upper" in data else None,
            None if modes is None else tuple(array(m).reshape(-1, 3) for m in modes),
        )


def best_option_iou(
    reference_boxes: np.ndarray,
    reference_class_ids: np.ndarray,
    proposal_boxes: np.ndarray,
    group_ids: np.ndarray,
    prior: BoxSizePrior,
    anchored: bool = True,
    anchor_mask: np.ndarray | None = None,
) -> np.ndarray:
    """(R,) the highest 3D IoU of each reference box with any box option of its own class
    (``BoxSizePrior.options``, with ``anchored`` boxes set into each fitted box) of the point sets
    that overlap it: the recall bound of a detector that names every class right and picks the best
    option.

    Args:
        reference_boxes: (R, 7) boxes; reference_class_ids: (R,) their classes.
        proposal_boxes: (M, 7) proposal boxes; group_ids: (M,) the point set of each, the first
            proposal of a set being its fitted box.
        prior: the class sizes.
        anchor_mask: (M,) bool, the proposals whose boxes sizes are set into besides each set's
            fitted box (``Proposals.anchor_mask``); ``None``: the fitted boxes alone.
    """

    reference_boxes = np.asarray(reference_boxes, np.float64).reshape(-1, 7)
    proposal_boxes = np.asarray(proposal_boxes, np.float64).reshape(-1, 7)
    group_ids = np.asarray(group_ids, np.int64)
    best = np.zeros(len(reference_boxes))
    if not len(reference_boxes) or not len(proposal_boxes):
        return best
    overlap = box_iou_3d(proposal_boxes, reference_boxes) > 0
    for r in range(len(reference_boxes)):
        sets = np.unique(group_ids[overlap[:, r]])
        if not len(sets):
            continue
        members = np.isin(group_ids, sets)
        boxes, owners = proposal_boxes[members], group_ids[members]
        is_anchor = np.zeros(len(boxes), bool) if anchor_mask is None else np.asarray(anchor_mask)[members]
        # Stable order keeps each set's fitted box first among its proposals.
        order = np.argsort(owners, kind="stable")
        boxes, owners, is_anchor = boxes[order], owners[order], is_anchor[order]
        first = np.concatenate([[True], owners[1:] != owners[:-1]])
        fitted = boxes[first][np.cumsum(first) - 1]
        anchor_boxes = boxes[first | is_anchor] if anchored else None
        class_id = int(reference_class_ids[r])
        options, _ = prior.options(boxes, class_id, fitted_boxes=fitted, anchor_boxes=anchor_boxes)
        best[r] = box_iou_3d(options, reference_boxes[r : r + 1]).max()
    return best
