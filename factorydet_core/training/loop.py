"""The labelling loop: train from a session's corrected labels and review verdicts, compare the
model before and after, and a simulated reviewer that answers the review queue from the
simulator's hidden truth (for ``factorydet bench hitl`` only; the app never calls it).

The loop, as the app and ``factorydet loop`` run it:

1. ``train_session(..., mode="full")`` trains from the session's labels with blind hard-negative
   mining (the paper's procedure) and mines one more batch after the last round. Every mined
   negative goes to the review queue of that run.
2. People review the queue (``SessionDB.review``): background, object of class C, wrong box, skip.
3. ``train_session(..., mode="next")`` goes on training the session's chosen (else latest) model
   on the corrected labels (``continued_model``, ``LoopSettings.round_epochs``). Its background
   set is the random first sample, every negative mined so far except those reviewed as real
   objects, and the confirmed background. It then mines the next queue.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.box_head import BoxHead
from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.classifier import ProposalClassifier, check_init_model
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.geometry import points_in_box
from factorydet_core.io.dataset import Dataset
from factorydet_core.proposals.merge import ExtrinsicRefinement, merge_frame
from factorydet_core.proposals.settings import FrontEndParams
from factorydet_core.session.store import (
    HIDE_LABELLED_IOU,
    MODEL_BOX_ORIGINS,
    SessionDB,
    label_arrays,
    on_labelled_object,
    read_cache,
    write_cache,
)
from factorydet_core.session.world import MOVING_CLASSES, WorldFrames, counting_box, place_box
from factorydet_core.training.mining import (
    FoldModel,
    FrameProposals,
    Progress,
    Scorer,
    TrainingRun,
    collect_proposals,
    group_overlaps,
    proposals_from_arrays,
    proposals_to_arrays,
    score_frames,
    train_with_mining,
)
from factorydet_core.training.settings import LoopSettings, folds_continue
from factorydet_core.types import (
    InputError,
)

MODES = ("full", "next")
_CACHE_FORMAT = 5  # bump when FrameProposals or the front half's output changes (5: sampled points)


def new_classifier(settings: LoopSettings, class_names: Sequence[str]) -> ProposalClassifier | BoxHead:
    """The unfitted back half ``settings.method`` names, with the settings' training options."""
    if settings.method in ("box_head", "head_options"):
        return BoxHead(
            class_names=tuple(class_names),
            epochs=settings.epochs,
            class_weight=settings.class_weight,
            seed=settings.seed,
            num_threads=settings.num_threads,
            recalibrate_background=settings.recalibrate_background,
            recalibrate_by_class=settings.recalibrate_by_class,
        )
    return ProposalClassifier(
        class_names=tuple(class_names),
        width=settings.width,
        epochs=settings.epochs,
        class_weight=settings.class_weight,
        seed=settings.seed,
        num_threads=settings.num_threads,
        geometry=settings.geometry,
    )


def continued_model(
    db: SessionDB,
    settings: LoopSettings,
    classifier: ProposalClassifier | BoxHead,
    front_end: FrontEndParams | None = None,
) -> tuple[int | None, DetectionModel | None, str]:
    """The session model a 'next' round under ``settings`` goes on from, if it can: the run whose
    model people chose to show (``SessionDB.shown_model``; a run they did not choose is not built
    on), else the latest run's.

    Args:
        front_end: the front half the round proposes with; a model trained on another one is not
            continued (its inputs would come from another distribution).

    Returns:
        ``(run_id, model, why)``: the run and its model, or ``None`` for both and why it cannot
        (no run, ``round_epochs`` 0, an unreadable checkpoint, another method, classes, network or
        front half).
    """
    runs = _runs_with_models(db)
    if not runs:
        return None, None, "the session has no training run"
    if not settings.round_epochs:
        return None, None, "round_epochs is 0: every round trains afresh"
    run_id = _continued_run_id(db, runs)
    try:
        model = DetectionModel.load(db.session.path / runs[run_id]["model_path"])
    except (InputError, OSError) as exc:
        return None, None, f"run {run_id}'s model does not load: {exc}"
    if model.method != settings.method:
        kinds = f"a {model.method} model, the settings train {settings.method}"
        return None, None, f"run {run_id}'s model is {kinds}"
    if front_end is not None and model.front_end is not None and model.front_end != front_end:
        return None, None, f"run {run_id}'s model was trained on another front half"
    try:
        check_init_model(classifier, model.classifier)
    except InputError as exc:
        return None, None, str(exc)
    return run_id, model, ""


