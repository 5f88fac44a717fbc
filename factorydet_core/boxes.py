"""Oriented 3D boxes: fitting to points and intersection over union.

Boxes are (cx, cy, cz, dx, dy, dz, yaw), z up, yaw counter-clockwise about +z (``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

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
        np.minimum(boxes_a[:, None, 2] + boxes_a[:, None, 5] / 2, boxes_b[None, :, 2] + boxes_b[None, :, 5] / 2)
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


def fit_box(points: np.ndarray, min_size: float = 0.02) -> np.ndarray:
    """Oriented upright box around points: the minimum-area rectangle of their ground-plane convex
    hull (rotating calipers over the hull's edges) and their z extent.

    Args:
        points: (N, 3) points, N >= 1.
        min_size: smallest box side, metres (a single point or a flat patch still gets a volume).

    Returns:
        (7,) box; yaw in [-pi/2, pi/2) with dx along yaw.
    """
    xy = np.asarray(points[:, :2], np.float64)
    z_lo, z_hi = float(points[:, 2].min()), float(points[:, 2].max())
    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):  # fewer than 3 points, or all collinear
        hull = xy
    best = None
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2)) if len(hull) > 1 else [0.0]
    for angle in angles:
        c, s = np.cos(angle), np.sin(angle)
        local = hull @ np.array([[c, -s], [s, c]])  # rotate by -angle
        lo, hi = local.min(axis=0), local.max(axis=0)
        area = float(np.prod(np.maximum(hi - lo, min_size)))
        if best is None or area < best[0]:
            best = (area, angle, lo, hi)
    _, angle, lo, hi = best
    c, s = np.cos(angle), np.sin(angle)
    centre_local = (lo + hi) / 2
    centre = np.array([c * centre_local[0] - s * centre_local[1], s * centre_local[0] + c * centre_local[1]])
    size = np.maximum(hi - lo, min_size)
    yaw = angle
    if size[1] > size[0]:  # dx is the longer side
        size = size[::-1]
        yaw = angle + np.pi / 2
    yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2
    return np.array(
        [centre[0], centre[1], (z_lo + z_hi) / 2, size[0], size[1], max(z_hi - z_lo, min_size), yaw]
    )
