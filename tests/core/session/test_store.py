"""The session database: labels, the edit log with undo and redo, reviews, durability, refusal of
bad files."""

from __future__ import annotations

import dataclasses
import json
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import (
    SCHEMA_VERSION,
    EditConflictError,
    SessionDB,
    SessionError,
    open_session,
)
from factorydet_core.training.mining import TrainingRun
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import InputError
from tests.fakes import mined_item, queue_run, unwritable

BOX = (1.0, 2.0, 0.5, 1.2, 0.8, 1.0, 0.3)


def _reopen(db: SessionDB) -> SessionDB:
    return SessionDB(db.session, db.dataset)


def _fake_run(model_path: Path, num_mined: int = 6) -> TrainingRun:
    """A real model with a made-up mining record, to fill the review queue without training."""
    items = [
        mined_item(
            i % 2,
            i,
            [float(i), 0.0, 0.5, 1.0, 1.0, 1.0, 0.0],
            0.9 - 0.1 * i,
            ["box", "barrel"][i % 2],
            [0.1] * 8,
        )
        for i in range(num_mined)
    ]
    return queue_run(model_path, [items, []], train_frames=(0, 1))


def test_first_access_imports_the_data_sets_annotations(db, dataset):
    frame = dataset.frame(0)
    labels = db.labels(0)
    assert len(labels) == len(frame.labels) > 0
    assert all(lab.origin == "dataset" and lab.version == 1 for lab in labels)
    np.testing.assert_allclose([lab.box for lab in labels], frame.labels.boxes, atol=1e-6)
    assert [lab.instance_id for lab in labels] == frame.labels.instance_ids.tolist()
    boxes, class_ids, label_ids = db.frame_boxes(0)
    assert boxes.shape == (len(labels), 7) and (class_ids == frame.labels.class_ids).all()
    # Imported once: reopening does not duplicate them.
    assert len(_reopen(db).labels(0)) == len(labels)


def test_database_uses_wal_full_sync_foreign_keys_and_a_schema_version(db):
    db.labels(0)
    connection = db._connect()
    try:
        assert connection.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert connection.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
        assert connection.execute("PRAGMA foreign_keys").fetchone()[0] == 1
        assert connection.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    finally:
        connection.close()
    assert db.path.name == "session.db"


def test_every_label_edit_survives_close_and_reopen(db):
    first, second = db.labels(0)[:2]
    added = db.add_label(0, BOX, "cone", "ann")
    moved = db.update_label(first.id, "ann", expected_version=first.version, box=BOX)
    renamed = db.update_label(second.id, "bob", class_name="truck")
    db.delete_labels([added.id], "ann")
    again = _reopen(db)
    assert again.label(added.id).deleted and again.label(added.id).origin == "user"
    assert again.label(moved.id).box == pytest.approx(BOX)
    assert again.label(renamed.id).class_name == "truck" and again.label(renamed.id).modified_by == "bob"
    assert added.id not in [lab.id for lab in again.labels(0)]
    assert [e.kind for e in again.edits()] == ["delete", "update", "update", "add"]


def test_bad_edits_are_refused_without_writing(db):
    count = len(db.edits())
    with pytest.raises(SessionError, match="unknown class"):
        db.add_label(0, BOX, "spaceship", "ann")
    with pytest.raises(SessionError, match="7 finite numbers"):
        db.add_label(0, BOX[:6], "box", "ann")
    with pytest.raises(SessionError, match="positive"):
        db.add_label(0, (*BOX[:3], 0.0, 1.0, 1.0, 0.0), "box", "ann")
    with pytest.raises(SessionError, match="out of range"):
        db.add_label(99, BOX, "box", "ann")
    with pytest.raises(SessionError, match="no label"):
        db.update_label(10**6, "ann", class_name="box")
    assert len(db.edits()) == count


def test_undo_and_redo_walk_the_authors_edits(db):
    label = db.labels(0)[0]
    db.update_label(label.id, "ann", class_name="truck")
    added = db.add_label(0, BOX, "cone", "ann")
    assert db.undo("ann").kind == "add"
    assert db.label(added.id).deleted
    assert db.undo("ann").kind == "update"
    assert db.label(label.id).class_name == label.class_name
    assert db.undo("ann") is None
    assert db.redo("ann").kind == "update" and db.label(label.id).class_name == "truck"
    assert db.redo("ann").kind == "add" and not db.label(added.id).deleted
    assert db.redo("ann") is None
    # A new edit drops what was left to redo.
    db.undo("ann")
    db.add_label(1, BOX, "box", "ann")
    assert db.redo("ann") is None
    assert db.can_undo("ann") == (True, False)


def test_undo_is_per_author_and_refuses_to_overwrite_a_later_change(db):
    label = db.labels(0)[0]
    db.update_label(label.id, "ann", class_name="truck")
    db.update_label(label.id, "bob", class_name="cone")
    with pytest.raises(EditConflictError, match="changed since"):
        db.undo("ann")
    assert db.label(label.id).class_name == "cone"
    assert db.undo("bob").kind == "update" and db.label(label.id).class_name == "truck"
    assert db.undo("ann") is not None and db.label(label.id).class_name == label.class_name


def test_a_stale_edit_is_told_not_applied(db):
    label = db.labels(0)[0]
    db.update_label(label.id, "ann", expected_version=label.version, class_name="truck")
    with pytest.raises(EditConflictError, match="changed by ann"):
        db.update_label(label.id, "bob", expected_version=label.version, class_name="cone")
    with pytest.raises(EditConflictError):
        db.delete_labels([label.id], "bob", {label.id: label.version})
    assert db.label(label.id).class_name == "truck" and not db.label(label.id).deleted


def test_concurrent_edits_from_two_threads_are_all_kept(db):
    db.labels(0)
    errors: list[BaseException] = []

    def work(author: str) -> None:
        try:
            for k in range(40):
                label = db.add_label(0, (k, 0, 0.5, 1, 1, 1, 0), "box", author)
                db.update_label(label.id, author, expected_version=label.version, class_name="cone")
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(a,)) for a in ("ann", "bob")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    mine = [lab for lab in db.labels(0) if lab.origin == "user"]
    assert len(mine) == 80 and all(lab.class_name == "cone" for lab in mine)
    assert len(db.edits(limit=1000)) == 160


_WRITER = """
import sys
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session
db = SessionDB(open_session("s", sys.argv[1]), open_dataset(sys.argv[2]))
print("READY", flush=True)
k = 0
while True:
    label = db.add_label(0, (k, 0, 0.5, 1, 1, 1, 0), "box", "writer")
    print("ACK", label.id, flush=True)
    k += 1
"""


def test_sigkill_mid_stream_loses_no_acknowledged_edit(db, tmp_path):
    db.labels(0)  # the database exists with the frame imported before the writers start
    rng = np.random.default_rng(0)
    acknowledged: list[int] = []
    for _ in range(8):
        writer = subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(db.session.root), str(db.dataset.path)],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert writer.stdout.readline().strip() == "READY"
        stop_after = int(rng.integers(1, 30))
        for _ in range(stop_after):
            acknowledged.append(int(writer.stdout.readline().split()[1]))
        time.sleep(float(rng.uniform(0, 0.01)))  # land the kill at a random point of the next edit
        writer.send_signal(signal.SIGKILL)
        writer.wait()
        writer.stdout.close()
    survived = {lab.id for lab in _reopen(db).labels(0)}
    assert set(acknowledged) <= survived
    assert len(acknowledged) >= 8


