"""The labelling loop: training from a session's labels and verdicts, the proposal cache, the
before/after comparison, and the simulated reviewer."""

import dataclasses

import numpy as np
import pytest

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.hitl import (
    add_truth_labels,
    pseudo_label_truth,
    queue_reach,
    simulated_review,
    truth_verdict,
    unannotated_coverage,
)
from factorydet_core.evaluation.measure import (
    compare_models,
    comparison_markdown,
    lost_classes,
    unlearned_classes,
    unlearned_text,
)
from factorydet_core.io.dataset import annotation_min_points, open_dataset
from factorydet_core.session.store import SessionDB, open_session
from factorydet_core.sim.truth import read_frame_truth
from factorydet_core.training.loop import (
    cached_proposals,
    new_classifier,
    proposals_cache_key,
    session_pseudo_labels,
    session_references,
    suspect_labels,
    train_session,
    with_session_labels,
)
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import Cancelled, InputError
from tests.fakes import mined_item, queue_run

# Two epochs make a classifier whose probabilities times a predicted IoU rarely reach mining's
# floor, so the plumbing tests of the loop train without the box quality regressor.
SETTINGS = LoopSettings(
    epochs=2,
    round_epochs=1,
    rounds=1,
    negatives_per_round=30,
    initial_negatives=120,
    score_threshold=0.05,
    box_quality=False,
    method="paper",
)


@pytest.fixture(scope="module")
def dataset(small_dataset_dir):
    return open_dataset(small_dataset_dir)


@pytest.fixture(scope="module")
def detector():
    return Detector("agv")


@pytest.fixture(scope="module")
def db(tmp_path_factory, dataset):
    return SessionDB(open_session("loop", tmp_path_factory.mktemp("sessions")), dataset)


@pytest.fixture(scope="module")
def frames(db, dataset, detector):
    return cached_proposals(db, dataset, detector, [0, 1])


def test_the_rig_is_calibrated_once_per_session_and_read_back_after(dataset, tmp_path, monkeypatch):
    from factorydet_core.proposals.merge import ExtrinsicRefinement
    from factorydet_core.training.loop import cached_calibration

    calls = []
    num_sensors = dataset.num_sensors

    def refine(frames, T_vehicle_sensor=None, **options):
        calls.append(T_vehicle_sensor)
        T = np.tile(np.eye(4), (num_sensors, 1, 1))
        T[:, 0, 3] = 0.01 * (len(calls) + np.arange(num_sensors))  # (a new answer each call)
        zeros = np.zeros(num_sensors)
        return ExtrinsicRefinement(T, zeros + 0.02, zeros + 0.01, zeros + 0.9)

    monkeypatch.setattr("factorydet_core.detection.detector.refine_extrinsics", refine)
    db = SessionDB(open_session("calibration", tmp_path), dataset)
    first = cached_calibration(db, dataset, Detector("agv"), 0)
    again = cached_calibration(db, dataset, Detector("agv"), 0)
    assert len(calls) == 1  # read back: ICP ran once
    np.testing.assert_array_equal(again.T_vehicle_sensor, first.T_vehicle_sensor)
    np.testing.assert_array_equal(again.calibration_.rmse_after, first.calibration_.rmse_after)
    # Another frame, or other starting extrinsics, is another calibration.
    cached_calibration(db, dataset, Detector("agv"), 1)
    cached_calibration(db, dataset, Detector("agv", first.T_vehicle_sensor), 0)
    assert len(calls) == 3 and calls[2] is not None


def test_proposals_are_cached_and_read_back_equal(db, dataset, detector, frames, monkeypatch):
    key = proposals_cache_key(dataset, detector)
    assert (db.session.cache_dir / f"{key}.npz").is_file()
    # A second call reads the cache: proposing again would fail.
    monkeypatch.setattr(
        "factorydet_core.training.loop.collect_proposals", lambda *a, **k: pytest.fail("re-proposed")
    )
    again = cached_proposals(db, dataset, detector, [1, 0])
    assert [f.frame_index for f in again] == [1, 0]
    for a, b in zip(frames, again[::-1]):
        assert a.patch_sets == b.patch_sets
        np.testing.assert_array_equal(a.groups.features, b.groups.features)
        np.testing.assert_array_equal(a.annotation_instance_ids, b.annotation_instance_ids)
    # Other front-half settings are another cache entry.
    other = Detector(detector.params.replace(voxel_size_m=0.3))
    assert proposals_cache_key(dataset, other) != key


def test_session_labels_replace_the_annotations(db, frames):
    frame = frames[0]
    labels = db.labels(0)
    db.update_label(labels[0].id, "ann", class_name="truck")
    db.delete_labels([labels[1].id], "ann")
    (relabelled,) = with_session_labels(db, [frame])
    assert len(relabelled.label_boxes) == len(frame.label_boxes) - 1
    truck = db.class_names.index("truck")
    assert relabelled.label_class_ids[0] == truck
    # The deleted instance's own points are no longer a positive; the renamed one's are a truck.
    kept = dict(zip(relabelled.annotation_instance_ids.tolist(), relabelled.annotation_class_ids.tolist()))
    assert labels[1].instance_id not in kept
    if labels[0].instance_id in kept:
        assert kept[labels[0].instance_id] == truck
    db.undo("ann")
    db.undo("ann")
    assert len(with_session_labels(db, [frame])[0].label_boxes) == len(frame.label_boxes)


