"""Box quality: the exported trees predict as scikit-learn does, the regressor learns from the
annotations, and detections take the option it rates best, scored by class probability times IoU."""

import dataclasses
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.ensemble import HistGradientBoostingRegressor

from factorydet_core.detection.box_quality import (
    OPTION_FEATURE_NAMES,
    BoxQuality,
    choose_boxes,
    class_option_features,
    num_option_features,
    option_features,
)
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.groups import ANCHORS_PER_SIZE, GROW_VARIANTS, BoxSizePrior
from factorydet_core.detection.model import DetectionModel
from factorydet_core.detection.scoring import score_groups
from factorydet_core.io.dataset import open_dataset
from factorydet_core.training.mining import collect_proposals
from factorydet_core.types import CLASS_NAMES, PROBABILITY_EXPONENT, InputError

NUM_CLASSES = len(CLASS_NAMES)


@pytest.fixture(scope="module")
def frames(small_dataset_dir):
    return collect_proposals(open_dataset(small_dataset_dir), [0, 1], Detector("agv"))


@pytest.fixture(scope="module")
def prior(frames):
    return BoxSizePrior.from_boxes(
        np.concatenate([f.label_boxes for f in frames]),
        np.concatenate([f.label_class_ids for f in frames]),
        NUM_CLASSES,
    )


@pytest.fixture(scope="module")
def fitted(frames, prior):
    quality = BoxQuality(max_iter=40)
    rows, targets = quality.training_rows(frames, prior, NUM_CLASSES)
    return quality.fit(rows, targets), rows, targets


def test_exported_trees_predict_exactly_as_scikit_learn(rng):
    features = rng.normal(size=(600, 5))
    targets = np.clip(0.5 + 0.3 * np.tanh(features[:, 0]) - 0.2 * (features[:, 1] > 0.3), 0, 1)
    quality = BoxQuality(max_iter=30).fit(features, targets)
    reference = HistGradientBoostingRegressor(
        max_iter=30, max_leaf_nodes=quality.max_leaf_nodes, learning_rate=0.1, random_state=0
    )
    reference.fit(features, targets)
    test = rng.normal(size=(300, 5)) * 1.5
    np.testing.assert_allclose(quality.predict(test), np.clip(reference.predict(test), 0, 1), atol=1e-9)
    # Thresholds exactly at a split go left, as in scikit-learn.
    on_split = test.copy()
    on_split[:, quality.trees_["feature"][0]] = quality.trees_["threshold"][0]
    expected = np.clip(reference.predict(on_split), 0, 1)
    np.testing.assert_allclose(quality.predict(on_split), expected, atol=1e-9)


def test_screen_keeps_the_full_walk_of_the_options_it_keeps(rng):
    features = rng.normal(size=(3000, 6))
    targets = np.clip(0.5 + 0.3 * np.tanh(features[:, 0]) - 0.2 * (features[:, 1] > 0.3), 0, 1)
    quality = BoxQuality(max_iter=60).fit(features, targets)
    owners = np.sort(rng.integers(0, 120, size=len(features)))
    full = quality.predict(features)
    screened = quality.with_screen(10, 5).predict_best(features, owners)
    kept = screened >= 0
    # Kept options carry the full walk's sum, bit for bit; each set keeps its 5 best (or all).
    np.testing.assert_array_equal(screened[kept], full[kept])
    assert np.all(screened[~kept] == -1.0)
    per_set = np.bincount(owners[kept], minlength=120)
    np.testing.assert_array_equal(per_set, np.minimum(np.bincount(owners, minlength=120), 5))
    # Keeping every option, or screening with every tree, is the full walk.
    np.testing.assert_array_equal(quality.with_screen(10, 10_000).predict_best(features, owners), full)
    np.testing.assert_array_equal(quality.with_screen(60, 1).predict_best(features, owners), full)
    np.testing.assert_array_equal(quality.with_screen(0, 32).predict_best(features, owners), full)
    # The screen picks the set's best in most sets on this smooth target.
    best_full = np.array([full[owners == g].max() for g in np.unique(owners)])
    best_screened = np.array([screened[owners == g].max() for g in np.unique(owners)])
    assert np.mean(best_full == best_screened) > 0.8
    # The reference walk (one row at a time) gives the same screen and sums.
    reference = quality.with_inference(screen_trees=10, screen_keep=5, interleaved_walk=False)
    np.testing.assert_array_equal(reference.predict_best(features, owners), screened)
    np.testing.assert_array_equal(reference.predict(features), full)
    with pytest.raises(InputError, match="not an inference setting"):
        quality.with_inference(max_iter=3)
    with pytest.raises(InputError):
        quality.with_screen(10, 5).predict_best(features, owners[:-1])
    with pytest.raises(InputError):
        BoxQuality(screen_trees=5, screen_keep=0)
    with pytest.raises(InputError):
        BoxQuality(screen_trees=-1)


