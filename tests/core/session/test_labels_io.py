"""Label export and import round trips (JSON, KITTI, npz scenes) and conflict reports."""

import warnings

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
from tests.fakes import unwritable


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


@pytest.mark.parametrize("field, value", [(14, "nan"), (14, "inf"), (8, "-inf"), (11, "NaN")])
def test_non_finite_kitti_fields_are_one_line_errors_without_a_warning(field, value):
    fields = kitti_line([10.0, 2.0, 0.75, 4.0, 2.0, 1.5, 0.0], "truck").split()
    fields[field] = value
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the angle arithmetic on nan warned before the check
        with pytest.raises(InputError, match="non-finite KITTI fields"):
            parse_kitti_line(" ".join(fields), "000001.txt")


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


# --- Import checks, one transaction, linear time; atomic exports (issue 29) -----------------------


def _labels_file(path, frames) -> None:
    import json

    path.write_text(json.dumps({"format": "factorydet-labels", "version": 1, "frames": frames}))


@pytest.mark.parametrize(
    ("frame", "match"),
    [
        (
            {"frame_index": 0, "boxes": [[0, 0, 0.5, 1e300, 1, 1, 0]], "labels": ["box"]},
            r"frames\[0\] box 0.*sizes",
        ),
        ({"frame_index": 0, "boxes": [[1e12, 0, 0.5, 1, 1, 1, 0]], "labels": ["box"]}, "from the vehicle"),
        ({"frame_index": 0, "boxes": [[0, 0, 0.5, 1, 1, 1, 1e20]], "labels": ["box"]}, "yaw"),
        ({"frame_index": 0, "boxes": [[0, 0, 0.5, 1, 1, 1]], "labels": ["box"]}, "7 finite numbers"),
        ({"frame_index": 0, "boxes": [["a", 0, 0.5, 1, 1, 1, 0]], "labels": ["box"]}, "7 numbers"),
        ({"frame_index": 0, "boxes": [[True, 0, 0.5, 1, 1, 1, 0]], "labels": ["box"]}, "7 numbers"),
        ({"frame_index": 0, "boxes": [["1", 0, 0.5, 1, 1, 1, 0]], "labels": ["box"]}, "7 numbers"),
        ({"frame_index": 99, "boxes": [[0, 0, 0.5, 1, 1, 1, 0]], "labels": ["box"]}, "frame 99 out of range"),
        ({"frame_index": 1.7, "boxes": [], "labels": []}, r"frames\[0\].frame_index.*integer"),
        ({"frame_index": True, "boxes": [], "labels": []}, "integer"),
        ({"frame_index": "1", "boxes": [], "labels": []}, "integer"),
        ({"frame_index": 0, "boxes": [[0, 0, 0.5, 1, 1, 1, 0]], "labels": []}, "same length"),
        ({"frame_index": 0, "boxes": 5, "labels": 5}, "lists"),
        ([1, 2], "frame_index"),
    ],
)
def test_absurd_boxes_and_frame_indices_are_refused_naming_the_item(db, tmp_path, frame, match):
    out = tmp_path / "bad.json"
    _labels_file(out, [frame])
    edits = len(db.edits())
    with pytest.raises(InputError, match=match) as caught:
        import_labels(db, out, "bob")
    assert "\n" not in str(caught.value) and str(out) in str(caught.value)
    assert len(db.edits()) == edits


def test_malformed_label_files_are_one_line_errors(db, tmp_path):
    cases = {
        "list.json": b"[1, 2, 3]",
        "nested.json": b"[" * 100_000 + b"]" * 100_000,
        "latin1.json": '{"frames": [], "note": "d\u00e9j\u00e0"}'.encode("latin-1"),
        "npz_bad.npz": b"PK\x03\x04 not a zip",
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError) as caught:
            import_labels(db, tmp_path / name, "bob")
        assert "\n" not in str(caught.value), name
    kitti = tmp_path / "kitti"
    kitti.mkdir()
    (kitti / "000000.txt").write_bytes("box 0 0 0 0 0 0 0 1 1 1 0 0 5 0 \u00e9\n".encode("latin-1"))
    with pytest.raises(InputError, match="UTF-8"):
        import_labels(db, kitti, "bob")
    (kitti / "000000.txt").write_text("box 0 0 0 0 0 0 0 1 1 -1 0 0 5 0\n")  # a negative length
    with pytest.raises(InputError, match=r"000000.txt:1.*sizes"):
        import_labels(db, kitti, "bob")


