"""Label export and import round trips (JSON, KITTI, npz scenes) and conflict reports."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.geometry import points_in_box
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.labels_io import (
    export_labels,
    import_labels,
    kitti_line,
    parse_kitti_line,
    read_labels,
    scene_arrays,
)
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.types import InputError


@pytest.fixture
def dataset(small_dataset_dir):
    return open_dataset(small_dataset_dir)


@pytest.fixture
def db(tmp_path, dataset):
    db = SessionDB(open_session("src", tmp_path), dataset)
    label = db.labels(0)[0]
    db.update_label(label.id, "ann", class_name="truck")
    db.add_label(1, (3.0, -2.0, 0.6, 1.1, 0.7, 1.2, 2.5), "cone", "ann")
    return db


def _all_labels(db):
    return sorted(
        (lab.frame_index, lab.class_name, tuple(np.round(lab.box, 3)))
        for index in range(db.dataset.num_frames)
        for lab in db.labels(index)
    )


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-40, 40), st.floats(-40, 40), st.floats(-1, 5), st.floats(0.1, 8), st.floats(0.1, 8),
    st.floats(0.1, 4), st.floats(-3.14, 3.14),
)  # fmt: skip
def test_kitti_line_round_trip(cx, cy, cz, dx, dy, dz, yaw):
    box = np.array([cx, cy, cz, dx, dy, dz, yaw])
    name, again = parse_kitti_line(kitti_line(box, "box"))
    assert name == "box"
    np.testing.assert_allclose(again[:6], box[:6], atol=2e-4)
    assert abs((again[6] - yaw + np.pi) % (2 * np.pi) - np.pi) < 1e-5


def test_kitti_axes_follow_kitti():
    # A box 10 m ahead, 2 m to the left, on the floor, heading straight ahead.
    fields = kitti_line([10.0, 2.0, 0.75, 4.0, 2.0, 1.5, 0.0], "truck").split()
    h, w, length, x, y, z, ry = map(float, fields[8:15])
    assert (h, w, length) == (1.5, 2.0, 4.0)
    assert (x, y, z) == (-2.0, 0.0, 10.0)  # x right, y down (bottom face at 0), z forward
    assert ry == pytest.approx(-np.pi / 2)


@pytest.mark.parametrize("fmt", ["json", "kitti", "npz"])
def test_export_then_import_into_a_fresh_session_round_trips(db, dataset, tmp_path, fmt):
    out = tmp_path / ("labels.json" if fmt == "json" else fmt)
    export_labels(db, fmt, out)
    fresh = SessionDB(open_session(f"dst_{fmt}", tmp_path), dataset)
    for index in range(dataset.num_frames):  # an empty session: drop the data set's labels first
        ids = [lab.id for lab in fresh.labels(index)]
        if ids:
            fresh.delete_labels(ids, "setup")
    report = import_labels(fresh, out, "bob", fmt)
    assert report["duplicates"] == [] and report["conflicts"] == []
    assert report["imported"] == sum(len(db.labels(i)) for i in range(dataset.num_frames))
    got, want = _all_labels(fresh), _all_labels(db)
    assert [(f, c) for f, c, _ in got] == [(f, c) for f, c, _ in want]
    np.testing.assert_allclose([b for *_, b in got], [b for *_, b in want], atol=2e-3)
    assert all(lab.origin == "import" for lab in fresh.labels(1))
    # The import is one undoable edit.
    fresh.undo("bob")
    assert all(len(fresh.labels(i)) == 0 for i in range(dataset.num_frames))


def test_importing_into_the_same_session_reports_duplicates_and_conflicts(db, tmp_path):
    out = tmp_path / "labels.json"
    export_labels(db, "json", out)
    before = _all_labels(db)
    report = import_labels(db, out, "bob")
    assert report["imported"] == 0 and len(report["duplicates"]) == len(before)
    # Change one class in the file: that box is imported and reported as a conflict.
    record = __import__("json").loads(out.read_text())
    record["frames"][1]["labels"][-1] = "barrel"
    out.write_text(__import__("json").dumps(record))
    report = import_labels(db, out, "bob")
    assert report["imported"] == 1 and len(report["conflicts"]) == 1
    conflict = report["conflicts"][0]
    assert conflict["class"] == "barrel" and conflict["label_class"] == "cone" and conflict["iou"] > 0.9


def test_npz_scene_has_per_point_labels_from_the_boxes(db):
    scene = scene_arrays(db, 1)
    labels = db.labels(1)
    assert scene["boxes"].shape == (len(labels), 7) and list(scene["labels"]) == [
        lab.class_name for lab in labels
    ]
    names = list(scene["semantic_names"])
    cone = next(k for k, lab in enumerate(labels) if lab.class_name == "cone")
    inside = points_in_box(scene["points"].astype(np.float64), scene["boxes"][cone].astype(np.float64))
    assert (scene["point_instance"][inside] > 0).all()
    assert ((scene["point_instance"] > 0) == (scene["point_semantic"] > 0)).all()
    if inside.any():
        assert names[scene["point_semantic"][inside][0]] in {lab.class_name for lab in labels}


def test_bad_files_and_classes_are_input_errors(db, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    with pytest.raises(InputError, match="not a factorydet label file"):
        read_labels(bad)
    kitti = tmp_path / "kitti"
    kitti.mkdir()
    (kitti / "000000.txt").write_text("spaceship 0 0 0 0 0 0 0 1 1 1 0 0 5 0\n")
    with pytest.raises(InputError, match="not the session's"):
        import_labels(db, kitti, "bob")
    (kitti / "000000.txt").write_text("box 0 0\n")
    with pytest.raises(InputError, match="15 fields"):
        read_labels(kitti)
    (kitti / "000000.txt").unlink()
    (kitti / "frame.txt").write_text("")
    with pytest.raises(InputError, match="named by frame index"):
        read_labels(kitti)


def test_repeats_inside_one_file_and_other_data_sets_are_caught(db, tmp_path):
    import json

    out = tmp_path / "labels.json"
    export_labels(db, "json", out, [1])
    record = json.loads(out.read_text())
    frame = record["frames"][0]
    fresh_box = [20.0, 20.0, 0.5, 1.0, 1.0, 1.0, 0.0]
    frame["boxes"] += [fresh_box, fresh_box]
    frame["labels"] += ["cone", "cone"]
    out.write_text(json.dumps(record))
    report = import_labels(db, out, "bob")
    assert report["imported"] == 1  # the first copy of the new box; the second repeats it
    assert sum(d["label_id"] is None for d in report["duplicates"]) == 1
    record["data_hash"] = "0000000000000000"
    out.write_text(json.dumps(record))
    with pytest.raises(InputError, match="another data set"):
        import_labels(db, out, "bob")
