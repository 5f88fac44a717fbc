"""A trained detection model: the proposal classifier, the class size prior that boxes its
detections, the box quality regressor that picks and scores those boxes, and the operating
thresholds, saved together as one checkpoint (``NAME.pt``, ``NAME.json`` and, with a box quality
regressor, ``NAME.boxq.npz``)."""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np

from factorydet_core.detection.box_head import BoxHead, check_head_input, head_candidates
from factorydet_core.detection.box_quality import BoxQuality, num_option_features
from factorydet_core.detection.checkpoint import check_checkpoint_files, read_checkpoint_note
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.groups import BoxSizePrior, ProposalGroups
from factorydet_core.detection.scoring import (
    BOX_VOTE_IOU,
    check_exponent,
    check_thresholds,
    score_groups,
    select_detections,
)
from factorydet_core.io.atomic import atomic_path
from factorydet_core.proposals.settings import FrontEndParams, front_end_from_record
from factorydet_core.settings_check import Setting
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

    def check_classes(self, class_names: tuple[str, ...] | list[str]) -> None:
        """Raise ``InputError`` unless ``class_names`` (a data set's) are this model's, in order."""
        if tuple(self.class_names) != tuple(class_names):
            raise InputError(
                f"the model's classes {list(self.class_names)} differ from the data set's {list(class_names)}"
            )

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
    def reads_features(self) -> bool:
        """Whether the classifier reads the point sets' 3DmFV (the box head reads their points and
        a descriptor baseline their descriptors: neither does)."""
        return "features" in getattr(self.classifier, "input_kind", "features")

    @property
    def method(self) -> str:
        """Which back half this is (``METHODS``): "box_head" for the learned box head
        (``box_head.BoxHead``) boxing its own detections, "head_options" for the box head's class
        probabilities with the box options of the size prior chosen by the box quality regressor,
        "paper" for the paper's classifier with those box options."""
        if isinstance(self.classifier, BoxHead):
            return "head_options" if self.box_quality is not None else "box_head"
        return "paper"

    def with_screen(self, screen_trees: int, screen_keep: int) -> DetectionModel:
        """This model with its box quality regressor screening options as given
        (``BoxQuality.screen_trees``, ``screen_keep``; 0 trees: every tree over every option)."""
        if self.box_quality is None:
            raise InputError("this model has no box quality regressor to screen options with")
        return self.with_box_quality(screen_trees=screen_trees, screen_keep=screen_keep)

    def with_box_quality(self, **changes) -> DetectionModel:
        """This model with its box quality regressor's inference settings changed
        (``BoxQuality.with_inference``: the screen, the walk)."""
        if self.box_quality is None:
            raise InputError("this model has no box quality regressor to change")
        return dataclasses.replace(self, box_quality=self.box_quality.with_inference(**changes))

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
        # The regressor first: the note, written last, is what says there is one, and records its
        # hash beside the weights' so that files of different saves are told apart on loading.
        companions: dict[str, Path] = {}
        if self.box_quality is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            companions["box_quality"] = self.box_quality.save(quality_path(path))
        return self.classifier.save(path, {**extra, **(note or {})}, companions)

    @classmethod
    def load(cls, path: str | os.PathLike) -> DetectionModel:
        """A model from ``save``'s checkpoint (``torch.load(weights_only=True)``). Every field of
        its note and the box quality arrays are checked before any network is built, and the
        weights against the network; ``InputError`` naming the file otherwise. A note that records
        its files' hashes (every checkpoint saved since they were) must find those very files: an
        interrupted save leaves new files beside the old note."""
        note = read_checkpoint_note(path)
        note_path = Path(path).with_suffix(".json")
        kind = BoxHead if _is_box_head(note, note_path) else ProposalClassifier
        unfitted = kind.from_note(note, note_path)
        class_names = unfitted.class_names
        try:
            prior = _box_prior_from_note(note.get("box_prior"), len(class_names))
            fields = {
                "score_threshold": _SCORE_THRESHOLD.check(
                    "score_threshold", note.get("score_threshold", 0.5)
                ),
                "nms_iou": _NMS_IOU.check("nms_iou", note.get("nms_iou", 0.25)),
                "front_end": _front_end_from_note(note.get("front_end")),
                "class_score_thresholds": _class_thresholds_from_note(
                    note.get("class_score_thresholds"), class_names
                ),
                "probability_exponent": _exponent_from_note(note.get("probability_exponent", 1.0)),
                "vote_iou": _vote_iou_from_note(note.get("vote_iou", BOX_VOTE_IOU)),
            }
            quality_note = note.get("box_quality")
            if quality_note is not None and not isinstance(quality_note, dict):
                raise InputError(
                    f"box_quality must be null or the regressor's settings, got {quality_note!r}"
                )
        except InputError as exc:
            raise InputError(f"{note_path}: {str(exc)[:300]}") from None
        check_checkpoint_files(note, {"weights": Path(path), "box_quality": quality_path(path)}, note_path)
        box_quality = None
        if quality_note:
            box_quality = BoxQuality.load(quality_path(path))
            expected = num_option_features(len(class_names), box_quality.anchored, box_quality.visibility)
            if box_quality.num_features_ != expected:
                raise InputError(
                    f"{quality_path(path)}: the regressor reads {box_quality.num_features_} features where"
                    f" this model's {len(class_names)} classes give {expected}"
                )
        # The note read and checked once above is the one the classifier keeps.
        classifier = unfitted.with_weights(path, note)
        return cls(classifier=classifier, box_prior=prior, box_quality=box_quality, **fields)

    @property
    def note(self) -> dict:
        return getattr(self.classifier, "note_", {})


