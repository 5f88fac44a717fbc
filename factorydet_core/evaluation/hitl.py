"""The simulated reviewer and the review-loop benchmark (``factorydet bench hitl``): it answers
the review queue from the simulator's hidden truth, so only benchmarks and tests may use it."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.evaluation.evaluate import measure
from factorydet_core.evaluation.quality import HELDOUT_SCRATCH, check_heldout, heldout_set
from factorydet_core.evaluation.records import (
    changed_fields,
    check_same_plan,
    library_version,
    library_versions,
    machine_info,
    runs_of_this_library,
    spread_frames,
)
from factorydet_core.io.dataset import Dataset, annotation_min_points, open_dataset
from factorydet_core.session.queue import review_order_of, unlearned_order
from factorydet_core.session.store import SessionDB, on_labelled_object, open_session
from factorydet_core.sim.truth import read_frame_truth
from factorydet_core.training.loop import Proposer, cached_proposals, session_pseudo_labels, train_session
from factorydet_core.training.mining import collect_proposals
from factorydet_core.training.settings import BEFORE_THEY_EXISTED, LoopSettings, folds_continue
from factorydet_core.types import (
    InputError,
)

BLIND_SAFE_SETTINGS: tuple[str, ...] = (
    "hold_places",
    "recalibrate_background",
    "recalibrate_by_class",
    "pseudo_label_confident",
    "carry_pseudo_labels",
)
"""``LoopSettings`` fields that shape the runs of the detectors that hold (``holds``: ``blind_safe``
and ``reviewed_safe_K``) alone, with their hold score: the other detectors run without them, so
their run plans leave them out (``_run_plan``)."""


def holds(variant: str) -> bool:
    """Whether ``bench hitl``'s detector ``variant`` holds its confident mined negatives out of the
    background until reviewed (and recalibrates with ``BLIND_SAFE_SETTINGS``): ``blind_safe``, which
    nobody reviews, and ``reviewed_safe_K``, whose reviewer answers K entries a round and leaves the
    rest held."""
    return variant == "blind_safe" or variant.startswith("reviewed_safe_")


VERDICTS: tuple[str, ...] = ("background", "object", "wrong_box", "skip")
REVIEW_COUNTS: tuple[str, ...] = (*VERDICTS, "boxes_drawn", "hidden", "best_view")
"""What ``simulated_review`` counts: its verdicts, the boxes it drew, the items the panel's filter
hid, and the places it answered from where the object is seen best (``best_view``)."""


OPTIONAL_RUN_FIGURES: tuple[str, ...] = (
    "per_class_precision",
    "in_factory",
    "fitted_frame_thresholds",
    "other_objective_thresholds",
    "fitted_frame_other_objective_thresholds",
)
"""A ``bench hitl`` run's figures that runs of older records lack (each was kept from some version
on): the table shows a figure's row only when every run has it (``hitl_markdown`` names the rows
it left out)."""


def truth_verdict(
    dataset: Dataset,
    item: dict,
    positive_iou: float = 0.6,
    object_overlap: float = 0.1,
    min_points: int | None = None,
) -> tuple[str, str | None, np.ndarray | None]:
    """What a careful person would answer for a mined negative, read from the simulator's truth,
    under the data set's annotation policy (objects of at least ``min_points`` points, by default
    ``annotation_min_points``).

    Returns:
        ``(verdict, class_name, true_box)``: 'object' with the class when the mined box matches an
        object of the policy at ``positive_iou``; 'wrong_box' with the object's class and true box
        when it overlaps one by at least ``object_overlap`` IoU; 'skip' when it overlaps only real
        objects too sparse for the policy (neither a label nor background: a person labelling to
        the policy leaves them as the annotations and the truth references do); else 'background'.
    """

    if min_points is None:
        min_points = annotation_min_points(dataset)
    truth = read_frame_truth(dataset.path, item["frame_index"])
    real = truth.instance_class_ids >= 0
    if not real.any():
        return "background", None, None
    iou = box_iou_3d(np.asarray([item["box"]], np.float64), truth.instance_boxes[real])[0]
    dense = truth.instance_num_points[real] >= min_points
    if dense.any():
        best = int(np.flatnonzero(dense)[iou[dense].argmax()])
        name = dataset.class_names[int(truth.instance_class_ids[real][best])]
        box = truth.instance_boxes[real][best]
        if iou[best] >= positive_iou:
            return "object", name, box
        if iou[best] >= object_overlap:
            return "wrong_box", name, box
    if (iou[~dense] >= object_overlap).any():
        return "skip", None, None
    return "background", None, None


def simulated_review(
    db: SessionDB,
    dataset: Dataset,
    budget: int,
    author: str = "simulated-reviewer",
    positive_iou: float = 0.6,
    max_label_iou: float | None = None,
    world=None,
    best_view: bool = False,
) -> dict:
    """Answer the top ``budget`` pending items of the latest run's queue from the truth
    (``truth_verdict``), one ``SessionDB.review`` call per item, as the review panel's buttons make
    them. A 'wrong box' is followed by the box a person would draw (``SessionDB.add_label``). An
    item on an object the session already labels (at ``positive_iou``, for instance one drawn for an
    earlier item) is a part, a duplicate or a misplaced box of a labelled object: a negative, so
    'background' when its box is off the object and 'skip' when it matches it (there is nothing to
    add), as the full labels of ``bench hitl`` would mine and keep it.

    Args:
        max_label_iou: review the queue with the panel's "hide items on labelled objects" filter
            (``SessionDB.review_queue``): an item whose box overlaps a current label at this IoU
            or more, checked when its turn comes (the panel's queue follows the labels the
            reviewer adds), is passed over and does not count against the budget.
        world: the frames placed in one world frame (``world.session_world``): review as the
            app does by default, one entry per place (``world.group_by_place``, most likely an
            object first), the verdict on its best item answering all its items, an object (or
            a box drawn for a wrong one) labelled in every frame that shows it (label once).
            ``budget`` then counts places.
        best_view: with ``world``, a place whose item shows too few points for the policy
            ('skip') is looked at where the frames see it best (``world.best_view``, the review
            panel's *Look where it is seen best*): an object of the policy there, not labelled
            yet and of a class that stands still, is labelled as the panel would (Object with the
            item's box, or Wrong box and the object's box drawn there), in every frame that
            shows it.

    Returns:
        Counts (``REVIEW_COUNTS``) per verdict, of boxes drawn, of items ``hidden`` by the filter
        and of places answered from their best view (``best_view``).
    """
    counts = dict.fromkeys(REVIEW_COUNTS, 0)
    answered = 0
    queue = db.review_queue(pending_only=True)
    if world is not None:
        return _review_places(
            db, dataset, budget, author, positive_iou, max_label_iou, world, queue, counts, best_view
        )
    for item in queue:
        if answered == budget:
            break
        if max_label_iou is not None and on_labelled_object(db.label_overlap([item])[0], max_label_iou):
            counts["hidden"] += 1
            continue
        verdict, class_name, true_box = _truth_answer(db, dataset, item, positive_iou)
        db.review(
            [item["id"]],
            verdict,
            author,
            class_name=class_name if verdict == "object" else None,
            expected={item["id"]: item["verdict"]},
        )
        counts[verdict] += 1
        answered += 1
        if verdict == "wrong_box":
            db.add_label(item["frame_index"], true_box, class_name, author)
            counts["boxes_drawn"] += 1
    return counts


def _unannotated_truth(dataset: Dataset, index: int, min_points: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The real objects of frame ``index`` the data set left unannotated, with at least
    ``min_points`` points (``None``: ``annotation_min_points``): (boxes (M, 7), class_ids (M,))
    from the simulator's truth."""

    if min_points is None:
        min_points = annotation_min_points(dataset)
    truth = read_frame_truth(dataset.path, index)
    missing = (
        (truth.instance_class_ids >= 0) & ~truth.annotated_mask & (truth.instance_num_points >= min_points)
    )
    return truth.instance_boxes[missing], truth.instance_class_ids[missing]


def add_truth_labels(
    db: SessionDB, dataset: Dataset, frame_indices: Sequence[int], min_points: int | None = None
) -> int:
    """Label every real object the data set left unannotated (at least ``min_points`` points, by
    default the annotation policy's) from the simulator's truth: the fully labelled upper bound of
    ``bench hitl``.

    Returns:
        How many labels were added.
    """
    added = 0
    for index in frame_indices:
        boxes, class_ids = _unannotated_truth(dataset, index, min_points)
        for box, class_id in zip(boxes, class_ids):
            db.add_label(index, box, dataset.class_names[int(class_id)], "truth", origin="import")
            added += 1
    return added


def unannotated_coverage_by_class(
    db: SessionDB,
    dataset: Dataset,
    frame_indices: Sequence[int],
    min_points: int | None = None,
    iou_threshold: float = 0.6,
) -> dict[str, tuple[int, int]]:
    """Per class, how many of the objects the data set left unannotated (``add_truth_labels``'
    set) the session now labels with their class at ``iou_threshold``: what the reviews gave back.

    Returns:
        ``{class_name: (covered, total)}`` for every class of the data set.
    """
    counts = {name: [0, 0] for name in dataset.class_names}
    for index in frame_indices:
        boxes, class_ids = _unannotated_truth(dataset, index, min_points)
        if not len(boxes):
            continue
        truth_names = np.asarray(dataset.class_names)[class_ids]
        labels, label_class_ids, _ = db.frame_boxes(index)
        covered_mask = np.zeros(len(boxes), bool)
        if len(labels):
            label_names = np.asarray(db.class_names)[label_class_ids]
            same_class = truth_names[:, None] == label_names[None, :]
            iou = np.where(same_class, box_iou_3d(boxes, labels), 0.0)
            covered_mask = iou.max(axis=1) >= iou_threshold
        for name, covered in zip(truth_names, covered_mask):
            counts[str(name)][0] += int(covered)
            counts[str(name)][1] += 1
    return {name: (covered, total) for name, (covered, total) in counts.items()}


PSEUDO_LABEL_KINDS: tuple[str, ...] = ("object", "loose_box", "other_class", "skip", "background")
"""How the truth judges a pseudo-label (``pseudo_label_truth``): an object of the predicted class
at the positive IoU; that class's object under a looser box; another class's object; an object
too sparse for the annotation policy; no object."""


def pseudo_label_truth(db: SessionDB, dataset: Dataset, pseudo_labels: dict) -> dict[str, dict[str, int]]:
    """Pseudo-labels as the simulator's truth judges them (``truth_verdict``).

    Args:
        pseudo_labels: frame index -> ``(patch_sets, boxes, class_ids)``, as
            ``training.loop.session_pseudo_labels`` gives the pseudo-labels a session trains with
            (a carried one has no point set: ``()``).

    Returns:
        ``{"all": counts, "carried": counts}``: how many of each ``PSEUDO_LABEL_KINDS``, of all
        of them and of those carried from another frame.
    """
    counts = {"all": dict.fromkeys(PSEUDO_LABEL_KINDS, 0), "carried": dict.fromkeys(PSEUDO_LABEL_KINDS, 0)}
    for index, (sets, boxes, class_ids) in pseudo_labels.items():
        for patch_set, box, class_id in zip(sets, boxes, class_ids):
            verdict, name, _ = truth_verdict(dataset, {"frame_index": index, "box": np.asarray(box).tolist()})
            if verdict in ("object", "wrong_box") and name != db.class_names[int(class_id)]:
                verdict = "other_class"
            kind = {"wrong_box": "loose_box"}.get(verdict, verdict)
            counts["all"][kind] += 1
            if not patch_set:
                counts["carried"][kind] += 1
    return counts


def unannotated_coverage(
    db: SessionDB,
    dataset: Dataset,
    frame_indices: Sequence[int],
    min_points: int | None = None,
    iou_threshold: float = 0.6,
) -> tuple[int, int]:
    """``unannotated_coverage_by_class`` over all classes.

    Returns:
        ``(covered, total)``.
    """
    return _coverage_totals(
        unannotated_coverage_by_class(db, dataset, frame_indices, min_points, iou_threshold)
    )


def _coverage_totals(by_class: dict[str, tuple[int, int]]) -> tuple[int, int]:
    """``(covered, total)`` over the classes of ``unannotated_coverage_by_class``' answer."""
    return sum(c for c, _ in by_class.values()), sum(t for _, t in by_class.values())


def _truth_answer(db: SessionDB, dataset: Dataset, item: dict, positive_iou: float, truth=None):
    """``truth_verdict`` as the reviewer answers it, knowing the session's labels: an object that
    is labelled already makes the item a negative ('skip' on its box, 'background' off it).
    ``truth``: the item's ``truth_verdict`` when read already."""
    verdict, class_name, true_box = truth or truth_verdict(dataset, item, positive_iou)
    if true_box is not None:
        boxes, _, _ = db.frame_boxes(item["frame_index"])
        if len(boxes) and box_iou_3d(true_box[None], boxes).max() >= positive_iou:
            verdict, class_name = ("skip" if verdict == "object" else "background"), None
    return verdict, class_name, true_box


def _review_places(
    db, dataset, budget, author, positive_iou, max_label_iou, world, queue, counts, best_view=False
) -> dict:
    """``simulated_review`` by place, as the app's review panel shows the queue by default. With
    the review order "learned" (``session.review_rank``), the places still pending are ordered
    again after each verdict, refitted every ``review_rank.REFIT_EVERY`` items answered, as the
    panel orders them."""
    from factorydet_core.session.review_rank import LearnedOrder, place_order
    from factorydet_core.session.world import MOVING_CLASSES, group_by_place, place_box
    from factorydet_core.session.world import best_view as world_best_view

    def placer(class_name):
        if class_name is None or class_name in MOVING_CLASSES:
            return None
        return lambda frame_index, box: place_box(world, frame_index, box).for_store()

    run_id = db.latest_run_id()
    order, relearn = place_order(db, run_id)
    places = base = group_by_place(world, queue, order=order)
    learned = LearnedOrder(db, world, db.class_names) if relearn else None
    if learned is not None:
        places = learned.order(run_id, queue, base)
    answered = 0
    done: set[int] = set()  # items answered with an earlier place (the queue is read once)
    passed: set[int] = set()  # places looked at: answered, or passed over by the filter
    while answered < budget:
        members = next((m for m in places if m[0] not in passed), None)
        if members is None:
            break
        passed.add(members[0])
        items = [queue[k] for k in members if queue[k]["id"] not in done]
        if not items:
            continue
        item = items[0]  # what the panel shows of the place: its best item
        if max_label_iou is not None and on_labelled_object(db.label_overlap([item])[0], max_label_iou):
            counts["hidden"] += 1
            continue
        truth = truth_verdict(dataset, item, positive_iou)
        verdict, class_name, true_box = _truth_answer(db, dataset, item, positive_iou, truth)
        drawn_in = item["frame_index"]
        if best_view and truth[0] == "skip":
            # Too few points here for the policy (not a repeat of a label here): the panel offers
            # the frame that sees the place best.
            view = world_best_view(world, item["frame_index"], item["box"])
            if view is not None:
                there = {"frame_index": view.frame_index, "box": view.box}
                answer = _truth_answer(db, dataset, there, positive_iou)
                # An object of the policy there, not labelled yet, that stands still: a moving one's
                # box carried by the frames' poses lands where it no longer is.
                if answer[0] in ("object", "wrong_box") and answer[1] not in MOVING_CLASSES:
                    (verdict, class_name, true_box), drawn_in = answer, view.frame_index
                    counts["best_view"] += 1
        # Pending when the queue was read, and only this reviewer answers: their verdicts are
        # still the ones read (reading the queue again per place recomputed every overlap).
        ids = [q["id"] for q in items]
        db.review(
            ids,
            verdict,
            author,
            class_name=class_name if verdict == "object" else None,
            expected={q["id"]: q["verdict"] for q in items},
            place=placer(class_name) if verdict == "object" else None,
            one_object=len(ids) > 1,
        )
        done.update(ids)
        counts[verdict] += 1
        answered += 1
        if verdict == "wrong_box":
            place = placer(class_name)
            if place is None:
                db.add_label(drawn_in, true_box, class_name, author)
            else:  # label once: the drawn box reaches every frame that shows the object
                _draw_object(db, author, drawn_in, class_name, *place(drawn_in, tuple(true_box)))
            counts["boxes_drawn"] += 1
        if learned is not None:
            # The panel reads the verdicts given; here the queue read once stands for it. Ordered
            # again after each verdict, as the panel's queue (refitted every few).
            for k in members:
                queue[k] = {**queue[k], "verdict": verdict}
            places = learned.order(run_id, queue, base)
    return counts


def _draw_object(db: SessionDB, author: str, frame_index: int, class_name: str, boxes: dict, show_in) -> None:
    """A box drawn in ``frame_index`` as the app's label once adds it: one object in every frame
    of ``show_in`` (``boxes`` by frame), except where it is labelled already
    (``world.not_labelled_yet``, the app's screen)."""
    from factorydet_core.session.world import not_labelled_yet

    items = [(f, boxes[f], class_name) for f in sorted(set(show_in) | {int(frame_index)})]
    db.add_labels(
        items,
        author,
        "user",
        as_object=True,
        screen=lambda current: not_labelled_yet(items, current, keep_frame=int(frame_index)),
    )


def queue_reach(
    db: SessionDB,
    dataset: Dataset,
    frame_indices: Sequence[int],
    run_id: int | None = None,
    object_overlap: float = 0.1,
    min_points: int | None = None,
    top: int | None = None,
    world=None,
) -> set[tuple[int, int]]:
    """The objects the data set left unannotated (``add_truth_labels``' set) that some item of a
    run's review queue (the latest by default) overlaps at ``object_overlap`` IoU: the ones a
    reviewer answering the whole queue could label ('object' or 'wrong box'). Reviews cannot give
    back more than this, whatever their budget. ``top``: only the first ``top`` entries of the
    queue, items, or with ``world`` places (``world.group_by_place``, every item of each): what a
    reviewer answering ``top`` entries can reach.

    Returns:
        ``(frame_index, k)`` pairs, ``k`` indexing the frame's unannotated objects in
        ``_unannotated_truth``'s order.
    """
    queue = db.review_queue(run_id)
    if world is not None:
        from factorydet_core.session.review_rank import review_places

        places = review_places(db, world, queue, run_id)[:top]
        queue = [queue[k] for place in places for k in place]
    elif top is not None:
        queue = queue[:top]
    by_frame: dict[int, list[list[float]]] = {}
    for item in queue:
        by_frame.setdefault(int(item["frame_index"]), []).append(item["box"])
    reached = set()
    for index in frame_indices:
        boxes, _ = _unannotated_truth(dataset, index, min_points)
        items = by_frame.get(int(index))
        if not len(boxes) or not items:
            continue
        iou = box_iou_3d(boxes, np.asarray(items, np.float64).reshape(-1, 7))
        reached.update((int(index), int(k)) for k in np.flatnonzero(iou.max(axis=1) >= object_overlap))
    return reached


def estimated_reach_share(db: SessionDB, top: int, world=None) -> float | None:
    """The share of the objects a run's review queue holds by the model's scores that its first
    ``top`` entries hold (``world.expected_reach``; entries are places with ``world``, as the
    review panel shows them, else items); ``None`` for an empty queue."""
    from factorydet_core.session.review_rank import review_places
    from factorydet_core.session.world import expected_reach, place_chance

    queue = db.review_queue()
    if world is not None:
        places = review_places(db, world, queue)
        chances = [place_chance([queue[k]["score"] for k in place]) for place in places]
    else:
        chances = [item["score"] for item in queue]
    first, total = expected_reach(chances, top)
    return first / total if total > 0 else None


def _mean_of(values) -> float | None:
    """The mean of ``values``, rounded, ``None`` left out (a class without references, a round
    without a reach); ``None`` when nothing is left."""
    given = [v for v in values if v is not None]
    return round(float(np.mean(given)), 4) if given else None


def bench_hitl(
    data: str | os.PathLike,
    *,
    budgets: Sequence[int] = (50, 200),
    rounds: int = 2,
    settings=None,
    seeds: Sequence[int] = (0,),
    max_label_iou: float | None = None,
    max_train_frames: int | None = None,
    max_test_frames: int | None = None,
    calibrate: bool = True,
    workdir: str | os.PathLike | None = None,
    command: str = "",
    progress=None,
    review_by: str = "item",
    variants: Sequence[str] | None = None,
    propose: Proposer = collect_proposals,
    earlier: dict | None = None,
    on_partial: Callable[[dict], None] | None = None,
    heldout_seeds: Sequence[int] = (),
    heldout_frames: int = 12,
    heldout_scratch: str | os.PathLike = HELDOUT_SCRATCH,
    best_view: bool = False,
    resume_other_library: bool = False,
    also: Mapping[str, dict] | None = None,
) -> dict:
    """Does reviewing mined negatives make the detector better? Several detectors, the same budget
    of mining rounds, F-score at IoU 0.6 against the full truth on the test frames:

    (a) ``blind``: mining on the partial labels, as the paper;
    (b) ``blind_safe``: the same, holding the mined negatives the model scores at its operating
        score or more (``LoopSettings.hold_confident``) out of the background, with the settings
        of ``BLIND_SAFE_SETTINGS``; nobody reviews them;
    (c) ``reviewed_K``: blind mining with a simulated reviewer answering the top K items of each
        round's queue from the truth, through ``SessionDB.review`` (the review panel's call);
    (d) ``full``: mining on full labels (every object of the annotation policy labelled,
        ``hitl.add_truth_labels``), the upper bound;
    (e) ``reviewed_safe_K``, asked for by name: the reviewer of (c) on top of (b): what the
        reviewer leaves unanswered stays held instead of going to the background;
    (f) ``full_late``, asked for by name: the labels of (d) added after the first fit, when a
        reviewer's arrive (a reviewer with unlimited time): what labels lose by arriving late.

    ``max_label_iou`` gives the reviewer the queue filter that hides items on labelled objects
    (``SessionDB.review_queue``); hidden items cost no budget. ``review_by`` "place" reviews as the
    app does by default once the frames are placed: one verdict per place of the queue, objects
    labelled once in every frame that shows them (``simulated_review``'s ``world``); K then counts
    places; with ``best_view`` as well, a place that shows too few points for the policy is judged
    where the frames see it best (``simulated_review``'s ``best_view``, the review panel's *Look
    where it is seen best*). ``variants`` runs some of the detectors only (their names as above;
    ``blind``, every other one's baseline, always runs); ``None``: (a) to (d).

    With ``heldout_seeds``, the figures (F-scores, mAP, recovered shares) are measured on held-out
    factories instead: ``heldout_frames`` frames of each simulator seed (``quality.heldout_set``,
    simulated once into ``heldout_scratch``), which no training or choice saw; each run keeps
    its figures on the training factory's test frames too (``in_factory``).

    Every variant runs ``rounds + 1`` fits: a first fit that mines, then ``rounds`` next rounds.
    Each seed (``LoopSettings.seed``: the first background sample, the network's initialisation
    and the box quality regressor) trains every variant afresh; F-scores are the seeds' means,
    and ``recovered[K]`` is (F(b) - F(a)) / (F(c) - F(a)) of the means. The training and test
    frames are spread evenly over their splits (``spread_frames``). Their proposals are made once,
    by ``propose`` (on Ray workers with ``scale.jobs.proposer``); the fits and the mining run here.

    After each detector of each seed, a partial record (``"complete": false``, the plan and the
    runs so far) goes to ``on_partial``; given back as ``earlier`` to a run of the same plan (its
    seeds aside), its runs are read back and only the missing ones train, so a long benchmark can
    be stopped and resumed. A run depends only on its seed, its variant (each trains in its own
    session) and the code, so a resumed run does the work an uninterrupted one would: each run
    keeps the version of the library it ran (``records.library_version``), and a resume that has
    detectors to train reads back only the runs of the running version (the others train again,
    with a warning) unless ``resume_other_library``; a resume with nothing to train renders the
    record as it is. The record counts its runs per library version (``library_versions``).
    ``also`` (records by name, e.g. their paths) adds the finished runs of other records of the
    plan, say the seeds another process ran (``_resumable_runs``).

    Raises:
        InputError: on bad arguments, or an ``earlier`` (or ``also``) record of another plan.
    """
    import tempfile

    dataset = open_dataset(data)
    if not (Path(data) / "truth").is_dir():
        raise InputError(
            f"{dataset.name}: bench hitl needs a simulated data set (its reviewer reads the truth)"
        )
    seeds, budgets = [int(s) for s in seeds], [int(k) for k in budgets]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise InputError(f"bench hitl needs one or more distinct seeds >= 0, got {seeds}")
    if not budgets or len(set(budgets)) != len(budgets) or min(budgets) < 1:
        raise InputError(f"bench hitl needs one or more distinct review budgets K >= 1, got {budgets}")
    if max_label_iou is not None and not 0.0 < max_label_iou <= 1.0:
        raise InputError(f"bench hitl: the queue filter's IoU must lie in (0, 1], got {max_label_iou}")
    if review_by not in ("item", "place"):
        raise InputError(f"bench hitl: review by 'item' or 'place', got {review_by!r}")
    if best_view and review_by != "place":
        raise InputError("bench hitl: the best view is a place's (--review-by place)")
    known = [name for name, _, _ in _variant_specs(budgets, None, default=False)]
    if variants is not None:
        unknown = sorted(set(variants) - set(known))
        if unknown:
            raise InputError(f"bench hitl: unknown variants {unknown}; choose from {', '.join(known)}")
        variants = [name for name in known if name == "blind" or name in variants]
    settings = settings or LoopSettings()
    for safety in BLIND_SAFE_SETTINGS:
        if getattr(settings, safety) and variants is not None and not any(map(holds, variants)):
            raise InputError(
                f"bench hitl: {safety} changes blind_safe and reviewed_safe_K alone, "
                "which --variants leaves out"
            )
    heldout_seeds = tuple(int(s) for s in heldout_seeds)
    if heldout_seeds:
        heldout_seeds = check_heldout(heldout_seeds, heldout_frames, dataset)
    settings = dataclasses.replace(settings, rounds=0)
    train = spread_frames(dataset.splits.get("train") or [], max_train_frames)
    test = spread_frames(dataset.splits.get("test") or [], max_test_frames)
    if not train or not test:
        raise InputError(f"{dataset.name}: bench hitl needs train and test frames")
    plan = _HitlPlan(
        dataset, data, train, test, budgets, rounds, settings, seeds, max_label_iou, calibrate, command,
        review_by, variants, propose, heldout_seeds, int(heldout_frames), Path(heldout_scratch),
        bool(best_view),
    )  # fmt: skip
    # a plan mismatch fails here, before any work
    resumed = _resumable_runs(plan, earlier, other_library=resume_other_library, also=also)
    if workdir is not None:
        return _hitl_variants(plan, Path(workdir), progress, resumed, on_partial)
    with tempfile.TemporaryDirectory(prefix="factorydet_hitl_") as scratch_dir:
        return _hitl_variants(plan, Path(scratch_dir), progress, resumed, on_partial)


def _candidates_of(model, frames: Sequence) -> dict:
    """Frame index -> ``model``'s candidates (``DetectionModel.candidates``; before any threshold)."""
    return {f.frame_index: model.candidates(f.proposal_boxes, f.groups) for f in frames}


def paired_difference(values: Sequence[float], baseline: Sequence[float]) -> dict:
    """The per-seed (paired) difference ``values - baseline``: its mean, standard error and 95%
    confidence interval (Student's t over the seeds; ``None`` with fewer than two seeds)."""
    from scipy import stats

    differences = np.asarray(values, np.float64) - np.asarray(baseline, np.float64)
    mean = float(differences.mean())
    if len(differences) < 2:
        return {"mean": round(mean, 4), "standard_error": None, "ci95": None, "num_seeds": len(differences)}
    error = float(differences.std(ddof=1) / np.sqrt(len(differences)))
    half = float(stats.t.ppf(0.975, len(differences) - 1) * error)
    return {
        "mean": round(mean, 4),
        "standard_error": round(error, 4),
        "ci95": [round(mean - half, 4), round(mean + half, 4)],
        "num_seeds": len(differences),
    }


def recovered_share(values: Sequence[float], baseline: Sequence[float], full: Sequence[float]) -> dict:
    """The share of the gap ``full - baseline`` that ``values`` recover, seed by seed paired: the
    ratio of the mean differences ``mean(values - baseline) / mean(full - baseline)`` and its 95%
    confidence interval by Fieller's theorem (the shares ``r`` for which the per-seed differences
    ``(values - baseline) - r (full - baseline)`` do not differ from 0 by Student's t).

    Returns:
        ``{"share", "ci95", "num_seeds"}``; ``share`` ``None`` when the mean gap is not positive,
        ``ci95`` ``None`` with fewer than two seeds or when the interval is unbounded (the gap's
        own interval reaches 0: the seeds cannot bound the share).
    """
    from scipy import stats

    x = np.asarray(values, np.float64) - np.asarray(baseline, np.float64)
    y = np.asarray(full, np.float64) - np.asarray(baseline, np.float64)
    n = len(x)
    if n == 0 or not y.mean() > 0:
        return {"share": None, "ci95": None, "num_seeds": n}
    share = float(x.mean() / y.mean())
    if n < 2:
        return {"share": round(share, 4), "ci95": None, "num_seeds": n}
    t2 = float(stats.t.ppf(0.975, n - 1)) ** 2
    covariance = np.cov(x, y) / n  # of the two means
    a = y.mean() ** 2 - t2 * covariance[1, 1]
    b = x.mean() * y.mean() - t2 * covariance[0, 1]
    c = x.mean() ** 2 - t2 * covariance[0, 0]
    if a <= 0:
        return {"share": round(share, 4), "ci95": None, "num_seeds": n}
    # With a > 0 the quadratic is <= 0 at the share itself (minus t^2 times a variance), so it has
    # real roots: a negative discriminant is rounding.
    root = float(np.sqrt(max(b * b - a * c, 0.0)))
    return {
        "share": round(share, 4),
        "ci95": [round((b - root) / a, 4), round((b + root) / a, 4)],
        "num_seeds": n,
    }


def _recovered(f1: dict[str, float], budgets: Sequence[int]) -> tuple[float, dict[str, float | None]]:
    """The gap F(full) - F(blind) and the share of it each ``reviewed_K`` recovers (``None``
    when there is no gap)."""
    gap = f1["full"] - f1["blind"]
    return gap, {
        str(k): None if gap <= 0 else round((f1[f"reviewed_{k}"] - f1["blind"]) / gap, 3) for k in budgets
    }


@dataclasses.dataclass(frozen=True)
class _HitlPlan:
    """``bench_hitl``'s checked arguments."""

    dataset: object
    data: str | os.PathLike
    train: list[int]
    test: list[int]
    budgets: list[int]
    rounds: int
    settings: object
    seeds: list[int]
    max_label_iou: float | None
    calibrate: bool
    command: str
    review_by: str = "item"
    variants: list[str] | None = None
    propose: Proposer = collect_proposals
    heldout_seeds: tuple[int, ...] = ()
    heldout_frames: int = 12
    heldout_scratch: Path = HELDOUT_SCRATCH
    best_view: bool = False

    def record(self) -> dict:
        """The plan as JSON: a result is resumed only by a run of the same plan (its seeds aside)."""
        values = {
            "data": Path(self.data).name,
            "train_frames": self.train,
            "test_frames": self.test,
            "budgets": self.budgets,
            "mining_rounds": self.rounds,
            # The seed is each run's own; the thread count is the machine's, not the model's.
            "settings": {
                k: v for k, v in dataclasses.asdict(self.settings).items() if k not in ("seed", "num_threads")
            },
            "seeds": self.seeds,
            "queue_max_label_iou": self.max_label_iou,
            "calibrate": self.calibrate,
            "review_by": self.review_by,
            "review_best_view": self.best_view,
            "variants": self.variants
            or [name for name, _, _ in _variant_specs(self.budgets, None, default=True)],
            # Where the figures are measured (None: on the test frames alone).
            "heldout": {"seeds": list(self.heldout_seeds), "frames": self.heldout_frames}
            if self.heldout_seeds
            else None,
        }
        return json.loads(json.dumps(values))


PLAN_BEFORE_THEY_EXISTED: dict[str, object] = {"heldout": None, "review_best_view": False}
"""What a plan record (``_HitlPlan.record``) from before a field existed did: measured on the test
frames (no held-out factories), reviewed without the best view."""


def _resumable_runs(
    plan: _HitlPlan,
    earlier: dict | None,
    other_library: bool = False,
    also: Mapping[str, dict] | None = None,
) -> dict[tuple[int, str], dict]:
    """The finished runs of an earlier (partial) result, as ``{(seed, variant): run}``: those of
    the plan's detectors whose run plan (``_run_plan``) the earlier record shares. ``also``, by
    name (a file's path), adds the finished runs of other records of the plan, say the seeds
    another process ran on the other core: a run the earlier record lacks, or one of this version
    of the library where the earlier record's ran another; a record without runs adds nothing.
    When some of the plan's runs are missing (there is training to do), only the runs of this
    version of the library (``records.library_version``) are read back, unless ``other_library``:
    a record whose runs ran other code would set two versions side by side in every paired
    difference. The runs left out train again, with a warning that says so.

    Raises:
        InputError: when a record (``earlier`` or one of ``also``, named) is not a hitl record, or
            has runs and shares no detector's run plan (it would mix two benchmarks).
    """
    mine = plan.record()
    version = library_version()
    runs: dict[tuple[int, str], dict] = {}
    named = [("--out", earlier)] if earlier else []
    for name, record in [*named, *(also or {}).items()]:
        where = "the earlier result" if name == "--out" else name
        if not isinstance(record, dict) or record.get("benchmark") != "hitl" or "plan" not in record:
            raise InputError(f"bench hitl --resume: {where} is not a resumable bench hitl record")
        per_seed = record.get("per_seed") or {}
        if name != "--out" and not any(per_seed.values()):
            continue  # (nothing to read back, whatever plan it ran)
        theirs = _record_plan(record)
        same = {
            variant for variant in mine["variants"] if _run_plan(mine, variant) == _run_plan(theirs, variant)
        }
        if not same:
            check_same_plan("hitl", mine, theirs, what=where)
        for variant, variant_runs in per_seed.items():
            for run in variant_runs:
                key = (int(run["seed"]), variant)
                if key[0] not in plan.seeds or variant not in same:
                    continue
                if key not in runs or (runs[key].get("library") != version and run.get("library") == version):
                    runs[key] = run
    wanted = {(seed, name) for seed in plan.seeds for name in mine["variants"]}
    if other_library or wanted <= set(runs):
        return runs  # (nothing to train: the record is rendered as it is)
    kept = runs_of_this_library({key: [run] for key, run in runs.items()}, "hitl", "runs")
    return {key: runs[key] for key in kept}


def _record_plan(record: dict) -> dict:
    """A record's plan as its runs ran it (the fields it predates at the values they ran)."""
    plan = {**PLAN_BEFORE_THEY_EXISTED, **record["plan"]}
    if isinstance(plan.get("settings"), dict):
        plan["settings"] = _settings_as_run(plan["settings"])
    return plan


def _run_plan(plan: dict, variant: str) -> dict:
    """What of a plan record (``_HitlPlan.record``) shapes the runs of ``variant``: the plan less
    its seeds, its list of detectors and its budgets (a reviewed detector's budget is in its name),
    less the reviewer's settings for a detector nobody reviews, less the holding of confident
    negatives (``hold_confident``, ``hold_places``) and background recalibration for all but
    the detectors that hold and recalibrate (``holds``), less whether the model's boxes are
    learnt from for a detector with no verdicts and no pseudo-labels (none of its labels has
    one), and less the box
    quality refit for blind mining and full labels, whose labels never change after the first fit. Runs of a
    detector whose run plans agree are the same runs, whatever else the two records measured: a
    record grows by a detector without training the others again."""
    out = {k: v for k, v in plan.items() if k not in ("seeds", "variants", "budgets")}
    untouched = set()
    settings = out.get("settings") if isinstance(out.get("settings"), dict) else {}
    if not variant.startswith("reviewed_"):
        out.pop("review_by", None)
        out.pop("queue_max_label_iou", None)
        out.pop("review_best_view", None)
        untouched |= {"review_order", "review_extra"}  # the queue, which nobody reviews
        # labels of the data set or imported: never checked
        untouched |= {"label_min_points", "threshold_label_min_points"}
        if not (holds(variant) and settings.get("pseudo_label_confident") is not None):
            untouched.add("model_box_targets")  # no verdict nor pseudo-label: no label with the model's box
    if settings.get("pseudo_label_confident") is None:
        untouched.add("carry_pseudo_labels")  # no pseudo-label to carry
    if settings.get("class_thresholds") is False:
        untouched.add("threshold_label_min_points")  # no threshold tuned
    if not holds(variant):
        untouched |= {"hold_confident", *BLIND_SAFE_SETTINGS}
    if variant in ("blind", "full"):
        # Their labels never change after the first fit, so a refit of the box quality regressor
        # meets the rows it was fitted on and keeps it (``train_with_mining``'s training digest).
        untouched |= {"refit_box_quality", "refit_trees", "refit_row_share"}
    if settings.get("box_quality") is False or settings.get("method") == "box_head":
        untouched |= {"quality_trees", "refit_row_share"}  # no regressor is fitted
    if (
        settings.get("refit_box_quality") is False
        or settings.get("refit_trees")
        or not settings.get("round_epochs")
    ):
        # No next round refits it from scratch (rounds trained afresh fit it on every row).
        untouched.add("refit_row_share")
    if not folds_continue({**settings, "continue_folds": True}, bool(plan.get("mining_rounds"))):
        untouched.add("continue_folds")  # no fold models, or no next round to go on from them
    if isinstance(out.get("settings"), dict):
        out["settings"] = {k: v for k, v in out["settings"].items() if k not in untouched}
        if "review_order" not in untouched:
            # None reviews in the queue order, and a learned one by item too: the same runs as
            # naming that order.
            out["settings"]["review_order"] = reviewer_order(out["settings"], plan.get("review_by"))
    return out


def reviewer_order(settings: dict, review_by: str | None) -> str | None:
    """The order a record's simulated reviewer saw its queue in, from its plan's ``settings`` (a
    mapping, as stored) and ``review_by``: ``review_order_of`` (None: the queue order), except
    that a learned order by item is the cut's (``session.queue.unlearned_order``: it orders
    places)."""
    order = review_order_of(settings)
    if review_by == "place":
        return order
    cut = settings.get("queue_order")
    return unlearned_order(order, None if cut is None else str(cut))


def _settings_as_run(settings: dict) -> dict:
    """A record's plan ``settings`` with every ``LoopSettings`` field it lacks at what was done
    before the field existed (``settings.BEFORE_THEY_EXISTED``, else its default; the seed and
    thread count aside, as ``_HitlPlan.record``)."""
    defaults = json.loads(json.dumps({**dataclasses.asdict(LoopSettings()), **BEFORE_THEY_EXISTED}))
    return {**{k: v for k, v in defaults.items() if k not in ("seed", "num_threads")}, **settings}


def _seed_settings(settings: LoopSettings, variant: str, seed: int, hold: float | None) -> LoopSettings:
    """The ``LoopSettings`` detector ``variant`` trains with for ``seed``: holding (at ``hold``)
    and recalibrating are the holding detectors' alone (``holds``), and the false positives
    queued for review alone (``review_extra``) the reviewed detectors' (a queue nobody reviews
    would only grow), as ``_run_plan`` says of their runs."""
    return dataclasses.replace(
        settings,
        seed=seed,
        hold_confident=hold,
        hold_places=settings.hold_places and holds(variant),
        recalibrate_background=settings.recalibrate_background if holds(variant) else None,
        recalibrate_by_class=settings.recalibrate_by_class and holds(variant),
        pseudo_label_confident=settings.pseudo_label_confident if holds(variant) else None,
        carry_pseudo_labels=settings.carry_pseudo_labels and holds(variant),
        review_extra=settings.review_extra if variant.startswith("reviewed_") else 0,
    )


def _variant_specs(
    budgets: Sequence[int], hold: float | None, default: bool
) -> list[tuple[str, int, float | None]]:
    """The detectors ``bench hitl`` can train, in table order: ``(name, review budget, hold score)``;
    ``default``: those it trains when none are named (``reviewed_safe_K`` and ``full_late`` are
    asked for by name)."""
    return [
        ("blind", 0, None),
        ("blind_safe", 0, hold),
        *((f"reviewed_{k}", int(k), None) for k in budgets),
        *([] if default else [(f"reviewed_safe_{k}", int(k), hold) for k in budgets]),
        *([] if default else [("full_late", 0, None)]),
        ("full", 0, None),
    ]


def _hitl_variants(
    plan: _HitlPlan,
    root: Path,
    progress,
    resumed: dict[tuple[int, str], dict] | None = None,
    on_partial: Callable[[dict], None] | None = None,
) -> dict:
    """``bench_hitl``'s work inside its sessions folder ``root``; ``resumed`` runs are read back."""

    dataset, data, train, test, budgets = plan.dataset, plan.data, plan.train, plan.test, plan.budgets
    rounds, settings, seeds, max_label_iou = plan.rounds, plan.settings, plan.seeds, plan.max_label_iou
    calibrate, command = plan.calibrate, plan.command
    resumed = resumed or {}
    # The holding detectors hold the negatives the model scores at its operating score or more
    # out of the background until reviewed.
    hold = settings.hold_confident if settings.hold_confident is not None else settings.score_threshold
    variants = _variant_specs(budgets, hold, default=plan.variants is None)
    if plan.variants is not None:
        variants = [v for v in variants if v[0] in plan.variants]
    train_frames = test_frames = world = proposal_seconds = heldout = None
    if any((seed, name) not in resumed for seed in seeds for name, _, _ in variants):
        # (a record resumed whole is only rendered again: nothing to propose or place)
        detector = Detector(params_for(None, dataset.num_sensors))
        if calibrate and dataset.num_sensors > 1:
            detector.calibrate(dataset.frame(train[0]))
        scratch = SessionDB(open_session("proposals", root), dataset)
        start = time.perf_counter()
        train_frames = cached_proposals(scratch, dataset, detector, train, propose=plan.propose)
        test_frames = cached_proposals(scratch, dataset, detector, test, propose=plan.propose)
        if plan.heldout_seeds:
            # The same front half as the training factory's proposals; each held-out factory's
            # sensors calibrated on its own first frame, as the app would.
            heldout = heldout_set(
                plan.heldout_seeds, plan.heldout_frames, plan.heldout_scratch, detector.params,
                propose=plan.propose, calibrate=calibrate,
            )  # fmt: skip
            if tuple(heldout.class_names) != tuple(dataset.class_names):
                raise InputError(
                    f"the held-out factories' classes {list(heldout.class_names)} are not "
                    f"{dataset.name}'s {list(dataset.class_names)}"
                )
        proposal_seconds = round(time.perf_counter() - start, 1)
        if plan.review_by == "place" or settings.carries_pseudo_labels:
            from factorydet_core.session.world import session_world

            world, _ = session_world(scratch.session, dataset)
    steps, done = len(seeds) * len(variants) * (rounds + 1), 0
    per_seed: dict[str, list[dict]] = {name: [] for name, _, _ in variants}
    for seed in seeds:
        for name, budget, variant_hold in variants:
            if (seed, name) in resumed:
                per_seed[name].append(resumed[(seed, name)])
                done += rounds + 1
                if progress is not None:
                    progress(done, steps)
                continue
            seed_settings = _seed_settings(settings, name, seed, variant_hold)
            db = SessionDB(open_session(f"{name}_seed{seed}", root), dataset)
            added = add_truth_labels(db, dataset, train) if name == "full" else 0
            reviews = dict.fromkeys(REVIEW_COUNTS, 0)
            fit_seconds = 0.0
            reached: set = set()  # unannotated objects some reviewable queue item overlaps
            reached_top: set = set()  # ... some of the first K entries the reviewer answers overlaps
            # Per reviewed round, the share of the queue's reach its first K entries hold: as the
            # model's scores estimate it (the review panel's line) and as the truth gives it.
            reach_shares: list[tuple[float | None, float | None]] = []
            for r in range(rounds + 1):
                _, run = train_session(
                    db, train_frames, seed_settings, mode="full" if r == 0 else "next", data_ref=str(data),
                    world=world,
                )  # fmt: skip
                fit_seconds += sum(x["fit_seconds"] for x in run.rounds)
                if name == "full_late" and r == 0:
                    # Every missing label arrives after the first fit, when a reviewer's would:
                    # what late labels are worth against labels from the start (full).
                    added = add_truth_labels(db, dataset, train)
                if name != "full" and r < rounds:
                    round_reach = queue_reach(db, dataset, train)
                    reached |= round_reach
                if budget and r < rounds:
                    answered = simulated_review(
                        db, dataset, budget, max_label_iou=max_label_iou, world=world,
                        best_view=plan.best_view,
                    )  # fmt: skip
                    for key, value in answered.items():
                        reviews[key] += value
                    # After the review: a learned order puts the places answered first (the
                    # others' orders do not change with verdicts).
                    round_top = queue_reach(db, dataset, train, top=budget, world=world)
                    reached_top |= round_top
                    reach_shares.append(
                        (
                            estimated_reach_share(db, budget, world),
                            len(round_top) / len(round_reach) if round_reach else None,
                        )
                    )
                done += 1
                if progress is not None:
                    progress(done, steps)
            # Candidates once per frame set: with thresholds tuned out of fold, the same network is
            # measured with the thresholds its fitted frames would have given too.
            folds = run.rounds[-1].get("threshold_folds")
            # The same network at each set of thresholds, by name: the model's own; with folds the
            # ones its fitted frames would have given, and the other objective's out of fold.
            thresholds_of: dict[str, dict | None] = {"model": run.model.class_score_thresholds}
            other_objective = None
            if folds is not None:
                thresholds_of["fitted_frames"] = dict(folds["fitted_frame_thresholds"])
                others = [o for o in folds["by_objective"] if o != folds["objective"]]
                other_objective = others[0]
                thresholds_of["other_objective"] = dict(folds["by_objective"][other_objective])
                # What the settings without folds give (``--threshold-folds 0`` and, when the run's
                # objective is "total", objective "class": the defaults before out-of-fold
                # thresholds); runs from before it was recorded lack it.
                if "fitted_frame_by_objective" in folds:
                    thresholds_of["fitted_frames_other_objective"] = dict(
                        folds["fitted_frame_by_objective"][other_objective]
                    )
            models = {
                key: dataclasses.replace(run.model, class_score_thresholds=t or None)
                for key, t in thresholds_of.items()
            }
            test_candidates = _candidates_of(run.model, test_frames)
            measured = {
                key: measure(model, dataset, test_frames, use_truth=True, candidates=test_candidates)
                for key, model in models.items()
            }
            in_factory = None
            if heldout is not None:
                in_factory = {k: measured["model"][k] for k in ("f1", "precision", "recall", "map")}
                heldout_candidates = _candidates_of(run.model, heldout.frames)
                measured = {
                    key: measure(
                        model,
                        None,
                        heldout.frames,
                        references=heldout.references,
                        ignored=heldout.ignored,
                        candidates=heldout_candidates,
                    )
                    for key, model in models.items()
                }
            metrics = measured["model"]
            fitted_frame = other_objective_thresholds = fitted_frame_other_objective = None
            if folds is not None:
                fitted_frame = {
                    **{k: measured["fitted_frames"][k] for k in ("f1", "precision", "recall", "map")},
                    "per_class_f1": {k: v["f1"] for k, v in measured["fitted_frames"]["per_class"].items()},
                    "thresholds": thresholds_of["fitted_frames"],
                    "out_of_fold_thresholds": dict(folds["thresholds"]),
                }
                other_objective_thresholds = {
                    "objective": other_objective,
                    **{k: measured["other_objective"][k] for k in ("f1", "precision", "recall", "map")},
                    "per_class_f1": {k: v["f1"] for k, v in measured["other_objective"]["per_class"].items()},
                    "thresholds": thresholds_of["other_objective"],
                }
                if "fitted_frames_other_objective" in measured:
                    at = measured["fitted_frames_other_objective"]
                    fitted_frame_other_objective = {
                        "objective": other_objective,
                        **{k: at[k] for k in ("f1", "precision", "recall", "map")},
                        "per_class_f1": {k: v["f1"] for k, v in at["per_class"].items()},
                        "thresholds": thresholds_of["fitted_frames_other_objective"],
                    }
            covered_by_class = unannotated_coverage_by_class(db, dataset, train)
            covered, unannotated = _coverage_totals(covered_by_class)
            pseudo = None
            if seed_settings.pseudo_label_confident is not None:
                pseudo = pseudo_label_truth(
                    db, dataset, session_pseudo_labels(db, seed_settings, train, world)
                )
            last_config = db.training_runs()[-1]["config"]
            per_seed[name].append(
                {
                    "seed": seed,
                    "f1": metrics["f1"],
                    "precision": metrics["precision"],
                    "recall": metrics["recall"],
                    "map": metrics["map"],
                    "per_class_f1": {k: v["f1"] for k, v in metrics["per_class"].items()},
                    # Whether a class's F moves by its false positives or by its misses.
                    "per_class_precision": {k: v["precision"] for k, v in metrics["per_class"].items()},
                    "per_class_recall": {k: v["recall"] for k, v in metrics["per_class"].items()},
                    "num_reviews": sum(reviews[k] for k in VERDICTS),
                    "reviews": reviews,
                    "truth_labels_added": added,
                    # A person's labels the last fit left out as too sparse (label_min_points).
                    "sparse_labels_ignored": last_config.get("sparse_labels_ignored"),
                    # ... and those it trained on but tuned its thresholds without
                    # (threshold_label_min_points).
                    "labels_tuning_ignored": last_config.get("labels_tuning_ignored"),
                    "unannotated_labelled": covered,
                    "unannotated_total": unannotated,
                    "unannotated_labelled_per_class": {c: list(v) for c, v in covered_by_class.items()},
                    "unannotated_in_queue": None if name == "full" else len(reached),
                    "unannotated_in_top_k": len(reached_top) if budget else None,
                    "reach_share_estimated": _mean_of([e for e, _ in reach_shares]),
                    "reach_share_true": _mean_of([t for _, t in reach_shares]),
                    # The pseudo-labels the session ends with, as the truth judges them.
                    "pseudo_labels": None if pseudo is None else pseudo["all"],
                    "pseudo_labels_carried": None if pseudo is None else pseudo["carried"],
                    "fit_seconds": round(fit_seconds, 1),
                    "library": library_version(),  # the code this run ran
                    # With held-out factories, the figures on the training factory's test frames.
                    **({"in_factory": in_factory} if in_factory is not None else {}),
                    # With thresholds tuned out of fold: the same model at its fitted frames'.
                    **({"fitted_frame_thresholds": fitted_frame} if fitted_frame is not None else {}),
                    # And at the other objective's out-of-fold thresholds.
                    **(
                        {"other_objective_thresholds": other_objective_thresholds}
                        if other_objective_thresholds is not None
                        else {}
                    ),
                    # And at the other objective's fitted frames' (no folds).
                    **(
                        {"fitted_frame_other_objective_thresholds": fitted_frame_other_objective}
                        if fitted_frame_other_objective is not None
                        else {}
                    ),
                }
            )
            if on_partial is not None:
                on_partial(
                    {
                        "benchmark": "hitl",
                        "complete": False,
                        "command": command,
                        "plan": plan.record(),
                        "per_seed": {n: runs for n, runs in per_seed.items() if runs},
                        "machine": machine_info(),
                    }
                )

    results = {}
    for name, runs in per_seed.items():
        results[name] = {
            **{key: _mean_of([r[key] for r in runs]) for key in ("f1", "precision", "recall", "map")},
            "f1_per_seed": [r["f1"] for r in runs],
            "f1_std": round(float(np.std([r["f1"] for r in runs], ddof=1)), 4) if len(runs) > 1 else None,
            "per_class_f1": {
                c: _mean_of([r["per_class_f1"][c] for r in runs]) for c in runs[0]["per_class_f1"]
            },
            # (runs read back from records before they were kept have neither)
            **{
                key: {c: _mean_of([r[key][c] for r in runs]) for c in runs[0][key]}
                for key in ("per_class_precision", "per_class_recall")
                if all(key in r for r in runs)
            },
            "num_reviews": _mean_of([r["num_reviews"] for r in runs]),
            # (runs read back from records before the best view have no count of it)
            "reviews": {
                k: _mean_of([r["reviews"].get(k, 0) for r in runs])
                for k in REVIEW_COUNTS
                if any(k in r["reviews"] for r in runs)
            },
            "truth_labels_added": _mean_of([r["truth_labels_added"] for r in runs]),
            # (runs read back from records before it have no count)
            "sparse_labels_ignored": _mean_of([r.get("sparse_labels_ignored") for r in runs]),
            "labels_tuning_ignored": _mean_of([r.get("labels_tuning_ignored") for r in runs]),
            # Of the objects the data set left unannotated on the training frames, the share the
            # session labels at the end (full: all; blind: none; reviewed: what the reviews gave back).
            "unannotated_labelled": _mean_of(
                [r["unannotated_labelled"] / max(r["unannotated_total"], 1) for r in runs]
            ),
            # ... per class: (mean over the seeds of) the share labelled, and how many there are.
            "unannotated_labelled_per_class": {
                c: {
                    "share": _mean_of(
                        [
                            r["unannotated_labelled_per_class"][c][0]
                            / r["unannotated_labelled_per_class"][c][1]
                            if r["unannotated_labelled_per_class"][c][1]
                            else None
                            for r in runs
                        ]
                    ),
                    "total": _mean_of([r["unannotated_labelled_per_class"][c][1] for r in runs]),
                }
                for c in runs[0].get("unannotated_labelled_per_class", {})
                if all("unannotated_labelled_per_class" in r for r in runs)
            },
            # Of those objects, the share some item of a reviewed round's queue overlaps (IoU 0.1):
            # all that reviews of any budget could give back (None for full labels: no queue of
            # unannotated objects to reach).
            "unannotated_in_queue": None
            if name == "full"
            else _mean_of([r["unannotated_in_queue"] / max(r["unannotated_total"], 1) for r in runs]),
            # ... and the share the first K entries of the reviewed rounds' queues reach (the
            # reviewer's budget: items, or places with --review-by place).
            "unannotated_in_top_k": None
            if runs[0]["unannotated_in_top_k"] is None
            else _mean_of([r["unannotated_in_top_k"] / max(r["unannotated_total"], 1) for r in runs]),
            # Of what a reviewed round's whole queue reaches, the share its first K entries hold: as
            # the review panel estimates it from the model's scores, and as the truth gives it.
            "reach_share_estimated": _mean_of([r["reach_share_estimated"] for r in runs]),
            "reach_share_true": _mean_of([r["reach_share_true"] for r in runs]),
            "fit_seconds": round(sum(r["fit_seconds"] for r in runs), 1),  # all seeds' fits together
            # How many runs measured each figure a run may lack (read back from a record made
            # before the run kept it): a row needs every run's, and the table says what it left out.
            "runs_measuring": {key: sum(1 for r in runs if key in r) for key in OPTIONAL_RUN_FIGURES},
        }
        # (runs from before carried pseudo-labels have no count of them)
        for key in ("pseudo_labels", "pseudo_labels_carried"):
            if all(r.get(key) is not None for r in runs):
                results[name][key] = {
                    kind: _mean_of([r[key][kind] for r in runs]) for kind in PSEUDO_LABEL_KINDS
                }
        if all("fitted_frame_thresholds" in r for r in runs):
            # Out-of-fold thresholds against the fitted frames' on the very same networks.
            results[name]["fitted_frame_thresholds"] = {
                "f1": _mean_of([r["fitted_frame_thresholds"]["f1"] for r in runs]),
                "f1_per_seed": [r["fitted_frame_thresholds"]["f1"] for r in runs],
                "out_of_fold_minus_fitted": paired_difference(
                    [r["f1"] for r in runs], [r["fitted_frame_thresholds"]["f1"] for r in runs]
                ),
            }
        if all("other_objective_thresholds" in r for r in runs):
            # The other objective's out-of-fold thresholds, on the very same networks.
            results[name]["other_objective_thresholds"] = {
                "objective": runs[0]["other_objective_thresholds"]["objective"],
                "f1": _mean_of([r["other_objective_thresholds"]["f1"] for r in runs]),
                "f1_per_seed": [r["other_objective_thresholds"]["f1"] for r in runs],
                "map": _mean_of([r["other_objective_thresholds"]["map"] for r in runs]),
                "minus_chosen": paired_difference(
                    [r["other_objective_thresholds"]["f1"] for r in runs], [r["f1"] for r in runs]
                ),
            }
        if all("fitted_frame_other_objective_thresholds" in r for r in runs):
            # The other objective's fitted frames' thresholds (the settings without folds), on the
            # very same networks.
            at = [r["fitted_frame_other_objective_thresholds"] for r in runs]
            results[name]["fitted_frame_other_objective_thresholds"] = {
                "objective": at[0]["objective"],
                "f1": _mean_of([a["f1"] for a in at]),
                "f1_per_seed": [a["f1"] for a in at],
                "map": _mean_of([a["map"] for a in at]),
                "chosen_minus_these": paired_difference([r["f1"] for r in runs], [a["f1"] for a in at]),
            }
        if all("in_factory" in r for r in runs):
            results[name]["in_factory"] = {
                **{key: _mean_of([r["in_factory"][key] for r in runs]) for key in ("f1", "map")},
                "f1_per_seed": [r["in_factory"]["f1"] for r in runs],
            }
    f1 = {name: r["f1"] for name, r in results.items()}
    for name in results:
        results[name]["difference_vs_blind"] = paired_difference(
            [r["f1"] for r in per_seed[name]], [r["f1"] for r in per_seed["blind"]]
        )
        if "other_objective_thresholds" in results[name] and "other_objective_thresholds" in results["blind"]:
            results[name]["other_objective_thresholds"]["difference_vs_blind"] = paired_difference(
                results[name]["other_objective_thresholds"]["f1_per_seed"],
                results["blind"]["other_objective_thresholds"]["f1_per_seed"],
            )
        for key in ("fitted_frame_thresholds", "fitted_frame_other_objective_thresholds"):
            if key in results[name] and key in results["blind"]:
                results[name][key]["difference_vs_blind"] = paired_difference(
                    results[name][key]["f1_per_seed"], results["blind"][key]["f1_per_seed"]
                )
    reviewed = [k for k in budgets if f"reviewed_{k}" in results]
    gap, recovered, recovered_per_seed, gap_significant = None, {}, {}, False
    if "full" in results:
        gap, recovered = _recovered(f1, reviewed)
        gap_stats = results["full"]["difference_vs_blind"]
        # A share of a gap no larger than its noise says nothing: stated only where the gap is more
        # than twice its standard error over the seeds.
        gap_significant = gap_stats["standard_error"] is not None and gap > 2 * gap_stats["standard_error"]
        seed_recovered = [
            _recovered({n: runs[i]["f1"] for n, runs in per_seed.items()}, reviewed)[1]
            for i in range(len(seeds))
        ]
        recovered_per_seed = {str(k): [r[str(k)] for r in seed_recovered] for k in reviewed}
        full_f1 = [r["f1"] for r in per_seed["full"]]
        for name in results:
            if name not in ("blind", "full"):
                results[name]["recovered_share"] = recovered_share(
                    [r["f1"] for r in per_seed[name]], [r["f1"] for r in per_seed["blind"]], full_f1
                )
    return {
        "benchmark": "hitl",
        "complete": True,
        "command": command,
        "plan": plan.record(),
        "data": Path(data).name,
        "train_frames": train,
        "test_frames": test,
        # The figures' frames: held-out factories (headline figures), or else the test frames
        # (in-factory figures).
        "heldout_factories": [{"seed": s, "frames": plan.heldout_frames} for s in plan.heldout_seeds] or None,
        "reference": "truth",
        "iou_threshold": 0.6,
        "mining_rounds": rounds,
        "seeds": seeds,
        # The reviewer's queue: in the run's queue order, without the items that overlap a label at
        # this IoU or more when set (the review panel's "hide items on labelled objects").
        "queue_max_label_iou": max_label_iou,
        "review_by": plan.review_by,
        "review_best_view": plan.best_view,
        "settings": {k: v for k, v in dataclasses.asdict(settings).items() if k != "seed"},
        "f1": f1,
        "recovered": recovered,
        "recovered_per_seed": recovered_per_seed,
        "gap_full_minus_blind": None if gap is None else round(gap, 4),
        "gap_significant": bool(gap_significant),
        "hold_confident": hold,
        "variants": results,
        "per_seed": per_seed,
        # None: every run was read back (with held-out factories: their simulation and proposals too)
        "proposal_seconds": proposal_seconds,
        # The versions of the library the runs ran (more than one: a mixed record).
        "library_versions": library_versions([run for runs in per_seed.values() for run in runs]),
        "machine": machine_info(),
    }


def pool_hitl_records(records: Sequence[dict], names: Sequence[str] | None = None) -> dict:
    """Several complete ``bench hitl`` records of one plan measured on disjoint sets of held-out
    factories, taken together: per training seed and detector, the mean of the records' F-scores
    weighted by their held-out frames (the mean F over the sets, not the F of the pooled frames:
    the records keep F-scores, not counts), then the gap of full labels over blind mining and the
    share of it each other detector recovers, seed by seed paired (``paired_difference``,
    ``recovered_share``), over the seeds every record ran.

    Returns:
        ``{"benchmark": "hitl-pool", "records", "heldout", "seeds", "variants", "f1",
        "f1_per_seed", "gap", "gap_significant", "recovered"}``: ``heldout`` ``{"seeds", "frames"}``
        of each record in turn, ``f1`` the seeds' means per detector, ``gap`` the paired
        difference full minus blind, ``recovered`` per detector but blind and full.

    Raises:
        InputError: fewer than two records, an incomplete one, one not on held-out factories, two
            sharing a factory, a detector's runs planned differently (the held-out factories
            aside), no detector or seed in common, or no blind mining and full labels to pool.
    """
    names = list(names) if names is not None else [f"record {k + 1}" for k in range(len(records))]
    if len(records) < 2:
        raise InputError("bench hitl-pool needs two or more bench hitl records")
    for name, record in zip(names, records):
        if not isinstance(record, dict) or record.get("benchmark") != "hitl" or "plan" not in record:
            raise InputError(f"bench hitl-pool: {name} is not a bench hitl record")
        if not record.get("complete", True):
            raise InputError(f"bench hitl-pool: {name} is a partial record; finish it first (--resume)")
        if not (record["plan"].get("heldout") or {}).get("seeds"):
            raise InputError(f"bench hitl-pool: {name} was not measured on held-out factories")
    factories = [int(s) for record in records for s in record["plan"]["heldout"]["seeds"]]
    if len(set(factories)) != len(factories):
        raise InputError("bench hitl-pool: the records share held-out factories; pool disjoint sets")
    variants = [v for v in records[0]["per_seed"] if all(v in r["per_seed"] for r in records[1:])]
    if not {"blind", "full"} <= set(variants):
        raise InputError("bench hitl-pool needs blind mining and full labels in every record")
    plans = [{**_record_plan(record), "heldout": None} for record in records]
    for variant in variants:
        mine = _run_plan(plans[0], variant)
        for name, plan in zip(names[1:], plans[1:]):
            theirs = _run_plan(plan, variant)
            if theirs != mine:
                changed = changed_fields(mine, theirs)
                if "settings" in changed and isinstance(mine.get("settings"), dict):
                    changed.remove("settings")
                    changed += [
                        f"settings.{k}"
                        for k in changed_fields(mine["settings"], theirs.get("settings") or {})
                    ]
                raise InputError(
                    f"bench hitl-pool: {name} planned {variant} differently from {names[0]}"
                    f" ({', '.join(changed)})"
                )
    by_seed = [
        {
            variant: {int(run["seed"]): run["f1"] for run in record["per_seed"][variant]}
            for variant in variants
        }
        for record in records
    ]
    seeds = sorted(set.intersection(*(set(runs[v]) for runs in by_seed for v in variants)))
    if not seeds:
        raise InputError("bench hitl-pool: no training seed ran every detector in every record")
    weights = np.array(
        [len(r["plan"]["heldout"]["seeds"]) * int(r["plan"]["heldout"]["frames"]) for r in records],
        np.float64,
    )
    f1_per_seed = {
        variant: [
            round(float(np.average([runs[variant][seed] for runs in by_seed], weights=weights)), 4)
            for seed in seeds
        ]
        for variant in variants
    }
    gap = paired_difference(f1_per_seed["full"], f1_per_seed["blind"])
    return {
        "benchmark": "hitl-pool",
        "records": names,
        "heldout": [dict(record["plan"]["heldout"]) for record in records],
        "seeds": seeds,
        "variants": variants,
        "f1": {variant: round(float(np.mean(values)), 4) for variant, values in f1_per_seed.items()},
        "f1_per_seed": f1_per_seed,
        "gap": gap,
        # (as in a record: a share of a gap no larger than its noise says nothing)
        "gap_significant": gap["standard_error"] is not None and gap["mean"] > 2 * gap["standard_error"],
        "recovered": {
            variant: recovered_share(f1_per_seed[variant], f1_per_seed["blind"], f1_per_seed["full"])
            for variant in variants
            if variant not in ("blind", "full")
        },
    }


def compare_hitl_records(
    record: dict,
    baseline: dict,
    names: tuple[str, str] = ("record", "baseline"),
    *,
    pair: tuple[str, str] | None = None,
) -> dict:
    """Seed by seed, each detector of one ``bench hitl`` record against the same detector of
    another (one setting changed, say), or one detector against another (``pair``; of one record
    when ``baseline`` is ``record``): the paired difference of their F-scores, of their mAPs, of
    their gains over their own blind mining, and of their in-factory F-scores where both runs
    measured them, over the seeds both ran.

    Args:
        record, baseline: complete ``bench hitl`` records of the same data and frames (the same
            record object twice to compare two of its detectors).
        names: what to call them (their file names, say).
        pair: ``(detector of record, detector of baseline)``: compare these two alone; by default
            every detector both ran, each against itself.

    Returns:
        ``{"benchmark": "hitl-compare", "record", "baseline", "differs", "seeds", "one_record",
        "heldout", "variants"}``: ``one_record`` whether ``baseline`` is ``record`` (two of its
        detectors compared), ``heldout`` whether F-scores are on held-out factories, ``differs``
        the plan fields that differ (``{field: [record's, baseline's]}``, settings by
        name), ``variants`` one row per compared pair (named by the detector, or "A minus B" for a
        ``pair`` of two), each ``{"variant", "baseline_variant", "f1", "map", "gain_over_blind"}``
        and ``"precision"``, ``"recall"``, ``"in_factory_f1"`` and ``"fitted_frame_f1"`` (at the
        fitted frames' thresholds, with threshold folds) where both measured it, each a
        ``paired_difference`` (record minus baseline).

    Raises:
        InputError: for a record that is not a complete ``bench hitl`` record, two records of
            other data, frames or no common seed, a ``pair`` detector a record did not run, or a
            detector against itself in one record.
    """
    for name, rec in zip(names, (record, baseline)):
        if rec.get("benchmark") != "hitl" or not rec.get("complete", True) or "per_seed" not in rec:
            raise InputError(f"{name}: not a complete bench hitl record")
    for key in ("data", "train_frames", "test_frames", "heldout_factories", "iou_threshold"):
        if record.get(key) != baseline.get(key):
            raise InputError(
                f"{names[0]} and {names[1]} ran on other {key.replace('_', ' ')}: nothing to pair"
            )
    seeds = [s for s in record["seeds"] if s in baseline["seeds"]]
    if not seeds:
        raise InputError(f"{names[0]} and {names[1]} share no seed: nothing to pair")

    one_record = record is baseline

    def by_seed(name: str, rec: dict, variant: str) -> dict[int, dict]:
        runs = {int(run["seed"]): run for run in rec["per_seed"][variant]}
        missing = [s for s in seeds if s not in runs]
        if missing:
            raise InputError(f"{name}: {variant} has no run of seed {missing[0]}: not a complete record")
        return runs

    if pair is None:
        pairs = [(v, v) for v in record["per_seed"] if v in baseline["per_seed"]]
    else:
        for name, rec, variant in zip(names, (record, baseline), pair):
            if variant not in rec["per_seed"]:
                raise InputError(f"{name} did not run {variant!r}; it ran {', '.join(rec['per_seed'])}")
        if one_record and pair[0] == pair[1]:
            raise InputError(f"{pair[0]} against itself in one record: nothing to compare")
        pairs = [tuple(pair)]
    for name, rec in zip(names, (record, baseline)):
        if "blind" not in rec["per_seed"]:
            raise InputError(f"{name}: no blind mining runs, which every bench hitl record has")
    variants = {}
    our_blind, their_blind = by_seed(names[0], record, "blind"), by_seed(names[1], baseline, "blind")
    for variant, baseline_variant in pairs:
        ours, theirs = by_seed(names[0], record, variant), by_seed(names[1], baseline, baseline_variant)
        row = {
            "variant": variant,
            "baseline_variant": baseline_variant,
            "f1": paired_difference([ours[s]["f1"] for s in seeds], [theirs[s]["f1"] for s in seeds]),
            "map": paired_difference([ours[s]["map"] for s in seeds], [theirs[s]["map"] for s in seeds]),
            "gain_over_blind": paired_difference(
                [ours[s]["f1"] - our_blind[s]["f1"] for s in seeds],
                [theirs[s]["f1"] - their_blind[s]["f1"] for s in seeds],
            ),
        }
        # Whether each seed's two runs ran one version of the library (unknown for runs of records
        # from before the runs kept it).
        versions = [(ours[s].get("library"), theirs[s].get("library")) for s in seeds]
        row["library"] = {
            "same": sum(1 for a, b in versions if a and b and a == b),
            "other": sum(1 for a, b in versions if a and b and a != b),
            "unknown": sum(1 for a, b in versions if not (a and b)),
        }
        if all("in_factory" in runs[s] for runs in (ours, theirs) for s in seeds):
            row["in_factory_f1"] = paired_difference(
                [ours[s]["in_factory"]["f1"] for s in seeds], [theirs[s]["in_factory"]["f1"] for s in seeds]
            )
        for key in ("precision", "recall"):  # whether an F that moves (or not) trades one for the other
            if all(key in runs[s] for runs in (ours, theirs) for s in seeds):
                row[key] = paired_difference([ours[s][key] for s in seeds], [theirs[s][key] for s in seeds])
        if all("fitted_frame_thresholds" in runs[s] for runs in (ours, theirs) for s in seeds):
            # Both tuned out of fold: the same networks at their fitted frames' thresholds too.
            row["fitted_frame_f1"] = paired_difference(
                [ours[s]["fitted_frame_thresholds"]["f1"] for s in seeds],
                [theirs[s]["fitted_frame_thresholds"]["f1"] for s in seeds],
            )
        row_name = variant if variant == baseline_variant else f"{variant} minus {baseline_variant}"
        variants[row_name] = row
    mine, other = ({**PLAN_BEFORE_THEY_EXISTED, **(rec.get("plan") or {})} for rec in (record, baseline))
    differs = {
        key: [mine.get(key), other.get(key)]
        for key in sorted(set(mine) | set(other))
        if key not in ("settings", "seeds", "variants") and mine.get(key) != other.get(key)
    }
    my_settings, other_settings = (_settings_as_run(p.get("settings") or {}) for p in (mine, other))
    for settings, plan in ((my_settings, mine), (other_settings, other)):  # the order the reviewer saw
        settings["review_order"] = reviewer_order(settings, plan.get("review_by"))
    for key in sorted(set(my_settings) | set(other_settings)):
        values = [my_settings.get(key), other_settings.get(key)]
        if values[0] != values[1]:
            differs[key] = values
    return {
        "benchmark": "hitl-compare",
        "record": names[0],
        "baseline": names[1],
        "record_command": record.get("command"),
        "baseline_command": baseline.get("command"),
        "differs": differs,
        "seeds": seeds,
        "one_record": one_record,
        "heldout": bool(record.get("heldout_factories")),
        "variants": variants,
    }
