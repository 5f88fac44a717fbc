import numpy as np
import pytest

from factorydet_core.session.review_rank import (
    MIN_ANSWERS,
    NUM_PLACE_FEATURES,
    REFIT_EVERY,
    LearnedOrder,
    ReviewRanker,
    fit_stage,
    place_answers,
    place_features,
    review_places,
)
from factorydet_core.session.world import WorldFrames, group_by_place
from factorydet_core.types import InputError
from tests.fakes import mined_item, queue_run

CLASSES = ("box", "cone", "pallet")


def _box(x: float, y: float = 0.0) -> list[float]:
    return [x, y, 0.5, 1.0, 1.0, 1.0, 0.0]


def _cloud(boxes, dense_mask, rng) -> np.ndarray:
    """60 points inside each dense box, one inside each other."""
    parts = [np.zeros((0, 3))]
    for box, dense in zip(boxes, dense_mask):
        count = 60 if dense else 1
        parts.append(np.asarray(box[:3]) + rng.uniform(-0.4, 0.4, (count, 3)))
    return np.concatenate(parts).astype(np.float32)


def test_a_places_features_are_its_chance_best_score_points_frames_items_and_class():
    items = [
        {"id": 1, "frame_index": 0, "box": _box(0.0), "score": 0.5, "predicted_class": "cone"},
        {"id": 2, "frame_index": 1, "box": _box(0.0), "score": 0.5, "predicted_class": "box"},
        {"id": 3, "frame_index": 1, "box": _box(5.0), "score": 0.2, "predicted_class": "person"},
    ]
    rng = np.random.default_rng(0)
    clouds = (_cloud([_box(0.0)], [True], rng), np.zeros((0, 3), np.float32))
    features = place_features(items, [[0, 1], [2]], clouds, CLASSES)
    assert features.shape == (2, NUM_PLACE_FEATURES + len(CLASSES))
    np.testing.assert_allclose(features[0, :5], [0.75, 0.5, np.log1p(60), 2, 2])
    assert features[0, 5:].tolist() == [0.0, 1.0, 0.0]  # its best item's class: cone
    np.testing.assert_allclose(features[1], [0.2, 0.2, 0.0, 1, 1, 0, 0, 0])  # a class not listed
    with pytest.raises(InputError, match="not among 2"):
        place_features([{**items[0], "frame_index": 4}], [[0]], clouds, CLASSES)
    with pytest.raises(InputError, match="place 0 has no items"):
        place_features(items, [[]], clouds, CLASSES)


def test_answers_are_any_verdict_useful_ones_give_a_label_and_a_skip_alone_is_a_skip():
    verdicts = [None, "skip", "background", "object", "wrong_box", "skip", None]
    items = [{"verdict": v} for v in verdicts]
    answered, useful, skipped = place_answers(items, [[0], [1], [2], [3], [4], [5, 4], [6, 0]])
    assert answered.tolist() == [False, True, True, True, True, True, False]
    assert useful.tolist() == [False, False, False, True, True, True, False]
    assert skipped.tolist() == [False, True, False, False, False, False, False]


def test_the_ranker_refits_every_few_answers_and_needs_both_outcomes():
    assert [fit_stage(n) for n in (0, REFIT_EVERY - 1, REFIT_EVERY, 2 * REFIT_EVERY + 3)] == [
        0, 0, REFIT_EVERY, 2 * REFIT_EVERY
    ]  # fmt: skip
    rng = np.random.default_rng(1)
    features = rng.normal(size=(MIN_ANSWERS, 3))
    assert not ReviewRanker().fit(features, np.ones(MIN_ANSWERS, bool)).fitted_  # one outcome
    assert not ReviewRanker().fit(features[:-1], np.arange(MIN_ANSWERS - 1) % 2 == 0).fitted_  # too few
    unfitted = ReviewRanker().fit(features, np.arange(MIN_ANSWERS) < 2)
    answered = np.array([False, True, False, True] + [False] * (MIN_ANSWERS - 4))
    skipped = np.zeros(MIN_ANSWERS, bool)
    skipped[1] = True
    # Unfitted, the given order stays, the answered first and the skipped last.
    order = unfitted.rank(features, answered, skipped).tolist()
    assert order == [3, 0, 2, *range(4, MIN_ANSWERS), 1]
    with pytest.raises(InputError, match="not fitted"):
        unfitted.predict_useful(features)
    with pytest.raises(InputError, match="3 places but 2 outcomes"):
        ReviewRanker().fit(features[:3], [True, False])
    with pytest.raises(InputError, match="regularization"):
        ReviewRanker(regularization=0.0).fit(features, np.arange(MIN_ANSWERS) % 2 == 0)


def test_fitted_the_pending_places_come_likeliest_useful_first():
    rng = np.random.default_rng(2)
    features = rng.normal(size=(60, 1))
    useful = features[:, 0] + rng.normal(0.0, 0.3, 60) > 0
    ranker = ReviewRanker().fit(features[:40], useful[:40])
    assert ranker.fitted_
    order = ranker.rank(features, np.arange(60) < 40)
    assert order[:40].tolist() == list(range(40))  # answered first, as given
    pending = order[40:]
    assert np.all(np.diff(features[pending, 0]) <= 0)  # one feature: its order exactly


