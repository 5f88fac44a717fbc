"""Training data from proposals, and training with iterative hard-negative mining (paper §3.5).

Positives are point sets whose proposals match an annotated instance; the first background set is
a random sample of point sets that overlap no annotated instance. Each mining round scores the
training frames, takes the detections that match no annotated instance, adds the highest scoring
of them to the background set, and retrains. On a partially annotated data set some of those
"false positives" are real, unannotated objects: they are mined blindly here, as in the paper, and
every round is recorded so that people can review them (``store.save_training_run``).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from factorydet_core.boxes import box_iou_3d, fit_boxes
from factorydet_core.detection.box_head import (
    BACKGROUND_SHARE,
    BoxHead,
    HeadSamples,
    label_point_sets,
    share_inside,
)
from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.groups import BoxSizePrior, ProposalGroups, describe_point_sets
from factorydet_core.detection.model import DetectionModel
from factorydet_core.detection.scoring import check_exponent
from factorydet_core.io.dataset import Dataset
from factorydet_core.metrics import IGNORE_IOU, detection_metrics
from factorydet_core.metrics import tune_class_thresholds as tune_thresholds
from factorydet_core.proposals.candidates import point_set_features
from factorydet_core.proposals.visibility import FreeSpace
from factorydet_core.session.queue import queue_order as queue_order_of
from factorydet_core.session.store import HIDE_LABELLED_IOU
from factorydet_core.training.settings import check_threshold_folds
from factorydet_core.types import (
    PROBABILITY_EXPONENT,
    SCORE_FLOOR,
    SCORE_THRESHOLD,
    THRESHOLD_OBJECTIVES,
    Cancelled,
    Detections,
    InputError,
    check_threshold_objective,
)

Progress = Callable[[str, int, int], None]
"""Called with (what, done, total)."""


@dataclasses.dataclass(frozen=True)
class FrameProposals:
    """What training and evaluation keep of one frame's front half."""

    frame_index: int
    proposal_boxes: np.ndarray
    """(M, 7) boxes of the proposals."""
    patch_sets: tuple[tuple[int, ...], ...]
    groups: ProposalGroups
    label_boxes: np.ndarray
    """(R, 7) annotated boxes."""
    label_class_ids: np.ndarray
    """(R,) their classes."""
    annotation_features: np.ndarray | None
    """(A, 20, 5, 5, 5) features of the annotated instances' own points (extra positives, as
    detectors add ground-truth boxes to their proposals when training); ``None`` when the front
    half computes no 3DmFV (``feature`` "none")."""
    annotation_descriptors: np.ndarray
    """(A, D) their geometric descriptors."""
    annotation_class_ids: np.ndarray
    """(A,) their classes."""
    annotation_instance_ids: np.ndarray
    """(A,) their data set instance ids."""
    ignore_boxes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 7)))
    """(Q, 7) places that are neither object nor background for training (a session's pre-labels
    no person has confirmed yet, held negatives' places with ``LoopSettings.hold_places``): the
    point sets on them are left out (``ignored_point_sets``), and detections on them count neither
    way when training tunes the thresholds."""
    label_model_box_mask: np.ndarray | None = None
    """(R,) which label boxes are the model's own, as a person accepted them (a reviewer's Object
    verdict on a mined box, a pre-label confirmed unmoved: ``store.MODEL_BOX_ORIGINS``); ``None``:
    none. With ``train_with_mining(model_box_targets=False)`` they teach their class alone."""
    label_tuning_ignore_mask: np.ndarray | None = None
    """(R,) which labels train as objects but count neither way when training tunes the score
    thresholds (``LoopSettings.threshold_label_min_points``: a person's labels sparser than the
    annotation policy the evaluation measures against); ``None``: none."""
    label_own_sets: tuple[tuple[int, ...], ...] | None = None
    """(R,) for each label, the patch set (patch ids) of the point set it was made from, which is
    its object whatever share of the set's points its box holds, or ``()`` for none; ``None``:
    none. A pseudo-label's (``with_pseudo_labels``): the model boxed that set, and its box need
    not hold the whole set."""

    def with_labels(
        self,
        boxes: np.ndarray,
        class_ids: np.ndarray,
        instance_classes: dict[int, int] | None = None,
        ignore_boxes: np.ndarray | None = None,
        model_box_mask: np.ndarray | None = None,
        tuning_ignore_mask: np.ndarray | None = None,
    ) -> FrameProposals:
        """The same proposals with other labels (a session's corrected ones).

        Args:
            boxes: (R, 7) label boxes.
            class_ids: (R,) their classes.
            instance_classes: data set instance id -> class id of the labels that are still the
                data set's instances; only their own-point samples are kept, with that class.
                ``None`` keeps them all as they are.
            ignore_boxes: (Q, 7) places training leaves out (``None``: none).
            model_box_mask: (R,) which boxes are the model's own (``label_model_box_mask``).
            tuning_ignore_mask: (R,) which labels the thresholds' tuning ignores
                (``label_tuning_ignore_mask``).
        """
        num_labels = len(np.asarray(boxes).reshape(-1, 7))
        keep = np.ones(len(self.annotation_instance_ids), bool)
        classes = np.array(self.annotation_class_ids)
        if instance_classes is not None:
            keep = np.array([int(i) in instance_classes for i in self.annotation_instance_ids], bool)
            classes = np.array([instance_classes.get(int(i), -1) for i in self.annotation_instance_ids])
        return dataclasses.replace(
            self,
            label_boxes=np.asarray(boxes, np.float64).reshape(-1, 7),
            label_class_ids=np.asarray(class_ids, np.int64),
            annotation_features=None if self.annotation_features is None else self.annotation_features[keep],
            annotation_descriptors=self.annotation_descriptors[keep],
            annotation_class_ids=classes[keep].astype(np.int64),
            annotation_instance_ids=self.annotation_instance_ids[keep],
            ignore_boxes=np.asarray([] if ignore_boxes is None else ignore_boxes, np.float64).reshape(-1, 7),
            label_model_box_mask=_label_mask(model_box_mask, num_labels, "model_box_mask"),
            label_tuning_ignore_mask=_label_mask(tuning_ignore_mask, num_labels, "tuning_ignore_mask"),
            label_own_sets=None,
        )

    def with_ignored(self, boxes: np.ndarray | None) -> FrameProposals:
        """The same proposals with more places training leaves out: ``boxes`` (K, 7) added to
        ``ignore_boxes`` (``None`` or none: this frame as it is)."""
        if boxes is None or not len(boxes):
            return self
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        return dataclasses.replace(self, ignore_boxes=np.concatenate([self.ignore_boxes, boxes]))

    def with_pseudo_labels(
        self,
        boxes: np.ndarray | None,
        class_ids: np.ndarray | None,
        patch_sets: Sequence[Sequence[int]] | None = None,
    ) -> FrameProposals:
        """The same proposals with ``boxes`` (K, 7) of ``class_ids`` (K,) added as labels whose
        box is the model's own (``label_model_box_mask``): confident mined negatives that teach
        their predicted class until a person reviews them (``LoopSettings.pseudo_label_confident``).
        ``patch_sets``: the K mined point sets' patch ids, each its label's object whatever share
        of it the box holds (``label_own_sets``). ``None`` or no boxes: this frame as it is."""
        if boxes is None or not len(boxes):
            return self
        boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
        class_ids = np.asarray(class_ids, np.int64).reshape(-1)
        sets = [()] * len(boxes) if patch_sets is None else [tuple(int(p) for p in s) for s in patch_sets]
        if len(class_ids) != len(boxes) or len(sets) != len(boxes):
            raise InputError(
                f"with_pseudo_labels: {len(boxes)} boxes, {len(class_ids)} classes and {len(sets)} point sets"
            )
        mask = self.label_model_box_mask
        mask = np.zeros(len(self.label_boxes), bool) if mask is None else mask
        own = self.label_own_sets if self.label_own_sets is not None else ((),) * len(self.label_boxes)
        tuning = self.label_tuning_ignore_mask
        if tuning is not None:  # (a pseudo-label is not checked for its points: it counts)
            tuning = np.concatenate([tuning, np.zeros(len(boxes), bool)])
        return dataclasses.replace(
            self,
            label_tuning_ignore_mask=tuning,
            label_boxes=np.concatenate([self.label_boxes.reshape(-1, 7), boxes]),
            label_class_ids=np.concatenate([np.asarray(self.label_class_ids, np.int64), class_ids]),
            label_model_box_mask=np.concatenate([mask, np.ones(len(boxes), bool)]),
            label_own_sets=(*own, *sets),
        )

    def own_set_labels(self) -> list[tuple[int, int]]:
        """``(point set, label)`` index pairs of the labels made from a point set
        (``label_own_sets``); sets this front half does not have are dropped."""
        if self.label_own_sets is None or not any(self.label_own_sets):
            return []
        lookup = self._point_set_lookup()
        return [
            (lookup[patch_set], label)
            for label, patch_set in enumerate(self.label_own_sets)
            if patch_set and patch_set in lookup
        ]

    def _point_set_lookup(self) -> dict[tuple[int, ...], int]:
        """Patch set (its patch ids) -> the point set (group) made of it."""
        lookup: dict[tuple[int, ...], int] = {}
        for proposal, group in enumerate(self.groups.group_ids):
            lookup.setdefault(tuple(self.patch_sets[proposal]), int(group))
        return lookup

    def ignored_point_sets(self) -> np.ndarray:
        """Indices of the point sets on an ignored place: half or more of the set's sampled points
        in an ``ignore_boxes`` box (``box_head.BACKGROUND_SHARE``, what keeps a set out of the
        background next to a label), or, without sampled points, a proposal of the set overlapping
        one at ``metrics.IGNORE_IOU`` or more (what keeps a detection there out of the metrics)."""
        if not len(self.ignore_boxes) or not self.groups.num_groups:
            return np.zeros(0, np.int64)
        if self.groups.points is not None:
            share = share_inside(self.groups.points, self.ignore_boxes)
            return np.flatnonzero(share.max(axis=1) >= BACKGROUND_SHARE).astype(np.int64)
        on_ignored = box_iou_3d(self.proposal_boxes, self.ignore_boxes).max(axis=1) >= IGNORE_IOU
        return np.unique(self.groups.group_ids[on_ignored]).astype(np.int64)

    def point_set_ids(self, patch_sets) -> np.ndarray:
        """Indices of the point sets (groups) made of the given patch sets; unknown ones are
        dropped (a front half with other settings cut the frame differently)."""
        lookup = self._point_set_lookup()
        return np.array(sorted({lookup[tuple(p)] for p in patch_sets if tuple(p) in lookup}), np.int64)