@pytest.mark.slow
def test_full_run_then_review_then_next_round(db, dataset, frames):
    run_id, run = train_session(db, frames, SETTINGS, mode="full", data_ref="small")
    assert [r["round"] for r in run.rounds] == [0, 1]
    # The mining round goes on from the first fit's network for round_epochs.
    assert [(r["continued"], r["epochs"]) for r in run.rounds] == [(False, 2), (True, 1)]
    assert run.model.probability_exponent == SETTINGS.probability_exponent == 0.5  # the loop's default
    queue = db.review_queue()
    mined_total = sum(len(r["mined"]) for r in run.rounds)
    assert len(queue) == mined_total > 0 and all(item["run_id"] == run_id for item in queue)
    assert db.training_runs()[-1]["kind"] == "full"
    assert db.training_runs()[-1]["snapshot_id"] is not None
    # Every label trains by default; the thresholds' tuning leaves out a person's labels sparser
    # than half the annotation policy, and nobody has labelled anything yet.
    config = db.training_runs()[-1]["config"]
    assert (config["label_points_floor"], config["sparse_labels_ignored"]) == (0, 0)
    policy = dataset.manifest["config"]["min_annotated_points"]
    assert (config["threshold_points_floor"], config["labels_tuning_ignored"]) == (round(policy / 2), 0)
    # A run trained with no front-end note (scripts, the benchmark) still loads.
    stored = DetectionModel.load(db.session.path / db.training_runs()[-1]["model_path"])
    assert stored.front_end is None and stored.class_names == run.model.class_names

    counts = simulated_review(db, dataset, budget=10)
    verdicts = ("background", "object", "wrong_box", "skip")
    assert sum(counts[v] for v in verdicts) == min(10, len(queue))
    # Drawn boxes are truth boxes, and no object ends up labelled twice.
    for index in (0, 1):
        labels, _, _ = db.frame_boxes(index)
        overlap = box_iou_3d(labels, labels)
        np.fill_diagonal(overlap, 0.0)
        assert overlap.max(initial=0.0) < 0.6
        truth_boxes = read_frame_truth(dataset.path, index).instance_boxes
        for lab in db.labels(index):
            if lab.created_by == "simulated-reviewer" and lab.origin == "user":
                assert box_iou_3d(np.array([lab.box]), truth_boxes).max() > 0.999
    progress = db.review_progress(run_id)
    assert progress["reviewed"] == min(10, len(queue)) - counts["skip"]
    # Every verdict agrees with the truth it was read from, except on an object the session
    # labels already: that item is a negative (or, matching the label, nothing to add).
    for item in db.review_queue(run_id):
        if item["verdict"] is None:
            continue
        truth, _, true_box = truth_verdict(dataset, item)
        if item["verdict"] != truth:
            assert truth in ("object", "wrong_box")
            assert item["verdict"] == {"object": "skip", "wrong_box": "background"}[truth]
            labels, _, _ = db.frame_boxes(item["frame_index"])
            assert box_iou_3d(true_box[None], labels).max() >= 0.6

    confirmed = db.reviewed_patch_sets()["background"]
    next_id, next_run = train_session(db, frames, SETTINGS, mode="next", data_ref="small")
    assert next_id == run_id + 1 and len(next_run.rounds) == 1
    # It went on from the latest run's model.
    assert next_run.rounds[0]["continued"] and db.training_runs()[-1]["config"]["continued_run"] == run_id
    # The next fit's background holds every earlier mined negative not reviewed as an object.
    assert next_run.rounds[0]["num_background"] >= SETTINGS.initial_negatives
    new_queue = db.review_queue()
    mined_before = {(i["frame_index"], tuple(i["patch_set"])) for i in queue}
    assert all((i["frame_index"], tuple(i["patch_set"])) not in mined_before for i in new_queue)
    assert all((index, tuple(p)) in mined_before for index, sets in confirmed.items() for p in sets)

    references = session_references(db, [0, 1])
    table = compare_models({"before": run.model, "after": next_run.model}, frames, references)
    assert set(table) == {"before", "after"}
    assert 0 <= table["after"]["f1"] <= 1
    assert "| **total** |" in comparison_markdown(table)


def test_a_cancelled_run_stores_nothing(db, frames):
    runs_before = len(db.training_runs())
    with pytest.raises(Cancelled):
        train_session(db, frames, SETTINGS, mode="next", should_stop=lambda: True)
    assert len(db.training_runs()) == runs_before


def _lone_sparse_box(truth):
    """The box of a real object with under 50 points that no object of 50 or more touches."""
    dense = truth.instance_num_points >= 50
    sparse = np.flatnonzero((truth.instance_class_ids >= 0) & ~dense)
    iou = box_iou_3d(truth.instance_boxes[sparse], truth.instance_boxes[dense])
    return truth.instance_boxes[sparse[iou.max(axis=1, initial=0.0) < 0.1][0]]


def test_truth_verdicts(dataset):
    truth = read_frame_truth(dataset.path, 0)
    real = np.flatnonzero((truth.instance_class_ids >= 0) & (truth.instance_num_points >= 50))[0]
    box = truth.instance_boxes[real]
    item = {"frame_index": 0, "box": box.tolist()}
    verdict, name, _ = truth_verdict(dataset, item)
    assert verdict == "object" and name == dataset.class_names[truth.instance_class_ids[real]]
    shifted = {"frame_index": 0, "box": (box + [box[3] * 0.6, 0, 0, 0, 0, 0, 0]).tolist()}
    assert truth_verdict(dataset, shifted)[0] == "wrong_box"
    far = {"frame_index": 0, "box": [500.0, 500.0, 0.5, 1, 1, 1, 0]}
    assert truth_verdict(dataset, far) == ("background", None, None)
    # An object too sparse for the annotation policy is neither labelled nor background.
    assert annotation_min_points(dataset) == 50
    item = {"frame_index": 0, "box": _lone_sparse_box(truth).tolist()}
    assert truth_verdict(dataset, item) == ("skip", None, None)
    # With a policy that takes every visible object, it is an object.
    assert truth_verdict(dataset, item, min_points=0)[0] == "object"


def test_pseudo_labels_are_judged_by_the_truth(dataset, tmp_path, tiny_model_path):
    truth = read_frame_truth(dataset.path, 0)
    real = np.flatnonzero((truth.instance_class_ids >= 0) & (truth.instance_num_points >= 50))[0]
    box = truth.instance_boxes[real]
    name = dataset.class_names[truth.instance_class_ids[real]]
    other = next(c for c in dataset.class_names if c != name)
    far = [500.0, 500.0, 0.5, 1, 1, 1, 0]

    def judged(session: str, items: list) -> dict:
        db = SessionDB(open_session(session, tmp_path), dataset)
        # Unlabel the object: pseudo-labels are off every label.
        on_it = [lab.id for lab in db.labels(0) if box_iou_3d(np.asarray([lab.box]), box[None])[0, 0] > 0]
        if on_it:
            db.delete_labels(on_it, "ann")
        db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
        counts = pseudo_label_truth(db, dataset, db.pseudo_labels(0.5))
        assert not any(counts["carried"].values())  # each in the frame it was mined in
        return {k: v for k, v in counts["all"].items() if v}

    labels = np.asarray([lab.box for lab in SessionDB(open_session("labels", tmp_path), dataset).labels(0)])
    labels = labels[box_iou_3d(labels, box[None])[:, 0] == 0]
    along = box[3] * 0.4 * np.array([np.cos(box[6]), np.sin(box[6])])  # IoU 0.6 / 1.4 with it
    shifted = next(  # a looser box of the object, off its labelled neighbours
        shift
        for shift in (box + [*(sign * along), 0, 0, 0, 0, 0] for sign in (1, -1))
        if box_iou_3d(shift[None], labels).max(initial=0.0) < 0.25
    )
    first = [
        mined_item(0, 0, box, 0.9, predicted_class=name),
        mined_item(0, 3, far, 0.7),
        mined_item(0, 4, _lone_sparse_box(truth), 0.7),
        mined_item(1, 5, far, 0.3),  # below the pseudo-label score
    ]
    assert judged("a", first) == {"object": 1, "skip": 1, "background": 1}
    assert judged("b", [mined_item(0, 1, box, 0.9, predicted_class=other)]) == {"other_class": 1}
    assert judged("c", [mined_item(0, 2, shifted, 0.8, predicted_class=name)]) == {"loose_box": 1}
    # A looser box of an object already pseudo-labelled is no second label.
    assert judged("d", [*first[:1], mined_item(0, 2, shifted, 0.8, predicted_class=name)]) == {"object": 1}
    # One carried from another frame (no point set of its own) is counted apart as well.
    db = SessionDB(open_session("e", tmp_path), dataset)
    carried = {0: ([()], box[None], np.array([dataset.class_names.index(name)]))}
    assert pseudo_label_truth(db, dataset, carried)["carried"]["object"] == 1


def _cube(centre, half_m: float = 0.3) -> np.ndarray:
    """(64, 3) float32: a 4 x 4 x 4 grid of points filling a cube around ``centre`` (3,)."""
    grid = np.stack(np.meshgrid(*[np.linspace(-half_m, half_m, 4)] * 3), -1).reshape(-1, 3)
    return (grid + centre).astype(np.float32)