def _assert_refused_untouched(path: Path, match: str, dataset) -> None:
    before = path.read_bytes()
    with pytest.raises(SessionError, match=match):
        SessionDB(open_session(path.parent.name, path.parent.parent), dataset)
    assert path.read_bytes() == before
    assert not Path(str(path) + "-wal").exists()


def test_newer_schema_is_refused_untouched(db, dataset):
    db.labels(0)
    connection = sqlite3.connect(db.path)
    connection.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    connection.execute("PRAGMA journal_mode = DELETE")
    connection.close()
    _assert_refused_untouched(db.path, "newer than this factorydet", dataset)


def test_garbage_and_truncated_databases_are_refused_untouched(db, dataset, tmp_path):
    for k in range(30):
        db.add_label(0, (k, 0, 0.5, 1, 1, 1, 0), "box", "ann")
    connection = sqlite3.connect(db.path)
    connection.execute("PRAGMA journal_mode = DELETE")  # fold the WAL into the file
    connection.close()
    data = db.path.read_bytes()
    db.path.write_bytes(data[: len(data) // 2])
    _assert_refused_untouched(db.path, "damaged|not a readable|malformed", dataset)
    db.path.write_bytes(b"this is not a database at all" * 100)
    _assert_refused_untouched(db.path, "not a readable", dataset)
    other = tmp_path / "o" / "session.db"
    other.parent.mkdir()
    connection = sqlite3.connect(other)
    connection.execute("CREATE TABLE stuff (x)")
    connection.close()
    _assert_refused_untouched(other, "not a factorydet session", dataset)


def test_a_session_refuses_a_different_data_set(db, default_dataset_dir):
    db.labels(0)
    with pytest.raises(SessionError, match="differs"):
        SessionDB(db.session, open_dataset(default_dataset_dir))


def test_review_verdicts_labels_undo_and_conflicts(db, tiny_model_path):
    run_id = db.save_training_run(_fake_run(tiny_model_path), "small", {"rounds": 1})
    queue = db.review_queue()
    assert [item["score"] for item in queue] == sorted((item["score"] for item in queue), reverse=True)
    assert all(item["verdict"] is None for item in queue) and len(queue) == 6
    assert len(db.review_queue(predicted_class="barrel")) == 3
    assert len(db.review_queue(frame_index=1)) == 3
    top, second, third = queue[0], queue[1], queue[2]

    num_labels = len(db.labels(top["frame_index"]))
    db.review([top["id"]], "object", "ann", class_name="bobbin", expected={top["id"]: None})
    labels = db.labels(top["frame_index"])
    assert len(labels) == num_labels + 1
    assert labels[-1].origin == "review" and labels[-1].class_name == "bobbin"
    assert labels[-1].box == pytest.approx(top["box"])
    db.review([second["id"], third["id"]], "background", "bob")
    progress = db.review_progress(run_id)
    assert progress == {
        "total": 6, "reviewed": 3, "background": 2, "object": 1, "wrong_box": 0, "skip": 0
    }  # fmt: skip
    # Someone who still sees the item unreviewed is told, not obeyed.
    with pytest.raises(EditConflictError, match="by ann"):
        db.review([top["id"]], "background", "bob", expected={top["id"]: None})
    # Changing the verdict away from 'object' deletes the label it made; undo brings it back.
    db.review([top["id"]], "wrong_box", "ann")
    assert len(db.labels(top["frame_index"])) == num_labels
    db.undo("ann")
    assert len(db.labels(top["frame_index"])) == num_labels + 1
    db.undo("ann")
    assert len(db.labels(top["frame_index"])) == num_labels
    assert db.review_queue()[0]["verdict"] is None
    assert len(db.review_queue(pending_only=True)) == 4
    reviewed = db.reviewed_patch_sets()
    assert sum(len(v) for v in reviewed["background"].values()) == 2
    with pytest.raises(SessionError, match="needs a class"):
        db.review([top["id"]], "object", "ann")
    with pytest.raises(SessionError, match="unknown verdict"):
        db.review([top["id"]], "maybe", "ann")
    # All of it is there after a reopen.
    assert _reopen(db).review_progress(run_id)["background"] == 2


def test_training_runs_point_at_their_checkpoints_and_label_snapshot(db, tiny_model_path):
    snapshot_id = db.snapshot_labels([0, 1])
    run_id = db.save_training_run(_fake_run(tiny_model_path), "small", {}, snapshot_id=snapshot_id)
    db.add_label(0, BOX, "cone", "ann")  # after the snapshot: not part of it
    run = db.training_runs()[0]
    assert run["id"] == run_id and run["snapshot_id"] == snapshot_id
    assert (db.session.path / run["model_path"]).is_file()
    assert [r["round"] for r in run["rounds"]] == [0, 1]
    snapshot = db.snapshot(snapshot_id)
    assert snapshot["frames"] == [0, 1]
    assert len(snapshot["labels"]) == len(db.labels(0)) - 1 + len(db.labels(1))


def test_a_new_verdict_never_discards_an_edit_of_the_label_it_made(db, tiny_model_path):
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    item = db.review_queue()[0]
    db.review([item["id"]], "object", "ann", class_name="box")
    label_id = db.review_queue()[0]["label_id"]
    db.update_label(label_id, "bob", class_name="truck")  # someone corrects the new label
    with pytest.raises(EditConflictError, match="edited since"):
        db.review([item["id"]], "background", "ann")
    assert db.label(label_id).class_name == "truck" and not db.label(label_id).deleted


def test_a_session_opens_the_data_set_it_was_made_on(small_dataset_dir, tmp_path):
    from factorydet_core.session.store import SessionError, open_session_data, session_data

    with pytest.raises(SessionError, match="has no data set"):
        open_session_data("fresh", tmp_path)
    # Made on a data set outside its folder: the database remembers which.
    db, dataset = open_session_data("outside", tmp_path, small_dataset_dir)
    assert dataset.path == Path(small_dataset_dir) and db.meta()["data"]
    again, dataset = open_session_data("outside", tmp_path)
    assert dataset.path.resolve() == Path(small_dataset_dir).resolve()
    assert session_data(again.session).resolve() == Path(small_dataset_dir).resolve()


# --- Read-only opens, busy writers, damaged files (issue 29) --------------------------------------


@pytest.fixture
def write_lock(db):
    """Hold the database's write lock from another connection, as a writing process would."""
    db.labels(0)
    holder = sqlite3.connect(db.path, isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    holder.execute("UPDATE meta SET value = value WHERE key = 'created'")
    yield holder
    holder.execute("ROLLBACK")
    holder.close()


def test_a_read_only_open_neither_writes_nor_waits_for_a_writer(db, dataset, tiny_model_path, write_lock):
    write_lock.execute("ROLLBACK")
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    write_lock.execute("BEGIN IMMEDIATE")
    before = db.path.read_bytes()
    start = time.perf_counter()
    reader = SessionDB(db.session, dataset, readonly=True)
    queue = reader.review_queue()
    labels = reader.frame_labels([0, 2])
    assert time.perf_counter() - start < 5.0  # a writer held the lock all along
    assert len(queue) == 6 and all(item["review_version"] == 0 for item in queue)
    # Frame 2 was never stored: read from the data set as the first write will store it.
    assert [lab.id for lab in labels[2]] == [None] * len(dataset.frame(2).labels)
    assert all(lab.id is not None for lab in labels[0])
    with pytest.raises(SessionError, match="read-only"):
        reader.add_label(0, BOX, "box", "ann")
    assert db.path.read_bytes() == before


def test_a_busy_writer_is_a_one_line_error_after_a_bounded_wait(db, dataset, write_lock):
    from factorydet_core.session.store import SessionBusyError

    writer = SessionDB(db.session, dataset, timeout=0.3)
    start = time.perf_counter()
    with pytest.raises(SessionBusyError, match="busy") as caught:
        writer.add_label(0, BOX, "box", "ann")
    assert time.perf_counter() - start < 5.0
    assert "\n" not in str(caught.value)


def test_a_read_only_session_file_can_be_read(db, dataset):
    db.labels(0)
    with unwritable(db.path):
        with pytest.raises(OSError):
            db.path.open("ab")  # really unwritable, also for root
        assert len(SessionDB(db.session, dataset, readonly=True).labels(0)) == len(dataset.frame(0).labels)


def test_a_schema_1_database_is_read_as_it_is_and_migrated_by_a_writer(tmp_path, dataset):
    from factorydet_core.session.store import _SCHEMA_V1

    session = open_session("old", tmp_path)
    session.path.mkdir()
    connection = sqlite3.connect(session.db_path, isolation_level=None)
    connection.executescript(_SCHEMA_V1 + ";PRAGMA user_version = 1;")
    connection.execute("INSERT INTO meta VALUES ('created', 'then')")
    connection.close()
    before = session.db_path.read_bytes()
    reader = SessionDB(session, dataset, readonly=True)
    assert reader.schema_version == 1 and reader.review_queue() == []
    assert len(reader.labels(0)) == len(dataset.frame(0).labels)
    assert session.db_path.read_bytes() == before
    SessionDB(session, dataset).labels(0)
    connection = sqlite3.connect(session.db_path)
    assert connection.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert "review_version" in {r[1] for r in connection.execute("PRAGMA table_info(mined_negatives)")}
    connection.close()


def _damage(path: Path, statements: list[str]) -> None:
    connection = sqlite3.connect(path, isolation_level=None)
    for statement in statements:
        connection.execute(statement)
    connection.close()


@pytest.mark.parametrize(
    "statements",
    [
        ["PRAGMA user_version = -1"],
        ["PRAGMA user_version = 99"],
        [
            "PRAGMA writable_schema = ON",
            "UPDATE sqlite_master SET sql = substr(sql, 1, 20) || ' garbage' WHERE name = 'labels'",
        ],
        ["PRAGMA foreign_keys = OFF", "DROP TABLE frames"],
        ["UPDATE labels SET box = 'not json' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE labels SET box = '[1,2]' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE labels SET box = '[1e999,0,0,1,1,1,0]' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE labels SET box = '{}' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE labels SET frame_index = 'x', box = 'nan' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE labels SET class_name = 'zzz' WHERE id = (SELECT min(id) FROM labels)"],
        ["UPDATE edits SET changes = 'garbage'"],
    ],
    ids=[
        "version-1",
        "version99",
        "schema",
        "no-frames",
        "box-text",
        "box-short",
        "box-inf",
        "box-dict",
        "frame-text",
        "class",
        "edit-log",
    ],
)
def test_a_damaged_database_is_a_one_line_error_and_is_never_written(db, dataset, statements):
    db.labels(0)
    db.update_label(db.labels(0)[0].id, "ann", class_name="cone")
    _damage(db.path, statements)
    before = db.path.read_bytes()
    with pytest.raises(SessionError) as caught:
        # What the commands and the app do first.
        opened = SessionDB(db.session)
        opened.frame_boxes(0)
        opened.edits()
        opened.training_runs()
        opened.review_progress()
        opened.undo("ann")
    assert "\n" not in str(caught.value)
    assert db.path.read_bytes() == before


# --- Every verdict is versioned (issue 29) --------------------------------------------------------


def test_a_queue_read_again_is_the_same_and_sees_new_verdicts(db, tiny_model_path):
    """A run's mined rows are checked once and kept; each read still takes the verdicts and review
    versions of that moment, and an item a caller changed does not change the next read."""
    db.save_training_run(_fake_run(tiny_model_path), "small", {"rounds": 1})
    first = db.review_queue()
    again = db.review_queue()
    assert again == first and again[0] is not first[0]
    first[0]["patch_set"].append(999)
    assert 999 not in db.review_queue()[0]["patch_set"]
    top = first[0]
    db.review([top["id"]], "background", "ann")
    after = {q["id"]: q for q in db.review_queue()}[top["id"]]
    assert after["verdict"] == "background" and after["reviewer"] == "ann"
    assert after["review_version"] == top["review_version"] + 1
    # Another process's view of the same database reads the same queue.
    other = SessionDB(db.session, db.dataset)
    assert other.review_queue() == db.review_queue()


def test_another_reviewers_verdict_is_a_conflict_unless_overridden(db, tiny_model_path):
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    first, second, third = db.review_queue()[:3]
    num_labels = len(db.labels(first["frame_index"]))
    db.review([first["id"]], "object", "ann", class_name="box")
    # Bob, from the command line (no expectation), is told item by item; nothing is written.
    with pytest.raises(EditConflictError, match=r"1 of 2 item\(s\) refused.*object \(box\) by ann") as caught:
        db.review([first["id"], second["id"]], "background", "bob")
    assert [c["id"] for c in caught.value.conflicts] == [first["id"]]
    assert {q["id"]: q["verdict"] for q in db.review_queue()}[second["id"]] is None
    assert len(db.labels(first["frame_index"])) == num_labels + 1
    # The same verdict is no conflict, and a skip is no decision: both go through.
    db.review([first["id"]], "object", "bob", class_name="box")
    db.review([third["id"]], "skip", "ann")
    db.review([third["id"]], "background", "bob")
    # Overridden explicitly: Bob's verdict stands, and Ann's undo is refused, not silent.
    db.review([first["id"]], "background", "bob", override=True)
    assert len(db.labels(first["frame_index"])) == num_labels
    with pytest.raises(EditConflictError, match="changed since"):
        db.undo("ann")


def test_a_verdict_against_a_stale_version_is_refused_even_if_it_looks_the_same(db, tiny_model_path):
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    seen = db.review_queue()[0]  # Alice's screen: unreviewed, version 0
    db.review([seen["id"]], "background", "bob")
    db.undo("bob")  # unreviewed again, as Alice saw it, but not the same state any more
    now = db.review_queue()[0]
    assert now["verdict"] is None and now["review_version"] == seen["review_version"] + 2
    with pytest.raises(EditConflictError, match="since you loaded it"):
        db.review([seen["id"]], "object", "alice", class_name="box", expected_versions={seen["id"]: 0})
    db.review([seen["id"]], "object", "alice", class_name="box", expected_versions={seen["id"]: 2})
    assert db.review_queue()[0]["review_version"] == 3


@pytest.mark.parametrize(
    ("box", "match"),
    [
        ((0, 0, 0, 1e300, 1, 1, 0), "sizes"),
        ((0, 0, 0, 0, 1, 1, 0), "sizes"),
        ((1e12, 0, 0, 1, 1, 1, 0), "from the vehicle"),
        ((0, 0, 0, 1, 1, 1, 1e20), "yaw"),
        ((0, 0, 0, 1, 1, 1, float("nan")), "finite"),
        ((0, 0, 0, 1, 1, 1), "7 finite numbers"),
        (("a", 0, 0, 1, 1, 1, 0), "7 numbers"),
    ],
)
def test_absurd_boxes_are_refused(db, box, match):
    with pytest.raises(SessionError, match=match):
        db.add_label(0, box, "box", "ann")


def test_a_yaw_is_wrapped_and_frame_indices_are_true_integers(db):
    from factorydet_core.session.store import check_frame_index

    assert db.add_label(0, (0, 0, 0.5, 1, 1, 1, 7.0), "box", "ann").box[6] == pytest.approx(7.0 - 2 * np.pi)
    assert check_frame_index(3) == check_frame_index(3.0) == check_frame_index(np.int64(3)) == 3
    for bad in (1.7, True, np.bool_(True), "1", None, -1, float("inf"), 2**70):
        with pytest.raises(SessionError, match="frame index"):
            check_frame_index(bad)


# --- Every row read is checked; undo writes back only what it checked (issue 29 review) --------


def _queue_db(db: SessionDB, tiny_model_path) -> list[dict]:
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    return db.review_queue()


_QUEUE_READS = ("review_queue", "review")
"""(``review_progress`` counts verdicts in SQL: it reads no other column, see the verdict case)"""


@pytest.mark.parametrize(
    ("statement", "match", "reads"),
    [
        ("UPDATE mined_negatives SET score = 'abc' WHERE id = {item}", "score", _QUEUE_READS),
        ("UPDATE mined_negatives SET box = '[1,2]' WHERE id = {item}", "box", _QUEUE_READS),
        ("UPDATE mined_negatives SET box = '{{}}' WHERE id = {item}", "box", _QUEUE_READS),
        ("UPDATE mined_negatives SET frame_index = 'x' WHERE id = {item}", "frame_index", _QUEUE_READS),
        (
            "UPDATE mined_negatives SET patch_set = '[\"a\"]' WHERE id = {item}",
            "patch_set",
            (*_QUEUE_READS, "mined_patch_sets"),
        ),
        ("UPDATE reviews SET label_id = 'x'", "label_id", ("review_queue",)),
        (
            "PRAGMA ignore_check_constraints = 1; UPDATE reviews SET verdict = 'maybe'",
            "verdict",
            ("review_queue", "review_progress"),
        ),
        ("UPDATE training_runs SET config = '[1]'", "config", ("training_runs",)),
        ("UPDATE training_rounds SET fit_seconds = 'x'", "fit_seconds", ("training_runs",)),
    ],
    ids=["score", "box-short", "box-dict", "frame", "patch-set", "review", "verdict", "config", "round"],
)
def test_a_damaged_row_of_any_table_is_a_one_line_error_naming_it(
    db, tiny_model_path, statement, match, reads
):
    queue = _queue_db(db, tiny_model_path)
    item = queue[0]["id"]
    db.review([item], "background", "ann")
    _damage(db.path, statement.format(item=item).split("; "))
    before = db.path.read_bytes()
    reader = SessionDB(db.session, db.dataset, readonly=True)
    table = statement.split("; ")[-1].split()[1]
    for name in reads:
        read = (
            (lambda: _reopen(db).review([item], "object", "bob", class_name="box", override=True))
            if name == "review"
            else getattr(reader, name)
        )
        with pytest.raises(SessionError, match=rf"damaged: {table} row [(\d, )]+\)?, {match}:") as caught:
            read()
        assert "\n" not in str(caught.value), name
    assert db.path.read_bytes() == before


def test_the_commands_refuse_damaged_mined_negatives_in_one_line(db, tiny_model_path, capsys):
    from factorydet_core import cli

    item = _queue_db(db, tiny_model_path)[0]["id"]
    common = ["--session", "s", "--root", str(db.session.root), "--data", str(db.dataset.path)]
    for statement, commands in (
        (f"UPDATE mined_negatives SET score = 'abc' WHERE id = {item}", [["queue"]]),
        (f"UPDATE mined_negatives SET box = '[1,2]' WHERE id = {item}", [["queue"], ["queue", "--json"]]),
        (f"UPDATE mined_negatives SET box = '{{}}' WHERE id = {item}", [["queue"], ["queue", "--json"]]),
        (
            f"UPDATE mined_negatives SET frame_index = 'x' WHERE id = {item}",
            [
                ["queue"],
                ["review", "--ids", str(item), "--verdict", "object", "--class", "box", "--author", "a"],
            ],
        ),
    ):
        _damage(db.path, [statement])
        for command in commands:
            capsys.readouterr()
            assert cli.main([command[0], *common, *command[1:]]) == 2, (statement, command)
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and f"mined_negatives row {item}" in err, err
        _damage(
            db.path,
            [
                f"UPDATE mined_negatives SET score = 0.5, box = '[0,0,0.5,1,1,1,0]', frame_index = 0"
                f" WHERE id = {item}"
            ],
        )


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ("[1]", "change 0 is 1"),
        ('[{"table": "meta", "key": 1, "before": null, "after": null}]', "names the table 'meta'"),
        ('{"a": 1}', "changes: .* is not a JSON list"),
        ("box", r"change 0, before \(labels row \d+\), box: .*1e\+300"),
        ("class", "class 'spaceship' is not one of the session's"),
        ("deleted", "deleted: True is not an integer"),
        ("frame", "frame 77 is not one of the data set's"),
    ],
)
def test_undo_and_redo_check_what_the_edit_log_would_write_back(db, changes, match):
    import json

    label = db.labels(0)[0]
    db.update_label(label.id, "ann", box=BOX)
    connection = sqlite3.connect(db.path)
    (logged,) = connection.execute("SELECT changes FROM edits ORDER BY id DESC LIMIT 1").fetchone()
    connection.close()
    change = json.loads(logged)[0]
    if changes == "box":
        change["before"]["box"] = "[0, 0, 0.5, 1e300, 1, 1, 0]"
    elif changes == "class":
        change["before"]["class_name"] = "spaceship"
    elif changes == "deleted":
        change["before"]["deleted"] = True
    elif changes == "frame":
        change["before"]["frame_index"] = 77
    text = json.dumps([change]) if changes in ("box", "class", "deleted", "frame") else changes
    _damage(db.path, [f"UPDATE edits SET changes = '{text}'"])
    stored = db.label(label.id)
    with pytest.raises(SessionError, match=f"edits row \\d+.*{match}") as caught:
        db.undo("ann")
    assert "\n" not in str(caught.value)
    assert db.label(label.id) == stored  # nothing written back
    connection = sqlite3.connect(db.path)
    assert connection.execute("SELECT state FROM edits ORDER BY id DESC LIMIT 1").fetchone()[0] == "done"
    connection.close()


def test_a_label_of_a_class_the_session_does_not_have_is_refused_where_it_is_read(db, tmp_path):
    from factorydet_core.session.labels_io import export_labels

    label = db.labels(0)[0]
    _damage(db.path, [f"UPDATE labels SET class_name = 'spaceship' WHERE id = {label.id}"])
    for read in (
        lambda: db.label(label.id),
        lambda: db.labels(0),
        lambda: export_labels(db, "json", tmp_path / "out.json"),
    ):
        with pytest.raises(SessionError, match=f"labels row {label.id}, class_name: 'spaceship'"):
            read()
    assert not (tmp_path / "out.json").exists()
    # The door a data set without classes left open (any class was taken) is closed.
    db.dataset.class_names = ()
    with pytest.raises(SessionError, match="the data set names no classes"):
        db.add_label(1, BOX, "spaceship", "ann")


def test_a_label_read_before_is_checked_again_once_its_row_changed(db):
    # Labels are checked once per row content (the app reads every shown frame's after each
    # edit): a row changed behind the session's back, its version untouched, is checked again.
    label = db.labels(0)[0]
    assert db.labels(0)[0] is label  # the same row: the label checked before
    _damage(db.path, [f"UPDATE labels SET box = '[1,2]' WHERE id = {label.id}"])
    with pytest.raises(SessionError, match=f"labels row {label.id}, box:"):
        db.labels(0)
    _damage(db.path, [f"UPDATE labels SET box = '{json.dumps([9.0, 9.0, 0.5, 1.0, 1.0, 1.0, 0.0])}'"
                      f" WHERE id = {label.id}"])  # fmt: skip
    assert db.label(label.id).box == (9.0, 9.0, 0.5, 1.0, 1.0, 1.0, 0.0)


def test_the_queues_overlap_with_the_labels_follows_every_label_edit(db, tiny_model_path):
    item = _queue_db(db, tiny_model_path)[0]
    frame = item["frame_index"]
    on_it = db.add_label(frame, item["box"], "box", "ann")
    assert {q["id"]: q["label_iou"] for q in db.review_queue()}[item["id"]] == pytest.approx(1.0)
    moved = [v + 50.0 if k < 2 else v for k, v in enumerate(item["box"])]
    db.update_label(on_it.id, "ann", box=moved, expected_version=on_it.version)
    assert {q["id"]: q["label_iou"] for q in db.review_queue()}[item["id"]] < 1.0
    db.undo("ann")
    assert {q["id"]: q["label_iou"] for q in db.review_queue()}[item["id"]] == pytest.approx(1.0)


# --- The data set's own annotations are the user's data (issue 29 review) ----------------------


def _dataset_with_boxes(source: Path, target: Path, boxes: list, class_ids: list | None = None) -> Path:
    """A copy of the data set ``source`` whose frame 0 has ``boxes`` as its annotations."""
    import shutil

    shutil.copytree(source, target)
    frame_file = target / "frames" / "frame_00000.npz"
    with np.load(frame_file) as stored:
        arrays = {name: stored[name] for name in stored.files}
    arrays["label_boxes"] = np.array(boxes, np.float64).reshape(-1, 7)
    count = len(arrays["label_boxes"])
    arrays["label_class_ids"] = np.array(class_ids or [2] * count, np.int32)
    arrays["label_instance_ids"] = np.arange(1, count + 1, dtype=np.int64)
    arrays["label_num_points"] = np.zeros(count, np.int64)
    np.savez(frame_file, **arrays)
    return target


def test_the_data_sets_own_odd_annotations_are_kept_and_usable(small_dataset_dir, tmp_path):
    from factorydet_core.session.labels_io import export_labels, import_labels, read_labels
    from factorydet_core.session.store import MIN_BOX_SIZE

    odd = [
        [1.0, 2.0, 0.5, 1.0, 1.0, 0.0, 0.0],  # flat: dz = 0
        [0.0, 0.0, 5.0, 150.0, 80.0, 10.0, 0.0],  # a hall outline
        [20_000.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0],  # 20 km out
    ]
    dataset = open_dataset(_dataset_with_boxes(small_dataset_dir, tmp_path / "odd", odd))
    db = SessionDB(open_session("odd", tmp_path / "sessions"), dataset)
    readonly_first = SessionDB(db.session, dataset, readonly=True).labels(0)  # before any write
    labels = db.labels(0)
    assert [lab.box for lab in readonly_first] == [lab.box for lab in labels]
    assert labels[0].box[5] == MIN_BOX_SIZE  # thickened, so that its volume and IoU are defined
    assert [lab.box[:5] for lab in labels] == [tuple(b[:5]) for b in odd]
    assert db.frame_boxes(0)[0].shape == (3, 7)
    # Export, import into the frame, a class change: all work on that frame.
    export_labels(db, "json", tmp_path / "odd.json")
    # The export imports back: every box (the odd ones of frame 0 too) repeats a label.
    exported = read_labels(tmp_path / "odd.json")
    assert sum(frame == 0 for frame, _, _ in exported) == 3
    again = import_labels(db, tmp_path / "odd.json", "ann")
    assert again["imported"] == 0 and len(again["duplicates"]) == len(exported)
    other = tmp_path / "new.json"
    other.write_text(
        '{"frames": [{"frame_index": 0, "boxes": [[1, 2, 0.5, 1, 1, 0.001, 0], [5, 5, 0.5, 1, 1, 1, 0]],'
        ' "labels": ["box", "box"]}]}'
    )
    report = import_labels(db, other, "ann")
    assert report["imported"] == 1 and len(report["duplicates"]) == 1  # the flat one repeats label 0
    db.update_label(labels[1].id, "ann", class_name="truck")
    db.undo("ann")
    assert db.label(labels[1].id).box == labels[1].box


@pytest.mark.parametrize(
    ("box", "class_id", "match"),
    [
        ([0.0, 0.0, 0.5, 1.0, -1.0, 1.0, 0.0], 2, "sizes must not be negative"),
        ([0.0, 0.0, 0.5, 1e12, 1.0, 1.0, 0.0], 2, "beyond"),
        ([0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0], 99, "class ids must lie"),  # the reader's own check
    ],
)
def test_an_unusable_data_set_annotation_names_the_data_set_frame_and_box(
    small_dataset_dir, tmp_path, box, class_id, match
):
    good = [0.0, 5.0, 0.5, 1.0, 1.0, 1.0, 0.0]
    data = _dataset_with_boxes(small_dataset_dir, tmp_path / "bad", [good, box], [2, class_id])
    dataset = open_dataset(data)
    db = SessionDB(open_session("bad", tmp_path / "sessions"), dataset)
    for read in (lambda: db.labels(0), lambda: SessionDB(db.session, dataset, readonly=True).labels(0)):
        with pytest.raises(InputError, match=match) as caught:
            read()
        message = str(caught.value)
        assert "\n" not in message and str(data) in message and "frame_00000" in message
        assert class_id == 99 or f"{data}: frame 0 (frame_00000), annotation 1:" in message
    assert len(db.labels(1)) == len(dataset.frame(1).labels)  # the other frames are unaffected


# --- Read-only folders and sessions (issue 29 review) ------------------------------------------


def test_a_wal_session_in_a_read_only_folder_can_be_read(db, dataset, tiny_model_path, tmp_path):
    from factorydet_core.session.labels_io import export_labels

    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    db.labels(0)
    assert not Path(f"{db.path}-shm").exists()  # every connection closed: no WAL index left
    with unwritable(db.session.path):
        with pytest.raises(OSError):
            (db.session.path / "probe").write_text("x")  # really unwritable, also for root
        reader = SessionDB(db.session, dataset, readonly=True)
        assert len(reader.review_queue()) == 6
        assert len(reader.labels(0)) == len(dataset.frame(0).labels)
        export_labels(reader, "json", tmp_path / "out.json", [0, 1])
        assert not Path(f"{db.path}-shm").exists()
    assert (tmp_path / "out.json").is_file()


def test_a_wal_with_changes_in_a_read_only_folder_is_a_clear_error(db, dataset, tmp_path):
    import shutil

    db.labels(0)
    holder = sqlite3.connect(db.path, isolation_level=None)
    try:
        holder.execute("PRAGMA wal_autocheckpoint = 0")
        holder.execute("UPDATE labels SET modified = 'later'")  # committed, in the WAL only
        copy = open_session("copy", tmp_path)
        copy.path.mkdir()
        for name in ("session.db", "session.db-wal"):  # a copy without the WAL index (-shm)
            shutil.copy(db.session.path / name, copy.path / name)
    finally:
        holder.close()
    with unwritable(copy.path):
        with pytest.raises(SessionError, match="holds changes not yet written") as caught:
            SessionDB(copy, dataset, readonly=True).labels(0)
    assert "\n" not in str(caught.value)


def test_a_session_that_cannot_be_written_is_refused_before_training(dataset, tmp_path, monkeypatch):
    from factorydet_core.proposals.settings import front_end_params
    from factorydet_core.training.settings import LoopSettings
    from factorydet_core.workflows import retrain_session

    SessionDB(open_session("ok", tmp_path), dataset).check_writable()  # writable: nothing said
    monkeypatch.setattr(
        "factorydet_core.workflows.cached_proposals", lambda *a, **k: pytest.fail("proposed first")
    )
    for name, match in (("file", "readonly database"), ("folder", "cannot write in")):
        db = SessionDB(open_session(name, tmp_path), dataset)
        db.labels(0)
        locked = unwritable(db.path if name == "file" else db.session.path)
        with (
            locked,
            pytest.raises(SessionError, match=f"session '{name}' cannot be written.*{match}") as exc,
        ):
            retrain_session(db, dataset, LoopSettings(), front_end_params("agv"), mode="full")
        assert "\n" not in str(exc.value)


# --- Boxes are real numbers (issue 29 review) ---------------------------------------------------


def test_a_box_of_bools_strings_or_complex_numbers_is_refused(db):
    from factorydet_core.session.store import check_box

    for bad in ([True, 0, 0.5, 1, 1, 1, 0], ["1", 0, 0.5, 1, 1, 1, 0], [1j, 0, 0.5, 1, 1, 1, 0], "1234567"):
        with pytest.raises(SessionError, match="7 numbers"):
            check_box(bad)
    with pytest.raises(SessionError, match="7 finite numbers"):
        check_box([10**400, 0, 0.5, 1, 1, 1, 0])
    with pytest.raises(SessionError, match="at least 0.001"):
        db.add_label(0, (0, 0, 0.5, 1e-7, 1, 1, 0), "box", "ann")  # would be stored as 0
    assert check_box(np.array([0, 0, 0.5, 1, 1, 1, 0], np.float32)) == [0, 0, 0.5, 1, 1, 1, 0]


# --- Reviewers are told apart by name (issue 29 review) -----------------------------------------


def test_review_and_undo_as_root_need_an_explicit_author(db, tiny_model_path, capsys, monkeypatch):
    from factorydet_core import cli

    item = _queue_db(db, tiny_model_path)[0]["id"]
    common = ["--session", "s", "--root", str(db.session.root), "--data", str(db.dataset.path)]
    review = ["review", *common, "--ids", str(item), "--verdict", "background"]
    monkeypatch.setattr("getpass.getuser", lambda: "root")
    for command in (review, ["undo", *common]):
        capsys.readouterr()
        assert cli.main(command) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "pass --author NAME" in err and "'root'" in err
    assert db.review_progress()["reviewed"] == 0
    assert cli.main([*review, "--author", "ann"]) == 0
    monkeypatch.setattr("getpass.getuser", lambda: "bob")  # a personal login is a name
    assert cli.main(["undo", *common]) == 1 and "nothing to undo for bob" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["review", "--help"])
    assert "as root, --author is therefore required" in " ".join(capsys.readouterr().out.split())


