"""What a user does, one function each, called by both the command line and the app: retrain a
session (``retrain_session``). Opening a session's data set (``session.store.open_session_data``)
and resolving a model (``session.models.resolve_model``) live with the session."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

from factorydet_core.detection.detector import Detector
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.measure import compare_models
from factorydet_core.io.dataset import Dataset
from factorydet_core.proposals.settings import FrontEndParams
from factorydet_core.scale.jobs import proposer, scoring
from factorydet_core.scale.runner import Execution
from factorydet_core.session.store import SessionDB
from factorydet_core.session.world import WorldFrames, session_world
from factorydet_core.training.loop import (
    cached_calibration,
    cached_proposals,
    run_notes,
    session_references_and_sparse,
    train_session,
)
from factorydet_core.training.mining import FrameProposals, Progress, TrainingRun
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import InputError


@dataclasses.dataclass(frozen=True)
class Retrained:
    """What ``retrain_session`` did."""

    run_id: int
    run: TrainingRun
    detector: Detector
    """The front half the run's frames were proposed with (calibrated when asked)."""
    train_frames: list[FrameProposals]
    """The training frames' proposals (the app looks for suspect labels on them)."""
    comparison: dict | None
    """``compare_models``' table of the models before and the new one on the test frames, or
    ``None`` when not compared (no test split, or not asked)."""
    notes: tuple[str, ...] = ()
    """What the run did otherwise than its settings asked, and why (``training.loop.run_notes``)."""


def training_frame_indices(dataset: Dataset, max_train_frames: int | None = None) -> list[int]:
    """The frames ``retrain_session`` trains on: the data set's train split (every frame without
    one), its first ``max_train_frames`` if given."""
    train = dataset.splits.get("train") or list(range(dataset.num_frames))
    return list(train[:max_train_frames] if max_train_frames else train)


def retrain_session(
    db: SessionDB,
    dataset: Dataset,
    settings: LoopSettings,
    front_end: FrontEndParams,
    *,
    mode: str = "next",
    before: Mapping[str, DetectionModel] | None = None,
    after_label: str = "run {run_id}",
    compare: bool = True,
    calibrate: bool = True,
    max_train_frames: int | None = None,
    max_test_frames: int | None = None,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    command: str = "",
    execution: Execution | None = None,
    world: WorldFrames | None = None,
) -> Retrained:
    """Retrain a session on its corrected labels and review verdicts: propose its training frames
    (through the session's cache), run ``training.loop.train_session`` (which stores the run and
    mines its review queue), then measure the models ``before`` and the new one on the test
    frames against the session's labels and store that table with the run.

    Args:
        settings: how to train (``LoopSettings``, whole).
        front_end: the front half's settings; the new models carry them.
        mode: "full" (a first fit and every mining round) or "next" (one more round).
        before: models to compare the new one with, by the name the table gives them.
        after_label: the new model's name in the table (``{run_id}`` is filled in).
        compare: measure on the test split (skipped when the data set has none).
        calibrate: refine the extrinsics by ICP on the first training frame (multi-sensor data).
        max_train_frames, max_test_frames: use only the first frames of each split.
        progress: called with (what, done, total); ``what`` is "calibrate", "proposals", "world", "fit",
            "box quality", "round" or "compare". "box quality" says (0, 1) when the regressor's
            fit starts and when the run starts waiting for it, then (trees fitted, trees) while the
            run waits. "compare" says (0, 1) first, then the test frames the proposals
            cache lacks, one by one (on Ray workers from (0, their number)). "compare" comes after
            the run is stored: a progress that raises to cancel must not raise then.
        should_stop: polled between epochs; True cancels (``types.Cancelled``), storing nothing.
        execution: where the per-frame work runs (``scale.runner.Execution``: Ray workers): the
            front half of the frames the cache lacks, and each mining round's scoring of the
            training frames (``scale.jobs.scoring``); ``None``: this process. The fits run here
            either way.
        world: the session's frames placed in one world frame (``session.world.session_world``),
            for ``LoopSettings.carry_pseudo_labels``; placed here when a next round carries
            pseudo-labels and none is given (progress "world").

    Raises:
        InputError: for a "next" round on a session without a run to continue, or a session that
            cannot be written (checked first: the run would be lost only after minutes of work).
    """
    if mode == "next" and db.latest_run_id() is None:
        raise InputError(f"session {db.session.name!r} has no training run to continue; use mode 'full'")
    db.check_writable()
    report = progress or (lambda what, done, total: None)
    train = training_frame_indices(dataset, max_train_frames)
    detector = Detector(front_end)
    if calibrate and dataset.num_sensors > 1:
        report("calibrate", 0, 1)
        cached_calibration(db, dataset, detector, train[0])
    propose = proposer(execution)
    frames = cached_proposals(db, dataset, detector, train, progress, propose)
    if world is None and mode == "next" and settings.carries_pseudo_labels:
        world, _ = session_world(
            db.session, dataset, progress=lambda done, total: report("world", done, total)
        )
    with scoring(execution) as score:
        run_id, run = train_session(
            db, frames, settings, mode=mode, data_ref=str(dataset.path), front_end=front_end,
            progress=progress, should_stop=should_stop, command=command, score=score, world=world,
        )  # fmt: skip
    test: Sequence[int] = dataset.splits.get("test") or []
    test = list(test[:max_test_frames] if max_test_frames else test)
    table = None
    if compare and test:
        report("compare", 0, 1)
        # The test frames' front half, on a session's first run, is most of the comparison's time:
        # its frames report as the comparison's progress.
        test_frames = cached_proposals(
            db, dataset, detector, test, lambda _what, done, total: report("compare", done, total), propose
        )
        models = {**(before or {}), after_label.format(run_id=run_id): run.model}
        # A person's labels too sparse to train on, or to tune the thresholds on, are neither
        # references nor false positives.
        references, sparse = session_references_and_sparse(db, test, settings.measure_points_floor(dataset))
        table = compare_models(models, test_frames, references, ignored=sparse)
        db.set_run_metrics(run_id, {"test_frames": test, "compare": table})
    return Retrained(run_id, run, detector, frames, table, run_notes(db.run_config(run_id)))