def test_screen_travels_with_the_arrays(rng):
    features = rng.normal(size=(200, 3))
    quality = BoxQuality(max_iter=10).fit(features, rng.uniform(size=200)).with_screen(4, 7)
    arrays = {k: np.array(v) for k, v in quality.to_arrays().items()}
    again = BoxQuality.from_arrays(arrays)
    assert (again.screen_trees, again.screen_keep) == (4, 7)
    # Files from before the screen walk every tree.
    older = BoxQuality.from_arrays({k: v for k, v in arrays.items() if not k.startswith("screen")})
    assert older.screen_trees == 0
    with pytest.raises(InputError, match="screen_keep"):
        BoxQuality.from_arrays({**arrays, "screen_keep": np.array(-3)})
    with pytest.raises(InputError, match="screen_trees"):
        BoxQuality.from_arrays({**arrays, "screen_trees": np.array(1.5)})


def test_arrays_round_trip_and_bad_input(rng):
    features = rng.normal(size=(200, 3))
    quality = BoxQuality(max_iter=10).fit(features, rng.uniform(size=200))
    arrays = {k: np.array(v) for k, v in quality.to_arrays().items()}
    again = BoxQuality.from_arrays(arrays)
    assert again.anchored
    # Checkpoints from before anchored options read their features without them.
    assert not BoxQuality.from_arrays({k: v for k, v in arrays.items() if k != "anchored"}).anchored
    np.testing.assert_array_equal(again.predict(features), quality.predict(features))
    with pytest.raises(InputError):
        again.predict(features[:, :2])
    with pytest.raises(InputError):
        BoxQuality.from_arrays({k: v for k, v in arrays.items() if k != "roots"})
    with pytest.raises(InputError):
        BoxQuality(background_rate=1.5)
    with pytest.raises(InputError):
        BoxQuality().fit(features, np.full(200, np.nan))


def test_the_training_digest_names_the_rows_and_settings_and_travels_with_the_trees(rng, tmp_path):
    features, targets = rng.normal(size=(200, 3)), rng.uniform(size=200)
    quality = BoxQuality(max_iter=10).fit(features, targets)
    digest = quality.training_digest_
    assert digest == BoxQuality(max_iter=10).training_digest(features, targets)
    changed_row = features.copy()
    changed_row[7, 1] += 1e-9
    others = {
        BoxQuality(max_iter=10).training_digest(changed_row, targets),
        BoxQuality(max_iter=10).training_digest(features[:-1], targets[:-1]),
        BoxQuality(max_iter=11).training_digest(features, targets),
        BoxQuality(max_iter=10, seed=1).training_digest(features, targets),
    }
    assert digest not in others and len(others) == 4
    loaded = BoxQuality.load(quality.save(tmp_path / "q.npz"))
    assert loaded.training_digest_ == digest
    assert loaded.with_screen(0, 1).training_digest_ == digest
    # Files from before the digest load with none (a refit is never skipped for them).
    arrays = {k: v for k, v in quality.to_arrays().items() if k != "training_digest"}
    assert BoxQuality.from_arrays(arrays).training_digest_ is None
    with pytest.raises(InputError, match="training_digest"):
        BoxQuality.from_arrays({**arrays, "training_digest": np.zeros(31, np.uint8)})


def test_a_fit_on_a_share_of_the_rows_boosts_on_a_seeded_sample_and_names_every_row(rng):
    features = rng.normal(size=(1000, 3))
    targets = np.clip(0.5 + 0.2 * features[:, 0] + 0.05 * rng.normal(size=1000), 0, 1)
    half = BoxQuality(max_iter=10, row_share=0.5)
    kept = half.sampled_rows(1000)
    assert len(kept) == 500 and len(np.unique(kept)) == 500 and (np.diff(kept) > 0).all()
    np.testing.assert_array_equal(BoxQuality(max_iter=10, row_share=0.5).sampled_rows(1000), kept)
    assert not np.array_equal(BoxQuality(max_iter=10, row_share=0.5, seed=1).sampled_rows(1000), kept)
    fitted = half.fit(features, targets)
    # The trees a fit on those rows alone gives; not the ones of every row.
    alone = BoxQuality(max_iter=10).fit(features[kept], targets[kept])
    np.testing.assert_array_equal(fitted.predict(features), alone.predict(features))
    every = BoxQuality(max_iter=10).fit(features, targets)
    assert not np.array_equal(fitted.predict(features), every.predict(features))
    # The digest names the rows learned from, sampled or not: a round on them keeps either.
    assert fitted.training_digest_ == every.training_digest_
    assert len(BoxQuality(row_share=0.001).sampled_rows(1000)) == 2  # never fewer than a fit needs
    assert BoxQuality().sampled_rows(1000) == slice(None)
    for bad in (0.0, 1.5, True):
        with pytest.raises(InputError, match="row_share"):
            BoxQuality(row_share=bad)