def test_a_copied_session_changes_without_changing_the_original(db, tmp_path):
    from factorydet_core.session.store import copy_session, read_cache, write_cache

    label = db.add_label(0, BOX, "box", "ann")
    write_cache(db.session, "proposals_x", {"a": np.arange(3)})
    (db.session.models_dir / "run_001").mkdir(parents=True)
    (db.session.models_dir / "run_001" / "final.json").write_text("{}")
    copy = copy_session(db.session, tmp_path / "copies")
    assert copy.name == db.session.name and copy.root == tmp_path / "copies"
    cached = "cache/proposals_x.npz"  # hard-linked: safe because every writer replaces the file
    assert (copy.path / cached).stat().st_ino == (db.session.path / cached).stat().st_ino
    copied = SessionDB(copy, db.dataset)
    assert [lab.id for lab in copied.labels(0)] == [lab.id for lab in db.labels(0)]
    assert (copy.models_dir / "run_001" / "final.json").read_text() == "{}"
    # Edits, caches and models written to the copy stay there.
    copied.delete_labels([label.id], "ann")
    write_cache(copy, "proposals_x", {"a": np.arange(5)})
    (copy.models_dir / "run_001" / "final.json").write_text('{"changed": 1}')
    assert label.id in [lab.id for lab in _reopen(db).labels(0)]
    np.testing.assert_array_equal(read_cache(db.session, "proposals_x")["a"], np.arange(3))
    assert (db.session.models_dir / "run_001" / "final.json").read_text() == "{}"
    with pytest.raises(SessionError, match="own folder"):
        copy_session(db.session, db.session.root)
    with pytest.raises(SessionError, match="no database"):
        copy_session(open_session("none", tmp_path), tmp_path / "copies")