def _runs_with_models(db: SessionDB) -> dict[int, dict]:
    """The session's training runs that have a model, by id."""
    return {run["id"]: run for run in db.training_runs() if run["model_path"]}


def _continued_run_id(db: SessionDB, runs: dict[int, dict]) -> int:
    """The run of ``runs`` (by id, each with a model) a next round goes on from: the shown
    model's, else the latest."""
    run_id = max(runs)
    chosen = db.shown_model()
    if chosen is not None:
        shown = [i for i, run in runs.items() if db.session.path / run["model_path"] == chosen[1]]
        run_id = shown[0] if shown else run_id
    return run_id


def fold_fit_epochs(db: SessionDB, settings: LoopSettings, mode: str, num_frames: int) -> int:
    """The epochs a run of ``mode`` on ``num_frames`` training frames will spend fitting its
    threshold fold models (``LoopSettings.folds_for``), counted as epochs on every training frame
    (K models on (K - 1) / K of the frames each): ``round_epochs`` each for a next round that goes
    on from the fold models of the run it continues (``folds_continue``, and that run has them),
    else ``epochs`` each; 0 without folds. What the app's time-left estimate counts."""
    folds = settings.folds_for(num_frames)
    if not folds:
        return 0
    continues = False
    if mode == "next" and folds_continue(dataclasses.asdict(settings), next_rounds=True):
        runs = _runs_with_models(db)
        continues = bool(runs) and bool(db.fold_model_paths(_continued_run_id(db, runs)))
    return (folds - 1) * (settings.round_epochs if continues else settings.epochs)


def run_notes(config: Mapping[str, object]) -> tuple[str, ...]:
    """What a stored run (its ``train_session`` config) did otherwise than its settings asked,
    one sentence each: a next round trained afresh, threshold folds skipped. What ``factorydet
    train`` and the app say with the run."""
    notes = []
    if config.get("mode") == "next" and config.get("afresh_because"):
        notes.append(f"trained afresh, not going on from a model: {config['afresh_because']}")
    if config.get("threshold_folds_skipped"):
        notes.append(str(config["threshold_folds_skipped"]))
    return tuple(notes)


def continued_folds(db: SessionDB, run_id: int, classifier: ProposalClassifier | BoxHead) -> list[FoldModel]:
    """Run ``run_id``'s threshold fold models that a next round can go on from (those that load and
    fit ``classifier``'s network); a fold model that does not is fitted afresh, as without them."""
    folds = []
    for path in db.fold_model_paths(run_id):
        try:
            fold = DetectionModel.load(path)
            check_init_model(classifier, fold.classifier)
            frame_indices = tuple(int(i) for i in fold.note["fold_frames"])
            if fold.note.get("run_id") != run_id:  # (a file left from another run)
                continue
        except (InputError, OSError, KeyError, TypeError, ValueError):
            continue
        folds.append(FoldModel(frame_indices, fold.classifier))
    return folds


def proposals_cache_key(dataset: Dataset, detector: Detector) -> str:
    """Names the cached proposals of a data set under a front half's settings and calibration."""
    digest = hashlib.sha256()
    digest.update(json.dumps([_CACHE_FORMAT, dataset.content_hash()]).encode())
    digest.update(json.dumps(dataclasses.asdict(detector.params), sort_keys=True, default=str).encode())
    if detector.T_vehicle_sensor is not None:
        digest.update(np.round(detector.T_vehicle_sensor, 6).tobytes())
    return f"proposals_{digest.hexdigest()[:16]}"


_CALIBRATION_FORMAT = 1  # bump when refine_extrinsics' defaults or result change


