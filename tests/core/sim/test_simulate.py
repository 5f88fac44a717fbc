import filecmp
import json

import numpy as np
import pytest

from factorydet_core.geometry import invert_transform, points_in_box, rotation_angle_deg
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.merge import merge_frame
from factorydet_core.sim.rig import HORIZONTAL_FOV_DEG, MAX_RANGE_M, VERTICAL_FOV_DEG
from factorydet_core.sim.simulate import FactorySimulator, SimConfig, simulate_dataset
from factorydet_core.sim.truth import read_frame_truth, read_truth
from factorydet_core.types import CLASS_NAMES


def _all_files(folder):
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())


def test_same_seed_gives_identical_bytes(tmp_path):
    config = SimConfig(num_frames=2, seed=3, points_per_frame=10_000)
    first, second = simulate_dataset(tmp_path / "a", config), simulate_dataset(tmp_path / "b", config)
    files = _all_files(first)
    assert files == _all_files(second) and len(files) == 2 * 2 + 2
    for rel in files:
        assert filecmp.cmp(first / rel, second / rel, shallow=False), rel


def test_another_seed_gives_another_factory(tmp_path):
    a = simulate_dataset(tmp_path / "a", SimConfig(num_frames=1, seed=1, points_per_frame=10_000))
    b = simulate_dataset(tmp_path / "b", SimConfig(num_frames=1, seed=2, points_per_frame=10_000))
    assert not filecmp.cmp(a / "frames/frame_00000.npz", b / "frames/frame_00000.npz", shallow=False)


def test_frames_have_twelve_sensors_and_about_80k_points(default_dataset_dir):
    dataset = open_dataset(default_dataset_dir)
    assert dataset.num_frames == 5 and dataset.num_sensors == 12
    for i in range(dataset.num_frames):
        frame = dataset.frame(i)
        assert set(np.unique(frame.sensor_ids)) == set(range(12))
        assert 76_000 <= frame.num_points <= 84_000


def test_points_respect_each_sensors_field_of_view_and_range(default_dataset_dir):
    frame = open_dataset(default_dataset_dir).frame(0)
    p = frame.points.astype(np.float64)
    ranges = np.linalg.norm(p, axis=1)
    azimuth = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    elevation = np.degrees(np.arcsin(p[:, 2] / ranges))
    tolerance = 1e-3  # degrees; float32 storage
    assert np.abs(azimuth).max() <= HORIZONTAL_FOV_DEG / 2 + tolerance
    assert np.abs(elevation).max() <= VERTICAL_FOV_DEG / 2 + tolerance
    assert ranges.max() <= MAX_RANGE_M + 0.1
    # The beams really fill the field of view, not a corner of it.
    assert (
        np.abs(azimuth).max() > HORIZONTAL_FOV_DEG / 2 - 1
        and np.abs(elevation).max() > VERTICAL_FOV_DEG / 2 - 2
    )


def test_every_class_is_annotated_somewhere_in_the_default_data(default_dataset_dir):
    dataset = open_dataset(default_dataset_dir)
    seen = set()
    for i in range(dataset.num_frames):
        seen |= set(dataset.frame(i).labels.class_ids.tolist())
    assert {CLASS_NAMES[c] for c in seen} == set(CLASS_NAMES)


def _truths(folder, num_frames):
    return [read_frame_truth(folder, i) for i in range(num_frames)]


def test_unannotated_fraction_of_eligible_objects_is_as_configured(default_dataset_dir):
    min_points = json.loads((default_dataset_dir / "manifest.json").read_text())["config"][
        "min_annotated_points"
    ]
    num_eligible = num_unannotated = 0
    for truth in _truths(default_dataset_dir, 5):
        eligible = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= min_points)
        num_eligible += int(eligible.sum())
        num_unannotated += int((eligible & ~truth.annotated_mask).sum())
        assert not (truth.annotated_mask & ~eligible).any(), "an instance below the minimum was annotated"
    assert num_eligible > 200
    assert 0.22 <= num_unannotated / num_eligible <= 0.38


@pytest.mark.parametrize("fraction", [0.0, 1.0])
def test_unannotated_fraction_extremes(tmp_path, fraction):
    folder = simulate_dataset(
        tmp_path, SimConfig(num_frames=1, seed=5, unlabelled_fraction=fraction, points_per_frame=20_000)
    )
    truth = read_frame_truth(folder, 0)
    eligible = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= 50)
    assert eligible.sum() > 5
    assert (truth.annotated_mask[eligible] == (fraction == 0.0)).all()


def test_the_same_object_stays_unannotated_in_every_frame(default_dataset_dir):
    truth_record = read_truth(default_dataset_dir)
    unannotated = {i["id"] for i in truth_record["instances"] if i["unannotated"]}
    for truth in _truths(default_dataset_dir, 5):
        for instance_id, annotated in zip(truth.instance_ids.tolist(), truth.annotated_mask.tolist()):
            if instance_id in unannotated:
                assert not annotated


