"""Training with hard-negative mining, its session record, and the trained model's detections."""

import dataclasses
import json
import time

import numpy as np
import pytest

from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.io.dataset import open_dataset
from factorydet_core.metrics import tune_class_thresholds
from factorydet_core.session.queue import queue_order
from factorydet_core.session.store import mined_negatives, open_session, save_training_run, training_runs
from factorydet_core.training import mining as training
from factorydet_core.training.mining import (
    collect_proposals,
    group_labels,
    group_overlaps,
    score_frames,
    train_with_mining,
)
from factorydet_core.types import InputError


@pytest.fixture(scope="module")
def frames(small_dataset_dir):
    return collect_proposals(open_dataset(small_dataset_dir), [0, 1], Detector("agv"))


@pytest.fixture(scope="module")
def run(frames):
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    return train_with_mining(
        frames,
        classifier,
        rounds=1,
        negatives_per_round=40,
        initial_negatives=150,
        fragment_iou=0.0,  # the paper's start: random sets that overlap nothing
        score_threshold=0.05,
    )


def test_collected_frames_group_proposals_and_keep_annotated_samples(frames):
    for frame in frames:
        assert len(frame.groups.group_ids) == len(frame.proposal_boxes)
        assert frame.groups.num_groups <= len(frame.proposal_boxes)
        # Proposals of one point set share it.
        for g in range(min(frame.groups.num_groups, 20)):
            members = np.flatnonzero(frame.groups.group_ids == g)
            assert len({frame.patch_sets[m] for m in members}) == 1
        assert len(frame.annotation_features) == len(frame.annotation_class_ids) > 0
        assert np.isfinite(frame.annotation_features).all()


def test_group_labels_follow_the_annotations(frames):
    frame = frames[0]
    labels, overlaps_any = group_labels(frame, frame.label_boxes, frame.label_class_ids, 7, 0.6)
    assert labels.shape == (frame.groups.num_groups,)
    positive = labels != 7
    assert overlaps_any[positive].all()
    # Without references everything is background and overlaps nothing.
    labels, overlaps_any = group_labels(frame, np.zeros((0, 7)), np.zeros(0, int), 7, 0.6)
    assert (labels == 7).all() and not overlaps_any.any()


def test_mining_adds_the_top_false_positives_to_the_background(run):
    first, second = run.rounds
    assert first["num_background"] == 150
    mined = first["mined"]
    assert 0 < len(mined) <= 40
    assert second["num_background"] == 150 + len(mined)
    scores = [m["score"] for m in mined]
    assert scores == sorted(scores, reverse=True)
    assert all(m["best_annotated_iou"] < 0.6 for m in mined)
    assert first["num_false_positives"] >= len(mined)
    assert second["mined"] == []  # the last round only measures
    assert len(run.models) == 2 and run.model is run.models[-1]
    assert {"f1", "precision", "recall", "per_class"} <= set(first["train_metrics"])