def _annotation_samples(
    frame, result, detector: Detector
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Features, descriptors and classes of the annotated instances' points in the segmented cloud."""
    cloud = result.cloud
    lookup = dict(zip(frame.labels.instance_ids.tolist(), frame.labels.class_ids.tolist()))
    ids, counts = np.unique(cloud.point_instance_ids, return_counts=True)
    chosen = [int(i) for i, n in zip(ids, counts) if i in lookup and n >= detector.params.min_proposal_points]
    point_lists = [np.flatnonzero(cloud.point_instance_ids == i) for i in chosen]
    features = None
    if detector.params.feature != "none":
        features = point_set_features(
            cloud.points,
            result.grid,
            result.voxel_features,
            point_lists,
            detector.params.weighting,
            detector.params.feature,
        ).reshape(-1, 20, 5, 5, 5)
    boxes = fit_boxes(cloud.points, point_lists)
    num_voxels = np.array([len(np.unique(result.grid.point_voxel_ids[p])) for p in point_lists])
    descriptors = describe_point_sets(cloud.points, point_lists, boxes, num_voxels, result.floor_plane)
    return (
        features,
        descriptors,
        np.array([lookup[i] for i in chosen], np.int64),
        np.array(chosen, np.int64),
    )


def collect_proposals(
    dataset: Dataset,
    frame_indices: Sequence[int],
    detector: Detector,
    progress: Progress | None = None,
) -> list[FrameProposals]:
    """Run the front half on ``frame_indices`` and keep what the back half needs."""
    out = []
    for n, index in enumerate(frame_indices):
        frame = dataset.frame(index)
        result = detector.propose(frame, detector.history(dataset, index))
        groups = detector.group(result)
        annotated = _annotation_samples(frame, result, detector)
        out.append(
            FrameProposals(
                frame_index=int(index),
                proposal_boxes=np.array(result.proposals.boxes),
                patch_sets=result.proposals.patch_sets,
                groups=groups,
                label_boxes=np.array(frame.labels.boxes),
                label_class_ids=np.array(frame.labels.class_ids),
                annotation_features=annotated[0],
                annotation_descriptors=annotated[1],
                annotation_class_ids=annotated[2],
                annotation_instance_ids=annotated[3],
            )
        )
        if progress is not None:
            progress("proposals", n + 1, len(frame_indices))
    return out


def group_overlaps(frame: FrameProposals, reference_boxes: np.ndarray) -> np.ndarray:
    """(G, R) the best IoU of any proposal of each point set with each reference box."""
    iou = box_iou_3d(frame.proposal_boxes, reference_boxes)
    best = np.zeros((frame.groups.num_groups, len(reference_boxes)))
    np.maximum.at(best, frame.groups.group_ids, iou)
    return best


def group_labels(
    frame: FrameProposals,
    reference_boxes: np.ndarray,
    reference_class_ids: np.ndarray,
    background_id: int,
    positive_iou: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Label each point set: the class of the reference it matches at ``positive_iou``, else
    background.

    Returns:
        ``(labels, overlaps_any)``: (G,) label ids, and (G,) whether the set overlaps any reference.
    """
    labels, best_iou = _labels_and_best_iou(
        frame, reference_boxes, reference_class_ids, background_id, positive_iou
    )
    return labels, best_iou > 0


def _labels_and_best_iou(
    frame: FrameProposals,
    reference_boxes: np.ndarray,
    reference_class_ids: np.ndarray,
    background_id: int,
    positive_iou: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``group_labels``' labels, with (G,) each set's best IoU with any reference (0 without any)."""
    overlap = group_overlaps(frame, reference_boxes)
    labels = np.full(frame.groups.num_groups, background_id, np.int64)
    if not overlap.shape[1]:
        return labels, np.zeros(len(labels))
    best = overlap.argmax(axis=1)
    best_iou = overlap[np.arange(len(best)), best]
    hit = best_iou >= positive_iou
    labels[hit] = np.asarray(reference_class_ids)[best[hit]]
    return labels, best_iou


@dataclasses.dataclass
class TrainingRun:
    """The result of ``train_with_mining``."""

    model: DetectionModel
    rounds: list[dict]
    """Per round: ``round``, ``num_positives``, ``num_background``, ``fit_seconds``, ``epochs``,
    ``continued`` (the fit went on from a model), ``box_quality_seconds`` (the regressor's fit, in
    round 0, on a thread of its own alongside the networks' fits), ``box_quality_wait_seconds``
    (round 0: how long the round's model waited for it before scoring), ``box_quality`` (round 0:
    "fitted", "kept" from a model, "same rows, kept" when a refit would have given the model's
    back, "continued, N trees", or ``None`` without one), ``score_seconds`` (scoring the training
    frames, and with threshold folds the fold models scoring theirs and the thresholds' tuning;
    the fold models' fits are the folds record's ``fit_seconds``),
    ``train_metrics`` (detection on the training frames against the annotations) and ``mined``
    (the negatives added after that round: frame, proposal, box, patch set, score, class)."""
    models: list[DetectionModel]
    """The model after each round."""
    train_frames: list[int]
    fold_models: list[FoldModel] = dataclasses.field(default_factory=list)
    """With ``threshold_folds``, the last round's fold models (a next round can go on from them)."""


def _training_set(
    frames: list[FrameProposals],
    frame_labels: dict[int, np.ndarray],
    background: dict[int, set[int]],
    background_id: int,
    annotation_positives: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features, descriptors and labels: the positive point sets (``frame_labels``: each frame's
    ``group_labels``), the background sets chosen so far, and the annotated instances' own points."""
    if any(f.groups.features is None for f in frames):
        raise InputError(
            'this classifier reads each point set\'s 3DmFV: propose the frames with feature "aggregated"'
            ' or "direct", not "none"'
        )
    features, descriptors, labels = [], [], []
    if annotation_positives:
        features += [f.annotation_features for f in frames]
        descriptors += [f.annotation_descriptors for f in frames]
        labels += [f.annotation_class_ids for f in frames]
    for frame in frames:
        set_labels = frame_labels[frame.frame_index]
        positive = np.flatnonzero(set_labels != background_id)
        negative = np.array(sorted(background.get(frame.frame_index, set())), np.int64)
        chosen = np.concatenate([positive, negative])
        features.append(frame.groups.features[chosen])
        descriptors.append(frame.groups.descriptors[chosen])
        labels.append(np.concatenate([set_labels[positive], np.full(len(negative), background_id)]))
    return np.concatenate(features), np.concatenate(descriptors), np.concatenate(labels)


def _label_mask(mask: np.ndarray | None, num_labels: int, name: str) -> np.ndarray | None:
    if mask is None:
        return None
    mask = np.asarray(mask, bool).reshape(-1)
    if len(mask) != num_labels:
        raise InputError(f"{name}: expected {num_labels} entries (one per label), got {len(mask)}")
    return mask


def box_target_mask(frame: FrameProposals, model_box_targets: bool = True) -> np.ndarray:
    """(R,) which of the frame's label boxes training learns boxes from: all of them, or with
    ``model_box_targets`` False those that are not the model's own (``label_model_box_mask``)."""
    learn = np.ones(len(frame.label_boxes), bool)
    if not model_box_targets and frame.label_model_box_mask is not None:
        learn &= ~frame.label_model_box_mask
    return learn


def box_targets(frames: Sequence[FrameProposals], model_box_targets: bool = True) -> dict[int, np.ndarray]:
    """Per frame index, (R,) which label boxes training learns boxes from (``box_target_mask``),
    except that a class none of whose labels is a box target learns from all of its boxes: the
    head, the regressor and the size prior need some box of each class they are to box (a session
    whose every label of a class is a confirmed pre-label, say)."""
    masks = {f.frame_index: box_target_mask(f, model_box_targets) for f in frames}
    if model_box_targets or not frames:
        return masks
    class_ids = np.concatenate([f.label_class_ids for f in frames]).astype(np.int64)
    learn = np.concatenate([masks[f.frame_index] for f in frames]).astype(bool)
    boxed = np.unique(class_ids[learn])
    for frame in frames:
        masks[frame.frame_index] |= ~np.isin(frame.label_class_ids, boxed)
    return masks


def _prior_boxes(
    frames: Sequence[FrameProposals], targets: dict[int, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The label boxes and classes the size prior is measured on: the box targets (``box_targets``)."""
    boxes = np.concatenate([f.label_boxes for f in frames]).reshape(-1, 7)
    class_ids = np.concatenate([f.label_class_ids for f in frames]).astype(np.int64)
    keep = np.concatenate([targets[f.frame_index] for f in frames]).astype(bool)
    return boxes[keep], class_ids[keep]


def head_labels(frame: FrameProposals, background_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point set's label for the box head by where its points lie
    (``box_head.label_point_sets``): ``(labels, owners)``, -1 for sets left out of training."""
    if frame.groups.points is None:
        raise InputError("the box head needs each point set's points: collect the proposals again")
    labels, owners = label_point_sets(
        frame.groups.points, frame.label_boxes, frame.label_class_ids, background_id
    )
    for group, label in frame.own_set_labels():  # the set a pseudo-label was made from is its object
        labels[group], owners[group] = frame.label_class_ids[label], label
    return labels, owners


def _head_training_set(
    frames: list[FrameProposals],
    frame_labels: dict[int, np.ndarray],
    frame_owners: dict[int, np.ndarray],
    background: dict[int, set[int]],
    excluded: dict[int, set[int]],
    targets_of: dict[int, np.ndarray],
) -> tuple[HeadSamples, np.ndarray]:
    """The box head's samples (every labelled point set of every frame, sets in ``excluded`` left
    out) and (M,) which of them are hard negatives (the sets in ``background``). A set whose label
    is not a box target (``targets_of``, per frame index (R,), from ``box_targets``) gets a NaN
    target: it teaches its class alone."""
    parts, hard = [], []
    for frame in frames:
        labels = frame_labels[frame.frame_index].copy()
        owners = frame_owners[frame.frame_index]
        labels[sorted(excluded.get(frame.frame_index, ()))] = -1
        keep = np.flatnonzero(labels >= 0)
        targets = np.full((frame.groups.num_groups, 7), np.nan)
        owned = np.flatnonzero(owners >= 0)
        owned = owned[targets_of[frame.frame_index][owners[owned]]]
        targets[owned] = frame.label_boxes[owners[owned]]
        groups = frame.groups
        parts.append(
            HeadSamples(
                points=groups.points[keep],
                anchor_boxes=groups.fitted_boxes[keep],
                descriptors=groups.descriptors[keep],
                labels=labels[keep],
                target_boxes=targets[keep],
            )
        )
        hard.append(np.isin(keep, sorted(background.get(frame.frame_index, ()))))
    return HeadSamples.concatenate(parts), np.concatenate(hard)


def score_frames(
    model: DetectionModel,
    frames: list[FrameProposals],
    score_threshold: float,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> list[dict]:
    """Detections of every frame down to ``score_threshold``, with the annotated references
    (``metrics.detection_metrics``'s input)."""
    out = []
    for n, frame in enumerate(frames):
        if should_stop is not None and should_stop():
            raise Cancelled("training cancelled")
        if progress is not None:
            progress("score", n, len(frames))
        out.append(scored_frame(frame, kept_detections(model, frame, score_threshold)))
    return out


def kept_detections(model: DetectionModel, frame: FrameProposals, score_threshold: float) -> Detections:
    """One frame's part of ``score_frames``: ``model``'s detections down to ``score_threshold``
    after NMS (the suppressed ones dropped)."""
    detections = model.detect(frame.proposal_boxes, frame.groups, score_threshold=score_threshold)
    return detections.subset(detections.kept_mask)


def scored_frame(frame: FrameProposals, kept: Detections) -> dict:
    """``score_frames``' item for one frame: its ``kept_detections`` with its references (its
    labels) and, where some labels train but the thresholds' tuning ignores them
    (``FrameProposals.label_tuning_ignore_mask``), that (R,) mask as ``tuning_ignore_mask``
    (``for_tuning``)."""
    item = {
        "frame_index": frame.frame_index,
        "detections": kept,
        "boxes": kept.boxes,
        "class_ids": kept.class_ids,
        "scores": kept.scores,
        "reference_boxes": frame.label_boxes,
        "reference_class_ids": frame.label_class_ids,
        "ignore_boxes": frame.ignore_boxes,
    }
    if frame.label_tuning_ignore_mask is not None and frame.label_tuning_ignore_mask.any():
        item["tuning_ignore_mask"] = frame.label_tuning_ignore_mask
    return item


def for_tuning(item: dict) -> dict:
    """A ``scored_frame`` item as the thresholds' tuning sees it: the labels of its
    ``tuning_ignore_mask`` moved from the references to the ignored places (a detection on one
    is neither a hit nor a false alarm, and it is nobody's miss); the item itself if it has none."""
    mask = item.get("tuning_ignore_mask")
    if mask is None:
        return item
    boxes = np.asarray(item["reference_boxes"], np.float64).reshape(-1, 7)
    class_ids = np.asarray(item["reference_class_ids"])
    ignore = np.asarray(item["ignore_boxes"], np.float64).reshape(-1, 7)
    return {
        **item,
        "reference_boxes": boxes[~mask],
        "reference_class_ids": class_ids[~mask],
        "ignore_boxes": np.concatenate([ignore, boxes[mask]]),
    }


Scorer = Callable[
    [DetectionModel, list[FrameProposals], float, Progress | None, Callable[[], bool] | None],
    list[dict],
]
"""What scores a mining round's frames (``train_with_mining``'s ``score``): ``score_frames`` in
this process, or ``scale.jobs.scoring`` on Ray workers; the same items either way."""


def with_tuned_thresholds(
    model: DetectionModel,
    scored: list[dict],
    positive_iou: float = 0.6,
    max_threshold: float = 1.0,
    objective: str = "class",
) -> DetectionModel:
    """``model`` with each class's score threshold tuned to the highest F-score on ``scored``
    (``score_frames``'s output for ``model``, down to ``types.SCORE_FLOOR``;
    ``metrics.tune_class_thresholds``, none above ``max_threshold``): the class's own, or with
    ``objective`` "total" that of all classes pooled; a class without a true positive keeps the
    global threshold. Labels the tuning ignores are ignored places there (``for_tuning``)."""
    tuned = tune_thresholds(
        [for_tuning(item) for item in scored],
        model.class_names,
        positive_iou,
        max_threshold=max_threshold,
        objective=objective,
        untuned_threshold=model.score_threshold,
    )
    return dataclasses.replace(
        model,
        class_score_thresholds={
            name: float(t) for name, t in zip(model.class_names, tuned) if np.isfinite(t)
        },
    )


class _Background:
    """``fn(*args)`` on a thread of its own, started at once; ``result`` waits for it."""

    def __init__(self, fn: Callable, *args) -> None:
        self._outcome: list = []
        # (a daemon: a cancelled run leaves it to finish its fit without keeping the process alive)
        self._thread = threading.Thread(target=self._run, args=(fn, args), daemon=True)
        self._thread.start()

    def _run(self, fn: Callable, args: tuple) -> None:
        try:
            self._outcome.append((True, fn(*args)))
        except BaseException as exc:  # handed to whoever waits for it
            self._outcome.append((False, exc))

    def running(self) -> bool:
        return self._thread.is_alive()

    def result(self, should_stop: Callable[[], bool] | None = None):
        """``fn``'s return value (or its exception, raised here); ``should_stop`` is polled while
        waiting (``types.Cancelled``: the thread is left to finish on its own)."""
        while self._thread.is_alive():
            if should_stop is not None and should_stop():
                raise Cancelled("training cancelled")
            self._thread.join(0.2)
        ok, value = self._outcome[0]
        if not ok:
            raise value
        return value


@dataclasses.dataclass(frozen=True)
class FoldModel:
    """A threshold fold's model (``train_with_mining``'s ``threshold_folds``): a classifier fitted
    on every training frame but ``frame_indices``, the fold it scores."""

    frame_indices: tuple[int, ...]
    classifier: ProposalClassifier | BoxHead


def threshold_fold_frames(frames: Sequence[FrameProposals], num_folds: int) -> list[tuple[int, ...]]:
    """The frame indices of each of ``num_folds`` folds of ``frames``: contiguous runs of frame
    indices (stretches of the drive), empty folds left out."""
    indices = sorted(frame.frame_index for frame in frames)
    return [
        tuple(int(i) for i in block) for block in np.array_split(np.asarray(indices), num_folds) if len(block)
    ]


def _fit_folds(
    frames: list[FrameProposals],
    num_folds: int,
    classifier: ProposalClassifier | BoxHead,
    fit: Callable,
    progress: Progress | None,
    init_folds: Sequence[FoldModel] = (),
    round_epochs: int = 0,
) -> tuple[list[FoldModel], int]:
    """A model per fold (``threshold_fold_frames``: a fold is a stretch of the drive whose objects
    its model mostly never saw), of ``classifier``'s settings fitted (``fit``) on the frames of the
    other folds: afresh, or, with ``round_epochs`` and a fold model of ``init_folds`` for the very
    same frames (an earlier run's), going on from that model for ``round_epochs`` epochs, as the
    run's own model goes on from the model it continues (that model never saw the fold either). A
    fold whose other folds hold no object is left out (nothing would score it).

    Returns:
        ``(fold_models, num_continued)``: the fitted fold models, and how many of them went on
        from ``init_folds``.
    """
    ordered = sorted(frames, key=lambda frame: frame.frame_index)
    earlier = {fold.frame_indices: fold.classifier for fold in init_folds} if round_epochs else {}
    folds = threshold_fold_frames(frames, num_folds)
    fitted_folds, num_continued = [], 0
    for k, fold in enumerate(folds):
        in_fold = set(fold)
        rest = [frame for frame in ordered if frame.frame_index not in in_fold]

        def fold_progress(epoch, epochs, k=k):
            progress("threshold folds", k * epochs + epoch, len(folds) * epochs)

        fit_progress = None if progress is None else fold_progress
        start_from = earlier.get(fold)
        trainer = (
            dataclasses.replace(classifier)
            if start_from is None
            else dataclasses.replace(classifier, epochs=round_epochs)
        )
        fitted, _ = fit(trainer, rest, start_from, fit_progress)
        if fitted is None:
            continue
        num_continued += start_from is not None
        fitted_folds.append(FoldModel(fold, fitted))
    return fitted_folds, num_continued


def _out_of_fold_scored(
    frames: list[FrameProposals],
    fold_models: Sequence[FoldModel],
    model_of: Callable,
    score: Scorer,
    should_stop: Callable[[], bool] | None,
) -> list[dict]:
    """``score``'s items for the frames of every fold of ``fold_models`` (``_fit_folds``), each
    scored by its fold's model, in the order of ``frames`` (a frame of no fold left out)."""
    position = {frame.frame_index: k for k, frame in enumerate(frames)}
    out: dict[int, dict] = {}
    for fold in fold_models:
        fold_frames = [frames[position[i]] for i in fold.frame_indices]
        scored = score(model_of(fold.classifier), fold_frames, SCORE_FLOOR, None, should_stop)
        out.update(zip((position[i] for i in fold.frame_indices), scored))
    return [out[k] for k in range(len(frames)) if k in out]


def train_with_mining(
    frames: list[FrameProposals],
    classifier: ProposalClassifier,
    *,
    rounds: int = 2,
    negatives_per_round: int = 500,
    initial_negatives: int = 2000,
    positive_iou: float = 0.6,
    fragment_iou: float = 0.4,
    fragments_per_frame: int | None = None,
    score_threshold: float = SCORE_THRESHOLD,
    nms_iou: float = 0.25,
    use_box_prior: bool = True,
    annotation_positives: bool = True,
    seed: int = 0,
    progress: Progress | None = None,
    background_sets: Mapping[int, Iterable[Sequence[int]]] | None = None,
    excluded_sets: Mapping[int, Iterable[Sequence[int]]] | None = None,
    mine_after_last: bool = False,
    hold_score: float | None = None,
    hold_places: bool = False,
    pseudo_label_score: float | None = None,
    should_stop: Callable[[], bool] | None = None,
    box_quality: BoxQuality | None = None,
    reuse_box_quality: BoxQuality | None = None,
    quality_round_trees: int = 0,
    mining_threshold: float | None = None,
    tune_class_thresholds: bool = True,
    probability_exponent: float = PROBABILITY_EXPONENT,
    round_epochs: int = 0,
    init_model: ProposalClassifier | BoxHead | None = None,
    score: Scorer = score_frames,
    queue_order: str = "score",
    review_extra: int | None = 0,
    model_box_targets: bool = True,
    threshold_folds: int = 0,
    threshold_objective: str = "class",
    init_folds: Sequence[FoldModel] = (),
) -> TrainingRun:
    """Train, then ``rounds`` times mine hard negatives and retrain.

    Args:
        frames: training frames' proposals (``collect_proposals``).
        classifier: an unfitted classifier; its settings are reused for every round.
        rounds: mining rounds after the first training (0: no mining).
        round_epochs: with more than 0, every round after the first goes on training the previous
            round's classifier for this many epochs (``fit``'s ``init_model``) instead of training
            afresh for the classifier's ``epochs``: a round then costs a fraction of a first fit.
            0 trains every round afresh (the paper's procedure).
        init_model: a fitted classifier (``classifier``'s type, classes and network) that even the
            first round goes on from, for ``round_epochs`` epochs: a 'next' round continuing a
            session's model. Needs ``round_epochs`` > 0.
        score: scores each round's model on the frames (``Scorer``): ``score_frames`` here, or
            ``scale.jobs.scoring``'s on Ray workers.
        negatives_per_round: N, the first false positives in ``queue_order`` added per round.
        queue_order: "score": the N highest scoring, as the paper; "class": the predicted classes
            take turns, each one's by score (``session.queue.queue_order``), so a class the model
            has barely learned gets its share of the cut and of the review queue.
        review_extra: the next this many false positives after the first N (in ``queue_order``;
            ``None``: all) of the run's last mining (after the last round with
            ``mine_after_last``, else the round before it) go to that round's record's
            ``queued``: the review queue's alone, neither background nor held
            (``LoopSettings.review_extra``).
        model_box_targets: learn boxes from every label (True), or let the labels whose box is
            the model's own (``FrameProposals.label_model_box_mask``) teach their class alone: the
            box head's box and IoU losses, the box quality regressor and the size prior leave
            them out, unless their class has no other box (``box_targets``;
            ``LoopSettings.model_box_targets``).
        initial_negatives: size of the random first background set (the paper starts from ~2,000).
        positive_iou: IoU with an annotated box that makes a point set a positive, and a detection
            a true positive when mining.
        fragment_iou: point sets that overlap an annotated box, but at most at this IoU (parts of
            an object, an object with its neighbours), all start in the background set: they are
            the negatives a detector meets next to every object, and without them a fragment
            scores as high as the whole object and wins NMS. Sets between this and
            ``positive_iou`` are left out of training. 0 starts from the paper's set alone
            (random sets overlapping nothing).
        fragments_per_frame: at most this many fragments per frame, sampled at random (``None``:
            all). A frame has about a thousand; on many frames they would dominate the fit's time.
        score_threshold: the models' operating score threshold; detections scoring below it are
            not mined unless ``mining_threshold`` says otherwise.
        nms_iou: NMS threshold of the detections that are mined.
        use_box_prior: box detections by the class sizes of the training annotations.
        annotation_positives: also train on each annotated instance's own points.
        seed: seeds the first background sample.
        progress: called with ("fit", epoch, epochs), ("score", frame, frames),
            ("threshold folds", epoch, epochs), ("round", round, rounds + 1) and ("box quality",
            0, 1) when the regressor's fit starts and when the run starts waiting for it, then
            (trees fitted, trees) from its thread while the run waits.
        background_sets: per frame, patch sets that start in the background set (confirmed
            background and negatives mined before), unless a label now makes them positives.
        excluded_sets: per frame, patch sets that are never background nor mined (real objects
            whose segment is wrong).
        mine_after_last: also mine after the last round; those negatives go to the record (to be
            reviewed) but into no fit.
        hold_score: mined negatives scoring at least this are held out of the background (left
            out of training, not mined again) instead of added to it (``LoopSettings.hold_confident``);
            they stay in the record, to be reviewed. ``None``: all go to the background (the paper).
        hold_places: a held negative also holds its place: its box (when it overlaps no label at
            ``HIDE_LABELLED_IOU``) joins its frame's ``ignore_boxes`` for the rounds after it, so
            every point set on it is neither background nor mined, and detections on it count
            neither way when thresholds are tuned (``LoopSettings.hold_places``).
        pseudo_label_score: mined negatives scoring at least this, off every label (box IoU below
            ``HIDE_LABELLED_IOU``), become labels of their predicted class whose box is the
            model's own (``FrameProposals.with_pseudo_labels``) for the rounds after, instead of
            background or held: self-training on the model's likeliest unlabelled objects
            (``LoopSettings.pseudo_label_confident``; ``None``: none). Without
            ``model_box_targets`` they teach their class alone.
        should_stop: asked between batches and frames (and the regressor's trees); True raises
            ``types.Cancelled``.
        box_quality: an unfitted ``BoxQuality``, fitted once on the frames' labels (it does not
            depend on the classifier) and shared by every round's model, so that mining sees the
            scores the model will give, or a fitted one (a model's that the run continues), used as
            it is; ``None`` keeps the size prior's box and the class probability as score. Needs
            ``use_box_prior``.
        reuse_box_quality: a fitted regressor (the continued model's) that stands in for fitting
            an unfitted ``box_quality`` when it was fitted on the very rows and settings this fit
            would use (``BoxQuality.training_digest``): the fit would give it back, so a round
            whose labels did not change since that model skips the regressor's fit.
        quality_round_trees: with ``reuse_box_quality`` and rows it was not fitted on, more than 0
            boosts it on with this many trees fitted to these rows (``BoxQuality.continued``)
            instead of fitting ``box_quality`` afresh.
        mining_threshold: detections scoring at least this are mined (``None``: the operating
            ``score_threshold``, as the paper). With box quality a score is a probability (to
            ``probability_exponent``) times a predicted IoU, so few clear the operating threshold
            on a few frames: a lower one fills the mined set and the review queue with the next
            most confident false positives.
        tune_class_thresholds: give each round's model a score threshold per class, the one up to
            ``score_threshold`` of highest F-score at ``positive_iou`` on the training frames' annotations
            (``metrics.tune_class_thresholds``; the scores mining computes anyway). The
            classifier's probabilities differ in scale between classes, and one threshold drops
            a whole class (``docs/default_model_validation.json``). ``False``: ``score_threshold``
            for all.
        threshold_folds: with ``tune_class_thresholds`` and 2 or more, the last round's model is
            tuned instead on scores no model fitted: the frames are cut into this many folds
            (contiguous runs of frame indices: stretches of the drive), each fold's frames are
            scored by a model of ``classifier``'s settings fitted afresh on the other folds'
            point sets as they stand after the last round (``_out_of_fold_scored``), and each
            class's threshold is the best on all of them together, with no ceiling. Scores on
            fitted frames run high, so thresholds tuned there are too high and
            ``score_threshold`` caps them; the cap holds every class at the operating score
            whatever the labels taught. Costs about one more fit of ``classifier``'s epochs.
            The round's record gets ``threshold_folds``: the folds, their seconds, the thresholds
            and those the fitted frames would have given, and the out-of-fold thresholds of
            each objective (``by_objective``). 0: tuned on the fitted frames.
        init_folds: fold models of an earlier run (its ``TrainingRun.fold_models``): with
            ``init_model`` (that run's model) and ``round_epochs``, a fold of the very same frames
            goes on from its model for
            ``round_epochs`` epochs instead of a fit afresh (a 'next' round continuing a session's
            model continues its folds too; ``LoopSettings.continue_folds``); other folds are
            fitted afresh.
        threshold_objective: whose F-score a tuned threshold is best for
            (``types.THRESHOLD_OBJECTIVES``): each class's own ("class"), or that of all
            classes' detections pooled ("total", the figure benchmarks report; a class of few,
            poorly scored objects is then held above where its own F would flood, up to off).
        probability_exponent: with ``box_quality``, the model's score is the class probability
            to this power times the predicted IoU (``DetectionModel.probability_exponent``); it
            ranks the mined negatives too. 1 is the plain product; the command line and the app
            train with 0.5 (see ``settings.LoopSettings``).
    """
    if not frames:
        raise InputError("train_with_mining: no training frames")
    check_exponent(probability_exponent)
    if mining_threshold is None:
        mining_threshold = score_threshold
    if not 0.0 <= mining_threshold <= 1.0:
        raise InputError(f"mining_threshold must lie in [0, 1], got {mining_threshold}")
    queue_order_of([], [], queue_order)  # a bad order fails before any work
    if review_extra is not None and (
        isinstance(review_extra, bool) or not isinstance(review_extra, (int, np.integer)) or review_extra < 0
    ):
        raise InputError(f"review_extra must be an integer >= 0 or None, got {review_extra!r}")
    if rounds < 0 or negatives_per_round < 0 or initial_negatives < 0:
        raise InputError("rounds, negatives_per_round and initial_negatives must be >= 0")
    if not 0.0 <= fragment_iou < positive_iou:
        raise InputError(f"fragment_iou must lie in [0, positive_iou), got {fragment_iou}")
    if fragments_per_frame is not None and fragments_per_frame < 0:
        raise InputError(f"fragments_per_frame must be >= 0 or None, got {fragments_per_frame}")
    if isinstance(round_epochs, bool) or not isinstance(round_epochs, (int, np.integer)) or round_epochs < 0:
        raise InputError(f"round_epochs must be an integer >= 0, got {round_epochs!r}")
    if hold_score is not None and not 0.0 < hold_score <= 1.0:
        raise InputError(f"hold_score must lie in (0, 1] or be None, got {hold_score}")
    if pseudo_label_score is not None and not 0.0 < pseudo_label_score <= 1.0:
        raise InputError(f"pseudo_label_score must lie in (0, 1] or be None, got {pseudo_label_score}")
    if init_model is not None and not round_epochs:
        raise InputError("init_model is trained on for round_epochs epochs: set round_epochs > 0")
    check_threshold_folds(threshold_folds)
    check_threshold_objective(threshold_objective)
    if threshold_folds > len(frames):
        raise InputError(f"threshold_folds: {threshold_folds} folds of {len(frames)} training frames")
    background_id = classifier.background_id
    num_classes = len(classifier.class_names)
    is_head = isinstance(classifier, BoxHead)
    targets_of = box_targets(frames, model_box_targets)
    box_prior = None
    if use_box_prior or is_head:
        box_prior = BoxSizePrior.from_boxes(*_prior_boxes(frames, targets_of), num_classes)
    # Each point set's label and best overlap, fixed for the whole run: the annotations do not change.
    # The head's sets are labelled by their points, not by their boxes, and it needs no overlaps.
    frame_labels, frame_best_iou, frame_owners = {}, {}, {}
    for frame in frames:
        _set_frame_labels(
            frame, background_id, positive_iou, is_head, frame_labels, frame_owners, frame_best_iou
        )
    by_index = {f.frame_index: f for f in frames}
    excluded = {
        index: set(by_index[index].point_set_ids(sets).tolist())
        for index, sets in (excluded_sets or {}).items()
        if index in by_index
    }
    # Sets on a place nobody has decided on yet (an unconfirmed pre-label, a held negative's
    # place) are neither object nor background: left out as the excluded ones are, mined neither.
    # A set a confirmed label makes an object stays one.
    for frame in frames:
        _exclude_ignored(frame, frame_labels[frame.frame_index], background_id, excluded)
    # The first background set: point sets that overlap no annotated box, sampled evenly, and the
    # fragments. None for the head (it has no overlaps): it draws its background afresh every
    # epoch and keeps only hard negatives as a set.
    rng = np.random.default_rng(seed)
    pool = [
        (index, int(g))
        for index, best_iou in frame_best_iou.items()
        for g in np.flatnonzero(best_iou == 0)
        if int(g) not in excluded.get(index, ())
    ]
    picked = rng.choice(len(pool), min(initial_negatives, len(pool)), replace=False) if pool else []
    background: dict[int, set[int]] = {}
    for i in picked:
        background.setdefault(pool[i][0], set()).add(pool[i][1])
    if fragment_iou > 0:
        for index, best_iou in frame_best_iou.items():
            fragments = np.flatnonzero((best_iou > 0) & (best_iou <= fragment_iou))
            fragments = fragments[frame_labels[index][fragments] == background_id]
            if fragments_per_frame is not None and len(fragments) > fragments_per_frame:
                fragments = np.sort(rng.choice(fragments, fragments_per_frame, replace=False))
            if len(fragments):
                background.setdefault(index, set()).update(
                    int(g) for g in fragments if int(g) not in excluded.get(index, ())
                )
    for index, sets in (background_sets or {}).items():
        if index not in by_index:
            continue
        for g in by_index[index].point_set_ids(sets):
            if frame_labels[index][g] == background_id and int(g) not in excluded.get(index, ()):
                background.setdefault(index, set()).add(int(g))

    # The regressor's trees fitted so far, and whether the run waits for them: its fit reports
    # them (``progress("box quality", trees, of)``) only then, the networks' fits having the bar
    # before.
    # Its thread and the run's share them: one lock, so that the reports come in order.
    quality_trees = {"done": 0, "total": 1, "waiting": False}
    quality_lock = threading.Lock()

    def tree_fitted(done: int, total: int) -> None:
        if should_stop is not None and should_stop():
            raise Cancelled("training cancelled")  # (the fit stops at its next tree)
        with quality_lock:
            quality_trees.update(done=done, total=total)
            # (not its start: the run said that when it began to wait)
            if progress is not None and quality_trees["waiting"] and done:
                progress("box quality", done, total)

    def fit_quality(excluded_now: dict[int, set[int]]) -> tuple[BoxQuality, str, float]:
        """The regressor the run's models box with, how it came (``TrainingRun`` rounds'
        ``box_quality``) and its seconds."""
        if progress is not None:
            progress("box quality", 0, 1)
        start = time.perf_counter()
        rows, targets = box_quality.training_rows(
            frames,
            box_prior,
            num_classes,
            excluded_now,
            box_targets=targets_of,
        )
        # (fit keeps its own digest: only a regressor to reuse needs one here)
        digest = None if reuse_box_quality is None else box_quality.training_digest(rows, targets)
        if digest is not None and getattr(reuse_box_quality, "training_digest_", None) == digest:
            fitted, source = reuse_box_quality, "same rows, kept"
        elif reuse_box_quality is not None and quality_round_trees:
            fitted = reuse_box_quality.continued(rows, targets, quality_round_trees, tree_fitted)
            fitted.training_digest_ = digest  # fitted last to these rows: a round on them keeps it
            source = f"continued, {quality_round_trees} trees"
        else:
            fitted, source = dataclasses.replace(box_quality).fit(rows, targets, tree_fitted), "fitted"
        seconds = time.perf_counter() - start
        del rows, targets
        return fitted, source, seconds

    # The regressor's fit needs the labels alone, and the networks' fits need no regressor: it is
    # fitted on a thread of its own while the first round's network (and, in a run of one round,
    # the fold models) fit, and waited for when that round's model first scores. Most of a next
    # round is this fit, and a network's fit leaves part of the cores idle.
    quality_fit: _Background | None = None
    kept_quality: tuple[BoxQuality | None, str | None, float] = (None, None, 0.0)
    if box_quality is not None and box_prior is not None and hasattr(box_quality, "trees_"):
        kept_quality = (box_quality, "kept", 0.0)
    elif box_quality is not None and box_prior is not None:
        # (a copy of the sets left out: mining adds to them once the round's model has scored)
        quality_fit = _Background(fit_quality, {index: set(sets) for index, sets in excluded.items()})

    quality_wait = [0.0]  # seconds the run waited for it, its fit done alongside the networks'

    def quality_now() -> tuple[BoxQuality | None, str | None, float]:
        nonlocal kept_quality, quality_fit
        if quality_fit is not None:
            waiting = time.perf_counter()
            if progress is not None and quality_fit.running():
                with quality_lock:
                    progress("box quality", 0, 1)  # (what the run is waiting for now)
                    # From here on its trees move the bar, those fitted already first.
                    quality_trees["waiting"] = True
                    if quality_trees["done"]:
                        progress("box quality", quality_trees["done"], quality_trees["total"])
            kept_quality, quality_fit = quality_fit.result(should_stop), None
            quality_wait[0] = time.perf_counter() - waiting
        return kept_quality

    def fit(trainer, fit_frames, start_from, fit_progress):
        """``trainer`` fitted on ``fit_frames``' sets as they stand; ``(fitted, labels)``, or
        ``(None, labels)`` when no set is an object."""
        if is_head:
            samples, hard = _head_training_set(
                fit_frames, frame_labels, frame_owners, background, excluded, targets_of
            )
            if not (samples.labels != background_id).any():
                return None, samples.labels
            fitted = trainer.fit(
                samples,
                box_prior.sizes,
                hard,
                progress=fit_progress,
                should_stop=should_stop,
                init_model=start_from,
            )
            return fitted, samples.labels
        features, descriptors, labels = _training_set(
            fit_frames, frame_labels, background, background_id, annotation_positives
        )
        if not (labels != background_id).any():
            return None, labels
        fitted = trainer.fit(
            features,
            labels,
            descriptors,
            progress=fit_progress,
            should_stop=should_stop,
            init_model=start_from,
        )
        return fitted, labels

    def model_of(fitted) -> DetectionModel:
        return DetectionModel(
            fitted,
            box_prior,
            score_threshold,
            nms_iou,
            box_quality=quality_now()[0],
            probability_exponent=probability_exponent,
        )

    records, models = [], []
    fold_models: list[FoldModel] = []
    previous = init_model
    for round_index in range(rounds + 1):
        fit_progress = None if progress is None else (lambda e, n: progress("fit", e, n))
        start_from = previous if round_epochs else None
        trainer = (
            dataclasses.replace(classifier)
            if start_from is None
            else dataclasses.replace(classifier, epochs=round_epochs)
        )
        fitted, labels = fit(trainer, frames, start_from, fit_progress)
        if fitted is None:
            raise InputError(
                "no point set lies in an annotated box: nothing to learn from"
                if is_head
                else f"no proposal matches an annotated instance at IoU {positive_iou}: nothing to learn from"
            )
        previous = fitted
        folds_seconds = 0.0
        # (the last model's thresholds tuned out of fold: its fold models fit now, score below)
        out_of_fold_round = bool(tune_class_thresholds and threshold_folds and round_index == rounds)
        if out_of_fold_round:
            # The last model's thresholds are tuned where no model fitted instead: each fold's
            # frames scored by a model fitted on the other folds' (the sets as they stand now, as
            # the round's own model saw them). Fitted before the round's model scores: they need
            # no regressor, which may still be fitting.
            fold_start = time.perf_counter()
            fold_models, num_continued = _fit_folds(
                frames, threshold_folds, classifier, fit, progress, init_folds,
                round_epochs if init_model is not None else 0,
            )  # fmt: skip
            folds_seconds = time.perf_counter() - fold_start
        model = model_of(fitted)
        start = time.perf_counter()
        scored = score(model, frames, min(SCORE_FLOOR, mining_threshold), progress, should_stop)
        folds_record = None
        if tune_class_thresholds:
            model = with_tuned_thresholds(
                model, scored, positive_iou, max_threshold=score_threshold, objective=threshold_objective
            )
        if out_of_fold_round:
            fold_start = time.perf_counter()
            out_of_fold = _out_of_fold_scored(frames, fold_models, model_of, score, should_stop)
            fitted_frame_thresholds = dict(model.class_score_thresholds or {})
            # The fitted frames' thresholds of every objective too (the same scores; the run's own
            # are the model's): a benchmark measures the same network at what the settings without
            # folds would have given.
            fitted_frame_by_objective = {
                objective: fitted_frame_thresholds
                if objective == threshold_objective
                else dict(
                    with_tuned_thresholds(
                        model, scored, positive_iou, max_threshold=score_threshold, objective=objective
                    ).class_score_thresholds
                    or {}
                )
                for objective in THRESHOLD_OBJECTIVES
            }
            # Both objectives' thresholds from the same scores: a benchmark measures the same
            # network at each (the model keeps ``threshold_objective``'s).
            by_objective = {
                objective: dict(
                    with_tuned_thresholds(
                        model, out_of_fold, positive_iou, objective=objective
                    ).class_score_thresholds
                    or {}
                )
                for objective in THRESHOLD_OBJECTIVES
            }
            model = dataclasses.replace(model, class_score_thresholds=dict(by_objective[threshold_objective]))
            folds_record = {
                "folds": threshold_folds,
                "seconds": round(folds_seconds + time.perf_counter() - fold_start, 2),
                "fit_seconds": round(folds_seconds, 2),
                "fold_frames": [list(fold.frame_indices) for fold in fold_models],
                "continued": num_continued,
                "thresholds": dict(model.class_score_thresholds or {}),
                "fitted_frame_thresholds": fitted_frame_thresholds,
                "fitted_frame_by_objective": fitted_frame_by_objective,
                "objective": threshold_objective,
                "by_objective": by_objective,
            }
        metrics = detection_metrics(
            scored, fitted.class_names, positive_iou, score_threshold, model.class_thresholds()
        )
        metrics.pop("pr_curves")
        _, quality_source, quality_seconds = quality_now()
        record = {
            "round": round_index,
            "num_positives": int((labels != background_id).sum()),
            "num_background": int((labels == background_id).sum()),
            "fit_seconds": round(fitted.fit_seconds_, 2),
            "epochs": trainer.epochs,
            # Background recalibration: drawn background sets left out of the fit's losses, summed
            # over its epochs (None: off; 0 in a fit from scratch, where it does not act).
            "recalibrated": sum(e["recalibrated"] for e in fitted.history_)
            if getattr(trainer, "recalibrate_background", None) is not None
            else None,
            "continued": start_from is not None,
            # The regressor is fitted once, before the first round (0 when kept from a model).
            "box_quality_seconds": round(quality_seconds, 2) if round_index == 0 else 0.0,
            "box_quality": quality_source if round_index == 0 else None,
            "box_quality_wait_seconds": round(quality_wait[0], 2) if round_index == 0 else 0.0,
            "score_seconds": round(time.perf_counter() - start, 2),
            "train_metrics": metrics,
            "mined": [],
        }
        if folds_record is not None:
            record["threshold_folds"] = folds_record
        if round_index < rounds or mine_after_last:
            mined = []
            for frame, item in zip(frames, scored):
                detections = item["detections"]
                operating = detections.scores >= mining_threshold
                best = (
                    box_iou_3d(detections.boxes, frame.label_boxes).max(axis=1)
                    if len(frame.label_boxes)
                    else np.zeros(len(detections))
                )
                group_of = frame.groups.group_ids[detections.proposal_ids]
                known = background.get(frame.frame_index, set()) | excluded.get(frame.frame_index, set())
                # A point set that is a positive (some proposal of it matches an annotation) stays
                # one, even when the box chosen for its detection does not match.
                set_labels = frame_labels[frame.frame_index]
                for k in np.flatnonzero(operating & (best < positive_iou)):
                    if int(group_of[k]) in known or set_labels[group_of[k]] != background_id:
                        continue
                    proposal = int(detections.proposal_ids[k])
                    mined.append(
                        {
                            "frame_index": frame.frame_index,
                            "group": int(group_of[k]),
                            "proposal": proposal,
                            "box": [round(float(v), 4) for v in detections.boxes[k]],
                            "patch_set": [int(p) for p in frame.patch_sets[proposal]],
                            "score": round(float(detections.scores[k]), 4),
                            "predicted_class": fitted.class_names[int(detections.class_ids[k])],
                            "probabilities": [round(float(p), 4) for p in detections.probabilities[k]],
                            "best_annotated_iou": round(float(best[k]), 4),
                        }
                    )
            cut = queue_order_of(
                [m["score"] for m in mined], [m["predicted_class"] for m in mined], queue_order
            )
            record["mined"] = [mined[k] for k in cut[:negatives_per_round]]
            last_mining = round_index == (rounds if mine_after_last else rounds - 1)
            extra = cut[negatives_per_round:]
            extra = extra if review_extra is None else extra[:review_extra]
            # For the reviewer alone, and only the last mining's: an earlier round's would be the
            # false positives of a model the run has since trained on.
            record["queued"] = [mined[k] for k in extra] if last_mining else []
            record["num_false_positives"] = len(mined)
            record["num_held"] = 0
            record["num_pseudo_labelled"] = 0
            held_boxes: dict[int, list] = {}
            pseudo: dict[int, list[dict]] = {}
            for m in record["mined"]:
                if (
                    pseudo_label_score is not None
                    and m["score"] >= pseudo_label_score
                    and m["best_annotated_iou"] < HIDE_LABELLED_IOU
                ):
                    # Very confident and off every label: most likely a real object nobody
                    # labelled. It teaches its predicted class until a person decides.
                    pseudo.setdefault(m["frame_index"], []).append(m)
                    record["num_pseudo_labelled"] += 1
                elif hold_score is not None and m["score"] >= hold_score:
                    # Confident: perhaps a real object nobody labelled. Neither background nor
                    # mined again until a person decides (it stays in the review queue).
                    excluded.setdefault(m["frame_index"], set()).add(m["group"])
                    record["num_held"] += 1
                    if hold_places and m["best_annotated_iou"] < HIDE_LABELLED_IOU:
                        held_boxes.setdefault(m["frame_index"], []).append(m["box"])
                else:
                    background.setdefault(m["frame_index"], set()).add(m["group"])
            if pseudo:
                frames = [
                    _with_pseudo(frame, pseudo.get(frame.frame_index), fitted.class_names) for frame in frames
                ]
                for frame in frames:
                    if frame.frame_index in pseudo:
                        _set_frame_labels(
                            frame,
                            background_id,
                            positive_iou,
                            is_head,
                            frame_labels,
                            frame_owners,
                            frame_best_iou,
                        )
                        # A set inside a pseudo-label is its object now, not background.
                        labels_of = frame_labels[frame.frame_index]
                        if frame.frame_index in background:
                            background[frame.frame_index] = {
                                g for g in background[frame.frame_index] if labels_of[g] == background_id
                            }
                targets_of = box_targets(frames, model_box_targets)
            if held_boxes:
                frames = [frame.with_ignored(held_boxes.get(frame.frame_index)) for frame in frames]
                for frame in frames:
                    if frame.frame_index in held_boxes:
                        labels_of = frame_labels[frame.frame_index]
                        _exclude_ignored(frame, labels_of, background_id, excluded, background)
        records.append(record)
        models.append(model)
        if progress is not None:
            progress("round", round_index + 1, rounds + 1)
    return TrainingRun(models[-1], records, models, [f.frame_index for f in frames], fold_models)


def _set_frame_labels(
    frame: FrameProposals,
    background_id: int,
    positive_iou: float,
    is_head: bool,
    frame_labels: dict[int, np.ndarray],
    frame_owners: dict[int, np.ndarray],
    frame_best_iou: dict[int, np.ndarray],
) -> None:
    """Each point set's label from the frame's labels, into ``frame_labels`` by frame index: the
    box head's by where the points lie (``head_labels``), with each set's owning label into
    ``frame_owners``; the paper classifier's by box overlap (``_labels_and_best_iou``), with each
    set's best overlap into ``frame_best_iou``."""
    index = frame.frame_index
    if is_head:
        frame_labels[index], frame_owners[index] = head_labels(frame, background_id)
    else:
        labels, best_iou = _labels_and_best_iou(
            frame, frame.label_boxes, frame.label_class_ids, background_id, positive_iou
        )
        for group, label in frame.own_set_labels():  # (the set a pseudo-label was made from is its object)
            labels[group] = frame.label_class_ids[label]
            best_iou[group] = 1.0
        frame_labels[index], frame_best_iou[index] = labels, best_iou


def _with_pseudo(
    frame: FrameProposals, mined: list[dict] | None, class_names: Sequence[str]
) -> FrameProposals:
    """``frame`` with the mined negatives ``mined`` (``train_with_mining``'s records) as pseudo-labels
    of their predicted classes (``FrameProposals.with_pseudo_labels``)."""
    if not mined:
        return frame
    names = list(class_names)
    return frame.with_pseudo_labels(
        np.asarray([m["box"] for m in mined], np.float64),
        np.asarray([names.index(m["predicted_class"]) for m in mined]),
        [m["patch_set"] for m in mined],
    )


def _exclude_ignored(
    frame: FrameProposals,
    set_labels: np.ndarray,
    background_id: int,
    excluded: dict[int, set],
    background: dict[int, set] | None = None,
) -> None:
    """Leave the frame's point sets on its ignored places (``ignored_point_sets``) out of
    training: into ``excluded`` and out of ``background``, except those a label makes objects
    (``set_labels`` (G,), each set's class)."""
    ignored = frame.ignored_point_sets()
    ignored = ignored[set_labels[ignored] == background_id].tolist()
    if ignored:
        excluded.setdefault(frame.frame_index, set()).update(ignored)
        if background is not None and frame.frame_index in background:
            background[frame.frame_index].difference_update(ignored)


def proposals_to_arrays(frames: Sequence[FrameProposals]) -> dict[str, np.ndarray]:
    """Flat arrays holding ``frames`` (for an ``.npz`` cache); ``proposals_from_arrays`` inverts it."""
    out: dict[str, np.ndarray] = {"frame_indices": np.array([f.frame_index for f in frames], np.int64)}
    for k, f in enumerate(frames):
        sizes = np.array([len(p) for p in f.patch_sets], np.int64)
        flat = np.array([i for p in f.patch_sets for i in p], np.int64)
        arrays = {
            "proposal_boxes": f.proposal_boxes,
            "patch_set_sizes": sizes,
            "patch_set_ids": flat,
            "group_ids": f.groups.group_ids,
            "representatives": f.groups.representatives,
            "descriptors": f.groups.descriptors,
            "anchor_mask": (
                np.zeros(len(f.proposal_boxes), bool)
                if f.groups.anchor_mask is None
                else f.groups.anchor_mask
            ),
            "label_boxes": f.label_boxes,
            "label_class_ids": f.label_class_ids,
            "annotation_descriptors": f.annotation_descriptors,
            "annotation_class_ids": f.annotation_class_ids,
            "annotation_instance_ids": f.annotation_instance_ids,
        }
        if f.groups.features is not None:
            arrays["features"] = f.groups.features
            arrays["annotation_features"] = f.annotation_features
        if f.groups.points is not None:
            arrays["points"] = f.groups.points
        if f.groups.free_space is not None:
            arrays |= {f"free_space/{n}": v for n, v in f.groups.free_space.to_arrays().items()}
        out |= {f"{k}/{name}": np.asarray(value) for name, value in arrays.items()}
    return out


def proposals_from_arrays(arrays: Mapping[str, np.ndarray]) -> list[FrameProposals]:
    """The frames stored by ``proposals_to_arrays``."""
    frames = []
    for k, index in enumerate(np.asarray(arrays["frame_indices"]).tolist()):
        a = {name.split("/", 1)[1]: v for name, v in arrays.items() if name.startswith(f"{k}/")}
        bounds = np.concatenate([[0], np.cumsum(a["patch_set_sizes"])])
        flat = a["patch_set_ids"].tolist()
        patch_sets = tuple(tuple(flat[lo:hi]) for lo, hi in zip(bounds[:-1], bounds[1:]))
        space = {n.split("/", 1)[1]: v for n, v in a.items() if n.startswith("free_space/")}
        groups = ProposalGroups(
            a["group_ids"],
            a["representatives"],
            a.get("features"),
            a["descriptors"],
            a.get("anchor_mask"),
            FreeSpace.from_arrays(space) if space else None,
            a.get("points"),
            a["proposal_boxes"][a["representatives"]],
        )
        frames.append(
            FrameProposals(
                frame_index=int(index),
                proposal_boxes=a["proposal_boxes"],
                patch_sets=patch_sets,
                groups=groups,
                label_boxes=a["label_boxes"],
                label_class_ids=a["label_class_ids"],
                annotation_features=a.get("annotation_features"),
                annotation_descriptors=a["annotation_descriptors"],
                annotation_class_ids=a["annotation_class_ids"],
                annotation_instance_ids=a["annotation_instance_ids"],
            )
        )
    return frames
