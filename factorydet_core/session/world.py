"""Label once: the session's frames placed in one world frame, so that a static object's box drawn
in one frame is the same object's box in every frame where it has points.

The paper annotated each object of its factory once, in the global map, and projected it into the
frames. Here the map is the frames themselves: each frame's pose is its odometry corrected by ICP
against the frame before (odometry drifts by a degree of heading over a dozen metres, which moves
a box 15 m away by a quarter of a metre), and a box moves between frames by those poses. The
vehicle drives on the floor: a pose is a heading and a position on it, at the odometry's height.
Chained ICP drifts by the rig's calibration error, step after step: the frames are merged for it
with extrinsics refined until they settle (``registration_extrinsics``). No GUI here: the app and
the command line call these, and ``store.SessionDB`` writes what they place.

People and trucks move: their boxes are per frame (``MOVING_CLASSES``); a class change still
applies to the whole object.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from factorydet_core.geometry import invert_transform, points_in_box, rotation_z, transform_boxes, wrap_angle
from factorydet_core.proposals.merge import merge_frame, o3d_cloud, refine_extrinsics
from factorydet_core.session.queue import queue_order
from factorydet_core.types import Frame, InputError, check_array

MOVING_CLASSES: frozenset[str] = frozenset({"person", "truck"})
"""Classes whose objects move between frames: their boxes are not carried from frame to frame."""

REGISTRATION_VOXEL_M = 0.1
"""Thinning of each frame's cloud before ICP."""
COUNT_VOXEL_M = 0.05
"""Thinning of each frame's cloud kept for counting an object's points (a 0.6 m barrel seen from
one side keeps dozens of points; the floor under it is left out by ``FLOOR_MARGIN_M``)."""
SURFACE_MARGIN_M = 0.02
"""How far outside its box (every side but the bottom) a point still counts for the object: a box
fits the object's surface, and the LiDAR's range noise (1.5 cm in the simulator) puts half of
that surface's points outside it; in a frame that sees an object by a few points those were often
all outside."""
FLOOR_MARGIN_M = 0.02
"""The bottom of a box that does not count its points: boxes stand on the floor, whose points
would otherwise make every box 'visible'. With ``SURFACE_MARGIN_M``, chosen on validation
factories (simulator seeds 201-203, ``bench world-labels --heldout-seeds 201,202,203``) as the
margins with the most frames shown where the object has points less twice those shown where it
has none (a box on empty space costs a labeller more than a missing box on an object of a few
points), with the poses of the detector's calibration. With the settled calibration's poses a 1
cm floor band scores two tenths of a percent higher on both the validation and the held-out
factories, for more boxes on no point of the object: too small a gain to move it."""
MIN_POINTS = 1
"""A frame shows an object when at least this many of its (thinned) points lie in its counting
box (``counting_box``). One: two left out most frames where an object has 1 to 4 points
(``bench world-labels`` sweeps it)."""
MIN_FITNESS = 0.3
"""The least ICP fitness (share of points with a correspondence) trusted; below it the frame keeps
its odometry step."""
REGISTRATION_CALIBRATION_ROUNDS = 8
"""Passes of ``merge.refine_extrinsics`` over the sensors for the extrinsics the frames are
registered with. The sensors settle one another slowly at the finest correspondence distance: the
detector's three passes leave each sensor tilted by a few tenths of a degree, and a merged cloud
that bent makes every ICP step a little wrong the same way, so the chained poses drift with the
trajectory's length. ``bench world-labels`` measures both against the truth's poses."""


