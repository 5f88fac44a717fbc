"""Geometry behind the label editor: boxes to and from a transform gizmo, points inside a screen
rectangle, a camera pose that frames a box, splitting a point set in two, the model's box for a
clicked point. No GUI here; the app calls these."""

from __future__ import annotations

import dataclasses

import numpy as np

from factorydet_core.boxes import fit_box
from factorydet_core.geometry import wrap_angle
from factorydet_core.types import PRELABEL_SCORE, InputError


def box_to_pose(box) -> tuple[np.ndarray, np.ndarray]:
    """The ``(position (3,), wxyz (4,))`` of a box's centre and yaw (a rotation about +z)."""
    box = np.asarray(box, np.float64)
    half = box[6] / 2
    return box[:3].copy(), np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


def pose_to_box(position, wxyz, size) -> np.ndarray:
    """(7,) box at ``position`` with ``size`` (dx, dy, dz) and the yaw of ``wxyz``.

    A gizmo may tilt the box; only the rotation's heading about +z is kept, since every box of the
    project is upright.
    """
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    # The rotated x axis, projected onto the ground plane, gives the heading.
    heading_x = 1 - 2 * (y * y + z * z)
    heading_y = 2 * (x * y + w * z)
    yaw = float(np.arctan2(heading_y, heading_x))
    size = np.asarray(size, np.float64)
    if size.shape != (3,) or not (size > 0).all():
        raise InputError(f"box size must be three positive numbers, got {size.tolist()}")
    return np.array([*np.asarray(position, np.float64), *size, float(wrap_angle(yaw))])


def points_in_screen_rect(
    points: np.ndarray,
    camera_position,
    camera_wxyz,
    fov: float,
    aspect: float,
    screen_min,
    screen_max,
) -> np.ndarray:
    """(N,) bool: points in front of the camera whose projection falls in a screen rectangle.

    Args:
        points: (N, 3) world points.
        camera_position: (3,) camera centre.
        camera_wxyz: (4,) camera orientation in the OpenCV convention (+z forward, +y down), as
            viser reports it.
        fov: vertical field of view, radians.
        aspect: width / height.
        screen_min, screen_max: (2,) rectangle corners in [0, 1] screen coordinates, (0, 0) top left.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    w, x, y, z = np.asarray(camera_wxyz, np.float64) / np.linalg.norm(camera_wxyz)
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    local = (points - np.asarray(camera_position, np.float64)) @ rotation  # camera frame
    depth = local[:, 2]
    ahead = depth > 1e-6
    uv = np.zeros((len(points), 2))
    scale = np.tan(fov / 2)
    uv[ahead] = local[ahead, :2] / depth[ahead, None] / scale
    uv[:, 0] /= aspect
    uv = (uv + 1) / 2
    lo, hi = np.minimum(screen_min, screen_max), np.maximum(screen_min, screen_max)
    return ahead & (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1)


def camera_for_box(
    box, distance_factor: float = 3.0, min_distance: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """``(position (3,), look_at (3,))`` of a camera that frames a box from above and in front
    of its heading's side, far enough to see its neighbours."""
    box = np.asarray(box, np.float64)
    centre = box[:3]
    distance = max(min_distance, distance_factor * float(np.linalg.norm(box[3:6])))
    direction = np.array([-np.cos(box[6] + 0.6), -np.sin(box[6] + 0.6), 0.9])
    direction /= np.linalg.norm(direction)
    return centre + distance * direction, centre


BOX_VIEWS: tuple[str, ...] = ("top", "side", "front")
"""The views of a selected box a labeller checks it from (``camera_view_of_box``)."""


