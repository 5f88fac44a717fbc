"""How a session trains: ``LoopSettings``, one frozen object with every setting of the loop and
the defaults of ``factorydet train``'s flags, the app's retrain and the benchmarks. Light on
purpose (no torch): the command line builds its flags from it."""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping
from types import MappingProxyType

from factorydet_core.io.dataset import Dataset, annotation_min_points
from factorydet_core.types import (
    DEFAULT_METHOD,
    METHODS,
    MINING_THRESHOLD,
    PROBABILITY_EXPONENT,
    QUEUE_ORDERS,
    REVIEW_ORDERS,
    SCORE_THRESHOLD,
    THRESHOLD_OBJECTIVES,
    InputError,
    check_threshold_objective,
)

SPARSE_LABEL_SHARE = 0.5
"""With ``LoopSettings.label_min_points`` None, a person's label holding fewer than this share of
the data set's annotation policy's points trains as an ignored place. A box counts fewer points
than the policy counts of its object (points just outside it, the floor band): on the training
factory of ``bench hitl`` (seed 0), 98% of the objects of the 50-point policy keep at least half
of it in their boxes, and 5% of the sparser ones do."""


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """How the loop trains: the classifier and the mining settings (``train_with_mining``)."""

    width: float = 0.0625
    epochs: int = 20
    round_epochs: int = 5
    """Epochs of a fit that goes on from a model instead of training afresh: each mining round
    after a full retrain's first fit goes on from the previous round's network, and a 'next'
    round goes on from the session's chosen (else latest) model (``loop.continued_model``) and
    refits its box quality regressor on the current labels (``refit_box_quality``). 0: every
    fit trains afresh for ``epochs`` and a 'next' round refits the regressor (the paper's
    procedure, several times slower; the default and paper checkpoints were trained so).
    ``factorydet bench mining`` measures both."""
    class_weight: str | None = "sqrt"
    """The box head learns best with the square root of the inverse class frequencies (its own
    default); the paper model was trained with "balanced" (``make paper-model``)."""
    rounds: int = 2
    """Mining rounds of a full retrain (a 'next' round is always one fit)."""
    negatives_per_round: int = 500
    initial_negatives: int = 2000
    positive_iou: float = 0.6
    fragment_iou: float = 0.4
    """Point sets overlapping a label at most this much start as background (0: the paper's start)."""
    fragments_per_frame: int | None = None
    """At most this many of them per frame (``None``: all)."""
    score_threshold: float = SCORE_THRESHOLD
    """Operating score; with box quality, the class probability to ``probability_exponent`` times
    the predicted IoU."""
    probability_exponent: float = PROBABILITY_EXPONENT
    """With box quality, the class probability's power in the score (``types.PROBABILITY_EXPONENT``)."""
    class_thresholds: bool = True
    """Give the model a threshold per class, tuned on the training frames' labels
    (``train_with_mining``'s ``tune_class_thresholds``; where, ``threshold_folds`` says);
    ``score_threshold`` is then the fallback of classes without a labelled match."""
    threshold_folds: int = 2
    """With ``class_thresholds``, 2 or more tunes the thresholds on scores of frames no model
    fitted: the training frames cut into this many stretches of the drive, each scored by a model
    fitted afresh on the others (``train_with_mining``'s ``threshold_folds``; about one more fit),
    with no ceiling; a session with fewer training frames than folds tunes them on its fitted
    frames. 0 tunes them on the frames the model fitted, where scores run high, so none may exceed
    ``score_threshold``. On factories no choice saw (``bench hitl``, docs/review-loop.md), 2 folds
    with ``threshold_objective`` "total" gave the same networks a higher F-score than the fitted
    frames' thresholds, the more so the more of the objects are labelled: what makes a reviewer's
    labels show in the model."""
    continue_folds: bool = True
    """With ``threshold_folds``, a next round that goes on from a model (``round_epochs`` > 0) goes
    on from that run's fold models too, for ``round_epochs`` epochs, where its folds are the same
    frames (each never saw the frames it scores), as its own model goes on from the run's: K folds
    then cost K - 1 times the round's own fit, not a fit of ``epochs`` afresh each, and follow the
    schedule of the model they stand in for (``train_with_mining``'s ``init_folds``). False fits
    them afresh every round."""
    threshold_objective: str = "total"
    """With ``class_thresholds``, whose F-score each class's threshold is best for
    (``types.THRESHOLD_OBJECTIVES``): the class's own ("class"), or that of all classes'
    detections pooled ("total", the figure the benchmarks report), which holds a class of few,
    poorly scored objects above where its own F would flood the detections, up to switching it
    off, and lets a class far better than the rest go below its own best
    (``train_with_mining``'s ``threshold_objective``)."""
    mining_threshold: float | None = MINING_THRESHOLD
    """Least score of a mined (and queued) false positive; ``None``: the operating threshold. The
    paper collects every false positive and adds the top N by score; with box quality a score is a
    probability (to ``probability_exponent``) times a predicted IoU, and at the operating threshold
    a few frames yield a few dozen
    (``bench hitl`` on four frames: 46 in two rounds, so reviewing 50 or 200 made no difference).
    0.05 is the score floor of AP and of the box quality regressor: below it nothing is reported."""
    hold_confident: float | None = None
    """Mined negatives scoring at least this are held out of the background (neither object nor
    background, as background recalibration ignores confident unlabelled detections) until someone
    reviews them: on a partially annotated data set the model's most confident false positives are
    the likeliest real, unlabelled objects. They stay in the review queue; a verdict moves each to
    the background or to a label. ``None``: every mined negative is background, as the paper.
    Measured on held-out factories (``bench hitl``, docs/review-loop.md), holding at the operating
    score gained over blind mining, at 30% and 50% unannotated, with thresholds tuned out of fold
    (``threshold_folds`` 2, ``threshold_objective`` "total", the defaults), ``hold_places`` and
    ``recalibrate_background`` 0.5; at the fitted frames' thresholds (``threshold_folds`` 0) it was
    level with blind mining or below it."""
    hold_places: bool = False
    """With ``hold_confident``, a held negative holds its place, not only its own point set: every
    point set with half its points or more in a held box (one off every label) is left out of the
    background too, as a pre-label's place is (``FrameProposals.ignored_point_sets``). An
    unlabelled object has many candidate sets (merge levels, fragments); holding the mined one
    alone leaves the others in the background the box head samples every epoch."""
    pseudo_label_confident: float | None = None
    """Mined negatives scoring at least this, off every label, teach their predicted class until
    someone reviews them, as labels whose box is the model's own (self-training; without
    ``model_box_targets`` they teach their class alone). Most negatives scoring 0.6 or more are
    real objects of their predicted class (``bench hitl`` at 50% unannotated, docs/review-loop.md):
    holding them leaves those objects out, a pseudo-label teaches them; too few to make blind
    mining safe there, which is why it is off by default.
    They stay in the review queue, and a verdict replaces the pseudo-label. They count as labels
    where the class thresholds are tuned on the training frames. Checked before
    ``hold_confident``: set above it, the negatives between the two are held. ``None``: none
    (the paper)."""
    carry_pseudo_labels: bool = False
    """With ``pseudo_label_confident``, each pseudo-label of an object that stands still (not
    ``session.world.MOVING_CLASSES``) also labels its object in every other training frame that
    shows it (``session.world.place_box``: the frames placed in one world frame), as a reviewer's
    Object verdict does, except where a label, another pseudo-label or a box a person rejected
    (``SessionDB.rejected_boxes``) is on that object there. Off by default: on held-out
    factories (``bench hitl`` at 50% unannotated, docs/review-loop.md) it changed nothing
    measurable, as most carried labels land on views too sparse for the annotation policy (a
    frame shows an object from one point) or on no object."""
    recalibrate_background: float | None = None
    """Background recalibration (the learned box head's methods): in a fit that goes on from a
    model (mining rounds, next rounds), a background set drawn at random (not a mined or reviewed
    negative) to which the network, as it trains, gives an object probability of at least this
    is left out of that step's classification and IoU losses (``BoxHead.recalibrate_background``).
    On a partially annotated data set those are the likeliest unlabelled objects, which the plain
    loss teaches to be background. ``None``: off, every drawn set is background (the paper)."""
    recalibrate_by_class: bool = False
    """With ``recalibrate_background``, a drawn set is left out only when its likeliest class's
    probability also reaches the median its class's labelled sets get (``BoxHead.recalibrate_by_class``):
    the network's probabilities differ in scale between classes, and one threshold leaves out
    background that looks like a high-scoring class by the hundred."""
    queue_order: str = "score"
    """Which mined negatives a round adds to the background (the first ``negatives_per_round``)
    and, unless ``review_order`` says otherwise, the review queue's order
    (``session.queue.queue_order``): "score", the paper's top N by
    score; "class", the predicted classes taking turns, each one's by score, so that the false
    positives of a class the model has barely learned (the likeliest place of its unlabelled
    objects) reach the cut and the reviewer."""
    review_order: str | None = "learned"
    """The review queue's order alone (``queue_order`` still cuts the mined negatives). "learned"
    (the default): the places likeliest to give a label ('object' or 'wrong box') first, by a
    logistic regression on the session's own verdicts refitted as they come
    (``session.review_rank``); the places answered first and the skipped ones last, the rest in
    ``queue_order`` until there are enough verdicts to fit on, and a queue shown by item in
    ``queue_order``. On held-out factories, with the cut by class turns, it gave more labels for
    the same verdicts than either fixed order, at 30% and 50% unannotated (``bench hitl``,
    docs/review-loop.md). "score", most likely an object first (with the queue grouped by place,
    each place's chance that one of its items is an object); "class", the predicted classes
    taking turns: class turns reach a class the model has barely learned, but give every
    predicted class the same share of the reviewer's first entries, among them classes whose
    queue is mostly background. ``None`` ("auto"): as ``queue_order``. A run keeps the order it
    was trained with (``SessionDB.review_order``): a change applies from the next run."""
    review_extra: int | None = 0
    """False positives beyond the first ``negatives_per_round`` (in ``queue_order``) that a run's
    last mining adds to its review queue alone: training leaves them out (neither background nor
    mined) until a verdict moves them; ``None``: all of them. The paper's cut of N bounds what
    the background takes, but also what a reviewer is shown: on a partially annotated data set
    most unlabelled objects the model finds score below the cut's last entry (``bench hitl`` at
    50% unannotated: about half of them), so a reviewer who answers the queue by place never
    meets them. 0: the queue is the mined negatives, as the paper."""
    refit_box_quality: bool = True
    """A 'next' round that goes on from a model (``round_epochs`` > 0) fits the box quality
    regressor again on the session's current labels (False: keeps the model's). The regressor
    learns each option's IoU with the labels, so one fitted while half the objects were unlabelled
    has learned that their boxes fit nothing (IoU 0) and scores them down whatever the classifier
    says; labels a reviewer adds later only reach it through a refit (``bench hitl``: 200 reviewed
    places a round recover about half the blind-to-full gap without it, most of it with it;
    docs/review-loop.md). Costs one regressor fit per round that changed labels or object verdicts
    (``bench mining``'s ``box_quality_seconds``): a round on the rows the model's regressor was
    fitted on keeps it, since the fit would give it back."""
    refit_trees: int = 0
    """With ``refit_box_quality``: 0 fits the regressor afresh (all its trees) on the current
    labels; N > 0 boosts the model's regressor on with N trees fitted to what it gets wrong on them
    (``BoxQuality.continued``), a fraction of the fit's time, the regressor N trees larger each
    round. 100 kept about half of what the refit gains (``bench hitl``, docs/review-loop.md)."""
    refit_row_share: float = 0.5
    """With ``refit_box_quality`` and ``refit_trees`` 0: the share of the option rows a next
    round's refit of the regressor boosts on (``BoxQuality.row_share``, a uniform sample; 1: all
    of them, as a full run's fit). The refit is most of a reviewer's round and its time grows
    with its rows: on the demo after 20 Object verdicts, half of them (about a million) took the
    fit to about 0.6 of its time and the round to about 0.7, and the rounds' models scored the
    same on held-out factories within the spread over training seeds (``bench mining
    --compare-set refit_row_share=1.0``, docs/performance.md; docs/changelog.md gives the check
    with one classifier that came before). A next round on the rows its model's regressor learned
    from keeps it, sampled or not."""
    model_box_targets: bool = False
    """Learn boxes from every label (True), or let a label whose box is the model's own teach its
    class alone (False): a reviewer's Object verdict keeps the mined box, and a confirmed pre-label
    the detection's (``store.MODEL_BOX_ORIGINS``; a box a person moved is theirs). Such a box fits
    its object only as well as the model did, and learning from it teaches the boxes to agree with
    the model; so the box head's box and IoU losses, the box quality regressor and the size prior
    leave it out (unless its class has no other box: ``mining.box_targets``), while its point sets
    still count as the object's. On held-out factories at 50% unannotated the reviewer's detector
    gained F by it, seed by seed (``bench hitl``, docs/review-loop.md)."""
    label_min_points: int | None = 0
    """A label a person made in the app (drawn, an Object verdict, carried by label once, a
    confirmed pre-label, a keyframe's computed box: every origin but the data set's own
    annotations and imported labels) whose box holds fewer than this many of its frame's
    points (``session.world.counting_box``, the frame merged with its nominal extrinsics) trains
    as an ignored place, neither object nor background, as the data set's annotation policy
    leaves such sparse objects unannotated and the evaluation ignores them (label once shows an
    object in every frame with a point of it, so many of a person's labels are sparse). 0 (the
    default) keeps every label: on held-out factories the reviewer's detector trained without
    its sparse labels traded recall for precision and gained no F-score at 30% or at 50%
    unannotated, its share of the gap to full labels falling at 30% (``bench hitl``,
    docs/review-loop.md). ``None``: ``SPARSE_LABEL_SHARE`` of the data set's annotation policy
    (its manifest's ``min_annotated_points``; none stated: every label kept). Pseudo-labels
    (``pseudo_label_confident``, carried or not) are not checked."""
    threshold_label_min_points: int | None = None
    """A label a person made (the origins ``label_min_points`` checks) holding fewer than this many
    of its frame's points still trains as an object, but the score thresholds are tuned (on the
    fitted frames and out of fold) as if it were an ignored place: a detection on it is neither a
    hit nor a false alarm, and nobody misses it. The evaluation measures against the data set's
    annotation policy and ignores objects sparser than that; label once puts a person's label in
    every frame with a point of its object, so without this the thresholds are tuned to find
    objects the evaluation never asks for. ``None`` (the default): ``SPARSE_LABEL_SHARE`` of the
    annotation policy, as ``label_min_points``'s ``None`` (on a third set of held-out factories
    the reviewer so recovered 80% of the gap between blind mining and full labels, the test fixed
    before its runs; docs/review-loop.md); 0: every label counts. At or
    below ``label_min_points`` it changes nothing (those labels are ignored already), nor
    without ``class_thresholds`` (nothing is tuned)."""
    nms_iou: float = 0.25
    seed: int = 0
    num_threads: int | None = None
    geometry: bool = True
    """Feed the point sets' geometric descriptors to the network beside the 3DmFV tensor."""
    box_quality: bool = True
    """Pick each detection's box and weigh its score by a regressor of the box's IoU
    (``box_quality.BoxQuality``); False keeps the size prior's box and the class probability."""
    quality_trees: int = 500
    """Trees of the box quality regressor's fit (``BoxQuality.max_iter``; a refit's too, unless
    ``refit_trees`` boosts it on). 500 trees of 63 leaves chose and scored boxes better on held-out
    frames than 300 of 31 (``BoxQuality``); fewer fit faster and coarser, which tests and quick
    trials may want: the fit grows about linearly with them. A next round that keeps the model's
    regressor (``refit_box_quality`` off, or its rows unchanged) keeps its size too."""
    visibility: bool | None = None
    """The box quality regressor also reads what the frame's rays saw of each box
    (``BoxQuality.visibility``). ``None``: on for multi-sensor data, whose rays start at the
    sensors of the merge's extrinsics; off for single scans (ScanNet and S3DIS clouds are sampled
    from meshes and read with an identity extrinsic, so their free space means nothing)."""

    def folds_for(self, num_frames: int) -> int:
        """The threshold folds a run on ``num_frames`` training frames uses: ``threshold_folds``
        with per-class thresholds and at least as many frames as folds, else 0 (tuned on the
        fitted frames: a fold needs a frame of its own)."""
        if not self.class_thresholds or num_frames < self.threshold_folds:
            return 0
        return self.threshold_folds

    def label_points_floor(self, dataset: Dataset | None) -> int:
        """The least points a person's label must hold in its frame to train as an object
        (``label_min_points``); 0: every label."""
        return _points_floor(self.label_min_points, dataset)

    def threshold_points_floor(self, dataset: Dataset | None) -> int:
        """The least points a person's label must hold in its frame to count when the thresholds
        are tuned (``threshold_label_min_points``); 0: every label, and without per-class
        thresholds (``class_thresholds`` off: nothing is tuned)."""
        if not self.class_thresholds:
            return 0
        return _points_floor(self.threshold_label_min_points, dataset)

    def measure_points_floor(self, dataset: Dataset | None) -> int:
        """The least points a person's label must hold in its frame to be a reference when a run's
        models are measured on the session's labels (the before/after table): a label the run
        does not train on, or does not tune its thresholds on, is ignored there too."""
        return max(self.label_points_floor(dataset), self.threshold_points_floor(dataset))

    def quality_visibility(self, dataset: Dataset | None) -> bool:
        """Whether the box quality regressor reads free space for ``dataset`` (``visibility``)."""
        if self.visibility is not None:
            return self.visibility
        return dataset is None or dataset.num_sensors > 1

    @property
    def carries_pseudo_labels(self) -> bool:
        """Whether a next round carries pseudo-labels to other frames: ``carry_pseudo_labels``
        with pseudo-labels on (``pseudo_label_confident``); it then needs the frames placed in
        one world frame."""
        return self.carry_pseudo_labels and self.pseudo_label_confident is not None

    method: str = DEFAULT_METHOD
    """"paper": the 3DmFV-Net classifier and the size prior's box options (with ``box_quality``);
    "box_head": the learned box head (``box_head.BoxHead``), which classifies and boxes each point
    set in one pass (``width``, ``geometry`` and ``box_quality`` do not apply); "head_options":
    the box head classifies, the box quality regressor boxes among the size prior's options
    (``width`` and ``geometry`` do not apply; ``box_quality`` must be on)."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        _check_count("refit_trees", self.refit_trees, 0)
        if isinstance(self.refit_row_share, bool) or not 0.0 < float(self.refit_row_share) <= 1.0:
            raise InputError(f"refit_row_share must lie in (0, 1], got {self.refit_row_share!r}")
        _check_count("quality_trees", self.quality_trees, 1)
        for name in ("label_min_points", "threshold_label_min_points"):
            if getattr(self, name) is not None:
                _check_count(name, getattr(self, name), 0)
        if self.queue_order not in QUEUE_ORDERS:
            orders = ", ".join(QUEUE_ORDERS)
            raise InputError(f"queue_order must be one of {orders}, got {self.queue_order!r}")
        if self.review_order is not None and self.review_order not in REVIEW_ORDERS:
            orders = ", ".join(REVIEW_ORDERS)
            raise InputError(f"review_order must be one of {orders} or None, got {self.review_order!r}")
        check_threshold_folds(self.threshold_folds)
        check_threshold_objective(self.threshold_objective)
        extra = self.review_extra
        if extra is not None and (isinstance(extra, bool) or not isinstance(extra, int) or extra < 0):
            raise InputError(f"review_extra must be an integer >= 0 or None, got {extra!r}")
        recalibrate = self.recalibrate_background
        if recalibrate is not None and (isinstance(recalibrate, bool) or not 0.0 < recalibrate <= 1.0):
            raise InputError(f"recalibrate_background must lie in (0, 1] or be None, got {recalibrate!r}")
        if recalibrate is not None and self.method == "paper":
            raise InputError("recalibrate_background applies to the learned box head's methods, not paper")
        if self.recalibrate_by_class and recalibrate is None:
            raise InputError("recalibrate_by_class refines recalibrate_background, which is off")
        if self.method == "head_options" and not self.box_quality:
            raise InputError("method head_options boxes by the box quality regressor: box_quality must be on")


def _check_count(name: str, value: object, minimum: int) -> None:
    """``InputError`` unless ``value`` (setting ``name``) is an integer of at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")