def test_pseudo_labels_of_standing_objects_are_carried_to_the_training_frames_that_show_them(
    dataset, tmp_path, tiny_model_path
):
    """``carry_pseudo_labels``: a pseudo-label of a static class labels its object in every
    training frame whose points show it, unless a label or a pseudo-label is on it there; a
    person's stays in its frame."""
    from factorydet_core.session.world import WorldFrames

    standing = np.array([500.0, 500.0, 0.5, 1, 1, 1, 0])
    walking = np.array([520.0, 500.0, 0.9, 0.7, 0.7, 1.8, 0])
    both = np.concatenate([_cube(standing[:3]), _cube(walking[:3])])
    # Frames 0 and 1 see both objects; frame 2 sees the standing one, frame 2 is no training frame.
    world = WorldFrames(np.stack([np.eye(4)] * 3), np.ones(3), (both, both, _cube(standing[:3])))
    db = SessionDB(open_session("carry", tmp_path), dataset)
    items = [
        mined_item(0, 0, standing, 0.9, predicted_class="box"),
        mined_item(0, 1, walking, 0.8, predicted_class="person"),
    ]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})
    settings = LoopSettings(pseudo_label_confident=0.6, carry_pseudo_labels=True)
    labels = session_pseudo_labels(db, settings, [0, 1], world)
    assert sorted(labels) == [0, 1]
    sets, boxes, class_ids = labels[1]
    assert sets == [()]  # carried: no point set of its own there
    np.testing.assert_allclose(boxes, standing[None])
    assert [db.class_names[int(c)] for c in class_ids] == ["box"]
    assert len(labels[0][0]) == 2  # the frame's own two, as mined
    # Off: each stays in its frame; without the world placed, carrying is refused.
    assert sorted(session_pseudo_labels(db, LoopSettings(pseudo_label_confident=0.6), [0, 1])) == [0]
    with pytest.raises(InputError, match="world frame"):
        session_pseudo_labels(db, settings, [0, 1])
    assert session_pseudo_labels(db, LoopSettings(carry_pseudo_labels=True), [0, 1], world) == {}
    # Frame 1's own pseudo-label of the object, or its label there, keeps the carried one out.
    db.save_training_run(
        queue_run(tiny_model_path, [[mined_item(1, 7, standing + [0.05, 0, 0, 0, 0, 0, 0], 0.7)]]),
        "small",
        {},
    )
    own = session_pseudo_labels(db, settings, [0, 1], world)[1]
    assert own[0] == [(7,)] and len(own[1]) == 1
    # A world of other data is refused.
    with pytest.raises(InputError, match="places 2 frames"):
        session_pseudo_labels(
            db, settings, [0, 1], WorldFrames(np.stack([np.eye(4)] * 2), np.ones(2), (both, both))
        )
    db.add_label(1, walking + [0, 0, 0, 0, 0, 0, 0.1], "box", "ann")  # (a label elsewhere changes nothing)
    db.add_label(1, standing, "cone", "ann")
    sets, boxes, _ = session_pseudo_labels(db, settings, [0, 1], world).get(1, ([], np.zeros((0, 7)), None))
    assert sets == [] and not len(boxes)


def test_carried_pseudo_labels_stay_off_what_a_person_rejected_and_come_from_the_nearest_frame(
    dataset, tmp_path, tiny_model_path
):
    from factorydet_core.session.world import WorldFrames

    standing = np.array([500.0, 500.0, 0.5, 1, 1, 1, 0])
    # Frame 2 sits 0.2 m further along x than frames 0 and 1 think (as drift would have it): the
    # object's box carried from frame 2 lands 0.2 m off in frames 0 and 1.
    poses = np.stack([np.eye(4)] * 3)
    poses[2, 0, 3] = 0.2
    cloud = _cube(standing[:3])
    world = WorldFrames(poses, np.ones(3), (cloud, cloud, _cube(standing[:3] - [0.2, 0, 0])))
    db = SessionDB(open_session("rejected", tmp_path), dataset)
    items = [
        mined_item(0, 0, standing, 0.9),
        mined_item(2, 1, standing - [0.2, 0, 0, 0, 0, 0, 0], 0.95, predicted_class="cone"),
    ]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1, 2)), "small", {})
    settings = LoopSettings(pseudo_label_confident=0.6, carry_pseudo_labels=True)
    _, boxes, class_ids = session_pseudo_labels(db, settings, [0, 1, 2], world)[1]
    # Frame 1 takes frame 0's box (the nearer frame), not frame 2's.
    assert len(boxes) == 1 and db.class_names[int(class_ids[0])] == "box"
    np.testing.assert_allclose(boxes[0], standing)
    # A Background verdict on the object in frame 1 keeps carried pseudo-labels off it there.
    mined_id = db.save_training_run(
        queue_run(tiny_model_path, [[mined_item(1, 3, standing, 0.2)]], train_frames=(1,)), "small", {}
    )
    queued = [item for item in db.review_queue(mined_id) if item["frame_index"] == 1]
    db.review([queued[0]["id"]], "background", "ann")
    assert 1 not in session_pseudo_labels(db, settings, [0, 1, 2], world)
    assert len(db.rejected_boxes([1])[1]) == 1 and not len(db.rejected_boxes([0])[0])
    db.review([queued[0]["id"]], "skip", "ann")
    assert 1 in session_pseudo_labels(db, settings, [0, 1, 2], world)
    # So does a label someone deleted there.
    added = db.add_label(1, standing, "box", "ann")
    db.delete_labels([added.id], "ann")
    assert 1 not in session_pseudo_labels(db, settings, [0, 1, 2], world)


def test_the_simulated_reviewer_answers_items_on_labelled_objects_as_negatives(
    dataset, tmp_path, tiny_model_path
):
    db = SessionDB(open_session("reviewer", tmp_path), dataset)
    truth = read_frame_truth(dataset.path, 0)
    # An annotated object (the data set's label is its truth box), and a box shifted off it.
    real = np.flatnonzero(truth.annotated_mask & (truth.instance_num_points >= 50))[0]
    box = truth.instance_boxes[real]
    shifted = box + [box[3] * 0.6, 0, 0, 0, 0, 0, 0]
    assert truth_verdict(dataset, {"frame_index": 0, "box": shifted.tolist()})[0] == "wrong_box"
    boxes = [shifted, box, _lone_sparse_box(truth)]
    items = [mined_item(0, g, b, 0.9 - 0.1 * g, probabilities=[0.1] * 8) for g, b in enumerate(boxes)]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    num_labels = len(db.labels(0))
    counts = simulated_review(db, dataset, budget=5)
    # The shifted box is a misplaced box of a labelled object: a negative. The exact one repeats
    # the label: nothing to add. The third touches only an object too sparse for the policy.
    assert counts == {
        "background": 1,
        "object": 0,
        "wrong_box": 0,
        "skip": 2,
        "boxes_drawn": 0,
        "hidden": 0,
        "best_view": 0,
    }
    assert [item["verdict"] for item in db.review_queue()] == ["background", "skip", "skip"]
    assert len(db.labels(0)) == num_labels


