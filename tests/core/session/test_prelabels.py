"""Pre-labels: the model's detections as labels nobody has confirmed yet, kept apart from the truth
(metrics, training, export) until a person confirms or edits them; schema 3's migration."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from factorydet_core.session.editing import prelabel_frame
from factorydet_core.session.labels_io import export_json, scene_arrays
from factorydet_core.session.store import (
    _SCHEMA_V1,
    _SCHEMA_V2,
    SCHEMA_VERSION,
    EditConflictError,
    SessionDB,
    open_session,
)
from factorydet_core.types import CLASS_NAMES, Detections, InputError


def _detections(boxes, scores, class_ids=None, suppressed_by=None) -> Detections:
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    k = len(boxes)
    return Detections(
        boxes=boxes,
        class_ids=np.zeros(k, np.int64) if class_ids is None else np.asarray(class_ids, np.int64),
        scores=np.asarray(scores, np.float32),
        probabilities=np.full((k, len(CLASS_NAMES) + 1), 1.0 / (len(CLASS_NAMES) + 1), np.float32),
        proposal_ids=np.arange(k, dtype=np.int64),
        suppressed_by=np.full(k, -1, np.int64) if suppressed_by is None else np.asarray(suppressed_by),
    )


FAR = [(30.0 + 3 * i, 30.0, 0.5, 0.6, 0.6, 1.0, 0.0) for i in range(4)]
"""Boxes far from every annotation of the small data set."""


def test_prelabelling_adds_the_confident_kept_detections_as_unreviewed_labels(db):
    before = len(db.labels(0))
    detections = _detections(FAR, [0.9, 0.4, 0.8, 0.95], suppressed_by=[-1, -1, -1, 0])
    added = prelabel_frame(db, 0, detections, "ann", min_score=0.5)
    assert len(added) == 2  # 0.4 is below the score, the 0.95 one was suppressed
    assert all(lab.origin == "model" and not lab.reviewed for lab in added)
    assert [lab.score for lab in added] == pytest.approx([0.9, 0.8])
    assert len(db.labels(0)) == before + 2
    assert [lab.id for lab in db.unreviewed_labels()] == [lab.id for lab in added]
    # Again: every place is labelled already, nothing is added twice.
    assert len(prelabel_frame(db, 0, detections, "ann", min_score=0.5)) == 0
    # The truth leaves them out: metrics, export.
    assert len(db.frame_boxes(0, reviewed=True)[0]) == before
    assert len(db.frame_boxes(0, reviewed=False)[0]) == 2
    db.undo("ann")
    assert db.unreviewed_labels() == [] and len(db.labels(0)) == before


def test_a_detection_on_a_labelled_object_is_no_pre_label(db):
    label = db.labels(0)[0]
    detections = _detections([label.box, FAR[0]], [0.9, 0.9])
    added = prelabel_frame(db, 0, detections, "ann")
    assert [tuple(lab.box) for lab in added] == [pytest.approx(FAR[0])]
    with pytest.raises(InputError, match="min_score"):
        prelabel_frame(db, 0, detections, "ann", min_score=1.5)


def test_confirming_or_editing_a_pre_label_makes_it_truth_and_undo_takes_it_back(db):
    added = prelabel_frame(db, 0, _detections(FAR[:3], [0.9, 0.8, 0.7]), "ann")
    a, b, c = added
    db.confirm_labels([a.id], "ann", expected_versions={a.id: a.version})
    assert db.label(a.id).reviewed and db.label(a.id).origin == "model"  # where it came from stays
    with pytest.raises(EditConflictError, match="confirmed already"):
        db.confirm_labels([a.id], "ann")
    db.update_label(b.id, "ann", box=(33.1, 30.0, 0.5, 0.6, 0.6, 1.0, 0.0))
    assert db.label(b.id).reviewed and db.label(b.id).origin == "user"  # a moved box is the person's
    db.update_label(c.id, "bob", class_name="box")
    assert [lab.id for lab in db.unreviewed_labels()] == []
    db.undo("bob")
    assert [lab.id for lab in db.unreviewed_labels()] == [c.id]
    db.undo("ann")  # the box edit
    db.undo("ann")  # the confirmation
    assert {lab.id for lab in db.unreviewed_labels()} == {a.id, b.id, c.id}
    db.redo("ann")
    assert db.label(a.id).reviewed


def test_export_writes_only_what_a_person_made_or_confirmed(db, tmp_path):
    a, b = prelabel_frame(db, 0, _detections(FAR[:2], [0.9, 0.8]), "ann")
    db.confirm_labels([a.id], "ann")
    record = export_json(db, tmp_path / "labels.json", [0])
    assert a.id in record["frames"][0]["label_ids"] and b.id not in record["frames"][0]["label_ids"]
    assert record["unreviewed_pre_labels_left_out"] == 1
    assert len(scene_arrays(db, 0)["boxes"]) == len(db.frame_boxes(0, reviewed=True)[0])


def test_snapshots_keep_whether_a_label_was_reviewed(db):
    (a,) = prelabel_frame(db, 0, _detections(FAR[:1], [0.9]), "ann")
    snapshot = db.snapshot(db.snapshot_labels([0]))
    flags = {lab["id"]: lab["reviewed"] for lab in snapshot["labels"]}
    assert flags[a.id] == 0 and sum(flags.values()) == len(flags) - 1


@pytest.mark.parametrize("version", [1, 2])
def test_an_older_database_is_migrated_keeping_its_labels_edits_and_references(tmp_path, dataset, version):
    session = open_session("old", tmp_path)
    session.path.mkdir()
    connection = sqlite3.connect(session.db_path, isolation_level=None)
    script = _SCHEMA_V1 + (";" + _SCHEMA_V2 if version == 2 else "")
    connection.executescript(script + f";PRAGMA user_version = {version};")
    connection.execute("INSERT INTO meta VALUES ('created', 'then')")
    connection.close()
    # A reader of the old file sees its labels, reviewed, and no pre-labels.
    reader = SessionDB(session, dataset, readonly=True)
    assert all(lab.reviewed for lab in reader.labels(0)) and reader.unreviewed_labels() == []
    db = SessionDB(session, dataset)
    label = db.labels(0)[0]
    db.update_label(label.id, "ann", class_name="box")
    # An edit logged before the migration (no origin, no reviewed) still undoes.
    connection = sqlite3.connect(session.db_path, isolation_level=None)
    assert connection.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    (changes,) = connection.execute("SELECT changes FROM edits").fetchone()
    old = json.loads(changes)
    for change in old:
        for side in ("before", "after"):
            change[side].pop("origin"), change[side].pop("reviewed")
    connection.execute("UPDATE edits SET changes = ?", (json.dumps(old),))
    assert connection.execute("PRAGMA foreign_key_check").fetchall() == []
    connection.close()
    db.undo("ann")
    assert db.label(label.id).class_name == label.class_name
    prelabel_frame(db, 0, _detections(FAR[:1], [0.9]), "ann")
    assert len(db.unreviewed_labels()) == 1