@pytest.fixture
def world(dataset):
    """The small data set's frames, unmoved, each frame's points dense in some boxes."""
    rng = np.random.default_rng(3)
    first = [_box(3.0 * k) for k in range(30)]
    second = [_box(3.0 * k, 20.0) for k in range(20)]
    clouds = [
        _cloud(first, np.arange(30) % 2 == 0, rng),
        _cloud(second, np.arange(20) % 2 == 1, rng),
        np.zeros((0, 3), np.float32),
    ]
    frames = dataset.num_frames
    return WorldFrames(np.stack([np.eye(4)] * frames), np.ones(frames), tuple(clouds[:frames])), first, second


def test_a_learned_order_puts_the_places_earlier_verdicts_found_useful_first(db, world, tiny_model_path):
    world, first, second = world
    # Run 1: the dense places were objects with a wrong box, the sparse ones background; their
    # scores say nothing of it.
    items = [mined_item(0, g, box, 0.3 + 0.02 * (g % 5)) for g, box in enumerate(first)]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": {"queue_order": "score"}})
    for item in db.review_queue():
        dense = int(round(item["box"][0] / 3.0)) % 2 == 0
        db.review([item["id"]], "wrong_box" if dense else "background", "ann")
    # Run 2, learned: its sparse places score highest, the cut's order would show them first.
    scores = [0.9 if g % 2 == 0 else 0.4 for g in range(len(second))]
    items = [mined_item(1, g, box, s, "cone") for g, (box, s) in enumerate(zip(second, scores))]
    run = db.save_training_run(
        queue_run(tiny_model_path, [items]),
        "small",
        {"settings": {"queue_order": "score", "review_order": "learned"}},
    )
    assert db.review_order(run) == "learned" and db.cut_order(run) == "score"
    queue = db.review_queue(run)
    assert [q["score"] for q in queue[:2]] == [0.9, 0.9]  # by item: the cut's order
    places = review_places(db, world, queue, run)
    assert sorted(k for place in places for k in place) == list(range(len(queue)))
    shown = [queue[place[0]] for place in places]
    dense = [int(round(q["box"][0] / 3.0)) % 2 == 1 for q in shown]
    assert all(dense[:10]) and not any(dense[10:])
    # An answered place goes first, a skipped one last, the rest keep the learned order.
    learned = LearnedOrder(db, world, db.class_names)
    db.review([shown[3]["id"]], "background", "ann")
    db.review([shown[0]["id"]], "skip", "ann")
    queue = db.review_queue(run)
    again = [queue[p[0]]["id"] for p in learned.order(run, queue, group_by_place(world, queue))]
    ids = [q["id"] for q in shown]
    assert again == [ids[3], ids[1], ids[2], *ids[4:], ids[0]]


def test_without_enough_verdicts_the_learned_order_is_the_cuts(db, world, tiny_model_path):
    world, _, second = world
    items = [
        mined_item(1, g, box, 0.9 - 0.01 * g, "cone" if g % 2 else "box") for g, box in enumerate(second)
    ]
    settings = {"queue_order": "class", "review_order": "learned"}
    run = db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": settings})
    queue = db.review_queue(run)
    assert review_places(db, world, queue, run) == group_by_place(world, queue, order="class")
    # Fewer answered items than the places a fit needs: no run's queue is read to refit.
    reads = []

    class Counting:
        def __getattr__(self, name):
            return getattr(db, name)

        def review_queue(self, *args, **kwargs):
            reads.append(args)
            return db.review_queue(*args, **kwargs)

    db.review([q["id"] for q in queue[: MIN_ANSWERS - 1]], "background", "ann")
    learned = LearnedOrder(Counting(), world, db.class_names)
    queue = db.review_queue(run)
    learned.ranked(run, queue, group_by_place(world, queue, order="class"))
    assert reads == []
    db.review([queue[MIN_ANSWERS - 1]["id"]], "background", "ann")  # a new refit stage, enough items
    queue = db.review_queue(run)
    learned.ranked(run, queue, group_by_place(world, queue, order="class"))
    assert reads == [(run,)]


def test_bench_hitls_reviewer_answers_the_places_in_the_learned_order(db, dataset, world, tiny_model_path):
    from factorydet_core.evaluation.hitl import simulated_review

    world, first, second = world
    items = [mined_item(0, g, box, 0.3) for g, box in enumerate(first)]
    db.save_training_run(queue_run(tiny_model_path, [items]), "small", {})
    for item in db.review_queue():
        dense = int(round(item["box"][0] / 3.0)) % 2 == 0
        db.review([item["id"]], "wrong_box" if dense else "background", "ann")
    items = [mined_item(1, g, box, 0.9 if g % 2 == 0 else 0.4) for g, box in enumerate(second)]
    settings = {"queue_order": "score", "review_order": "learned"}
    run = db.save_training_run(queue_run(tiny_model_path, [items]), "small", {"settings": settings})
    counts = simulated_review(db, dataset, budget=10, world=world)
    assert sum(counts[v] for v in ("background", "object", "wrong_box", "skip")) == 10
    answered = [q for q in db.review_queue(run) if q["verdict"] is not None]
    assert len(answered) == 10 and all(int(round(q["box"][0] / 3.0)) % 2 == 1 for q in answered)
