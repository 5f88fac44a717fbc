"""The order of mined negatives: which of them a mining round adds to the background (the first
``negatives_per_round``, ``LoopSettings.queue_order``) and in which order the review queue shows
them (``LoopSettings.review_order``: "auto" the same, "learned" by default).

By score, as the paper: the model's most confident false positives first. On a partially
annotated data set that order spends a reviewer's budget on the classes the first fit already
knows: a class it has barely learned (cones and pallets after 5 epochs) scores low everywhere, so
none of its false positives, among them its unlabelled objects, make the cut (``bench hitl`` at
50% unannotated: no cone among the first queue's 500 items). By class, the predicted classes take
turns: each class's most confident item, then each class's second, and so on.

The turns are those of the whole queue a run mined: an order worked out again on what is left
after some verdicts would move each class's remaining items up a turn, ahead of the one a
reviewer is looking at (``store.SessionDB.review_queue`` keeps every item at its place in the
whole queue; the app groups places on the whole queue before it filters them).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from factorydet_core.types import QUEUE_ORDERS, InputError


def review_order_of(settings: Mapping[str, object]) -> str | None:
    """The order a run's review queue follows, from its ``LoopSettings`` as stored (a mapping):
    ``review_order``, else the ``queue_order`` that cut its mined negatives (``None`` when the
    settings have neither: runs from before both were settings)."""
    order = settings.get("review_order") or settings.get("queue_order")
    return None if order is None else str(order)


def unlearned_order(review_order: str | None, cut_order: str | None) -> str | None:
    """The order a run's review queue lists its items in: its ``review_order``, except that a
    learned one (``session.review_rank``) orders places alone, over the queue in the order that cut
    the run's mined negatives (``cut_order``, ``LoopSettings.queue_order``). So by item, and for
    its places until it has verdicts enough to fit, a learned order is the cut's.

    The one statement of that rule: the store's queue, the app's places and ``bench hitl``'s
    record of what its reviewer saw all read it from here."""
    return cut_order if review_order == "learned" else review_order


def class_ranks(scores, classes: Sequence[str]) -> np.ndarray:
    """(M,) int64: each item's rank within its predicted class, by decreasing score (0: the
    class's most confident; ties keep the items' given order): its turn in the class order."""
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(classes) != len(scores):
        raise InputError(f"queue order: {len(scores)} scores but {len(classes)} classes")
    by_score = np.argsort(-scores, kind="stable")
    _, class_ids = np.unique(np.asarray(classes, dtype=object).astype(str), return_inverse=True)
    rank = np.empty(len(scores), np.int64)
    for class_id in np.unique(class_ids):
        members = by_score[class_ids[by_score] == class_id]  # this class's items, by score
        rank[members] = np.arange(len(members))
    return rank


def queue_order(scores, classes: Sequence[str], order: str = "score") -> np.ndarray:
    """Positions of the items in queue order.

    Args:
        scores: (M,) each item's score.
        classes: M predicted class names.
        order: "score": by decreasing score. "class": by each item's rank within its predicted
            class (``class_ranks``), then by decreasing score: the classes take turns, the most
            confident first within each turn.

    Returns:
        (M,) int64 permutation of ``range(M)``; ties keep the items' given order.
    """
    if order not in QUEUE_ORDERS:
        raise InputError(f"queue order must be one of {', '.join(QUEUE_ORDERS)}, got {order!r}")
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(classes) != len(scores):
        raise InputError(f"queue order: {len(scores)} scores but {len(classes)} classes")
    by_score = np.argsort(-scores, kind="stable")
    if order == "score" or not len(scores):
        return by_score.astype(np.int64)
    rank = class_ranks(scores, classes)
    position = np.empty(len(scores), np.int64)
    position[by_score] = np.arange(len(scores))
    return np.lexsort((position, rank)).astype(np.int64)