@pytest.mark.slow
def test_fragments_of_annotated_objects_start_in_the_background(frames):
    """Point sets that overlap a label at IoU in (0, fragment_iou] are all background from the
    start; sets between fragment_iou and positive_iou are left out."""
    expected = 0
    for frame in frames:
        best = group_overlaps(frame, frame.label_boxes).max(axis=1)
        labels, _ = group_labels(frame, frame.label_boxes, frame.label_class_ids, 7, 0.6)
        expected += int(((best > 0) & (best <= 0.4) & (labels == 7)).sum())
    assert expected > 0
    classifier = ProposalClassifier(width=0.0625, epochs=1, num_threads=1)
    run = train_with_mining(frames, classifier, rounds=0, initial_negatives=0, fragment_iou=0.4)
    assert run.rounds[0]["num_background"] == expected
    with pytest.raises(InputError, match="fragment_iou"):
        train_with_mining(frames, classifier, rounds=0, fragment_iou=0.6)
    # A cap samples at most that many per frame.
    per_frame = []
    for frame in frames:
        best = group_overlaps(frame, frame.label_boxes).max(axis=1)
        labels, _ = group_labels(frame, frame.label_boxes, frame.label_class_ids, 7, 0.6)
        per_frame.append(int(((best > 0) & (best <= 0.4) & (labels == 7)).sum()))
    cap = max(1, min(per_frame) // 2)
    capped = train_with_mining(frames, classifier, rounds=0, initial_negatives=0, fragments_per_frame=cap)
    assert capped.rounds[0]["num_background"] == sum(min(n, cap) for n in per_frame)
    with pytest.raises(InputError, match="fragments_per_frame"):
        train_with_mining(frames, classifier, rounds=0, fragments_per_frame=-1)


def test_session_stores_checkpoints_rounds_and_the_review_queue(run, tmp_path):
    session = open_session("t", tmp_path)
    run_id = save_training_run(session, run, "small", {"rounds": 1})
    assert run_id == 1
    runs = training_runs(session)
    assert len(runs) == 1 and [r["round"] for r in runs[0]["rounds"]] == [0, 1]
    assert (session.path / runs[0]["model_path"]).is_file()
    queue = mined_negatives(session)
    assert len(queue) == len(run.rounds[0]["mined"])
    assert queue[0]["verdict"] is None and len(queue[0]["box"]) == 7
    assert save_training_run(session, run, "small", {}) == 2


@pytest.mark.slow
def test_box_quality_is_fitted_once_and_shared_by_every_round(frames):
    run = train_with_mining(
        frames,
        ProposalClassifier(width=0.0625, epochs=1, num_threads=1),
        rounds=1,
        negatives_per_round=10,
        initial_negatives=100,
        box_quality=BoxQuality(max_iter=10),
    )
    quality = run.models[0].box_quality
    assert quality is not None and all(m.box_quality is quality for m in run.models)
    frame = frames[0]
    detections = run.model.detect(frame.proposal_boxes, frame.groups, score_threshold=0.0)
    probability = detections.probabilities[np.arange(len(detections.scores)), detections.class_ids]
    # The probability to the model's exponent (0.5 by default) times a predicted IoU in [0, 1].
    exponent = run.model.probability_exponent
    assert exponent == 0.5
    assert (detections.scores <= probability**exponent + 1e-6).all()


def test_the_box_quality_regressor_fits_alongside_the_networks_and_the_models_wait_for_it(
    frames, monkeypatch
):
    """The regressor's fit needs the labels alone: it runs on a thread of its own while the
    round's network and fold models fit, and the round's model waits for it before scoring."""
    import threading

    events = []
    released = threading.Event()
    real_fit, real_classifier_fit = BoxQuality.fit, ProposalClassifier.fit

    def slow_quality_fit(self, features, targets, progress=None):
        released.wait(30)  # (until the networks have fitted and the run waits for it)
        events.append(("box quality", threading.current_thread() is threading.main_thread()))
        return real_fit(self, features, targets, progress)

    def classifier_fit(self, *args, **kwargs):
        events.append(("network", threading.current_thread() is threading.main_thread()))
        return real_classifier_fit(self, *args, **kwargs)

    def score(model, score_frames_, *args):
        released.set()
        events.append(("score", model.box_quality is not None))
        return score_frames(model, score_frames_, *args)

    quality_reports = []

    def release_once_waited_for(what, done, total):
        if what == "box quality":
            quality_reports.append((done, total))
            if len(quality_reports) == 2:  # its start, then the run's wait for it
                released.set()

    monkeypatch.setattr(BoxQuality, "fit", slow_quality_fit)
    monkeypatch.setattr(ProposalClassifier, "fit", classifier_fit)
    run = train_with_mining(
        frames, ProposalClassifier(width=0.0625, epochs=1, num_threads=1), rounds=0,
        initial_negatives=50, box_quality=BoxQuality(max_iter=5), threshold_folds=2, score=score,
        progress=release_once_waited_for,
    )  # fmt: skip
    # The network and both fold models fitted (here) while the regressor's fit was held back on
    # its own thread; every model scored with it.
    assert events[:3] == [("network", True)] * 3
    assert events[3] == ("box quality", False)
    assert set(events[4:]) == {("score", True)}
    # Waited for, its trees were reported, each as it was fitted.
    assert quality_reports == [(0, 1), (0, 1)] + [(tree, 5) for tree in range(1, 6)]
    record = run.rounds[0]
    assert record["box_quality"] == "fitted" and record["box_quality_wait_seconds"] > 0
    assert record["box_quality_seconds"] >= record["box_quality_wait_seconds"]
    assert run.model.box_quality is not None


def test_a_failed_box_quality_fit_fails_the_run_and_a_cancel_does_not_wait_for_it(frames, monkeypatch):
    import threading

    from factorydet_core.types import Cancelled

    def broken(self, features, targets, progress=None):
        raise InputError("box quality: broken on purpose")

    monkeypatch.setattr(BoxQuality, "fit", broken)
    options = {"rounds": 0, "initial_negatives": 50, "box_quality": BoxQuality(max_iter=5)}
    classifier = ProposalClassifier(width=0.0625, epochs=1, num_threads=1)
    with pytest.raises(InputError, match="broken on purpose"):
        train_with_mining(frames, classifier, **options)
    held = threading.Event()
    monkeypatch.setattr(BoxQuality, "fit", lambda self, rows, targets, progress=None: held.wait(30) and self)
    stop = threading.Event()

    def progress(what, done, total):
        if what == "fit" and done == total:
            stop.set()  # (cancelled once the network has fitted, the regressor still fitting)

    start = time.perf_counter()
    with pytest.raises(Cancelled):
        train_with_mining(frames, classifier, progress=progress, should_stop=stop.is_set, **options)
    assert time.perf_counter() - start < 20  # (the regressor is held for 30 s)
    held.set()


def test_a_cancel_stops_the_box_quality_fit_at_its_next_tree(frames, monkeypatch):
    import threading

    from factorydet_core.types import Cancelled

    ended, real_fit = [], BoxQuality.fit

    def watched_fit(self, features, targets, progress=None):
        try:
            return real_fit(self, features, targets, progress)
        except BaseException as exc:
            ended.append(type(exc).__name__)
            raise

    monkeypatch.setattr(BoxQuality, "fit", watched_fit)
    stop = threading.Event()

    def progress(what, done, total):
        if what == "fit" and done == total:
            stop.set()  # (cancelled once the network has fitted, the regressor still fitting)

    with pytest.raises(Cancelled):
        train_with_mining(
            frames, ProposalClassifier(width=0.0625, epochs=1, num_threads=1), rounds=0,
            initial_negatives=50, box_quality=BoxQuality(max_iter=100_000), progress=progress,
            should_stop=stop.is_set,
        )  # fmt: skip
    # Its thread does not go on boosting (100,000 trees) for nobody: it stops at its next tree.
    deadline = time.perf_counter() + 30
    while not ended and time.perf_counter() < deadline:
        time.sleep(0.05)
    assert ended == ["Cancelled"]


@pytest.mark.slow
def test_a_refit_on_the_rows_a_regressor_was_fitted_on_keeps_that_regressor(frames):
    def first_fit(reuse=None, frames=frames, trees=0):
        return train_with_mining(
            frames,
            ProposalClassifier(width=0.0625, epochs=1, num_threads=1),
            rounds=0,
            initial_negatives=50,
            box_quality=BoxQuality(max_iter=5),
            reuse_box_quality=reuse,
            quality_round_trees=trees,
        )

    run = first_fit()
    fitted = run.model.box_quality
    assert run.rounds[0]["box_quality"] == "fitted"
    same = first_fit(reuse=fitted)
    assert same.model.box_quality is fitted and same.rounds[0]["box_quality"] == "same rows, kept"
    # One label less: other rows, so the regressor is fitted again.
    fewer = [dataclasses.replace(frames[0], label_boxes=frames[0].label_boxes[1:],
                                 label_class_ids=frames[0].label_class_ids[1:]), *frames[1:]]  # fmt: skip
    refit = first_fit(reuse=fitted, frames=fewer)
    assert refit.model.box_quality is not fitted and refit.rounds[0]["box_quality"] == "fitted"
    assert refit.model.box_quality.training_digest_ != fitted.training_digest_
    # Boosted on instead: the model's trees and 3 more, fitted last to these rows (kept on them).
    boosted = first_fit(reuse=fitted, frames=fewer, trees=3)
    assert boosted.rounds[0]["box_quality"] == "continued, 3 trees"
    assert len(boosted.model.box_quality.trees_["roots"]) == len(fitted.trees_["roots"]) + 3
    assert boosted.model.box_quality.training_digest_ == refit.model.box_quality.training_digest_


def test_each_round_takes_its_tuned_thresholds(frames, monkeypatch):
    seen = []

    def fake_tuning(scored, class_names, iou_threshold, max_threshold, objective, untuned_threshold):
        assert objective == "class" and untuned_threshold == 0.5  # the default; the model's global
        seen.append((len(scored), iou_threshold, max_threshold))
        out = np.full(len(class_names), np.nan)
        out[[1, 6]] = [0.45, 0.15]  # bobbins and trucks
        return out

    monkeypatch.setattr(training, "tune_thresholds", fake_tuning)
    run = train_with_mining(
        frames, ProposalClassifier(width=0.0625, epochs=1, num_threads=1), rounds=1, initial_negatives=100,
        score_threshold=0.5, probability_exponent=1.0,
    )  # fmt: skip
    assert seen == [(len(frames), 0.6, 0.5)] * 2  # never above the global threshold
    for model, record in zip(run.models, run.rounds):
        assert model.class_score_thresholds == {"bobbin": 0.45, "truck": 0.15}
        thresholds = record["train_metrics"]["class_score_thresholds"]
        assert thresholds["bobbin"] == 0.45 and thresholds["truck"] == 0.15 and thresholds["box"] == 0.5
    untuned = train_with_mining(
        frames,
        ProposalClassifier(width=0.0625, epochs=1, num_threads=1),
        rounds=0,
        initial_negatives=100,
        tune_class_thresholds=False,
        probability_exponent=0.5,
    )
    assert untuned.model.class_score_thresholds is None and len(seen) == 2
    assert untuned.model.probability_exponent == 0.5 and run.model.probability_exponent == 1.0
    for bad in (0, -1.0, float("inf"), True):  # refused before anything is fitted
        with pytest.raises(InputError, match="probability_exponent"):
            train_with_mining(frames, None, probability_exponent=bad)
    assert "class_score_thresholds" not in untuned.rounds[0]["train_metrics"]


@pytest.mark.slow
def test_saved_model_detects_like_the_trained_one(run, frames, tmp_path, small_dataset_dir):
    path = run.model.save(tmp_path / "m.pt")
    loaded = DetectionModel.load(path)
    frame = frames[0]
    a = run.model.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    b = loaded.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    np.testing.assert_allclose(a.scores, b.scores, atol=1e-5)
    np.testing.assert_allclose(a.boxes, b.boxes)
    # Each round's model gets the per-class thresholds of highest F-score on the training frames'
    # annotations, from the scores its round computed (none here: this two-epoch classifier
    # matches no annotation above 0.1; test_each_round_takes_its_tuned_thresholds has some).
    names = run.model.class_names
    expected = tune_class_thresholds(score_frames(run.model, frames, 0.05), names, 0.6, max_threshold=0.05)
    assert run.model.class_score_thresholds == {
        c: float(t) for c, t in zip(names, expected) if np.isfinite(t)
    }
    # Per-class thresholds travel with the checkpoint and are the operating point when no
    # threshold is asked for.
    tuned = {names[0]: 0.9, names[1]: 0.06}
    path = dataclasses.replace(run.model, class_score_thresholds=tuned).save(tmp_path / "t.pt")
    loaded_tuned = DetectionModel.load(path)
    assert loaded_tuned.class_score_thresholds == tuned
    own = loaded_tuned.detect(frame.proposal_boxes, frame.groups)
    kept = own.subset(own.kept_mask)
    floor = np.array([tuned.get(names[c], loaded_tuned.score_threshold) for c in kept.class_ids])
    assert (kept.scores >= floor).all()
    note = json.loads(path.with_suffix(".json").read_text())
    note["class_score_thresholds"] = {names[0]: 1.5}
    path.with_suffix(".json").write_text(json.dumps(note))
    with pytest.raises(InputError, match=rf"\[{names[0]!r}\] must lie in \[0, 1\], got 1.5"):
        DetectionModel.load(path)
    note["class_score_thresholds"] = {names[0]: "high"}
    path.with_suffix(".json").write_text(json.dumps(note))
    with pytest.raises(InputError, match="must be a number"):
        DetectionModel.load(path)
    # The whole pipeline in one call.
    detector = Detector("agv", model=loaded)
    result = detector.detect(open_dataset(small_dataset_dir).frame(0), score_threshold=0.05)
    assert {"classification", "nms", "total"} <= set(result.timings_ms)
    assert len(result.candidates) == result.groups.num_groups
    kept = result.detections.kept_mask
    assert (result.detections.scores >= 0.05).all()
    assert np.all(np.diff(result.detections.scores) <= 0)
    assert (result.detections.suppressed_by[~kept] >= 0).all()
    assert loaded.reads_features and result.groups.features is not None  # the paper's classifier reads them
    with pytest.raises(InputError):
        Detector("agv").detect(open_dataset(small_dataset_dir).frame(0))


def test_training_without_frames_or_positives_is_an_input_error(frames):
    with pytest.raises(InputError):
        train_with_mining([], ProposalClassifier(epochs=1))
    empty = [
        type(frames[0])(**{**frames[0].__dict__, "label_boxes": np.zeros((0, 7)),
                           "label_class_ids": np.zeros(0, int),
                           "annotation_features": np.zeros((0, 20, 5, 5, 5), np.float32),
                           "annotation_descriptors": np.zeros((0, 14), np.float32),
                           "annotation_class_ids": np.zeros(0, int)})
    ]  # fmt: skip
    with pytest.raises(InputError):
        train_with_mining(empty, ProposalClassifier(epochs=1), initial_negatives=10)


def test_mined_sets_are_never_positives(run, frames):
    for m in run.rounds[0]["mined"]:
        frame = next(f for f in frames if f.frame_index == m["frame_index"])
        labels, _ = group_labels(frame, frame.label_boxes, frame.label_class_ids, 7, 0.6)
        assert labels[m["group"]] == 7


def _first_round(frames, **options):
    """A 2-epoch fit from the paper's start (random sets that overlap nothing), mined after."""
    start = {"rounds": 0, "negatives_per_round": 40, "initial_negatives": 150, "fragment_iou": 0.0}
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    return train_with_mining(frames, classifier, mine_after_last=True, **{**start, **options})


@pytest.mark.slow
def test_mining_threshold_decides_what_is_mined_not_the_operating_threshold(frames, run):
    def first_round(**thresholds):
        return _first_round(frames, **thresholds)

    # Mining at 0.05 under a 0.5 operating threshold mines what the 0.05 run mined.
    low = first_round(score_threshold=0.5, mining_threshold=0.05)
    assert low.model.score_threshold == 0.5
    assert [m["group"] for m in low.rounds[0]["mined"]] == [m["group"] for m in run.rounds[0]["mined"]]
    # Without it, mining follows the operating threshold.
    high = first_round(score_threshold=0.5)
    assert all(m["score"] >= 0.5 for m in high.rounds[0]["mined"])
    assert high.rounds[0]["num_false_positives"] <= low.rounds[0]["num_false_positives"]
    with pytest.raises(InputError):
        first_round(mining_threshold=1.5)


def test_the_box_head_trains_with_mining_and_its_checkpoint_detects(frames, tmp_path, small_dataset_dir):
    from factorydet_core.detection.box_head import BoxHead

    head = BoxHead(channels=(16, 32), hidden=32, epochs=2, batch_size=64, num_threads=1)
    run = train_with_mining(frames, head, rounds=1, negatives_per_round=30, score_threshold=0.05)
    assert isinstance(run.model.classifier, BoxHead) and run.model.method == "box_head"
    assert run.model.box_quality is None  # the head scores its own boxes
    first, second = run.rounds
    # Mined negatives are sets the head's labels call background, and they are in the next fit.
    labels = {f.frame_index: training.head_labels(f, head.background_id)[0] for f in frames}
    assert first["mined"] and all(labels[m["frame_index"]][m["group"]] == head.background_id
                                  for m in first["mined"])  # fmt: skip
    assert second["num_background"] >= first["num_background"]
    path = run.model.save(tmp_path / "head.pt")
    loaded = DetectionModel.load(path)
    assert loaded.method == "box_head"
    frame = frames[0]
    a = run.model.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    b = loaded.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    np.testing.assert_allclose(a.scores, b.scores, atol=1e-5)
    np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-6)
    frame_0 = open_dataset(small_dataset_dir).frame(0)
    result = Detector("agv", model=loaded).detect(frame_0, score_threshold=0.05)
    assert len(result.candidates) == result.groups.num_groups
    assert (result.detections.scores >= 0.05).all()
    # The head reads no 3DmFV: the detector builds none unless told to.
    assert not loaded.reads_features and result.proposal.proposals.features is None
    computed = Detector("agv", model=loaded, skip_unread_features=False).detect(frame_0)
    assert computed.proposal.proposals.features is not None and computed.groups.features is not None
    assert run.models[0].reads_features is False


