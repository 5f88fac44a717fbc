"""Typed, frozen containers passed between pipeline stages.

Every array is made read-only when a container is built, so a stage that tries to mutate its input
fails loudly instead of corrupting a cached frame. Conventions (frames, box layout) are in
``docs/conventions.md``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

CLASS_NAMES: tuple[str, ...] = ("barrel", "bobbin", "box", "cone", "pallet", "person", "truck")
"""The seven object classes of the paper, in class-id order. Background is not a class id here."""


BOX_KINDS: tuple[str, ...] = ("fitted", "completed", "view-completed", "aligned", "aligned-completed")
"""How a proposal's box was made (``Proposals.box_kind``): the point set's L-shape box, the same
completed behind its visible side, the box headed along the line of sight and completed, the box at
the scene's heading (``boxes.scene_heading``), the same completed."""
ANCHOR_BOX_KINDS: tuple[int, ...] = (0, 3)
"""Box kinds that class sizes are set into (``BoxSizePrior.anchored`` and the like): the fitted
box and the scene-aligned one, the two that hug the seen points."""
LEVELS: tuple[str, ...] = ("segment", "union", "patch")
"""Where a proposal's point set comes from (``Proposals.level``)."""
SCORE_FLOOR = 0.05
"""The least score anything is reported at: detections below it are not ranked for AP, get no box
quality prediction (their class probability stays their score) and do not vote on boxes."""
MINING_THRESHOLD = SCORE_FLOOR
"""The loop's and the command line's least score of a mined false positive: the score floor, so
the mined set is every false positive the detector reports (the top N by score go to the
background, as the paper)."""
PROBABILITY_EXPONENT = 0.5
"""The loop's and the command line's power of the class probability in a detection's score (with
box quality: probability ** exponent x predicted IoU). The square root weighs the classifier less
against the predicted IoU and evens out the classes' score scales: on the default corpus's held-out
frames it raised total F at the best threshold on two disjoint frame sets and on the demo's test
frames, and the per-class thresholds training tunes all came out equal (README, "The default
model")."""
PRELABEL_SCORE = 0.5
"""Pre-labelling (``session.editing.prelabel_frame``) takes the model's detections scoring this
much or more, by default: above the operating threshold, since each one costs a person a look."""
SCORE_THRESHOLD = 0.35
"""The loop's and the command line's operating score, the best single threshold of that score on
the default corpus's frames 40-49."""

METHODS: tuple[str, ...] = ("paper", "box_head", "head_options")
"""The back halves a model can be (``model.DetectionModel.method``): the paper's 3DmFV-Net
classifier choosing among the size prior's box options by the box quality regressor; the learned
box head classifying and boxing each point set; the box head classifying and the regressor boxing."""
DEFAULT_METHOD = "head_options"
"""The back half ``factorydet train`` and the app's retrain train unless told otherwise: the shipped
model's. On the held-out factories it scored the paper pipeline's F-score with a higher mAP and
recognition, and kept far more of the background as background (``docs/bench/quality.md``)."""

QUEUE_ORDERS: tuple[str, ...] = ("score", "class")
"""How mined negatives are cut (``LoopSettings.queue_order``) and queued for review
(``LoopSettings.review_order`` "auto"; ``session.queue.queue_order``): by score, as
the paper adds the top N false positives; or by class, each predicted class taking turns."""
REVIEW_ORDERS: tuple[str, ...] = (*QUEUE_ORDERS, "learned")
"""How the review queue is ordered (``LoopSettings.review_order``): as a cut's order, or learned
from the session's own verdicts (``session.review_rank``; with the queue grouped by place)."""

THRESHOLD_OBJECTIVES: tuple[str, ...] = ("class", "total")
"""What per-class thresholds are tuned for (``LoopSettings.threshold_objective``;
``metrics.tune_class_thresholds``): each class's own F-score, or the F-score of all classes'
detections pooled, the figure the benchmarks report. A class of few, poorly scored objects reaches
its own best F low down its scores, where its false positives cost the pooled F more than its
matches give; a class far better than the rest goes the other way, below its own best."""

