"""The front half's settings: ``FrontEndParams`` (frozen, validated), its named ``PRESETS`` and
the one rule that picks a preset for a data set. Checkpoints carry the settings their proposals
were made with, whole (``to_dict`` / ``from_dict``), so a model is always run on the same front
half it was trained on."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Literal

from factorydet_core.proposals.candidates import FeatureKind, Weighting
from factorydet_core.proposals.segment import SegmentationParams
from factorydet_core.proposals.voxels import DEFAULT_VOXEL_SIZE
from factorydet_core.types import (
    InputError,
)


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
    """Proposal feature: "aggregated" voxel features, or "direct" 3DmFV of the proposal's points."""
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
        if self.crop_z_m is not None:
            try:
                low, high = (float(v) for v in self.crop_z_m)
            except (TypeError, ValueError):
                raise InputError(f"crop_z_m must be two heights in metres, got {self.crop_z_m!r}") from None
            if not low < high:  # also false for NaN
                raise InputError(f"crop_z_m must be (low, high) with low < high, got {self.crop_z_m!r}")
            object.__setattr__(self, "crop_z_m", (low, high))
        if self.crop_radius_m is not None and not self.crop_radius_m > 0:
            raise InputError(f"crop_radius_m must be > 0 (or None: no crop), got {self.crop_radius_m}")
        if self.history_frames < 0:
            raise InputError(f"history_frames must be >= 0, got {self.history_frames}")
        if not self.voxel_size_m > 0:
            raise InputError(f"voxel_size_m must be > 0, got {self.voxel_size_m}")
        if self.prune_m < 0:
            raise InputError(f"prune_m must be >= 0, got {self.prune_m}")
        if self.segment_on not in ("points", "voxels"):
            raise InputError(f"segment_on must be 'points' or 'voxels', got {self.segment_on!r}")
        if self.min_proposal_points < 1:
            raise InputError(f"min_proposal_points must be >= 1, got {self.min_proposal_points}")

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
        before a setting existed ran without it).

        Raises:
            InputError: for an unknown name or a bad value.
        """
        values = dict(values)
        segmentation = values.pop("segmentation", None) or {}
        if not isinstance(segmentation, Mapping):
            raise InputError(f"front-end settings: segmentation must be a mapping, got {segmentation!r}")
        seg_names = {f.name for f in dataclasses.fields(SegmentationParams)}
        unknown = sorted(set(segmentation) - seg_names)
        if unknown:
            raise InputError(f"front-end settings: unknown segmentation setting {', '.join(unknown)}")
        seg_values = {k: tuple(v) if isinstance(v, list) else v for k, v in segmentation.items()}
        own = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        try:
            params = cls().replace(**own)  # segmentation names at the top level too
            return dataclasses.replace(
                params, segmentation=dataclasses.replace(params.segmentation, **seg_values)
            )
        except TypeError as exc:
            raise InputError(f"front-end settings: bad value ({exc})") from None

    def replace(self, **changes) -> FrontEndParams:
        """A copy with ``changes``; ``segmentation`` fields may be given by name too.

        Raises:
            InputError: for an unknown name or a value of the wrong kind.
        """
        seg_fields = {f.name for f in dataclasses.fields(SegmentationParams)}
        own_fields = {f.name for f in dataclasses.fields(self)} - {"segmentation"}
        unknown = sorted(set(changes) - seg_fields - own_fields)
        if unknown:
            raise InputError(
                f"unknown parameter {', '.join(unknown)}; "
                f"choose from {', '.join(sorted(own_fields | seg_fields))}"
            )
        seg_changes = {k: changes.pop(k) for k in list(changes) if k in seg_fields}
        try:
            if seg_changes:
                changes["segmentation"] = dataclasses.replace(self.segmentation, **seg_changes)
            return dataclasses.replace(self, **changes)
        except TypeError as exc:  # e.g. a text where a number belongs
            raise InputError(f"bad parameter value: {exc}") from None


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
    preset = preset or preset_for(num_sensors)
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[preset].replace(**dict(overrides or {}))


def front_end_from_record(record: Mapping[str, object] | None) -> FrontEndParams | None:
    """The settings a checkpoint's note or a training run's record holds: ``to_dict``'s output,
    or (checkpoints from before the settings were saved whole) ``{"preset": ..., "overrides":
    {...}}``. ``None`` when it names none: the data's preset then applies.

    Raises:
        InputError: for an unknown preset, name or value.
    """
    if not record:
        return None
    record = dict(record)
    if set(record) <= {"preset", "overrides"}:
        if not record.get("preset"):
            return None
        return front_end_params(str(record["preset"]), record.get("overrides") or {})
    return FrontEndParams.from_dict(record)