def test_the_box_head_classifies_and_the_box_quality_regressor_boxes(frames, tmp_path):
    from factorydet_core.detection.box_head import BoxHead
    from factorydet_core.detection.scoring import score_groups

    head = BoxHead(channels=(16, 32), hidden=32, epochs=2, batch_size=64, num_threads=1)
    quality = BoxQuality(max_iter=20, max_leaf_nodes=8, visibility=False)
    run = train_with_mining(frames, head, rounds=0, score_threshold=0.05, box_quality=quality)
    model = run.model
    assert model.method == "head_options" and model.box_quality is not None
    frame = frames[0]
    # The candidates are the paper pipeline's box choice over the head's class probabilities.
    probabilities = model.probabilities(frame.groups)
    assert probabilities.shape == (frame.groups.num_groups, len(model.class_names) + 1)
    expected = score_groups(
        frame.proposal_boxes, frame.groups, probabilities, model.box_prior, model.class_names,
        model.box_quality, model.probability_exponent,
    )  # fmt: skip
    got = model.candidates(frame.proposal_boxes, frame.groups)
    np.testing.assert_allclose(got.boxes, expected.boxes)
    np.testing.assert_allclose(got.scores, expected.scores)
    # They differ from the head's own boxes, which the same head without the regressor gives.
    own = dataclasses.replace(model, box_quality=None)
    assert own.method == "box_head"
    assert not np.allclose(own.candidates(frame.proposal_boxes, frame.groups).boxes, got.boxes)
    loaded = DetectionModel.load(model.save(tmp_path / "options.pt"))
    assert loaded.method == "head_options"
    a = model.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    b = loaded.detect(frame.proposal_boxes, frame.groups, score_threshold=0.05)
    np.testing.assert_allclose(a.scores, b.scores, atol=1e-5)
    np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-4)  # the note keeps sizes to 0.1 mm