def test_a_fit_reports_its_trees_and_fits_the_same_trees_with_or_without(rng):
    features = rng.normal(size=(3000, 4))
    targets = np.clip(0.5 + 0.2 * features[:, 0] + 0.05 * rng.normal(size=3000), 0, 1)
    reported = []

    def report(done: int, total: int) -> None:
        reported.append((done, total))

    watched = BoxQuality(max_iter=12).fit(features, targets, report)
    assert reported == [(tree, 12) for tree in range(13)]  # before the first tree, then after each
    plain = BoxQuality(max_iter=12).fit(features, targets)
    for key, array in plain.trees_.items():
        np.testing.assert_array_equal(watched.trees_[key], array, err_msg=key)
    # A continued regressor reports its new trees.
    reported.clear()
    plain.continued(features, targets, 3, progress=report)
    assert reported == [(0, 3), (1, 3), (2, 3), (3, 3)]

    class StopError(Exception):
        pass

    def cancel_after_two(done: int, total: int) -> None:
        if done == 2:
            raise StopError  # (a cancel: the fit stops at the tree it was on)

    with pytest.raises(StopError):
        BoxQuality(max_iter=12).fit(features, targets, progress=cancel_after_two)


def test_a_continued_regressor_boosts_on_from_its_raw_sums(rng, tmp_path):
    from sklearn.ensemble import HistGradientBoostingRegressor

    from factorydet_core.detection.box_quality import _evaluate_trees

    features = rng.normal(size=(2000, 4))
    targets = np.clip(0.5 + 0.2 * features[:, 0] + 0.05 * rng.normal(size=2000), 0, 1)
    quality = BoxQuality(max_iter=20).fit(features, targets)
    changed = np.clip(targets + 0.3 * (features[:, 1] > 1), 0, 1)  # new labels: some options fit now
    more = quality.continued(features, changed, 10)
    assert len(more.trees_["roots"]) == 30 and len(quality.trees_["roots"]) == 20  # the original kept
    # As one boosting run that went on with 10 trees fitted to its errors on the new targets.
    errors = changed - _evaluate_trees(quality.trees_, features)
    extra = HistGradientBoostingRegressor(max_iter=10, max_leaf_nodes=63, early_stopping=False,
                                          random_state=0).fit(features, errors)  # fmt: skip
    expected = np.clip(_evaluate_trees(quality.trees_, features) + extra.predict(features), 0, 1)
    np.testing.assert_allclose(more.predict(features), expected, atol=1e-12)
    error = np.abs(more.predict(features) - changed).mean()
    assert error < np.abs(quality.predict(features) - changed).mean()
    assert more.training_digest_ is None  # not what a fit on these rows gives
    again = BoxQuality.load(more.save(tmp_path / "more.npz"))
    np.testing.assert_array_equal(again.predict(features), more.predict(features))
    with pytest.raises(InputError):
        quality.continued(features, changed, 0)
    with pytest.raises(InputError):
        quality.continued(features[:, :3], changed, 5)


@pytest.mark.parametrize("anchored", [False, True])
def test_option_features_describe_every_option(frames, prior, anchored):
    frame = frames[0]
    members = frame.groups.members()
    assert sorted(np.concatenate(members).tolist()) == list(range(len(frame.proposal_boxes)))
    for g in range(min(20, frame.groups.num_groups)):
        boxes = frame.proposal_boxes[members[g]]
        np.testing.assert_array_equal(boxes[0], frame.proposal_boxes[frame.groups.representatives[g]])
        options, features = option_features(
            boxes, 2, frame.groups.descriptors[g], prior, NUM_CLASSES, anchored
        )
        assert features.shape == (len(options), num_option_features(NUM_CLASSES, anchored))
        assert np.isfinite(features).all()
        assert (features[:, 2] == 1).all() and features[:, :NUM_CLASSES].sum() == len(options)
        # The set's own boxes come first, unchanged.
        np.testing.assert_array_equal(options[: len(boxes)], boxes)
        num_modes = len(prior.class_modes(2))
        num_grown = len(boxes) * (1 + len(GROW_VARIANTS) * num_modes)
        if not anchored:
            assert len(options) == num_grown
            continue
        # After the grown blocks, per mode: the corners, the floor, the stack.
        placed = []
        for m in prior.class_modes(2):
            fitted = boxes[:1]
            placed += [prior.anchored(fitted, m), prior.standing(fitted, m)[0], prior.stacked(fitted, m)[0]]
        placed = np.concatenate(placed)
        assert len(placed) >= ANCHORS_PER_SIZE * num_modes
        assert len(options) == num_grown + len(placed)
        np.testing.assert_array_equal(options[num_grown:], placed)
        flag = features[:, NUM_CLASSES + len(OPTION_FEATURE_NAMES)]
        np.testing.assert_array_equal(flag, np.arange(len(options)) >= num_grown)


