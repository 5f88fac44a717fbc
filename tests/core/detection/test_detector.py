import dataclasses

import numpy as np
import pytest

from factorydet_core.boxes import heading_gap
from factorydet_core.detection.detector import STAGES, Detector, ProposalResult
from factorydet_core.geometry import invert_transform, points_in_box
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.candidates import build_proposals
from factorydet_core.proposals.settings import PRESETS, FrontEndParams, front_end_params
from factorydet_core.types import BoxLabels, InputError


@pytest.fixture(scope="module")
def frame0(small_dataset_dir):
    return open_dataset(small_dataset_dir).frame(0)


@pytest.fixture(scope="module")
def result(frame0) -> ProposalResult:
    return Detector("agv").propose(frame0)


def channel_norms(features: np.ndarray) -> np.ndarray:
    return np.linalg.norm(features.reshape(len(features), 20, 125).astype(np.float64), axis=2)


def test_result_stages_describe_the_same_cloud(result, frame0):
    cloud = result.cloud
    assert result.merged.num_points == frame0.num_points
    assert 0 < cloud.num_points < result.merged.num_points
    assert len(cloud.points) == len(result.segmentation.patch_ids) == len(result.grid.point_voxel_ids)
    assert result.grid.num_points.sum() == cloud.num_points
    assert result.voxel_features.shape == (result.grid.num_voxels, 20, 5, 5, 5)
    assert np.isfinite(result.voxel_features).all()
    # The cloud was cropped to the preset's range and height.
    params = PRESETS["agv"]
    assert np.hypot(cloud.points[:, 0], cloud.points[:, 1]).max() <= params.crop_radius_m + 1e-4
    assert cloud.points[:, 2].min() >= params.crop_z_m[0] - 1e-4
    assert cloud.points[:, 2].max() <= params.crop_z_m[1] + 1e-4
    # The simulated hall has a level floor, and it was removed.
    assert np.isfinite(result.floor_plane).all() and result.floor_plane[2] > 0.99
    height = cloud.points.astype(np.float64) @ result.floor_plane[:3] + result.floor_plane[3]
    assert height.min() > params.floor_distance_m


def test_proposals_are_well_formed(result):
    proposals = result.proposals
    num = len(proposals)
    assert num > 10
    assert proposals.features.shape == (num, 20, 5, 5, 5) and proposals.features.dtype == np.float32
    assert np.isfinite(proposals.features).all()
    norms = channel_norms(proposals.features)
    assert (np.isclose(norms, 1, atol=1e-4) | np.isclose(norms, 0, atol=1e-4)).all()
    assert np.isfinite(proposals.boxes).all()
    assert (proposals.boxes[:, 3:6] > 0).all()
    assert (proposals.num_points >= PRESETS["agv"].min_proposal_points).all()
    assert set(np.unique(proposals.level)) <= {0, 1, 2}
    # fitted, completed, view-completed, aligned, aligned-completed
    assert set(np.unique(proposals.box_kind)) == {0, 1, 2, 3, 4}
    # The simulated hall is built along its axes, and the aligned boxes follow it.
    heading = proposals.scene_heading
    assert min(heading, np.pi / 2 - heading) < np.radians(2)
    aligned = proposals.boxes[proposals.box_kind >= 3]
    assert heading_gap(aligned[:, 6], heading).max() < 1e-9
    assert (proposals.anchor_mask == np.isin(proposals.box_kind, (0, 3))).all()
    num_patches = result.segmentation.num_patches
    assert all(len(s) >= 1 and max(s) < num_patches for s in proposals.patch_sets)
    # num_points matches the patch sets.
    patch_sizes = np.bincount(result.segmentation.patch_ids, minlength=num_patches)
    np.testing.assert_array_equal(
        proposals.num_points, [patch_sizes[list(s)].sum() for s in proposals.patch_sets]
    )


