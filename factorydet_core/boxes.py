"""Oriented 3D boxes: fitting to points and intersection over union.

Boxes are (cx, cy, cz, dx, dy, dz, yaw), z up, yaw counter-clockwise about +z (``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np

from factorydet_core.jit import run_kernel
from factorydet_core.types import InputError, check_array


def _inside(points: np.ndarray, rectangles: np.ndarray) -> np.ndarray:
    """(K, n) whether each of ``points`` (K, n, 2) lies in its pair's CCW ``rectangles`` (K, 4, 2)."""
    edges = np.roll(rectangles, -1, axis=1) - rectangles
    rel = points[:, :, None, :] - rectangles[:, None, :, :]
    cross = edges[:, None, :, 0] * rel[..., 1] - edges[:, None, :, 1] * rel[..., 0]
    scale = np.abs(edges).sum(axis=-1).max(axis=-1)[:, None, None]
    # The tolerance absorbs rounding for corners on an edge (identical or flush boxes) and no
    # more: at 1e-9 a corner 3e-10 m outside counted as inside, an IoU error above 1e-9.
    return (cross >= -1e-12 * scale * scale).all(axis=-1)


def rectangle_intersection_areas(corners_a: np.ndarray, corners_b: np.ndarray) -> np.ndarray:
    """Areas of the intersections of pairs of convex quadrilaterals: each of ``corners_a`` clipped
    by the four edges of its pair in ``corners_b`` (Sutherland-Hodgman), in a compiled kernel.

    NMS of a frame's candidates down to the AP floor compares some 300,000 pairs of boxes; the
    vectorised NumPy construction (``_intersection_areas_numpy``, kept as the reference the tests
    compare against) took 7 microseconds a pair, two seconds a frame.

    Args:
        corners_a: (K, 4, 2) counter-clockwise corners.
        corners_b: (K, 4, 2) counter-clockwise corners.

    Returns:
        (K,) areas.
    """
    corners_a = np.ascontiguousarray(corners_a, np.float64).reshape(-1, 4, 2)
    corners_b = np.ascontiguousarray(corners_b, np.float64).reshape(-1, 4, 2)
    out = np.zeros(len(corners_a))
    if len(out):
        run_kernel(_compile_intersection_areas, corners_a, corners_b, out)
    return out


def _compile_intersection_areas():
    import numba

    @numba.njit(cache=True, nogil=True)
    def areas(corners_a, corners_b, out):
        # Exact clipping of a quadrilateral by four half-planes leaves at most 8 corners; the
        # room beyond that (and the guard below) keeps rounding on near-degenerate boxes in bounds.
        polygon = np.empty((32, 2))
        clipped = np.empty((32, 2))
        for k in range(out.shape[0]):
            num = 4
            for i in range(4):
                polygon[i, 0] = corners_a[k, i, 0]
                polygon[i, 1] = corners_a[k, i, 1]
            # Rounding tolerance as the reference's: a corner on an edge (flush or identical boxes)
            # counts as inside.
            scale = 0.0
            for e in range(4):
                f = (e + 1) % 4
                scale = max(
                    scale,
                    abs(corners_b[k, f, 0] - corners_b[k, e, 0])
                    + abs(corners_b[k, f, 1] - corners_b[k, e, 1]),
                )
            tolerance = 1e-12 * scale * scale
            for e in range(4):
                if num == 0:
                    break
                f = (e + 1) % 4
                x0, y0 = corners_b[k, e, 0], corners_b[k, e, 1]
                ex, ey = corners_b[k, f, 0] - x0, corners_b[k, f, 1] - y0
                count = 0
                for i in range(num):
                    j = (i + 1) % num
                    px, py = polygon[i, 0], polygon[i, 1]
                    qx, qy = polygon[j, 0], polygon[j, 1]
                    side_p = ex * (py - y0) - ey * (px - x0)  # >= 0: left of the CCW edge, inside
                    side_q = ex * (qy - y0) - ey * (qx - x0)
                    inside_p, inside_q = side_p >= -tolerance, side_q >= -tolerance
                    if count >= 30:
                        break
                    if inside_p:
                        clipped[count, 0], clipped[count, 1] = px, py
                        count += 1
                    if inside_p != inside_q:
                        t = side_p / (side_p - side_q)
                        clipped[count, 0] = px + t * (qx - px)
                        clipped[count, 1] = py + t * (qy - py)
                        count += 1
                for i in range(count):
                    polygon[i, 0], polygon[i, 1] = clipped[i, 0], clipped[i, 1]
                num = count
            twice_area = 0.0
            for i in range(num):
                j = (i + 1) % num
                twice_area += polygon[i, 0] * polygon[j, 1] - polygon[j, 0] * polygon[i, 1]
            out[k] = abs(twice_area) / 2 if num >= 3 else 0.0

    return areas