def _screen_reference(items, current):
    """The import's duplicate and conflict rules, box by box against everything before it."""
    from factorydet_core.boxes import box_iou_3d
    from factorydet_core.session.labels_io import CONFLICT_IOU, DUPLICATE_IOU

    keep, duplicates, conflicts = [], [], []
    for k, (frame_index, box, name) in enumerate(items):
        labels = current.get(frame_index, [])
        earlier = [(items[j][1], items[j][2]) for j in keep if items[j][0] == frame_index]
        boxes = np.array([lab.box for lab in labels] + [b for b, _ in earlier]).reshape(-1, 7)
        names = [lab.class_name for lab in labels] + [n for _, n in earlier]
        ids = [lab.id for lab in labels] + [None] * len(earlier)
        if len(boxes):
            iou = box_iou_3d(np.asarray(box)[None], boxes)[0]
            same = np.array([n == name for n in names])
            if same.any() and iou[same].max() >= DUPLICATE_IOU:
                duplicates.append((k, ids[int(np.flatnonzero(same)[iou[same].argmax()])]))
                continue
            if (~same).any() and iou[~same].max() >= CONFLICT_IOU:
                conflicts.append((k, ids[int(np.flatnonzero(~same)[iou[~same].argmax()])]))
        keep.append(k)
    return keep, duplicates, conflicts


def test_the_linear_screen_finds_what_the_box_by_box_check_finds(db):
    import dataclasses

    from factorydet_core.session.labels_io import _screen

    rng = np.random.default_rng(3)
    current = {f: db.labels(f) for f in range(3)}
    # Large labels already in the session: a 100 m hall outline, and a long thin box of the
    # volume of the small ones (size classes must not hide them, nor make the screen quadratic).
    template = current[0][0]
    for n, box in enumerate(
        [(0.0, 0.0, 5.0, 100.0, 100.0, 10.0, 0.0), (0.0, 3.0, 0.5, 60.0, 0.05, 1.0, 0.1)]
    ):
        current[0].append(dataclasses.replace(template, id=10_000 + n, box=box, class_name="box"))
    items = []
    for k in range(600):
        frame_index = int(rng.integers(3))
        if k > 20 and rng.random() < 0.4:  # a near copy of an earlier item or a label
            source = items[int(rng.integers(len(items)))] if rng.random() < 0.5 else None
            if source is None and current[frame_index]:
                lab = current[frame_index][int(rng.integers(len(current[frame_index])))]
                source = (frame_index, np.array(lab.box), lab.class_name)
            if source is not None:
                box = source[1] + rng.normal(0, 0.02, 7) * [1, 1, 1, 0, 0, 0, 1]
                name = source[2] if rng.random() < 0.7 else "cone"
                items.append((source[0], box, name))
                continue
        box = np.array([*rng.uniform(-15, 15, 2), 0.5, *rng.uniform(0.3, 3, 3), rng.uniform(-3, 3)])
        items.append((frame_index, box, ["box", "cone", "barrel"][int(rng.integers(3))]))
    # Large items among them: copies of the large labels (one of another class), a large box of
    # their own, its near copy, and boxes of every size class in between.
    items += [
        (0, np.array(current[0][-2].box), "box"),
        (0, np.array(current[0][-1].box) + [0.01, 0, 0, 0, 0, 0, 0], "cone"),
        (1, np.array([5.0, 5.0, 2.0, 80.0, 90.0, 4.0, 0.3]), "box"),
        (1, np.array([5.1, 5.0, 2.0, 80.0, 90.0, 4.0, 0.3]), "box"),
        (1, np.array([5.1, 5.0, 2.0, 80.0, 90.0, 3.0, 0.3]), "cone"),
    ]
    for size in 2.0 ** np.arange(-3, 7):
        box = np.array([*rng.uniform(-5, 5, 2), 0.5, size, size * 0.7, min(size, 50.0), 0.0])
        items += [(2, box, "box"), (2, box * [1, 1, 1, 1.2, 1, 1, 1], "barrel")]
    keep, duplicates, conflicts = _screen(items, current)
    want_keep, want_duplicates, want_conflicts = _screen_reference(items, current)
    assert keep == want_keep
    assert len(duplicates) == len(want_duplicates) > 20 and len(conflicts) == len(want_conflicts) > 20
    assert [d["label_id"] for d in duplicates] == [i for _, i in want_duplicates]
    assert [c["label_id"] for c in conflicts] == [i for _, i in want_conflicts]


