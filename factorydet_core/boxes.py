"""Oriented 3D boxes: fitting to points and intersection over union.

Boxes are (cx, cy, cz, dx, dy, dz, yaw), z up, yaw counter-clockwise about +z (``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np

from .types import check_array


def _rectangle_corners(box: np.ndarray) -> np.ndarray:
    """(4, 2) ground-plane corners of a box, counter-clockwise."""
    cx, cy, _, dx, dy, _, yaw = box
    half = np.array([[dx, dy], [-dx, dy], [-dx, -dy], [dx, -dy]]) / 2
    c, s = np.cos(yaw), np.sin(yaw)
    return half @ np.array([[c, s], [-s, c]]) + (cx, cy)


def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex polygon ``subject`` inside convex ``clipper`` (both CCW)."""
    output = subject
    for i in range(len(clipper)):
        if len(output) == 0:
            break
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        edge = b - a
        side = edge[0] * (output[:, 1] - a[1]) - edge[1] * (output[:, 0] - a[0])  # > 0: inside
        new = []
        for j in range(len(output)):
            p, q = output[j], output[(j + 1) % len(output)]
            sp, sq = side[j], side[(j + 1) % len(output)]
            if sp >= 0:
                new.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                new.append(p + t * (q - p))
        output = np.array(new).reshape(-1, 2)
    return output


def _polygon_area(polygon: np.ndarray) -> float:
    if len(polygon) < 3:
        return 0.0
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def box_iou_3d(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Exact 3D IoU of oriented, upright boxes.

    Args:
        boxes_a: (A, 7) boxes.
        boxes_b: (B, 7) boxes.

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
    # Cheap rejection: circumscribed circles and z ranges must overlap.
    radius_a = np.hypot(boxes_a[:, 3], boxes_a[:, 4]) / 2
    radius_b = np.hypot(boxes_b[:, 3], boxes_b[:, 4]) / 2
    centre_distance = np.hypot(
        boxes_a[:, None, 0] - boxes_b[None, :, 0], boxes_a[:, None, 1] - boxes_b[None, :, 1]
    )
    z_overlap = np.maximum(
        0,
        np.minimum(
            boxes_a[:, None, 2] + boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] + boxes_b[None, :, 5] / 2
        )
        - np.maximum(
            boxes_a[:, None, 2] - boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] - boxes_b[None, :, 5] / 2
        ),
    )
    candidates = np.argwhere((centre_distance < radius_a[:, None] + radius_b[None]) & (z_overlap > 0))
    volume_a = boxes_a[:, 3] * boxes_a[:, 4] * boxes_a[:, 5]
    volume_b = boxes_b[:, 3] * boxes_b[:, 4] * boxes_b[:, 5]
    corners_a = [None] * len(boxes_a)
    corners_b = [None] * len(boxes_b)
    for i, j in candidates:
        if corners_a[i] is None:
            corners_a[i] = _rectangle_corners(boxes_a[i])
        if corners_b[j] is None:
            corners_b[j] = _rectangle_corners(boxes_b[j])
        area = _polygon_area(_clip(corners_a[i], corners_b[j]))
        intersection = area * z_overlap[i, j]
        union = volume_a[i] + volume_b[j] - intersection
        iou[i, j] = intersection / union if union > 0 else 0.0
    return iou


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
    xy = np.asarray(points[:, :2], np.float64)
    z_lo, z_hi = float(points[:, 2].min()), float(points[:, 2].max())
    search = xy[:: max(1, -(-len(xy) // max_search_points))] - xy.mean(axis=0)  # ceil: at most the limit
    angle = 0.0 if heading is None else float(heading) % (np.pi / 2)
    if heading is None and len(search) >= 3:
        angles = np.radians(np.arange(0.0, 90.0, angle_step_deg))
        c, s = np.cos(angles), np.sin(angles)
        u = search[:, 0, None] * c + search[:, 1, None] * s  # (n, A) along the heading
        v = -search[:, 0, None] * s + search[:, 1, None] * c  # (n, A) across it
        du = np.minimum(u - u.min(axis=0), u.max(axis=0) - u)
        dv = np.minimum(v - v.min(axis=0), v.max(axis=0) - v)
        closeness = (1.0 / np.maximum(np.minimum(du, dv), 0.01)).sum(axis=0)
        angle = float(angles[int(np.argmax(closeness))])
    c, s = np.cos(angle), np.sin(angle)
    u = xy[:, 0] * c + xy[:, 1] * s
    v = -xy[:, 0] * s + xy[:, 1] * c
    centre_u, centre_v = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    size = np.maximum([u.max() - u.min(), v.max() - v.min()], min_size)
    centre = np.array([c * centre_u - s * centre_v, s * centre_u + c * centre_v])
    yaw = angle
    if size[1] > size[0]:  # dx is the longer side
        size = size[::-1]
        yaw = angle + np.pi / 2
    yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2
    return np.array(
        [centre[0], centre[1], (z_lo + z_hi) / 2, size[0], size[1], max(z_hi - z_lo, min_size), yaw]
    )


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
