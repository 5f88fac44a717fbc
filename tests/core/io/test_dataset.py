import json

import numpy as np
import pytest

from factorydet_core.io.dataset import annotation_min_points, open_dataset
from factorydet_core.proposals.merge import merge_frame
from factorydet_core.types import InputError


def test_frames_are_read_only_and_typed(small_dataset_dir):
    frame = open_dataset(small_dataset_dir).frame(1)
    assert frame.points.dtype == np.float32 and frame.points.shape[1] == 3
    assert frame.T_vehicle_sensor.shape == (12, 4, 4)
    with pytest.raises(ValueError, match="read-only"):
        frame.points[0, 0] = 1.0
    assert frame.point_class_ids.shape == (frame.num_points,)
    assert set(np.unique(frame.point_class_ids)) <= set(range(-1, 7))


def test_merge_does_not_mutate_and_matches_per_sensor_transform(small_dataset_dir):
    frame = open_dataset(small_dataset_dir).frame(0)
    before = frame.points.copy()
    merged = merge_frame(frame)
    np.testing.assert_array_equal(frame.points, before)
    sensor = 5
    mask = frame.sensor_ids == sensor
    T = frame.T_vehicle_sensor[sensor]
    expected = frame.points[mask].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(merged.points[mask], expected, atol=1e-4)


def test_frame_index_out_of_range(small_dataset_dir):
    with pytest.raises(IndexError):
        open_dataset(small_dataset_dir).frame(3)


def test_missing_and_malformed_data_sets_give_one_line_errors(tmp_path, small_dataset_dir):
    with pytest.raises(InputError, match="no such file"):
        open_dataset(tmp_path / "nope")
    with pytest.raises(InputError, match="no manifest.json"):
        open_dataset(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(InputError, match="malformed manifest") as info:
        open_dataset(tmp_path)
    assert "\n" not in str(info.value)


def test_truncated_frame_gives_a_clear_error(tmp_path, small_dataset_dir):
    manifest = json.loads((small_dataset_dir / "manifest.json").read_text())
    (tmp_path / "frames").mkdir()
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    data = (small_dataset_dir / "frames" / "frame_00000.npz").read_bytes()
    (tmp_path / "frames" / "frame_00000.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="frame_00000.npz: unreadable frame"):
        open_dataset(tmp_path).frame(0)
    with pytest.raises(InputError, match="frame file missing"):
        open_dataset(tmp_path).frame(1)


def test_merged_cloud_selection_keeps_rows_together(small_dataset_dir):
    merged = merge_frame(open_dataset(small_dataset_dir).frame(0))
    keep = merged.below(2.0)
    assert 0 < keep.sum() < merged.num_points
    low = merged.select(keep)
    assert low.points[:, 2].max() <= 2.0 and low.num_points == keep.sum()
    np.testing.assert_array_equal(low.sensor_ids, merged.sensor_ids[keep])
    np.testing.assert_array_equal(low.point_instance_ids, merged.point_instance_ids[keep])


def test_annotation_policy_is_read_from_the_manifest(small_dataset_dir, tmp_path):
    assert annotation_min_points(open_dataset(small_dataset_dir)) == 50  # the simulator's default
    manifest = json.loads((small_dataset_dir / "manifest.json").read_text())
    manifest["config"]["min_annotated_points"] = 20
    other = tmp_path / "other"
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps(manifest))
    assert annotation_min_points(open_dataset(other)) == 20
    del manifest["config"]
    (other / "manifest.json").write_text(json.dumps(manifest))
    assert annotation_min_points(open_dataset(other)) == 50
    assert annotation_min_points(open_dataset(other), default=None) is None
