"""The front half's settings: ``FrontEndParams`` (frozen, validated), its named ``PRESETS`` and
the one rule that picks a preset for a data set. Checkpoints carry the settings their proposals
were made with, whole (``to_dict`` / ``from_dict``), so a model is always run on the same front
half it was trained on."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import Literal, get_args

from factorydet_core.proposals.candidates import FeatureKind, Weighting
from factorydet_core.proposals.cloud import MIN_CELL_M
from factorydet_core.proposals.segment import SegmentationParams
from factorydet_core.proposals.voxels import DEFAULT_VOXEL_SIZE
from factorydet_core.settings_check import Setting, short_repr
from factorydet_core.types import InputError

MAX_HISTORY_FRAMES = 10
"""The most earlier frames accumulated with the current one: each is one more frame of points
through the whole front half (the benchmarks measured 2)."""

MAX_EXTENT_M = 1000.0
"""The farthest a crop reaches from the vehicle, metres: a factory hall, not a city."""

_HEIGHT = Setting(float, -MAX_EXTENT_M, MAX_EXTENT_M)

_SETTINGS: dict[str, Setting] = {
    "history_frames": Setting(int, 0, MAX_HISTORY_FRAMES),
    "icp_between_frames": Setting(bool),
    "crop_radius_m": Setting(float, 0.0, MAX_EXTENT_M, low_open=True, optional=True),
    "prune_m": Setting(float, 0.0, 10.0),
    "max_points": Setting(int, 1_000, 100_000_000, optional=True),
    "remove_floor": Setting(bool),
    "floor_distance_m": Setting(float, 0.0, 10.0),
    # Each occupied voxel's Fisher vector takes 10 kB (20 x 5 x 5 x 5 float32): a centimetre cell
    # already holds about one point, and finer ones would only cost memory.
    "voxel_size_m": Setting(float, 0.01, 10.0),
    "segment_on": Setting(str, choices=("points", "voxels")),
    "min_proposal_points": Setting(int, 1, 1_000_000),
    "weighting": Setting(str, choices=get_args(Weighting)),
    "feature": Setting(str, choices=get_args(FeatureKind)),
    "include_history": Setting(bool),
    "complete_boxes": Setting(bool),
    "align_to_scene": Setting(bool),
    "include_patches": Setting(bool),
}
"""The scalar settings of ``FrontEndParams`` and what each may hold (``crop_z_m`` and
``segmentation`` are checked on their own)."""


@dataclasses.dataclass(frozen=True)
class FrontEndParams:
    """Settings of the front half. ``PRESETS`` holds the documented starting points."""

    history_frames: int = 0
    """m: earlier frames accumulated with the current one (needs the frames passed to ``propose``)."""
    icp_between_frames: bool = False
    """Refine the odometry of accumulated frames by ICP against the current frame."""
    crop_radius_m: float | None = 25.0
    """Horizontal range kept around the vehicle; ``None`` keeps everything."""
    crop_z_m: tuple[float, float] | None = (-0.5, 4.5)
    """Height range kept (drops the roof); ``None`` keeps everything."""
    prune_m: float = 0.05
    """Voxel down-sampling cell; 0 keeps every point."""
    max_points: int | None = 120_000
    """A cropped and pruned cloud of more points is pruned again with a coarser cell, the finest
    that leaves at most this many (``cloud.cap_points``): what follows costs time and memory by
    the points, and a dense scan (millions of points, terrestrial or accumulated) then costs what
    a sparse frame does. An AGV frame of 80,000 points is below it. ``None``: no cap."""
    remove_floor: bool = True
    """Remove the floor plane, which touches every object."""
    floor_distance_m: float = 0.06
    """Points within this distance of the floor plane are floor."""
    voxel_size_m: float = DEFAULT_VOXEL_SIZE
    """Cell of the sparse grid whose voxels get Fisher vectors."""
    segmentation: SegmentationParams = SegmentationParams()
    segment_on: Literal["points", "voxels"] = "points"
    """Graph nodes of the cut pursuit: the pruned points, or the occupied voxels (their centroids;
    the paper's patches are sets of voxels, and it is several times faster)."""
    min_proposal_points: int = 30
    """Smaller segments are not proposed."""
    weighting: Weighting = "points"
    """Voxel weights when aggregating Fisher vectors (Eq. 7)."""
    feature: FeatureKind = "aggregated"
    """Proposal feature: "aggregated" voxel features, "direct" 3DmFV of the proposal's points, or
    "none" (no 3DmFV: for back halves that read the points, as the learned box head does;
    ``Detector.detect`` proposes so for a model that reads none whatever this says)."""
    include_history: bool = True
    """Also propose the intermediate unions of the merge hierarchy."""
    complete_boxes: bool = True
    """Also propose each segment with its box completed behind the visible side."""
    align_to_scene: bool = True
    """With ``complete_boxes``, also propose each segment boxed at the scene's heading (round
    objects' own boxes have none; ``build_proposals``)."""
    include_patches: bool = True
    """Also propose single patches (an object may be exactly one patch that merging then grew)."""

    def __post_init__(self) -> None:
        # Every value is checked whatever built it (a checkpoint's note, a run's record in the
        # session database, ``--set``, code), and kept as a plain Python value.
        for name, setting in _SETTINGS.items():
            object.__setattr__(self, name, setting.check(name, getattr(self, name)))
        if 0 < self.prune_m < MIN_CELL_M:
            raise InputError(
                f"prune_m must be 0 (keep every point) or at least {MIN_CELL_M} m, got {self.prune_m}"
            )
        if self.crop_z_m is not None:
            low, high = _HEIGHT.check_tuple("crop_z_m", self.crop_z_m, length=2)
            if not low < high:
                raise InputError(f"crop_z_m must be (low, high) with low < high, got {(low, high)}")
            object.__setattr__(self, "crop_z_m", (low, high))
        if not isinstance(self.segmentation, SegmentationParams):
            raise InputError(
                f"segmentation must be a SegmentationParams, got {short_repr(self.segmentation)}"
            )

    def to_dict(self) -> dict:
        """Every setting, JSON-ready (tuples as lists, ``segmentation`` as a nested dict)."""

        def plain(value):
            if isinstance(value, tuple):
                return [plain(v) for v in value]
            if isinstance(value, dict):
                return {k: plain(v) for k, v in value.items()}
            return value

        return plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, values: Mapping[str, object]) -> FrontEndParams:
        """The settings ``to_dict`` wrote; missing names keep their defaults (a checkpoint from
        before a setting existed ran without it), except those of ``SEGMENTATION_BEFORE``, which
        such a checkpoint ran the earlier way.

        Raises:
            InputError: for an unknown name or a bad value.
        """
        if not isinstance(values, Mapping):
            raise InputError(f"front-end settings must map names to values, got {short_repr(values)}")
        values = dict(values)
        segmentation = values.pop("segmentation", None)
        if segmentation is None:
            segmentation = {}
        if not isinstance(segmentation, Mapping):
            raise InputError(
                f"front-end settings: segmentation must be a mapping, got {short_repr(segmentation)}"
            )
        unknown = set(segmentation) - _SEGMENTATION_NAMES
        if unknown:
            raise InputError(f"front-end settings: unknown segmentation setting {_names(unknown)}")
        if segmentation:
            # A record from before a setting existed ran the way the code then did, not as today's
            # default says.
            given = set(segmentation) | set(values)
            earlier = {k: v for k, v in SEGMENTATION_BEFORE.items() if k not in given}
            segmentation = {**earlier, **segmentation}
        params = cls().with_changes(values)  # segmentation names at the top level too
        return dataclasses.replace(
            params, segmentation=dataclasses.replace(params.segmentation, **segmentation)
        )

    def replace(self, **changes: object) -> FrontEndParams:
        """A copy with ``changes``; ``segmentation`` fields may be given by name too.

        Raises:
            InputError: for an unknown name or a bad value.
        """
        return self.with_changes(changes)

    def with_changes(self, changes: Mapping[str, object]) -> FrontEndParams:
        """``replace`` with the changes as a mapping (a parsed ``--set`` or a record's overrides,
        whose names need not even be texts).

        Raises:
            InputError: for an unknown name or a bad value.
        """
        if not isinstance(changes, Mapping):
            raise InputError(f"front-end overrides must map names to values, got {short_repr(changes)}")
        own_names = {f.name for f in dataclasses.fields(self)} - {"segmentation"}
        unknown = set(changes) - _SEGMENTATION_NAMES - own_names
        if unknown:
            raise InputError(
                f"unknown parameter {_names(unknown)}; "
                f"choose from {', '.join(sorted(own_names | _SEGMENTATION_NAMES))}"
            )
        own = {name: value for name, value in changes.items() if name in own_names}
        segmentation = {name: value for name, value in changes.items() if name in _SEGMENTATION_NAMES}
        if segmentation:
            own["segmentation"] = dataclasses.replace(self.segmentation, **segmentation)
        return dataclasses.replace(self, **own)