def test_fitted_boxes_contain_their_points(result):
    proposals, cloud, patch_ids = result.proposals, result.cloud, result.segmentation.patch_ids
    fitted = np.flatnonzero(proposals.box_kind == 0)
    for index in fitted[:: max(1, len(fitted) // 25)]:
        chosen = np.isin(patch_ids, proposals.patch_sets[index])
        assert points_in_box(cloud.points[chosen], proposals.boxes[index], margin=1e-3).all()


def test_timings_cover_every_stage(result):
    assert set(STAGES) | {"total"} == set(result.timings_ms)
    assert all(t >= 0 for t in result.timings_ms.values())
    assert result.timings_ms["total"] == pytest.approx(sum(result.timings_ms[s] for s in STAGES))


def test_direct_feature_gives_the_same_shapes(frame0):
    direct = Detector(dataclasses.replace(PRESETS["agv"], feature="direct")).propose(frame0)
    proposals = direct.proposals
    assert len(proposals) > 10
    assert proposals.features.shape == (len(proposals), 20, 5, 5, 5)
    assert proposals.features.dtype == np.float32 and np.isfinite(proposals.features).all()
    norms = channel_norms(proposals.features)
    assert (np.isclose(norms, 1, atol=1e-4) | np.isclose(norms, 0, atol=1e-4)).all()


def test_direct_and_aggregated_features_describe_the_same_proposals(result):
    # Rebuilt from the same intermediate results (two runs of propose need not give the same floor:
    # open3d's RANSAC is not reproducible, see the report).
    params = PRESETS["agv"]
    direct = build_proposals(
        result.cloud.points,
        result.segmentation,
        result.grid,
        result.voxel_features,
        min_points=params.min_proposal_points,
        feature="direct",
        include_history=params.include_history,
        include_patches=params.include_patches,
        complete_boxes=params.complete_boxes,
        floor_plane=result.floor_plane,
    )
    aggregated = result.proposals
    assert direct.features.shape == aggregated.features.shape
    assert direct.patch_sets == aggregated.patch_sets
    np.testing.assert_allclose(direct.boxes, aggregated.boxes)
    assert np.isfinite(direct.features).all()
    assert np.abs(direct.features - aggregated.features).max() > 0.1


def test_progress_is_reported_in_stage_order(frame0):
    calls = []
    Detector("agv").propose(frame0, progress=lambda stage, fraction: calls.append((stage, fraction)))
    assert [stage for stage, _ in calls] == list(STAGES)
    fractions = [fraction for _, fraction in calls]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)


def test_history_frames_are_accumulated(small_dataset_dir):
    dataset = open_dataset(small_dataset_dir)
    params = PRESETS["agv"].replace(history_frames=1)
    out = Detector(params).propose(dataset.frame(1), history=[dataset.frame(0)])
    assert out.merged.num_points == dataset.frame(0).num_points + dataset.frame(1).num_points
    assert set(np.unique(out.merged.frame_ages)) == {0, 1}


@pytest.mark.parametrize("num_points", [0, 1])
def test_frames_with_almost_no_points_give_empty_proposals(frame0, num_points):
    # A point 2 m ahead of the vehicle at 1 m height, measured by sensor 0.
    vehicle_point = np.array([2.0, 0.0, 1.0, 1.0])
    sensor_point = (invert_transform(frame0.T_vehicle_sensor[0]) @ vehicle_point)[:3]
    tiny = dataclasses.replace(
        frame0,
        points=np.tile(sensor_point, (num_points, 1)).astype(np.float32),
        sensor_ids=np.zeros(num_points, np.int16),
        point_instance_ids=np.zeros(num_points, np.int64),
        labels=BoxLabels.empty(),
    )
    out = Detector("agv").propose(tiny)
    assert out.cloud.num_points == num_points
    assert len(out.proposals) == 0
    assert out.proposals.features.shape == (0, 20, 5, 5, 5)
    assert out.grid.num_voxels == num_points
    assert set(STAGES) <= set(out.timings_ms)


def test_unknown_preset_raises():
    with pytest.raises(InputError, match="unknown preset"):
        Detector("lidar-on-a-bicycle")


def test_extrinsics_of_another_rig_raise(frame0):
    with pytest.raises(InputError, match="extrinsics"):
        Detector("agv", T_vehicle_sensor=np.eye(4)[None]).propose(frame0)


@pytest.mark.parametrize(
    "changes",
    [
        {"history_frames": -1},
        {"voxel_size_m": 0.0},
        {"prune_m": -0.1},
        {"segment_on": "pixels"},
        {"min_proposal_points": 0},
        {"crop_radius_m": 0.0},
        {"crop_radius_m": float("nan")},
        {"crop_z_m": (4.5, -0.5)},
        {"crop_z_m": (0.0, float("nan"))},
    ],
)
def test_invalid_front_end_params_raise(changes):
    with pytest.raises(InputError, match=next(iter(changes))):
        FrontEndParams(**changes)


def test_params_replace_accepts_segmentation_fields():
    params = PRESETS["agv"].replace(max_edge_m=0.2, prune_m=0.1)
    assert params.segmentation.max_edge_m == 0.2 and params.prune_m == 0.1
    assert PRESETS["agv"].segmentation.max_edge_m == 0.3  # the preset is unchanged


def test_containers_never_freeze_or_alias_the_callers_arrays():
    from factorydet_core.types import MergedCloud

    points = np.zeros((4, 3), np.float32)
    base = np.zeros((8, 3), np.float32)
    cloud = MergedCloud(
        points=points,
        sensor_ids=np.zeros(4, np.int16),
        point_instance_ids=np.zeros(4, np.int64),
        T_vehicle_sensor=np.eye(4)[None],
    )
    view_cloud = dataclasses.replace(cloud, points=base[:4])
    assert points.flags.writeable and base.flags.writeable  # the caller's arrays stay theirs
    base[0] = 7.0
    assert view_cloud.points[0, 0] == 0.0  # and the container does not see later writes
    assert not cloud.points.flags.writeable


def test_unknown_or_malformed_parameters_are_input_errors():
    params = PRESETS["agv"]
    with pytest.raises(InputError, match="unknown parameter foo"):
        params.replace(foo=1)
    with pytest.raises(InputError, match="max_object_size_m"):
        params.replace(max_object_size_m=5)
    with pytest.raises(InputError, match="crop_z_m"):
        params.replace(crop_z_m="abc")
    assert params.replace(max_object_size_m=[3, 2]).segmentation.max_object_size_m == (3.0, 2.0)


@pytest.mark.slow
def test_detection_casts_rays_only_for_a_regressor_that_reads_them(
    small_dataset_dir, tiny_model_path, result
):
    from factorydet_core.detection.model import DetectionModel

    detector = Detector("agv")
    assert detector.group(result).free_space is not None
    assert detector.group(result, with_free_space=False).free_space is None
    from factorydet_core.detection.box_quality import BoxQuality
    from factorydet_core.training.mining import collect_proposals

    model = DetectionModel.load(tiny_model_path)
    dataset = open_dataset(small_dataset_dir)
    frames = collect_proposals(dataset, [0], detector)
    qualities = []
    for visibility in (True, False):
        quality = BoxQuality(max_iter=3, visibility=visibility)
        qualities.append(quality.fit(*quality.training_rows(frames, model.box_prior, len(model.class_names))))
    for box_quality, reads in zip((*qualities, None), (True, False, False)):
        detector.model = dataclasses.replace(model, box_quality=box_quality)
        groups = detector.detect(dataset.frame(0)).groups
        assert (groups.free_space is not None) == reads


def test_a_dense_cloud_is_thinned_to_the_cap_before_segmentation(small_dataset_dir):
    frame = open_dataset(small_dataset_dir).frame(0)
    uncapped = Detector(front_end_params("agv", {"max_points": None})).propose(frame)
    default = Detector("agv").propose(frame)
    # A small frame is under the default cap: nothing changes.
    np.testing.assert_array_equal(default.cloud.points, uncapped.cloud.points)
    np.testing.assert_array_equal(default.proposals.boxes, uncapped.proposals.boxes)
    capped = Detector(front_end_params("agv", {"max_points": 3000})).propose(frame)
    assert capped.cloud.num_points <= 3000 < uncapped.cloud.num_points
    assert len(capped.proposals) > 0


def test_detect_proposes_without_3dmfv_for_a_model_that_reads_none():
    import types

    params = dataclasses.replace(PRESETS["agv"], feature="direct")
    reads = types.SimpleNamespace(reads_features=True)
    reads_none = types.SimpleNamespace(reads_features=False)
    assert Detector(params, model=reads).detect_params is params
    assert Detector(params).detect_params is params  # no model yet: the front half as set
    assert Detector(params, model=reads_none).detect_params == dataclasses.replace(params, feature="none")
    assert Detector(params, model=reads_none, skip_unread_features=False).detect_params is params