MAX_RAY_WORKERS = 4096
"""The most Ray workers a batch may ask for (``scale.runner.Execution``, a session's setting)."""


class InputError(ValueError):
    """Bad input data: the message names the file or array and the problem, on one line."""


class FrameLostError(RuntimeError):
    """A batch frame's worker died ``scale.runner.FRAME_ATTEMPTS`` times while computing it: out of
    memory, or a crash in native code. The message names the frame and the output folder."""


class Cancelled(Exception):  # noqa: N818 - a request, not an error
    """Raised by long work when its ``should_stop`` callback asked it to stop."""


def check_threshold_objective(objective: object) -> str:
    """``objective`` if it is one of ``THRESHOLD_OBJECTIVES``; ``InputError`` otherwise (the
    settings', ``train_with_mining``'s and ``metrics.tune_class_thresholds``'s check)."""
    if objective not in THRESHOLD_OBJECTIVES:
        objectives = ", ".join(THRESHOLD_OBJECTIVES)
        raise InputError(f"threshold_objective must be one of {objectives}, got {objective!r}")
    return str(objective)


def _frozen(array: np.ndarray) -> np.ndarray:
    """Return ``array`` as a read-only C-contiguous array that nobody else can write to.

    The caller's array is never made read-only itself: a writeable array, or a view of memory that
    may be writeable elsewhere, is copied first. Only an array that is already read-only and owns
    its memory (such as another container's field) is shared.
    """
    if array.flags.writeable or array.base is not None or not array.flags.c_contiguous:
        array = np.array(array, order="C", copy=True)
    array.flags.writeable = False
    return array


def check_array(
    array: np.ndarray,
    shape: tuple[int | None, ...],
    *,
    name: str,
    finite: bool = False,
) -> None:
    """Raise ``InputError`` unless ``array`` has ``shape`` (``None`` matches any length).

    Args:
        array: the array to check.
        shape: expected shape; ``None`` entries are free.
        name: how the message names the array.
        finite: also require every element to be finite.
    """
    if not isinstance(array, np.ndarray):
        raise InputError(f"{name}: expected a numpy array, got {type(array).__name__}")
    if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{name}: expected shape {want}, got {array.shape}")
    if finite and array.dtype.kind == "f" and not np.isfinite(array).all():
        num_bad = (
            int((~np.isfinite(array)).any(axis=-1).sum())
            if array.ndim > 1
            else int((~np.isfinite(array)).sum())
        )
        raise InputError(f"{name}: {num_bad} rows hold NaN or Inf values")


@dataclasses.dataclass(frozen=True)
class BoxLabels:
    """Labelled instances of one frame; row i of every array belongs to instance i."""

    boxes: np.ndarray
    """(M, 7) float64: (cx, cy, cz, dx, dy, dz, yaw) in the vehicle frame, metres and radians."""
    class_ids: np.ndarray
    """(M,) int32: index into the frame's ``class_names``."""
    instance_ids: np.ndarray
    """(M,) int64: instance id, > 0, the same object keeps its id across frames."""
    num_points: np.ndarray
    """(M,) int64: number of points of the frame that belong to the instance."""

    def __post_init__(self) -> None:
        num = len(self.boxes) if isinstance(self.boxes, np.ndarray) else -1
        check_array(self.boxes, (None, 7), name="boxes", finite=True)
        check_array(self.class_ids, (num,), name="class_ids")
        check_array(self.instance_ids, (num,), name="instance_ids")
        check_array(self.num_points, (num,), name="num_points")
        object.__setattr__(self, "boxes", _frozen(self.boxes.astype(np.float64, copy=False)))
        object.__setattr__(self, "class_ids", _frozen(self.class_ids.astype(np.int32, copy=False)))
        object.__setattr__(self, "instance_ids", _frozen(self.instance_ids.astype(np.int64, copy=False)))
        object.__setattr__(self, "num_points", _frozen(self.num_points.astype(np.int64, copy=False)))

    def __len__(self) -> int:
        return len(self.boxes)

    def check_class_ids(self, num_classes: int) -> None:
        """Raise ``InputError`` unless every class id indexes a vocabulary of ``num_classes``."""
        if len(self) and (self.class_ids.min() < 0 or self.class_ids.max() >= num_classes):
            raise InputError(f"label class ids must lie in [0, {num_classes})")

    @classmethod
    def empty(cls) -> BoxLabels:
        return cls(
            boxes=np.zeros((0, 7)),
            class_ids=np.zeros(0, np.int32),
            instance_ids=np.zeros(0, np.int64),
            num_points=np.zeros(0, np.int64),
        )