@pytest.mark.parametrize("anchored", [False, True])
def test_batched_options_equal_the_per_set_ones(frames, prior, anchored):
    """Inference builds the options of all sets of a class at once; rows must be option_features's,
    set after set (the regressor was trained on those)."""
    frame = frames[0]
    members = frame.groups.members()
    anchor_mask = frame.groups.anchor_mask
    # The front half's scene-aligned boxes are anchors besides the fitted ones, in some sets.
    assert anchor_mask is not None
    has_aligned_anchor = [anchor_mask[m[1:]].any() for m in members]
    assert any(has_aligned_anchor) and not all(has_aligned_anchor)
    sets = list(range(0, frame.groups.num_groups, 3))
    for class_id in (0, 2, 4, 6):
        options, features, owner, sources = class_option_features(
            frame.proposal_boxes,
            [members[g] for g in sets],
            class_id,
            frame.groups.descriptors[sets],
            prior,
            NUM_CLASSES,
            anchored,
            anchor_mask,
            frame.groups.free_space if anchored else None,
        )
        expected = [
            option_features(
                frame.proposal_boxes[members[g]],
                class_id,
                frame.groups.descriptors[g],
                prior,
                NUM_CLASSES,
                anchored,
                anchor_mask[members[g]],
                frame.groups.free_space if anchored else None,
            )
            for g in sets
        ]
        np.testing.assert_array_equal(options, np.concatenate([e[0] for e in expected]))
        # Each set's options and costs are BoxSizePrior.options's for that set alone, its fitted
        # box and its aligned one the anchors.
        anchors_of = {g: members[g][(members[g] == members[g][0]) | anchor_mask[members[g]]] for g in sets}
        reference = [
            prior.option_sources(
                frame.proposal_boxes[members[g]],
                class_id,
                anchor_boxes=frame.proposal_boxes[anchors_of[g]] if anchored else None,
            )
            for g in sets
        ]
        np.testing.assert_array_equal(options, np.concatenate([r[0] for r in reference]))
        cost_column = NUM_CLASSES + OPTION_FEATURE_NAMES.index("prior_cost")
        np.testing.assert_array_equal(features[:, cost_column], np.concatenate([r[1] for r in reference]))
        np.testing.assert_array_equal(features, np.concatenate([e[1] for e in expected]))
        np.testing.assert_array_equal(owner, np.repeat(np.arange(len(sets)), [len(e[0]) for e in expected]))
        for row, g in enumerate(sets):
            # Grown boxes come from the box they grew; placed ones from the anchor they were placed by.
            _, _, kinds, option_rows, _ = reference[row]
            expected_sources = np.where(
                kinds < 2,
                members[g][np.minimum(option_rows, len(members[g]) - 1)],
                anchors_of[g][np.minimum(option_rows, len(anchors_of[g]) - 1)],
            )
            np.testing.assert_array_equal(sources[owner == row], expected_sources)
        if anchored and class_id == 2:
            assert any(len(anchors_of[g]) > 1 for g in sets)


def test_regressor_learns_the_iou_of_options(fitted):
    quality, rows, targets = fitted
    assert len(rows) == len(targets) and ((targets >= 0) & (targets <= 1)).all()
    # Both ends are in the training set: good boxes of annotated objects and background at 0.
    assert (targets > 0.6).any() and (targets == 0).any()
    predicted = quality.predict(rows)
    assert ((predicted >= 0) & (predicted <= 1)).all()
    # It ranks: options it rates high overlap their objects far more than those it rates low.
    high, low = predicted >= np.quantile(predicted, 0.9), predicted <= np.quantile(predicted, 0.5)
    assert targets[high].mean() > 0.3 + targets[low].mean()