def check_threshold_folds(folds: object) -> int:
    """``folds`` if it is 0 (off) or an integer of at least 2; ``InputError`` otherwise (the
    settings' check and ``train_with_mining``'s)."""
    if isinstance(folds, bool) or not isinstance(folds, numbers.Integral) or folds < 0 or folds == 1:
        raise InputError(f"threshold_folds must be 0 (off) or an integer >= 2, got {folds!r}")
    return int(folds)


BEFORE_THEY_EXISTED: dict[str, object] = {
    "threshold_folds": 0,
    "threshold_objective": "class",
    "queue_order": "score",
    "review_order": None,
    "refit_box_quality": False,
    "refit_trees": 0,
    "refit_row_share": 1.0,
    "model_box_targets": True,
    "quality_trees": 500,
    "continue_folds": False,
    "label_min_points": 0,
    "threshold_label_min_points": 0,
}
"""What a record written before each of these ``LoopSettings`` fields existed ran with: the
behaviour the field was added to keep by default. A record that lacks a field is read with these,
not with today's default, so a default changed since does not rewrite what an old record ran."""


def _points_floor(setting: int | None, dataset: Dataset | None) -> int:
    """A points floor setting as a number: itself, or with ``None`` ``SPARSE_LABEL_SHARE`` of the
    data set's annotation policy (0, every label, when it states none)."""
    if setting is not None:
        return setting
    policy = None if dataset is None else annotation_min_points(dataset, default=None)
    return 0 if not policy else max(1, int(round(SPARSE_LABEL_SHARE * policy)))