def test_the_reviewer_with_the_labelled_filter_spends_its_budget_off_labelled_objects(
    dataset, tmp_path, tiny_model_path
):
    db = SessionDB(open_session("filtered", tmp_path), dataset)
    truth = read_frame_truth(dataset.path, 0)
    real = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= 50)
    labelled = truth.instance_boxes[np.flatnonzero(real & truth.annotated_mask)[0]]
    unlabelled = truth.instance_boxes[np.flatnonzero(real & ~truth.annotated_mask)[0]]
    along = 0.5 * labelled[3] * np.array([np.cos(labelled[6]), np.sin(labelled[6])])
    shifted = labelled + [*along, 0, 0, 0, 0, 0]  # half its length along its own axis: IoU 1/3
    # Highest score first: two items on a labelled object, an unlabelled object, a duplicate of
    # it (on a labelled object once the first is answered), and a lone sparse object.
    boxes = [shifted, labelled, unlabelled, unlabelled, _lone_sparse_box(truth)]
    items = [mined_item(0, g, b, 0.9 - 0.1 * g, probabilities=[0.1] * 8) for g, b in enumerate(boxes)]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    shown = db.review_queue(max_label_iou=0.25)
    assert [item["proposal"] for item in shown] == [2, 3, 4]
    # Of the unannotated objects (in truth order), the queue reaches the first, items 2 and 3.
    assert queue_reach(db, dataset, [0, 1]) == {(0, 0)}
    # A reviewer answering the first K entries reaches only what those overlap.
    assert queue_reach(db, dataset, [0, 1], top=2) == set() and queue_reach(db, dataset, [0, 1], top=3) == {
        (0, 0)
    }
    assert db.review_queue()[0]["label_iou"] == pytest.approx(1 / 3, abs=1e-3)

    counts = simulated_review(db, dataset, budget=2, max_label_iou=0.25)
    assert counts == {
        "background": 0,
        "object": 1,
        "wrong_box": 0,
        "skip": 1,
        "boxes_drawn": 0,
        "hidden": 3,
        "best_view": 0,
    }
    assert [item["verdict"] for item in db.review_queue()] == [None, None, "object", None, "skip"]
    # The label the verdict made hides its duplicate from the filtered queue too.
    assert [item["proposal"] for item in db.review_queue(max_label_iou=0.25)] == [4]
    with pytest.raises(InputError, match="max_label_iou"):
        db.review_queue(max_label_iou=0.0)


def test_suspect_labels_are_the_ones_the_classifier_contradicts(db, frames, tiny_model_path):
    model = DetectionModel.load(tiny_model_path)
    suspects = suspect_labels(db, model, frames, max_label_probability=1.0)
    assert suspects, "with no probability limit, every matched label the model ranks lower is listed"
    probabilities = [s["label_probability"] for s in suspects]
    assert probabilities == sorted(probabilities)
    for s in suspects:
        assert (
            s["predicted_class"] != s["class_name"] and s["predicted_probability"] >= s["label_probability"]
        )
        assert db.label(s["label_id"]).class_name == s["class_name"]
    strict = suspect_labels(db, model, frames, max_label_probability=0.05)
    assert len(strict) <= len(suspects)
    assert all(s["label_probability"] <= 0.05 for s in strict)


def test_free_space_is_read_by_default_for_multi_sensor_data_only(dataset):
    from types import SimpleNamespace

    assert dataset.num_sensors > 1 and LoopSettings().quality_visibility(dataset)
    single_scan = SimpleNamespace(num_sensors=1)  # an imported ScanNet room: one identity extrinsic
    assert not LoopSettings().quality_visibility(single_scan)
    assert LoopSettings(visibility=True).quality_visibility(single_scan)
    assert not LoopSettings(visibility=False).quality_visibility(dataset)


def test_unannotated_coverage_counts_the_truth_labels_a_session_gained(dataset, tmp_path):
    db = SessionDB(open_session("coverage", tmp_path), dataset)
    covered, total = unannotated_coverage(db, dataset, [0, 1])
    assert covered == 0 and total > 0  # the data set's own labels are the annotated objects only
    assert add_truth_labels(db, dataset, [0]) > 0
    covered_0, total_0 = unannotated_coverage(db, dataset, [0])
    assert covered_0 == total_0 and unannotated_coverage(db, dataset, [0, 1]) == (covered_0, total)
    # A label of another class over the object does not count.
    label = next(lab for lab in db.labels(0) if lab.origin == "import")
    other = next(name for name in db.class_names if name != label.class_name)
    db.update_label(label.id, "ann", class_name=other)
    assert unannotated_coverage(db, dataset, [0]) == (covered_0 - 1, total_0)


def test_the_loop_settings_name_a_back_half_and_check_it():
    from factorydet_core.detection.box_head import BoxHead

    assert isinstance(new_classifier(LoopSettings(method="head_options"), ("a", "b")), BoxHead)
    assert isinstance(new_classifier(LoopSettings(method="paper"), ("a", "b")), ProposalClassifier)
    with pytest.raises(InputError, match="box_quality"):
        LoopSettings(method="head_options", box_quality=False)  # it boxes by the regressor
    with pytest.raises(InputError, match="method"):
        LoopSettings(method="magic")


def test_a_next_round_goes_on_from_the_shown_run_trained_on_the_same_front_half(
    dataset, tiny_model_path, tmp_path
):
    from factorydet_core.proposals.settings import front_end_params
    from factorydet_core.training.loop import continued_model

    db = SessionDB(open_session("continue", tmp_path), dataset)
    settings = LoopSettings(method="paper", round_epochs=2)
    classifier = new_classifier(settings, db.class_names)
    tiny = DetectionModel.load(tiny_model_path)
    assert continued_model(db, settings, classifier)[2] == "the session has no training run"
    first = db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {}, kind="full")
    second = db.save_training_run(queue_run(tiny_model_path, [[]]), "small", {}, kind="next")
    run_id, model, why = continued_model(db, settings, classifier, tiny.front_end)
    assert (run_id, why) == (second, "") and model is not None  # no choice made: the latest run
    db.set_shown_model("run 1", db.session.path / db.training_runs()[0]["model_path"])
    assert continued_model(db, settings, classifier, tiny.front_end)[0] == first  # the chosen one
    other = front_end_params("agv").replace(voxel_size_m=0.3)
    assert continued_model(db, settings, classifier, other)[2].endswith("another front half")
    assert "box_head" in continued_model(db, LoopSettings(method="box_head", round_epochs=2), classifier)[2]
    afresh = LoopSettings(method="paper", round_epochs=0)
    assert "round_epochs is 0" in continued_model(db, afresh, classifier)[2]
    (db.session.path / db.training_runs()[0]["model_path"]).write_bytes(b"not a checkpoint")
    assert "does not load" in continued_model(db, settings, classifier)[2]


@pytest.mark.slow
def test_the_reviewer_by_place_answers_an_object_mined_in_two_frames_once_and_labels_it_once(
    dataset, tmp_path, tiny_model_path
):
    from factorydet_core.session.world import register_frames

    world = register_frames([dataset.frame(i) for i in range(dataset.num_frames)], use_icp=False)
    first, second = read_frame_truth(dataset.path, 0), read_frame_truth(dataset.path, 1)
    # An object the data set left unannotated, dense enough for the policy in both frames.
    dense = (first.instance_num_points >= 50) & ~first.annotated_mask & (first.instance_class_ids >= 0)
    ids = [
        i
        for i in first.instance_ids[dense]
        if i in set(second.instance_ids[second.instance_num_points >= 50])
    ]
    assert ids, "the small data set has no unannotated object seen in frames 0 and 1"
    box0 = first.instance_boxes[list(first.instance_ids).index(ids[0])]
    box1 = second.instance_boxes[list(second.instance_ids).index(ids[0])]
    items = [
        mined_item(0, 1, box0, 0.9, probabilities=[0.1] * 8),
        mined_item(1, 2, box1, 0.8, probabilities=[0.1] * 8),
    ]
    db = SessionDB(open_session("places", tmp_path), dataset)
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    counts = simulated_review(db, dataset, budget=1, world=world)
    assert counts["object"] == 1 and sum(counts[v] for v in ("background", "wrong_box", "skip")) == 0
    assert [q["verdict"] for q in db.review_queue()] == ["object", "object"]
    labels = [lab for f in range(dataset.num_frames) for lab in db.labels(f) if lab.origin == "review"]
    assert {lab.frame_index for lab in labels} >= {0, 1} and len({lab.instance_id for lab in labels}) == 1
    assert len({lab.frame_index for lab in labels}) == len(labels)  # once in each frame