def cached_calibration(db: SessionDB, dataset: Dataset, detector: Detector, frame_index: int) -> Detector:
    """``detector.calibrate`` on frame ``frame_index`` through the session's ``cache/``: ICP of
    the rig's sensors against each other (seconds, every retrain) runs once per data
    set, frame and starting extrinsics, and is read back after. Returns ``detector``, calibrated."""
    digest = hashlib.sha256()
    digest.update(json.dumps([_CALIBRATION_FORMAT, dataset.content_hash(), int(frame_index)]).encode())
    if detector.T_vehicle_sensor is not None:
        digest.update(np.round(detector.T_vehicle_sensor, 9).tobytes())
    key = f"calibration_{digest.hexdigest()[:16]}"
    arrays = read_cache(db.session, key)
    fields = [field.name for field in dataclasses.fields(ExtrinsicRefinement)]
    if arrays is not None and set(fields) <= set(arrays):
        detector.calibration_ = ExtrinsicRefinement(**{name: arrays[name] for name in fields})
        detector.T_vehicle_sensor = detector.calibration_.T_vehicle_sensor
        return detector
    detector.calibrate(dataset.frame(frame_index))
    write_cache(db.session, key, dataclasses.asdict(detector.calibration_))
    return detector


Proposer = Callable[[Dataset, Sequence[int], Detector, Progress | None], list[FrameProposals]]
"""What proposes frames for ``cached_proposals``: ``mining.collect_proposals`` in this process, or
``scale.jobs.proposer`` on Ray workers."""


def cached_proposals(
    db: SessionDB,
    dataset: Dataset,
    detector: Detector,
    frame_indices: Sequence[int],
    progress: Progress | None = None,
    propose: Proposer = collect_proposals,
) -> list[FrameProposals]:
    """``collect_proposals`` through the session's ``cache/``: frames proposed before under the same
    settings are read back, the others proposed (by ``propose``) and added."""
    key = proposals_cache_key(dataset, detector)
    arrays = read_cache(db.session, key)
    cached = {f.frame_index: f for f in proposals_from_arrays(arrays)} if arrays else {}
    missing = [int(i) for i in frame_indices if int(i) not in cached]
    if missing:
        for frame in propose(dataset, missing, detector, progress):
            cached[frame.frame_index] = frame
        write_cache(db.session, key, proposals_to_arrays([cached[i] for i in sorted(cached)]))
    return [cached[int(i)] for i in frame_indices]