@dataclasses.dataclass(frozen=True)
class Frame:
    """One scan of the vehicle's sensors, as stored: points in each sensor's own frame.

    A single file read from disk (PLY, LAS, ...) is a frame with one sensor whose extrinsic is the
    identity.
    """

    name: str
    """Human-readable frame name, e.g. ``frame_00003`` or the file name."""
    points: np.ndarray
    """(N, 3) float32: points in the frame of the sensor that measured them, metres."""
    sensor_ids: np.ndarray
    """(N,) int16: index into ``T_vehicle_sensor`` of the sensor that measured each point."""
    T_vehicle_sensor: np.ndarray
    """(S, 4, 4) float64: nominal extrinsic of each sensor (sensor frame -> vehicle frame)."""
    T_world_vehicle: np.ndarray
    """(4, 4) float64: vehicle pose from odometry (vehicle frame -> world frame)."""
    labels: BoxLabels
    """Annotated instances, boxes in the vehicle frame."""
    point_instance_ids: np.ndarray
    """(N,) int64: annotated instance id of each point, 0 where the point belongs to none."""
    class_names: tuple[str, ...] = CLASS_NAMES
    """Class vocabulary that ``labels.class_ids`` and ``point_class_ids`` index."""
    colors: np.ndarray | None = None
    """(N, 3) uint8 RGB, when the source has colours."""
    intensity: np.ndarray | None = None
    """(N,) float32 return intensity, when the source has it."""
    origin_offset: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    """(3,) float64: subtracted from the source coordinates on reading (large georeferenced
    coordinates), added back on export."""

    def __post_init__(self) -> None:
        check_array(self.points, (None, 3), name=f"{self.name}: points", finite=True)
        num_points = len(self.points)
        check_array(self.sensor_ids, (num_points,), name=f"{self.name}: sensor_ids")
        check_array(self.T_vehicle_sensor, (None, 4, 4), name=f"{self.name}: T_vehicle_sensor", finite=True)
        check_array(self.T_world_vehicle, (4, 4), name=f"{self.name}: T_world_vehicle", finite=True)
        check_array(self.point_instance_ids, (num_points,), name=f"{self.name}: point_instance_ids")
        check_array(self.origin_offset, (3,), name=f"{self.name}: origin_offset", finite=True)
        num_sensors = len(self.T_vehicle_sensor)
        if num_points and (self.sensor_ids.min() < 0 or self.sensor_ids.max() >= num_sensors):
            raise InputError(f"{self.name}: sensor_ids must lie in [0, {num_sensors})")
        try:
            self.labels.check_class_ids(len(self.class_names))
        except InputError as exc:
            raise InputError(f"{self.name}: {exc}") from None
        if self.colors is not None:
            check_array(self.colors, (num_points, 3), name=f"{self.name}: colors")
            object.__setattr__(self, "colors", _frozen(self.colors.astype(np.uint8, copy=False)))
        if self.intensity is not None:
            check_array(self.intensity, (num_points,), name=f"{self.name}: intensity", finite=True)
            object.__setattr__(self, "intensity", _frozen(self.intensity.astype(np.float32, copy=False)))
        object.__setattr__(self, "class_names", tuple(str(c) for c in self.class_names))
        object.__setattr__(self, "points", _frozen(self.points.astype(np.float32, copy=False)))
        object.__setattr__(self, "sensor_ids", _frozen(self.sensor_ids.astype(np.int16, copy=False)))
        object.__setattr__(self, "T_vehicle_sensor", _frozen(self.T_vehicle_sensor.astype(np.float64)))
        object.__setattr__(self, "T_world_vehicle", _frozen(self.T_world_vehicle.astype(np.float64)))
        object.__setattr__(
            self, "point_instance_ids", _frozen(self.point_instance_ids.astype(np.int64, copy=False))
        )
        object.__setattr__(self, "origin_offset", _frozen(self.origin_offset.astype(np.float64)))

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def num_sensors(self) -> int:
        return len(self.T_vehicle_sensor)

    @property
    def point_class_ids(self) -> np.ndarray:
        """(N,) int32: class id of each point's annotated instance, -1 where there is none."""
        lookup = dict(zip(self.labels.instance_ids.tolist(), self.labels.class_ids.tolist()))
        unique_ids, inverse = np.unique(self.point_instance_ids, return_inverse=True)
        per_unique = np.array([lookup.get(int(i), -1) for i in unique_ids], dtype=np.int32)
        return per_unique[inverse.reshape(-1)] if len(per_unique) else np.zeros(0, np.int32)