class _CapturedError(Exception):
    """Raised by ``_capture_training``'s stand-in for ``train_with_mining``."""


def _capture_training(monkeypatch) -> dict:
    """What ``train_session`` hands ``train_with_mining`` (its frames and keyword arguments), in
    the dict returned; the stand-in then raises ``_CapturedError``."""
    seen: dict = {}

    def capture(frames, *args, **kwargs):
        seen.update(frames=frames, **kwargs)
        raise _CapturedError

    monkeypatch.setattr("factorydet_core.training.loop.train_with_mining", capture)
    return seen


def test_held_negatives_hold_their_places_when_asked(dataset, frames, tiny_model_path, tmp_path, monkeypatch):
    """``hold_places``: the next round's frames leave out every point set on a held box (off the
    labels), not only the mined set; without it, or below the hold score, they do not."""
    db = SessionDB(open_session("held", tmp_path), dataset)
    frame = frames[0]
    labels = db.frame_boxes(0)[0]
    off_labels = box_iou_3d(frame.proposal_boxes, labels).max(axis=1) == 0.0

    def others_on(proposal: int) -> set:  # other point sets a hold of this proposal's box takes
        on_box = frame.with_ignored(frame.proposal_boxes[proposal][None]).ignored_point_sets()
        return set(on_box.tolist()) - {int(frame.groups.group_ids[proposal])}

    proposal = next(int(k) for k in np.flatnonzero(off_labels) if others_on(int(k)))
    box = frame.proposal_boxes[proposal]
    group = int(frame.groups.group_ids[proposal])
    items = [mined_item(0, group, box, 0.9), mined_item(0, group + 1, box + [0, 0, 0, 0, 0, 0, 0.1], 0.2)]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})

    seen = _capture_training(monkeypatch)
    for hold_places in (False, True):
        settings = LoopSettings(**{**SETTINGS.__dict__, "hold_confident": 0.5, "hold_places": hold_places})
        with pytest.raises(_CapturedError):
            train_session(db, frames, settings, mode="next", data_ref="small")
        held = seen["frames"][0]
        if hold_places:
            np.testing.assert_allclose(held.ignore_boxes, [box])  # the 0.2 one is below the hold
            # The mined set and the other sets on its box, not only the mined one.
            assert {group} | others_on(proposal) <= set(held.ignored_point_sets().tolist())
        else:
            assert len(held.ignore_boxes) == 0 and len(held.ignored_point_sets()) == 0
        assert len(seen["frames"][1].ignore_boxes) == 0  # nothing held in frame 1


def test_a_session_with_fewer_training_frames_than_threshold_folds_tunes_on_its_fitted_frames(
    db, frames, monkeypatch
):
    """The default threshold folds need a training frame each; with fewer, the run tunes its
    thresholds on the frames it fitted instead of refusing to train."""
    assert LoopSettings().threshold_folds == 2 and LoopSettings().threshold_objective == "total"
    seen = _capture_training(monkeypatch)
    settings = LoopSettings(**{**SETTINGS.__dict__, "threshold_folds": 2})
    with pytest.raises(_CapturedError):
        train_session(db, frames[:2], settings, mode="full", data_ref="small")
    assert seen["threshold_folds"] == 2
    with pytest.raises(_CapturedError):
        train_session(db, frames[:1], settings, mode="full", data_ref="small")
    assert seen["threshold_folds"] == 0
    without = LoopSettings(**{**SETTINGS.__dict__, "threshold_folds": 2, "class_thresholds": False})
    assert without.folds_for(10) == 0 and settings.folds_for(10) == 2 and settings.folds_for(1) == 0


def test_a_run_says_what_it_did_otherwise_than_its_settings_asked():
    from factorydet_core.training.loop import run_notes

    assert run_notes({"mode": "next"}) == ()
    # (a full run trains afresh by design: nothing to say)
    assert run_notes({"mode": "full", "afresh_because": "the session has no training run"}) == ()
    notes = run_notes(
        {"mode": "next", "afresh_because": "round_epochs is 0: every round trains afresh",
         "threshold_folds_skipped": "1 training frame(s), fewer than the 2 threshold folds"}
    )  # fmt: skip
    assert notes == (
        "trained afresh, not going on from a model: round_epochs is 0: every round trains afresh",
        "1 training frame(s), fewer than the 2 threshold folds",
    )


def test_confident_negatives_teach_their_class_in_a_next_round_when_asked(
    dataset, frames, tiny_model_path, tmp_path, monkeypatch
):
    """``pseudo_label_confident``: a next round's frames carry the undecided mined negatives
    scoring that much, off the labels, as labels of their predicted class with the model's box,
    neither background nor left out; those below it are held (or background) as before."""
    db = SessionDB(open_session("pseudo", tmp_path), dataset)
    frame = frames[0]
    labels = db.frame_boxes(0)[0]
    off = np.flatnonzero(box_iou_3d(frame.proposal_boxes, labels).max(axis=1) == 0.0)
    sure, unsure = int(off[0]), int(off[-1])
    items = [
        mined_item(0, int(frame.groups.group_ids[k]), frame.proposal_boxes[k], score, predicted_class="cone")
        for k, score in ((sure, 0.9), (unsure, 0.5))
    ]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})
    seen = _capture_training(monkeypatch)
    for pseudo in (None, 0.6):
        settings = LoopSettings(
            **{**SETTINGS.__dict__, "hold_confident": 0.4, "pseudo_label_confident": pseudo}
        )
        with pytest.raises(_CapturedError):
            train_session(db, frames, settings, mode="next", data_ref="small")
        trained = seen["frames"][0]
        excluded = set(seen["excluded_sets"].get(0, []))
        background = set(seen["background_sets"].get(0, []))
        assert seen["pseudo_label_score"] == pseudo
        assert (items[1]["group"],) in excluded  # held either way
        if pseudo is None:
            assert len(trained.label_boxes) == len(labels) and (items[0]["group"],) in excluded
        else:
            assert len(trained.label_boxes) == len(labels) + 1
            np.testing.assert_allclose(trained.label_boxes[-1], items[0]["box"])
            assert db.class_names[int(trained.label_class_ids[-1])] == "cone"
            assert trained.label_model_box_mask.tolist() == [False] * len(labels) + [True]
            assert trained.label_own_sets[-1] == tuple(items[0]["patch_set"])  # its set is the object
            assert (items[0]["group"],) not in excluded | background
        assert len(seen["frames"][1].label_boxes) == len(db.frame_boxes(1)[0])


