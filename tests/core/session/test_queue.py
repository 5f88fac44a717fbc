import collections

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.session.queue import queue_order, unlearned_order
from factorydet_core.types import InputError


def test_by_score_the_most_confident_first_and_ties_keep_their_order():
    order = queue_order([0.2, 0.9, 0.5, 0.9], ["box", "box", "cone", "cone"], "score")
    assert order.tolist() == [1, 3, 2, 0]


def test_by_class_the_classes_take_turns_most_confident_first_within_a_turn():
    scores = [0.95, 0.9, 0.85, 0.8, 0.2, 0.1, 0.3]
    classes = ["box", "box", "box", "box", "cone", "cone", "pallet"]
    order = queue_order(scores, classes, "class")
    # Turn 1: box 0.95, pallet 0.3, cone 0.2; turn 2: box 0.9, cone 0.1; then the boxes left.
    assert order.tolist() == [0, 6, 4, 1, 5, 2, 3]


@pytest.mark.parametrize(
    ("review_order", "cut_order", "expected"),
    [("learned", "class", "class"), ("learned", "score", "score"), ("learned", None, None),
     ("score", "class", "score"), ("class", "score", "class"), (None, "class", None)],
)  # fmt: skip
def test_a_learned_order_lists_items_in_the_cuts_order_another_in_its_own(review_order, cut_order, expected):
    assert unlearned_order(review_order, cut_order) == expected


def test_a_bad_order_or_mismatched_lengths_are_refused():
    with pytest.raises(InputError, match="queue order must be one of score, class"):
        queue_order([0.5], ["box"], "random")
    with pytest.raises(InputError, match="2 scores but 1 classes"):
        queue_order([0.5, 0.4], ["box"], "class")
    assert queue_order([], [], "class").tolist() == []


@given(
    st.lists(
        st.tuples(st.floats(0.0, 1.0, allow_nan=False), st.sampled_from(["box", "cone", "pallet", "truck"])),
        max_size=40,
    )
)
@settings(max_examples=60, deadline=None)
def test_every_prefix_of_the_class_order_is_as_even_over_classes_as_the_items_allow(items):
    scores = [s for s, _ in items]
    classes = [c for _, c in items]
    order = queue_order(scores, classes, "class").tolist()
    assert sorted(order) == list(range(len(items)))
    totals = collections.Counter(classes)
    for k in range(1, len(order) + 1):
        counts = collections.Counter(classes[i] for i in order[:k])
        # A class with items left never trails another class by more than one item.
        open_classes = [c for c in totals if counts[c] < totals[c]]
        if open_classes:
            assert max(counts.values()) - min(counts[c] for c in open_classes) <= 1
    for name in totals:  # within a class, by decreasing score
        own = [scores[i] for i in order if classes[i] == name]
        assert own == sorted(own, reverse=True)
    # The same items in score order, as a permutation too.
    by_score = queue_order(scores, classes, "score")
    assert np.all(np.diff(np.asarray(scores)[by_score]) <= 0)