def test_two_imports_of_one_file_at_once_add_each_box_once(db, dataset, tmp_path):
    import threading

    boxes = [[2.0 * k - 20, 15.0, 0.5, 1.0, 1.0, 1.0, 0.0] for k in range(40)]
    out = tmp_path / "new.json"
    _labels_file(out, [{"frame_index": f, "boxes": boxes, "labels": ["box"] * 40} for f in (0, 1)])
    before = sum(len(db.labels(f)) for f in (0, 1))
    reports, barrier = [], threading.Barrier(2)

    def run(author: str) -> None:
        mine = SessionDB(db.session, dataset)
        barrier.wait()
        reports.append(import_labels(mine, out, author))

    threads = [threading.Thread(target=run, args=(a,)) for a in ("ann", "bob")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(r["imported"] for r in reports) == [0, 80]
    assert sorted(len(r["duplicates"]) for r in reports) == [0, 80]
    assert sum(len(db.labels(f)) for f in (0, 1)) == before + 80


def test_an_export_stopped_midway_leaves_the_old_file(db, tmp_path, monkeypatch):
    from pathlib import Path

    def cut_off(self, data, *args, **kwargs):
        with open(self, "w") as f:
            f.write(data[: len(data) // 2])
        raise KeyboardInterrupt  # the process stopped mid-write

    def savez_cut_off(file, **arrays):
        Path(file).write_bytes(b"PK\x03\x04")
        raise KeyboardInterrupt

    for fmt, out, written in (
        ("json", tmp_path / "l.json", tmp_path / "l.json"),
        ("kitti", tmp_path / "k", tmp_path / "k" / "000000.txt"),
        ("npz", tmp_path / "n", tmp_path / "n" / "frame_00000.npz"),
    ):
        export_labels(db, fmt, out, [0])
        old = written.read_bytes()
        with monkeypatch.context() as patch:
            patch.setattr(Path, "write_text", cut_off)
            patch.setattr(np, "savez_compressed", savez_cut_off)
            with pytest.raises(KeyboardInterrupt):
                export_labels(db, fmt, out, [0])
        assert written.read_bytes() == old
        assert [p.name for p in written.parent.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_ten_thousand_boxes_import_once(db, tmp_path):
    # Its time is measured by `factorydet bench import` (docs/bench/label_import.json), not here.
    grid = np.arange(3334)
    frames = [
        {
            "frame_index": f,
            "boxes": [[3.0 * (g % 58) - 90, 3.0 * (g // 58) - 90, 0.5, 1.0, 1.5, 1.0, 0.2] for g in grid],
            "labels": ["box"] * len(grid),
        }
        for f in range(3)
    ]
    out = tmp_path / "many.json"
    _labels_file(out, frames)
    report = import_labels(db, out, "bob")
    assert report["imported"] == 3 * 3334
    again = import_labels(db, out, "bob")  # every box now repeats a label
    assert again["imported"] == 0 and len(again["duplicates"]) == 3 * 3334


@pytest.mark.parametrize("fmt", ["json", "kitti", "npz"])
def test_mutated_label_files_import_or_give_one_line_errors(db, tmp_path, fmt):
    """The fuzzing campaign's mutations (``evaluation.fuzz``), in-process: every mutated export
    imports or is refused with one line, never another exception."""
    from hypothesis import HealthCheck

    from factorydet_core.evaluation.fuzz import make_case

    out = tmp_path / ("labels.json" if fmt == "json" else fmt)
    written = export_labels(db, fmt, out)
    seed_file = out if fmt == "json" else written[0]
    target = f"labels-{fmt}"
    counter = iter(range(10**6))

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.integers(0, 2**32 - 1))
    def check(seed):
        case = make_case(next(counter), target, seed_file, tmp_path / "cases", np.random.default_rng(seed))
        try:
            report = import_labels(db, case.path, "fuzz", fmt)
        except InputError as exc:
            assert "\n" not in str(exc).strip(), str(exc)
        else:
            assert report["imported"] >= 0

    check()


def test_a_label_file_with_a_huge_integer_is_a_one_line_error(db, tmp_path):
    out = tmp_path / "huge.json"
    out.write_text('{"frames": [{"frame_index": ' + "1" * 5000 + ', "boxes": [], "labels": []}]}')
    with pytest.raises(InputError, match="not a factorydet label file.*digits") as caught:
        import_labels(db, out, "bob")
    assert "\n" not in str(caught.value) and str(out) in str(caught.value)


def test_complex_npz_boxes_are_refused_not_cut_to_their_real_part(db, tmp_path):
    scene = tmp_path / "frame_00000.npz"
    np.savez(scene, boxes=np.array([[0, 0, 0.5, 1, 1, 1, 0]], np.complex128) + 1j, labels=np.array(["box"]))
    with pytest.raises(InputError, match="complex128 values, not real numbers"):
        import_labels(db, scene, "bob")


@pytest.mark.parametrize("fmt", ["json", "kitti", "npz"])
def test_exports_make_missing_folders_and_name_what_they_cannot_write(db, tmp_path, fmt):
    name = "labels.json" if fmt == "json" else fmt
    written = export_labels(db, fmt, tmp_path / "new" / "deeper" / name, [0])
    assert all(p.is_file() for p in written)
    cases = [tmp_path / "locked" / name]
    (tmp_path / "locked").mkdir()
    if fmt == "json":
        (tmp_path / "folder.json").mkdir()
        cases.append(tmp_path / "folder.json")
    else:
        (tmp_path / "file").write_text("")
        cases.append(tmp_path / "file")
    with unwritable(tmp_path / "locked"):
        for target in cases:
            with pytest.raises(InputError) as caught:
                export_labels(db, fmt, target, [0])
            message = str(caught.value)
            assert message.startswith(f"cannot write {target}") and "\n" not in message, message
            assert ".tmp" not in message