def test_rounds_after_the_first_go_on_from_the_previous_round(frames, monkeypatch):
    from factorydet_core.detection.box_head import BoxHead

    calls = []
    real_fit = BoxHead.fit

    def spy(self, *args, init_model=None, **kwargs):
        fitted = real_fit(self, *args, init_model=init_model, **kwargs)
        calls.append((self.epochs, init_model, fitted))
        return fitted

    monkeypatch.setattr(BoxHead, "fit", spy)
    head = BoxHead(channels=(16, 32), hidden=32, epochs=2, batch_size=64, num_threads=1)
    quality = BoxQuality(max_iter=20, max_leaf_nodes=8, visibility=False)
    run = train_with_mining(frames, head, rounds=1, score_threshold=0.05, box_quality=quality, round_epochs=1)
    first, second = run.rounds
    assert (first["continued"], first["epochs"], second["continued"], second["epochs"]) == (False, 2, True, 1)
    (epochs_0, start_0, fitted_0), (epochs_1, start_1, fitted_1) = calls
    assert (epochs_0, start_0, epochs_1) == (2, None, 1) and start_1 is fitted_0
    assert run.models[0].classifier is fitted_0 and run.model.classifier is fitted_1
    assert first["recalibrated"] is None  # background recalibration off
    # With it on, the round that goes on from the first fit counts the sets it left out.
    recalibrating = dataclasses.replace(head, recalibrate_background=1e-6)
    rounds = train_with_mining(frames, recalibrating, rounds=1, score_threshold=0.05, round_epochs=1).rounds
    assert rounds[0]["recalibrated"] == 0 and rounds[1]["recalibrated"] > 0
    # A run that goes on from a model (a 'next' round) continues it in its first round, and a
    # fitted regressor is used as it is.
    calls.clear()
    kept = run.model.box_quality
    again = train_with_mining(frames, head, rounds=0, score_threshold=0.05, box_quality=kept,
                              round_epochs=1, init_model=run.model.classifier)  # fmt: skip
    assert again.rounds[0]["continued"] and calls[0][1] is run.model.classifier
    assert again.model.box_quality is kept
    # Without round_epochs every round trains afresh, and a model to go on from is refused.
    calls.clear()
    train_with_mining(frames, head, rounds=1, score_threshold=0.05, round_epochs=0)
    assert [(e, s) for e, s, _ in calls] == [(2, None), (2, None)]
    with pytest.raises(InputError, match="round_epochs"):
        train_with_mining(frames, head, rounds=0, init_model=run.model.classifier)
    with pytest.raises(InputError, match="round_epochs"):
        train_with_mining(frames, head, rounds=0, round_epochs=-1)


def test_the_box_head_trains_and_detects_on_proposals_without_3dmfv(small_dataset_dir, frames, run):
    from factorydet_core.detection.box_head import BoxHead
    from factorydet_core.proposals.settings import PRESETS

    dataset = open_dataset(small_dataset_dir)
    plain = collect_proposals(dataset, [0, 1], Detector(dataclasses.replace(PRESETS["agv"], feature="none")))
    assert all(f.groups.features is None and f.annotation_features is None for f in plain)
    # The proposals' cache keeps them so.
    again = training.proposals_from_arrays(training.proposals_to_arrays(plain))
    assert all(f.groups.features is None and f.annotation_features is None for f in again)
    np.testing.assert_array_equal(again[0].groups.points, plain[0].groups.points)
    head = BoxHead(channels=(16, 32), hidden=32, epochs=1, batch_size=64, num_threads=1)
    quality = BoxQuality(max_iter=10, max_leaf_nodes=8, visibility=False)
    head_run = train_with_mining(plain, head, rounds=0, score_threshold=0.05, box_quality=quality)
    # The point-reading model detects the same on proposals built with and without their 3DmFV
    # from the same segmented cloud (two runs of the front half need not segment alike).
    from factorydet_core.proposals.candidates import build_proposals

    params = PRESETS["agv"]
    detector = Detector(params)
    result = detector.propose(dataset.frame(0))
    rebuilt = build_proposals(
        result.cloud.points, result.segmentation, result.grid, None, min_points=params.min_proposal_points,
        feature="none", include_history=params.include_history, include_patches=params.include_patches,
        complete_boxes=params.complete_boxes, align_to_scene=params.align_to_scene,
        floor_plane=result.floor_plane,
    )  # fmt: skip
    without = dataclasses.replace(result, proposals=rebuilt)
    assert result.proposals.features is not None and without.proposals.features is None
    np.testing.assert_array_equal(rebuilt.boxes, result.proposals.boxes)
    a = head_run.model.detect(result.proposals.boxes, detector.group(result), score_threshold=0.05)
    b = head_run.model.detect(rebuilt.boxes, detector.group(without), score_threshold=0.05)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.class_ids, b.class_ids)
    frame = frames[0]
    stripped = dataclasses.replace(frame.groups, features=None)
    # The paper's classifier reads the 3DmFV: it says so rather than failing deep inside.
    with pytest.raises(InputError, match='"none"'):
        train_with_mining(plain, ProposalClassifier(width=0.0625, epochs=1, num_threads=1), rounds=0)
    with pytest.raises(InputError, match='"none"'):
        run.model.detect(frame.proposal_boxes, stripped)  # the module's paper-method run


