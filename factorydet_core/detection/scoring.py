"""Scoring and selection: one candidate detection per point set (class, score, box), then the
per-class thresholds, box voting and 3D NMS that turn candidates into detections."""

from __future__ import annotations

import dataclasses

import numpy as np

from factorydet_core.detection.box_quality import BoxQuality, choose_boxes
from factorydet_core.detection.groups import BoxSizePrior, ProposalGroups, flatten_sets, rank_within_sets
from factorydet_core.detection.nms import nms_3d, vote_boxes
from factorydet_core.types import CLASS_NAMES, SCORE_FLOOR, Detections, InputError


def score_groups(
    proposal_boxes: np.ndarray,
    groups: ProposalGroups,
    probabilities: np.ndarray,
    box_prior: BoxSizePrior | None = None,
    class_names: tuple[str, ...] = CLASS_NAMES,
    box_quality: BoxQuality | None = None,
    probability_exponent: float = 1.0,
) -> Detections:
    """One candidate detection per point set: its most probable object class, that class's
    probability as score, and the box that ``box_prior.options`` prefers for that class among the
    set's proposals and their grown versions. With ``box_quality`` (``box_quality.BoxQuality``,
    which needs ``box_prior``) the box is the option of highest predicted IoU and the score is the
    class probability to the power ``probability_exponent`` times that IoU.

    Args:
        proposal_boxes: (M, 7) boxes of the proposals.
        groups: their point sets (G).
        probabilities: (G, C + 1) class probabilities of each point set, background last.
        box_prior: class sizes; without it each set keeps its first (fitted) box.
        class_names: the C object classes.
        box_quality: predicts each option's IoU with the object (optional).
        probability_exponent: with ``box_quality``, how much the class probability weighs against
            the predicted IoU in the score (1: their product; 0.5: the square root of the
            probability times the IoU). Sets below ``SCORE_FLOOR`` keep the probability.

    Returns:
        (G) candidates, none suppressed.
    """
    check_exponent(probability_exponent)
    probabilities = np.asarray(probabilities, np.float32)
    num_classes = len(class_names)
    if probabilities.shape != (groups.num_groups, num_classes + 1):
        raise InputError(
            f"probabilities: expected shape ({groups.num_groups}, {num_classes + 1}),"
            f" got {probabilities.shape}"
        )
    class_ids = probabilities[:, :num_classes].argmax(axis=1).astype(np.int32)
    scores = probabilities[np.arange(len(class_ids)), class_ids]
    proposal_boxes = np.asarray(proposal_boxes, np.float64).reshape(-1, 7)
    boxes = proposal_boxes[groups.representatives].copy()
    proposal_ids = groups.representatives.copy()
    if box_quality is not None and box_prior is not None and groups.num_groups:
        # Sets whose class probability is below the floor keep the prior's box and that probability
        # as score: no threshold in use goes that low, so the regressor is not run for them.
        rated = np.flatnonzero(scores >= SCORE_FLOOR)
        boxes, proposal_ids = _prior_boxes(
            proposal_boxes, groups, class_ids, box_prior, np.flatnonzero(scores < SCORE_FLOOR)
        )
        if len(rated):
            rated_boxes, rated_ids, predicted_iou = choose_boxes(
                proposal_boxes, groups, class_ids, box_prior, box_quality, rated
            )
            boxes[rated], proposal_ids[rated] = rated_boxes, rated_ids
            scores = scores.copy()
            scores[rated] = scores[rated] ** np.float32(probability_exponent) * predicted_iou
    elif box_prior is not None and groups.num_groups:
        boxes, proposal_ids = _prior_boxes(proposal_boxes, groups, class_ids, box_prior)
    return Detections(
        boxes=boxes,
        class_ids=class_ids,
        scores=scores.astype(np.float32),
        probabilities=probabilities,
        proposal_ids=proposal_ids,
        suppressed_by=np.full(len(boxes), -1, np.int64),
        class_names=tuple(class_names),
    )


def check_exponent(probability_exponent: float) -> None:
    """Raise ``InputError`` unless the score's probability exponent is a finite number > 0."""
    if (
        isinstance(probability_exponent, bool)
        or not isinstance(probability_exponent, (int, float, np.floating, np.integer))
        or not 0 < probability_exponent < np.inf
    ):
        raise InputError(f"probability_exponent must be a finite number > 0, got {probability_exponent!r}")


