"""The detector's front half in one call: merge, crop, prune, floor, voxels, features, segments,
proposals (paper sections 3.1 to 3.4).

``Detector.propose(frame)`` returns a ``ProposalResult`` that keeps every intermediate result, so
that the app can show each stage and benchmarks can time them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from factorydet_core.detection.groups import ProposalGroups, group_proposals
from factorydet_core.detection.scoring import select_detections
from factorydet_core.proposals.candidates import build_proposals
from factorydet_core.proposals.cloud import cap_points, crop, floor_mask, prune
from factorydet_core.proposals.merge import ExtrinsicRefinement, accumulate, refine_extrinsics
from factorydet_core.proposals.segment import segment
from factorydet_core.proposals.settings import FrontEndParams, front_end_params
from factorydet_core.proposals.visibility import free_space
from factorydet_core.proposals.voxels import voxel_fisher_vectors, voxelize
from factorydet_core.types import (
    Detections,
    Frame,
    InputError,
    MergedCloud,
    Proposals,
    Segmentation,
    VoxelGrid,
)

if TYPE_CHECKING:
    from factorydet_core.detection.model import DetectionModel

STAGES: tuple[str, ...] = ("merge", "prune", "voxelize", "features", "segmentation", "aggregation")
"""Stage names, in order, as used in ``ProposalResult.timings_ms`` and the benchmark."""


def params_for(model: DetectionModel | None, num_sensors: int) -> FrontEndParams:
    """The front-half settings ``model`` was trained with (``DetectionModel.front_end``), else
    the preset for data of ``num_sensors`` sensors (``settings.preset_for``)."""
    front_end = getattr(model, "front_end", None)
    return front_end if front_end is not None else front_end_params(num_sensors=num_sensors)


@dataclasses.dataclass(frozen=True)
class ProposalResult:
    """Every intermediate result of the front half for one frame."""

    merged: MergedCloud
    """All points of the frame (and its history) in the vehicle frame, before cropping."""
    cloud: MergedCloud
    """The cropped, pruned, floor-free cloud that was voxelised and segmented."""
    floor_plane: np.ndarray
    """(4,) floor plane (a, b, c, d), NaN when none was found or removal is off."""
    grid: VoxelGrid
    voxel_features: np.ndarray | None
    """(V, 20, 5, 5, 5) float32 per-voxel Fisher vectors; ``None`` when the proposals' features are
    their points' own or none (``feature`` "direct" or "none"), which do not read them
    (``voxels.voxel_fisher_vectors`` of ``cloud`` and ``grid`` computes them)."""
    segmentation: Segmentation
    proposals: Proposals
    timings_ms: dict[str, float]
    """Wall time of each of ``STAGES`` and the total, milliseconds."""
    voxel_colors: np.ndarray | None = None
    """(V, 3) uint8 display colours of the voxels by their 3DmFV (``voxels.voxel_colors``), for a
    viewer that keeps these instead of the (V, 20, 5, 5, 5) vectors; ``None``: not computed."""


FREE_SPACE_MAX_RADIUS_M = 40.0
"""``Detector.group``'s free-space grid spans at most this radius (0.1 m cells: 800 x 800 x 50 at
40 m, 32 MB); a larger crop leaves objects beyond it unseen to the box quality regressor."""

FREE_SPACE_MAX_RAYS = 500_000
"""``Detector.group`` casts rays to at most this many points (``cloud.cap_points`` of the merged
cloud); an AGV frame's 80,000 are all cast."""

ProgressCallback = Callable[[str, float], None]
"""Called with (stage name, fraction of the front half done) as stages finish."""


@dataclasses.dataclass(frozen=True)
class DetectionResult:
    """The front half's results and the back half's: candidates and detections."""

    proposal: ProposalResult
    groups: ProposalGroups
    """The distinct point sets of the proposals, with their features and descriptors."""
    candidates: Detections
    """One scored candidate per point set, before the score threshold and NMS."""
    detections: Detections
    """Candidates above the score threshold, by decreasing score; NMS-suppressed ones flagged."""
    timings_ms: dict[str, float]
    """Front-half stages, then "grouping", "classification", "nms" and "total"."""