_SEGMENTATION_NAMES = frozenset(f.name for f in dataclasses.fields(SegmentationParams))

SEGMENTATION_BEFORE: dict[str, object] = {"split_structure": True}
"""Segmentation settings whose default changed, with the value that records written before the
setting existed ran with (``FrontEndParams.from_dict``)."""


def _names(names: Iterable[object]) -> str:
    """Setting names for a one-line message: sorted, at most five, any that is not a plain name
    quoted and cut short (a hand-edited file's key may hold anything, line breaks included)."""
    shown = sorted(n if isinstance(n, str) and n.isidentifier() else short_repr(n) for n in names)
    more = f" and {len(shown) - 5} more" if len(shown) > 5 else ""
    return ", ".join(shown[:5]) + more


PRESETS: dict[str, FrontEndParams] = {
    # The AGV's 12-sensor frames of a factory hall (the simulator's data).
    "agv": FrontEndParams(
        # The sensors' beams are 0.7 x 1.2 degrees apart: 1.5 times that spacing (0.04 m per
        # metre) keeps far objects in one piece. Measured with `bench pipeline` on the corpus's
        # 20 test frames: truck option recall 0.675 at 0 (a fixed 0.3 m), 0.818 at 0.03, 0.883
        # at 0.04, 0.870 at 0.05; the other classes within 0.02 either way.
        segmentation=SegmentationParams(max_edge_per_range=0.04),
    ),
    # One static indoor scan (ScanNet, S3DIS, a labelCloud file): denser, smaller objects on
    # furniture, no roof to cut, no range limit.
    "indoor": FrontEndParams(
        crop_radius_m=None,
        crop_z_m=None,
        prune_m=0.04,
        voxel_size_m=0.2,
        segmentation=SegmentationParams(
            k_features=20,
            k_graph=10,
            max_edge_m=0.15,
            regularization=0.1,
            merge_threshold=0.15,
            max_object_size_m=(3.0, 2.2),
            # Dense reconstructed meshes: 10-point slivers are noise here, not crate corners
            # (measured on the three ScanNet scenes: higher recall, fewer proposals than 3).
            min_patch_points=10,
        ),
    ),  # fmt: skip
}


