"""Box quality: which of a point set's box options fits the object, and how well.

A point set has several box hypotheses (fitted, completed behind the visible side, headed along
the view) and ``groups.BoxSizePrior`` adds the same boxes grown to its class's typical sizes.
Measured on the simulator with the true classes given, choosing among those options by the prior's
rule kept a detection F-score of 0.42 where the best option would give 0.59; and a classifier's
probability alone says nothing about whether the chosen box is a fragment, a whole object, or an
object with its neighbour. ``BoxQuality`` learns both from the annotations, as IoU-Net-style
localisation confidence does: a gradient-boosted regressor predicts, for every option, its 3D IoU
with the annotated object the set belongs to (0 for sets that overlap no annotation). A detection
takes the option of highest predicted IoU, and its score becomes the class probability (to the
model's ``probability_exponent``, 0.5 for the loop and the command line) times that predicted IoU.

The regressor is scikit-learn's ``HistGradientBoostingRegressor``; for checkpoints it is exported to
plain arrays (``to_arrays``) and evaluated by ``predict`` here, so loading a model never unpickles
anything; ``BoxQuality.load`` checks the arrays first (``_check_trees``), since the compiled walk
reads their indices unchecked. ``tests/core/test_box_quality.py`` checks that ``predict`` equals
scikit-learn's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.groups import (
    DESCRIPTOR_NAMES,
    BoxSizePrior,
    ProposalGroups,
    _horizontal_sorted_sizes,
    flatten_sets,
    rank_within_sets,
)
from factorydet_core.io.atomic import atomic_path
from factorydet_core.io.npz import load_npz
from factorydet_core.jit import run_kernel
from factorydet_core.proposals.visibility import FreeSpace, box_visibility
from factorydet_core.types import InputError

OPTION_FEATURE_NAMES: tuple[str, ...] = (
    "log_length",
    "log_width",
    "log_height",
    "log_length_over_fitted",
    "log_width_over_fitted",
    "log_height_over_fitted",
    "log_distance_to_nearest_mode",
    "prior_cost",
    "hypothesis_rank",
    "grown_to_mode",
    "range_m",
)
"""Per box option, after the one-hot class and before the point set's descriptors."""

ANCHORED_FEATURE_NAMES: tuple[str, ...] = (
    "anchored",
    "offset_from_viewer_m",
    "offset_sideways_m",
    "offset_up_m",
)
"""With anchored options (``BoxQuality.anchored``), after ``OPTION_FEATURE_NAMES``: whether the
option is a mode-sized box placed by the fitted box (set into its corner, standing on the floor
under it, or stacked inside it: ``groups.OPTION_KINDS``), and where its centre lies from the
fitted box's centre: away from the viewer (the vehicle origin) in the ground plane, sideways
(absolute) and up."""

VISIBILITY_FEATURE_NAMES: tuple[str, ...] = ("seen_free_share", "seen_occupied_share")
"""With ``BoxQuality.visibility``, after the anchored ones: the share of the option's volume that
the frame's rays passed through, and the share where they ended (``visibility.box_visibility``).
An object's box holds its visible surface and the unseen space behind it; a box grown the wrong
way, or of the wrong size, holds space the scan saw empty."""


_ROW_SAMPLE_STREAM = 1
"""Spawn key of ``BoxQuality.sampled_rows``' generator beside its ``seed``."""

INFERENCE_SETTINGS: tuple[str, ...] = ("screen_trees", "screen_keep", "interleaved_walk")
"""``BoxQuality`` settings that change how a fitted regressor predicts, not what it learnt
(``BoxQuality.with_inference``)."""


def option_features(
    boxes: np.ndarray,
    class_id: int,
    descriptors: np.ndarray,
    prior: BoxSizePrior,
    num_classes: int,
    anchored: bool = False,
    anchor_mask: np.ndarray | None = None,
    free_space: FreeSpace | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A point set's box options for one class and what the regressor reads of each.

    Args:
        boxes: (M, 7) the set's box hypotheses, the fitted box first.
        class_id: the class the options are grown for.
        descriptors: (len(DESCRIPTOR_NAMES),) the set's geometric descriptors.
        prior: the class size prior that grows the options.
        num_classes: C, the number of object classes.
        anchored: add the class's sizes placed by the fitted box (``BoxSizePrior.anchored``,
            ``standing``, ``stacked``) to the options.
        anchor_mask: (M,) bool, the boxes sizes are placed by (the fitted one is always among
            them); ``None``: the fitted box alone.
        free_space: the frame's rays; given, ``VISIBILITY_FEATURE_NAMES`` are added.

    Returns:
        ``(options, features)``: (K, 7) boxes (``BoxSizePrior.options``) and (K, F) features: the
        one-hot class (C), ``OPTION_FEATURE_NAMES``, ``ANCHORED_FEATURE_NAMES`` when
        ``anchored``, ``VISIBILITY_FEATURE_NAMES`` with ``free_space``, then the descriptors.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    options, features, _, _ = class_option_features(
        boxes,
        [np.arange(len(boxes))],
        class_id,
        np.asarray(descriptors, np.float64).reshape(1, -1),
        prior,
        num_classes,
        anchored,
        anchor_mask,
        free_space,
    )
    return options, features