def test_a_next_round_carries_pseudo_labels_and_the_label_decides_a_held_set_of_the_object(
    dataset, frames, tiny_model_path, tmp_path, monkeypatch
):
    """``carry_pseudo_labels``: the frames a next round trains on get the carried labels, a held
    point set of the object in a frame it is carried to is no longer left out, and without the
    world placed the round is refused before anything is written."""
    import dataclasses

    from factorydet_core.session.world import WorldFrames

    db = SessionDB(open_session("carry-round", tmp_path), dataset)
    target = frames[1]
    off = np.flatnonzero(box_iou_3d(target.proposal_boxes, db.frame_boxes(1)[0]).max(axis=1) == 0.0)
    k = int(off[0])
    box = target.proposal_boxes[k]
    on_0 = box_iou_3d(box[None], db.frame_boxes(0)[0]).max(initial=0.0)
    assert on_0 < 0.25  # (the same place in frame 0, with the world's identity poses, is off its labels too)

    def item(frame_index, patch_set, score):
        return {
            **mined_item(frame_index, 0, box, score, predicted_class="cone"),
            "patch_set": list(patch_set),
        }

    held_set = tuple(int(p) for p in target.patch_sets[k])
    items = [item(0, (9999,), 0.9), item(1, held_set, 0.5)]
    db.save_training_run(queue_run(tiny_model_path, [items], train_frames=(0, 1)), "small", {})
    cloud = _cube(box[:3], half_m=0.2)
    world = WorldFrames(np.stack([np.eye(4)] * 3), np.ones(3), (cloud, cloud, cloud))
    seen = _capture_training(monkeypatch)
    settings = LoopSettings(
        **{
            **SETTINGS.__dict__,
            "hold_confident": 0.4,
            "pseudo_label_confident": 0.6,
            "carry_pseudo_labels": True,
        }
    )
    snapshots = []
    snapshot = db.snapshot_labels
    monkeypatch.setattr(db, "snapshot_labels", lambda indices: snapshots.append(indices) or snapshot(indices))
    with pytest.raises(InputError, match="world frame"):
        train_session(db, frames, settings, mode="next")
    assert not snapshots  # refused before anything was written
    with pytest.raises(_CapturedError):
        train_session(db, frames, settings, mode="next", world=world)
    trained = seen["frames"][1]
    assert len(trained.label_boxes) == len(db.frame_boxes(1)[0]) + 1
    np.testing.assert_allclose(trained.label_boxes[-1], box)
    assert trained.label_own_sets[-1] == ()
    assert held_set not in set(seen["excluded_sets"].get(1, []))
    # Not carried: the set stays held.
    with pytest.raises(_CapturedError):
        train_session(db, frames, dataclasses.replace(settings, carry_pseudo_labels=False), mode="next")
    assert held_set in set(seen["excluded_sets"].get(1, []))
    assert len(seen["frames"][1].label_boxes) == len(db.frame_boxes(1)[0])


def test_a_next_round_keeps_the_models_box_quality_regressor_unless_told_to_refit_it(db, frames, monkeypatch):
    import dataclasses
    import types

    from factorydet_core.training import loop

    kept = object()  # the continued model's fitted regressor
    monkeypatch.setattr(
        loop,
        "continued_model",
        lambda *a, **k: (1, types.SimpleNamespace(box_quality=kept, classifier=None), ""),
    )
    given = []

    class StopError(Exception):
        pass

    def capture(*args, box_quality=None, reuse_box_quality=None, **kwargs):
        given.append((box_quality, reuse_box_quality))
        raise StopError

    monkeypatch.setattr(loop, "train_with_mining", capture)
    with_quality = LoopSettings(
        epochs=2, round_epochs=1, method="head_options", refit_box_quality=False, quality_trees=40
    )
    assert LoopSettings().refit_box_quality  # refitted by default
    for settings in (with_quality, dataclasses.replace(with_quality, refit_box_quality=True)):
        with pytest.raises(StopError):
            train_session(db, frames, settings, mode="next")
    assert given[0] == (kept, None)
    # Refitted: a new, unfitted regressor of the run's own settings, the model's kept only if the
    # refit would give it back (train_with_mining compares their training rows).
    refit, reuse = given[1]
    assert isinstance(refit, loop.BoxQuality) and not hasattr(refit, "trees_") and reuse is kept
    assert refit.max_iter == 40  # the size the settings ask for
    # On a share of the rows (a full run's fit takes all of them).
    assert refit.row_share == LoopSettings().refit_row_share < 1.0
    with pytest.raises(StopError):
        train_session(
            db,
            frames,
            dataclasses.replace(with_quality, refit_box_quality=True, refit_row_share=0.25),
            mode="next",
        )
    assert given[2][0].row_share == 0.25
    # A full run fits on every row whatever the setting.
    with pytest.raises(StopError):
        train_session(db, frames, dataclasses.replace(with_quality, refit_row_share=0.25), mode="full")
    assert given[3][0].row_share == 1.0
    with pytest.raises(InputError, match="refit_row_share"):
        LoopSettings(refit_row_share=0.0)


@pytest.mark.slow
def test_false_positives_queued_for_review_alone_stay_out_of_the_next_rounds_background(
    dataset, frames, tmp_path
):
    import dataclasses

    db = SessionDB(open_session("extra", tmp_path), dataset)
    settings = dataclasses.replace(SETTINGS, negatives_per_round=10, review_extra=None)
    run_id, run = train_session(db, frames, settings, mode="full", data_ref="small")
    queue = db.review_queue(run_id)
    extras = {(i["frame_index"], tuple(i["patch_set"])) for i in queue if not i["in_background"]}
    mined = {(i["frame_index"], tuple(i["patch_set"])) for i in queue if i["in_background"]}
    # The last mining's false positives after its 10, the earlier round's none.
    assert run.rounds[0]["queued"] == [] and len(extras) == len(run.rounds[-1]["queued"]) > 0
    assert db.training_runs()[-1]["rounds"][-1]["num_false_positives"] >= 10 + len(extras)
    background = {(index, tuple(p)) for index, sets in db.mined_patch_sets().items() for p in sets}
    assert background == mined and not extras & background
    _, next_run = train_session(db, frames, settings, mode="next", data_ref="small")
    again = {(i["frame_index"], tuple(i["patch_set"])) for i in db.review_queue()}
    # Mined again (they were no background), unlike the mined ones.
    assert again & extras and not again & mined


@pytest.mark.slow
def test_the_reviewer_with_the_best_view_labels_an_object_too_sparse_where_it_was_mined(
    dataset, tmp_path, tiny_model_path
):
    from factorydet_core.session.world import register_frames

    world = register_frames([dataset.frame(i) for i in range(dataset.num_frames)], use_icp=False)
    truths = [read_frame_truth(dataset.path, f) for f in range(dataset.num_frames)]
    first = truths[0]
    # An object the data set left unannotated, too sparse for the policy in frame 0, dense elsewhere
    # (an annotated one is labelled there already: nothing to add).
    sparse = (first.instance_num_points < 50) & (first.instance_class_ids >= 0)
    dense_later = {
        int(i): bool(a)
        for t in truths[1:]
        for i, n, a in zip(t.instance_ids, t.instance_num_points, t.annotated_mask)
        if n >= 50
    }
    ids = [int(i) for i in first.instance_ids[sparse] if dense_later.get(int(i)) is False]
    box = first.instance_boxes[list(first.instance_ids).index(ids[0])]
    assert truth_verdict(dataset, mined_item(0, 1, box, 0.9))[0] == "skip"
    answers = {}
    for best_view in (False, True):
        db = SessionDB(open_session(f"best-{best_view}", tmp_path), dataset)
        db.save_training_run(queue_run(tiny_model_path, [[mined_item(0, 1, box, 0.9)]]), "small", {})
        counts = simulated_review(db, dataset, budget=1, world=world, best_view=best_view)
        labelled = {
            lab.frame_index
            for f in range(dataset.num_frames)
            for lab in db.labels(f)
            if lab.origin != "dataset"
        }
        answers[best_view] = (counts, labelled)
    counts, labelled = answers[False]
    assert counts["skip"] == 1 and counts["best_view"] == 0 and not labelled
    counts, labelled = answers[True]
    assert counts["best_view"] == 1 and counts["object"] + counts["wrong_box"] == 1 and counts["skip"] == 0
    dense_frames = {
        f
        for f, t in enumerate(truths)
        if any(int(i) == ids[0] and n >= 50 for i, n in zip(t.instance_ids, t.instance_num_points))
    }
    assert dense_frames <= labelled  # labelled once, in the frames where the policy labels it