@dataclasses.dataclass(frozen=True)
class MergedCloud:
    """All points of one frame in the vehicle frame."""

    points: np.ndarray
    """(N, 3) float32: points in the vehicle frame, metres."""
    sensor_ids: np.ndarray
    """(N,) int16: sensor that measured each point."""
    point_instance_ids: np.ndarray
    """(N,) int64: annotated instance of each point, 0 for none."""
    T_vehicle_sensor: np.ndarray
    """(S, 4, 4) float64: the extrinsics that were used to merge."""
    frame_ages: np.ndarray | None = None
    """(N,) int16: how many frames before the current one each point was measured (0 = current);
    ``None`` means all points are from the current frame."""

    def __post_init__(self) -> None:
        check_array(self.points, (None, 3), name="merged points", finite=True)
        check_array(self.sensor_ids, (len(self.points),), name="merged sensor_ids")
        check_array(self.point_instance_ids, (len(self.points),), name="merged point_instance_ids")
        if self.frame_ages is None:
            object.__setattr__(self, "frame_ages", np.zeros(len(self.points), np.int16))
        check_array(self.frame_ages, (len(self.points),), name="merged frame_ages")
        for field in ("points", "sensor_ids", "point_instance_ids", "T_vehicle_sensor", "frame_ages"):
            object.__setattr__(self, field, _frozen(getattr(self, field)))

    @property
    def num_points(self) -> int:
        return len(self.points)

    def below(self, max_z: float) -> np.ndarray:
        """(N,) bool mask of the points at or below ``max_z`` metres (to look under the roof)."""
        return self.points[:, 2] <= max_z

    def select(self, mask: np.ndarray) -> MergedCloud:
        """A new cloud with the points where the (N,) ``mask`` holds."""
        return dataclasses.replace(
            self,
            points=self.points[mask],
            sensor_ids=self.sensor_ids[mask],
            point_instance_ids=self.point_instance_ids[mask],
            frame_ages=self.frame_ages[mask],
        )


