"""Labelling and reviewing as two people do it, in-process: the browser tests only check that the
clicks reach these actions."""

from __future__ import annotations

import numpy as np
import pytest

from app.browser_session import FAILED, BrowserSession
from app.state import AppState
from factorydet_core.evaluation.diagnostics import review_item_markdown
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.session.world import WorldFrames
from tests.fakes import mined_item, queue_run


@pytest.fixture
def state(small_dataset_dir, tiny_model_path, tmp_path):
    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("people", tmp_path), dataset)
    items = [
        mined_item(
            i % 2, i, [2.0 * i, 1.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9 - 0.05 * i, ["box", "barrel"][i % 2]
        )
        for i in range(6)
    ]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    return AppState(dataset, db=db)


def _person(state: AppState, name: str) -> BrowserSession:
    person = BrowserSession(state, drawn_result=lambda: (None, state.frame_index))
    person.author = name
    return person


def test_review_walks_the_pending_queue_and_the_verdict_is_stored(state):
    alice = _person(state, "alice")
    alice.verdict("background")  # nothing shown yet: show the first item, judge nothing
    first = alice.current_item()
    assert first is not None and first["verdict"] is None
    assert state.frame_index == first["frame_index"]
    alice.verdict("background")
    assert state.db.review_queue()[0]["verdict"] == "background"
    second = alice.current_item()
    assert second is not None and second["id"] != first["id"] and second["verdict"] is None
    alice.verdict("object", class_name="cone", advance=False)
    stored = {q["id"]: q for q in state.db.review_queue()}[second["id"]]
    assert stored["verdict"] == "object" and alice.current_item()["id"] == second["id"]
    alice.step(+1)
    assert alice.current_item()["verdict"] is None  # pending only, by default


def test_filters_and_a_batch_verdict_are_one_undoable_edit(state):
    alice = _person(state, "alice")
    alice.filter_class = "barrel"
    queue = alice.load_queue()
    assert queue and {q["predicted_class"] for q in queue} == {"barrel"}
    assert alice.batch_verdict("background") == len(queue)
    verdicts = {q["id"]: q["verdict"] for q in state.db.review_queue()}
    assert all(verdicts[q["id"]] == "background" for q in queue)
    assert sum(v is None for v in verdicts.values()) == 6 - len(queue)
    alice.undo()
    assert all(q["verdict"] is None for q in state.db.review_queue())
    assert alice.messages[-1][0] == "Undone"
    assert alice.batch_verdict("background") == len(queue)
    alice.filter_class = "cone"  # nothing pending there
    assert alice.batch_verdict("background") == 0 and alice.messages[-1][0] == "Batch"


def test_someone_elses_change_in_between_is_refused_not_overwritten(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box")], "importer")[0]
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.select_label(label.id)
    bob.select_label(label.id)
    bob.set_class("cone")
    assert state.db.label(label.id).class_name == "cone"
    assert alice._edit_selected(
        "Set class",
        lambda i, v: state.db.update_label(i, alice.author, expected_version=v, class_name="barrel"),
    ) is FAILED  # fmt: skip
    title, _, error = alice.messages[-1]
    assert error and "someone else got there first" in title
    assert state.db.label(label.id).class_name == "cone"
    # Alice now sees Bob's version: her next edit goes through.
    alice.set_class("barrel")
    assert state.db.label(label.id).class_name == "barrel"


def test_undo_is_per_person_and_nothing_to_undo_says_so(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box")], "importer")[0]
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.select_label(label.id)
    alice.apply_box((1.5, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0))
    bob.undo()
    assert bob.messages[-1] == ("Undo", "Nothing to undo.", False)
    assert state.db.label(label.id).box[0] == pytest.approx(1.5)
    alice.undo()
    assert state.db.label(label.id).box[0] == pytest.approx(1.0)
    alice.undo(redo=True)
    assert state.db.label(label.id).box[0] == pytest.approx(1.5)
    alice.delete_selected()
    assert state.db.label(label.id).deleted and alice.selected_label() is None


def test_edits_need_a_selection_and_a_session(state):
    alice = _person(state, "alice")
    alice.set_class("box")
    assert alice.messages[-1] == ("Set class", "Select a label first (click its box).", False)
    alice.label_segment("box")
    assert alice.messages[-1][0] == "Label segment"
    alice.next_suspect()
    assert alice.messages[-1][0] == "Suspect labels"


def test_an_edit_after_a_was_deleted_conflict_is_still_versioned(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box")], "importer")[0]
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.select_label(label.id)
    bob.select_label(label.id)
    bob.delete_selected()
    alice.set_class("cone")
    assert alice.messages[-1][2] and "someone else got there first" in alice.messages[-1][0]
    # Bob restores it and moves it: Alice, who last saw it deleted, is refused, not obeyed.
    bob.undo()
    bob.select_label(label.id)
    bob.apply_box((5.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0))
    alice.set_class("cone")
    assert "someone else got there first" in alice.messages[-1][0]
    assert state.db.label(label.id).class_name == "box" and state.db.label(label.id).box[0] == 5.0
    alice.set_class("cone")  # she now sees Bob's version
    assert state.db.label(label.id).class_name == "cone" and state.db.label(label.id).box[0] == 5.0


def test_a_verdict_on_an_item_changed_since_it_was_shown_is_refused(state):
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.step(0)
    shown = alice.current_item()
    bob.step(0)
    bob.verdict("object", class_name="box", advance=False)
    bob.undo()  # unreviewed again, as Alice sees it, yet changed twice since
    alice.verdict("background")
    assert "someone else got there first" in alice.messages[-1][0]
    assert {q["id"]: q["verdict"] for q in state.db.review_queue()}[shown["id"]] is None
    alice.verdict("background")  # reloaded: now it goes through
    assert {q["id"]: q["verdict"] for q in state.db.review_queue()}[shown["id"]] == "background"


def test_an_undo_does_not_take_in_someone_elses_change_to_the_selected_label(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box")], "importer")[0]
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.select_label(label.id)
    alice.step(0)
    alice.verdict("background", advance=False)  # an edit that is not of the selected label
    bob.select_label(label.id)
    bob.set_class("cone")
    alice.undo()  # undoes her verdict; Bob's change of her selected label stays unseen by her
    assert alice.messages[-1][0] == "Undone"
    alice.set_class("barrel")
    assert "someone else got there first" in alice.messages[-1][0]
    assert state.db.label(label.id).class_name == "cone"
    # Her own edit of the label and its undo: followed, so her next edit goes through.
    alice.set_class("barrel")  # she has seen Bob's version since the refusal
    alice.undo()
    assert state.db.label(label.id).class_name == "cone"
    alice.set_class("pallet")
    assert state.db.label(label.id).class_name == "pallet" and not alice.messages[-1][2]


def test_a_refused_undo_does_not_take_in_someone_elses_change_either(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box")], "importer")[0]
    alice, bob = _person(state, "alice"), _person(state, "bob")
    alice.select_label(label.id)
    alice.step(0)
    item = alice.current_item()
    alice.verdict("background", advance=False)
    state.db.review([item["id"]], "skip", "bob", override=True)  # what her undo would restore
    bob.select_label(label.id)
    bob.set_class("cone")
    alice.undo()
    assert "someone else got there first" in alice.messages[-1][0]
    alice.set_class("barrel")  # the refused undo was about the verdict, not about this label
    assert "someone else got there first" in alice.messages[-1][0]
    assert state.db.label(label.id).class_name == "cone"


def test_the_chosen_class_follows_the_selected_label_and_the_shown_item(state):
    label = state.db.add_labels([(0, (1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0), "cone")], "importer")[0]
    alice = _person(state, "alice")
    shown = []
    alice._object_class_shown = shown.append  # what the dropdowns would show
    assert alice.object_class == state.dataset.class_names[0]
    alice.select_label(label.id)
    assert alice.object_class == "cone" and shown[-1] == "cone"
    alice.set_class(alice.object_class)  # C without picking another class: no silent relabel
    assert state.db.label(label.id).class_name == "cone"
    alice.step(+1)  # the review queue's first item, a box predicted as such
    item = alice.current_item()
    assert alice.object_class == item["predicted_class"] == shown[-1]
    # A suspect label: the class the model says it is, ready for Set class [C].
    suspect = {
        "label_id": label.id,
        "frame_index": 0,
        "box": list(label.box),
        "class_name": "cone",
        "label_probability": 0.01,
        "predicted_class": "pallet",
        "predicted_probability": 0.9,
    }
    state.set_suspects([suspect])
    alice.next_suspect()
    assert alice.selected_label_id == label.id and alice.object_class == "pallet"
    # Background is no class to label with: the label's own class stays chosen.
    state.set_suspects([{**suspect, "predicted_class": "background"}])
    alice.next_suspect()
    assert alice.object_class == "cone"


def _cube(centre, num: int = 60):
    rng = np.random.default_rng(3)
    return (np.asarray(centre) + rng.uniform(-0.25, 0.25, (num, 3))).astype(np.float32)


def _placed_world(state: AppState, seen_in: tuple[int, ...]):
    """The small data set's three frames placed 2 m apart along x; a cube stands at world
    (10, 1, 0.5), seen only in ``seen_in``."""
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 2.0, 4.0]
    clouds = tuple(
        _cube((10.0 - 2.0 * f, 1.0, 0.5)) if f in seen_in else np.zeros((0, 3), np.float32) for f in range(3)
    )
    state.set_world(WorldFrames(poses, np.ones(3), clouds), "3 frames placed")


def test_label_once_labels_moves_and_deletes_an_object_in_every_frame_that_shows_it(state):
    person = _person(state, "ann")
    points = _cube((10.0, 1.0, 0.5))
    person.drawn_result = lambda: (None, 0)
    person.selected_points = lambda: points
    person.selected_frame = 0
    # Not placed yet: the label stays in its frame.
    person.label_segment("barrel")
    assert [lab.frame_index for lab in state.db.object_labels(person.selected_label_id)] == [0]
    state.db.undo("ann")
    _placed_world(state, seen_in=(0, 2))
    person.label_segment("barrel")
    members = state.db.object_labels(person.selected_label_id)
    assert [lab.frame_index for lab in members] == [0, 2]  # frame 1 does not show it
    np.testing.assert_allclose(members[1].box[0], members[0].box[0] - 4.0)
    # Moving it in frame 0 moves it in frame 2, one edit; the class follows everywhere.
    moved = (10.5, 1.0, 0.5, 0.6, 0.6, 0.6, 0.0)
    person.apply_box(moved)
    person.set_class("cone")
    members = state.db.object_labels(person.selected_label_id)
    assert [lab.box[0] for lab in members] == pytest.approx([10.5, 6.5])
    assert {lab.class_name for lab in members} == {"cone"}
    person.undo()
    person.undo()
    assert {lab.class_name for lab in state.db.object_labels(person.selected_label_id)} == {"barrel"}
    # Flipping to frame 2 selects the same object there; frame 1 has no label of it: it stays.
    state.set_frame(1)
    person.follow_object()
    assert person.selected_label().frame_index == 0
    state.set_frame(2)
    person.follow_object()
    assert (
        person.selected_label().frame_index == 2
        and person.selected_label().instance_id == members[0].instance_id
    )
    state.set_frame(0)
    person.follow_object()
    # Off: this frame only.
    person.label_once = False
    person.set_class("box")
    assert [lab.class_name for lab in state.db.object_labels(person.selected_label_id)] == ["box", "barrel"]
    person.label_once = True
    person.delete_selected()
    assert not any(lab.class_name in ("box", "barrel") and lab.box[0] > 5 for lab in state.db.labels(0))
    assert all(lab.instance_id != members[0].instance_id for f in (0, 2) for lab in state.db.labels(f))


def test_a_person_or_truck_moves_so_its_box_changes_in_its_frame_only(state):
    person = _person(state, "ann")
    _placed_world(state, seen_in=(0, 1, 2))
    person.drawn_result = lambda: (None, 0)
    person.selected_points = lambda: _cube((10.0, 1.0, 0.5))
    person.selected_frame = 0
    person.label_segment("person")
    assert len(state.db.object_labels(person.selected_label_id)) == 1


def test_label_every_frame_waits_for_the_placement_then_is_one_undoable_edit(state):
    person = _person(state, "ann")
    person.spread_labels()
    assert "not placed" in person.messages[-1][1]
    labelled = [lab for lab in state.db.labels(0) if lab.instance_id is not None]
    poses = np.stack([np.eye(4)] * 3)
    clouds = tuple(
        np.concatenate([_cube(lab.box[:3], num=10) for lab in labelled]).astype(np.float32) for _ in range(3)
    )
    state.set_world(WorldFrames(poses, np.ones(3), clouds), "3 frames placed")
    before = {f: len(state.db.labels(f)) for f in range(3)}
    person.spread_labels()
    assert "label(s) added" in person.messages[-1][1]
    assert sum(len(state.db.labels(f)) for f in range(3)) > sum(before.values())
    person.undo()
    assert {f: len(state.db.labels(f)) for f in range(3)} == before
    person.spread_labels()
    person.spread_labels()
    assert "already" in person.messages[-1][1]


def test_nudges_move_the_selected_box_along_its_heading_in_centimetres(state):
    person = _person(state, "ann")
    person.label_once = False
    label = state.db.add_label(0, (1.0, 2.0, 0.5, 1.0, 0.5, 0.8, np.pi / 2), "box", "ann")
    person.select_label(label.id)
    person.nudge(forward=0.01)  # heading +y
    person.nudge(left=0.01)  # its left is -x
    person.nudge(up=-0.01, yaw_deg=1.0)
    box = np.array(state.db.label(label.id).box)
    np.testing.assert_allclose(box[:3], [0.99, 2.01, 0.49], atol=1e-9)
    assert box[6] == pytest.approx(np.pi / 2 + np.radians(1.0))
    assert len([e for e in state.db.edits("ann") if e.kind == "update"]) == 3
    person.nudge(taller=0.01)  # alt+Y: its bottom stays on the floor
    person.nudge(longer=-0.01)  # alt+K
    box = np.array(state.db.label(label.id).box)
    np.testing.assert_allclose(box[2:6], [0.495, 0.99, 0.5, 0.81], atol=1e-9)
    person.clear_selection()
    person.nudge(forward=0.01)
    assert "Select a label first" in person.messages[-1][1]


def test_an_accepted_suggestion_is_a_label_of_the_chosen_class_in_every_frame_that_shows_it(state):
    from factorydet_core.session.editing import Suggestion

    person = _person(state, "ann")
    person.accept_suggestion()
    assert "Click an object first" in person.messages[-1][1]
    _placed_world(state, seen_in=(0, 1))
    suggestion = Suggestion(
        box=(10.0, 1.0, 0.5, 0.6, 0.6, 0.6, 0.0), class_name="cone", score=0.4, num_patches=2
    )
    person.suggest(0, suggestion)
    assert person.object_class == "cone"  # the suggestion's class is the chosen one
    person.set_object_class("barrel")  # a person may correct it before accepting
    person.accept_suggestion()
    label = person.selected_label()
    assert label.class_name == "barrel" and label.frame_index == 0 and label.box == suggestion.box
    assert [lab.frame_index for lab in state.db.object_labels(label.id)] == [0, 1]
    assert person.suggestion is None  # selecting the new label clears it


@pytest.mark.parametrize("fmt", ["json", "kitti", "npz"])
def test_labels_export_for_a_download_as_the_command_line_writes_them(state, fmt):
    import io
    import json
    import zipfile

    person = _person(state, "ann")
    name, content = person.export_labels(fmt)
    if fmt == "json":
        record = json.loads(content)
        assert name == "people_labels.json" and len(record["frames"]) == state.dataset.num_frames
    else:
        files = zipfile.ZipFile(io.BytesIO(content)).namelist()
        assert name == f"people_labels_{fmt}.zip" and len(files) == state.dataset.num_frames
    assert person.export_labels("las") is None and "unknown label format" in person.messages[-1][1]


def test_escape_clears_the_description_of_the_last_thing_clicked(state):
    person = _person(state, "ann")
    state.set_selection("**Patch 10**: 25 points")
    person.clear_selection()
    assert state.selection_markdown == "" and person.suggestion is None


def test_box_views_move_this_browsers_camera_onto_the_selected_box(state):
    person = _person(state, "ann")
    cameras = []
    person.set_camera = lambda position, look_at, up: cameras.append((position, look_at, up))
    person.view_selected("top")
    assert not cameras and "Select a label first" in person.messages[-1][1]
    label = state.db.add_label(0, (1.0, 2.0, 0.5, 1.0, 0.5, 0.8, 0.0), "box", "ann")
    person.select_label(label.id)
    person.view_selected("front")
    np.testing.assert_allclose(cameras[-1][1], [1.0, 2.0, 0.5])
    assert cameras[-1][0][0] > 1.0  # in front of it, along its heading (+x)


def test_an_object_verdict_labels_the_object_in_every_frame_and_a_later_verdict_takes_it_back(state):
    person = _person(state, "ann")
    person.step(0)
    item = person.current_item()
    centre = item["box"][:3]
    # Every frame sees the item's object at the same place.
    state.set_world(
        WorldFrames(np.stack([np.eye(4)] * 3), np.ones(3), tuple(_cube(centre, num=30) for _ in range(3))),
        "3 frames placed",
    )
    person.verdict("object", "box", advance=False)
    label_id = next(q for q in state.db.review_queue() if q["id"] == item["id"])["label_id"]
    members = state.db.object_labels(label_id)
    assert sorted(lab.frame_index for lab in members) == [0, 1, 2]
    assert {lab.origin for lab in members} == {"review"} and {lab.class_name for lab in members} == {"box"}
    person.verdict("background", advance=False)
    assert all(state.db.label(lab.id).deleted for lab in members)
    person.undo()  # the background verdict: the object is back in every frame
    assert not any(state.db.label(lab.id).deleted for lab in members)
    person.undo()  # the object verdict: gone everywhere
    assert all(state.db.label(lab.id).deleted for lab in members)


def _detected(state: AppState, boxes, scores) -> None:
    """The shown frame's detections are in (only their candidates matter to pre-labelling)."""
    from types import SimpleNamespace

    from tests.core.session.test_prelabels import _detections

    with state.lock:
        state.detection_result = SimpleNamespace(candidates=_detections(boxes, scores))
        state.detection_frame_index = state.frame_index


def test_pre_labels_are_added_walked_confirmed_and_fixed_from_the_queue(state):
    from tests.core.session.test_prelabels import FAR

    ann = _person(state, "ann")
    ann.prelabel_frame(0.5)
    assert "not computed yet" in ann.messages[-1][1]
    _detected(state, FAR[:3], [0.9, 0.7, 0.3])
    ann.prelabel_frame(0.5)
    waiting = state.db.unreviewed_labels()
    assert len(waiting) == 2 and ann.selected_label_id == waiting[0].id  # the best first
    ann.confirm_selected()  # right as it is: confirmed, and the next one selected
    assert ann.selected_label_id == waiting[1].id
    assert [lab.id for lab in state.db.unreviewed_labels()] == [waiting[1].id]
    ann.set_class("person")  # a fix confirms it too
    assert state.db.unreviewed_labels() == []
    ann.confirm_selected()
    assert "Select a pre-label first" in ann.messages[-1][1]
    ann.next_prelabel()
    assert "None waits" in ann.messages[-1][1]
    # Lower: the third one only (the others are labelled there now), then all of the frame at once.
    ann.prelabel_frame(0.2)
    assert [lab.score for lab in state.db.unreviewed_labels()] == [pytest.approx(0.3)]
    ann.confirm_frame()
    assert state.db.unreviewed_labels() == []
    assert state.references(0)[2].shape == (0, 7)  # nothing ignored any more: all truth
    ann.undo()
    assert len(state.references(0)[2]) == 1  # the unconfirmed one is neither truth nor a miss
    boxes, _, prelabel_mask = state.drawn_labels(0)
    assert prelabel_mask.sum() == 1 and len(boxes) == len(prelabel_mask)


def test_next_pre_label_moves_to_its_frame(state):
    from tests.core.session.test_prelabels import FAR

    _detected(state, FAR[:1], [0.9])
    ann = _person(state, "ann")
    ann.prelabel_frame(0.5)
    ann.clear_selection()
    state.set_frame(1)
    ann.next_prelabel()  # none from frame 1 on: round to the first
    assert state.frame_index == 0 and ann.selected_label().score == pytest.approx(0.9)


def test_a_keyframe_in_another_frame_computes_the_boxes_between(state):
    person = _person(state, "ann")
    person.keyframe_here()
    assert "Select a person or truck" in person.messages[-1][1]
    person.drawn_result = lambda: (None, 0)
    person.selected_points = lambda: _cube((10.0, 1.0, 0.5))
    person.selected_frame = 0
    person.label_segment("person")
    first = person.selected_label()
    state.set_frame(2)
    person.keyframe_here()
    assert "not placed" in person.messages[-1][1]
    _placed_world(state, seen_in=(0, 1, 2))
    person.keyframe_here()
    end = person.selected_label()
    assert end.frame_index == 2 and end.instance_id == state.db.label(first.id).instance_id
    # Carried by the poses (frame 2 is 4 m further along x); then moved 1 m onto the person.
    assert end.box[0] == pytest.approx(first.box[0] - 4.0)
    person.apply_box((end.box[0] + 1.0, *end.box[1:]))
    middle = [lab for lab in state.db.object_labels(first.id) if lab.frame_index == 1]
    assert len(middle) == 1 and middle[0].origin == "interpolated"
    # Half way in the world: frame 1 sits 2 m along x, so 0.5 m past the start carried there.
    assert middle[0].box[0] == pytest.approx(first.box[0] - 2.0 + 0.5)
    person.keyframe_here()
    assert "labelled in this frame already" in person.messages[-1][1]
    person.undo()
    person.undo()
    assert [lab.frame_index for lab in state.db.object_labels(first.id)] == [0]
    state.set_frame(0)
    person.select_label(first.id)
    person.set_class("box")
    state.set_frame(1)
    person.keyframe_here()
    assert "stands still" in person.messages[-1][1]


def test_one_queue_entry_per_place_and_its_verdict_answers_every_item(state, tiny_model_path):
    person = _person(state, "ann")
    before = len(person.load_queue())
    # One object at world (10, 1, 0.5) mined in each of the three frames (placed 2 m apart).
    items = [
        mined_item(f, 50 + f, [10.0 - 2.0 * f, 1.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.95 - 0.01 * f)
        for f in range(3)
    ]
    state.db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    person.group_places = False
    assert len(person.load_queue()) == 3  # the new run's queue, item by item
    person.group_places = True
    assert len(person.load_queue()) == 3  # not placed yet: nothing to group by
    _placed_world(state, seen_in=(0, 1, 2))
    queue = person.load_queue()
    assert len(queue) == 1 and queue[0]["place_frames"] == [0, 1, 2]
    person.step(0)
    person.verdict("object", "cone")
    verdicts = [q["verdict"] for q in state.db.review_queue()]
    assert verdicts == ["object"] * 3
    cones = [lab for f in range(3) for lab in state.db.labels(f) if lab.origin == "review"]
    assert len(cones) == 3 and len({lab.instance_id for lab in cones}) == 1
    assert {lab.class_name for lab in cones} == {"cone"} and before == 6


def test_after_confirming_the_last_pre_label_the_selection_can_still_be_edited(state):
    from tests.core.session.test_prelabels import FAR

    _detected(state, FAR[:1], [0.9])
    ann = _person(state, "ann")
    ann.prelabel_frame(0.5)
    (waiting,) = state.db.unreviewed_labels()
    ann.confirm_selected()  # the last one: the selection stays on it
    assert ann.selected_label_id == waiting.id
    ann.nudge(forward=0.01)  # made against the confirmed version: no conflict
    assert not any(error for _, _, error in ann.messages)
    assert state.db.label(waiting.id).box[0] != waiting.box[0]


def test_the_queue_is_read_again_only_after_a_write_or_another_filter(state, monkeypatch):
    person = _person(state, "ann")
    reads = []
    original = state.db.review_queue
    monkeypatch.setattr(state.db, "review_queue", lambda **kw: reads.append(kw) or original(**kw))
    first = person.load_queue()
    assert person.load_queue() == first and len(reads) == 1  # the refreshes of one change: one read
    person.step(0)
    person.verdict("background")  # a write: read once more, whatever the refreshes after it
    person.load_queue()
    assert len(reads) == 2 and first[0]["id"] not in [q["id"] for q in person.queue]  # judged: not pending
    person.filter_class = "box"
    person.load_queue()
    assert len(reads) == 3 and reads[-1]["predicted_class"] == "box"
    # A write by another process (the command line) is seen too.
    state.db.add_label(0, [30.0, 30.0, 0.5, 1, 1, 1, 0], "box", "cli")
    person.load_queue()
    assert len(reads) == 4


def test_a_class_order_queue_by_place_visits_every_place_once_in_its_turn(state, tiny_model_path):
    _placed_world(state, seen_in=(0, 1, 2))
    # Three classes, three places each, every place mined once in frame 0, far apart.
    scores = {"box": (0.9, 0.8, 0.7), "cone": (0.5, 0.4, 0.3), "pallet": (0.2, 0.15, 0.1)}
    items = [
        mined_item(0, 60 + 3 * c + k, [40.0 + 3.0 * (3 * c + k), 5.0, 0.5, 0.6, 0.6, 0.6, 0.0], s, name)
        for c, (name, values) in enumerate(scores.items())
        for k, s in enumerate(values)
    ]
    state.db.save_training_run(
        queue_run(tiny_model_path, [items]), "small", {"settings": {"queue_order": "class"}}
    )
    person = _person(state, "ann")
    expected = [(q["predicted_class"], q["score"]) for q in person.load_queue()]
    assert expected == [
        ("box", 0.9), ("cone", 0.5), ("pallet", 0.2), ("box", 0.8), ("cone", 0.4), ("pallet", 0.15),
        ("box", 0.7), ("cone", 0.3), ("pallet", 0.1),
    ]  # fmt: skip
    # Each verdict moves on to the next place of the whole queue's order: none is passed over,
    # although the classes' turns, worked out again on what is left, would differ.
    visited = []
    person.step(0)
    while person.current_item() is not None:
        shown = person.current_item()
        visited.append((shown["predicted_class"], shown["score"]))
        person.verdict("background")
    assert visited == expected


def test_a_learned_order_queue_with_nothing_to_learn_from_yet_keeps_the_cuts_order_and_says_so(
    state, tiny_model_path
):
    _placed_world(state, seen_in=(0, 1, 2))
    scores = {"box": (0.9, 0.8), "cone": (0.5, 0.4)}
    items = [
        mined_item(0, 60 + 2 * c + k, [40.0 + 3.0 * (2 * c + k), 5.0, 0.5, 0.6, 0.6, 0.6, 0.0], s, name)
        for c, (name, values) in enumerate(scores.items())
        for k, s in enumerate(values)
    ]
    settings = {"queue_order": "class", "review_order": "learned"}  # today's default review order
    state.db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": settings})
    person = _person(state, "ann")
    queue = person.load_queue()
    assert [(q["predicted_class"], q["score"]) for q in queue] == [
        ("box", 0.9), ("cone", 0.5), ("box", 0.8), ("cone", 0.4)
    ]  # fmt: skip
    assert all(q["place_useful"] is None and q["learned_from"] == 0 for q in queue)
    assert "Learned order: the queue order until 20 places" in review_item_markdown(queue[0], [], 1, 4)
    # A skipped place goes last even before the order has anything to learn from.
    person.step(0)
    person.verdict("skip")
    assert [q["score"] for q in person.load_queue()] == [0.5, 0.8, 0.4, 0.9]


def test_a_verdict_orders_the_places_once_though_the_panel_reads_the_queue_again(
    state, tiny_model_path, monkeypatch
):
    from factorydet_core.session.review_rank import LearnedOrder

    _placed_world(state, seen_in=(0, 1, 2))
    items = [
        mined_item(0, 60 + k, [40.0 + 3.0 * k, 5.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.9 - 0.1 * k, "box")
        for k in range(4)
    ]
    settings = {"queue_order": "class", "review_order": "learned"}
    state.db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": settings})
    person = _person(state, "ann")
    ranked = []
    original = LearnedOrder.ranked
    monkeypatch.setattr(LearnedOrder, "ranked", lambda self, *a: ranked.append(1) or original(self, *a))
    person.step(0)
    assert len(ranked) == 1
    person.verdict("background")  # a write: the queue read and ordered again, once
    assert len(ranked) == 2
    shown = person.current_item()
    # The panel reads the queue again with the next item shown: the same order, not worked out again.
    assert [q["id"] for q in person.load_queue()] == [q["id"] for q in person.queue]
    assert len(ranked) == 2 and shown["score"] == 0.8
    person.hide_labelled = True  # another filter of the same read: filtered, not ordered again
    person.load_queue()
    assert len(ranked) == 2


def test_a_learned_order_queue_shows_the_next_likeliest_place_and_a_skipped_one_again_last(
    state, tiny_model_path
):
    cubes = [(10.0 + 3.0 * k, 1.0, 0.5) for k in range(6)]
    clouds = (
        np.concatenate([_cube(c) for c in cubes]),
        _cube((60.0, 1.0, 0.5)),
        np.zeros((0, 3), np.float32),
    )
    state.set_world(WorldFrames(np.stack([np.eye(4)] * 3), np.ones(3), clouds), "3 frames placed")
    # An answered run: its places on the cubes gave labels, those on no points did not.
    on = [mined_item(0, 70 + k, [*c, 0.6, 0.6, 0.6, 0.0], 0.3) for k, c in enumerate(cubes)]
    off = [mined_item(0, 80 + k, [10.0 + 3.0 * k, 20.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.3) for k in range(20)]
    answered = state.db.save_training_run(queue_run(tiny_model_path, [on + off]), "small", {})
    queue = state.db.review_queue(answered)
    state.db.review([q["id"] for q in queue if q["box"][1] < 10.0], "wrong_box", "ann")
    state.db.review([q["id"] for q in queue if q["box"][1] > 10.0], "background", "ann")
    # A learned run: its places on no points score higher; the cube's points put its place first.
    items = [mined_item(1, 200, [60.0, 1.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.2)] + [
        mined_item(1, 201 + k, [30.0 + 3.0 * k, 9.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.9 - 0.1 * k)
        for k in range(3)
    ]
    settings = {"queue_order": "score", "review_order": "learned"}
    state.db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": settings})
    person = _person(state, "ann")
    queue = person.load_queue()
    assert [q["score"] for q in queue] == [0.2, 0.9, 0.8, 0.7]
    # What the panel says of each place: its learned chance, the first the highest.
    chances = [q["place_useful"] for q in queue]
    assert chances[0] > max(chances[1:]) and all(q["learned_from"] == 26 for q in queue)
    visited = []
    person.step(0)
    verdicts = iter(["skip", "skip", "background", "background", "background", "background", "background"])
    while person.current_item() is not None and len(visited) < 7:
        visited.append(person.current_item()["score"])
        person.verdict(next(verdicts))
    # Every place once, the unreviewed ones before any skipped one, then the skipped ones again.
    assert visited == [0.2, 0.9, 0.8, 0.7, 0.9, 0.2]


def test_a_sparse_item_is_looked_at_where_the_frames_see_it_best(state, tiny_model_path):
    person = _person(state, "ann")
    # One object at world (10, 1, 0.5), mined in frame 0 where it shows 5 points; frame 2 shows 60.
    item = mined_item(0, 70, [10.0, 1.0, 0.5, 0.6, 0.6, 0.6, 0.0], 0.99)
    state.db.save_training_run(queue_run(tiny_model_path, [[item]]), "small", {})
    person.step(0)
    shown = person.current_item()
    assert person.best_view(shown) is None  # not placed yet
    person.look_where_seen_best()
    assert "not placed yet" in person.messages[-1][1] and state.frame_index == 0
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 2.0, 4.0]
    clouds = (_cube((10.0, 1.0, 0.5), num=5), np.zeros((0, 3), np.float32), _cube((6.0, 1.0, 0.5)))
    state.set_world(WorldFrames(poses, np.ones(3), clouds), "3 frames placed")
    view = person.best_view(shown)
    assert (view.frame_index, view.num_points, view.num_points_here) == (2, 60, 5)
    # A person or truck moves: the frames' poses carry its box to where it no longer is.
    assert person.best_view({**shown, "id": -1, "predicted_class": "person"}) is None
    assert "Seen best in frame 3: 60 points in its box there against 5 here" in review_item_markdown(
        shown, [], 1, 1, best_view=view
    )
    person.look_where_seen_best()
    assert state.frame_index == 2 and person.current_item()["id"] == shown["id"]  # still the item judged
    assert person.messages[-1][0] == "Seen best"
    person.verdict("object", "box")
    boxes = {
        lab.frame_index: lab.box for f in range(3) for lab in state.db.labels(f) if lab.origin == "review"
    }
    assert set(boxes) == {0, 2} and boxes[2][0] == pytest.approx(6.0)  # labelled once, where it shows