def folds_continue(settings: Mapping[str, object], next_rounds: bool) -> bool:
    """Whether a run with ``settings`` (``LoopSettings`` as a dict, or a record's settings, read
    with ``BEFORE_THEY_EXISTED``'s values where they lack a field) goes on from its threshold fold
    models in its next rounds: per-class thresholds tuned out of fold, ``round_epochs`` (a next
    round continues the model), ``continue_folds``, and ``next_rounds`` (the run has a round that
    continues a model: a session's saved run, or a benchmark's mining rounds after the first fit).
    The loop, the benchmark's run plans and its record text all ask this."""
    return bool(
        next_rounds
        and settings.get("class_thresholds", True)
        and settings.get("threshold_folds")
        and settings.get("round_epochs")
        and settings.get("continue_folds", BEFORE_THEY_EXISTED["continue_folds"])
    )


@dataclasses.dataclass(frozen=True)
class Control:
    """How people set one field of ``LoopSettings``: ``factorydet train``'s flag and the app's
    Training panel control are both built from it, so their defaults, bounds and help agree.

    Args:
        field: the ``LoopSettings`` field.
        label: the app's label.
        help: one line for the flag's help and the control's hint.
        kind: ``int``, ``float``, ``bool`` or ``str`` (a choice).
        minimum, maximum, step: a number's bounds (inclusive) and the app's step.
        choices: for a choice, ``(text, value)`` pairs: what is typed or picked, what it means.
        none_as: for a number whose field may be ``None``, the number that stands for ``None``
            (``fragments_per_frame``: 0 means all).
        flag: the command-line flag (default ``--field-name``; a bool that defaults to True is
            turned off by ``--no-field-name``).
    """

    field: str
    label: str
    help: str
    kind: type = float
    minimum: float | None = None
    maximum: float | None = None
    step: float | None = None
    choices: tuple[tuple[str, object], ...] | None = None
    none_as: float | None = None
    flag: str | None = None

    @property
    def default(self) -> object:
        return getattr(LoopSettings(), self.field)

    @property
    def cli_flag(self) -> str:
        if self.flag is not None:
            return self.flag
        name = self.field.replace("_", "-")
        return f"--no-{name}" if self.kind is bool and self.default else f"--{name}"

    def text_of(self, value: object) -> str:
        """A choice's text for ``value``."""
        for text, meaning in self.choices or ():
            if meaning == value:
                return text
        raise InputError(f"{self.field}: {value!r} is none of {[t for t, _ in self.choices or ()]}")

    def shown(self, value: object) -> object:
        """``value`` as the app's control shows it (a choice's text, ``none_as`` for ``None``)."""
        if self.choices is not None:
            return self.text_of(value)
        if value is None and self.none_as is not None:
            return self.kind(self.none_as)
        return value

    def arguments(self, value: object) -> list[str]:
        """The command-line arguments that set the field to ``value``: none for the default, the
        flag alone for a switch, else the flag and the value as the flag takes it."""
        if value == self.default:
            return []
        if value is None and self.none_as is None and self.choices is None:
            raise InputError(f"{self.field}: no command-line flag sets it to None")
        if self.kind is bool:
            return [self.cli_flag]
        return [self.cli_flag, str(self.shown(value))]

    def parse(self, raw: object) -> object:
        """The field's value of what a flag or a control gave, checked; ``InputError`` otherwise."""
        if self.choices is not None:
            for text, meaning in self.choices:
                if raw == text:
                    return meaning
            raise InputError(
                f"{self.label}: choose one of {', '.join(t for t, _ in self.choices)}, got {raw!r}"
            )
        if self.kind is bool:
            if not isinstance(raw, bool):
                raise InputError(f"{self.label}: expected true or false, got {raw!r}")
            return raw
        if raw is None:
            return None
        try:
            number = float(raw)
        except (TypeError, ValueError):
            raise InputError(f"{self.label}: expected a number, got {raw!r}") from None
        if self.none_as is not None and number == self.none_as:
            return None
        if self.kind is int and number != int(number):
            raise InputError(f"{self.label}: expected a whole number, got {raw!r}")
        if (self.minimum is not None and number < self.minimum) or (
            self.maximum is not None and number > self.maximum
        ):
            raise InputError(f"{self.label}: {raw!r} is outside [{self.minimum:g}, {self.maximum:g}]")
        return int(number) if self.kind is int else number