def _compared(recalls: dict[str, float], num_reference: int = 5) -> dict:
    per_class = {
        c: {
            "precision": 0.5,
            "recall": r,
            "f1": 2 * 0.5 * r / (0.5 + r) if r else 0.0,
            "num_reference": num_reference,
        }
        for c, r in recalls.items()
    }
    return {"per_class": per_class, "precision": 0.5, "recall": 0.5, "f1": 0.5}


def test_the_before_after_table_says_when_the_new_model_has_lost_a_class():
    table = {
        "before (run 1)": _compared({"cone": 0.6, "barrel": 0.5, "pallet": 0.0}),
        "after (run 2)": _compared({"cone": 0.0, "barrel": 0.4, "pallet": 0.0}),
    }
    # Cones: found before, none after. Pallets were never found: nothing lost.
    assert lost_classes(table) == ["cone"]
    text = comparison_markdown(table)
    assert (
        "**after (run 2) finds none of the 5 labelled instances of cone; before (run 1) finds 60% of them.**"
        in text
    )
    assert "instances of pallet" not in text and "instances of barrel" not in text
    # A class without labels on the test frames is never lost; nor is anything with one model.
    table["after (run 2)"]["per_class"]["cone"]["num_reference"] = 0
    assert lost_classes(table) == []
    assert lost_classes({"run 1": _compared({"cone": 0.0})}) == []
    assert "finds none" not in comparison_markdown({"run 1": _compared({"cone": 0.0})})


def test_the_before_after_table_says_when_the_new_model_scores_lower_in_total():
    before, after = _compared({"cone": 0.6}), _compared({"cone": 0.5})
    before["f1"], after["f1"] = 0.244, 0.205
    table = {"before (run 1)": before, "after (run 2)": after}
    assert (
        "**after (run 2) scores a lower total F-score than before (run 1) on these frames "
        "(0.205 against 0.244)**" in comparison_markdown(table)
    )
    after["f1"] = 0.25  # better: nothing said; nor with one model, or an undefined F
    assert "lower total F-score" not in comparison_markdown(table)
    assert "lower total F-score" not in comparison_markdown({"run 1": before})
    after["f1"] = None
    assert "lower total F-score" not in comparison_markdown(table)


def test_a_class_the_fit_finds_none_of_on_its_training_frames_is_named():
    from factorydet_core.metrics import detection_metrics

    barrel, cone = [0.0, 0.0, 0.5, 0.6, 0.6, 1.0, 0.0], [5.0, 0.0, 0.3, 0.34, 0.34, 0.57, 0.0]
    scored = [
        {
            # The cone comes as a barrel, as a fit that has not learned cones gives it.
            "boxes": np.array([barrel, cone]),
            "class_ids": np.array([0, 0]),
            "scores": np.array([0.9, 0.8]),
            "reference_boxes": np.array([barrel, cone]),
            "reference_class_ids": np.array([0, 1]),
        }
    ]
    metrics = detection_metrics(scored, ("barrel", "cone", "pallet"), 0.6, 0.35)
    # The barrel is found, pallets have no labels here: only cones are named.
    assert unlearned_classes(metrics) == {"cone": 1}
    assert "finds none of the labelled instances of cone (1)" in unlearned_text(metrics)
    scored[0]["class_ids"] = np.array([0, 1])  # found, even below the operating score: learned
    scored[0]["scores"] = np.array([0.9, 0.1])
    metrics = detection_metrics(scored, ("barrel", "cone", "pallet"), 0.6, 0.35)
    assert unlearned_classes(metrics) == {} and unlearned_text(metrics) == ""


@pytest.mark.slow
def test_a_next_round_goes_on_from_the_saved_fold_models(dataset, frames, tmp_path, monkeypatch):
    import dataclasses

    from factorydet_core.training import loop

    db = SessionDB(open_session("folds", tmp_path), dataset)
    settings = dataclasses.replace(SETTINGS, rounds=0, threshold_folds=2)
    run_id, run = train_session(db, frames, settings, mode="full")
    # Each fold model is saved beside the run's checkpoints with the frames it never saw, and
    # loads back as the fold model of those frames.
    paths = db.fold_model_paths(run_id)
    assert [p.name for p in paths] == ["fold_0.pt", "fold_1.pt"]
    classifier = loop.new_classifier(settings, db.class_names)
    folds = loop.continued_folds(db, run_id, classifier)
    assert [f.frame_indices for f in folds] == [f.frame_indices for f in run.fold_models] == [(0,), (1,)]
    assert db.fold_model_paths(run_id + 1) == []
    # The time left counts the fold models' epochs on every frame: a next round goes on from
    # these for its round epochs each, a full run (or one not continuing folds) fits them afresh.
    assert loop.fold_fit_epochs(db, settings, "next", 2) == settings.round_epochs
    assert loop.fold_fit_epochs(db, settings, "full", 2) == settings.epochs
    afresh = dataclasses.replace(settings, continue_folds=False)
    assert loop.fold_fit_epochs(db, afresh, "next", 2) == settings.epochs
    assert loop.fold_fit_epochs(db, settings, "next", 1) == 0  # (fewer frames than folds: none)
    assert loop.fold_fit_epochs(db, dataclasses.replace(settings, threshold_folds=0), "next", 2) == 0
    fresh = SessionDB(open_session("no_folds_yet", tmp_path), dataset)
    assert loop.fold_fit_epochs(fresh, settings, "next", 2) == settings.epochs  # (no run to go on from)
    (paths[0].parent / "fold_a.pt").write_bytes(b"")  # not a name of ours: not a fold
    assert db.fold_model_paths(run_id) == paths
    # A file that does not load is fitted afresh, not an error.
    paths[1].write_bytes(b"not a checkpoint")
    assert [f.frame_indices for f in loop.continued_folds(db, run_id, classifier)] == [(0,)]

    given = []

    class StopError(Exception):
        pass

    def capture(*args, init_folds=(), **kwargs):
        given.append([f.frame_indices for f in init_folds])
        raise StopError

    monkeypatch.setattr(loop, "train_with_mining", capture)
    for continue_folds in (True, False):
        with pytest.raises(StopError):
            train_session(
                db, frames, dataclasses.replace(settings, continue_folds=continue_folds), mode="next"
            )
    assert given == [[(0,)], []]


