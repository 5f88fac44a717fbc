"""A review order learned from the session's own verdicts (``LoopSettings.review_order`` "learned").

The queue's places come by the chance that one of their items is an object
(``world.group_by_place``), the predicted classes taking turns: the model's scores say which
false positives it is least sure are background, not which of them a reviewer will find to be an
unlabelled object. Among a queue's places at 50% unannotated, a place's points decide much of it
(a place of a few points is one the reviewer skips: nothing to see), its frames some more, and how
well its scores rank varies by predicted class. Every verdict a reviewer gives says which of these
places were worth their time: a logistic regression on each answered place's features, its
target whether the verdict gave a label ('object' or 'wrong box'), ranks the places still
pending. It is refitted as verdicts come (every ``REFIT_EVERY`` answered items), on the answers
of this run and of every earlier run of the session.

Until the answers hold ``MIN_ANSWERS`` places with at least ``MIN_EACH`` of each outcome, the
places keep the order the run's queue cut its negatives in (``LoopSettings.queue_order``).
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Sequence

import numpy as np

from factorydet_core.geometry import points_in_box
from factorydet_core.session.queue import unlearned_order
from factorydet_core.session.store import VERDICTS
from factorydet_core.session.world import group_by_place, place_chance
from factorydet_core.types import InputError, check_array

MIN_ANSWERS = 20
"""The fewest answered places a learned order is fitted on."""
MIN_EACH = 3
"""... with at least this many places of each outcome (useful and not)."""
REFIT_EVERY = 10
"""The learned order is refitted once every this many answered items of the run (in between it
stays as it was, so that the places after the shown one do not move with each verdict)."""
USEFUL_VERDICTS = ("object", "wrong_box")
"""The verdicts that give a label: what the learned order ranks places by the chance of."""
NUM_PLACE_FEATURES = 5
"""Features of a place before its predicted class's one-hot (``place_features``)."""


def place_features(
    items: Sequence[dict],
    places: Sequence[Sequence[int]],
    clouds: Sequence[np.ndarray],
    class_names: Sequence[str],
) -> np.ndarray:
    """What the learned order knows of each place, before anyone looks at it.

    Args:
        items: queue items (``SessionDB.review_queue``): dicts with ``frame_index``, ``box`` (7,)
            in that frame, ``score`` and ``predicted_class``.
        places: lists of positions in ``items``, each place's best item first
            (``world.group_by_place``).
        clouds: each frame's points (K_f, 3) in its vehicle frame (``world.WorldFrames.clouds``).
        class_names: the data set's object classes, the one-hot's columns (a predicted class not
            among them sets none).

    Returns:
        (P, NUM_PLACE_FEATURES + C) float64: the place's chance that one of its items is an
        object (``world.place_chance``), its best score, log(1 + the points in its best item's
        box), its frames, its items, and its best item's predicted class one-hot.
    """
    out = np.zeros((len(places), NUM_PLACE_FEATURES + len(class_names)), np.float64)
    column = {str(name): NUM_PLACE_FEATURES + k for k, name in enumerate(class_names)}
    for p, members in enumerate(places):
        if not len(members):
            raise InputError(f"place_features: place {p} has no items")
        place = [items[k] for k in members]
        scores = [float(q["score"]) for q in place]
        best = place[0]
        frame = int(best["frame_index"])
        if not 0 <= frame < len(clouds):
            raise InputError(
                f"place_features: item {best.get('id')} is of frame {frame}, not among {len(clouds)}"
            )
        box = np.asarray(best["box"], np.float64)
        out[p, 0] = place_chance(scores)
        out[p, 1] = min(max(max(scores), 0.0), 1.0)
        out[p, 2] = np.log1p(int(points_in_box(clouds[frame], box).sum()))
        out[p, 3] = len({int(q["frame_index"]) for q in place})
        out[p, 4] = len(place)
        k = column.get(str(best.get("predicted_class")))
        if k is not None:
            out[p, k] = 1.0
    return out