def test_places_nobody_decided_on_are_neither_background_nor_mined(frames, run):
    """An unconfirmed pre-label's place (``ignore_boxes``) is left out: no point set on it is
    sampled as background or mined, and the metrics do not count a detection there."""
    mined = run.rounds[0]["mined"]
    ignoring = []
    for frame in frames:
        boxes = [m["box"] for m in mined if m["frame_index"] == frame.frame_index]
        ignoring.append(frame.with_labels(frame.label_boxes, frame.label_class_ids, None, np.array(boxes)))
    ignored = {f.frame_index: set(f.ignored_point_sets().tolist()) for f in ignoring}
    assert sum(map(len, ignored.values())) >= len(mined) > 0
    mined_groups = {(m["frame_index"], m["group"]) for m in mined}
    assert mined_groups <= {(i, g) for i, groups in ignored.items() for g in groups}
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    again = train_with_mining(
        ignoring, classifier, rounds=1, negatives_per_round=40, initial_negatives=150, fragment_iou=0.0,
        score_threshold=0.05,
    )  # fmt: skip
    assert not any(m["group"] in ignored[m["frame_index"]] for m in again.rounds[0]["mined"])
    # Without sampled points the proposals' boxes decide (metrics.IGNORE_IOU).
    frame = ignoring[0]
    without_points = dataclasses.replace(frame, groups=dataclasses.replace(frame.groups, points=None))
    by_boxes = set(without_points.ignored_point_sets().tolist())
    assert {m["group"] for m in mined if m["frame_index"] == frame.frame_index} <= by_boxes


def test_held_negatives_stay_out_of_the_background_and_are_not_mined_again(frames, run):
    """``hold_score``: mined negatives the model scores that confidently are neither background
    nor mined again (background recalibration); they stay in the record for review."""
    first = run.rounds[0]["mined"]
    hold = float(np.median([m["score"] for m in first]))
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    held_run = train_with_mining(
        frames, classifier, rounds=2, negatives_per_round=40, initial_negatives=150, fragment_iou=0.0,
        score_threshold=0.05, hold_score=hold,
    )  # fmt: skip
    rounds = held_run.rounds
    for before, after in zip(rounds[:-1], rounds[1:]):
        held = [m for m in before["mined"] if m["score"] >= hold]
        assert before["num_held"] == len(held)
        assert after["num_background"] == before["num_background"] + len(before["mined"]) - len(held)
    assert sum(r["num_held"] for r in rounds[:-1]) > 0
    # What was held once is never mined again.
    for k, record in enumerate(rounds[:-1]):
        held = {(m["frame_index"], m["group"]) for m in record["mined"] if m["score"] >= hold}
        later = {(m["frame_index"], m["group"]) for r in rounds[k + 1 :] for m in r["mined"]}
        assert not held & later
    with pytest.raises(InputError, match="hold_score"):
        train_with_mining(frames, classifier, rounds=0, hold_score=0.0)


def test_held_negatives_hold_their_places_in_the_rounds_after_them(frames, run):
    """``hold_places``: every point set on a held box off the labels (not only the mined one) is
    neither background nor mined in the later rounds."""
    from factorydet_core.session.store import HIDE_LABELLED_IOU

    hold = float(np.median([m["score"] for m in run.rounds[0]["mined"]]))
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    held_run = train_with_mining(
        frames, classifier, rounds=1, negatives_per_round=40, initial_negatives=150, fragment_iou=0.0,
        score_threshold=0.05, hold_score=hold, hold_places=True,
    )  # fmt: skip
    first, second = held_run.rounds
    held_boxes: dict[int, list] = {}
    for m in first["mined"]:
        if m["score"] >= hold and m["best_annotated_iou"] < HIDE_LABELLED_IOU:
            held_boxes.setdefault(m["frame_index"], []).append(m["box"])
    assert held_boxes, "nothing held off the labels: the test shows nothing"
    places = {
        f.frame_index: set(f.with_ignored(held_boxes.get(f.frame_index)).ignored_point_sets()) for f in frames
    }
    held_sets = {(m["frame_index"], m["group"]) for m in first["mined"] if m["score"] >= hold}
    # The places hold more than the held sets themselves (other candidate sets of the same objects).
    assert sum(len(p) for p in places.values()) > len(held_sets)
    assert not any(m["group"] in places[m["frame_index"]] for m in second["mined"])
    # Fewer sets are background in the second round than holding the sets alone leaves there.
    sets_only = train_with_mining(
        frames, classifier, rounds=1, negatives_per_round=40, initial_negatives=150, fragment_iou=0.0,
        score_threshold=0.05, hold_score=hold,
    )  # fmt: skip
    assert second["num_background"] <= sets_only.rounds[1]["num_background"]
    assert any(m["group"] in places[m["frame_index"]] for m in sets_only.rounds[1]["mined"]) or (
        second["num_background"] < sets_only.rounds[1]["num_background"]
    )


def test_an_unconfirmed_pre_label_on_a_labelled_object_takes_none_of_its_positives(frames):
    from factorydet_core.detection.box_head import BoxHead

    # The box head: its training set drops excluded sets, positives included.
    classifier = BoxHead(channels=(16, 32), hidden=32, epochs=1, batch_size=64, num_threads=1)
    plain = train_with_mining(frames, classifier, rounds=0, initial_negatives=50, fragment_iou=0.0)
    # Pre-labels exactly on every label: the sets there are the labels' positives, not ignored.
    on_labels = [f.with_labels(f.label_boxes, f.label_class_ids, None, f.label_boxes) for f in frames]
    assert sum(len(f.ignored_point_sets()) for f in on_labels) > 0
    both = train_with_mining(on_labels, classifier, rounds=0, initial_negatives=50, fragment_iou=0.0)
    assert both.rounds[0]["num_positives"] == plain.rounds[0]["num_positives"] > 0