def test_a_persons_label_too_sparse_for_the_policy_is_an_ignored_place(db, dataset, frames):
    """A label a person made on a handful of points trains as neither object nor background; the
    data set's annotations and imported labels are the policy's and are not checked."""
    from factorydet_core.geometry import points_in_box
    from factorydet_core.proposals.merge import merge_frame
    from factorydet_core.session.world import counting_box
    from factorydet_core.training.loop import session_labels, session_references_and_sparse, sparse_label_mask

    frame = frames[0]
    points = merge_frame(dataset.frame(0)).points
    counts = [int(points_in_box(points, counting_box(box)).sum()) for box in frame.label_boxes]
    dense = tuple(frame.label_boxes[int(np.argmax(counts))].tolist())
    assert max(counts) >= 25
    empty = (dense[0], dense[1], dense[2] + 30.0, *dense[3:])  # high above everything: no point
    labels = [
        {"box": dense, "origin": "user"},
        {"box": empty, "origin": "user"},
        {"box": empty, "origin": "review"},
        {"box": empty, "origin": "dataset"},
        {"box": empty, "origin": "import"},
    ]
    expected = [False, True, True, False, False]
    np.testing.assert_array_equal(sparse_label_mask(dataset, 0, labels, 25), expected)
    assert not sparse_label_mask(dataset, 0, labels, 0).any()

    label = db.add_label(0, empty, "box", "sparse")
    try:
        (kept,) = with_session_labels(db, [frame])
        (left_out,), num_sparse = session_labels(db, [frame], min_points=25)
        assert num_sparse == 1
        # The before/after table measures as training learns: neither a reference nor a miss.
        assert len(session_references(db, [0])[0][0]) == len(frame.label_boxes) + 1
        assert len(session_references(db, [0], 25)[0][0]) == len(frame.label_boxes)
        np.testing.assert_allclose(session_references_and_sparse(db, [0], 25)[1][0], [label.box])
        assert len(kept.label_boxes) == len(frame.label_boxes) + 1
        assert len(left_out.label_boxes) == len(frame.label_boxes)
        np.testing.assert_allclose(left_out.ignore_boxes, [label.box])
        # With a floor for the thresholds' tuning alone, it trains as an object and the tuning
        # ignores it; the data set's labels are not checked.
        (tuned,), num_sparse = session_labels(db, [frame], tuning_min_points=25)
        assert num_sparse == 0 and len(tuned.label_boxes) == len(frame.label_boxes) + 1
        assert tuned.label_tuning_ignore_mask.tolist() == [False] * len(frame.label_boxes) + [True]
        (both,), _ = session_labels(db, [frame], min_points=25, tuning_min_points=25)
        assert both.label_tuning_ignore_mask is None  # (nothing left for the tuning to ignore)
    finally:
        db.delete_labels([label.id], "sparse")


def test_the_label_points_floor_follows_the_data_sets_policy(dataset):
    policy = dataset.manifest["config"]["min_annotated_points"]
    assert LoopSettings(label_min_points=None).label_points_floor(dataset) == round(policy / 2)
    assert LoopSettings().label_points_floor(dataset) == 0  # every label, the default
    assert LoopSettings(label_min_points=7).label_points_floor(dataset) == 7
    assert LoopSettings(label_min_points=None).label_points_floor(None) == 0  # no policy: every label
    with pytest.raises(InputError, match="label_min_points"):
        LoopSettings(label_min_points=-1)
    # The control's -1 is the policy's floor; below it is refused; the default needs no flag.
    from factorydet_core.training.settings import CONTROL_BY_FIELD

    control = CONTROL_BY_FIELD["label_min_points"]
    assert control.parse("-1") is None and control.parse("25") == 25
    assert control.arguments(None) == ["--label-min-points", "-1"] and control.arguments(0) == []
    with pytest.raises(InputError):
        control.parse("-2")


def test_a_run_tunes_its_thresholds_without_a_persons_sparse_labels(db, dataset, frames, monkeypatch):
    """``threshold_label_min_points`` reaches the frames a run trains on: a person's label on a
    handful of points stays a label, marked for the thresholds' tuning to ignore."""
    from factorydet_core.training import loop

    class StopError(Exception):
        pass

    given = []

    def capture(frames_given, *args, **kwargs):
        given.append(frames_given)
        raise StopError

    monkeypatch.setattr(loop, "train_with_mining", capture)
    box = tuple(frames[0].label_boxes[0].tolist())
    label = db.add_label(0, (box[0], box[1], box[2] + 30.0, *box[3:]), "box", "sparse")  # no point
    try:
        for floor in (0, 25):
            with pytest.raises(StopError):
                train_session(db, frames, dataclasses.replace(SETTINGS, threshold_label_min_points=floor))
    finally:
        db.delete_labels([label.id], "sparse")
    every, floored = ({f.frame_index: f for f in run} for run in given)
    assert every[0].label_tuning_ignore_mask is None
    mask = floored[0].label_tuning_ignore_mask
    assert len(floored[0].label_boxes) == len(every[0].label_boxes) and mask[-1] and not mask[:-1].any()


def test_a_runs_config_counts_the_labels_its_thresholds_were_tuned_without(dataset, frames, tmp_path):
    db = SessionDB(open_session("tuning_floor", tmp_path), dataset)
    box = tuple(frames[0].label_boxes[0].tolist())
    db.add_label(0, (box[0], box[1], box[2] + 30.0, *box[3:]), "box", "sparse")  # no point
    settings = dataclasses.replace(SETTINGS, rounds=0, threshold_label_min_points=25)
    run_id, _ = train_session(db, frames, settings)
    config = db.run_config(run_id)
    assert (config["threshold_points_floor"], config["labels_tuning_ignored"]) == (25, 1)
    assert (config["label_points_floor"], config["sparse_labels_ignored"]) == (0, 0)  # it trained
    # Without per-class thresholds nothing is tuned, and nothing is counted.
    run_id, _ = train_session(db, frames, dataclasses.replace(settings, class_thresholds=False))
    config = db.run_config(run_id)
    assert (config["threshold_points_floor"], config["labels_tuning_ignored"]) == (0, 0)


def test_the_thresholds_label_floor_follows_the_data_sets_policy_too(dataset):
    policy = dataset.manifest["config"]["min_annotated_points"]
    floor = LoopSettings(threshold_label_min_points=None).threshold_points_floor(dataset)
    assert floor == LoopSettings(label_min_points=None).label_points_floor(dataset) == round(policy / 2)
    assert LoopSettings().threshold_points_floor(dataset) == floor  # the default
    assert LoopSettings(threshold_label_min_points=0).threshold_points_floor(dataset) == 0  # every label
    assert LoopSettings(threshold_label_min_points=9).threshold_points_floor(dataset) == 9
    # The before/after table ignores what the run neither trained nor tuned on.
    assert LoopSettings(threshold_label_min_points=9).measure_points_floor(dataset) == 9
    assert LoopSettings(label_min_points=12, threshold_label_min_points=9).measure_points_floor(dataset) == 12
    with pytest.raises(InputError, match="threshold_label_min_points"):
        LoopSettings(threshold_label_min_points=-1)
    from factorydet_core.training.settings import CONTROL_BY_FIELD

    control = CONTROL_BY_FIELD["threshold_label_min_points"]
    assert control.parse("-1") is None
    assert control.arguments(None) == []  # the default: no flag
    assert control.arguments(0) == ["--threshold-label-min-points", "0"]