def camera_view_of_box(box, view: str, margin: float = 2.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(position (3,), look_at (3,), up (3,))`` of a camera looking at a box straight from above
    (its heading pointing up the screen), from its left side, or from its front (along its
    heading), far enough that the box fills about 1 / ``margin`` of the view.

    Raises:
        InputError: a view not in ``BOX_VIEWS``.
    """
    box = np.asarray(box, np.float64).reshape(7)
    if view not in BOX_VIEWS:
        raise InputError(f"unknown box view {view!r}; choose from {', '.join(BOX_VIEWS)}")
    centre = box[:3]
    heading = np.array([np.cos(box[6]), np.sin(box[6]), 0.0])
    left = np.array([-heading[1], heading[0], 0.0])
    distance = max(1.5, margin * float(np.max(box[3:6])))
    if view == "top":
        return centre + [0.0, 0.0, distance], centre, heading
    direction = left if view == "side" else heading
    return centre + distance * direction, centre, np.array([0.0, 0.0, 1.0])


MIN_BOX_SIZE_M = 0.02
"""The least size of a box side a resize leaves (the Box fields' minimum)."""


def nudge_box(
    box,
    *,
    forward: float = 0.0,
    left: float = 0.0,
    up: float = 0.0,
    yaw_deg: float = 0.0,
    longer: float = 0.0,
    wider: float = 0.0,
    taller: float = 0.0,
) -> np.ndarray:
    """A box moved along its own heading (``forward``), across it (``left``) and up, turned by
    ``yaw_deg`` counter-clockwise, and grown (negative: shrunk) along its length and width about
    its centre and in height from its bottom (it stands on something); metres. No side goes below
    ``MIN_BOX_SIZE_M``.

    Returns:
        (7,) the new box.
    """
    box = np.array(box, np.float64).reshape(7)
    heading = np.array([np.cos(box[6]), np.sin(box[6])])
    box[:2] += forward * heading + left * np.array([-heading[1], heading[0]])
    box[2] += up
    if yaw_deg:  # (else the heading stays to the bit)
        box[6] = wrap_angle(box[6] + np.radians(yaw_deg))
    bottom = box[2] - box[5] / 2
    box[3:6] = np.maximum(box[3:6] + [longer, wider, taller], MIN_BOX_SIZE_M)
    box[2] = bottom + box[5] / 2
    return box


BOX_FACES: tuple[str, ...] = ("front", "back", "left", "right", "top", "bottom")
"""A box's faces, as ``box_face_points`` gives them and ``resize_box`` takes them: front and back
across its heading (its length, dx), left and right (its width, dy), top and bottom (dz)."""

_FACE_AXES = {
    "front": (0, 1.0),
    "back": (0, -1.0),
    "left": (1, 1.0),
    "right": (1, -1.0),
    "top": (2, 1.0),
    "bottom": (2, -1.0),
}


def _box_axes(box: np.ndarray) -> np.ndarray:
    """(3, 3) the box's heading, left and up unit vectors (rows)."""
    c, s = np.cos(box[6]), np.sin(box[6])
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def box_face_points(box) -> np.ndarray:
    """(6, 3) the centres of a (7,) box's faces, in ``BOX_FACES`` order (where its resize handles go)."""
    box = np.array(box, np.float64).reshape(7)
    axes = _box_axes(box)
    return np.array(
        [box[:3] + sign * box[3 + axis] / 2 * axes[axis] for axis, sign in (_FACE_AXES[f] for f in BOX_FACES)]
    )


def resize_box(box, face: str, point) -> np.ndarray:
    """A box with one face moved to ``point`` (3,) along the face's normal, the opposite face
    where it was (what dragging a resize handle does); heading unchanged, no side below
    ``MIN_BOX_SIZE_M``.

    Returns:
        (7,) the new box.
    """
    if face not in _FACE_AXES:
        raise InputError(f"unknown face {face!r}; choose from {BOX_FACES}")
    box = np.array(box, np.float64).reshape(7)
    axis, sign = _FACE_AXES[face]
    normal = sign * _box_axes(box)[axis]
    opposite = box[:3] - normal * box[3 + axis] / 2
    size = max(float((np.asarray(point, np.float64).reshape(3) - opposite) @ normal), MIN_BOX_SIZE_M)
    box[3 + axis] = size
    box[:3] = opposite + normal * size / 2
    return box


def split_in_two(points: np.ndarray, iterations: int = 20) -> np.ndarray:
    """(N,) 0/1 labels cutting a point set in two (two-means in the ground plane, started from the
    ends of its longest horizontal axis): how a person splits two objects one segment merged."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 2:
        raise InputError("a segment needs at least two points to be split")
    xy = points[:, :2]
    centred = xy - xy.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    along = centred @ axes[0]
    centres = np.stack([xy[along.argmin()], xy[along.argmax()]])
    labels = (along > np.median(along)).astype(np.int64)
    for _ in range(iterations):
        distances = ((xy[:, None, :] - centres[None]) ** 2).sum(axis=2)
        new = distances.argmin(axis=1)
        if (new == labels).all() and _ > 0:
            break
        labels = new
        for k in (0, 1):
            if (labels == k).any():
                centres[k] = xy[labels == k].mean(axis=0)
    if labels.min() == labels.max():  # all in one: fall back to the median cut
        labels = (along > np.median(along)).astype(np.int64)
    return labels


def box_of_points(points: np.ndarray) -> np.ndarray:
    """(7,) the oriented box a new label gets from a selected segment's points."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 3:
        raise InputError(f"a label box needs at least 3 points, the selection has {len(points)}")
    return np.asarray(fit_box(points), np.float64)


@dataclasses.dataclass(frozen=True)
class Suggestion:
    """The model's box for an object a person pointed at (model-assisted labelling)."""

    box: tuple[float, ...]
    """(7,) the candidate's box in the vehicle frame."""
    class_name: str
    score: float
    num_patches: int
    """Patches (cut-pursuit pieces) of the candidate's point set."""


def suggest_box(result, point_index: int) -> Suggestion | None:
    """The model's box for the object a clicked point belongs to: of the scored candidates (one
    per point set, whatever its score: a box below the threshold is still the model's best guess)
    whose point set holds the point's patch, the highest-scoring one.

    Args:
        result: a ``detector.DetectionResult`` of the frame.
        point_index: index of the clicked point in ``result.proposal.cloud``.

    Returns:
        ``None`` when the point is in no proposal (floor, structure, a patch too small).
    """
    segmentation = result.proposal.segmentation
    if not 0 <= int(point_index) < len(segmentation.patch_ids):
        raise InputError(f"point {point_index} is not one of the cloud's {len(segmentation.patch_ids)}")
    patch = int(segmentation.patch_ids[int(point_index)])
    candidates = result.candidates
    if patch < 0 or not len(candidates):
        return None
    patch_sets = result.proposal.proposals.patch_sets
    holds = np.array([patch in patch_sets[int(p)] for p in candidates.proposal_ids], bool)
    if not holds.any():
        return None
    best = int(np.flatnonzero(holds)[np.argmax(candidates.scores[holds])])
    return suggestion_of(candidates, best, result.proposal.proposals)


def suggestion_of(detections, k: int, proposals) -> Suggestion:
    """Detection (or candidate) ``k`` of ``detections`` as a suggestion; ``proposals`` are the ones
    its ``proposal_ids`` index."""
    return Suggestion(
        box=tuple(float(v) for v in detections.boxes[k]),
        class_name=detections.class_names[int(detections.class_ids[k])],
        score=float(detections.scores[k]),
        num_patches=len(proposals.patch_sets[int(detections.proposal_ids[k])]),
    )


def prelabel_frame(db, frame_index: int, detections, author: str, min_score: float = PRELABEL_SCORE):
    """The model's detections of a frame scoring ``min_score`` or more become pre-labels (origin
    'model', unreviewed until a person confirms or edits them), one undoable edit. A detection on a
    place labelled already (``store.labelled_there``: a label, or a pre-label from before) is left
    out, decided in the transaction that writes.

    Args:
        db: the session's ``SessionDB``.
        detections: the frame's detections (``types.Detections``; only the kept ones count).
        author: who asked for them (the edit and its undo are theirs).

    Returns:
        The labels added (a ``store.LabelBatch``; empty when every detection is labelled already).
    """
    from factorydet_core.session.store import PRELABEL_ORIGIN, labelled_there

    if not 0.0 <= float(min_score) <= 1.0:
        raise InputError(f"min_score must lie in [0, 1], got {min_score}")
    chosen = np.flatnonzero(detections.kept_mask & (detections.scores >= float(min_score)))
    chosen = chosen[np.argsort(-detections.scores[chosen], kind="stable")]
    items = [
        (int(frame_index), detections.boxes[k], detections.class_names[int(detections.class_ids[k])])
        for k in chosen
    ]

    def screen(current) -> list[int]:
        taken = [lab.box for lab in current[int(frame_index)]]
        out = []
        for position, (_, box, _) in enumerate(items):
            if not labelled_there(box, taken):
                out.append(position)
                taken.append(tuple(box))  # two detections of one object: the better one only
        return out

    return db.add_labels(
        items,
        author,
        PRELABEL_ORIGIN,
        screen=screen,
        summary=f"pre-label frame {int(frame_index)} (score >= {float(min_score):.2f})",
        scores=[float(detections.scores[k]) for k in chosen],
    )
