"""How a session trains: ``LoopSettings``, one frozen object with every setting of the loop and
the defaults of ``factorydet train``'s flags, the app's retrain and the benchmarks. Light on
purpose (no torch): the command line builds its flags from it."""

from __future__ import annotations

import dataclasses

from factorydet_core.io.dataset import Dataset
from factorydet_core.types import (
    DEFAULT_METHOD,
    METHODS,
    MINING_THRESHOLD,
    PROBABILITY_EXPONENT,
    SCORE_THRESHOLD,
    InputError,
)


@dataclasses.dataclass(frozen=True)
class LoopSettings:
    """How the loop trains: the classifier and the mining settings (``train_with_mining``)."""

    width: float = 0.0625
    epochs: int = 20
    class_weight: str | None = "balanced"
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
    (``train_with_mining``'s ``tune_class_thresholds``); ``score_threshold`` is then the fallback
    of classes without a labelled match."""
    mining_threshold: float | None = MINING_THRESHOLD
    """Least score of a mined (and queued) false positive; ``None``: the operating threshold. The
    paper collects every false positive and adds the top N by score; with box quality a score is a
    probability (to ``probability_exponent``) times a predicted IoU, and at the operating threshold
    a few frames yield a few dozen
    (``bench hitl`` on four frames: 46 in two rounds, so reviewing 50 or 200 made no difference).
    0.05 is the score floor of AP and of the box quality regressor: below it nothing is reported."""
    nms_iou: float = 0.25
    seed: int = 0
    num_threads: int | None = None
    geometry: bool = True
    """Feed the point sets' geometric descriptors to the network beside the 3DmFV tensor."""
    box_quality: bool = True
    """Pick each detection's box and weigh its score by a regressor of the box's IoU
    (``box_quality.BoxQuality``); False keeps the size prior's box and the class probability."""
    visibility: bool | None = None
    """The box quality regressor also reads what the frame's rays saw of each box
    (``BoxQuality.visibility``). ``None``: on for multi-sensor data, whose rays start at the
    sensors of the merge's extrinsics; off for single scans (ScanNet and S3DIS clouds are sampled
    from meshes and read with an identity extrinsic, so their free space means nothing)."""

    def quality_visibility(self, dataset: Dataset | None) -> bool:
        """Whether the box quality regressor reads free space for ``dataset`` (``visibility``)."""
        if self.visibility is not None:
            return self.visibility
        return dataset is None or dataset.num_sensors > 1

    method: str = DEFAULT_METHOD
    """"paper": the 3DmFV-Net classifier and the size prior's box options (with ``box_quality``);
    "box_head": the learned box head (``box_head.BoxHead``), which classifies and boxes each point
    set in one pass (``width``, ``geometry`` and ``box_quality`` do not apply); "head_options":
    the box head classifies, the box quality regressor boxes among the size prior's options
    (``width`` and ``geometry`` do not apply; ``box_quality`` must be on)."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.method == "head_options" and not self.box_quality:
            raise InputError("method head_options boxes by the box quality regressor: box_quality must be on")