@pytest.mark.slow
def test_a_class_order_cut_takes_the_classes_in_turns_from_every_false_positive(frames):
    def mixed_classes(model, frames, threshold, progress=None, should_stop=None):
        # A 2-epoch model calls nearly everything one class: spread its detections over the
        # classes, so that the order has turns to take.
        scored = score_frames(model, frames, threshold, progress, should_stop)
        for item in scored:
            detections = item["detections"]
            class_ids = np.arange(len(detections)) % 3
            item["detections"] = dataclasses.replace(detections, class_ids=class_ids)
            item["class_ids"] = class_ids
        return scored

    def first_round(**options):
        options = {"score_threshold": 0.05, "tune_class_thresholds": False, "score": mixed_classes, **options}
        return _first_round(frames, **options).rounds[0]

    every = first_round(negatives_per_round=100_000)["mined"]
    assert len({m["predicted_class"] for m in every}) == 3
    cut = first_round(negatives_per_round=12, queue_order="class")
    assert cut["num_false_positives"] == len(every)
    expected = queue_order([m["score"] for m in every], [m["predicted_class"] for m in every], "class")[:12]
    assert [(m["frame_index"], m["group"]) for m in cut["mined"]] == [
        (every[k]["frame_index"], every[k]["group"]) for k in expected
    ]
    assert sorted(expected.tolist()) != list(range(12))  # not the 12 highest scores: a test of the cut
    with pytest.raises(InputError, match="queue order"):
        first_round(negatives_per_round=12, queue_order="size")


@pytest.mark.slow
def test_review_extra_queues_the_false_positives_after_the_cut_for_review_alone(frames):
    def keys(items):
        return [(m["frame_index"], m["group"]) for m in items]

    def first_round(**options):  # (a 2-epoch model mines little at the operating threshold)
        return _first_round(frames, score_threshold=0.05, tune_class_thresholds=False, **options)

    every = first_round(negatives_per_round=100_000).rounds[0]
    assert every["queued"] == [] and len(every["mined"]) > 12
    capped = first_round(negatives_per_round=8, review_extra=3).rounds[0]
    assert keys(capped["mined"]) == keys(every["mined"][:8])
    assert keys(capped["queued"]) == keys(every["mined"][8:11])  # the cut's order goes on
    rest = first_round(negatives_per_round=8, review_extra=None).rounds[0]
    assert keys(rest["queued"]) == keys(every["mined"][8:])
    assert first_round(negatives_per_round=8).rounds[0]["queued"] == []  # the paper's queue
    # Only the last mining queues extras: the rounds before it mine for the background alone.
    two = first_round(rounds=1, negatives_per_round=8, review_extra=None)
    assert two.rounds[0]["queued"] == [] and len(two.rounds[1]["queued"]) > 0
    # Without mining after the last round, the round before it is the last to mine.
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    options = {"initial_negatives": 150, "fragment_iou": 0.0, "score_threshold": 0.05}
    before_last = train_with_mining(
        frames, classifier, rounds=1, negatives_per_round=8, review_extra=None,
        tune_class_thresholds=False, **options,
    )  # fmt: skip
    assert len(before_last.rounds[0]["queued"]) > 0 and "queued" not in before_last.rounds[1]
    for bad in (-1, 2.5, True):
        with pytest.raises(InputError, match="review_extra"):
            first_round(review_extra=bad)


def test_confident_negatives_off_the_labels_become_pseudo_labels_of_their_class(frames):
    """``pseudo_label_score``: a mined negative scoring that much, off every label, is a label of
    its predicted class (with the model's box) in the rounds after: an object, not background,
    and never mined again; the rest go on as before."""
    from factorydet_core.detection.box_head import BoxHead
    from factorydet_core.session.store import HIDE_LABELLED_IOU

    head = BoxHead(channels=(16, 32), hidden=32, epochs=2, batch_size=64, num_threads=1)
    probe = train_with_mining(
        frames, head, rounds=0, negatives_per_round=30, score_threshold=0.05, mine_after_last=True
    )
    scores = [m["score"] for m in probe.rounds[0]["mined"] if m["best_annotated_iou"] < HIDE_LABELLED_IOU]
    pseudo = float(np.median(scores))
    run = train_with_mining(
        frames, head, rounds=1, negatives_per_round=30, score_threshold=0.05, pseudo_label_score=pseudo
    )
    first, second = run.rounds
    chosen = [
        m for m in first["mined"] if m["score"] >= pseudo and m["best_annotated_iou"] < HIDE_LABELLED_IOU
    ]
    assert first["num_pseudo_labelled"] == len(chosen) > 0
    assert second["num_positives"] > first["num_positives"]
    assert second["num_background"] < first["num_background"] + len(first["mined"]) - len(chosen) + 1
    names = list(head.class_names)
    by_index = {f.frame_index: f for f in frames}
    for m in chosen:  # each is its predicted class's object in a frame that carries it
        frame = by_index[m["frame_index"]].with_pseudo_labels(
            np.array([m["box"]]), np.array([names.index(m["predicted_class"])]), [m["patch_set"]]
        )
        assert training.head_labels(frame, head.background_id)[0][m["group"]] == names.index(
            m["predicted_class"]
        )
        assert frame.label_model_box_mask[-1] and not frame.label_model_box_mask[:-1].any()
        assert frame.own_set_labels() == [(m["group"], len(frame.label_boxes) - 1)]
    later = {(m["frame_index"], m["group"]) for m in second["mined"]}
    assert not later & {(m["frame_index"], m["group"]) for m in chosen}
    with pytest.raises(InputError, match="pseudo_label_score"):
        train_with_mining(frames, head, rounds=0, pseudo_label_score=1.5)


def test_labels_with_the_models_boxes_can_teach_their_class_alone(frames, monkeypatch):
    """With ``model_box_targets`` off, a label marked as the model's box keeps its point sets as
    the object's, but gives the head no target box, the regressor no rows and the size prior no
    size (unless its class has no other box); on, the run is the one without the mark."""
    from factorydet_core.detection.box_head import BoxHead
    from factorydet_core.training import mining

    marked = []
    for frame in frames:
        mask = np.zeros(len(frame.label_boxes), bool)
        mask[::2] = True
        marked.append(frame.with_labels(frame.label_boxes, frame.label_class_ids, model_box_mask=mask))
    seen = {}
    fit_rows = mining.BoxQuality.training_rows

    def rows(self, frames_, prior, num_classes, excluded=None, box_targets=None):
        seen["box_targets"] = box_targets
        seen["prior"] = prior
        return fit_rows(self, frames_, prior, num_classes, excluded, box_targets)

    def head_fit(self, samples, templates, *args, **kwargs):
        seen["samples"] = samples
        raise InputError("stop here")

    monkeypatch.setattr(mining.BoxQuality, "training_rows", rows)
    monkeypatch.setattr(BoxHead, "fit", head_fit)
    head = BoxHead(channels=(8,), hidden=8, epochs=1, num_threads=1)
    quality = BoxQuality(max_iter=5, max_leaf_nodes=4, visibility=False)
    for learn in (True, False):
        with pytest.raises(InputError, match="stop here"):
            train_with_mining(marked, head, rounds=0, box_quality=quality, model_box_targets=learn)
        samples, targets = seen["samples"], seen["box_targets"]
        objects = samples.labels < len(head.class_names)
        has_target = np.isfinite(samples.target_boxes).all(axis=1)
        if learn:
            assert has_target[objects].all()
            assert all(t.all() for t in targets.values())
        else:
            assert 0 < has_target[objects].sum() < objects.sum()
            classes_all = np.concatenate([f.label_class_ids for f in marked])
            unmarked_all = np.concatenate([~f.label_model_box_mask for f in marked])
            boxed = np.unique(classes_all[unmarked_all])
            for f in marked:  # the marked boxes are no targets, but for a class with no other box
                expected = ~f.label_model_box_mask | ~np.isin(f.label_class_ids, boxed)
                np.testing.assert_array_equal(targets[f.frame_index], expected)
            # The prior's sizes are those of the unmarked boxes where a class has some.
            boxes = np.concatenate([f.label_boxes[~f.label_model_box_mask] for f in marked])
            classes = np.concatenate([f.label_class_ids[~f.label_model_box_mask] for f in marked])
            for c in np.unique(classes):
                assert mining.BoxSizePrior.from_boxes(
                    boxes[classes == c], classes[classes == c], len(head.class_names)
                ).sizes[c] == pytest.approx(seen["prior"].sizes[c], nan_ok=True)