@dataclasses.dataclass(frozen=True)
class VoxelGrid:
    """Occupied cells of a regular grid over a cloud (sparse: empty cells are not stored)."""

    voxel_size: float
    """Edge length of a cell, metres."""
    origin: np.ndarray
    """(3,) float64: corner of cell (0, 0, 0)."""
    coords: np.ndarray
    """(V, 3) int32: integer cell index of every occupied voxel, sorted lexicographically."""
    point_voxel_ids: np.ndarray
    """(N,) int64: the voxel of each point of the cloud the grid was built from."""
    num_points: np.ndarray
    """(V,) int64: points per voxel, all >= 1."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"voxel_size must be a positive number of metres, got {self.voxel_size}")
        check_array(self.origin, (3,), name="voxel grid origin", finite=True)
        check_array(self.coords, (None, 3), name="voxel coords")
        check_array(self.num_points, (len(self.coords),), name="voxel num_points")
        check_array(self.point_voxel_ids, (None,), name="point_voxel_ids")
        for field in ("origin", "coords", "point_voxel_ids", "num_points"):
            object.__setattr__(self, field, _frozen(getattr(self, field)))

    @property
    def num_voxels(self) -> int:
        return len(self.coords)

    @property
    def centres(self) -> np.ndarray:
        """(V, 3) float64 cell centres, metres."""
        return self.origin + (self.coords + 0.5) * self.voxel_size

    def below(self, max_z: float) -> np.ndarray:
        """(V,) bool mask of the voxels whose centre is at or below ``max_z`` metres."""
        return self.centres[:, 2] <= max_z


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """Over-segmentation of a cloud into patches and the object segments built from them."""

    patch_ids: np.ndarray
    """(N,) int64: cut-pursuit patch of each point, in [0, num_patches)."""
    segment_ids: np.ndarray
    """(N,) int64: merged segment of each point, in [0, num_segments)."""
    patch_segment_ids: np.ndarray
    """(P,) int64: the segment each patch ended up in."""
    merge_history: tuple[tuple[int, ...], ...] = ()
    """Patch-id sets of every union formed while merging (each one is also a proposal candidate)."""
    patch_is_structure: np.ndarray | None = None
    """(P,) bool: patches of building structure (walls, racks), never proposed; all False if None."""

    def __post_init__(self) -> None:
        check_array(self.patch_ids, (None,), name="patch_ids")
        check_array(self.segment_ids, (len(self.patch_ids),), name="segment_ids")
        check_array(self.patch_segment_ids, (None,), name="patch_segment_ids")
        if self.patch_is_structure is None:
            object.__setattr__(self, "patch_is_structure", np.zeros(len(self.patch_segment_ids), bool))
        check_array(self.patch_is_structure, (len(self.patch_segment_ids),), name="patch_is_structure")
        object.__setattr__(self, "patch_is_structure", _frozen(self.patch_is_structure.astype(bool)))
        for field in ("patch_ids", "segment_ids", "patch_segment_ids"):
            object.__setattr__(self, field, _frozen(getattr(self, field).astype(np.int64, copy=False)))

    @property
    def num_patches(self) -> int:
        return len(self.patch_segment_ids)

    @property
    def num_segments(self) -> int:
        return int(self.patch_segment_ids.max()) + 1 if len(self.patch_segment_ids) else 0


@dataclasses.dataclass(frozen=True)
class Proposals:
    """Object proposals: a point set, an oriented box and a Fisher-vector feature each."""

    boxes: np.ndarray
    """(M, 7) float64: (cx, cy, cz, dx, dy, dz, yaw) in the vehicle frame."""
    features: np.ndarray | None
    """(M, 20, 5, 5, 5) float32: aggregated 3DmFV of each proposal; ``None`` when the front half
    computes none (``feature`` "none": the back half reads the points)."""
    patch_sets: tuple[tuple[int, ...], ...]
    """The patches each proposal is made of."""
    num_points: np.ndarray
    """(M,) int64: points in the proposal."""
    num_voxels: np.ndarray
    """(M,) int64: occupied voxels the proposal touches."""
    level: np.ndarray
    """(M,) int8: 0 = final merged segment, 1 = an intermediate union of the merge hierarchy,
    2 = a single patch."""
    box_kind: np.ndarray | None = None
    """(M,) int8 index into ``BOX_KINDS``: 0 = box fitted to the points, 1 = that box completed
    behind its visible side (``boxes.complete_hidden_side``), 2 = a box headed along the viewing
    direction, completed behind, 3 = a box at the scene's heading, 4 = that box completed; all 0
    when ``None``."""
    scene_heading: float | None = None
    """Radians in [0, pi/2): the heading the aligned boxes (kinds 3 and 4) were fitted at; ``None``
    without them."""

    @property
    def anchor_mask(self) -> np.ndarray:
        """(M,) bool: the proposals whose boxes class sizes are set into (``ANCHOR_BOX_KINDS``)."""
        return np.isin(self.box_kind, ANCHOR_BOX_KINDS)

    def __post_init__(self) -> None:
        num = len(self.boxes) if isinstance(self.boxes, np.ndarray) else -1
        check_array(self.boxes, (None, 7), name="proposal boxes", finite=True)
        if self.features is not None:
            check_array(self.features, (num, 20, 5, 5, 5), name="proposal features")
        check_array(self.num_points, (num,), name="proposal num_points")
        check_array(self.num_voxels, (num,), name="proposal num_voxels")
        check_array(self.level, (num,), name="proposal level")
        if self.box_kind is None:
            object.__setattr__(self, "box_kind", np.zeros(num, np.int8))
        check_array(self.box_kind, (num,), name="proposal box_kind")
        if len(self.patch_sets) != num:
            raise InputError(f"proposal patch_sets: expected {num}, got {len(self.patch_sets)}")
        for field in ("boxes", "features", "num_points", "num_voxels", "level", "box_kind"):
            if getattr(self, field) is not None:
                object.__setattr__(self, field, _frozen(getattr(self, field)))

    def __len__(self) -> int:
        return len(self.boxes)


@dataclasses.dataclass(frozen=True)
class Detections:
    """Classified proposals: one box per point set, with its class and score.

    The same container holds every scored candidate (``suppressed_by`` all -1) and the result of
    ``scoring.select_detections`` (score threshold and NMS; suppressed candidates stay, with the
    index of the detection that suppressed them, so that the app can show them).
    """

    boxes: np.ndarray
    """(K, 7) float64 boxes in the vehicle frame."""
    class_ids: np.ndarray
    """(K,) int32 index into ``class_names`` (never background)."""
    scores: np.ndarray
    """(K,) float32: probability of ``class_ids``."""
    probabilities: np.ndarray
    """(K, C + 1) float32: probability of each class, background last."""
    proposal_ids: np.ndarray
    """(K,) int64: the proposal (index into ``Proposals``) whose box and point set this is."""
    suppressed_by: np.ndarray
    """(K,) int64: index of the detection that suppressed this one in NMS, -1 if kept."""
    class_names: tuple[str, ...] = CLASS_NAMES

    def __post_init__(self) -> None:
        num = len(self.boxes) if isinstance(self.boxes, np.ndarray) else -1
        check_array(self.boxes, (None, 7), name="detection boxes", finite=True)
        check_array(self.class_ids, (num,), name="detection class_ids")
        check_array(self.scores, (num,), name="detection scores", finite=True)
        check_array(self.probabilities, (num, len(self.class_names) + 1), name="detection probabilities")
        check_array(self.proposal_ids, (num,), name="detection proposal_ids")
        check_array(self.suppressed_by, (num,), name="detection suppressed_by")
        object.__setattr__(self, "class_names", tuple(self.class_names))
        for field, dtype in (
            ("boxes", np.float64),
            ("class_ids", np.int32),
            ("scores", np.float32),
            ("probabilities", np.float32),
            ("proposal_ids", np.int64),
            ("suppressed_by", np.int64),
        ):
            object.__setattr__(self, field, _frozen(getattr(self, field).astype(dtype, copy=False)))

    def __len__(self) -> int:
        return len(self.boxes)

    @property
    def kept_mask(self) -> np.ndarray:
        """(K,) bool: not suppressed."""
        return self.suppressed_by < 0

    def subset(self, ids: np.ndarray) -> Detections:
        """The detections ``ids`` (indices or a mask); ``suppressed_by`` is reset to -1."""
        ids = np.flatnonzero(ids) if np.asarray(ids).dtype == bool else np.asarray(ids, np.int64)
        return Detections(
            boxes=self.boxes[ids],
            class_ids=self.class_ids[ids],
            scores=self.scores[ids],
            probabilities=self.probabilities[ids],
            proposal_ids=self.proposal_ids[ids],
            suppressed_by=np.full(len(ids), -1, np.int64),
            class_names=self.class_names,
        )

    @classmethod
    def empty(cls, class_names: tuple[str, ...] = CLASS_NAMES) -> Detections:
        return cls(
            boxes=np.zeros((0, 7)),
            class_ids=np.zeros(0, np.int32),
            scores=np.zeros(0, np.float32),
            probabilities=np.zeros((0, len(class_names) + 1), np.float32),
            proposal_ids=np.zeros(0, np.int64),
            suppressed_by=np.zeros(0, np.int64),
            class_names=class_names,
        )