def test_mined_point_sets_by_score_and_by_whether_someone_decided(db, tiny_model_path):
    items = [
        mined_item(0, g, [2.0 * g, 1.0, 0.5, 1.0, 1.0, 1.0, 0.0], score)
        for g, score in enumerate((0.9, 0.6, 0.3))
    ]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    assert db.mined_patch_sets() == {0: [(0,), (1,), (2,)]}
    assert db.mined_patch_sets(below_score=0.6) == {0: [(2,)]}
    assert db.mined_patch_sets(at_least_score=0.6) == {0: [(0,), (1,)]}
    ids = {q["score"]: q["id"] for q in db.review_queue()}
    db.review([ids[0.9]], "background", "ann")
    db.review([ids[0.6]], "skip", "ann")  # a skip decides nothing
    assert db.mined_patch_sets(at_least_score=0.6, undecided_only=True) == {0: [(1,)]}


def test_held_places_are_the_undecided_confident_boxes_off_the_labels(db, tiny_model_path):
    label = db.labels(0)[0]
    on_label = list(label.box)
    on_label[3] *= 1.2  # a loose box of a labelled object: IoU 1 / 1.2 with it
    off = [[40.0 + 2.0 * g, 40.0, 0.5, 1.0, 1.0, 1.0, 0.0] for g in range(3)]
    items = [
        mined_item(0, 0, off[0], 0.9),
        mined_item(0, 1, off[1], 0.8),
        mined_item(0, 2, off[2], 0.2),  # below the hold score
        mined_item(0, 3, on_label, 0.95),
        mined_item(1, 4, off[0], 0.7),
    ]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})
    held = db.held_places(0.5)
    assert set(held) == {0, 1}
    np.testing.assert_allclose(held[0], [off[0], off[1]])
    np.testing.assert_allclose(held[1], [off[0]])
    ids = {q["score"]: q["id"] for q in db.review_queue()}
    db.review([ids[0.9]], "background", "ann")  # decided: no longer held
    db.review([ids[0.8]], "skip", "ann")  # a skip decides nothing
    np.testing.assert_allclose(db.held_places(0.5)[0], [off[1]])
    # A label drawn on a held box makes it a labelled object's: no longer held.
    db.add_label(1, off[0], "box", "ann")
    assert 1 not in db.held_places(0.5)


