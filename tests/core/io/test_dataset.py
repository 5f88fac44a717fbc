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


def _copy_with_frame0(tmp_path, small_dataset_dir, **replace):
    """A copy of the small data set whose frame 0 has the arrays ``replace``."""
    manifest = json.loads((small_dataset_dir / "manifest.json").read_text())
    (tmp_path / "frames").mkdir()
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    for path in (small_dataset_dir / "frames").glob("*.npz"):
        with np.load(path) as data:
            arrays = dict(data)
        if path.name == "frame_00000.npz":
            arrays.update(replace)
        np.savez_compressed(tmp_path / "frames" / path.name, **arrays)
    return tmp_path


def test_frame_labels_read_the_label_arrays_alone(tmp_path, small_dataset_dir):
    dataset = open_dataset(small_dataset_dir)
    for index in range(dataset.num_frames):
        name, labels = dataset.frame_labels(index)
        frame = dataset.frame(index)
        assert name == frame.name and len(labels) > 0
        for field in ("boxes", "class_ids", "instance_ids", "num_points"):
            np.testing.assert_array_equal(getattr(labels, field), getattr(frame.labels, field))
    with pytest.raises(IndexError):
        dataset.frame_labels(dataset.num_frames)
    # Points the frame refuses are not read: the annotations still come.
    with np.load(small_dataset_dir / "frames" / "frame_00000.npz") as data:
        points = data["points"].copy()
    points[0] = np.nan
    broken = open_dataset(_copy_with_frame0(tmp_path, small_dataset_dir, points=points))
    with pytest.raises(InputError, match="points"):
        broken.frame(0)
    np.testing.assert_array_equal(broken.frame_labels(0)[1].boxes, dataset.frame(0).labels.boxes)


def test_frame_labels_leave_the_frame_cache_alone(small_dataset_dir):
    from factorydet_core.io.dataset import Dataset

    dataset = open_dataset(small_dataset_dir)
    Dataset._read_frame.cache_clear()  # (one cache for the class)
    for index in range(dataset.num_frames):
        dataset.frame_labels(index)
    assert Dataset._read_frame.cache_info().currsize == 0


def test_frame_labels_refuse_what_the_frame_refuses(tmp_path, small_dataset_dir):
    with np.load(small_dataset_dir / "frames" / "frame_00000.npz") as data:
        class_ids = data["label_class_ids"].copy()
    class_ids[0] = 99
    broken = open_dataset(_copy_with_frame0(tmp_path, small_dataset_dir, label_class_ids=class_ids))
    with pytest.raises(InputError, match=r"frame_00000.npz: label class ids must lie in \[0, "):
        broken.frame_labels(0)
    with pytest.raises(InputError, match="label class ids must lie in"):
        broken.frame(0)


def test_frame_labels_name_a_missing_label_array(tmp_path, small_dataset_dir):
    manifest = json.loads((small_dataset_dir / "manifest.json").read_text())
    (tmp_path / "frames").mkdir()
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    for path in (small_dataset_dir / "frames").glob("*.npz"):
        with np.load(path) as data:
            arrays = {k: v for k, v in data.items() if k != "label_num_points"}
        np.savez_compressed(tmp_path / "frames" / path.name, **arrays)
    with pytest.raises(InputError, match="frame_00000.npz: frame lacks the array 'label_num_points'"):
        open_dataset(tmp_path).frame_labels(0)
    with pytest.raises(InputError, match="frame lacks the array 'label_num_points'"):
        open_dataset(tmp_path).frame(0)
