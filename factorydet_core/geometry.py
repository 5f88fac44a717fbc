"""Rigid transforms and oriented boxes.

Boxes are (cx, cy, cz, dx, dy, dz, yaw): centre, full edge lengths along the box's own axes, and
a counter-clockwise rotation about +z taking the frame's x axis onto the box's x axis (the ``dx``
edge). z is up, units are metres and radians. See ``docs/conventions.md``.
"""

from __future__ import annotations

import numpy as np

from factorydet_core.types import InputError, check_array

BOX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
)
"""(12, 2) corner indices of a box's edges, for corners in the order of ``box_corners``."""

# Unit-box corners, bottom face counter-clockwise seen from above, then the top face.
_UNIT_CORNERS = 0.5 * np.array(
    [[1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1], [1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1]],
    dtype=np.float64,
)


def rotation_z(yaw: float | np.ndarray) -> np.ndarray:
    """Rotation matrices about +z; (3, 3) for a scalar, (..., 3, 3) for an array of angles."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack(
        [np.stack([c, -s, zeros], -1), np.stack([s, c, zeros], -1), np.stack([zeros, zeros, ones], -1)], -2
    )


def rotation_ypr(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) rotation R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (intrinsic z-y'-x'')."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) homogeneous transform from a (3, 3) rotation and a (3,) translation."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = translation
    return transform


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform, without a general matrix inverse."""
    rotation, translation = transform[:3, :3], transform[:3, 3]
    return make_transform(rotation.T, -rotation.T @ translation)


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points; returns (N, 3) in the points' dtype."""
    check_array(transform, (4, 4), name="transform", finite=True)
    check_array(points, (None, 3), name="points")
    out = points.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
    return out.astype(points.dtype, copy=False)


def apply_transforms(transforms: np.ndarray, transform_ids: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Move each point by its own transform, ``transforms[transform_ids[i]]`` for point ``i``.

    Args:
        transforms: (T, 4, 4) rigid transforms.
        transform_ids: (N,) integer index into ``transforms`` of each point.
        points: (N, 3) points.

    Returns:
        (N, 3) float64 moved points.
    """
    transform_ids = np.asarray(transform_ids)
    rotations = transforms[transform_ids, :3, :3]  # (N, 3, 3)
    translations = transforms[transform_ids, :3, 3]
    return np.einsum("nij,nj->ni", rotations, np.asarray(points, np.float64)) + translations


def rotation_angle_deg(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Angle in degrees of the rotation taking ``rotation_b`` onto ``rotation_a``."""
    cos_angle = (np.trace(rotation_a @ rotation_b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0))))


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners of (M, 7) boxes as (M, 8, 3), in the order that ``BOX_EDGES`` indexes."""
    check_array(boxes, (None, 7), name="boxes", finite=True)
    local = _UNIT_CORNERS[None] * boxes[:, None, 3:6]
    return np.einsum("mij,mkj->mki", rotation_z(boxes[:, 6]), local) + boxes[:, None, :3]


def box_wireframe_segments(boxes: np.ndarray) -> np.ndarray:
    """Edges of (M, 7) boxes as (M * 12, 2, 3) line segments."""
    return box_corners(boxes)[:, BOX_EDGES].reshape(-1, 2, 3)


def box_dashed_segments(boxes: np.ndarray, num_dashes: int = 2) -> np.ndarray:
    """Edges of (M, 7) boxes as dashes, (M * 12 * num_dashes, 2, 3): each edge cut in ``num_dashes``
    equal parts, the first half of each drawn (how the app tells a detection from a label)."""
    if num_dashes < 1:
        raise InputError(f"num_dashes must be >= 1, got {num_dashes}")
    edges = box_wireframe_segments(boxes)
    start, step = edges[:, 0], (edges[:, 1] - edges[:, 0]) / num_dashes
    k = np.arange(num_dashes)[None, :, None]
    begin = start[:, None] + k * step[:, None]
    return np.stack([begin, begin + step[:, None] / 2], axis=2).reshape(-1, 2, 3)


def box_corner_segments(boxes: np.ndarray, fraction: float = 0.25) -> np.ndarray:
    """Edges of (M, 7) boxes as corner brackets, (M * 24, 2, 3): the ``fraction`` of each edge next
    to either end (how the app draws a pre-label nobody has confirmed)."""
    if not 0.0 < fraction <= 0.5:
        raise InputError(f"fraction must lie in (0, 0.5], got {fraction}")
    edges = box_wireframe_segments(boxes)
    reach = (edges[:, 1] - edges[:, 0]) * fraction
    first = np.stack([edges[:, 0], edges[:, 0] + reach], axis=1)
    last = np.stack([edges[:, 1] - reach, edges[:, 1]], axis=1)
    return np.stack([first, last], axis=1).reshape(-1, 2, 3)


def points_in_box(points: np.ndarray, box: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,) bool mask of the (N, 3) points inside one (7,) box grown by ``margin`` on every side."""
    check_array(points, (None, 3), name="points")
    check_array(box, (7,), name="box", finite=True)
    # A cheap square around the box first (most points of a frame are far from any one box); the
    # rotation only for the points in it.
    reach = float(np.hypot(box[3], box[4])) / 2 + max(margin, 0.0)
    near = np.flatnonzero((np.abs(points[:, 0] - box[0]) <= reach) & (np.abs(points[:, 1] - box[1]) <= reach))
    local = (points[near].astype(np.float64) - box[:3]) @ rotation_z(box[6])  # R_z(-yaw) applied row-wise.
    inside = np.zeros(len(points), bool)
    inside[near] = (np.abs(local) <= box[3:6] / 2 + margin).all(axis=1)
    return inside