def preset_for(num_sensors: int) -> str:
    """The preset for data of ``num_sensors`` sensors: "agv" for the AGV's multi-sensor frames,
    "indoor" for single scans (ScanNet, S3DIS, a labelling tool's file)."""
    return "agv" if num_sensors > 1 else "indoor"


def front_end_params(
    preset: str | None = None, overrides: Mapping[str, object] | None = None, num_sensors: int = 1
) -> FrontEndParams:
    """``PRESETS[preset]`` (``preset_for(num_sensors)`` when ``None``) with ``overrides``
    (``FrontEndParams.replace``'s names, segmentation fields included).

    Raises:
        InputError: for an unknown preset, name or value.
    """
    if preset is None or (isinstance(preset, str) and not preset):
        preset = preset_for(num_sensors)
    if not isinstance(preset, str) or preset not in PRESETS:
        raise InputError(f"unknown preset {short_repr(preset)}; choose from {', '.join(PRESETS)}")
    return PRESETS[preset].with_changes(overrides if overrides is not None else {})


def front_end_from_record(record: object) -> FrontEndParams | None:
    """The settings a checkpoint's note or a training run's record holds: ``to_dict``'s output,
    or (checkpoints from before the settings were saved whole) ``{"preset": ..., "overrides":
    {...}}``. ``None`` when it names none: the data's preset then applies.

    Raises:
        InputError: for a record that is not a mapping, an unknown preset, name or value.
    """
    if record is None:
        return None
    if not isinstance(record, Mapping):
        raise InputError(f"front-end settings must map names to values, got {short_repr(record)}")
    if not record:
        return None
    if set(record) <= {"preset", "overrides"}:
        preset, overrides = record.get("preset"), record.get("overrides")
        if preset is None or preset == "":
            return None
        overrides = {} if overrides is None else overrides
        if isinstance(overrides, Mapping):  # (anything else is refused by front_end_params)
            overrides = {**SEGMENTATION_BEFORE, **overrides}  # a record from before them
        return front_end_params(preset, overrides)
    return FrontEndParams.from_dict(record)