def class_option_features(
    proposal_boxes: np.ndarray,
    members: Sequence[np.ndarray],
    class_id: int,
    descriptors: np.ndarray,
    prior: BoxSizePrior,
    num_classes: int,
    anchored: bool = False,
    anchor_mask: np.ndarray | None = None,
    free_space: FreeSpace | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The box options of many point sets of one class and their features, set after set, each
    set's options in ``BoxSizePrior.options``'s order (one call for all sets: per-set calls cost
    more than the regressor at inference).

    Args:
        proposal_boxes: (M, 7) boxes of the proposals.
        members: S arrays of proposal indices, one per set, its fitted box first.
        class_id: the class of every one of these sets.
        descriptors: (S, len(DESCRIPTOR_NAMES)) their descriptors.
        prior: the class size prior.
        num_classes: C.
        anchored: add the class's sizes placed by each set's fitted box (corners, floor, stack).
        anchor_mask: (M,) bool over ``proposal_boxes``, the boxes sizes are placed by besides each
            set's fitted box (``Proposals.anchor_mask``: the scene-aligned ones); ``None``: the
            fitted boxes alone.
        free_space: the frame's rays; given, ``VISIBILITY_FEATURE_NAMES`` are added.

    Returns:
        ``(options, features, owners, sources)``: (K, 7) boxes, (K, F) features (as
        ``option_features``), (K,) the set (0..S-1) of each row and (K,) the proposal its box came
        from (an anchored box's is the box it was placed by).
    """
    member_ids, owner, starts = flatten_sets(members)
    boxes = np.asarray(proposal_boxes, np.float64)[member_ids]
    member = np.arange(len(boxes)) - starts[owner]
    fitted = boxes[starts]
    anchor_rows = starts
    if anchor_mask is not None:
        # Rows of boxes, set after set (members are listed set after set), each set's fitted first.
        anchor_rows = np.union1d(starts, np.flatnonzero(np.asarray(anchor_mask, bool)[member_ids]))
    has_size = np.isfinite(prior.sizes[class_id]).all()
    options, cost, kinds, option_sources, mode_ids = prior.option_sources(
        boxes,
        class_id,
        fitted_boxes=fitted[owner],
        anchor_boxes=boxes[anchor_rows] if anchored and has_size else None,
    )
    from_boxes = kinds < 2  # hypotheses and grown ones come from a box; the others from an anchor
    box_rows = np.where(from_boxes, option_sources, 0)
    anchor_of = anchor_rows[np.where(from_boxes, 0, option_sources)] if len(anchor_rows) else box_rows
    owner = np.where(from_boxes, owner[box_rows], owner[anchor_of])
    member = np.where(from_boxes, member[box_rows], 0)
    sources = np.where(from_boxes, member_ids[box_rows], member_ids[anchor_of])
    grown = mode_ids + 1
    is_anchored = ~from_boxes
    # Set after set, each set's options in the order BoxSizePrior.options gives one set's (its
    # blocks list the sets in order, so a stable sort by set keeps that order within each).
    order = np.argsort(owner, kind="stable")
    options, cost, owner, member, grown, sources, is_anchored = (
        a[order] for a in (options, cost, owner, member, grown, sources, is_anchored)
    )
    log_dims = np.log(np.maximum(_horizontal_sorted_sizes(options), 1e-3))
    log_fitted = np.log(np.maximum(_horizontal_sorted_sizes(fitted), 1e-3))[owner]
    modes = prior.class_modes(class_id)
    modes = modes[np.isfinite(modes).all(axis=1)] if len(modes) else modes
    to_mode = np.full(len(options), np.inf) if len(modes) else np.zeros(len(options))
    for log_mode in np.log(modes):  # one mode at a time: no (K, modes, 3) array
        np.minimum(to_mode, np.abs(log_dims - log_mode).sum(axis=1), out=to_mode)
    one_hot = np.zeros((len(options), num_classes))
    one_hot[:, class_id] = 1.0
    columns = [
        one_hot,
        log_dims,
        log_dims - log_fitted,
        to_mode,
        cost,
        np.minimum(member, 2),
        grown,
        np.hypot(options[:, 0], options[:, 1]),
    ]
    if anchored:
        columns += [is_anchored, *_offsets_from_fitted(options, fitted[owner])]
    if free_space is not None:
        columns.append(box_visibility(free_space, options))
    columns.append(np.asarray(descriptors, np.float64)[owner])
    # Filled column block by column block (np.column_stack made each column 2-D first).
    widths = [1 if column.ndim == 1 else column.shape[1] for column in columns]
    features = np.empty((len(options), sum(widths)))
    at = 0
    for column, width in zip(columns, widths):
        features[:, at : at + width] = column.reshape(len(options), width)
        at += width
    return options, features, owner, sources


def _offsets_from_fitted(options: np.ndarray, fitted: np.ndarray) -> tuple[np.ndarray, ...]:
    """(away from the viewer, sideways (absolute), up) offsets in metres of (K, 7) options' centres
    from their (K, 7) fitted boxes' centres; the viewer is the vehicle origin."""
    offset = options[:, :3] - fitted[:, :3]
    radial = fitted[:, :2] / np.maximum(np.linalg.norm(fitted[:, :2], axis=1), 1e-6)[:, None]
    away = np.einsum("kd,kd->k", offset[:, :2], radial)
    sideways = np.abs(offset[:, 0] * radial[:, 1] - offset[:, 1] * radial[:, 0])
    return away, sideways, offset[:, 2]


def num_option_features(num_classes: int, anchored: bool = False, visibility: bool = False) -> int:
    extra = len(ANCHORED_FEATURE_NAMES) if anchored else 0
    extra += len(VISIBILITY_FEATURE_NAMES) if visibility else 0
    return num_classes + len(OPTION_FEATURE_NAMES) + extra + len(DESCRIPTOR_NAMES)


@dataclasses.dataclass
class BoxQuality:
    """Predicts the 3D IoU of a point set's box options with the object it belongs to.

    Args:
        background_rate: share of the point sets that overlap no annotation (IoU below
            ``min_overlap``) taken into training, each with a random class and the target 0 (their
            options' best IoU with any annotation); they teach that structure and clutter fit no
            object whatever the box.
        min_overlap: a point set whose best proposal overlaps an annotated box at least this much
            is trained towards the IoU of each option with the nearest annotated object of that
            box's class (a set of several crates holds several right boxes, one per crate).
        max_iter: boosting iterations (no early stopping: all of them are fitted).
        max_leaf_nodes: leaves per tree. The earlier 300 trees of 31 leaves with early stopping
            underfitted: on its own training frames it picked an option at IoU 0.6 for under a
            third of the sets that had one. 500 of 63 chose and scored better on held-out frames;
            2,000 of 127 overfitted (the issue notes of 2026-11-24 give the ad hoc runs).
        seed: seeds the background sample, its classes, the rows' sample (``row_share``) and the
            regressor.
        row_share: the share of the training rows ``fit`` boosts on, a uniform sample drawn with
            ``seed`` (1: every row). A fit's time grows about linearly with its rows; a next round
            that refits the regressor fits on ``LoopSettings.refit_row_share`` of them. The
            ``training_digest`` leaves it out: it names the rows a regressor learned from, sampled
            or not, so that a round on the same rows keeps either.
        anchored: the options include each class size set into the fitted box's corners
            (``BoxSizePrior.anchored``): the boxes of objects in a segment of several, and of
            objects seen from one side. Checkpoints from before it load with ``False``.
        visibility: the regressor also reads how much of each option the frame's rays saw empty
            or occupied (``VISIBILITY_FEATURE_NAMES``; the point sets' groups must carry their
            frame's ``free_space``). Checkpoints from before it load with ``False``.
        screen_trees: at inference, ``predict_best`` first sums this many trees over every option
            and walks the rest only for each set's ``screen_keep`` best by that partial sum
            (0: every tree over every option). The choice and the predicted IoU of an option it
            keeps are those of the full walk, bit for bit; a set's choice differs only when its
            best option ranks below ``screen_keep`` after ``screen_trees`` trees. 50 of 500 trees
            keeping 32 of some 200 options per set changed the held-out F-score by under 0.01
            (``bench detect --heldout``, docs/performance.md); files from before it load with 0.
        screen_keep: options per set that the screen keeps.
        interleaved_walk: walk the trees eight rows at a time (``_compile_walk``); False walks one
            row at a time (``_compile_row_walk``, the reference the benchmarks compare with). The
            sums are the same bit for bit either way; an inference setting, not saved.
    """

    background_rate: float = 0.1
    min_overlap: float = 0.1
    max_iter: int = 500
    max_leaf_nodes: int = 63
    learning_rate: float = 0.1
    seed: int = 0
    row_share: float = 1.0
    anchored: bool = True
    visibility: bool = True
    screen_trees: int = 50
    screen_keep: int = 32
    interleaved_walk: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.background_rate <= 1.0:
            raise InputError(f"background_rate must lie in [0, 1], got {self.background_rate}")
        if not 0.0 < self.min_overlap < 1.0:
            raise InputError(f"min_overlap must lie in (0, 1), got {self.min_overlap}")
        if self.max_iter < 1:
            raise InputError(f"max_iter must be >= 1, got {self.max_iter}")
        if self.max_leaf_nodes < 2:
            raise InputError(f"max_leaf_nodes must be >= 2, got {self.max_leaf_nodes}")
        if isinstance(self.row_share, bool) or not 0.0 < float(self.row_share) <= 1.0:
            raise InputError(f"row_share must lie in (0, 1], got {self.row_share!r}")
        for name in ("screen_trees", "screen_keep"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InputError(f"{name} must be an integer >= 0, got {value!r}")
        if self.screen_trees and self.screen_keep < 1:
            raise InputError("screen_keep must be >= 1 when screen_trees is on")

    def training_rows(
        self,
        frames: Sequence,
        prior: BoxSizePrior,
        num_classes: int,
        excluded: dict[int, set[int]] | None = None,
        box_targets: dict[int, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(R, F) features and (R,) target IoUs of every option of the training point sets.

        Args:
            frames: ``mining.FrameProposals`` with their labels.
            prior: the size prior that grows the options.
            num_classes: C.
            excluded: per frame index, point sets (group ids) to leave out (real objects whose
                segment is wrong, from a review).
            box_targets: per frame index, (L,) which of its labels' boxes are box targets
                (``None``, or a frame left out: all). A set whose best overlapping label is not
                one is left out: that box is the model's own, and IoUs against it would teach the
                regressor to agree with the model. (A kept set's options are still measured
                against every label of its class, as ``bench hitl`` measured it.)
        """
        rng = np.random.default_rng(self.seed)
        rows, targets = [], []
        for frame in frames:
            if not len(frame.label_boxes):
                continue
            skip = (excluded or {}).get(frame.frame_index, set())
            learn = (box_targets or {}).get(frame.frame_index)
            learn = np.ones(len(frame.label_boxes), bool) if learn is None else np.asarray(learn, bool)
            iou = box_iou_3d(frame.proposal_boxes, frame.label_boxes)
            members = frame.groups.members()
            taken: list[tuple[int, int, bool]] = []  # (set, class of its options, overlaps a label)
            for g, set_members in enumerate(members):
                best = iou[set_members].max(axis=0)
                label = int(best.argmax())
                overlapping = best[label] >= self.min_overlap
                # Both draws for every set, taken or not: the sample depends on the seed alone.
                take_background = rng.random() < self.background_rate
                random_class = int(rng.integers(num_classes))
                if g in skip or not (overlapping or take_background) or (overlapping and not learn[label]):
                    continue
                class_id = int(frame.label_class_ids[label]) if overlapping else random_class
                taken.append((g, class_id, bool(overlapping)))
            frame_rows, frame_targets = self._frame_rows(frame, members, taken, prior, num_classes)
            rows += frame_rows
            targets += frame_targets
        if not rows:
            raise InputError("box quality: no training frame has annotations")
        return np.concatenate(rows), np.concatenate(targets)

    def _frame_rows(
        self,
        frame,
        members: Sequence[np.ndarray],
        taken: Sequence[tuple[int, int, bool]],
        prior: BoxSizePrior,
        num_classes: int,
    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """``training_rows``' rows of one frame: per taken ``(set, class, overlapping)``, its
        options' (K, F) features and (K,) targets, in ``taken``'s order. The options are grown
        for all sets of one class and kind in one ``class_option_features`` call (per-set calls
        cost most of a refit's row building); each set's rows are the ones a call for it alone
        gives."""
        if not taken:
            return [], []
        features_of: list[np.ndarray | None] = [None] * len(taken)
        targets_of: list[np.ndarray | None] = [None] * len(taken)
        free_space = self.free_space_of(frame.groups)
        for class_id, overlapping in sorted({(c, o) for _, c, o in taken}):
            picked = [k for k, (_, c, o) in enumerate(taken) if (c, o) == (class_id, overlapping)]
            set_ids = [taken[k][0] for k in picked]
            options, features, owner, _ = class_option_features(
                frame.proposal_boxes,
                [members[g] for g in set_ids],
                class_id,
                frame.groups.descriptors[set_ids],
                prior,
                num_classes,
                self.anchored,
                frame.groups.anchor_mask,
                free_space,
            )
            # An overlapping set's options are right when they fit any object of its class (the
            # neighbour's box in a stack of crates is no worse than the first one's); a
            # background set's, when they fit anything.
            same_class = frame.label_class_ids == class_id
            reference = frame.label_boxes[same_class] if overlapping else frame.label_boxes
            set_targets = box_iou_3d(options, reference).max(axis=1)
            # (rows come set after set: owner is sorted)
            bounds = np.cumsum(np.bincount(owner, minlength=len(picked)))[:-1]
            for k, set_features, set_target in zip(
                picked, np.split(features, bounds), np.split(set_targets, bounds), strict=True
            ):
                features_of[k], targets_of[k] = set_features, set_target
        return features_of, targets_of

    def free_space_of(self, groups: ProposalGroups) -> FreeSpace | None:
        """The free space the features read from ``groups``: theirs with ``visibility``, else none."""
        if not self.visibility:
            return None
        if groups.free_space is None:
            raise InputError(
                "box quality: this regressor reads free space, but the point sets carry none"
                " (group them with Detector.group)"
            )
        return groups.free_space

    def fit(
        self, features: np.ndarray, targets: np.ndarray, progress: Callable[[int, int], None] | None = None
    ) -> BoxQuality:
        """Fit the regressor on (R, F) option features and their (R,) IoUs; returns self.

        ``progress(trees fitted, trees)`` is called before the first tree and after each (the
        same trees as without it, bit for bit); an exception it raises (a cancel) stops the fit."""
        features, targets = _checked_rows(features, targets)
        kept = self.sampled_rows(len(targets))
        self.trees_ = self._boost(features[kept], targets[kept], self.max_iter, progress)
        self.num_features_ = features.shape[1]
        self.training_digest_ = self.training_digest(features, targets)
        return self

    def sampled_rows(self, num_rows: int) -> np.ndarray | slice:
        """Which of ``num_rows`` training rows ``fit`` boosts on: (round(row_share * R),) sorted
        indices drawn without replacement (at least 2), from a stream of ``seed``'s own (not the
        background sample's); every row (a slice) with ``row_share`` 1."""
        if self.row_share >= 1.0:
            return slice(None)
        num_kept = min(num_rows, max(2, round(float(self.row_share) * num_rows)))
        rng = np.random.default_rng([int(self.seed), _ROW_SAMPLE_STREAM])
        return np.sort(rng.choice(num_rows, num_kept, replace=False))

    def _boost(
        self,
        features: np.ndarray,
        targets: np.ndarray,
        num_trees: int,
        progress: Callable[[int, int], None] | None = None,
    ) -> dict[str, np.ndarray]:
        """``num_trees`` boosted trees of this regressor's leaves, learning rate and seed fitted to
        ``targets``, as ``_export_trees``' arrays; ``progress`` as ``fit``'s."""
        from sklearn.ensemble import HistGradientBoostingRegressor

        watch = {}
        if progress is not None:
            # scikit-learn's boosting has no callback; its early-stopping scorer is called before
            # the first tree and after each. This one scores nothing (no prediction) and reports
            # the trees, and stopping never triggers (patience beyond the last tree): the fit is
            # the one without it, tree for tree.
            watch = {
                "validation_fraction": None,
                "scoring": _TreeProgress(progress, int(num_trees)),
                "n_iter_no_change": int(num_trees) + 1,
            }
        regressor = HistGradientBoostingRegressor(
            max_iter=int(num_trees),
            max_leaf_nodes=self.max_leaf_nodes,
            learning_rate=self.learning_rate,
            early_stopping=progress is not None,
            random_state=self.seed,
            **watch,
        ).fit(features, targets)
        return _export_trees(regressor)

    def continued(
        self,
        features: np.ndarray,
        targets: np.ndarray,
        num_trees: int,
        progress: Callable[[int, int], None] | None = None,
    ) -> BoxQuality:
        """A copy of this fitted regressor boosted on: ``num_trees`` more trees (its leaves and
        learning rate) fitted to what it gets wrong on (R, F) ``features`` and their (R,) IoUs,
        added after its own. Boosting goes on from its raw sums (not clipped), so the copy predicts
        what one longer boosting run would, with the last trees fitted to these rows: a new
        label's options are corrected at a fraction of a fit from scratch. ``progress`` as
        ``fit``'s, over the new trees."""
        if isinstance(num_trees, bool) or not isinstance(num_trees, (int, np.integer)) or num_trees < 1:
            raise InputError(f"box quality: num_trees must be an integer >= 1, got {num_trees!r}")
        features, targets = _checked_rows(features, targets, self.num_features_)
        residuals = targets - _evaluate_trees(self.trees_, features, interleaved=self.interleaved_walk)
        more = self._boost(features, residuals, num_trees, progress)
        offset = len(self.trees_["is_leaf"])
        for key in ("left", "right", "roots"):  # node indices: the new trees' nodes come after
            more[key] = more[key] + offset
        trees = {
            key: np.concatenate([self.trees_[key], more[key]])
            for key in ("feature", "threshold", "left", "right", "is_leaf", "value", "roots")
        }
        trees["baseline"] = self.trees_["baseline"] + more["baseline"]
        out = dataclasses.replace(self)
        out.trees_ = _check_trees(trees, self.num_features_)
        out.num_features_ = self.num_features_
        out.training_digest_ = None
        return out

    def training_digest(self, features: np.ndarray, targets: np.ndarray) -> str:
        """A SHA-256 (hex) of what a fit on (R, F) ``features`` and (R,) ``targets`` depends on:
        the rows, their targets and the fit's settings but ``row_share``. ``fit`` keeps it as
        ``training_digest_`` and it is saved with the trees: a regressor whose digest equals the one
        of new rows learned from those rows (all of them, or a sample), and need not be fitted
        again."""
        digest = hashlib.sha256()
        settings = (
            self.background_rate, self.min_overlap, self.max_iter, self.max_leaf_nodes,
            self.learning_rate, self.seed, self.anchored, self.visibility,
        )  # fmt: skip
        digest.update(repr(settings).encode())
        for array in (features, targets):
            array = np.ascontiguousarray(array, np.float64)
            digest.update(repr(array.shape).encode())
            digest.update(array.tobytes())
        return digest.hexdigest()

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(R,) predicted IoUs in [0, 1] of (R, F) option features."""
        features = np.asarray(features, np.float64)
        if features.ndim != 2 or features.shape[1] != self.num_features_:
            raise InputError(
                f"box quality: expected (R, {self.num_features_}) features, got {features.shape}"
            )
        return np.clip(_evaluate_trees(self.trees_, features, interleaved=self.interleaved_walk), 0.0, 1.0)

    def predict_best(self, features: np.ndarray, owners: np.ndarray) -> np.ndarray:
        """(R,) predicted IoUs of (R, F) option features of the sets ``owners`` (R,) names, each
        set's best option's exactly as ``predict`` gives it, with the screen (``screen_trees``,
        ``screen_keep``): options it drops get -1, below every prediction. Without it, ``predict``.
        """
        num_trees = len(self.trees_["roots"])
        if not self.screen_trees or self.screen_trees >= num_trees:
            return self.predict(features)
        features = np.asarray(features, np.float64)
        owners = np.asarray(owners, np.int64)
        if features.ndim != 2 or features.shape[1] != self.num_features_ or owners.shape != (len(features),):
            raise InputError(
                f"box quality: expected (R, {self.num_features_}) features and (R,) owners, got"
                f" {features.shape} and {owners.shape}"
            )
        partial = _evaluate_trees(
            self.trees_, features, last_tree=self.screen_trees, interleaved=self.interleaved_walk
        )
        # Each set's screen_keep best rows by partial sum walk on.
        kept = _best_in_sets(owners, partial, self.screen_keep)
        out = np.full(len(features), -1.0)
        out[kept] = np.clip(
            _evaluate_trees(
                self.trees_,
                features[kept],
                first_tree=self.screen_trees,
                initial=partial[kept],
                interleaved=self.interleaved_walk,
            ),
            0.0,
            1.0,
        )
        return out

    def with_screen(self, screen_trees: int, screen_keep: int) -> BoxQuality:
        """A copy of this fitted regressor that screens options as given (``screen_trees`` 0: off)."""
        return self.with_inference(screen_trees=screen_trees, screen_keep=screen_keep)

    def with_inference(self, **changes) -> BoxQuality:
        """A copy of this fitted regressor with inference settings changed (``screen_trees``,
        ``screen_keep``, ``interleaved_walk``); the trees are shared."""
        unknown = set(changes) - set(INFERENCE_SETTINGS)
        if unknown:
            raise InputError(f"not an inference setting of the box quality regressor: {sorted(unknown)}")
        changed = dataclasses.replace(self, **changes)
        changed.trees_, changed.num_features_ = self.trees_, self.num_features_
        changed.training_digest_ = getattr(self, "training_digest_", None)
        return changed

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fitted trees as plain arrays (for ``np.savez``; ``from_arrays`` reads them back)."""
        return {
            **self.trees_,
            "num_features": np.array(self.num_features_),
            "anchored": np.array(self.anchored),
            "visibility": np.array(self.visibility),
            "screen_trees": np.array(self.screen_trees),
            "screen_keep": np.array(self.screen_keep),
            **(
                {"training_digest": np.frombuffer(bytes.fromhex(self.training_digest_), np.uint8)}
                if getattr(self, "training_digest_", None)
                else {}
            ),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], where: str = "box quality arrays") -> BoxQuality:
        """The regressor ``to_arrays`` wrote, its trees checked (``_check_trees``) so that every walk
        stays in bounds and ends; ``InputError`` starting with ``where`` otherwise."""
        try:
            flags = {name: _flag(arrays, name) for name in ("anchored", "visibility")}
            missing = [key for key in (*_TREE_KEYS, "num_features") if key not in arrays]
            if missing:
                raise InputError(f"lacks {', '.join(missing)}")
            num_features = np.asarray(arrays["num_features"])
            if num_features.shape != () or num_features.dtype.kind not in "iu":
                raise InputError(
                    f"num_features must be an integer, got {num_features.dtype} {num_features.shape}"
                )
            if not 1 <= int(num_features) <= MAX_FEATURES:
                raise InputError(f"num_features must lie in [1, {MAX_FEATURES}], got {int(num_features)}")
            trees = _check_trees({key: np.asarray(arrays[key]) for key in _TREE_KEYS}, int(num_features))
            # Files from before the screen walk every tree, as they were measured.
            screen_trees, screen_keep = _count(arrays, "screen_trees"), _count(arrays, "screen_keep")
            model = cls(
                **flags,
                screen_trees=0 if screen_trees is None else screen_trees,
                screen_keep=cls.screen_keep if screen_keep is None else screen_keep,
            )
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
        model.trees_ = trees
        model.num_features_ = int(num_features)
        model.training_digest_ = _digest(arrays, where)
        return model

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``to_arrays`` to ``path`` (.npz), whole or not at all."""
        path = Path(path)
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, **self.to_arrays())
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> BoxQuality:
        """The regressor ``save`` wrote to ``path``, read as untrusted input: no array larger than
        ``MAX_TREE_NODES`` is read and the trees are checked (``from_arrays``); ``InputError``
        naming the file otherwise."""
        path = Path(path)
        return cls.from_arrays(
            _read_arrays(path, (*_TREE_KEYS, *_SCALAR_KEYS, "training_digest")), where=str(path)
        )


MAX_TREE_NODES = 2**22
"""The most tree nodes a box quality file may hold: 67 times the 62,500 of the default regressor
(500 trees of at most 125 nodes), some 120 MB of arrays. No array of the file larger than this is
read."""

MAX_FEATURES = 2**16
"""The most option features a regressor may read (``num_option_features`` gives 38 for the 7
classes, and under 300 for ``checkpoint.MAX_CLASSES``)."""

MAX_FILE_BYTES = 2**30

_TREE_KEYS = ("feature", "threshold", "left", "right", "is_leaf", "value", "roots", "baseline")
_SCALAR_KEYS = ("num_features", "anchored", "visibility", "screen_trees", "screen_keep")


def _flag(arrays: Mapping[str, np.ndarray], name: str) -> bool:
    """A boolean scalar of ``arrays``; ``False`` when missing (files from before the option)."""
    if name not in arrays:
        return False
    value = np.asarray(arrays[name])
    if value.shape != () or value.dtype.kind != "b":
        raise InputError(f"{name} must be a boolean, got {value.dtype} {value.shape}")
    return bool(value)


def _count(arrays: Mapping[str, np.ndarray], name: str) -> int | None:
    """A non-negative integer scalar of ``arrays``; ``None`` when missing (files from before it)."""
    if name not in arrays:
        return None
    value = np.asarray(arrays[name])
    if value.shape != () or value.dtype.kind not in "iu":
        raise InputError(f"{name} must be an integer, got {value.dtype} {value.shape}")
    if not 0 <= int(value) <= MAX_TREE_NODES:
        raise InputError(f"{name} must lie in [0, {MAX_TREE_NODES}], got {int(value)}")
    return int(value)


def _checked_rows(
    features: np.ndarray, targets: np.ndarray, num_features: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(R, F) features and (R,) targets as float64, R >= 2, finite, F ``num_features`` when
    given; ``InputError`` otherwise."""
    features = np.asarray(features, np.float64)
    targets = np.asarray(targets, np.float64)
    if features.ndim != 2 or targets.shape != (len(features),) or len(features) < 2:
        raise InputError(
            f"box quality: features must be (R, F) and targets (R,), R >= 2, got {features.shape}"
            f" and {targets.shape}"
        )
    if num_features is not None and features.shape[1] != num_features:
        raise InputError(f"box quality: expected (R, {num_features}) features, got {features.shape}")
    if not (np.isfinite(features).all() and np.isfinite(targets).all()):
        raise InputError("box quality: features and targets must be finite")
    return features, targets


def _digest(arrays: Mapping[str, np.ndarray], where: str) -> str | None:
    """The saved ``training_digest_`` (hex); ``None`` when missing (files from before it)."""
    if "training_digest" not in arrays:
        return None
    value = np.asarray(arrays["training_digest"])
    if value.shape != (32,) or value.dtype != np.uint8:
        raise InputError(f"{where}: training_digest must be 32 bytes, got {value.dtype} {value.shape}")
    return value.tobytes().hex()


def _check_trees(trees: dict[str, np.ndarray], num_features: int) -> dict[str, np.ndarray]:
    """``trees`` (``_export_trees``'s arrays) in the dtypes ``_evaluate_trees`` walks, checked so
    that no walk reads out of bounds or loops: the compiled walk reads indices unchecked, and a
    node that is its own descendant would never return (not even to a cancel).

    Every tree is a contiguous run of nodes starting at its root, and as the fitter lays them out
    (depth first), every split node's children come after it in its own tree: so each step of a
    walk moves forward, and it ends at a leaf within that tree. A leaf's children and feature are
    never read, so any values pass there.

    Raises:
        InputError: for a wrong dtype or shape, a child, root or feature index out of bounds or not
            after its parent, or a NaN or infinite threshold, value or baseline.
    """
    kinds = {"i": ("iu", "integer"), "f": ("f", "float"), "b": ("b", "boolean")}
    expected = {"feature": "i", "left": "i", "right": "i", "roots": "i", "is_leaf": "b"}
    for key, array in trees.items():
        allowed, name = kinds[expected.get(key, "f")]
        if array.ndim != 1 or array.dtype.kind not in allowed:
            raise InputError(f"{key} must be a 1-D {name} array, got {array.dtype} {array.shape}")
    is_leaf = trees["is_leaf"]
    num_nodes = len(is_leaf)
    if not 1 <= num_nodes <= MAX_TREE_NODES:
        raise InputError(f"the trees must hold 1 to {MAX_TREE_NODES} nodes, got {num_nodes}")
    for key in ("feature", "threshold", "left", "right", "value"):
        if len(trees[key]) != num_nodes:
            raise InputError(f"{key} has {len(trees[key])} entries for {num_nodes} nodes")
    baseline = trees["baseline"].astype(np.float64)
    if baseline.shape != (1,) or not np.isfinite(baseline).all():
        raise InputError(f"baseline must be one finite number, got {baseline.shape}")
    # Integers compared in int64 (uint64 beyond it wraps negative, and is refused as such).
    roots = trees["roots"].astype(np.int64)
    if (
        not 1 <= len(roots) <= num_nodes
        or roots[0] != 0
        or (np.diff(roots) <= 0).any()
        or roots[-1] >= num_nodes
    ):
        raise InputError(f"roots must rise strictly from 0 to below {num_nodes}")
    node = np.arange(num_nodes)
    tree_end = np.append(roots[1:], num_nodes)[np.searchsorted(roots, node, side="right") - 1]
    split = ~is_leaf
    for key in ("left", "right"):
        child = trees[key].astype(np.int64)[split]
        bad = np.flatnonzero((child <= node[split]) | (child >= tree_end[split]))
        if len(bad):
            at = node[split][bad[0]]
            raise InputError(f"{key}[{at}] = {child[bad[0]]} is not a later node of the same tree")
    feature = trees["feature"].astype(np.int64)[split]
    bad = np.flatnonzero((feature < 0) | (feature >= num_features))
    if len(bad):
        raise InputError(f"split feature {feature[bad[0]]} is not one of the {num_features} features")
    threshold, value = trees["threshold"].astype(np.float64), trees["value"].astype(np.float64)
    if not (np.isfinite(threshold[split]).all() and np.isfinite(value).all()):
        raise InputError("thresholds and values must be finite")
    # Leaves' children and features are never read: zeroed, they fit the walk's int32 too.
    return {
        "feature": np.where(split, trees["feature"], 0).astype(np.int32),
        "threshold": threshold,
        "left": np.where(split, trees["left"], 0).astype(np.int32),
        "right": np.where(split, trees["right"], 0).astype(np.int32),
        "is_leaf": is_leaf.copy(),
        "value": value,
        "roots": roots,
        "baseline": baseline,
    }


def _read_arrays(path: Path, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of the ``.npz`` at ``path`` (those it has), each read only after its
    header shows at most ``MAX_TREE_NODES`` rows and no Python objects (a few compressed bytes
    can declare gigabytes); ``InputError`` naming ``path`` if it is unreadable."""
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            raise InputError(f"{path}: box quality file larger than {MAX_FILE_BYTES // 2**20} MB")
        return load_npz(path, keys, max_points=MAX_TREE_NODES)[1]
    except OSError as exc:
        raise InputError(f"{path}: unreadable box quality arrays ({exc.strerror or exc})") from None


class _TreeProgress:
    """An early-stopping scorer of scikit-learn's boosting that reports ``progress(trees fitted,
    num_trees)`` and scores nothing: called once before the first tree, then after each."""

    def __init__(self, progress: Callable[[int, int], None], num_trees: int) -> None:
        self.progress = progress
        self.num_trees = num_trees
        self.calls = 0

    def __call__(self, estimator, features, targets, **kwargs) -> float:
        self.progress(min(self.calls, self.num_trees), self.num_trees)
        self.calls += 1
        return 0.0


def _export_trees(regressor) -> dict[str, np.ndarray]:
    """A fitted ``HistGradientBoostingRegressor`` as flat node arrays over all its trees (children
    indices made global); it relies on the estimator's ``_predictors`` and ``_baseline_prediction``,
    whose use ``predict`` is tested against."""
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("feature", "threshold", "left", "right", "is_leaf", "value")
    }
    roots, offset = [], 0
    for (predictor,) in regressor._predictors:
        nodes = predictor.nodes
        if nodes["is_categorical"].any():
            raise InputError("box quality: categorical splits are not exported")
        roots.append(offset)
        parts["feature"].append(nodes["feature_idx"].astype(np.int32))
        parts["threshold"].append(nodes["num_threshold"].astype(np.float64))
        parts["left"].append(nodes["left"].astype(np.int32) + offset)
        parts["right"].append(nodes["right"].astype(np.int32) + offset)
        parts["is_leaf"].append(nodes["is_leaf"].astype(bool))
        parts["value"].append(nodes["value"].astype(np.float64))
        offset += len(nodes)
    out = {k: np.concatenate(v) for k, v in parts.items()}
    out["roots"] = np.array(roots, np.int64)
    out["baseline"] = np.asarray(regressor._baseline_prediction, np.float64).reshape(-1)[:1]
    return out


def _evaluate_trees(
    trees: dict[str, np.ndarray],
    features: np.ndarray,
    first_tree: int = 0,
    last_tree: int | None = None,
    initial: np.ndarray | None = None,
    interleaved: bool = True,
) -> np.ndarray:
    """The baseline plus every tree's leaf value, as scikit-learn adds them (in tree order, so the
    sums are those of one row at a time): compiled by numba, blocks of rows split over the cores,
    each block walking one tree at a time while that tree is in cache, eight rows down the tree at
    once (``_compile_walk``), or one (``interleaved`` False: ``_compile_row_walk``, the reference,
    several times faster than the vectorised ``_evaluate_trees_numpy``). Features are finite, so the
    missing-value branch of a split never applies.

    With ``first_tree``, ``last_tree`` and ``initial`` ((R,) sums so far), only trees
    ``first_tree:last_tree`` are added to ``initial``: a sum continued this way is bit for bit the
    sum of one walk over all trees (``BoxQuality.predict_best`` relies on it).
    """
    split_feature = np.where(trees["is_leaf"], -1, trees["feature"]).astype(np.int32)
    # children[2 * node + 1] is the right child (``_compile_step``).
    children = np.stack([trees["left"], trees["right"]], axis=1).astype(np.int32).reshape(-1)
    if initial is None:
        initial = np.full(len(features), float(trees["baseline"][0]))
    return run_kernel(
        _compile_walk if interleaved else _compile_row_walk,
        np.ascontiguousarray(features, np.float64),
        trees["roots"][first_tree:last_tree].astype(np.int64),
        split_feature,
        children,
        trees["threshold"].astype(np.float64),
        trees["value"].astype(np.float64),
        np.ascontiguousarray(initial, np.float64),
    )


def _compile_step():
    """One step down a tree, for both walks: values equal to a threshold go left, as in
    scikit-learn (and NaN right)."""
    import numba

    @numba.njit(inline="always")
    def step(features, row, node, feature, children, threshold):
        return children[2 * node + 1 - (features[row, feature] <= threshold[node])]

    return step


def _compile_walk():
    """The walk ``_evaluate_trees`` runs. A tree's splits depend on the row, so one row's walk is a
    chain of dependent loads and unpredictable branches; eight rows walked side by side, each in
    scalars of its own (which numba keeps in registers; an array of eight went through memory and
    gained half as much), overlap those latencies. Measured on a bench frame's 241,000 options:
    2.5 times faster than one row at a time over the first 50 trees, 1.9 times over the rest, and
    the same sums bit for bit."""
    import numba

    block = 1024  # rows per block: a few hundred kB of features, while one tree stays in L1
    step = _compile_step()

    @numba.njit(inline="always")
    def advance(features, row, node, feature, split_feature, children, threshold):
        """One level down for a row still inside the tree (``feature`` >= 0); a row at its leaf
        stays."""
        if feature < 0:
            return node, feature
        node = step(features, row, node, feature, children, threshold)
        return node, split_feature[node]

    @numba.njit(parallel=True, cache=True, nogil=True)
    def walk(features, roots, split_feature, children, threshold, value, initial):
        num_rows = features.shape[0]
        total = np.empty(num_rows)
        for b in numba.prange((num_rows + block - 1) // block):
            lo, hi = b * block, min((b + 1) * block, num_rows)
            acc = initial[lo:hi].copy()
            for t in range(roots.shape[0]):
                root = roots[t]
                r = lo
                while r + 8 <= hi:
                    n0 = n1 = n2 = n3 = n4 = n5 = n6 = n7 = root
                    f0 = f1 = f2 = f3 = f4 = f5 = f6 = f7 = split_feature[root]
                    # (max(f0, ..., f7) >= 0 reads shorter and ran 5 % slower)
                    while (
                        f0 >= 0 or f1 >= 0 or f2 >= 0 or f3 >= 0 or f4 >= 0 or f5 >= 0 or f6 >= 0 or f7 >= 0
                    ):
                        n0, f0 = advance(features, r, n0, f0, split_feature, children, threshold)
                        n1, f1 = advance(features, r + 1, n1, f1, split_feature, children, threshold)
                        n2, f2 = advance(features, r + 2, n2, f2, split_feature, children, threshold)
                        n3, f3 = advance(features, r + 3, n3, f3, split_feature, children, threshold)
                        n4, f4 = advance(features, r + 4, n4, f4, split_feature, children, threshold)
                        n5, f5 = advance(features, r + 5, n5, f5, split_feature, children, threshold)
                        n6, f6 = advance(features, r + 6, n6, f6, split_feature, children, threshold)
                        n7, f7 = advance(features, r + 7, n7, f7, split_feature, children, threshold)
                    i = r - lo
                    acc[i] += value[n0]
                    acc[i + 1] += value[n1]
                    acc[i + 2] += value[n2]
                    acc[i + 3] += value[n3]
                    acc[i + 4] += value[n4]
                    acc[i + 5] += value[n5]
                    acc[i + 6] += value[n6]
                    acc[i + 7] += value[n7]
                    r += 8
                while r < hi:  # the block's last rows, one at a time
                    node = root
                    feature = split_feature[node]
                    while feature >= 0:
                        node = step(features, r, node, feature, children, threshold)
                        feature = split_feature[node]
                    acc[r - lo] += value[node]
                    r += 1
            total[lo:hi] = acc
        return total

    return walk


def _compile_row_walk():
    """``_compile_walk`` one row at a time: the reference walk."""
    import numba

    block = 1024
    step = _compile_step()

    @numba.njit(parallel=True, cache=True, nogil=True)
    def row_walk(features, roots, split_feature, children, threshold, value, initial):
        num_rows = features.shape[0]
        total = np.empty(num_rows)
        for b in numba.prange((num_rows + block - 1) // block):
            lo, hi = b * block, min((b + 1) * block, num_rows)
            acc = initial[lo:hi].copy()
            for t in range(roots.shape[0]):
                for r in range(lo, hi):
                    node = roots[t]
                    feature = split_feature[node]
                    while feature >= 0:
                        node = step(features, r, node, feature, children, threshold)
                        feature = split_feature[node]
                    acc[r - lo] += value[node]
            total[lo:hi] = acc
        return total

    return row_walk


def _evaluate_trees_numpy(trees: dict[str, np.ndarray], features: np.ndarray) -> np.ndarray:
    """``_evaluate_trees`` in plain numpy (the reference its test compares with): one tree at a time,
    all rows descending a level per step (a few hundred short vector steps; walking all trees at
    once gathers over rows x trees and was several times slower). Features are finite, so the
    missing-value branch of a split never applies."""
    num_rows = len(features)
    columns = np.ascontiguousarray(features.T)  # (F, R): one feature's values are contiguous
    rows = np.arange(num_rows)
    feature, threshold = trees["feature"], trees["threshold"]
    left, right, is_leaf, value = trees["left"], trees["right"], trees["is_leaf"], trees["value"]
    total = np.full(num_rows, float(trees["baseline"][0]))
    for root in trees["roots"].tolist():
        node = np.full(num_rows, root, np.int64)
        leaf = is_leaf[node]
        while not leaf.all():
            go_left = columns[feature[node], rows] <= threshold[node]
            node = np.where(leaf, node, np.where(go_left, left[node], right[node]))
            leaf = is_leaf[node]
        total += value[node]
    return total


def choose_boxes(
    proposal_boxes: np.ndarray,
    groups: ProposalGroups,
    class_ids: np.ndarray,
    prior: BoxSizePrior,
    quality: BoxQuality,
    subset: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point set's option of highest predicted IoU for its class.

    Args:
        proposal_boxes: (M, 7) boxes of the proposals.
        groups: their point sets (G).
        class_ids: (G,) the class of each set.
        prior: grows the options.
        quality: the fitted regressor.
        subset: (S,) the sets to choose for (default: all).

    Returns:
        ``(boxes, proposal_ids, predicted_iou)``: (S, 7) chosen boxes, (S,) the proposal each
        option came from, (S,) its predicted IoU, in the order of ``subset``.
    """
    members = groups.members()
    chosen = np.arange(groups.num_groups) if subset is None else np.asarray(subset, np.int64)
    boxes = np.zeros((len(chosen), 7))
    proposal_ids = np.zeros(len(chosen), np.int64)
    predicted = np.zeros(len(chosen))
    # A few thousand sets at a time: a dense scan's tens of thousands of sets have millions of
    # options, whose features alone would take gigabytes at once.
    for lo in range(0, len(chosen), SETS_PER_CHUNK):
        block = slice(lo, lo + SETS_PER_CHUNK)
        boxes[block], proposal_ids[block], predicted[block] = _choose_chunk(
            proposal_boxes,
            groups,
            members,
            chosen[block],
            np.asarray(class_ids)[chosen[block]],
            prior,
            quality,
        )
    return boxes, proposal_ids, predicted


def _best_in_sets(owners: np.ndarray, values: np.ndarray, keep: int) -> np.ndarray:
    """(K,) ascending rows of each set's ``keep`` greatest (R,) ``values`` (the earlier row first
    on ties): ``flatnonzero(rank_within_sets(owners, -values) < keep)``. Sets listed set after set
    (``class_option_features``' order) are ranked one at a time in a compiled kernel instead of
    sorting every row; other orders take the general way."""
    owners = np.asarray(owners, np.int64)
    if len(owners) < 2 or np.all(owners[1:] >= owners[:-1]):
        starts = np.flatnonzero(np.r_[True, owners[1:] != owners[:-1]]) if len(owners) else owners
        mask = run_kernel(_compile_best_in_runs, np.ascontiguousarray(values, np.float64), starts, keep)
        return np.flatnonzero(mask)
    return np.flatnonzero(rank_within_sets(owners, -np.asarray(values, np.float64)) < keep)


def _compile_best_in_runs():
    import numba

    @numba.njit(cache=True, nogil=True)
    def best_in_runs(values, starts, keep):
        mask = np.zeros(len(values), np.bool_)
        for k in range(len(starts)):
            lo = starts[k]
            hi = starts[k + 1] if k + 1 < len(starts) else len(values)
            if hi - lo <= keep:
                mask[lo:hi] = True
                continue
            if keep == 1:  # the first greatest: no sort
                best = lo
                for j in range(lo + 1, hi):
                    if values[j] > values[best]:
                        best = j
                mask[best] = True
                continue
            # A stable sort of -values: equal values keep their order, the earlier row first.
            order = np.argsort(-values[lo:hi], kind="mergesort")
            for j in range(keep):
                mask[lo + order[j]] = True
        return mask

    return best_in_runs


SETS_PER_CHUNK = 2048
"""Point sets whose options ``choose_boxes`` builds and rates at once, class by class (at most
some 400,000 options and 120 MB of features at the default prior's 200 options per set)."""


def _choose_chunk(
    proposal_boxes: np.ndarray,
    groups: ProposalGroups,
    members: list[np.ndarray],
    chosen: np.ndarray,
    chosen_classes: np.ndarray,
    prior: BoxSizePrior,
    quality: BoxQuality,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``choose_boxes`` for the sets ``chosen`` (S,) of classes ``chosen_classes`` (S,): class by
    class (a set's options are all of its one class, so the screen and the choice need no other
    class's options; the options of all classes at once made a copy of a hundred megabytes)."""
    num_classes = len(prior.sizes)
    boxes = np.zeros((len(chosen), 7))
    proposal_ids = np.zeros(len(chosen), np.int64)
    predicted = np.zeros(len(chosen))
    for class_id in np.unique(chosen_classes).tolist():
        rows = np.flatnonzero(chosen_classes == class_id)
        options, features, owner, source = class_option_features(
            proposal_boxes,
            [members[g] for g in chosen[rows].tolist()],
            int(class_id),
            groups.descriptors[chosen[rows]],
            prior,
            num_classes,
            quality.anchored,
            groups.anchor_mask,
            quality.free_space_of(groups),
        )
        iou = quality.predict_best(features, owner)
        first = _best_in_sets(owner, iou, 1)  # each set's best option
        set_rows = rows[owner[first]]
        boxes[set_rows], proposal_ids[set_rows] = options[first], source[first]
        predicted[set_rows] = iou[first]
    return boxes, proposal_ids, predicted