def test_an_option_fitting_another_object_of_the_class_is_right(frames, prior):
    """A set that holds several objects of one class (a stack of crates) has one right box per
    object: the option that fits the second object is trained towards IoU 1, not towards its
    overlap with the object the set overlaps most."""
    from factorydet_core.boxes import box_iou_3d

    frame = frames[0]
    members = frame.groups.members()
    iou = box_iou_3d(frame.proposal_boxes, frame.label_boxes)
    g = next(g for g, m in enumerate(members) if iou[m].max() >= 0.5)
    label = int(iou[members[g]].max(axis=0).argmax())
    class_id = int(frame.label_class_ids[label])
    options, features = option_features(
        frame.proposal_boxes[members[g]],
        class_id,
        frame.groups.descriptors[g],
        prior,
        NUM_CLASSES,
        True,
        free_space=frame.groups.free_space,
    )
    overlap = box_iou_3d(options, frame.label_boxes[label : label + 1])[:, 0]
    other = int(np.argmin(overlap))
    assert overlap[other] < 0.5
    # A second object of the class exactly where that option lies.
    with_second = dataclasses.replace(
        frame,
        label_boxes=np.concatenate([frame.label_boxes, options[other : other + 1]]),
        label_class_ids=np.concatenate([frame.label_class_ids, [class_id]]),
    )
    rows, targets = BoxQuality(background_rate=0.0).training_rows([with_second], prior, NUM_CLASSES)
    same_row = np.flatnonzero((rows == features[other]).all(axis=1))
    assert len(same_row) and targets[same_row] == pytest.approx(1.0)


def test_sets_rated_in_chunks_choose_as_all_at_once(frames, prior, fitted, monkeypatch, rng):
    from factorydet_core.detection import box_quality as module

    frame = frames[0]
    class_ids = rng.integers(0, NUM_CLASSES, frame.groups.num_groups)
    whole = choose_boxes(frame.proposal_boxes, frame.groups, class_ids, prior, fitted[0])
    monkeypatch.setattr(module, "SETS_PER_CHUNK", 7)
    chunked = choose_boxes(frame.proposal_boxes, frame.groups, class_ids, prior, fitted[0])
    for a, b in zip(whole, chunked):
        np.testing.assert_array_equal(a, b)
    subset = np.arange(0, frame.groups.num_groups, 3)
    some = choose_boxes(frame.proposal_boxes, frame.groups, class_ids, prior, fitted[0], subset)
    for a, b in zip(whole, some):
        np.testing.assert_array_equal(a[subset], b)