def point_box_ids(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) int64: the first of the (M, 7) ``boxes`` each of the (N, 3) ``points`` lies in, -1 for
    none (per-point labels from boxes)."""
    check_array(points, (None, 3), name="points")
    check_array(boxes, (None, 7), name="boxes", finite=True)
    out = np.full(len(points), -1, np.int64)
    for k in range(len(boxes) - 1, -1, -1):  # backwards, so that the first box wins
        out[points_in_box(points, boxes[k])] = k
    return out


def transform_boxes(transform: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Move (M, 7) boxes by a (4, 4) transform whose rotation is about z only; returns (M, 7)."""
    check_array(boxes, (None, 7), name="boxes", finite=True)
    rotation = transform[:3, :3]
    if not np.allclose(rotation[2], [0, 0, 1], atol=1e-6):
        raise ValueError("transform_boxes: the transform must keep z up (a rotation about z only)")
    out = boxes.copy()
    out[:, :3] = boxes[:, :3] @ rotation.T + transform[:3, 3]
    out[:, 6] = wrap_angle(boxes[:, 6] + np.arctan2(rotation[1, 0], rotation[0, 0]))
    return out


def group_bounds(points: np.ndarray, group_ids: np.ndarray, num_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of each group of points.

    Args:
        points: (N, 3) points.
        group_ids: (N,) group of each point, in [0, num_groups).
        num_groups: G.

    Returns:
        ``(lo, hi)``: (G, 3) float64 minimum and maximum corners; +inf / -inf for empty groups.
    """
    if len(group_ids) != len(points):
        raise ValueError(f"group_bounds: {len(group_ids)} group ids for {len(points)} points")
    lo = np.full((num_groups, 3), np.inf)
    hi = np.full((num_groups, 3), -np.inf)
    if not len(group_ids):
        return lo, hi
    # Sorted runs of each group reduced at once (np.minimum.at, one point at a time, was the
    # slowest step of merging patches).
    order = np.argsort(group_ids, kind="stable")
    sorted_ids = np.asarray(group_ids)[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_ids[1:] != sorted_ids[:-1]]))
    grouped = np.asarray(points)[order]
    lo[sorted_ids[starts]] = np.minimum.reduceat(grouped, starts, axis=0)
    hi[sorted_ids[starts]] = np.maximum.reduceat(grouped, starts, axis=0)
    return lo, hi