def session_references(
    db: SessionDB, frame_indices: Sequence[int], min_points: int = 0
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Frame index -> (boxes (R, 7), class_ids (R,)) of the session's current labels (those a
    person made or confirmed: the model's unconfirmed pre-labels are not truth), less those too
    sparse to train on (``sparse_label_mask`` at ``min_points``)."""
    return session_references_and_sparse(db, frame_indices, min_points)[0]


def session_references_and_sparse(
    db: SessionDB, frame_indices: Sequence[int], min_points: int
) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]], dict[int, np.ndarray]]:
    """``session_references`` of the frames, and frame index -> (Q, 7) boxes of the labels
    holding fewer than ``min_points`` of their frame's points (``sparse_label_mask``): places a
    measurement against those references ignores, as training (or the thresholds' tuning) does.
    Each frame's labels are read and its points counted once (a measurement needs both)."""
    references, sparse_boxes = {}, {}
    for index in frame_indices:
        labels = _reviewed_labels(db, index)
        sparse = sparse_label_mask(db.dataset, index, labels, min_points)
        boxes, class_ids, _ = label_arrays(
            [lab["label"] for lab, s in zip(labels, sparse) if not s], db.class_names
        )
        references[int(index)] = (boxes, class_ids)
        sparse_boxes[int(index)] = np.array(
            [lab["box"] for lab, s in zip(labels, sparse) if s], np.float64
        ).reshape(-1, 7)
    return references, sparse_boxes


def _reviewed_labels(db: SessionDB, frame_index: int) -> list[dict]:
    """The frame's labels a person made or confirmed, as ``sparse_label_mask`` reads them."""
    return [
        {"box": list(lab.box), "origin": lab.origin, "label": lab}
        for lab in db.labels(frame_index)
        if lab.reviewed
    ]


def with_session_labels(
    db: SessionDB,
    frames: Sequence[FrameProposals],
    snapshot: dict | None = None,
    min_points: int = 0,
    tuning_min_points: int = 0,
) -> list[FrameProposals]:
    """The frames with the session's labels in place of the data set's annotations: the current
    ones, or those of a stored ``snapshot`` (``SessionDB.snapshot``), so that a run trains on
    exactly the labels it records. The model's pre-labels nobody has confirmed yet are neither
    objects nor background: their places are left out of training (``FrameProposals.ignore_boxes``),
    and so are a person's labels that hold fewer than ``min_points`` of their frame's points
    (``sparse_label_mask``; ``LoopSettings.label_min_points``). Labels whose box is the model's
    own (origins ``MODEL_BOX_ORIGINS``) are marked so (``FrameProposals.label_model_box_mask``),
    and so are a person's labels that train but hold fewer than ``tuning_min_points`` of their
    frame's points, which the thresholds' tuning ignores
    (``FrameProposals.label_tuning_ignore_mask``; ``LoopSettings.threshold_label_min_points``)."""
    return session_labels(db, frames, snapshot, min_points, tuning_min_points)[0]


def session_labels(
    db: SessionDB,
    frames: Sequence[FrameProposals],
    snapshot: dict | None = None,
    min_points: int = 0,
    tuning_min_points: int = 0,
) -> tuple[list[FrameProposals], int]:
    """``with_session_labels``' frames, and how many labels it left out as too sparse."""
    names = db.class_names
    if snapshot is None:
        by_frame = {
            f.frame_index: [
                {
                    "box": list(lab.box),
                    "class_name": lab.class_name,
                    "origin": lab.origin,
                    "instance_id": lab.instance_id,
                    "reviewed": lab.reviewed,
                }
                for lab in db.labels(f.frame_index)
            ]
            for f in frames
        }
    else:
        by_frame = {f.frame_index: [] for f in frames}
        for lab in snapshot["labels"]:
            by_frame.setdefault(lab["frame_index"], []).append(lab)
    out, num_sparse = [], 0
    for frame in frames:
        given = by_frame[frame.frame_index]
        labels = [lab for lab in given if lab.get("reviewed", True)]
        ignored = [lab["box"] for lab in given if not lab.get("reviewed", True)]
        tuning_ignored = None
        if max(min_points, tuning_min_points) > 0:
            counts = label_point_counts(db.dataset, frame.frame_index, labels)
            sparse = counts < min_points
            num_sparse += int(sparse.sum())
            ignored += [lab["box"] for lab, is_sparse in zip(labels, sparse) if is_sparse]
            labels = [lab for lab, is_sparse in zip(labels, sparse) if not is_sparse]
            if tuning_min_points > min_points:
                tuning_ignored = counts[~sparse] < tuning_min_points
        model_box_mask = np.array([lab["origin"] in MODEL_BOX_ORIGINS for lab in labels], bool)
        instance_classes = {
            int(lab["instance_id"]): names.index(lab["class_name"])
            for lab in labels
            if lab["origin"] == "dataset" and lab.get("instance_id") is not None
        }
        out.append(
            frame.with_labels(
                np.array([lab["box"] for lab in labels], np.float64).reshape(-1, 7),
                np.array([names.index(lab["class_name"]) for lab in labels], np.int64),
                instance_classes,
                np.array(ignored, np.float64).reshape(-1, 7),
                model_box_mask,
                tuning_ignored,
            )
        )
    return out, num_sparse


POLICY_ORIGINS = ("dataset", "import")
"""Label origins that follow the data set's annotation policy as they come (its own annotations,
labels imported from elsewhere): ``sparse_label_mask`` does not check them."""


def sparse_label_mask(
    dataset: Dataset | None, frame_index: int, labels: Sequence[dict], min_points: int
) -> np.ndarray:
    """(L,) bool: which of a frame's labels (dicts with ``box`` and ``origin``) a person made
    (origin not in ``POLICY_ORIGINS``) and hold fewer than ``min_points`` of the frame's points,
    counted in ``world.counting_box`` (the box's surface grown a little, the floor band left
    out) of the frame merged with its nominal extrinsics. Reads the frame only when it has such a
    label."""
    if min_points <= 0:
        return np.zeros(len(labels), bool)
    return label_point_counts(dataset, frame_index, labels) < min_points


def label_point_counts(dataset: Dataset | None, frame_index: int, labels: Sequence[dict]) -> np.ndarray:
    """(L,) int64: the frame's points each of a frame's labels (dicts with ``box`` and ``origin``)
    holds, as ``sparse_label_mask`` counts them, for those a person made; the largest int64 for
    those of ``POLICY_ORIGINS``, which are not checked. Reads the frame only when it has such a
    label."""
    counts = np.full(len(labels), np.iinfo(np.int64).max, np.int64)
    checked = [k for k, lab in enumerate(labels) if lab["origin"] not in POLICY_ORIGINS]
    if not checked:
        return counts
    if dataset is None:
        raise InputError(
            "label_min_points, threshold_label_min_points: counting a label's points needs the"
            " session's data set"
        )
    points = merge_frame(dataset.frame(frame_index)).points
    for k in checked:
        counts[k] = int(points_in_box(points, counting_box(labels[k]["box"])).sum())
    return counts


def _merge(*maps: dict[int, list]) -> dict[int, list]:
    out: dict[int, list] = {}
    for m in maps:
        for index, items in m.items():
            out.setdefault(index, []).extend(items)
    return out


def _without(sets_by_frame: dict[int, list], removed: dict[int, list]) -> dict[int, list]:
    """``sets_by_frame`` (frame index -> point sets, each a sequence of patch ids) less the sets
    of ``removed``."""
    out: dict[int, list] = {}
    for index, sets in sets_by_frame.items():
        gone = {tuple(s) for s in removed.get(index, ())}
        kept = [s for s in sets if tuple(s) not in gone]
        if kept:
            out[index] = kept
    return out


def session_pseudo_labels(
    db: SessionDB,
    settings: LoopSettings,
    frame_indices: Sequence[int],
    world: WorldFrames | None = None,
) -> dict[int, tuple[list[tuple[int, ...]], np.ndarray, np.ndarray]]:
    """The pseudo-labels a next round trains with (``LoopSettings.pseudo_label_confident``), by
    frame: the session's own (``SessionDB.pseudo_labels``), and with
    ``settings.carry_pseudo_labels`` each of an object that stands still carried into every frame
    of ``frame_indices`` that shows it (``world.place_box``), unless that frame has on that object
    (box IoU ``store.HIDE_LABELLED_IOU`` or more) a label, a pseudo-label of its own or one carried
    already, or a box a person rejected there (``SessionDB.rejected_boxes``: a Background verdict,
    a deleted label). A frame takes the carried ones from the nearest frames first (the poses
    drift with the distance driven).

    Args:
        frame_indices: the training frames (only these receive carried pseudo-labels).
        world: the frames placed in one world frame; needed when the settings carry.

    Returns:
        Frame index -> ``(patch_sets, boxes, class_ids)`` as ``SessionDB.pseudo_labels``: a carried
        pseudo-label has no point set of its own (``()``) and comes after the frame's own ones.
        Empty without ``pseudo_label_confident``.

    Raises:
        InputError: the settings carry and ``world`` is missing or places another number of frames.
    """
    if settings.pseudo_label_confident is None:
        return {}
    if settings.carries_pseudo_labels:
        check_carry_world(db, world)
    own = db.pseudo_labels(settings.pseudo_label_confident)
    if not settings.carries_pseudo_labels:
        return own
    wanted = sorted({int(f) for f in frame_indices})
    names = db.class_names
    rejected = db.rejected_boxes(wanted)
    labels = db.frame_labels(wanted)  # (every frame's in one read)
    # Per frame, the boxes a carried pseudo-label must stay off.
    taken = {
        f: np.concatenate(
            [
                np.asarray(label_arrays(labels[f], names)[0], np.float64).reshape(-1, 7),
                rejected[f],
                own[f][1] if f in own else np.zeros((0, 7)),
            ]
        )
        for f in wanted
    }
    # Every pseudo-label placed once: (source frame, its boxes in every frame, visible frames, class).
    placed = []
    for source in sorted(own):
        _, boxes, class_ids = own[source]
        for box, class_id in zip(boxes, class_ids):
            if names[int(class_id)] not in MOVING_CLASSES:
                placement = place_box(world, source, box)
                placed.append((source, placement.boxes, placement.visible_mask, int(class_id)))
    out = dict(own)
    for f in wanted:
        carried = []
        for source, boxes, visible_mask, class_id in sorted(placed, key=lambda p: abs(p[0] - f)):
            if source == f or not visible_mask[f]:
                continue
            there = boxes[f]
            if len(taken[f]) and on_labelled_object(
                float(box_iou_3d(there[None], taken[f]).max()), HIDE_LABELLED_IOU
            ):
                continue
            taken[f] = np.concatenate([taken[f], there[None]])
            carried.append((there, class_id))
        if carried:
            sets, boxes, class_ids = out.get(f, ([], np.zeros((0, 7)), np.zeros(0, np.int64)))
            out[f] = (
                [*sets, *[()] * len(carried)],
                np.concatenate([boxes, np.asarray([b for b, _ in carried], np.float64)]),
                np.concatenate([class_ids, np.asarray([c for _, c in carried], np.int64)]),
            )
    return out


def check_carry_world(db: SessionDB, world: WorldFrames | None) -> None:
    """Refuse (``InputError``) to carry pseudo-labels without ``world``, or with one that places
    another number of frames than the session's data set."""
    if world is None:
        raise InputError("carrying pseudo-labels to other frames needs the frames placed in one world frame")
    if world.num_frames != db.dataset.num_frames:
        raise InputError(
            f"the world places {world.num_frames} frames; the session's data set has {db.dataset.num_frames}"
        )


def _sets_on(frame: FrameProposals, patch_sets, boxes: np.ndarray) -> list[tuple[int, ...]]:
    """Those of ``patch_sets`` (the frame's point sets, each its patch ids) whose proposal box
    overlaps one of ``boxes`` (K, 7) at ``store.HIDE_LABELLED_IOU`` or more: on that object."""
    box_of = {}
    for proposal, patch_set in enumerate(frame.patch_sets):
        box_of.setdefault(tuple(patch_set), proposal)
    sets = [tuple(p) for p in patch_sets if tuple(p) in box_of]
    if not sets or not len(boxes):
        return []
    iou = box_iou_3d(frame.proposal_boxes[[box_of[p] for p in sets]], np.asarray(boxes).reshape(-1, 7))
    return [p for p, best in zip(sets, iou.max(axis=1)) if on_labelled_object(float(best), HIDE_LABELLED_IOU)]


def train_session(
    db: SessionDB,
    frames: Sequence[FrameProposals],
    settings: LoopSettings,
    *,
    mode: str = "next",
    data_ref: str = "",
    front_end: FrontEndParams | None = None,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    command: str = "",
    score: Scorer = score_frames,
    world: WorldFrames | None = None,
) -> tuple[int, TrainingRun]:
    """Train on the session's labels and verdicts, store the run, and mine its review queue.

    Args:
        frames: the training frames' proposals (``cached_proposals``), with any labels: the
            session's replace them.
        mode: 'full' retrains from scratch with ``settings.rounds`` blind mining rounds; 'next'
            runs one more round on top of everything mined and reviewed so far, going on from the
            session's chosen (else latest) model (``continued_model``: its network trained on for
            ``settings.round_epochs`` epochs, its box quality regressor kept unless
            ``settings.refit_box_quality``, and then too when the labels it was fitted on did
            not change) when it can, else
            afresh (the run's config says why).
        front_end: the front half's settings the frames were proposed with, saved whole in the
            models and the run's record.
        should_stop: cancels the run (``types.Cancelled``); nothing is stored then.
        score: what scores each round's model on the frames (``training.mining.Scorer``): here,
            or on Ray workers (``scale.jobs.scoring``).
        world: the frames placed in one world frame (``session.world.session_world``), which
            ``LoopSettings.carry_pseudo_labels`` carries the pseudo-labels of a next round with.

    Returns:
        ``(run_id, run)``.
    """
    if mode not in MODES:
        raise InputError(f"unknown training mode {mode!r}; choose from {', '.join(MODES)}")
    if not frames:
        raise InputError("no training frames")
    frame_indices = [f.frame_index for f in frames]
    if mode == "next" and settings.carries_pseudo_labels:
        check_carry_world(db, world)  # (before anything is written)
    snapshot_id = db.snapshot_labels(frame_indices)
    snapshot = db.snapshot(snapshot_id)
    # A person's labels too sparse to learn from are left out as ignored places (the run says how many).
    label_floor = settings.label_points_floor(db.dataset)
    # ... and those sparser than the thresholds' floor train but are left out of their tuning.
    tuning_floor = settings.threshold_points_floor(db.dataset)
    labelled, num_sparse = session_labels(db, frames, snapshot, label_floor, tuning_floor)
    reviewed = db.reviewed_patch_sets()
    excluded = _merge(reviewed["object"], reviewed["wrong_box"])
    classifier = new_classifier(settings, db.class_names)
    box_quality = (
        BoxQuality(
            seed=settings.seed,
            visibility=settings.quality_visibility(db.dataset),
            max_iter=settings.quality_trees,
        )
        if settings.box_quality and settings.method != "box_head"
        else None
    )
    continued_run, continued, why = None, None, ""
    reuse_quality = None
    init_folds: list[FoldModel] = []
    num_folds = settings.folds_for(len(labelled))
    if mode == "next":
        hold = settings.hold_confident
        background = _merge(db.mined_patch_sets(below_score=hold), reviewed["background"])
        if hold is not None:  # held negatives nobody has decided on: neither background nor mined
            excluded = _merge(excluded, db.mined_patch_sets(at_least_score=hold, undecided_only=True))
            if settings.hold_places:
                held = db.held_places(hold, below_score=settings.pseudo_label_confident)
                labelled = [frame.with_ignored(held.get(frame.frame_index)) for frame in labelled]
        if settings.pseudo_label_confident is not None:
            # Confident negatives nobody has decided on teach their predicted class: labels, so
            # neither background nor left out.
            pseudo = session_pseudo_labels(db, settings, frame_indices, world)
            pseudo_sets = {index: sets for index, (sets, _, _) in pseudo.items()}
            background = _without(background, pseudo_sets)
            excluded = _without(excluded, pseudo_sets)
            with_pseudo = []
            for frame in labelled:  # (a frame without any: None boxes, kept as it is)
                sets, boxes, class_ids = pseudo.get(frame.frame_index, (None, None, None))
                with_pseudo.append(frame.with_pseudo_labels(boxes, class_ids, sets))
                if sets is not None and frame.frame_index in excluded and not all(sets):
                    # A carried one's object may be held here under another point set: the
                    # label decides it now (its own sets are the frame's pseudo-labels', above).
                    carried = boxes[[k for k, patch_set in enumerate(sets) if not patch_set]]
                    on_it = _sets_on(frame, excluded[frame.frame_index], carried)
                    excluded = _without(excluded, {frame.frame_index: on_it})
            labelled = with_pseudo
        rounds = 0
        continued_run, continued, why = continued_model(db, settings, classifier, front_end)
        if num_folds and folds_continue(dataclasses.asdict(settings), continued is not None):
            init_folds = continued_folds(db, continued_run, classifier)
        keep_quality = continued is not None and continued.box_quality is not None and box_quality is not None
        if keep_quality and not settings.refit_box_quality:
            box_quality = continued.box_quality
        elif keep_quality:  # a refit that would give the model's regressor back is skipped
            reuse_quality = continued.box_quality
            box_quality = dataclasses.replace(box_quality, row_share=settings.refit_row_share)
    else:
        background = reviewed["background"]
        rounds = settings.rounds
    run = train_with_mining(
        labelled,
        classifier,
        rounds=rounds,
        negatives_per_round=settings.negatives_per_round,
        initial_negatives=settings.initial_negatives,
        positive_iou=settings.positive_iou,
        fragment_iou=settings.fragment_iou,
        fragments_per_frame=settings.fragments_per_frame,
        score_threshold=settings.score_threshold,
        tune_class_thresholds=settings.class_thresholds,
        threshold_folds=num_folds,
        threshold_objective=settings.threshold_objective,
        probability_exponent=settings.probability_exponent,
        mining_threshold=settings.mining_threshold,
        nms_iou=settings.nms_iou,
        seed=settings.seed,
        box_quality=box_quality,
        reuse_box_quality=reuse_quality,
        quality_round_trees=settings.refit_trees,
        progress=progress,
        background_sets=background,
        excluded_sets=excluded,
        mine_after_last=True,
        hold_score=settings.hold_confident,
        hold_places=settings.hold_places,
        pseudo_label_score=settings.pseudo_label_confident,
        should_stop=should_stop,
        round_epochs=settings.round_epochs,
        queue_order=settings.queue_order,
        review_extra=settings.review_extra,
        model_box_targets=settings.model_box_targets,
        init_model=None if continued is None else continued.classifier,
        score=score,
        init_folds=init_folds,
    )
    for model in run.models:
        model.front_end = front_end
    config = {
        "mode": mode,
        "continued_run": continued_run,
        "settings": dataclasses.asdict(settings),
        "front_end": None if front_end is None else front_end.to_dict(),
    }
    if why and mode == "next":
        config["afresh_because"] = why
    if num_folds != settings.threshold_folds and settings.class_thresholds:
        config["threshold_folds_skipped"] = (
            f"{len(labelled)} training frame(s), fewer than the {settings.threshold_folds} threshold folds:"
            " the thresholds were tuned on the fitted frames"
        )
    config["label_points_floor"] = label_floor
    config["sparse_labels_ignored"] = num_sparse
    # A person's labels that trained but that the thresholds' tuning ignored as too sparse.
    config["threshold_points_floor"] = tuning_floor
    config["labels_tuning_ignored"] = sum(
        int(f.label_tuning_ignore_mask.sum()) for f in labelled if f.label_tuning_ignore_mask is not None
    )
    if command:
        config["command"] = command  # the checkpoints' notes say how to reproduce them
    run_id = db.save_training_run(run, data_ref, config, kind=mode, snapshot_id=snapshot_id)
    return run_id, run


# --- The simulated reviewer (benchmarks only) -----------------------------------------------------


def suspect_labels(
    db: SessionDB,
    model: DetectionModel,
    frames: Sequence[FrameProposals],
    min_iou: float = 0.5,
    max_label_probability: float = 0.2,
) -> list[dict]:
    """Labels the classifier disagrees with strongly: the point set that best matches the label
    (IoU >= ``min_iou``) gets at most ``max_label_probability`` for the label's class and a
    different class (or background) on top. Most suspect first.

    Returns:
        Dicts with ``label_id``, ``frame_index``, ``class_name``, ``box``, ``label_probability``,
        ``predicted_class`` and ``predicted_probability``.
    """

    names = (*model.class_names, "background")
    out = []
    for frame in frames:
        # (a pre-label nobody confirmed is the model's own box: its queue is where it is checked)
        labels = [lab for lab in db.labels(frame.frame_index) if lab.reviewed]
        if not labels or not frame.groups.num_groups:
            continue
        probabilities = model.probabilities(frame.groups)
        overlap = group_overlaps(frame, np.array([lab.box for lab in labels]))
        for r, lab in enumerate(labels):
            g = int(overlap[:, r].argmax())
            if overlap[g, r] < min_iou or lab.class_name not in names:
                continue
            p = probabilities[g]
            p_label = float(p[names.index(lab.class_name)])
            top = int(p.argmax())
            if p_label <= max_label_probability and names[top] != lab.class_name:
                out.append(
                    {
                        "label_id": lab.id,
                        "frame_index": lab.frame_index,
                        "class_name": lab.class_name,
                        "box": list(lab.box),
                        "label_probability": round(p_label, 4),
                        "predicted_class": names[top],
                        "predicted_probability": round(float(p[top]), 4),
                    }
                )
    out.sort(key=lambda s: s["label_probability"])
    return out