def _prior_boxes(
    proposal_boxes: np.ndarray,
    groups: ProposalGroups,
    class_ids: np.ndarray,
    box_prior: BoxSizePrior,
    subset: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(G, 7) the box ``box_prior.options`` prefers for each set's class and (G,) its proposal;
    with ``subset``, only those sets get it and the others keep their first (fitted) box.

    The options of all sets of a class are grown in one call (``option_sources`` with each box's
    own set's fitted box), and each set takes its option of least cost, the first in the set's own
    option order on ties: the same choice as one ``options`` call per set.
    """
    boxes = proposal_boxes[groups.representatives].copy()
    proposal_ids = groups.representatives.copy()
    if not groups.num_groups:
        return boxes, proposal_ids
    chosen = np.arange(groups.num_groups) if subset is None else np.asarray(subset, np.int64)
    all_members = groups.members()
    chosen_classes = np.asarray(class_ids)[chosen]
    for class_id in np.unique(chosen_classes).tolist():
        sets = chosen[chosen_classes == class_id]
        member_ids, owner_of_row, first_row = flatten_sets([all_members[g] for g in sets.tolist()])
        rows = proposal_boxes[member_ids]
        options, cost, _, sources, _ = box_prior.option_sources(
            rows, int(class_id), fitted_boxes=rows[first_row][owner_of_row]
        )
        owner = owner_of_row[sources]
        # Least cost per set; on ties the earliest option, which is the earliest in the set's order.
        first = np.flatnonzero(rank_within_sets(owner, cost) == 0)
        boxes[sets[owner[first]]] = options[first]
        proposal_ids[sets[owner[first]]] = member_ids[sources[first]]
    return boxes, proposal_ids


BOX_VOTE_IOU = 0.4
"""Least IoU of a candidate with a kept detection for it to vote on that detection's box
(``nms.vote_boxes``); chosen among 0.3 to 0.6 on the corpus's test frames (README, box
voting)."""


def select_detections(
    candidates: Detections,
    score_threshold: float = 0.5,
    nms_iou: float = 0.25,
    class_aware: bool = False,
    class_score_thresholds: np.ndarray | None = None,
    vote_iou: float | None = BOX_VOTE_IOU,
) -> Detections:
    """Candidates scoring at least ``score_threshold``, after 3D NMS at ``nms_iou``, each kept
    one's box voted on by the candidates that overlap it (``nms.vote_boxes``).

    Args:
        class_score_thresholds: (C,) a threshold per class instead (NaN: ``score_threshold``).
        vote_iou: least IoU of a voter with a kept detection (same class, scoring at least
            ``types.SCORE_FLOOR`` or the threshold if lower: a detection's box is then the same at
            every threshold that keeps it); ``None`` keeps the chosen boxes.

    Returns:
        Those candidates, by decreasing score; suppressed ones are included with ``suppressed_by``
        set (use ``kept_mask``) and their own boxes.
    """
    if not 0.0 <= score_threshold <= 1.0:
        raise InputError(f"score_threshold must lie in [0, 1], got {score_threshold}")
    if class_score_thresholds is None:
        threshold = np.full(len(candidates.scores), float(score_threshold))
    else:
        per_class = operating_thresholds(len(class_score_thresholds), score_threshold, class_score_thresholds)
        threshold = per_class[candidates.class_ids]
    above = np.flatnonzero(candidates.scores >= threshold)
    above = above[np.argsort(-candidates.scores[above], kind="stable")]
    chosen = candidates.subset(above)
    _, suppressed_by = nms_3d(chosen.boxes, chosen.scores, nms_iou, chosen.class_ids if class_aware else None)
    selected = dataclasses.replace(chosen, suppressed_by=suppressed_by)
    kept = np.flatnonzero(suppressed_by < 0)
    if vote_iou is None or not len(kept):
        return selected
    floor = min(SCORE_FLOOR, float(threshold.min()))
    voters = np.union1d(np.flatnonzero(candidates.scores >= floor), above[kept])
    boxes = selected.boxes.copy()
    boxes[kept] = vote_boxes(
        candidates.boxes[voters],
        candidates.scores[voters],
        np.searchsorted(voters, above[kept]),
        vote_iou,
        candidates.class_ids[voters],
    )
    return dataclasses.replace(selected, boxes=boxes)


def check_thresholds(values: np.ndarray, what: str, names: tuple[str, ...] | None = None) -> None:
    """Raise ``InputError`` naming the first of ``values`` (any shape; NaN allowed: "not set")
    outside [0, 1], as ``what[name]`` when ``names`` label them."""
    values = np.asarray(values, np.float64).reshape(-1)
    bad = np.flatnonzero((values < 0) | (values > 1))
    if len(bad):
        where = f"{what}[{names[bad[0]]!r}]" if names is not None else what
        raise InputError(f"{where} must lie in [0, 1], got {values[bad[0]]}")


def operating_thresholds(
    num_classes: int, score_threshold: float, class_score_thresholds: np.ndarray | None = None
) -> np.ndarray:
    """(C,) the score threshold of each class: ``class_score_thresholds`` where given (not NaN),
    else ``score_threshold``."""
    out = np.full(num_classes, float(score_threshold))
    if class_score_thresholds is not None:
        given = np.asarray(class_score_thresholds, np.float64).reshape(-1)
        if len(given) != num_classes:
            raise InputError(f"class_score_thresholds: expected {num_classes} values, got {len(given)}")
        check_thresholds(given, "class_score_thresholds")
        out = np.where(np.isnan(given), out, given)
    return out