def test_pseudo_labels_are_the_undecided_confident_negatives_off_the_labels(db, tiny_model_path):
    label = db.labels(0)[0]
    on_label = list(label.box)
    on_label[3] *= 1.2  # a loose box of a labelled object
    off = [[40.0 + 2.0 * g, 40.0, 0.5, 1.0, 1.0, 1.0, 0.0] for g in range(3)]
    items = [
        mined_item(0, 0, off[0], 0.9, predicted_class="cone"),
        mined_item(0, 1, off[1], 0.7, predicted_class="barrel"),
        mined_item(0, 2, off[2], 0.5),  # below the pseudo-label score: held, when holding
        mined_item(0, 3, on_label, 0.95),
        mined_item(1, 4, off[0], 0.8, predicted_class="no such class"),
    ]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})
    pseudo = db.pseudo_labels(0.6)
    assert set(pseudo) == {0}  # frame 1's class is not the session's: it teaches nothing
    sets, boxes, class_ids = pseudo[0]
    assert sets == [(0,), (1,)]
    np.testing.assert_allclose(boxes, [off[0], off[1]])
    assert [db.class_names[c] for c in class_ids] == ["cone", "barrel"]
    # The held places below the pseudo-labels: those between the two scores.
    np.testing.assert_allclose(db.held_places(0.4, below_score=0.6)[0], [off[2]])
    ids = {q["score"]: q["id"] for q in db.review_queue()}
    db.review([ids[0.9]], "background", "ann")  # a verdict replaces the pseudo-label
    db.review([ids[0.7]], "skip", "ann")  # a skip decides nothing
    assert db.pseudo_labels(0.6)[0][0] == [(1,)]
    # A set mined again by a later run is one pseudo-label, and a verdict on either row decides
    # both; another set on the same object (IoU 0.25 or more with a kept one) is none.
    again = [
        mined_item(0, 1, off[1], 0.65, predicted_class="barrel"),
        mined_item(0, 5, np.add(off[1], [0.1, 0, 0, 0, 0, 0, 0]).tolist(), 0.62, predicted_class="cone"),
        mined_item(0, 6, [60.0, 40.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9, predicted_class="cone"),
    ]
    again[1]["patch_set"] = [5]
    db.save_training_run(queue_run(tiny_model_path, [again], train_frames=(0, 1)), "small", {})
    assert db.pseudo_labels(0.6)[0][0] == [(6,), (1,)]  # most confident first
    newer = next(q["id"] for q in db.review_queue() if q["score"] == 0.65)
    db.review([newer], "background", "ann")
    assert db.pseudo_labels(0.6)[0][0] == [(6,), (5,)]  # (1,) decided; (5,) now stands alone
    assert (1,) not in db.mined_patch_sets(at_least_score=0.6, undecided_only=True)[0]
    # The review panel reads a run's pseudo-label score from its settings.
    run = db.save_training_run(
        queue_run(tiny_model_path, [[]]), "small", {"settings": {"pseudo_label_confident": 0.6}}
    )
    assert db.pseudo_label_score(run) == 0.6 and db.pseudo_label_score(run - 1) is None


def test_a_runs_hold_score_is_read_from_its_settings(db, tiny_model_path):
    first = db.save_training_run(
        queue_run(tiny_model_path, [[]]), "small", {"settings": {"hold_confident": 0.35}}
    )
    second = db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {})
    assert db.hold_score(first) == 0.35 and db.hold_score(second) is None
    with pytest.raises(SessionError, match="no training run 99"):
        db.hold_score(99)


