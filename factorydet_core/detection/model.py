"""A trained detection model: the proposal classifier, the class size prior that boxes its
detections, the box quality regressor that picks and scores those boxes, and the operating
thresholds, saved together as one checkpoint (``NAME.pt``, ``NAME.json`` and, with a box quality
regressor, ``NAME.boxq.npz``)."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from factorydet_core.detection.box_head import BoxHead, check_head_input, head_candidates
from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.groups import BoxSizePrior, ProposalGroups
from factorydet_core.detection.scoring import (
    BOX_VOTE_IOU,
    check_exponent,
    check_thresholds,
    score_groups,
    select_detections,
)
from factorydet_core.proposals.settings import FrontEndParams, front_end_from_record
from factorydet_core.types import Detections, InputError

DEFAULT_MODEL = Path(__file__).parent.parent / "models" / "default.pt"
"""The checkpoint shipped with the package (trained on the demo data, see the README)."""

PAPER_MODEL = Path(__file__).parent.parent / "models" / "paper.pt"
"""The shipped checkpoint of the paper's pipeline (3DmFV-Net classifier, box options, box quality
regressor), trained on the same corpus as ``DEFAULT_MODEL``: the benchmarks' reference."""


@dataclasses.dataclass
class DetectionModel:
    """Classifier, box prior and thresholds.

    Args:
        classifier: a fitted ``ProposalClassifier`` (or any classifier with ``predict_proba``,
            ``labels_`` and ``input_kind``: "features", "descriptors" or "features+descriptors").
        box_prior: class sizes that pick each detection's box; ``None`` keeps fitted boxes.
        score_threshold: operating score threshold.
        nms_iou: 3D NMS threshold.
        front_end: the front-half settings the training proposals were made with, saved whole in
            the checkpoint (``Detector.for_model`` runs the model on them); ``None``: unknown,
            the data's preset applies.
        box_quality: picks each detection's box among the prior's options by predicted IoU and
            multiplies its score by that IoU (``box_quality.BoxQuality``); ``None`` keeps the
            prior's choice and the class probability as score.
        class_score_thresholds: per class name, its own operating threshold (tuned on the
            training frames, ``metrics.tune_class_thresholds``); classes not in it use
            ``score_threshold``. ``None``: one threshold for all.
        probability_exponent: with ``box_quality``, a detection's score is its class probability
            to this power times its predicted IoU (``scoring.score_groups``); checkpoints from
            before it was kept load with 1.
        vote_iou: after NMS, the candidates overlapping a kept detection at least this much vote
            on its box (``nms.vote_boxes``); ``None`` keeps the chosen box. Voting needs no
            training, so checkpoints from before it load with the default.
    """

    classifier: object
    box_prior: BoxSizePrior | None = None
    score_threshold: float = 0.5
    nms_iou: float = 0.25
    front_end: FrontEndParams | None = None
    box_quality: BoxQuality | None = None
    class_score_thresholds: dict[str, float] | None = None
    probability_exponent: float = 1.0
    vote_iou: float | None = BOX_VOTE_IOU

    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(self.classifier.labels_[:-1])

    def class_thresholds(self) -> np.ndarray | None:
        """(C,) the per-class operating thresholds (NaN: ``score_threshold``), or ``None``."""
        if not self.class_score_thresholds:
            return None
        return np.array([self.class_score_thresholds.get(c, np.nan) for c in self.class_names], np.float64)

    def probabilities(self, groups: ProposalGroups) -> np.ndarray:
        """(G, C + 1) class probabilities of each point set."""
        return group_probabilities(self.classifier, groups)

    @property
    def method(self) -> str:
        """Which back half this is (``METHODS``): "box_head" for the learned box head
        (``box_head.BoxHead``) boxing its own detections, "head_options" for the box head's class
        probabilities with the box options of the size prior chosen by the box quality regressor,
        "paper" for the paper's classifier with those box options."""
        if isinstance(self.classifier, BoxHead):
            return "head_options" if self.box_quality is not None else "box_head"
        return "paper"

    def candidates(self, proposal_boxes: np.ndarray, groups: ProposalGroups) -> Detections:
        """Every point set as a candidate detection (no threshold, no NMS), in point-set order."""
        if self.method == "box_head":
            return head_candidates(groups, self.classifier, self.probability_exponent)
        return score_groups(
            proposal_boxes,
            groups,
            self.probabilities(groups),
            self.box_prior,
            self.class_names,
            self.box_quality,
            self.probability_exponent,
        )

    def detect(
        self,
        proposal_boxes: np.ndarray,
        groups: ProposalGroups,
        score_threshold: float | None = None,
        nms_iou: float | None = None,
    ) -> Detections:
        """Candidates above the score threshold after NMS (suppressed ones flagged). Without
        ``score_threshold``, the model's operating point: its per-class thresholds when it has
        them; with it, that one threshold for every class."""
        return select_detections(
            self.candidates(proposal_boxes, groups),
            self.score_threshold if score_threshold is None else score_threshold,
            self.nms_iou if nms_iou is None else nms_iou,
            class_score_thresholds=self.class_thresholds() if score_threshold is None else None,
            vote_iou=self.vote_iou,
        )

    def save(self, path: str | os.PathLike, note: dict | None = None) -> Path:
        """Checkpoint: the classifier's state dict at ``path`` and a JSON note beside it."""
        if not isinstance(self.classifier, (ProposalClassifier, BoxHead)):
            raise InputError("only the 3DmFV-Net classifier and the box head are saved as checkpoints")
        extra = {
            "box_prior": None if self.box_prior is None else self.box_prior.to_json(),
            "score_threshold": self.score_threshold,
            "nms_iou": self.nms_iou,
            "front_end": None if self.front_end is None else self.front_end.to_dict(),
            "box_quality": None if self.box_quality is None else dataclasses.asdict(self.box_quality),
            "class_score_thresholds": self.class_score_thresholds,
            "probability_exponent": self.probability_exponent,
            "vote_iou": self.vote_iou,
        }
        written = self.classifier.save(path, {**extra, **(note or {})})
        if self.box_quality is not None:
            np.savez_compressed(quality_path(path), **self.box_quality.to_arrays())
        return written

    @classmethod
    def load(cls, path: str | os.PathLike) -> DetectionModel:
        """A model from ``save``'s checkpoint (``torch.load(weights_only=True)``)."""
        classifier = BoxHead.load(path) if _is_box_head(path) else ProposalClassifier.load(path)
        note = classifier.note_
        prior = note.get("box_prior")
        box_quality = None
        if note.get("box_quality"):
            arrays_path = quality_path(path)
            try:
                with np.load(arrays_path, allow_pickle=False) as arrays:
                    box_quality = BoxQuality.from_arrays(dict(arrays))
            except (OSError, ValueError) as exc:
                raise InputError(f"{arrays_path}: unreadable box quality arrays ({exc})") from None
        return cls(
            classifier=classifier,
            box_prior=None if prior is None else BoxSizePrior.from_json(prior),
            score_threshold=float(note.get("score_threshold", 0.5)),
            nms_iou=float(note.get("nms_iou", 0.25)),
            front_end=front_end_from_record(note.get("front_end")),
            box_quality=box_quality,
            class_score_thresholds=_class_thresholds_from_note(note.get("class_score_thresholds")),
            probability_exponent=_exponent_from_note(note.get("probability_exponent", 1.0)),
            vote_iou=_vote_iou_from_note(note.get("vote_iou", BOX_VOTE_IOU)),
        )

    @property
    def note(self) -> dict:
        return getattr(self.classifier, "note_", {})


