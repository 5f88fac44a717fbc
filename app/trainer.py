"""Retraining from the app: one background thread runs the next mining round or a full retrain on
the session's corrected labels and verdicts, reports progress into the state, can be cancelled,
and ends with a before/after table on the test frames and the new model offered, not shown: people
decide from the table whether to show it (the Training panel's **Show this model**, which the
session remembers), so a retrain that came out worse never replaces the model in use.

A crash or a cancel of the job never touches the labels: the run is stored only once it has
finished, and labels are only ever read here.
"""

from __future__ import annotations

import threading
import time
import traceback

from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.evaluation.measure import unlearned_text
from factorydet_core.scale.jobs import proposer
from factorydet_core.scale.runner import Execution
from factorydet_core.training.loop import (
    cached_calibration,
    cached_proposals,
    fold_fit_epochs,
    suspect_labels,
)
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import Cancelled, InputError
from factorydet_core.workflows import retrain_session, training_frame_indices

from .naming import short_name
from .state import SharedState

_clock = time.perf_counter
"""The clock of the time-left estimate (a test sets its own)."""


def epochs_left(
    mode: str,
    settings: LoopSettings,
    round_index: int,
    epochs_done: int,
    epochs_total: int,
    fold_epochs: int = 0,
) -> int:
    """Epochs still to fit in a run: the rest of the current round's, every later round's (a full
    retrain's rounds after the first fit ``round_epochs`` each, or ``epochs`` afresh), and
    ``fold_epochs``, the threshold fold models' after the last round
    (``training.loop.fold_fit_epochs``)."""
    rounds = settings.rounds + 1 if mode == "full" else 1
    later = max(0, rounds - round_index - 1) * (settings.round_epochs or settings.epochs)
    return max(0, epochs_total - epochs_done) + later + fold_epochs


def time_left_text(seconds: float) -> str:
    """``about 40 s`` / ``about 3 min``: an estimate, said as one."""
    if seconds < 90:
        return f"about {max(5, round(seconds / 5) * 5):.0f} s"
    return f"about {round(seconds / 60):.0f} min"


class Pace:
    """Time left in a phase of counted steps (frames of proposals, frames scored), at the pace
    since the phase's first reported step: the first report only starts the clock."""

    def __init__(self) -> None:
        self._phase: object = None
        self._start = 0.0
        self._first = 0

    def left(self, phase: object, done: int, total: int) -> float | None:
        """Seconds left in ``phase`` after ``done`` of ``total`` steps; ``None`` until a step has
        been timed (a new phase restarts the clock)."""
        if phase != self._phase:
            self._phase, self._start, self._first = phase, _clock(), done
            return None
        if done <= self._first:
            return None
        return (_clock() - self._start) / (done - self._first) * max(0, total - done)

    def text(self, phase: object, done: int, total: int) -> str:
        """`` · about 40 s left`` once known, else empty."""
        left = self.left(phase, done, total)
        return "" if left is None else f" · {time_left_text(left)} left"


def run_choice(run_id: int, kind: str) -> str:
    """The Training panel's name of a run's final model (``panels.training_panel.model_choices``)."""
    return f"run {run_id} ({kind}) final"