def test_a_class_whose_every_box_is_the_models_learns_from_them(frames):
    from factorydet_core.training.mining import box_targets

    all_marked = [
        f.with_labels(f.label_boxes, f.label_class_ids, model_box_mask=np.ones(len(f.label_boxes), bool))
        for f in frames
    ]
    assert all(t.all() for t in box_targets(all_marked, model_box_targets=False).values())
    assert all(t.all() for t in box_targets(all_marked, model_box_targets=True).values())


def test_the_box_targets_are_every_label_or_those_that_are_not_the_models(frames):
    import types

    from factorydet_core.training.mining import box_target_mask

    frame = types.SimpleNamespace(
        label_boxes=np.zeros((3, 7)), label_model_box_mask=np.array([0, 1, 0], bool)
    )
    assert box_target_mask(frame).all()
    assert box_target_mask(frame, model_box_targets=False).tolist() == [True, False, True]
    unmarked = types.SimpleNamespace(label_boxes=np.zeros((2, 7)), label_model_box_mask=None)
    assert box_target_mask(unmarked, model_box_targets=False).all()
    frame = frames[0]
    with pytest.raises(InputError, match="one per label"):
        frame.with_labels(
            frame.label_boxes, frame.label_class_ids, model_box_mask=np.zeros(len(frame.label_boxes) + 1)
        )


def test_threshold_folds_tune_the_last_model_on_frames_no_fit_saw(frames, monkeypatch):
    events, tunings = [], []
    real_training_set, real_tuning = training._training_set, training.tune_thresholds

    def spy_training_set(fit_frames, *args, **kwargs):
        events.append(("fit", sorted(f.frame_index for f in fit_frames)))
        return real_training_set(fit_frames, *args, **kwargs)

    def spy_score(model, score_frames_, *args):
        events.append(("score", sorted(f.frame_index for f in score_frames_)))
        return score_frames(model, score_frames_, *args)

    def spy_tuning(scored, class_names, iou_threshold, max_threshold, objective, untuned_threshold):
        tunings.append((len(scored), max_threshold, objective))
        real_tuning(
            scored, class_names, iou_threshold, max_threshold=max_threshold, objective=objective,
            untuned_threshold=untuned_threshold,
        )  # (it runs)  # fmt: skip
        out = np.full(len(class_names), np.nan)
        # Bobbins: capped on fitted frames, not beyond; the objectives differ out of fold.
        fitted, out_of_fold = {"class": 0.25, "total": 0.2}, {"class": 0.7, "total": 0.6}
        out[1] = (fitted if max_threshold < 1 else out_of_fold)[objective]
        return out

    monkeypatch.setattr(training, "_training_set", spy_training_set)
    monkeypatch.setattr(training, "tune_thresholds", spy_tuning)
    classifier = ProposalClassifier(width=0.0625, epochs=1, num_threads=1)
    run = train_with_mining(
        frames, classifier, rounds=1, initial_negatives=100, score_threshold=0.3, threshold_folds=2,
        score=spy_score,
    )  # fmt: skip
    both = sorted(f.frame_index for f in frames)
    first, second = both
    # Each round fits and scores every frame; the last one fits each fold's model on the other
    # fold alone before its own model scores (they need no box quality regressor, which may still
    # be fitting), and then each fold's frame is scored by its fold's model.
    assert events == [
        ("fit", both), ("score", both), ("fit", both), ("fit", [second]), ("fit", [first]),
        ("score", both), ("score", [first]), ("score", [second]),
    ]  # fmt: skip
    # Round 0 on its fitted frames under the ceiling; the last on its fitted frames under the
    # ceiling (the model's before the folds), then for the record the other objective's there and
    # each objective's on the out-of-fold scores without one.
    assert tunings == [
        (2, 0.3, "class"), (2, 0.3, "class"), (2, 0.3, "total"), (2, 1.0, "class"), (2, 1.0, "total"),
    ]  # fmt: skip
    assert run.model.class_score_thresholds == {"bobbin": 0.7}
    assert run.models[0].class_score_thresholds == {"bobbin": 0.25}
    folds = run.rounds[-1]["threshold_folds"]
    assert folds["folds"] == 2 and folds["seconds"] > folds["fit_seconds"] > 0
    assert folds["thresholds"] == {"bobbin": 0.7} and folds["fitted_frame_thresholds"] == {"bobbin": 0.25}
    assert folds["objective"] == "class"
    assert folds["by_objective"] == {"class": {"bobbin": 0.7}, "total": {"bobbin": 0.6}}
    # What no folds would have given, each objective: what a benchmark compares the folds with.
    assert folds["fitted_frame_by_objective"] == {"class": {"bobbin": 0.25}, "total": {"bobbin": 0.2}}
    assert "threshold_folds" not in run.rounds[0]
    # The record's metrics are the model's as it is returned.
    assert run.rounds[-1]["train_metrics"]["class_score_thresholds"]["bobbin"] == 0.7
    assert run.rounds[-1]["train_metrics"]["class_score_thresholds"]["box"] == 0.3
    # Tuned for the pooled F, every tuning says so and the model keeps that objective's.
    tunings.clear()
    pooled = train_with_mining(
        frames, classifier, rounds=0, initial_negatives=100, score_threshold=0.3, threshold_folds=2,
        threshold_objective="total",
    )  # fmt: skip
    assert tunings == [(2, 0.3, "total"), (2, 0.3, "class"), (2, 1.0, "class"), (2, 1.0, "total")]
    assert pooled.model.class_score_thresholds == {"bobbin": 0.6}
    assert pooled.rounds[-1]["threshold_folds"]["objective"] == "total"
    fitted_frame_by_objective = pooled.rounds[-1]["threshold_folds"]["fitted_frame_by_objective"]
    assert fitted_frame_by_objective == {"class": {"bobbin": 0.25}, "total": {"bobbin": 0.2}}
    with pytest.raises(InputError, match="threshold_objective must be one of class, total"):
        train_with_mining(frames, classifier, threshold_objective="micro")