def test_a_runs_config_is_read_alone_as_it_was_stored(db, tiny_model_path):
    config = {"mode": "next", "afresh_because": "the labels changed", "settings": {"epochs": 3}}
    first = db.save_training_run(queue_run(tiny_model_path, [[]]), "small", config)
    second = db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {"mode": "full"})
    assert db.run_config(first) == config and db.run_config(second) == {"mode": "full"}
    assert [db.run_config(r["id"]) for r in db.training_runs()] == [r["config"] for r in db.training_runs()]
    with pytest.raises(SessionError, match="no training run 99"):
        db.run_config(99)


def test_the_change_stamp_never_returns_after_a_verdict_is_undone_and_redone(db, tiny_model_path):
    """A queue cached on the stamp must see the verdicts' new versions: an undo then a redo leaves
    the edit log as it was, not the versions."""
    db.save_training_run(_fake_run(tiny_model_path), "small", {"rounds": 1})
    top = db.review_queue()[0]
    db.review([top["id"]], "background", "ann")
    stamps = [db.change_stamp()]
    db.undo("ann")
    stamps.append(db.change_stamp())
    db.redo("ann")
    stamps.append(db.change_stamp())
    assert len(set(stamps)) == 3
    assert {q["id"]: q for q in db.review_queue()}[top["id"]]["review_version"] == top["review_version"] + 3