class Detector:
    """The detection pipeline.

    Args:
        params: front-half settings, or the name of a preset in ``PRESETS``.
        T_vehicle_sensor: (S, 4, 4) extrinsics to merge with; each frame's nominal ones by default.
            ``calibrate`` sets them by ICP.
        model: the trained back half (``model.DetectionModel``) that ``detect`` needs.
        skip_unread_features: ``detect`` builds the proposals without 3DmFV (feature "none") when
            the model reads none (``DetectionModel.reads_features``: the box head reads points),
            whatever ``params.feature`` says; the detections are the same, and computing the 3DmFV
            of every proposal was about half of the aggregation stage. False computes them anyway
            (the reference path of ``bench detect``).
    """

    def __init__(
        self,
        params: FrontEndParams | str = "agv",
        T_vehicle_sensor: np.ndarray | None = None,
        model: DetectionModel | None = None,
        skip_unread_features: bool = True,
    ) -> None:
        if isinstance(params, str):
            params = front_end_params(params)
        self.params = params
        self.T_vehicle_sensor = None if T_vehicle_sensor is None else np.asarray(T_vehicle_sensor, float)
        self.calibration_: ExtrinsicRefinement | None = None
        self.model = model
        self.skip_unread_features = skip_unread_features

    @property
    def detect_params(self) -> FrontEndParams:
        """The front-half settings ``detect`` proposes with: ``params``, with feature "none" for a
        model that reads no 3DmFV while ``skip_unread_features`` is on. A held-out set measured
        for this detector's model is proposed with them, as its detections are."""
        if self.model is None or self.model.reads_features or not self.skip_unread_features:
            return self.params
        return self.params.replace(feature="none")

    @classmethod
    def for_model(
        cls, model: DetectionModel | None, num_sensors: int, T_vehicle_sensor: np.ndarray | None = None
    ) -> Detector:
        """A detector with the front half ``model`` was trained with (``params_for``) and ``model``
        as its back half."""
        return cls(params_for(model, num_sensors), T_vehicle_sensor, model)

    def history(self, dataset, frame_index: int) -> list[Frame]:
        """The frames of ``dataset`` before ``frame_index`` the front half merges with it (up to
        ``params.history_frames``, oldest first)."""
        first = max(0, int(frame_index) - self.params.history_frames)
        return [dataset.frame(i) for i in range(first, int(frame_index))]

    def calibrate(self, frames: Frame | Sequence[Frame], **icp_options) -> Detector:
        """Refine the rig's extrinsics by ICP between sensors (``merge.refine_extrinsics``)."""
        self.calibration_ = refine_extrinsics(frames, self.T_vehicle_sensor, **icp_options)
        self.T_vehicle_sensor = self.calibration_.T_vehicle_sensor
        return self

    def _segment(self, cloud: MergedCloud, grid: VoxelGrid) -> Segmentation:
        params = self.params
        if params.segment_on == "points":
            return segment(cloud.points, params.segmentation)
        centroids = np.zeros((grid.num_voxels, 3))
        np.add.at(centroids, grid.point_voxel_ids, cloud.points)
        centroids /= np.maximum(grid.num_points, 1)[:, None]
        # Neighbouring voxel centroids can be up to two cells apart; a shorter edge limit would
        # split every surface.
        seg_params = dataclasses.replace(
            params.segmentation,
            max_edge_m=max(params.segmentation.max_edge_m, 2.0 * grid.voxel_size),
            min_patch_points=max(1, params.segmentation.min_patch_points // 4),
        )
        by_voxel = segment(centroids.astype(np.float32), seg_params)
        return Segmentation(
            patch_ids=by_voxel.patch_ids[grid.point_voxel_ids],
            segment_ids=by_voxel.segment_ids[grid.point_voxel_ids],
            patch_segment_ids=by_voxel.patch_segment_ids,
            merge_history=by_voxel.merge_history,
            patch_is_structure=by_voxel.patch_is_structure,
        )

    def propose(
        self,
        frame: Frame,
        history: Sequence[Frame] = (),
        progress: ProgressCallback | None = None,
        *,
        params: FrontEndParams | None = None,
    ) -> ProposalResult:
        """Run the front half on ``frame``.

        Args:
            frame: the current frame.
            history: earlier frames, oldest first; the last ``params.history_frames`` are used.
            progress: optional callback for a progress bar.
            params: the front-half settings to propose with (default ``self.params``; ``detect``
                passes ``detect_params``).

        Returns:
            All intermediate results and the proposals (empty for a frame with too few points).
        """
        params = self.params if params is None else params
        timings: dict[str, float] = {}
        clock = time.perf_counter()

        def done(stage: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timings[stage] = (now - clock) * 1000.0
            clock = now
            if progress is not None:
                progress(stage, (STAGES.index(stage) + 1) / len(STAGES))

        extrinsics = self.T_vehicle_sensor
        if extrinsics is not None and len(extrinsics) != frame.num_sensors:
            raise InputError(
                f"{frame.name}: {frame.num_sensors} sensors, but the detector has extrinsics for "
                f"{len(extrinsics)}"
            )
        used_history = list(history)[-params.history_frames :] if params.history_frames else []
        merged = accumulate(used_history + [frame], extrinsics, refine_with_icp=params.icp_between_frames)
        done("merge")

        cloud = crop(
            merged,
            radius=params.crop_radius_m,
            box_min=None if params.crop_z_m is None else (-np.inf, -np.inf, params.crop_z_m[0]),
            box_max=None if params.crop_z_m is None else (np.inf, np.inf, params.crop_z_m[1]),
        )
        cloud = prune(cloud, params.prune_m)
        floor_plane = np.full(4, np.nan)
        if params.remove_floor:
            is_floor, floor_plane = floor_mask(cloud, distance_m=params.floor_distance_m)
            cloud = cloud.select(~is_floor)
        # The cap counts what is segmented: the floor, when removed, is not.
        cloud = cap_points(cloud, params.max_points, params.prune_m)
        done("prune")

        grid = voxelize(cloud.points, params.voxel_size_m)
        done("voxelize")
        # Direct proposal features read the points, not the voxels', and "none" reads neither:
        # skipping the voxels' saves a dense scan's largest array (10 kB per voxel).
        voxel_features = None if params.feature != "aggregated" else voxel_fisher_vectors(cloud, grid)
        done("features")
        segmentation = self._segment(cloud, grid)
        done("segmentation")
        proposals = build_proposals(
            cloud.points,
            segmentation,
            grid,
            voxel_features,
            min_points=params.min_proposal_points,
            weighting=params.weighting,
            feature=params.feature,
            include_history=params.include_history,
            include_patches=params.include_patches,
            complete_boxes=params.complete_boxes,
            align_to_scene=params.align_to_scene,
            floor_plane=floor_plane if params.remove_floor else None,
        )
        done("aggregation")
        timings["total"] = sum(timings[s] for s in STAGES)
        return ProposalResult(
            merged=merged,
            cloud=cloud,
            floor_plane=floor_plane,
            grid=grid,
            voxel_features=voxel_features,
            segmentation=segmentation,
            proposals=proposals,
            timings_ms=timings,
        )

    def group(self, proposal: ProposalResult, with_free_space: bool = True) -> ProposalGroups:
        """The point sets of a frame's proposals, described for the back half, with the frame's
        free space (``visibility.free_space``, unless ``with_free_space`` is False) over the
        cropped region (``free_space``'s default extent without a crop; at most
        ``FREE_SPACE_MAX_RADIUS_M`` across, since the grid's memory grows with the square of its
        radius)."""
        space = None
        if with_free_space:
            extent = {}
            if self.params.crop_radius_m is not None:
                extent["radius_m"] = min(self.params.crop_radius_m, FREE_SPACE_MAX_RADIUS_M)
            if self.params.crop_z_m is not None:
                extent["z_range_m"] = self.params.crop_z_m
            # A dense scan's millions of rays end in the same few hundred thousand cells: rays
            # to one point per cell of a cloud thinned to FREE_SPACE_MAX_RAYS see the same space.
            space = free_space(cap_points(proposal.merged, FREE_SPACE_MAX_RAYS, 0.0), **extent)
        return group_proposals(
            proposal.proposals, proposal.cloud.points, proposal.segmentation, proposal.floor_plane, space
        )

    def detect(
        self,
        frame: Frame,
        history: Sequence[Frame] = (),
        progress: ProgressCallback | None = None,
        score_threshold: float | None = None,
        nms_iou: float | None = None,
    ) -> DetectionResult:
        """The whole pipeline on ``frame``: proposals, classification, box choice, threshold, NMS."""
        if self.model is None:
            raise InputError("the detector has no model: train one (factorydet train) or load a checkpoint")

        def front_progress(stage: str, fraction: float) -> None:
            if progress is not None:
                progress(stage, 0.8 * fraction)

        proposal = self.propose(frame, history, front_progress, params=self.detect_params)
        timings = {k: v for k, v in proposal.timings_ms.items() if k != "total"}
        clock = time.perf_counter()
        # Casting the rays costs about 0.17 s a frame: only for a regressor that reads them.
        quality = self.model.box_quality
        groups = self.group(proposal, with_free_space=quality is not None and quality.visibility)
        timings["grouping"] = (time.perf_counter() - clock) * 1000.0
        clock = time.perf_counter()
        candidates = self.model.candidates(proposal.proposals.boxes, groups)
        timings["classification"] = (time.perf_counter() - clock) * 1000.0
        if progress is not None:
            progress("classification", 0.95)
        clock = time.perf_counter()
        detections = select_detections(
            candidates,
            self.model.score_threshold if score_threshold is None else score_threshold,
            self.model.nms_iou if nms_iou is None else nms_iou,
            # The model's per-class thresholds are its operating point unless one is asked for.
            class_score_thresholds=self.model.class_thresholds() if score_threshold is None else None,
            vote_iou=self.model.vote_iou,
        )
        timings["nms"] = (time.perf_counter() - clock) * 1000.0
        timings["total"] = sum(timings.values())
        if progress is not None:
            progress("nms", 1.0)
        return DetectionResult(proposal, groups, candidates, detections, timings)