def place_answers(
    items: Sequence[dict], places: Sequence[Sequence[int]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which places a reviewer answered and which answers gave a label.

    A place is answered when any of its items has a verdict ('skip' included: the reviewer looked
    and found nothing to say, an answer the ranker learns from), useful when any has a verdict of
    ``USEFUL_VERDICTS``, skipped when every verdict it has is 'skip'.

    Returns:
        ``(answered_mask, useful_mask, skipped_mask)``, (P,) bool each.
    """
    answered = np.zeros(len(places), bool)
    useful = np.zeros(len(places), bool)
    skipped = np.zeros(len(places), bool)
    for p, members in enumerate(places):
        verdicts = [v for v in (items[k].get("verdict") for k in members) if v is not None]
        answered[p] = bool(verdicts)
        useful[p] = any(v in USEFUL_VERDICTS for v in verdicts)
        skipped[p] = bool(verdicts) and all(v == "skip" for v in verdicts)
    return answered, useful, skipped


def fit_stage(num_answered: int) -> int:
    """The stage of the learned order's fit when a run has ``num_answered`` answered items: the
    last multiple of ``REFIT_EVERY`` (it is refitted when the stage changes)."""
    return (max(int(num_answered), 0) // REFIT_EVERY) * REFIT_EVERY


class ReviewRanker:
    """A logistic regression from a place's features (``place_features``) to whether a reviewer's
    verdict on it gives a label, scikit-learn style.

    Args:
        regularization: the inverse L2 strength ``C`` on standardized features. 0.1: fitted on
            a round's 200 answers and ranking the next round's places (``bench hitl`` on the
            training factory at 50% unannotated, seeds 0-2), it put more useful places among the
            first 200 than 1 or 10.
        min_answers, min_each: the fewest answered places, and places of each outcome, it fits on;
            with fewer, ``fit`` leaves it unfitted (``fitted_`` False) and ``rank`` keeps the
            fallback order.
    """

    def __init__(
        self, regularization: float = 0.1, min_answers: int = MIN_ANSWERS, min_each: int = MIN_EACH
    ) -> None:
        self.regularization = regularization
        self.min_answers = min_answers
        self.min_each = min_each

    def fit(self, features: np.ndarray, useful_mask: np.ndarray) -> ReviewRanker:
        """Fit on answered places: ``features`` (A, F), ``useful_mask`` (A,) bool."""
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        check_array(features, (None, None), name="features", finite=True)
        useful_mask = np.asarray(useful_mask, bool).reshape(-1)
        if len(useful_mask) != len(features):
            raise InputError(f"ReviewRanker.fit: {len(features)} places but {len(useful_mask)} outcomes")
        if not self.regularization > 0:
            raise InputError(f"ReviewRanker: regularization must be > 0, got {self.regularization!r}")
        self.num_features_ = features.shape[1]
        num_useful = int(useful_mask.sum())
        self.fitted_ = (
            len(useful_mask) >= self.min_answers
            and min(num_useful, len(useful_mask) - num_useful) >= self.min_each
        )
        self.model_ = None
        if self.fitted_:
            self.model_ = make_pipeline(
                StandardScaler(), LogisticRegression(C=float(self.regularization), max_iter=5000)
            ).fit(features, useful_mask)
        return self

    def predict_useful(self, features: np.ndarray) -> np.ndarray:
        """(P,) float64: each place's probability that a verdict on it gives a label."""
        if not getattr(self, "fitted_", False):
            raise InputError("ReviewRanker: not fitted on enough answers yet (fitted_ is False)")
        check_array(features, (None, self.num_features_), name="features", finite=True)
        return self.model_.predict_proba(features)[:, 1].astype(np.float64)

    def rank(
        self, features: np.ndarray, answered_mask: np.ndarray, skipped_mask: np.ndarray | None = None
    ) -> np.ndarray:
        """The places in review order: the answered ones first, in their given order (the one a
        reviewer has worked through), then the pending ones likeliest useful first (ties, and an
        unfitted ranker, keep the given order), then the skipped ones (to look at again last).

        Args:
            features: (P, F) every place's features, in the fallback order.
            answered_mask: (P,) bool, the skipped places included.
            skipped_mask: (P,) bool, answered places whose answers are all 'skip' (``None``: none).

        Returns:
            (P,) int64 permutation of ``range(P)``.
        """
        answered_mask = np.asarray(answered_mask, bool).reshape(-1)
        if len(answered_mask) != len(features):
            raise InputError(f"ReviewRanker.rank: {len(features)} places but {len(answered_mask)} answers")
        skipped_mask = (
            np.zeros_like(answered_mask) if skipped_mask is None else np.asarray(skipped_mask, bool)
        )
        if skipped_mask.shape != answered_mask.shape:
            raise InputError(f"ReviewRanker.rank: {len(answered_mask)} places but {len(skipped_mask)} skips")
        pending = np.flatnonzero(~answered_mask)
        if getattr(self, "fitted_", False) and len(pending):
            chance = self.predict_useful(np.asarray(features)[pending])
            pending = pending[np.argsort(-chance, kind="stable")]
        first = np.flatnonzero(answered_mask & ~skipped_mask)
        return np.concatenate([first, pending, np.flatnonzero(answered_mask & skipped_mask)]).astype(np.int64)


@dataclasses.dataclass(frozen=True)
class RankedPlaces:
    """Places in the learned order, with what the panel says of them."""

    places: list
    """Lists of positions in the items, in review order."""
    useful: dict
    """By item id, the chance that a verdict on the item's place gives a label (empty while the
    ranker has too few answers)."""
    num_answers: int
    """How many answered places the ranker was fitted on."""


class LearnedOrder:
    """The learned review order of one session's queues, on one set of frames placed in a world
    frame: each place's features worked out once (a run's items never change), the ranker
    refitted when the run's answered items reach a new multiple of ``REFIT_EVERY``
    (``SessionDB.review_progress``: whatever part of the queue a caller shows). What the app's
    review panel and ``bench hitl``'s simulated reviewer both order places with; safe to share
    between threads (one fit at a time).

    Args:
        db: the session (``SessionDB``; read only).
        world: its frames in one world frame (``world.session_world``).
        class_names: the data set's object classes.
    """

    def __init__(self, db, world, class_names: Sequence[str]) -> None:
        self.db = db
        self.world = world
        self.class_names = tuple(str(name) for name in class_names)
        self._lock = threading.Lock()
        self._rows: dict = {}  # a place's item ids -> its features
        self._groups: dict = {}  # (run id, items) -> the run's whole queue by place
        self._fit: tuple | None = None  # ((run id, stage), ReviewRanker, answered places fitted on)

    def _features(self, items: Sequence[dict], places: Sequence[Sequence[int]]) -> np.ndarray:
        """``place_features`` of ``places``, each place's worked out once (by its items' ids: an
        item's frame, box and score never change)."""
        keys = [tuple(int(items[k]["id"]) for k in members) for members in places]
        missing = [p for p, key in enumerate(keys) if key not in self._rows]
        if missing:
            rows = place_features(items, [places[p] for p in missing], self.world.clouds, self.class_names)
            self._rows.update({keys[p]: row for p, row in zip(missing, rows)})
        width = NUM_PLACE_FEATURES + len(self.class_names)
        return np.array([self._rows[key] for key in keys], np.float64).reshape(-1, width)

    def _places(self, run_id: int, items: Sequence[dict]) -> list[list[int]]:
        """A whole run's queue by place, grouped once per run (its items never change)."""
        key = (int(run_id), len(items))
        cached = self._groups.get(key)
        if cached is None:
            cached = self._groups[key] = group_by_place(self.world, items)
        return cached

    def _answered_items(self, run_id: int) -> int:
        """Run ``run_id``'s items with a verdict, skips included (``SessionDB.review_progress``)."""
        progress = self.db.review_progress(run_id)
        return sum(progress.get(v, 0) for v in VERDICTS)

    def _ranker(self, run_id: int) -> tuple[ReviewRanker, int]:
        """The ranker fitted on the answered places of every run up to ``run_id`` (each run's
        whole queue grouped by place), and how many they are; refitted when run ``run_id``'s
        answered items reach a new ``fit_stage``."""
        key = (int(run_id), fit_stage(self._answered_items(run_id)))
        if self._fit is not None and self._fit[0] == key:
            return self._fit[1], self._fit[2]
        ranker = ReviewRanker()
        features, useful = [], []
        runs = [run["id"] for run in self.db.training_runs() if run["id"] <= run_id]
        # Counted in SQL: a run's whole queue is only read when there are answers to fit on.
        answered_items = {run: self._answered_items(run) for run in runs}
        if sum(answered_items.values()) < ranker.min_answers:
            runs = []  # fewer answered items than places to fit on: nothing to read
        for run in runs:
            if not answered_items[run]:
                continue
            items = self.db.review_queue(run)
            places = self._places(run, items)
            run_features = self._features(items, places)
            answered, run_useful, _ = place_answers(items, places)
            features.append(run_features[answered])
            useful.append(run_useful[answered])
        width = NUM_PLACE_FEATURES + len(self.class_names)
        ranker.fit(
            np.concatenate(features) if features else np.zeros((0, width)),
            np.concatenate(useful) if useful else np.zeros(0, bool),
        )
        self._fit = (key, ranker, sum(len(u) for u in useful))
        return ranker, self._fit[2]

    def ranked(self, run_id: int, items: Sequence[dict], places: Sequence[Sequence[int]]) -> RankedPlaces:
        """``places`` of run ``run_id``'s queue ``items`` (positions in ``items``, in the fallback
        order: ``world.group_by_place`` with the run's ``queue_order``; the items' verdicts as
        the caller last read them) in the learned order: the answered ones first as given, then
        the pending ones likeliest to give a label first (``ReviewRanker.rank``; as given while
        the ranker has too few answers), the skipped ones last."""
        places = [list(members) for members in places]
        with self._lock:
            features = self._features(items, places)
            ranker, num_answers = self._ranker(run_id)
        answered, _, skipped = place_answers(items, places)
        useful = {}
        if ranker.fitted_ and len(places):
            chance = ranker.predict_useful(features)
            useful = {int(items[k]["id"]): float(c) for members, c in zip(places, chance) for k in members}
        order = ranker.rank(features, answered, skipped).tolist()
        return RankedPlaces([places[k] for k in order], useful, num_answers)

    def order(self, run_id: int, items: Sequence[dict], places: Sequence[Sequence[int]]) -> list[list[int]]:
        """``ranked``'s places alone."""
        return self.ranked(run_id, items, places).places


def place_order(db, run_id: int) -> tuple[str, bool]:
    """How run ``run_id``'s places are grouped and ordered (``world.group_by_place``'s ``order``),
    and whether a ``LearnedOrder`` then orders them again: a learned review order groups in the
    order the run cut its negatives in (``SessionDB.cut_order``), any other in itself."""
    order, cut = db.orders(run_id)
    return unlearned_order(order, cut), order == "learned"


def review_places(
    db, world, items: Sequence[dict], run_id: int | None = None, learned: LearnedOrder | None = None
):
    """Run ``run_id``'s queue ``items`` (the latest run's by default) by place
    (``world.group_by_place``) in its review order (``SessionDB.review_order``; ``place_order``),
    a learned one by ``learned`` (a ``LearnedOrder`` of the session, made here when ``None``:
    keep one to refit only as verdicts come).

    Returns:
        Lists of positions in ``items``, each place's items by decreasing score.
    """
    if run_id is None:
        run_id = db.latest_run_id()
    order, relearn = place_order(db, run_id)
    places = group_by_place(world, items, order=order)
    if not relearn:
        return places
    if learned is None:
        learned = LearnedOrder(db, world, db.class_names)
    return learned.order(run_id, items, places)