def _intersection_areas_numpy(corners_a: np.ndarray, corners_b: np.ndarray) -> np.ndarray:
    """The same areas, vectorised over pairs in NumPy: the reference the compiled kernel is tested
    against.

    The intersection of two convex polygons is the convex hull of the corners of each that lie
    inside the other and of their edge crossings; all of these lie on that hull, so sorting them
    by angle around their mean and applying the shoelace formula gives its area.

    Args:
        corners_a: (K, 4, 2) counter-clockwise corners.
        corners_b: (K, 4, 2) counter-clockwise corners.

    Returns:
        (K,) areas.
    """
    num = len(corners_a)
    if num == 0:
        return np.zeros(0)
    start_a, step_a = corners_a, np.roll(corners_a, -1, axis=1) - corners_a
    start_b, step_b = corners_b, np.roll(corners_b, -1, axis=1) - corners_b
    # Edge i of a against edge j of b: start_a + t step_a = start_b + u step_b.
    da, db = step_a[:, :, None, :], step_b[:, None, :, :]
    diff = start_b[:, None, :, :] - start_a[:, :, None, :]
    denom = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
    safe = np.where(np.abs(denom) > 1e-12, denom, 1.0)
    t = (diff[..., 0] * db[..., 1] - diff[..., 1] * db[..., 0]) / safe
    u = (diff[..., 0] * da[..., 1] - diff[..., 1] * da[..., 0]) / safe
    crossing_mask = (np.abs(denom) > 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    crossings = start_a[:, :, None, :] + t[..., None] * da
    points = np.concatenate([corners_a, corners_b, crossings.reshape(num, 16, 2)], axis=1)
    valid = np.concatenate(
        [_inside(corners_a, corners_b), _inside(corners_b, corners_a), crossing_mask.reshape(num, 16)],
        axis=1,
    )
    count = valid.sum(axis=1)
    centre = (points * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    angle = np.arctan2(points[..., 1] - centre[:, None, 1], points[..., 0] - centre[:, None, 0])
    order = np.argsort(np.where(valid, angle, np.inf), axis=1)
    ordered = np.take_along_axis(points, order[..., None], axis=1)
    # Unused slots (sorted last) repeat the first point, so they add nothing to the shoelace sum.
    slot_valid = np.arange(24)[None, :] < count[:, None]
    ordered = np.where(slot_valid[..., None], ordered, ordered[:, :1, :])
    following = np.roll(ordered, -1, axis=1)
    twice_area = (ordered[..., 0] * following[..., 1] - following[..., 0] * ordered[..., 1]).sum(axis=1)
    return np.where(count >= 3, np.abs(twice_area) / 2, 0.0)


def rectangle_corners(boxes: np.ndarray) -> np.ndarray:
    """(M, 4, 2) ground-plane corners of (M, 7) boxes, counter-clockwise."""
    half = np.stack(
        [
            boxes[:, 3] / 2 * np.array([[1], [-1], [-1], [1]]),
            boxes[:, 4] / 2 * np.array([[1], [1], [-1], [-1]]),
        ],
        axis=-1,
    ).transpose(1, 0, 2)  # (M, 4, 2)
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = half[..., 0] * c - half[..., 1] * s + boxes[:, None, 0]
    y = half[..., 0] * s + half[..., 1] * c + boxes[:, None, 1]
    return np.stack([x, y], axis=-1)


def box_iou_3d(boxes_a: np.ndarray, boxes_b: np.ndarray, max_block: int = 4_000_000) -> np.ndarray:
    """Exact 3D IoU of oriented, upright boxes: the ground-plane intersection area times the height
    overlap, over the union volume.

    Args:
        boxes_a: (A, 7) boxes.
        boxes_b: (B, 7) boxes.
        max_block: pairs screened at once (bounds memory on large inputs).

    Returns:
        (A, B) IoU in [0, 1].
    """
    boxes_a = np.asarray(boxes_a, np.float64).reshape(-1, 7)
    boxes_b = np.asarray(boxes_b, np.float64).reshape(-1, 7)
    check_array(boxes_a, (None, 7), name="boxes_a", finite=True)
    check_array(boxes_b, (None, 7), name="boxes_b", finite=True)
    iou = np.zeros((len(boxes_a), len(boxes_b)))
    if not len(boxes_a) or not len(boxes_b):
        return iou
    radius_a = np.hypot(boxes_a[:, 3], boxes_a[:, 4]) / 2
    radius_b = np.hypot(boxes_b[:, 3], boxes_b[:, 4]) / 2
    top_a, bottom_a = boxes_a[:, 2] + boxes_a[:, 5] / 2, boxes_a[:, 2] - boxes_a[:, 5] / 2
    top_b, bottom_b = boxes_b[:, 2] + boxes_b[:, 5] / 2, boxes_b[:, 2] - boxes_b[:, 5] / 2
    volume_a = boxes_a[:, 3] * boxes_a[:, 4] * boxes_a[:, 5]
    volume_b = boxes_b[:, 3] * boxes_b[:, 4] * boxes_b[:, 5]
    corners_a, corners_b = rectangle_corners(boxes_a), rectangle_corners(boxes_b)
    rows_per_block = max(1, max_block // len(boxes_b))
    for lo in range(0, len(boxes_a), rows_per_block):
        rows = slice(lo, lo + rows_per_block)
        # Cheap rejection: circumscribed circles and z ranges must overlap.
        centre_distance = np.hypot(
            boxes_a[rows, None, 0] - boxes_b[None, :, 0], boxes_a[rows, None, 1] - boxes_b[None, :, 1]
        )
        z_overlap = np.minimum(top_a[rows, None], top_b[None]) - np.maximum(
            bottom_a[rows, None], bottom_b[None]
        )
        i, j = np.nonzero((centre_distance < radius_a[rows, None] + radius_b[None]) & (z_overlap > 0))
        if not len(i):
            continue
        iou[lo + i, j] = _iou_of_pairs(
            corners_a[lo + i], corners_b[j], z_overlap[i, j], volume_a[lo + i], volume_b[j]
        )
    return np.clip(iou, 0.0, 1.0)


def _iou_of_pairs(corners_a, corners_b, z_overlap, volume_a, volume_b) -> np.ndarray:
    """(R,) IoU of R pairs of boxes given their (R, 4, 2) ground corners, (R,) height overlaps
    and (R,) volumes (not clipped to [0, 1])."""
    intersection = rectangle_intersection_areas(corners_a, corners_b) * z_overlap
    union = volume_a + volume_b - intersection
    return np.where(union > 0, intersection / np.where(union > 0, union, 1.0), 0.0)


def overlapping_box_pairs(boxes: np.ndarray, min_iou: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)``, i < j, of (M, 7) boxes whose 3D IoU is at least ``min_iou`` > 0,
    as ``box_iou_3d(boxes, boxes) >= min_iou`` finds them, without the (M, M) matrix: only boxes
    whose circumscribed circles meet are compared (a k-d tree on their centres)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    check_array(boxes, (None, 7), name="boxes", finite=True)
    if not min_iou > 0:
        raise InputError(f"min_iou must be > 0, got {min_iou}")
    empty = np.zeros(0, np.int64)
    if len(boxes) < 2:
        return empty, empty
    from scipy.spatial import cKDTree

    radius = np.hypot(boxes[:, 3], boxes[:, 4]) / 2
    pairs = cKDTree(boxes[:, :2]).query_pairs(2 * float(radius.max()), output_type="ndarray")
    if not len(pairs):
        return empty, empty
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    top, bottom = boxes[:, 2] + boxes[:, 5] / 2, boxes[:, 2] - boxes[:, 5] / 2
    # The same screen and formula as box_iou_3d, pair by pair.
    centre_distance = np.hypot(boxes[i, 0] - boxes[j, 0], boxes[i, 1] - boxes[j, 1])
    z_overlap = np.minimum(top[i], top[j]) - np.maximum(bottom[i], bottom[j])
    near = (centre_distance < radius[i] + radius[j]) & (z_overlap > 0)
    i, j, z_overlap = i[near], j[near], z_overlap[near]
    corners = rectangle_corners(boxes)
    volume = boxes[:, 3] * boxes[:, 4] * boxes[:, 5]
    iou = np.clip(_iou_of_pairs(corners[i], corners[j], z_overlap, volume[i], volume[j]), 0.0, 1.0)
    keep = iou >= min_iou
    order = np.lexsort((j[keep], i[keep]))
    return i[keep][order], j[keep][order]


def fit_box(
    points: np.ndarray,
    min_size: float = 0.02,
    angle_step_deg: float = 1.0,
    max_search_points: int = 256,
    heading: float | None = None,
) -> np.ndarray:
    """Oriented upright box around points, robust to one- and two-sided (L-shaped) views.

    The heading is the one that maximises the closeness criterion of L-shape fitting (Zhang et al.
    2017): points of a partially seen object lie on one or two sides of its box, so each point
    scores 1 / max(d, 1 cm), d its distance to the nearest side of the bounding rectangle at that
    heading. The minimum-area rectangle, by contrast, turns an L-shaped view diagonally. The box's
    extents are then the points' extents at that heading, with the z range of the points.

    Args:
        points: (N, 3) points, N >= 1.
        min_size: smallest box side, metres (a single point or a flat patch still gets a volume).
        angle_step_deg: heading search step over [0, 90) degrees.
        max_search_points: the heading search uses at most this many points (evenly strided).
        heading: use this heading (radians) instead of searching one.

    Returns:
        (7,) box; dx >= dy, yaw in [-pi/2, pi/2) along dx.
    """
    points = np.asarray(points)
    headings = None if heading is None else np.array([heading], np.float64)
    return fit_boxes(points, [np.arange(len(points))], headings, min_size, angle_step_deg, max_search_points)[
        0
    ]


def fit_boxes(
    points: np.ndarray,
    point_lists: list[np.ndarray],
    headings: np.ndarray | None = None,
    min_size: float = 0.02,
    angle_step_deg: float = 1.0,
    max_search_points: int = 256,
) -> np.ndarray:
    """``fit_box`` of many point sets at once, compiled and spread over the cores (a frame's few
    thousand point sets took most of the proposal stage one call at a time).

    Args:
        points: (N, 3) the cloud (further columns are ignored).
        point_lists: M arrays of indices into ``points``, none empty.
        headings: (M,) each set's heading in radians, NaN to search it; ``None`` searches all.
        min_size, angle_step_deg, max_search_points: as ``fit_box``.

    Returns:
        (M, 7) boxes; dx >= dy, yaw in [-pi/2, pi/2) along dx.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"points: expected shape (N, 3), got {points.shape}")
    if any(np.asarray(p).dtype == bool for p in point_lists):
        raise InputError("point_lists: expected arrays of point indices, got a boolean mask")
    sizes = np.array([len(p) for p in point_lists], np.int64)
    if (sizes == 0).any():
        raise InputError(f"point set {int(np.argmin(sizes))} is empty: a box needs at least one point")
    if max_search_points < 1 or angle_step_deg <= 0:
        raise InputError("max_search_points must be >= 1 and angle_step_deg > 0")
    num_sets = len(point_lists)
    if headings is None:
        headings = np.full(num_sets, np.nan)
    headings = np.asarray(headings, np.float64).reshape(-1)
    if len(headings) != num_sets:
        raise InputError(f"headings: expected {num_sets} values, got {len(headings)}")
    out = np.zeros((num_sets, 7))
    if not num_sets:
        return out
    indptr = np.concatenate([[0], np.cumsum(sizes)])
    indices = np.concatenate([np.asarray(p, np.int64).reshape(-1) for p in point_lists])
    if indices.min() < 0 or indices.max() >= len(points):
        raise InputError("point_lists index outside the points")
    angles = np.radians(np.arange(0.0, 90.0, angle_step_deg))
    run_kernel(
        _compile_fit_boxes,
        np.ascontiguousarray(points[:, :2], np.float64),
        np.ascontiguousarray(points[:, 2], np.float64),
        indptr,
        indices,
        headings,
        angles,
        np.cos(angles),
        np.sin(angles),
        float(min_size),
        int(max_search_points),
        out,
    )
    return out


def _compile_fit_boxes():
    import math

    import numba

    @numba.njit(parallel=True, cache=True, nogil=True)
    def fit(xy, z, indptr, indices, headings, angles, cos_a, sin_a, min_size, max_search, out):
        for m in numba.prange(indptr.shape[0] - 1):
            lo, num = indptr[m], indptr[m + 1] - indptr[m]
            mean_x, mean_y, z_lo, z_hi = 0.0, 0.0, np.inf, -np.inf
            for i in range(num):
                p = indices[lo + i]
                mean_x += xy[p, 0]
                mean_y += xy[p, 1]
                z_lo = min(z_lo, z[p])
                z_hi = max(z_hi, z[p])
            mean_x /= num
            mean_y /= num
            stride = max(1, -(-num // max_search))  # ceil: at most max_search points
            num_search = -(-num // stride)
            angle = 0.0
            if not np.isnan(headings[m]):
                angle = headings[m] % (np.pi / 2)
            elif num_search >= 3:
                sx = np.empty(num_search)
                sy = np.empty(num_search)
                for j in range(num_search):
                    p = indices[lo + j * stride]
                    sx[j] = xy[p, 0] - mean_x
                    sy[j] = xy[p, 1] - mean_y
                best = -1.0
                for a in range(angles.shape[0]):
                    c, s = cos_a[a], sin_a[a]
                    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
                    for j in range(num_search):
                        u = sx[j] * c + sy[j] * s
                        v = -sx[j] * s + sy[j] * c
                        u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                        v_lo, v_hi = min(v_lo, v), max(v_hi, v)
                    closeness = 0.0
                    for j in range(num_search):
                        u = sx[j] * c + sy[j] * s
                        v = -sx[j] * s + sy[j] * c
                        gap = min(min(u - u_lo, u_hi - u), min(v - v_lo, v_hi - v))
                        closeness += 1.0 / max(gap, 0.01)
                    if closeness > best:  # the first of equal maxima, like argmax
                        best = closeness
                        angle = angles[a]
            c, s = math.cos(angle), math.sin(angle)
            u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
            for i in range(num):
                p = indices[lo + i]
                u = xy[p, 0] * c + xy[p, 1] * s
                v = -xy[p, 0] * s + xy[p, 1] * c
                u_lo, u_hi = min(u_lo, u), max(u_hi, u)
                v_lo, v_hi = min(v_lo, v), max(v_hi, v)
            centre_u, centre_v = (u_lo + u_hi) / 2, (v_lo + v_hi) / 2
            size_u, size_v = max(u_hi - u_lo, min_size), max(v_hi - v_lo, min_size)
            yaw = angle
            if size_v > size_u:  # dx is the longer side
                size_u, size_v = size_v, size_u
                yaw = angle + np.pi / 2
            out[m, 0] = c * centre_u - s * centre_v
            out[m, 1] = s * centre_u + c * centre_v
            out[m, 2] = (z_lo + z_hi) / 2
            out[m, 3] = size_u
            out[m, 4] = size_v
            out[m, 5] = max(z_hi - z_lo, min_size)
            out[m, 6] = (yaw + np.pi / 2) % np.pi - np.pi / 2

    return fit


def complete_hidden_side(boxes: np.ndarray, viewpoint: np.ndarray | None = None) -> np.ndarray:
    """Extend each box away from the viewpoint along its shorter horizontal side until its footprint
    is square.

    A sensor sees only the surfaces that face it, so a box fitted to the points of a barrel or a
    crate is cut at the hidden back; assuming a square footprint recovers round and near-square
    objects (barrels, bobbins, cones, many crates) and is one extra hypothesis next to the fitted
    box, not a replacement.

    Args:
        boxes: (M, 7) fitted boxes (dx >= dy, as ``fit_box`` returns).
        viewpoint: (2,) or (3,) sensor position in the boxes' frame; the origin by default.

    Returns:
        (M, 7) completed boxes.
    """
    boxes = np.array(boxes, np.float64).reshape(-1, 7)
    view = np.zeros(2) if viewpoint is None else np.asarray(viewpoint, np.float64)[:2]
    long_side = np.maximum(boxes[:, 3], boxes[:, 4])
    short_side = np.minimum(boxes[:, 3], boxes[:, 4])
    yaw = boxes[:, 6] + np.where(boxes[:, 3] >= boxes[:, 4], np.pi / 2, 0.0)  # direction of the short side
    axis = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    away = np.sign(np.einsum("md,md->m", axis, boxes[:, :2] - view))
    away[away == 0] = 1.0
    shift = (long_side - short_side) / 2
    out = boxes.copy()
    out[:, :2] += axis * (away * shift)[:, None]
    out[:, 3] = long_side
    out[:, 4] = long_side
    return out


def heading_gap(yaw: np.ndarray | float, heading: float) -> np.ndarray:
    """The angle in [0, pi/4] between yaws (any shape) and a heading, modulo 90 degrees: a box's
    heading is the same after a quarter turn (its sides swap), so 0 and 90 degrees are no gap."""
    return np.abs(_fold_quarter(np.asarray(yaw, np.float64) - heading))


def _fold_quarter(angle: np.ndarray) -> np.ndarray:
    """Angles folded into [-pi/4, pi/4) modulo pi/2."""
    return (angle + np.pi / 4) % (np.pi / 2) - np.pi / 4


def scene_heading(boxes: np.ndarray, weights: np.ndarray | None = None, bin_deg: float = 1.0) -> float:
    """The dominant heading of a scene, modulo 90 degrees: the mode of (M, 7) boxes' yaws folded
    into [0, 90) degrees, each box weighted by ``weights`` (M,) (its number of points, say).

    Factories, warehouses and rooms are built on a rectangular grid: walls, racks and the crates
    and bobbins on their shelves share a heading, and the points of walls and racks outweigh the
    rest. A round object's own box has no heading to find (a bobbin seen from one side gives the
    L-shape search a curve), and boxing it at the scene's heading lines it up with its shelf.

    Returns:
        The heading in radians, in [0, pi/2); 0 without boxes.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    if not len(boxes):
        return 0.0
    weights = np.ones(len(boxes)) if weights is None else np.asarray(weights, np.float64)
    num_bins = max(1, round(90.0 / bin_deg))
    folded = np.mod(boxes[:, 6], np.pi / 2)
    bins = np.minimum((folded / (np.pi / 2) * num_bins).astype(np.int64), num_bins - 1)
    histogram = np.bincount(bins, weights=weights, minlength=num_bins)
    # Circular smoothing over neighbouring bins: 0 and 89.9 degrees are one heading.
    smoothed = histogram + np.roll(histogram, 1) + np.roll(histogram, -1)
    peak = int(np.argmax(smoothed))
    # The weighted mean of the folded yaws within one bin of the peak, unwrapped around it.
    centre = (peak + 0.5) * (np.pi / 2) / num_bins
    offset = _fold_quarter(folded - centre)
    near = np.abs(offset) <= 1.5 * (np.pi / 2) / num_bins
    refined = centre + np.average(offset[near], weights=np.maximum(weights[near], 1e-12))
    return float(refined % (np.pi / 2))