def test_the_change_stamp_moves_with_every_edit_undo_and_redo_and_not_with_reads(db):
    stamps = [db.change_stamp()]
    db.labels(0)  # a first read imports the frame's annotations: not a change to anyone's view
    db.review_queue()
    assert db.change_stamp() == stamps[0]
    db.add_label(0, [30.0, 30.0, 0.5, 1, 1, 1, 0], "box", "ann")
    stamps.append(db.change_stamp())
    db.undo("ann")
    stamps.append(db.change_stamp())
    db.undo("ann")  # nothing more to undo
    assert db.change_stamp() == stamps[-1]
    db.redo("ann")  # back to the state after the edit, and its stamp
    assert db.change_stamp() == stamps[1] and len(set(stamps)) == 3
    db.add_label(0, [40.0, 30.0, 0.5, 1, 1, 1, 0], "box", "bob")
    db.undo("bob")
    bob_undone = db.change_stamp()
    db.redo("bob")
    db.undo("ann")  # one edit undone again, another one
    assert db.change_stamp() != bob_undone


def test_the_ray_setting_survives_reopening_and_bad_values_are_refused(db, dataset):
    assert db.execution() == {"workers": None, "ray_address": None}
    db.set_execution(3, "auto")
    assert SessionDB(db.session, dataset).execution() == {"workers": 3, "ray_address": "auto"}
    for workers, address in ((0, None), (True, None), (2.5, None), (5000, None), (None, " "), (None, 7)):
        with pytest.raises(SessionError):
            db.set_execution(workers, address)
    assert db.execution() == {"workers": 3, "ray_address": "auto"}
    with db._write() as connection:
        connection.execute("UPDATE meta SET value = '{\"workers\": -1}' WHERE key = 'execution'")
    with pytest.raises(SessionError, match="damaged"):
        db.execution()


def test_a_class_order_runs_queue_takes_turns_and_keeps_its_positions_under_filters(db, tiny_model_path):
    box = [40.0, 40.0, 0.5, 1.0, 1.0, 1.0, 0.0]
    mined = [(0.9, "box"), (0.8, "box"), (0.7, "box"), (0.3, "cone"), (0.2, "cone")]
    items = [mined_item(0, g, [box[0] + 2.0 * g, *box[1:]], s, name) for g, (s, name) in enumerate(mined)]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": {"queue_order": "class"}})
    assert db.review_order() == "class"
    queue = db.review_queue()
    assert [(q["predicted_class"], q["score"]) for q in queue] == [
        ("box", 0.9), ("cone", 0.3), ("box", 0.8), ("cone", 0.2), ("box", 0.7)
    ]  # fmt: skip
    db.review([queue[0]["id"]], "background", "ann")
    # A verdict or a filter leaves the rest where the whole queue put them.
    assert [q["score"] for q in db.review_queue(pending_only=True)] == [0.3, 0.8, 0.2, 0.7]
    assert [q["score"] for q in db.review_queue(predicted_class="box")] == [0.9, 0.8, 0.7]
    # A run of the paper's order, and one from before the setting, queue by score.
    for config in ({"settings": {"queue_order": "score"}}, {}):
        run = db.save_training_run(queue_run(tiny_model_path, [items]), "small", config)
        assert db.review_order(run) == "score"
        assert [q["score"] for q in db.review_queue(run)] == [0.9, 0.8, 0.7, 0.3, 0.2]
    # Cut by class turns, reviewed most likely first: the review queue follows review_order.
    run = db.save_training_run(
        queue_run(tiny_model_path, [items]),
        "small",
        {"settings": {"queue_order": "class", "review_order": "score"}},
    )
    assert db.review_order(run) == "score"
    assert [q["score"] for q in db.review_queue(run)] == [0.9, 0.8, 0.7, 0.3, 0.2]
    # A run with today's default settings reviews in the learned order, its items (and its places
    # until the ranker has answers to fit on) in the order its cut took.
    defaults = json.loads(json.dumps(dataclasses.asdict(LoopSettings(queue_order="class"))))
    run = db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": defaults})
    assert (db.review_order(run), db.cut_order(run)) == db.orders(run) == ("learned", "class")
    assert [q["score"] for q in db.review_queue(run)] == [0.9, 0.3, 0.8, 0.2, 0.7]
    broken = db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": [1, 2]})
    with pytest.raises(SessionError, match="its settings are .*not a mapping"):
        db.review_queue(broken)