def test_detections_take_the_best_rated_option_and_its_iou_in_the_score(frames, prior, fitted):
    quality = fitted[0]
    frame = frames[0]
    num_groups = frame.groups.num_groups
    probabilities = np.full((num_groups, NUM_CLASSES + 1), 0.01, np.float32)
    probabilities[:, 2] = 0.9  # every set a "box" with probability 0.9
    plain = score_groups(frame.proposal_boxes, frame.groups, probabilities, prior)
    rated = score_groups(frame.proposal_boxes, frame.groups, probabilities, prior, box_quality=quality)
    boxes, proposal_ids, predicted = choose_boxes(
        frame.proposal_boxes, frame.groups, np.full(num_groups, 2), prior, quality
    )
    np.testing.assert_allclose(rated.boxes, boxes)
    np.testing.assert_array_equal(rated.proposal_ids, proposal_ids)
    np.testing.assert_allclose(rated.scores, 0.9 * predicted, rtol=1e-5)
    np.testing.assert_allclose(plain.scores, 0.9, rtol=1e-6)
    members = frame.groups.members()
    for g in range(0, num_groups, max(1, num_groups // 15)):
        mask = frame.groups.anchor_mask[members[g]]
        options, features = option_features(
            frame.proposal_boxes[members[g]],
            2,
            frame.groups.descriptors[g],
            prior,
            NUM_CLASSES,
            True,
            mask,
            frame.groups.free_space,
        )
        assert quality.predict(features).max() == pytest.approx(predicted[g])
        assert proposal_ids[g] in members[g]
    # Sets below the floor keep the prior's box and their probability.
    probabilities[:5, 2] = 0.02
    low = score_groups(frame.proposal_boxes, frame.groups, probabilities, prior, box_quality=quality)
    np.testing.assert_allclose(low.scores[:5], 0.02, rtol=1e-5)
    np.testing.assert_allclose(low.boxes[:5], plain.boxes[:5])
    # The probability's power in the score: the same boxes, the square root of 0.9 times the IoU,
    # and sets below the floor still keep their probability.
    rooted = score_groups(
        frame.proposal_boxes,
        frame.groups,
        probabilities,
        prior,
        box_quality=quality,
        probability_exponent=0.5,
    )
    np.testing.assert_allclose(rooted.boxes, low.boxes)
    np.testing.assert_allclose(rooted.scores[5:], np.sqrt(0.9) * predicted[5:], rtol=1e-5)
    np.testing.assert_allclose(rooted.scores[:5], 0.02, rtol=1e-5)
    with pytest.raises(InputError, match="probability_exponent"):
        score_groups(frame.proposal_boxes, frame.groups, probabilities, prior, box_quality=quality,
                     probability_exponent=0.0)  # fmt: skip


def test_checkpoint_keeps_the_regressor(tiny_model_path, fitted, tmp_path):
    model = dataclasses.replace(DetectionModel.load(tiny_model_path), box_quality=fitted[0])
    path = model.save(tmp_path / "q.pt")
    loaded = DetectionModel.load(path)
    assert loaded.note["box_quality"]["max_iter"] == 40
    assert loaded.probability_exponent == model.probability_exponent == PROBABILITY_EXPONENT
    rooted = dataclasses.replace(model, probability_exponent=0.75)
    rooted = DetectionModel.load(rooted.save(tmp_path / "r.pt"))
    assert rooted.probability_exponent == 0.75
    note_path = tmp_path / "r.json"
    note = json.loads(note_path.read_text())
    del note["probability_exponent"]  # a checkpoint from before the exponent was kept
    note_path.write_text(json.dumps(note))
    assert DetectionModel.load(tmp_path / "r.pt").probability_exponent == 1.0
    note_path.write_text(json.dumps({**note, "probability_exponent": -1}))
    with pytest.raises(InputError, match="probability_exponent"):
        DetectionModel.load(tmp_path / "r.pt")
    # Box voting: kept, switched off (null), and the default for checkpoints from before it.
    from factorydet_core.detection.scoring import BOX_VOTE_IOU

    assert loaded.vote_iou == BOX_VOTE_IOU and loaded.note["vote_iou"] == BOX_VOTE_IOU
    for value, expected in ((None, None), (0.6, 0.6)):
        note_path.write_text(json.dumps({**note, "vote_iou": value}))
        assert DetectionModel.load(tmp_path / "r.pt").vote_iou == expected
    del note["vote_iou"]
    note_path.write_text(json.dumps(note))
    assert DetectionModel.load(tmp_path / "r.pt").vote_iou == BOX_VOTE_IOU
    note_path.write_text(json.dumps({**note, "vote_iou": 1.5}))
    with pytest.raises(InputError, match="vote_iou"):
        DetectionModel.load(tmp_path / "r.pt")
    rows = fitted[1][:50]
    np.testing.assert_array_equal(loaded.box_quality.predict(rows), fitted[0].predict(rows))
    (tmp_path / "q.boxq.npz").unlink()
    with pytest.raises(InputError):
        DetectionModel.load(path)


def test_detection_details_show_the_predicted_iou(small_dataset_dir, prior, fitted):
    from factorydet_core.evaluation.diagnostics import describe_detection

    frame = open_dataset(small_dataset_dir).frame(0)
    detector = Detector("agv")
    result = detector.propose(frame)
    groups = detector.group(result)
    probabilities = np.full((groups.num_groups, NUM_CLASSES + 1), 0.01, np.float32)
    probabilities[:, 2] = 0.9
    rated = score_groups(result.proposals.boxes, groups, probabilities, prior, box_quality=fitted[0])
    k = int(np.argmax(rated.scores))
    info = describe_detection(rated, k, result.proposals, frame)
    assert float(info["predicted box IoU"]) == pytest.approx(rated.scores[k] / 0.9, abs=0.006)
    # With the square root of the probability in the score, the same IoU.
    rooted = score_groups(
        result.proposals.boxes, groups, probabilities, prior, box_quality=fitted[0], probability_exponent=0.5
    )
    info = describe_detection(rooted, k, result.proposals, frame, probability_exponent=0.5)
    assert float(info["predicted box IoU"]) == pytest.approx(rated.scores[k] / 0.9, abs=0.006)
    plain = score_groups(result.proposals.boxes, groups, probabilities, prior)
    assert "predicted box IoU" not in describe_detection(plain, k, result.proposals, frame)


def test_compiled_tree_walk_equals_the_numpy_walk_from_several_threads(rng):
    from concurrent.futures import ThreadPoolExecutor

    from factorydet_core.detection.box_quality import _evaluate_trees, _evaluate_trees_numpy

    features = rng.normal(size=(800, 6))
    targets = np.clip(0.4 + 0.3 * np.sin(features[:, 0] * 2) + 0.1 * features[:, 2], 0, 1)
    quality = BoxQuality(max_iter=50).fit(features, targets)
    # Not a multiple of the eight rows walked side by side: the last rows walk alone.
    test = rng.normal(size=(2003, 6)) * 1.3
    test[7] = np.nan  # never a feature, but walked as the reference walks it (right at every split)
    expected = _evaluate_trees_numpy(quality.trees_, test)
    # Both add the trees in order, row by row: the same sums bit for bit.
    np.testing.assert_array_equal(_evaluate_trees(quality.trees_, test), expected)
    partial = _evaluate_trees(quality.trees_, test, last_tree=20)
    continued = _evaluate_trees(quality.trees_, test, first_tree=20, initial=partial)
    np.testing.assert_array_equal(continued, expected)
    np.testing.assert_array_equal(_evaluate_trees(quality.trees_, test, interleaved=False), expected)
    # The app predicts from its worker and its callbacks' threads at once.
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda _: _evaluate_trees(quality.trees_, test), range(8)))
    for result in results:
        np.testing.assert_array_equal(result, expected)