LOOP_CONTROLS: tuple[Control, ...] = (
    Control("method", "Method", "back half: paper (3DmFV-Net and box options), box_head (the learned head "
            "classifies and boxes), head_options (the head classifies, the box quality regressor boxes)",
            str, choices=tuple((m, m) for m in METHODS)),
    Control("epochs", "Epochs", "passes over the training set per fit", int, 1, 500, 1),
    Control("round_epochs", "Epochs per round", "epochs of a mining round or next round that goes on from "
            "the previous model (0: every round trains afresh, the paper's procedure)", int, 0, 500, 1),
    Control("rounds", "Mining rounds", "hard-negative mining rounds after the first fit (full retrain)",
            int, 0, 20, 1),
    Control("negatives_per_round", "Negatives per round", "mined negatives added per round (N)", int, 0,
            1_000_000, 50, flag="--negatives"),
    Control("initial_negatives", "Initial negatives", "random background set to start", int, 0, 1_000_000,
            100),
    Control("width", "Network width", "3DmFV-Net width (1.0 = the paper's, 46M parameters)", float, 0.015625,
            2.0, 0.015625),
    Control("class_weight", "Class weight", "loss weighting: inverse class frequency, its square root, or "
            "none (the paper's plain loss)", str,
            choices=(("balanced", "balanced"), ("sqrt", "sqrt"), ("none", None))),
    Control("geometry", "Geometric descriptors", "feed the point sets' descriptors to the network beside the "
            "3DmFV tensor (off: the paper's network on the tensor alone)", bool),
    Control("positive_iou", "Positive IoU", "a point set is an object if its box overlaps a label this much",
            float, 0.05, 1.0, 0.05),
    Control("fragment_iou", "Fragment IoU", "point sets overlapping a label at most this much start as "
            "background (0: the paper's start)", float, 0.0, 1.0, 0.05),
    Control("fragments_per_frame", "Fragments per frame", "sample at most N of those per frame (0: all; "
            "bounds the fit's time on many frames)", int, 0, 1_000_000, 10, none_as=0),
    Control("score_threshold", "Score threshold", "operating score of the model and of mining (with box "
            "quality: class probability to the exponent times the predicted IoU)", float, 0.0, 1.0, 0.05),
    Control("probability_exponent", "Probability exponent", "with box quality, the class probability's "
            "power in the score (1: the plain product)", float, 0.05, 10.0, 0.05),
    Control("mining_threshold", "Mining threshold", "mine (and queue for review) false positives scoring at "
            "least this; the top N by score go to the background", float, 0.0, 1.0, 0.01),
    Control("class_thresholds", "Per-class thresholds", "each class's own operating threshold, tuned on the "
            "training frames' labels (off: the score threshold for every class)", bool),
    Control("threshold_folds", "Threshold folds", "with per-class thresholds, tune them on stretches of "
            "the drive each scored by a model fitted without it, with no ceiling (about one more fit; 0: on "
            "the fitted frames, never above the score threshold)", int, 0, 20, 1),
    Control("continue_folds", "Continue fold models", "with threshold folds, a next round goes on from the "
            "fold models of the run it continues, for its round epochs (off: fits them afresh every "
            "round)", bool),
    Control("threshold_objective", "Threshold objective", "with per-class thresholds, whose F-score each "
            "threshold is best for: the class's own (class), or all classes' detections pooled (total: a "
            "class of few, poorly scored objects is held up, even off, rather than flood the detections)",
            str, choices=tuple((o, o) for o in THRESHOLD_OBJECTIVES)),
    Control("hold_confident", "Hold confident negatives", "mined negatives scoring at least this are neither "
            "background nor object until reviewed (0: off, every mined negative is background, as the "
            "paper). On held-out factories it gained over blind mining with threshold folds 2, objective "
            "total (the defaults), hold their places and recalibrate background 0.5; with threshold folds "
            "0 it did not", float, 0.0, 1.0, 0.05,
            none_as=0),
    Control("hold_places", "Hold their places", "with held negatives (hold confident above 0; hitl: "
            "blind_safe's and reviewed_safe_K's), every point set on a held box off the labels is left "
            "out of the background too, not only the mined set", bool),
    Control("pseudo_label_confident", "Pseudo-label confident negatives", "mined negatives scoring at least "
            "this, off every label, teach their predicted class until reviewed, as labels with the model's "
            "box (0: off; hitl: blind_safe's and reviewed_safe_K's)", float, 0.0, 1.0, 0.05, none_as=0),
    Control("carry_pseudo_labels", "Carry pseudo-labels", "with pseudo-labels, each one of an object that "
            "stands still labels it in every training frame that shows it too (label once; hitl: "
            "blind_safe's and reviewed_safe_K's)", bool),
    Control("recalibrate_background", "Recalibrate background", "(box head) drawn background sets the "
            "network gives this object probability or more are left out of the loss, as likely unlabelled "
            "objects (0: off; hitl: blind_safe's and reviewed_safe_K's)", float, 0.0, 1.0, 0.05,
            none_as=0),
    Control("recalibrate_by_class", "Recalibrate by class", "with recalibrate background, only sets whose "
            "likeliest class's probability also reaches the median of that class's labelled sets", bool),
    Control("queue_order", "Queue order", "which mined negatives go to the background and (with review "
            "order auto) the review queue's order: by score (the paper's top N), or the predicted classes "
            "taking turns",
            str, choices=tuple((o, o) for o in QUEUE_ORDERS)),
    Control("review_order", "Review order", "the review queue's order alone, from the next run on: "
            "learned from the session's verdicts, the places likeliest to give a label first (learned; by "
            "place), most likely an object first (score), the predicted classes taking turns (class), or "
            "as the queue order (auto)", str,
            # The default first, as the drop-down lists them; "auto" last, as the help names it.
            choices=(*((o, o) for o in sorted(REVIEW_ORDERS, key=lambda o: o != "learned")), ("auto", None))),
    Control("review_extra", "Review extra", "false positives beyond the mined negatives that the last "
            "mining queues for review alone, left out of training until reviewed (0: none, the paper; "
            "-1: all)", int, -1, 10_000_000, 1, none_as=-1),  # (a step of 100 from -1 allowed 99, 199, ...)
    Control("refit_box_quality", "Refit box quality", "a next round that goes on from a model refits the "
            "box quality regressor on the current labels, when they changed (off: keeps the model's)", bool),
    Control("refit_trees", "Refit trees", "with refit box quality, boost the model's regressor on with "
            "this many trees fitted to the current labels (0: fit it afresh)", int, 0, 2000, 10),
    Control("refit_row_share", "Refit row share", "with refit box quality (and refit trees 0), the share "
            "of the option rows the refit fits on, a random sample (1: all of them, as a full run's "
            "fit; fewer: a faster refit)", float, 0.05, 1.0, 0.05),
    Control("model_box_targets", "Learn model boxes", "labels whose box is the model's own (an Object "
            "verdict's mined box, a confirmed pre-label whose box nobody moved) are box targets too "
            "(off: they teach their class alone)", bool),
    Control("label_min_points", "Label min points", "a label a person made (drawn, a verdict, carried "
            "by label once, a confirmed pre-label; not the data set's nor imported ones) holding fewer of "
            "its frame's points trains as an ignored place, neither object nor background (0: every "
            "label, the default; -1: half the data set's annotation policy, none without one)",
            int, -1, 1_000_000, 1, none_as=-1),
    Control("threshold_label_min_points", "Threshold label min points", "a label a person made "
            "(as Label min points) holding fewer of its frame's points still trains as an object, but "
            "the score thresholds are tuned as if it were an ignored place, as the evaluation ignores "
            "objects sparser than the annotation policy (0: every label counts; -1, the default: half "
            "the data set's annotation policy, none without one)", int, -1, 1_000_000, 1, none_as=-1),
    Control("nms_iou", "NMS IoU", "3D non-maximum suppression overlap", float, 0.0, 1.0, 0.05),
    Control("seed", "Seed", "random seed of the fit and of the background samples", int, 0, 2**31 - 1, 1),
    Control("box_quality", "Box quality regressor", "pick each box among the options by a regressor of its "
            "IoU and weigh the score by it (off: the size prior's box and the class probability)", bool),
    Control("quality_trees", "Box quality trees", "trees of the box quality regressor's fit (fewer: a "
            "faster, coarser fit)", int, 1, 5000, 1),
    Control("visibility", "Free space", "the box quality regressor reads what the rays saw in each box "
            "(auto: on for multi-sensor data, off for single scans)", str,
            choices=(("auto", None), ("on", True), ("off", False))),
)  # fmt: skip
"""Every ``LoopSettings`` field people set (``num_threads`` is the machine's, not the model's)."""

CONTROL_BY_FIELD: Mapping[str, Control] = MappingProxyType({c.field: c for c in LOOP_CONTROLS})
"""``LOOP_CONTROLS`` by the ``LoopSettings`` field each sets."""


def loop_arguments(settings: LoopSettings) -> list[str]:
    """``factorydet train``'s arguments that give ``settings`` from the defaults: what a benchmark
    passes on to the training command it times."""
    values = ((control, getattr(settings, control.field)) for control in LOOP_CONTROLS)
    return [argument for control, value in values for argument in control.arguments(value)]


def loop_settings_from(values: dict[str, object], base: LoopSettings | None = None) -> LoopSettings:
    """``base`` (default ``LoopSettings()``) with the fields of ``values`` (raw flag or control
    values by field name) parsed by their ``LOOP_CONTROLS``; ``InputError`` for a bad one."""
    unknown = sorted(set(values) - set(CONTROL_BY_FIELD))
    if unknown:
        raise InputError(f"unknown training settings {unknown}")
    parsed = {name: CONTROL_BY_FIELD[name].parse(raw) for name, raw in values.items()}
    return dataclasses.replace(base or LoopSettings(), **parsed)
