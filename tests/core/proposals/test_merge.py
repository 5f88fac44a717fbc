import numpy as np
import pytest

from factorydet_core.geometry import invert_transform, make_transform, rotation_angle_deg, rotation_ypr
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.merge import ExtrinsicRefinement, accumulate, merge_frame, refine_extrinsics
from factorydet_core.sim.truth import read_truth
from factorydet_core.types import BoxLabels, Frame, InputError


def single_sensor_frame(name: str, points_vehicle: np.ndarray, T_world_vehicle: np.ndarray) -> Frame:
    num = len(points_vehicle)
    return Frame(
        name=name,
        points=points_vehicle.astype(np.float32),
        sensor_ids=np.zeros(num, np.int16),
        T_vehicle_sensor=np.eye(4)[None],
        T_world_vehicle=T_world_vehicle,
        labels=BoxLabels.empty(),
        point_instance_ids=np.arange(num, dtype=np.int64),
    )


def test_merge_frame_uses_the_given_extrinsics():
    points = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], np.float32)
    extrinsics = np.stack(
        [make_transform(rotation_ypr(np.pi / 2, 0, 0), [1, 2, 3]), make_transform(np.eye(3), [0, 0, -1])]
    )
    frame = Frame(
        name="two",
        points=points,
        sensor_ids=np.array([0, 1, 0], np.int16),
        T_vehicle_sensor=np.stack([np.eye(4)] * 2),
        T_world_vehicle=np.eye(4),
        labels=BoxLabels.empty(),
        point_instance_ids=np.array([5, 6, 7]),
    )
    nominal = merge_frame(frame)
    np.testing.assert_allclose(nominal.points, points)
    merged = merge_frame(frame, extrinsics)
    np.testing.assert_allclose(merged.points, [[1, 3, 3], [0, 1, -1], [1, 2, 4]], atol=1e-6)
    np.testing.assert_array_equal(merged.point_instance_ids, [5, 6, 7])
    np.testing.assert_array_equal(merged.T_vehicle_sensor, extrinsics)
    with pytest.raises(InputError, match="T_vehicle_sensor"):
        merge_frame(frame, extrinsics[:1])


def test_accumulate_puts_both_frames_in_the_current_vehicle_frame():
    rng = np.random.default_rng(0)
    world = rng.uniform(-10, 10, (300, 3))
    T_world_vehicle_0 = make_transform(rotation_ypr(0.2, 0.0, 0.0), [1.0, -2.0, 0.0])
    T_world_vehicle_1 = make_transform(rotation_ypr(0.5, 0.0, 0.0), [2.5, -1.0, 0.0])
    frames = [
        single_sensor_frame(f"f{i}", world @ invert_transform(T)[:3, :3].T + invert_transform(T)[:3, 3], T)
        for i, T in enumerate([T_world_vehicle_0, T_world_vehicle_1])
    ]
    # The two frames' raw points differ: the vehicle moved.
    assert np.abs(frames[0].points - frames[1].points).max() > 1.0
    cloud = accumulate(frames)
    assert cloud.num_points == 600
    np.testing.assert_array_equal(np.sort(np.unique(cloud.frame_ages)), [0, 1])
    current, older = cloud.frame_ages == 0, cloud.frame_ages == 1
    assert current.sum() == older.sum() == 300
    np.testing.assert_array_equal(cloud.points[current], frames[1].points)
    # Same world point (same instance id) ends up at the same place.
    order_current = np.argsort(cloud.point_instance_ids[current])
    order_older = np.argsort(cloud.point_instance_ids[older])
    np.testing.assert_allclose(
        cloud.points[older][order_older], cloud.points[current][order_current], atol=1e-4
    )


def test_accumulate_of_one_frame_is_the_merged_frame():
    frame = single_sensor_frame("f", np.random.default_rng(1).uniform(-5, 5, (50, 3)), np.eye(4))
    cloud = accumulate([frame])
    np.testing.assert_array_equal(cloud.points, merge_frame(frame).points)
    assert (cloud.frame_ages == 0).all()
    with pytest.raises(InputError, match="no frames"):
        accumulate([])


def test_refine_extrinsics_needs_frames_and_two_sensors():
    frame = single_sensor_frame("f", np.random.default_rng(1).uniform(-5, 5, (50, 3)), np.eye(4))
    with pytest.raises(InputError, match="two sensors"):
        refine_extrinsics(frame)
    with pytest.raises(InputError, match="no frames"):
        refine_extrinsics([])


def test_icp_recovers_a_known_transform(small_dataset_dir):
    frame = open_dataset(small_dataset_dir).frame(0)
    truth = np.array(read_truth(small_dataset_dir)["T_vehicle_sensor_true"], np.float64)
    assert truth.shape == (frame.num_sensors, 4, 4)
    sensor = 3
    # About 2 degrees about the sensor's own origin, and about 5 cm.
    start = truth.copy()
    start[sensor, :3, :3] = (
        rotation_ypr(np.radians(1.5), np.radians(1.0), np.radians(-0.8)) @ truth[sensor, :3, :3]
    )
    start[sensor, :3, 3] += [0.03, -0.03, 0.025]
    angle_before = rotation_angle_deg(start[sensor, :3, :3], truth[sensor, :3, :3])
    offset_before = np.linalg.norm(start[sensor, :3, 3] - truth[sensor, :3, 3])
    assert 1.8 < angle_before < 2.2 and 0.045 < offset_before < 0.055

    result = refine_extrinsics(frame, start, rounds=2)

    assert isinstance(result, ExtrinsicRefinement)
    assert result.T_vehicle_sensor.shape == (frame.num_sensors, 4, 4)
    angle_after = rotation_angle_deg(result.T_vehicle_sensor[sensor, :3, :3], truth[sensor, :3, :3])
    offset_after = np.linalg.norm(result.T_vehicle_sensor[sensor, :3, 3] - truth[sensor, :3, 3])
    assert angle_after < 0.7
    assert offset_after < 0.6 * offset_before
    # The sensors that started right stay (nearly) right.
    others = [
        rotation_angle_deg(result.T_vehicle_sensor[s, :3, :3], truth[s, :3, :3])
        for s in range(frame.num_sensors)
        if s != sensor
    ]
    assert max(others) < 1.0
    # The perturbed sensor fits the others better afterwards.
    assert result.rmse_after[sensor] < result.rmse_before[sensor]
    assert result.rmse_before.shape == result.rmse_after.shape == result.fitness.shape == (frame.num_sensors,)
    assert ((result.fitness > 0) & (result.fitness <= 1)).all()
    # Still rigid transforms.
    rotations = result.T_vehicle_sensor[:, :3, :3]
    np.testing.assert_allclose(
        np.einsum("sij,skj->sik", rotations, rotations),
        np.broadcast_to(np.eye(3), rotations.shape),
        atol=1e-9,
    )
    np.testing.assert_allclose(result.T_vehicle_sensor[:, 3], [[0, 0, 0, 1]] * 12, atol=1e-12)


@pytest.mark.slow
def test_refine_extrinsics_repeats_exactly(small_dataset_dir):
    # open3d's parallel sums differ in the last bits from call to call; unsnapped, that grows into
    # different extrinsics and then into different segments, so no figure repeated run to run.
    frame = open_dataset(small_dataset_dir).frame(0)
    first = refine_extrinsics(frame, rounds=2).T_vehicle_sensor
    for _ in range(2):
        np.testing.assert_array_equal(refine_extrinsics(frame, rounds=2).T_vehicle_sensor, first)