def test_published_frames_hold_annotated_instances_only(default_dataset_dir):
    dataset = open_dataset(default_dataset_dir)
    for i, truth in enumerate(_truths(default_dataset_dir, 5)):
        frame = dataset.frame(i)
        assert set(frame.labels.instance_ids.tolist()) == set(
            truth.instance_ids[truth.annotated_mask].tolist()
        )
        published = set(np.unique(frame.point_instance_ids).tolist()) - {0}
        assert published == set(frame.labels.instance_ids.tolist())
        # Classes and boxes published are the true ones.
        order = np.searchsorted(truth.instance_ids, frame.labels.instance_ids)
        np.testing.assert_array_equal(truth.instance_class_ids[order], frame.labels.class_ids)


def test_boxes_contain_their_instances_points(default_dataset_dir):
    truth_record = read_truth(default_dataset_dir)
    T_true = np.array(truth_record["T_vehicle_sensor_true"])
    dataset = open_dataset(default_dataset_dir)
    for i in (0, 4):
        frame, truth = dataset.frame(i), read_frame_truth(default_dataset_dir, i)
        points = merge_frame(frame, T_true).points
        for instance_id, box in zip(truth.instance_ids, truth.instance_boxes):
            own = points[truth.point_instance_ids == instance_id]
            inside = points_in_box(own, box, margin=0.08)  # range noise sigma is 1.5 cm
            assert inside.mean() >= 0.995, (i, instance_id, inside.mean())


def test_calibration_error_is_about_one_degree_and_two_centimetres(default_dataset_dir):
    nominal = open_dataset(default_dataset_dir).T_vehicle_sensor
    true = np.array(read_truth(default_dataset_dir)["T_vehicle_sensor_true"])
    angles = [rotation_angle_deg(t[:3, :3], n[:3, :3]) for t, n in zip(true, nominal)]
    shifts = np.linalg.norm(true[:, :3, 3] - nominal[:, :3, 3], axis=1)
    assert 0.5 <= np.median(angles) <= 1.5 and max(angles) <= 2.0
    assert 0.005 <= np.median(shifts) <= 0.05


def test_odometry_drifts_from_the_true_pose_but_stays_close(default_dataset_dir):
    dataset = open_dataset(default_dataset_dir)
    errors = []
    for i in range(5):
        T_err = (
            invert_transform(read_frame_truth(default_dataset_dir, i).T_world_vehicle)
            @ dataset.frame(i).T_world_vehicle
        )
        errors.append(np.linalg.norm(T_err[:3, 3]))
    assert errors[0] == 0.0 and 0.0 < max(errors) < 0.5


def test_people_and_trucks_move_between_frames():
    simulator = FactorySimulator(SimConfig(num_frames=2, seed=1, points_per_frame=2_000))
    moving = simulator.factory.moving_objects
    assert {o.kind for o in moving} == {"person", "truck"}
    for obj in moving:
        assert np.linalg.norm(obj.box_at(0.0)[:2] - obj.box_at(1.5)[:2]) > 0.5
    static_kinds = {o.kind for o in simulator.factory.static_objects}
    assert {"person", "truck", "machine", "table", "bin"} <= static_kinds


def test_splits_are_deterministic_disjoint_and_two_thirds_train(tmp_path):
    manifest = FactorySimulator(SimConfig(num_frames=9, seed=0, points_per_frame=2_000)).manifest()
    train, test = manifest["splits"]["train"], manifest["splits"]["test"]
    assert train == list(range(6)) and test == [6, 7, 8]


def test_objects_touch_their_neighbours():
    """The data must keep the paper's hard case: objects in contact with others."""
    simulator = FactorySimulator(SimConfig(num_frames=1, seed=1, points_per_frame=2_000))
    boxes = np.array([o.box_at(0.0) for o in simulator.factory.static_objects if o.class_id >= 0])
    centers, half = boxes[:, :3], boxes[:, 3:6] / 2
    # Axis-aligned test is enough: shelf goods and barrel groups are placed axis-aligned or round.
    radius = np.linalg.norm(half[:, :2], axis=1)
    gaps = (
        np.linalg.norm(centers[:, None, :2] - centers[None, :, :2], axis=2) - radius[:, None] - radius[None]
    )
    np.fill_diagonal(gaps, np.inf)
    assert (gaps.min(axis=1) < 0.02).mean() > 0.5


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="unlabelled_fraction"):
        SimConfig(unlabelled_fraction=1.5)
    with pytest.raises(ValueError, match="num_frames"):
        SimConfig(num_frames=0)