@dataclasses.dataclass(frozen=True)
class WorldFrames:
    """Every frame of a data set placed in one world frame, with what each frame saw."""

    T_world_vehicle: np.ndarray
    """(F, 4, 4) float64: each frame's corrected pose, a rotation about +z only (boxes stay upright)."""
    fitness: np.ndarray
    """(F,) float64: ICP fitness of each frame against the one before (1 for the first frame, 0 where
    the odometry step was kept)."""
    clouds: tuple[np.ndarray, ...]
    """F arrays (K_f, 3) float32: each frame's merged points in its vehicle frame, thinned to
    ``COUNT_VOXEL_M``."""

    def __post_init__(self) -> None:
        check_array(self.T_world_vehicle, (None, 4, 4), name="T_world_vehicle", finite=True)
        num_frames = len(self.T_world_vehicle)
        check_array(self.fitness, (num_frames,), name="fitness")
        if len(self.clouds) != num_frames:
            raise InputError(f"WorldFrames: {len(self.clouds)} clouds for {num_frames} poses")
        for k, cloud in enumerate(self.clouds):
            check_array(cloud, (None, 3), name=f"cloud of frame {k}")

    @property
    def num_frames(self) -> int:
        return len(self.T_world_vehicle)


@dataclasses.dataclass(frozen=True)
class Placement:
    """One box carried into every frame."""

    boxes: np.ndarray
    """(F, 7) float64: the box in each frame's vehicle frame."""
    num_points: np.ndarray
    """(F,) int64: each frame's thinned points inside the box (``counting_box``: its surface
    grown by ``SURFACE_MARGIN_M``, its bottom ``FLOOR_MARGIN_M`` left out)."""
    visible_mask: np.ndarray
    """(F,) bool: frames that show the object (``MIN_POINTS`` or more, and the frame it was drawn in)."""

    def for_store(self) -> tuple[dict[int, tuple[float, ...]], list[int]]:
        """``({frame: box} of every frame, frames that show it)``: what ``SessionDB.update_object``
        (``boxes``, ``show_in``) and ``SessionDB.review``'s ``place`` take."""
        boxes = {f: tuple(box) for f, box in enumerate(self.boxes.tolist())}
        return boxes, np.flatnonzero(self.visible_mask).tolist()

    def best_frame(self, frame_index: int) -> int:
        """The frame that sees the object best, by its points in the box (``num_points``);
        ``frame_index`` (the frame the box was drawn in) when none has more. An object mined where
        it is a few points can be plain to see a few frames on: the review panel offers that view
        (``bench hitl --review-best-view``'s reviewer judges it there)."""
        here = int(frame_index)
        if not 0 <= here < len(self.num_points):
            raise InputError(f"frame {frame_index} is not one of the {len(self.num_points)} frames placed")
        best = int(np.argmax(self.num_points))
        return here if self.num_points[here] >= self.num_points[best] else best

    def boxes_by_frame(self, frames=None) -> dict[int, tuple[float, ...]]:
        """``{frame index: box}`` for the visible frames and any of ``frames`` besides."""
        wanted = set(np.flatnonzero(self.visible_mask).tolist()) | {int(f) for f in frames or ()}
        return {f: tuple(float(v) for v in self.boxes[f]) for f in sorted(wanted)}


def planar(transform: np.ndarray) -> np.ndarray:
    """(4, 4) the transform with its rotation reduced to its heading about +z (translation kept)."""
    transform = np.asarray(transform, np.float64)
    out = np.eye(4)
    out[:3, :3] = rotation_z(np.arctan2(transform[1, 0], transform[0, 0]))
    out[:3, 3] = transform[:3, 3]
    return out