def _is_box_head(note: dict, note_path: Path) -> bool:
    """Whether a checkpoint's note describes a box head (its format says so); a note of another
    format is refused."""
    kind = note.get("format", "factorydet-classifier/1")  # notes before formats were the classifier's
    if kind not in ("factorydet-classifier/1", "factorydet-box-head/1"):
        raise InputError(f"{note_path}: unknown checkpoint format {kind!r}"[:300])
    return kind == "factorydet-box-head/1"


def copy_checkpoint(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copy the checkpoint at ``source`` (``NAME.pt``, its note and any box quality arrays) to
    ``target`` (a .pt path), each file whole or not at all, the note last (``save``'s order). The
    copies are byte for byte, so the hashes the note records still hold; a copy cut short leaves
    the target's old note, which refuses the new files beside it if it records its own."""
    source, target = Path(source), Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    pairs = [(source, target), (source.with_suffix(".json"), target.with_suffix(".json"))]
    if quality_path(source).is_file():
        pairs.insert(1, (quality_path(source), quality_path(target)))
    for src, dst in pairs:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    return target


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
    if groups.features is None:
        raise InputError(
            "this model reads each point set's 3DmFV, and these proposals were built without"
            ' (front-half feature "none"): propose with feature "aggregated" or "direct"'
        )
    if kind == "features+descriptors":
        return classifier.predict_proba(groups.features, groups.descriptors)
    return classifier.predict_proba(groups.features)


def describe_checkpoint(path: str | os.PathLike) -> dict:
    """The JSON note of a checkpoint, without loading its weights (``InputError`` if unreadable)."""
    return read_checkpoint_note(path)


_SCORE_THRESHOLD = Setting(float, 0.0, 1.0)
_NMS_IOU = Setting(float, 0.0, 1.0, low_open=True)
MAX_MODES = 64
"""The most size modes a note's prior may give a class (``BoxSizePrior.from_boxes`` keeps 8)."""


def _size_rows(value: object, rows: int | None, name: str) -> np.ndarray:
    """A note's (rows, 3) sizes in metres (``null`` for a class never seen: NaN), checked positive;
    ``rows=None`` takes up to ``MAX_MODES`` rows."""
    count_ok = isinstance(value, list) and (
        len(value) == rows if rows is not None else len(value) <= MAX_MODES
    )
    if not count_ok or not all(isinstance(row, list) and len(row) == 3 for row in value):
        want = f"{rows}" if rows is not None else f"at most {MAX_MODES}"
        raise InputError(f"box_prior {name} must be {want} rows of three sizes")
    if not all(
        v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for row in value for v in row
    ):
        raise InputError(f"box_prior {name} must hold numbers or null")
    try:
        sizes = np.array([[np.nan if v is None else v for v in row] for row in value], np.float64)
    except OverflowError:  # an integer of hundreds of digits
        raise InputError(f"box_prior {name} must hold sizes in metres") from None
    sizes = sizes.reshape(-1, 3)
    known = sizes[~np.isnan(sizes)]
    if not (np.isfinite(known).all() and (known > 0).all()):
        raise InputError(f"box_prior {name} must hold positive sizes")
    return sizes


def _box_prior_from_note(value: object, num_classes: int) -> BoxSizePrior | None:
    """A checkpoint note's class size prior (``BoxSizePrior.to_json``, or a plain list of
    medians from before the range was kept), checked: one row per class, positive sizes."""
    if value is None:
        return None
    if isinstance(value, list):
        value = {"median": value}
    if not isinstance(value, dict) or "median" not in value:
        raise InputError("box_prior must be null, a list of sizes or the prior's fields")
    if ("lower" in value) != ("upper" in value):
        raise InputError("box_prior must give both lower and upper sizes, or neither")
    checked = {
        name: _size_rows(value[name], num_classes, name)
        for name in ("median", "lower", "upper")
        if name in value
    }
    modes = value.get("modes")
    if modes is not None:
        if not isinstance(modes, list) or len(modes) != num_classes:
            raise InputError(f"box_prior modes must be {num_classes} lists of sizes")
        modes = tuple(_size_rows(m, None, "modes") for m in modes)
    return BoxSizePrior(checked["median"], checked.get("lower"), checked.get("upper"), modes)


def _front_end_from_note(value: object) -> FrontEndParams | None:
    """A checkpoint note's front-end settings (``front_end_from_record`` checks their names and
    values), a clear error for a note whose settings are not a mapping."""
    if value is not None and not isinstance(value, dict):
        raise InputError(f"front_end must be null or the front half's settings, got {value!r}")
    try:
        return front_end_from_record(value)
    except (TypeError, ValueError, AttributeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"front_end: bad settings ({exc})") from None


def _exponent_from_note(value) -> float:
    """A checkpoint note's probability exponent, checked (a finite number > 0)."""
    exponent = Setting(float, 0.0, low_open=True).check("probability_exponent", value)
    check_exponent(exponent)
    return exponent


def _class_thresholds_from_note(value, class_names: tuple[str, ...]) -> dict[str, float] | None:
    """A checkpoint note's per-class thresholds, checked (a hand-edited note gets a clear error):
    thresholds in [0, 1] of the model's own classes."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise InputError(f"class_score_thresholds must map class names to thresholds, got {value!r}")
    names = tuple(str(name) for name in value)
    unknown = [name for name in names if name not in class_names]
    if unknown:
        raise InputError(f"class_score_thresholds names {unknown[0]!r}, not one of the model's classes")
    number = Setting(float)
    thresholds = np.array(
        [number.check(f"class_score_thresholds[{name!r}]", t) for name, t in zip(names, value.values())],
        np.float64,
    )
    check_thresholds(thresholds, "class_score_thresholds", names)
    return dict(zip(names, thresholds.tolist()))


def _vote_iou_from_note(value) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise InputError(f"checkpoint note: vote_iou must be null or in (0, 1], got {value!r}")
    return float(value)