def test_a_continued_run_goes_on_from_the_fold_models_of_the_same_frames(frames, monkeypatch):
    classifier = ProposalClassifier(width=0.0625, epochs=2, num_threads=1)
    options = {"initial_negatives": 100, "score_threshold": 0.3, "threshold_folds": 2}
    run = train_with_mining(frames, classifier, rounds=0, **options)
    both = sorted(f.frame_index for f in frames)
    # The run keeps its fold models: each fitted afresh on the other fold (its own epochs).
    assert [fold.frame_indices for fold in run.fold_models] == training.threshold_fold_frames(frames, 2)
    assert sorted(i for fold in run.fold_models for i in fold.frame_indices) == both
    assert [len(fold.classifier.history_) for fold in run.fold_models] == [2, 2]
    assert run.rounds[-1]["threshold_folds"]["continued"] == 0
    assert run.rounds[-1]["threshold_folds"]["fold_frames"] == [[both[0]], [both[1]]]

    starts = []
    real_fit = ProposalClassifier.fit

    def spy_fit(self, *args, init_model=None, **kwargs):
        starts.append(init_model)
        return real_fit(self, *args, init_model=init_model, **kwargs)

    monkeypatch.setattr(ProposalClassifier, "fit", spy_fit)
    on = train_with_mining(
        frames, classifier, rounds=0, round_epochs=1, init_model=run.model.classifier,
        init_folds=run.fold_models, **options,
    )  # fmt: skip
    # The model goes on from the run's, each fold from the fold model of its frames, for the
    # round's epochs.
    assert starts == [run.model.classifier, *(fold.classifier for fold in run.fold_models)]
    assert [len(fold.classifier.history_) for fold in on.fold_models] == [1, 1]
    assert on.rounds[-1]["threshold_folds"]["continued"] == 2
    # A fold model of other frames never stands in (it may have fitted the frames it would score),
    # and without round epochs every fold is fitted afresh.
    starts.clear()
    other = [dataclasses.replace(fold, frame_indices=(99,)) for fold in run.fold_models]
    mixed = [other[0], run.fold_models[1]]
    partly = train_with_mining(
        frames, classifier, rounds=0, round_epochs=1, init_model=run.model.classifier, init_folds=mixed,
        **options,
    )  # fmt: skip
    assert starts[1:] == [None, run.fold_models[1].classifier]
    assert partly.rounds[-1]["threshold_folds"]["continued"] == 1
    afresh = train_with_mining(frames, classifier, rounds=0, init_folds=run.fold_models, **options)
    assert afresh.rounds[-1]["threshold_folds"]["continued"] == 0
    # Nor without the run's own model to go on from (a full run).
    full = train_with_mining(
        frames, classifier, rounds=0, round_epochs=1, init_folds=run.fold_models, **options
    )  # fmt: skip
    assert full.rounds[-1]["threshold_folds"]["continued"] == 0
    assert train_with_mining(frames, classifier, rounds=0, initial_negatives=100).fold_models == []


def test_threshold_folds_are_zero_or_at_least_two_and_no_more_than_the_frames(frames):
    from factorydet_core.training.settings import LoopSettings

    for bad in (1, -1, True, 1.5):
        with pytest.raises(InputError, match="threshold_folds"):
            train_with_mining(frames, ProposalClassifier(epochs=1), threshold_folds=bad)
        with pytest.raises(InputError, match="threshold_folds"):
            LoopSettings(threshold_folds=bad)
    with pytest.raises(InputError, match="3 folds of 2 training frames"):
        train_with_mining(frames, ProposalClassifier(epochs=1), threshold_folds=3)


def test_labels_the_tuning_ignores_are_neither_found_nor_missed_by_the_tuning(frames, monkeypatch):
    """``label_tuning_ignore_mask``: such a label is a reference of the scored frame (the round's
    metrics, mining) but an ignored place where the thresholds are tuned (``for_tuning``), so a
    detection on it counts neither way there; pseudo-labels added after count."""
    from types import SimpleNamespace

    from factorydet_core.metrics import detection_metrics
    from factorydet_core.training.mining import for_tuning, scored_frame, with_tuned_thresholds

    frame = next(f for f in frames if len(f.label_boxes) >= 2)
    boxes, class_ids = frame.label_boxes, frame.label_class_ids
    mask = np.zeros(len(boxes), bool)
    mask[0] = True
    masked = frame.with_labels(boxes, class_ids, tuning_ignore_mask=mask)
    np.testing.assert_array_equal(masked.label_boxes, boxes)  # every label still trains
    kept = SimpleNamespace(boxes=boxes[:1], class_ids=class_ids[:1], scores=np.array([0.9]))
    names = tuple(f"c{k}" for k in range(int(class_ids.max()) + 1))
    name = names[int(class_ids[0])]
    item = scored_frame(masked, kept)
    assert item.keys() - scored_frame(frame, kept).keys() == {"tuning_ignore_mask"}
    np.testing.assert_array_equal(item["reference_boxes"], boxes)  # (the round's own metrics)
    plain, tuned = (detection_metrics([x], names, 0.6, 0.5) for x in (item, for_tuning(item)))
    assert plain["per_class"][name]["tp"] == 1
    assert tuned["per_class"][name]["tp"] == 0 and tuned["per_class"][name]["num_detections"] == 0
    num_refs = sum(v["num_reference"] for v in plain["per_class"].values())
    assert sum(v["num_reference"] for v in tuned["per_class"].values()) == num_refs - 1
    np.testing.assert_allclose(for_tuning(item)["ignore_boxes"][-1], boxes[0])
    assert for_tuning(scored_frame(frame, kept)) == scored_frame(frame, kept)
    # ... and the tuning is given that view of every item.
    seen = []

    def tune(items, class_names, *args, **kwargs):
        seen.extend(items)
        return np.full(len(class_names), 0.5)

    @dataclasses.dataclass(frozen=True)
    class Model:
        class_names: tuple
        score_threshold: float = 0.35
        class_score_thresholds: dict | None = None

    monkeypatch.setattr(training, "tune_thresholds", tune)
    out = with_tuned_thresholds(Model(names), [item, scored_frame(frame, kept)])
    assert out.class_score_thresholds == dict.fromkeys(names, 0.5)
    assert [len(x["reference_boxes"]) for x in seen] == [len(boxes) - 1, len(boxes)]
    pseudo = masked.with_pseudo_labels(boxes[:1] + [0, 0, 5, 0, 0, 0, 0], class_ids[:1])
    np.testing.assert_array_equal(pseudo.label_tuning_ignore_mask, [*mask, False])
    with pytest.raises(InputError, match="tuning_ignore_mask"):
        frame.with_labels(boxes, class_ids, tuning_ignore_mask=mask[:1])