def _thinned(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(K, 3) float32: the first point of every occupied voxel (deterministic, no library)."""
    if not len(points):
        return np.zeros((0, 3), np.float32)
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.ascontiguousarray(points[np.sort(first)], dtype=np.float32)


def register_frames(
    frames: Sequence[Frame],
    T_vehicle_sensor: np.ndarray | None = None,
    *,
    use_icp: bool = True,
    max_correspondence_m: float = 0.5,
    poses: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> WorldFrames:
    """Place every frame in one world frame: the first frame's odometry pose, then each next frame
    by point-to-plane ICP against the one before, started from their odometry step.

    Args:
        frames: the data set's frames in time order (a ``Dataset`` reads them one at a time).
        T_vehicle_sensor: (S, 4, 4) extrinsics to merge with; each frame's nominal ones by default.
        use_icp: False keeps the odometry (what ``bench world-labels`` compares against).
        max_correspondence_m: the first ICP pass's correspondence distance; a second pass uses a
            third of it.
        poses: (F, 4, 4) poses registered before (``session_world``'s cache): only the clouds
            are read.
        progress: called with ``(frames done, frames)``.

    Returns:
        The frames' poses, ICP fitness and thinned clouds.
    """
    num_frames = len(frames)
    if num_frames == 0:
        raise InputError("register_frames: no frames given")
    known = poses is not None
    if known:
        check_array(poses, (num_frames, 4, 4), name="poses", finite=True)
        use_icp = False
    poses = np.array(poses, np.float64) if known else np.zeros((num_frames, 4, 4))
    fitness = np.zeros(num_frames)
    clouds: list[np.ndarray] = []
    previous_target = None
    previous_odometry = None
    for index in range(num_frames):
        frame = frames[index]
        points = merge_frame(frame, T_vehicle_sensor).points
        clouds.append(_thinned(points, COUNT_VOXEL_M))
        odometry = planar(frame.T_world_vehicle)
        if not known and index == 0:
            poses[0], fitness[0] = odometry, 1.0
        elif not known:
            step = invert_transform(previous_odometry) @ odometry
            if use_icp and len(points) >= 10 and previous_target is not None:
                step, fitness[index] = _icp_step(points, previous_target, step, max_correspondence_m)
            poses[index] = planar(poses[index - 1] @ step)
            # On the floor: a bent merged cloud makes every ICP step climb or sink a little, and
            # chained over a long trajectory that lifts a carried pallet (0.15 m tall) off its own.
            poses[index][2, 3] = odometry[2, 3]
        previous_odometry = odometry
        previous_target = _icp_target(points) if use_icp and len(points) >= 10 else None
        if progress is not None:
            progress(index + 1, num_frames)
    return WorldFrames(T_world_vehicle=poses, fitness=fitness, clouds=tuple(clouds))


def _icp_target(points: np.ndarray):
    import open3d as o3d

    target = o3d_cloud(points).voxel_down_sample(REGISTRATION_VOXEL_M)
    target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
    return target


def _icp_step(points: np.ndarray, target, start: np.ndarray, distance_m: float) -> tuple[np.ndarray, float]:
    """The step from the previous frame to this one by ICP, coarse then fine; the odometry step
    ``start`` where ICP finds too few correspondences (``MIN_FITNESS``)."""
    import open3d as o3d

    source = o3d_cloud(points).voxel_down_sample(REGISTRATION_VOXEL_M)
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    transform = start
    result = None
    for distance in (distance_m, distance_m / 3):
        result = o3d.pipelines.registration.registration_icp(source, target, distance, transform, estimation)
        transform = result.transformation
    if result is None or result.fitness < MIN_FITNESS:
        return start, 0.0
    # open3d sums in parallel: snap the last bits so that a re-run places boxes identically.
    return np.round(np.asarray(transform), 10), float(result.fitness)


def count_points(
    world: WorldFrames,
    boxes: np.ndarray,
    *,
    surface_margin_m: float = SURFACE_MARGIN_M,
    floor_margin_m: float = FLOOR_MARGIN_M,
) -> np.ndarray:
    """(F,) int64: each frame's thinned points inside its own box ``boxes[f]`` (F, 7) grown by
    ``surface_margin_m`` on every side but the bottom, its bottom ``floor_margin_m`` left out (the
    floor it stands on)."""
    check_array(boxes, (world.num_frames, 7), name="boxes", finite=True)
    return np.array(
        [_count(cloud, box, surface_margin_m, floor_margin_m) for cloud, box in zip(world.clouds, boxes)],
        np.int64,
    )


def counting_box(box, surface_margin_m: float = SURFACE_MARGIN_M, floor_margin_m: float = FLOOR_MARGIN_M):
    """(7,) the box whose points count for ``box`` (7,): grown by ``surface_margin_m`` on each side
    and at the top, its bottom raised by ``floor_margin_m`` (a box too low for that keeps its
    bottom)."""
    box = np.array(box, np.float64)
    bottom, top = box[2] - box[5] / 2, box[2] + box[5] / 2 + surface_margin_m
    if box[5] > 2 * floor_margin_m:
        bottom += floor_margin_m
    box[2], box[5] = (bottom + top) / 2, top - bottom
    box[3:5] += 2 * surface_margin_m
    return box


def _count(
    cloud: np.ndarray, box, surface_margin_m: float = SURFACE_MARGIN_M, floor_margin_m: float = FLOOR_MARGIN_M
) -> int:
    """Points of ``cloud`` (K, 3) in ``counting_box(box)``."""
    return int(points_in_box(cloud, counting_box(box, surface_margin_m, floor_margin_m)).sum())


def place_box(world: WorldFrames, frame_index: int, box, *, min_points: int = MIN_POINTS) -> Placement:
    """Carry a box drawn in one frame into every frame, and say where the object shows.

    Args:
        frame_index: the frame whose vehicle frame ``box`` is in.
        box: (7,) ``(cx, cy, cz, dx, dy, dz, yaw)``.
        min_points: the least thinned points in the box for a frame to show the object.
    """
    if not 0 <= int(frame_index) < world.num_frames:
        raise InputError(f"frame {frame_index} is not one of the {world.num_frames} frames placed")
    box = np.asarray(box, np.float64).reshape(7)
    check_array(box, (7,), name="box", finite=True)
    in_world = transform_boxes(world.T_world_vehicle[int(frame_index)], box[None])
    boxes = np.stack([transform_boxes(invert_transform(T), in_world)[0] for T in world.T_world_vehicle])
    boxes[int(frame_index)] = box  # exactly as drawn, no round trip
    num_points = count_points(world, boxes)
    visible = num_points >= min_points
    visible[int(frame_index)] = True
    return Placement(boxes=boxes, num_points=num_points, visible_mask=visible)


@dataclasses.dataclass(frozen=True)
class BestView:
    """Another frame that sees a box's object better than the frame it was drawn (or mined) in."""

    frame_index: int
    num_points: int
    """The thinned points in the box there (``Placement.num_points``)."""
    num_points_here: int
    """... and in the frame it was drawn in."""
    box: np.ndarray
    """(7,) the box carried into that frame."""


def best_view(world: WorldFrames, frame_index: int, box) -> BestView | None:
    """Where the frames see the object of ``box`` (7,), drawn in ``frame_index``, best
    (``Placement.best_frame``); ``None`` when that is ``frame_index`` itself. What the review
    panel's *Look where it is seen best* shows, and where ``bench hitl``'s reviewer judges a place
    too sparse for the policy in its own frame (``--review-best-view``)."""
    placement = place_box(world, frame_index, box)
    best = placement.best_frame(frame_index)
    if best == int(frame_index):
        return None
    return BestView(
        frame_index=best,
        num_points=int(placement.num_points[best]),
        num_points_here=int(placement.num_points[int(frame_index)]),
        box=placement.boxes[best].copy(),
    )


def interpolate_boxes(world: WorldFrames, keyframes: dict) -> dict[int, tuple[float, ...]]:
    """A moving object's boxes in the frames between its keyframes (people and trucks: their boxes
    are drawn in some frames, the keyframes, and computed in the frames between).

    Between two consecutive keyframes, in the world frame (the frames' poses), the centre and the
    size go linearly with the frame index and the heading turns the shorter way; each box is then
    carried into its own frame. Frames before the first keyframe and after the last get none.

    Args:
        keyframes: ``{frame_index: box (7,)}`` in each frame's vehicle frame.

    Returns:
        ``{frame_index: box}`` of every frame strictly between two keyframes.
    """
    frames = sorted(int(f) for f in keyframes)
    for f in frames:
        if not 0 <= f < world.num_frames:
            raise InputError(f"keyframe {f} is not one of the {world.num_frames} frames placed")
    in_world = {
        f: transform_boxes(world.T_world_vehicle[f], np.asarray(keyframes[f], np.float64).reshape(1, 7))[0]
        for f in frames
    }
    out: dict[int, tuple[float, ...]] = {}
    for a, b in zip(frames[:-1], frames[1:]):
        start, end = in_world[a], in_world[b]
        turn = float(wrap_angle(end[6] - start[6]))
        for f in range(a + 1, b):
            t = (f - a) / (b - a)
            box = start + t * (end - start)
            box[6] = wrap_angle(start[6] + t * turn)
            local = transform_boxes(invert_transform(world.T_world_vehicle[f]), box[None])[0]
            out[f] = tuple(float(v) for v in local)
    return out


PLACE_IOU = 0.25
"""Two queue items whose boxes, carried into the world frame, overlap this much are one place (the
same rule label once uses to keep from labelling an object twice in a frame)."""


def place_chance(scores) -> float:
    """The chance that at least one of a place's items is a real object, each item's score taken
    as its own, independent chance: ``1 - prod(1 - score)`` (scores clipped to [0, 1])."""
    return 1.0 - float(np.prod(1.0 - np.clip(np.asarray(scores, np.float64), 0.0, 1.0)))


def expected_reach(chances, top: int) -> tuple[float, float]:
    """How many real objects a review queue holds by the model's scores: ``(expected in the first
    ``top`` entries, expected in all)``, the sums of the entries' chances (``place_chance``, or
    an item's score). A reviewer's reach as the app can estimate it without the truth; ``bench
    hitl`` compares the share with the one the truth gives."""
    values = np.clip(np.asarray(chances, np.float64).reshape(-1), 0.0, 1.0)
    return float(values[: max(int(top), 0)].sum()), float(values.sum())


def group_by_place(
    world: WorldFrames, items: Sequence[dict], min_iou: float = PLACE_IOU, order: str = "score"
) -> list[list[int]]:
    """The review queue's items by place: items of one object mined in several frames (and
    duplicates in one frame) are one place, so that one verdict answers them all.

    Greedily, most confident first: each item not yet placed starts a place and takes every item
    not yet placed whose box, carried into the world frame by the frames' poses, overlaps its own
    at ``min_iou`` or more. Overlap with the place's first item, not a chain of overlaps: on a
    shelf of boxes a chain would join neighbour to neighbour into one place. Places come most
    likely an object first: by the chance that at least one of their items is one,
    ``1 - prod(1 - score)`` (a place the model finds again in frame after frame is likelier real
    than one confident detection). With ``order`` "class" the places' classes (their first
    item's predicted class) take turns, each class's places by that chance
    (``session.queue.queue_order``; the run's review order, ``SessionDB.review_order``).

    Args:
        items: dicts with ``frame_index``, ``box`` (7,) in that frame and ``score`` (and
            ``predicted_class`` with ``order`` "class").

    Returns:
        Lists of positions in ``items``, each place's items by decreasing score.
    """
    from factorydet_core.boxes import overlapping_box_pairs

    if not len(items):
        return []
    frames = np.array([int(item["frame_index"]) for item in items])
    boxes = np.array([item["box"] for item in items], np.float64).reshape(-1, 7)
    in_world = np.zeros_like(boxes)
    for frame in np.unique(frames).tolist():  # each frame's boxes carried at once
        rows = frames == frame
        in_world[rows] = transform_boxes(world.T_world_vehicle[frame], boxes[rows])
    first, second = overlapping_box_pairs(in_world, min_iou)  # a queue of thousands: no (M, M) matrix
    scores = np.array([float(item["score"]) for item in items])
    by_score = np.argsort(-scores, kind="stable")
    rank = np.empty(len(items), np.int64)
    rank[by_score] = np.arange(len(items))
    # Each item's overlapping items and itself, most confident first.
    ends = np.concatenate([first, second, np.arange(len(items))])
    starts = np.concatenate([second, first, np.arange(len(items))])
    by_start = np.lexsort((rank[ends], starts))
    ends = ends[by_start]
    bounds = np.searchsorted(starts[by_start], np.arange(len(items) + 1))
    placed = np.zeros(len(items), bool)
    places = []
    for seed in by_score.tolist():
        if placed[seed]:
            continue
        candidates = ends[bounds[seed] : bounds[seed + 1]]
        members = candidates[~placed[candidates]]  # by decreasing score, the seed included
        placed[members] = True
        places.append(members.tolist())
    chance = [place_chance(scores[m]) for m in places]
    ranked = sorted(range(len(places)), key=lambda p: (-chance[p], places[p][0]))
    if order != "score":
        classes = [str(items[places[p][0]]["predicted_class"]) for p in ranked]
        ranked = [ranked[k] for k in queue_order([chance[p] for p in ranked], classes, order).tolist()]
    return [places[p] for p in ranked]


def spread_objects(labels_by_frame: dict, world: WorldFrames, *, min_points: int = MIN_POINTS) -> list[tuple]:
    """What carries each labelled object that stands still into every frame that shows it and has
    no label of it yet (the data set annotates an object only where it has enough points).

    Each object (labels sharing an instance id) is carried from the label whose box holds the most
    points of its own frame, with that label's class; its existing labels are left as they are.

    Args:
        labels_by_frame: ``{frame_index: [store.Label]}`` of every frame (``SessionDB.frame_labels``,
            deleted ones included: a frame where someone deleted the object's label is left alone).
        world: the frames placed in one world frame.

    Returns:
        ``(frame_index, box, class_name, instance_id)`` items for ``SessionDB.add_labels``.
    """
    objects: dict[int, list] = {}
    deleted_in: dict[int, set[int]] = {}
    for labels in labels_by_frame.values():
        for label in labels:
            if label.instance_id is None:
                continue
            if label.deleted:  # someone took the object out of that frame: it stays out
                deleted_in.setdefault(int(label.instance_id), set()).add(label.frame_index)
            elif label.class_name not in MOVING_CLASSES:
                objects.setdefault(int(label.instance_id), []).append(label)
    items = []
    for instance_id, members in sorted(objects.items()):
        labelled = {m.frame_index for m in members} | deleted_in.get(instance_id, set())
        source = max(
            members,
            key=lambda m: (_count(world.clouds[m.frame_index], m.box), -m.frame_index),
        )
        placement = place_box(world, source.frame_index, source.box, min_points=min_points)
        for f in np.flatnonzero(placement.visible_mask):
            if int(f) not in labelled:
                box = tuple(float(v) for v in placement.boxes[f])
                items.append((int(f), box, source.class_name, instance_id))
    return items


def registration_extrinsics(dataset) -> np.ndarray:
    """(S, 4, 4) the rig's extrinsics the frames are registered with: refined as
    ``calibrated_extrinsics`` refines them, but until they settle
    (``REGISTRATION_CALIBRATION_ROUNDS`` passes instead of three)."""
    return calibrated_extrinsics(dataset, rounds=REGISTRATION_CALIBRATION_ROUNDS)


def calibrated_extrinsics(dataset, **refine_options) -> np.ndarray:
    """(S, 4, 4) the rig's extrinsics refined by ICP between its sensors on the first frame, as the
    app's viewer and the detector refine them for the clouds they merge (``merge.refine_extrinsics``
    with its defaults, three passes, unless ``refine_options`` say otherwise; the nominal ones for a
    single sensor). The frames are registered with ``registration_extrinsics``."""
    nominal = np.asarray(dataset.T_vehicle_sensor, np.float64)
    if len(nominal) < 2:
        return nominal
    return refine_extrinsics(dataset.frame(0), nominal, **refine_options).T_vehicle_sensor


def session_world(
    session,
    dataset,
    T_vehicle_sensor: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[WorldFrames, bool]:
    """The session's data set placed in one world frame. The poses (and the extrinsics they were
    registered with) are cached with the session by the data set's content hash; the clouds are
    read again each time.

    Args:
        session: a ``store.Session``.
        dataset: its ``Dataset`` (frames with their odometry).
        T_vehicle_sensor: (S, 4, 4) the extrinsics to register the frames with; by default the
            cached ones, else ``registration_extrinsics`` (the poses are the vehicle's, whatever
            extrinsics the frames are drawn with).

    Returns:
        ``(world, from_cache)``.
    """
    from factorydet_core.session.store import read_cache, write_cache

    # v2: the vehicle's height stays the odometry's (poses cached before drifted in height).
    key = f"world-poses-v2-{dataset.content_hash()}"
    cached = read_cache(session, key) or {}
    cached_extrinsics = cached.get("T_vehicle_sensor")
    usable = (
        cached_extrinsics is not None
        and cached_extrinsics.shape == np.shape(dataset.T_vehicle_sensor)
        and cached.get("T_world_vehicle", np.zeros(0)).shape == (len(dataset), 4, 4)
    )
    if T_vehicle_sensor is None:
        T_vehicle_sensor = cached_extrinsics if usable else registration_extrinsics(dataset)
    T_vehicle_sensor = np.asarray(T_vehicle_sensor, np.float64)
    from_cache = usable and np.allclose(cached_extrinsics, T_vehicle_sensor, atol=1e-9)
    poses = cached["T_world_vehicle"] if from_cache else None
    world = register_frames(_Frames(dataset), T_vehicle_sensor, poses=poses, progress=progress)
    if from_cache:
        world = dataclasses.replace(world, fitness=cached.get("fitness", world.fitness))
    else:
        write_cache(
            session,
            key,
            {
                "T_world_vehicle": world.T_world_vehicle,
                "fitness": world.fitness,
                "T_vehicle_sensor": T_vehicle_sensor,
            },
        )
    return world, from_cache


class _Frames(Sequence):
    """A data set's frames as a sequence, read one at a time."""

    def __init__(self, dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return self.dataset.num_frames

    def __getitem__(self, index):
        return self.dataset.frame(index)


def not_labelled_yet(items: list[tuple], current: dict, keep_frame: int | None = None) -> list[int]:
    """Positions in ``items`` (``(frame_index, box, class_name[, instance_id])``) whose frame has no
    live label overlapping the box (IoU ``store.SAME_OBJECT_IOU`` or more) nor, with an instance id,
    a label of that object: where label once may add the object without labelling it twice.
    ``keep_frame``'s items are kept whatever (the frame the person drew it in).

    Args:
        current: ``{frame_index: [store.Label]}``, the frames' live labels (``add_labels``'s screen
            reads them in its writing transaction).
    """
    from factorydet_core.session.store import labelled_there

    keep = []
    for k, item in enumerate(items):
        frame, box = int(item[0]), item[1]
        labels = [lab for lab in current.get(frame, []) if not lab.deleted]
        if frame == keep_frame:
            keep.append(k)
            continue
        instance_id = item[3] if len(item) > 3 else None
        if instance_id is not None and any(lab.instance_id == instance_id for lab in labels):
            continue
        if labelled_there(box, [lab.box for lab in labels]):
            continue
        keep.append(k)
    return keep


def spread_session(db, world: WorldFrames, author: str, *, min_points: int = MIN_POINTS):
    """Label once what the session labels per frame: every object that stands still gets a label in
    each frame that shows it and has none (``spread_objects``), as one undoable edit. The CLI's
    ``labels spread`` and the app's *Label every frame that shows them* call this.

    Args:
        db: the session's ``SessionDB``.

    Returns:
        The labels added (a ``store.LabelBatch``; empty when every object is labelled everywhere).
    """
    frames = range(db.dataset.num_frames)
    items = spread_objects(db.frame_labels(frames, include_deleted=True), world, min_points=min_points)

    num_objects = len({item[3] for item in items})
    return db.add_labels(
        items,
        author,
        "user",
        screen=lambda current: not_labelled_yet(items, current),  # read again in the writing transaction
        summary=f"label once: {num_objects} object(s) labelled in {len(items)} more frame label(s)",
    )