def _is_box_head(path: str | os.PathLike) -> bool:
    """Whether the checkpoint at ``path`` holds a box head (its note's format says so)."""
    try:
        return describe_checkpoint(path).get("format", "").startswith("factorydet-box-head/")
    except (OSError, json.JSONDecodeError, AttributeError):
        return False  # the classifier's loader says what is wrong with it


def quality_path(path: str | os.PathLike) -> Path:
    """Where a checkpoint's box quality arrays live: ``NAME.boxq.npz`` beside ``NAME.pt``."""
    path = Path(path)
    return path.with_name(path.stem + ".boxq.npz")


def group_probabilities(classifier, groups: ProposalGroups) -> np.ndarray:
    """(G, C + 1) probabilities of a classifier for point sets, fed what its ``input_kind`` names."""
    if not groups.num_groups:
        return np.zeros((0, len(classifier.labels_)), np.float32)
    kind = getattr(classifier, "input_kind", "features")
    if kind == "points":
        check_head_input(groups)
        return classifier.predict_proba(groups.points, groups.fitted_boxes, groups.descriptors)
    if kind == "descriptors":
        return classifier.predict_proba(groups.descriptors)
    if kind == "features+descriptors":
        return classifier.predict_proba(groups.features, groups.descriptors)
    return classifier.predict_proba(groups.features)


def describe_checkpoint(path: str | os.PathLike) -> dict:
    """The JSON note of a checkpoint, without loading its weights."""
    return json.loads(Path(path).with_suffix(".json").read_text())


def _exponent_from_note(value) -> float:
    """A checkpoint note's probability exponent, checked."""
    check_exponent(value)
    return float(value)


def _class_thresholds_from_note(value) -> dict[str, float] | None:
    """A checkpoint note's per-class thresholds, checked (a hand-edited note gets a clear error)."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise InputError(f"class_score_thresholds must map class names to thresholds, got {value!r}")
    names = tuple(str(name) for name in value)
    for name, threshold in zip(names, value.values()):
        if (
            isinstance(threshold, bool)
            or not isinstance(threshold, (int, float))
            or not np.isfinite(threshold)
        ):
            raise InputError(f"class_score_thresholds[{name!r}] must be a number, got {threshold!r}")
    thresholds = np.array(list(value.values()), np.float64)
    check_thresholds(thresholds, "class_score_thresholds", names)
    return dict(zip(names, thresholds.tolist()))


def _vote_iou_from_note(value) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise InputError(f"checkpoint note: vote_iou must be null or in (0, 1], got {value!r}")
    return float(value)