def test_visibility_features_are_the_options_seen_free_and_occupied_shares(frames, prior, fitted):
    from factorydet_core.detection.box_quality import ANCHORED_FEATURE_NAMES, VISIBILITY_FEATURE_NAMES
    from factorydet_core.proposals.visibility import box_visibility

    frame = frames[0]
    members = frame.groups.members()
    g = len(members) // 2
    args = (frame.proposal_boxes[members[g]], 2, frame.groups.descriptors[g], prior, NUM_CLASSES, True)
    options, features = option_features(*args, free_space=frame.groups.free_space)
    _, without = option_features(*args)
    assert features.shape[1] == num_option_features(NUM_CLASSES, True, True) == without.shape[1] + 2
    start = NUM_CLASSES + len(OPTION_FEATURE_NAMES) + len(ANCHORED_FEATURE_NAMES)
    shares = features[:, start : start + len(VISIBILITY_FEATURE_NAMES)]
    np.testing.assert_array_equal(shares, box_visibility(frame.groups.free_space, options))
    assert shares[:, 0].max() > 0  # some option of the set holds space the rays saw empty
    # The shipped arrays keep the flag; arrays from before it load without visibility.
    arrays = fitted[0].to_arrays()
    assert fitted[0].visibility and BoxQuality.from_arrays(arrays).visibility
    del arrays["visibility"]
    assert not BoxQuality.from_arrays(arrays).visibility


def test_the_shipped_screen_chooses_as_the_full_walk_on_small_frames(frames, prior):
    # The fast path against the reference on the small frames' every point set and class: with
    # the screen the shipped model uses, nearly every set's chosen option and predicted IoU are the
    # full walk's, and a set that chooses otherwise loses little predicted IoU.
    quality = BoxQuality(max_iter=100, screen_trees=0)
    quality.fit(*quality.training_rows(frames, prior, NUM_CLASSES))
    screened = quality.with_screen(BoxQuality.screen_trees, BoxQuality.screen_keep)
    assert (screened.screen_trees, screened.screen_keep) == (50, 32)
    same, lost = [], []
    for frame in frames:
        for class_id in range(NUM_CLASSES):
            class_ids = np.full(frame.groups.num_groups, class_id)
            full_boxes, _, full_iou = choose_boxes(
                frame.proposal_boxes, frame.groups, class_ids, prior, quality
            )
            boxes, _, iou = choose_boxes(frame.proposal_boxes, frame.groups, class_ids, prior, screened)
            same.append((boxes == full_boxes).all(axis=1) & (iou == full_iou))
            lost.append(full_iou - iou)
    same, lost = np.concatenate(same), np.concatenate(lost)
    assert same.mean() >= 0.99
    assert lost.min() >= 0.0  # the full walk's choice is the best there is
    assert lost.max() <= 0.1


def test_prior_boxes_of_all_sets_at_once_are_those_of_one_set_at_a_time(frames, prior, rng):
    from factorydet_core.detection.scoring import _prior_boxes

    frame = frames[1]
    class_ids = rng.integers(0, NUM_CLASSES, frame.groups.num_groups)
    subset = np.flatnonzero(rng.random(frame.groups.num_groups) < 0.7)
    boxes, proposal_ids = _prior_boxes(frame.proposal_boxes, frame.groups, class_ids, prior, subset)
    members = frame.groups.members()
    for g in range(frame.groups.num_groups):
        if g not in set(subset.tolist()):
            np.testing.assert_array_equal(boxes[g], frame.proposal_boxes[frame.groups.representatives[g]])
            continue
        options, cost = prior.options(frame.proposal_boxes[members[g]], int(class_ids[g]))
        best = int(np.argmin(cost))
        np.testing.assert_array_equal(boxes[g], options[best])
        assert proposal_ids[g] == members[g][best % len(members[g])]


@given(st.lists(st.tuples(st.integers(1, 6), st.integers(0, 3)), min_size=0, max_size=30))
@settings(max_examples=60, deadline=None)
def test_each_sets_best_is_what_the_ranking_puts_first(blocks):
    from factorydet_core.detection.box_quality import _best_in_sets
    from factorydet_core.detection.groups import rank_within_sets

    # Sets listed set after set; few distinct values, so ties are common.
    owners = np.repeat(np.arange(len(blocks)), [size for size, _ in blocks]).astype(np.int64)
    rng = np.random.default_rng(len(owners))
    values = rng.integers(-1, 3, size=len(owners)).astype(np.float64) / 2
    expected = np.flatnonzero(rank_within_sets(owners, -values) == 0)
    np.testing.assert_array_equal(_best_in_sets(owners, values, 1), expected)