class TrainingWorker:
    """Runs at most one training job at a time.

    Args:
        state: the shared state (its ``db`` must be set).
        settings: how to train.
        calibrate: refine the extrinsics by ICP first (multi-sensor data), as the viewer does.
    """

    def __init__(
        self, state: SharedState, settings: LoopSettings | None = None, calibrate: bool = True
    ) -> None:
        self.state = state
        self.settings = settings or LoopSettings()
        self.calibrate = calibrate
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.last_run_id: int | None = None

    @property
    def busy(self) -> bool:
        # The status the GUI shows, not the thread's liveness: the thread lives a little after it
        # says "done", and a click right after "done" must not be refused as busy.
        return self.state.training_busy

    def _finish(self, **training) -> None:
        """End the job: publish its final status, which frees the trainer."""
        self.state.set_training(busy=False, **training)

    def execution(self) -> Execution:
        """Where retraining proposes the frames the session's cache lacks: the session's setting
        (``SessionDB.execution``; this process unless the Training panel chose Ray)."""
        if self.state.db is None:
            return Execution()
        try:
            return Execution(**self.state.db.execution())
        except InputError as exc:  # a damaged setting: say so, and work here rather than not at all
            print(f"factorydet app: the session's Ray setting is unusable ({exc}); proposing in this process")
            return Execution()

    def start(
        self, mode: str, settings: LoopSettings | None = None, execution: Execution | None = None
    ) -> bool:
        """Start a job ('next' or 'full') with ``settings`` (default: the worker's own, e.g. as
        the Training panel's controls set them) on ``execution`` (given: kept as the session's
        setting; default: the session's); False when one is already running or there is no
        session."""
        with self._lock:
            if self.busy or self.state.db is None:
                return False
            if mode == "next" and self.state.db.latest_run_id() is None:
                mode = "full"  # nothing to continue from yet
            settings = self.settings if settings is None else settings
            if execution is not None and execution != self.execution():
                self.state.db.set_execution(execution.workers, execution.ray_address)
            self._cancel.clear()
            self.state.set_training(busy=True, status=f"starting ({mode})", progress=0.0)
            self._thread = threading.Thread(
                target=self._run, args=(mode, settings), name="factorydet-training", daemon=True
            )
            self._thread.start()
            return True

    def find_suspects(self) -> bool:
        """Look for labels the shown model contradicts, in the background; False when busy."""
        with self._lock:
            if self.busy or self.state.db is None or self.state.model is None:
                return False
            self._cancel.clear()
            self.state.set_training(busy=True, status="looking for suspect labels", progress=0.0)
            self._thread = threading.Thread(target=self._suspects, name="factorydet-suspects", daemon=True)
            self._thread.start()
            return True

    def _suspects(self) -> None:
        state = self.state
        try:
            detector = self._detector()
            train = training_frame_indices(state.dataset)

            def progress(_what: str, done: int, total: int) -> None:
                if self._cancel.is_set():
                    raise Cancelled("cancelled")
                state.set_training(
                    status=f"suspect labels: proposals of frame {done} of {total}",
                    progress=0.9 * done / total,
                )

            propose = proposer(self.execution())
            frames = cached_proposals(state.db, state.dataset, detector, train, progress, propose)
            suspects = suspect_labels(state.db, state.model, frames)
            state.set_suspects(suspects)
            self._finish(status=f"{len(suspects)} suspect label(s) found", progress=1.0)
        except Cancelled:
            self._finish(status="cancelled", progress=0.0)
        except Exception as exc:  # keep the app alive; say what went wrong
            traceback.print_exc()
            self._finish(status=f"failed: {exc}", progress=0.0)

    def _detector(self) -> Detector:
        """The front half the shown model was trained with, calibrated like the viewer's."""
        dataset = self.state.dataset
        detector = Detector(params_for(self.state.model, dataset.num_sensors))
        if self.calibrate and dataset.num_sensors > 1:
            train = training_frame_indices(dataset)
            self.state.set_training(status="refining the sensor extrinsics (ICP)", progress=0.01)
            cached_calibration(self.state.db, dataset, detector, train[0])
        return detector

    def cancel(self) -> None:
        self._cancel.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self, mode: str, settings: LoopSettings) -> None:
        try:
            self._train(mode, settings)
        except Cancelled:
            self._finish(status="cancelled; nothing was stored", progress=0.0)
        except Exception as exc:  # keep the app alive; say what went wrong
            traceback.print_exc()
            self._finish(status=f"failed: {exc}", progress=0.0)

    def _train(self, mode: str, settings: LoopSettings) -> None:
        state, db, dataset = self.state, self.state.db, self.state.dataset
        with state.lock:
            # (the world the view placed for label once, if it is done: carried pseudo-labels use it)
            before, before_name, world = state.model, state.model_name, state.world
            world_status = state.world_status
        if mode == "next" and settings.carries_pseudo_labels:
            if world is None:
                # (placing them here too would run ICP twice on the same cores, with the view's
                # extrinsics or not)
                self._finish(
                    status="carrying pseudo-labels needs the frames placed in one world frame, which "
                    f"is not done ({world_status or 'not started'}): train again when it is, or turn "
                    "*Carry pseudo-labels* off",
                    progress=0.0,
                )
                return
        rounds = settings.rounds + 1 if mode == "full" else 1
        fold_epochs = fold_fit_epochs(db, settings, mode, len(training_frame_indices(dataset)))
        # The fold models that tune the thresholds take about one round's share.
        units = rounds + (1 if fold_epochs else 0)
        # Shares of the progress bar: proposals, the fits, the before/after measurement.
        fit_share = 0.75
        score_share = 0.2  # of each round's share: its scoring (the fit has the rest)
        # Of the first round's share: the box quality regressor's trees when the round's model
        # waits for them (fitted alongside that round's network; kept or done sooner, the bar
        # passes over it).
        quality_share = 0.3
        done_fits = [0]
        folds_fitted = [0]  # 1 once the last round's fold models are fitting
        fit_started = [0.0, -1, 0]  # this round's first reported epoch: when, which round, which epoch
        pace = Pace()
        execution = self.execution()
        on_ray = ""
        if execution.uses_ray:
            where = f"{execution.workers} " if execution.workers else ""
            on_ray = f" on {where}Ray workers" + (
                f" at {execution.ray_address}" if execution.ray_address else ""
            )

        def quality_room() -> float:
            """Of this round's share, what the regressor's wait has before the round's scoring."""
            return quality_share if done_fits[0] == 0 else 0.0

        def progress(what: str, done: int, total: int) -> None:
            # "compare" comes after the run is stored: too late to cancel without losing it.
            if self._cancel.is_set() and what != "compare":
                raise Cancelled("training cancelled")
            if what == "calibrate":
                state.set_training(status="refining the sensor extrinsics (ICP)", progress=0.01)
            elif what == "world":
                state.set_training(
                    status=f"placing the frames in one world frame: {done}/{total}", progress=0.1
                )
            elif what == "proposals":
                status = f"proposals: frame {done} of {total}{on_ray}" + pace.text(what, done, total)
                state.set_training(status=status, progress=0.1 * done / total)
            elif what == "score":
                # Each round scores every training frame (what mining and the thresholds read),
                # the last one after its fold models' fits.
                before = done_fits[0] + folds_fitted[0] + (1 - score_share)
                fraction = (before + score_share * done / total) / units
                status = f"round {done_fits[0] + 1} of {rounds}: scoring frame {done + 1} of {total}"
                status += pace.text((what, done_fits[0]), done, total)
                state.set_training(status=status, progress=0.1 + fit_share * fraction)
            elif what == "fit":
                fraction = (done_fits[0] + (1 - score_share - quality_room()) * done / total) / units
                status = f"round {done_fits[0] + 1} of {rounds}: epoch {done} of {total}"
                if fit_started[1] != done_fits[0]:
                    fit_started[:] = [_clock(), done_fits[0], done]
                elif done > fit_started[2]:
                    # The epochs left at this round's pace since its first reported epoch; scoring
                    # and the comparison come on top.
                    per_epoch = (_clock() - fit_started[0]) / (done - fit_started[2])
                    left = per_epoch * epochs_left(mode, settings, done_fits[0], done, total, fold_epochs)
                    status += f" · {time_left_text(left)} of fitting left"
                state.set_training(status=status, progress=0.1 + fit_share * fraction)
            elif what == "threshold folds":
                # After the last round's fit, before its scoring: the fold models' epochs.
                folds_fitted[0] = 1
                status = f"tuning the thresholds on frames no model fitted: epoch {done} of {total}"
                status += pace.text(what, done, total)
                fraction = (done_fits[0] + (1 - score_share - quality_room()) + done / total) / units
                state.set_training(status=status, progress=0.1 + fit_share * fraction)
            elif what == "box quality" and done == 0:
                # Said when its fit starts (alongside the first fit) and again if the round's model
                # has to wait for it.
                state.set_training(status="fitting the box quality regressor")
            elif what == "box quality" and done < total:
                # The round's model waits for it: its trees move the bar.
                status = f"fitting the box quality regressor: tree {done} of {total}"
                status += pace.text(what, done, total)
                left = quality_room() * (1 - done / total)
                fraction = (done_fits[0] + folds_fitted[0] + 1 - score_share - left) / units
                state.set_training(status=status, progress=0.1 + fit_share * fraction)
            elif what == "round":
                done_fits[0] = done
            elif what == "compare":
                # (after (0, 1), the test frames the cache lacks go through the front half first)
                status = "measuring before and after on the test frames"
                if 0 < done < total or (done == 0 and total > 1):
                    status += f": proposals, frame {done} of {total}" + pace.text(what, done, total)
                # (all proposed: the models are measured on them, the status plain again)
                state.set_training(status=status, progress=0.88 + 0.1 * done / max(total, 1))

        done = retrain_session(
            db, dataset, settings, params_for(before, dataset.num_sensors), mode=mode,
            before={} if before is None else {f"before ({short_name(before_name)})": before},
            after_label="after (run {run_id})", calibrate=self.calibrate, progress=progress,
            should_stop=self._cancel.is_set, execution=execution, world=world,
        )  # fmt: skip
        self.last_run_id = done.run_id
        queue = db.review_queue(done.run_id)
        alone = sum(not item["in_background"] for item in queue)
        # A class the fit did not learn, said with the run (mining with it loses the class).
        unlearned = unlearned_text(done.run.rounds[-1]["train_metrics"])
        state.offer_model(run_choice(done.run_id, mode))
        state.session_changed()
        self._finish(
            status=f"run {done.run_id} ({mode}) done: {len(queue)} items to review ({len(queue) - alone} "
            f"mined negatives{f', {alone} for review alone' if alone else ''}); the table "
            "compares it with the shown model, and **Show this model** uses it"
            + (f". {unlearned}" if unlearned else "")
            + "".join(f". Note: {note}" for note in done.notes),
            progress=1.0,
            comparison=done.comparison,
        )