def test_items_queued_for_review_alone_are_no_background_until_a_verdict(db, tiny_model_path):
    mined = [mined_item(0, g, [2.0 * g, 1.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9 - 0.1 * g) for g in range(2)]
    queued = [mined_item(0, g, [2.0 * g, 1.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.5 - 0.1 * g) for g in (2, 3, 4)]
    run = queue_run(tiny_model_path, [mined])
    run.rounds[0]["queued"] = queued
    db.save_training_run(run, "small", {})
    queue = db.review_queue()
    assert [q["in_background"] for q in queue] == [1, 1, 0, 0, 0]  # all of them in the queue
    assert db.mined_patch_sets() == {0: [(0,), (1,)]}
    assert db.held_places(0.0) == {0: pytest.approx(np.array([m["box"] for m in mined]))}
    db.review([queue[2]["id"]], "background", "ann")
    db.review([queue[3]["id"]], "object", "ann", class_name="box")
    reviewed = db.reviewed_patch_sets()
    assert reviewed["background"] == {0: [(2,)]} and reviewed["object"] == {0: [(3,)]}
    assert db.mined_patch_sets() == {0: [(0,), (1,)]}  # still: the verdicts decide the others


def test_a_schema_3_database_gains_in_background_with_its_rows_mined(tmp_path, dataset, tiny_model_path):
    from factorydet_core.session.store import _SCHEMA_V1, _SCHEMA_V2, _SCHEMA_V3

    session = open_session("v3", tmp_path)
    session.path.mkdir()
    connection = sqlite3.connect(session.db_path, isolation_level=None)
    connection.executescript(";".join((_SCHEMA_V1, _SCHEMA_V2, _SCHEMA_V3)) + ";PRAGMA user_version = 3;")
    connection.execute("INSERT INTO meta VALUES ('created', 'then')")
    connection.execute(
        "INSERT INTO training_runs VALUES (1, 'then', 'mining', 'small', '{}', '[0]', NULL, 'm.pt', NULL)"
    )
    connection.execute(
        "INSERT INTO mined_negatives (run_id, round, frame_index, proposal, box, patch_set, score,"
        " predicted_class, best_annotated_iou) VALUES (1, 0, 0, 7, '[0,0,0.5,1,1,1,0]', '[7]', 0.5, 'box', 0)"
    )
    connection.close()
    reader = SessionDB(session, dataset, readonly=True)  # read as it is: no column to filter on
    assert reader.schema_version == 3 and reader.mined_patch_sets() == {0: [(7,)]}
    assert [q["in_background"] for q in reader.review_queue()] == [1]
    db = SessionDB(session, dataset)
    assert db.schema_version == SCHEMA_VERSION and db.mined_patch_sets() == {0: [(7,)]}
    assert [q["in_background"] for q in db.review_queue()] == [1]


def test_a_box_the_model_gave_becomes_a_persons_when_they_move_it(db, tiny_model_path):
    """An Object verdict's label keeps the mined box (origin 'review': the model's box); a class
    change leaves it so, a moved box makes it the person's (origin 'user'), and undo gives the
    origin back. Training reads the origins as which boxes are the model's."""
    from factorydet_core.session.store import MODEL_BOX_ORIGINS
    from factorydet_core.training.loop import with_session_labels

    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    item = db.review_queue()[0]
    db.review([item["id"]], "object", "ann", class_name="box")
    label_id = db.review_queue()[0]["label_id"]
    assert db.label(label_id).origin == "review" and "review" in MODEL_BOX_ORIGINS
    db.update_label(label_id, "ann", class_name="barrel")
    assert db.label(label_id).origin == "review"

    class Frame:  # what with_session_labels reads of a frame's proposals
        frame_index = item["frame_index"]

        def with_labels(self, boxes, class_ids, instance_classes, ignore, model_box_mask, tuning_mask):
            return boxes, model_box_mask

    boxes, mask = with_session_labels(db, [Frame()])[0]
    assert mask.sum() == 1 and boxes[mask][0] == pytest.approx(db.label(label_id).box)
    moved = np.asarray(db.label(label_id).box) + np.array([0.05, 0, 0, 0, 0, 0, 0])
    db.update_label(label_id, "ann", box=moved)
    assert db.label(label_id).origin == "user"
    assert not with_session_labels(db, [Frame()])[0][1].any()
    db.undo("ann")
    assert db.label(label_id).origin == "review"


def test_a_schema_4_database_gives_people_the_model_boxes_they_moved(db, tiny_model_path):
    """Before version 5 a moved Object label kept origin 'review': the migration reads the edit log
    and makes the labels whose box an edit in force moved the person's; an unmoved one, or one
    whose move was undone, stays the model's."""
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    first, second, third = db.review_queue()[:3]
    for item in (first, second, third):
        db.review([item["id"]], "object", "ann", class_name="box")
    moved, kept, undone = (db.review_queue()[k]["label_id"] for k in range(3))
    for label_id in (moved, undone):
        box = np.asarray(db.label(label_id).box) + np.array([0.1, 0, 0, 0, 0, 0, 0])
        db.update_label(label_id, "ann", box=box)
    db.undo("ann")  # the last move
    assert [db.label(i).origin for i in (moved, kept, undone)] == ["user", "review", "review"]
    # As version 4 left it: the moved label still says 'review'.
    connection = sqlite3.connect(db.session.db_path, isolation_level=None)
    connection.execute("UPDATE labels SET origin = 'review' WHERE id = ?", (moved,))
    connection.execute("PRAGMA user_version = 4")
    connection.close()
    assert SessionDB(db.session, db.dataset, readonly=True).label(moved).origin == "review"
    again = _reopen(db)
    assert again.schema_version == SCHEMA_VERSION == 5
    assert [again.label(i).origin for i in (moved, kept, undone)] == ["user", "review", "review"]


def test_a_changed_verdict_deletes_the_object_it_made_though_a_person_moved_it(db, tiny_model_path, dataset):
    """An Object verdict with label once makes an object in every frame that shows it; moving the
    object makes its boxes the person's, and a verdict changed to background still deletes every
    one of them (undo brings them back)."""
    db.save_training_run(_fake_run(tiny_model_path), "small", {})
    item = db.review_queue()[0]
    other = 1 - item["frame_index"]

    def place(frame_index, box):
        return {frame_index: box, other: box}, [frame_index, other]

    db.review([item["id"]], "object", "ann", class_name="box", place=place)
    label_id = db.review_queue()[0]["label_id"]
    instance = db.label(label_id).instance_id
    members = [lab for f in (0, 1) for lab in db.labels(f) if lab.instance_id == instance]
    assert len(members) == 2 and {lab.origin for lab in members} == {"review"}
    sibling = next(lab for lab in members if lab.id != label_id)
    db.update_label(sibling.id, "ann", box=np.asarray(sibling.box) + np.array([0.1, 0, 0, 0, 0, 0, 0]))
    assert db.label(sibling.id).origin == "user"
    db.review([item["id"]], "background", "ann")
    assert db.label(label_id).deleted and db.label(sibling.id).deleted
    db.undo("ann")
    assert not db.label(label_id).deleted and not db.label(sibling.id).deleted