@given(
    st.lists(st.tuples(st.integers(1, 7), st.integers(0, 3)), min_size=0, max_size=25),
    st.integers(1, 4),
    st.booleans(),
)
@settings(max_examples=80, deadline=None)
def test_best_in_sets_keeps_what_the_ranking_ranks_below_keep(blocks, keep, shuffled):
    from factorydet_core.detection.box_quality import _best_in_sets
    from factorydet_core.detection.groups import rank_within_sets

    owners = np.repeat(np.arange(len(blocks)), [size for size, _ in blocks]).astype(np.int64)
    rng = np.random.default_rng(len(owners) + keep)
    if shuffled:  # sets not listed set after set: the general way
        owners = rng.permutation(owners)
    values = rng.integers(-2, 3, size=len(owners)).astype(np.float64) / 4  # ties are common
    expected = np.flatnonzero(rank_within_sets(owners, -values) < keep)
    np.testing.assert_array_equal(_best_in_sets(owners, values, keep), expected)


def test_sets_on_a_label_that_is_no_box_target_are_left_out(frames, prior):
    """A label whose box is the model's own (``box_targets`` False) gives the regressor no rows:
    the sets it overlaps most are left out, the others' rows are the same as without the mask."""
    from factorydet_core.boxes import box_iou_3d

    frame = frames[0]
    quality = BoxQuality(background_rate=0.0)
    learn = np.ones(len(frame.label_boxes), bool)
    learn[0] = False
    all_rows, all_targets = quality.training_rows([frame], prior, NUM_CLASSES)
    rows, targets = quality.training_rows([frame], prior, NUM_CLASSES, box_targets={frame.frame_index: learn})
    iou = box_iou_3d(frame.proposal_boxes, frame.label_boxes)
    best = [iou[m].max(axis=0) for m in frame.groups.members()]
    on_first = sum(b.argmax() == 0 and b.max() >= quality.min_overlap for b in best)
    assert on_first > 0
    assert 0 < len(rows) < len(all_rows)
    # What is kept is what the other labels' sets gave, row for row.
    kept = {(r.tobytes(), float(t)) for r, t in zip(rows, targets)}
    assert kept <= {(r.tobytes(), float(t)) for r, t in zip(all_rows, all_targets)}
    # All labels learnt from: the rows of no mask at all.
    same, same_targets = quality.training_rows(
        [frame], prior, NUM_CLASSES, box_targets={frame.frame_index: np.ones_like(learn)}
    )
    np.testing.assert_array_equal(same, all_rows)
    np.testing.assert_array_equal(same_targets, all_targets)


@pytest.mark.parametrize("anchored", [True, False])
def test_training_rows_are_each_sets_own_options_in_set_order(frames, prior, anchored):
    """Rows grown for many sets at once are, bit for bit and in the same order, what growing
    each taken set's options alone gives (``option_features``), with the same background sample."""
    from factorydet_core.boxes import box_iou_3d

    quality = BoxQuality(background_rate=0.3, anchored=anchored, seed=3)
    excluded = {frames[0].frame_index: {0, 1}}
    rows, targets = quality.training_rows(frames, prior, NUM_CLASSES, excluded=excluded)

    rng = np.random.default_rng(quality.seed)
    expected_rows, expected_targets = [], []
    kinds = set()
    for frame in frames:
        iou = box_iou_3d(frame.proposal_boxes, frame.label_boxes)
        for g, members in enumerate(frame.groups.members()):
            best = iou[members].max(axis=0)
            label = int(best.argmax())
            overlapping = best[label] >= quality.min_overlap
            take_background = rng.random() < quality.background_rate
            random_class = int(rng.integers(NUM_CLASSES))
            if (frame is frames[0] and g in (0, 1)) or not (overlapping or take_background):
                continue
            class_id = int(frame.label_class_ids[label]) if overlapping else random_class
            kinds.add(bool(overlapping))
            options, features = option_features(
                frame.proposal_boxes[members],
                class_id,
                frame.groups.descriptors[g],
                prior,
                NUM_CLASSES,
                anchored,
                None if frame.groups.anchor_mask is None else frame.groups.anchor_mask[members],
                quality.free_space_of(frame.groups),
            )
            same_class = frame.label_class_ids == class_id
            reference = frame.label_boxes[same_class] if overlapping else frame.label_boxes
            expected_rows.append(features)
            expected_targets.append(box_iou_3d(options, reference).max(axis=1))
    assert kinds == {True, False}  # sets on objects and background sets both taken
    np.testing.assert_array_equal(rows, np.concatenate(expected_rows))
    np.testing.assert_array_equal(targets, np.concatenate(expected_targets))
