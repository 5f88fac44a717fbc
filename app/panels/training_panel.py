"""Retraining (shared by every browser): start the next mining round or a full retrain, watch it,
cancel it; the before/after table; the model rounds with their label snapshots, and switching the
shown model back to an earlier one."""

from __future__ import annotations

import dataclasses
import math

import viser

from factorydet_core.detection.model import DEFAULT_MODEL, PAPER_MODEL, DetectionModel
from factorydet_core.evaluation.measure import comparison_markdown
from factorydet_core.scale.runner import Execution
from factorydet_core.training.settings import (
    CONTROL_BY_FIELD,
    LOOP_CONTROLS,
    Control,
    LoopSettings,
    loop_settings_from,
)
from factorydet_core.types import InputError

from ..state import AppState
from ..trainer import TrainingWorker, run_choice
from . import short_name

MODES = {"next round": "next", "full retrain": "full"}
SHIPPED = "shipped default model"
SHIPPED_PAPER = "shipped paper pipeline"
FIRST_CONTROLS = ("method", "epochs")
"""Shown above the Train button; the other ``LOOP_CONTROLS`` sit in a "Settings" folder below."""


def add_control(server: viser.ViserServer | viser.ClientHandle, control: Control, value: object):
    """The GUI handle of one training setting, showing ``value`` (``Control.shown``)."""
    shown = control.shown(value)
    if control.kind is bool:
        return server.gui.add_checkbox(control.label, initial_value=bool(shown), hint=control.help)
    if control.choices is not None:
        texts = [text for text, _ in control.choices]
        return server.gui.add_dropdown(control.label, texts, initial_value=shown, hint=control.help)
    return server.gui.add_number(
        control.label,
        initial_value=shown,
        min=control.minimum,
        max=control.maximum,
        step=control.step,
        hint=control.help,
    )


def settings_of(controls: dict[str, object], base: LoopSettings) -> LoopSettings:
    """The settings the controls show (``InputError`` for a value outside a setting's bounds)."""
    return loop_settings_from({field: handle.value for field, handle in controls.items()}, base)


def execution_of(workers: float, address: str) -> Execution:
    """The Ray controls' ``Execution``: 0 workers and no address is this process."""
    if not math.isfinite(workers) or workers != int(workers) or workers < 0:
        raise InputError(f"Ray workers must be a whole number, got {workers}")
    return Execution(workers=int(workers) or None, ray_address=address.strip() or None)


def model_choices(state: AppState) -> dict[str, str]:
    """Dropdown text -> checkpoint path of every model the session can show."""
    shipped = {SHIPPED: DEFAULT_MODEL, SHIPPED_PAPER: PAPER_MODEL}
    choices = {name: str(path) for name, path in shipped.items() if path.is_file()}
    if state.db is None:
        return choices
    for run in reversed(state.db.training_runs()):
        choices[run_choice(run["id"], run["kind"])] = str(state.db.session.path / run["model_path"])
        for r in reversed(run["rounds"]):
            choices[f"run {run['id']} round {r['round']}"] = str(state.db.session.path / r["model_path"])
    return choices


def runs_markdown(state: AppState) -> str:
    if state.db is None:
        return ""
    runs = state.db.training_runs()
    if not runs:
        return "_No training runs in this session yet._"
    rows = []
    for run in runs[-8:]:
        snapshot = run["snapshot_id"]
        labels = state.db.snapshot_size(snapshot) if snapshot is not None else "–"
        ignored = (run.get("config") or {}).get("sparse_labels_ignored")
        if ignored and snapshot is not None:
            # Labels the floor (label_min_points) left out; they trained as ignored places.
            labels = f"{labels - ignored} (+{ignored} too sparse, ignored)"
        last = run["rounds"][-1]["train_metrics"].get("f1") if run["rounds"] else None
        f1 = "–" if last is None else f"{last:.3f}"
        when = run["created"][:16].replace("T", " ")
        rows.append(f"| {run['id']} | {run['kind']} | {len(run['rounds'])} | {labels} | {f1} | {when} |")
    return (
        "| run | mode | rounds | labels trained on | train F1 | when |\n|---|---|---|---|---|---|\n"
        + "\n".join(rows)
    )


@dataclasses.dataclass
class TrainingPanel:
    mode: viser.GuiDropdownHandle
    controls: dict[str, object]
    """One handle per ``LOOP_CONTROLS`` field."""
    train: viser.GuiButtonHandle
    cancel: viser.GuiButtonHandle
    progress: viser.GuiProgressBarHandle
    status: viser.GuiMarkdownHandle
    comparison: viser.GuiMarkdownHandle
    runs: viser.GuiMarkdownHandle
    model: viser.GuiDropdownHandle
    show_model: viser.GuiButtonHandle
    ray_workers: viser.GuiNumberHandle
    ray_address: viser.GuiTextHandle
    _seen: tuple = ()

    def execution(self) -> Execution:
        """Where the Ray controls say to propose (``InputError`` for a bad value)."""
        return execution_of(self.ray_workers.value, self.ray_address.value)

    def refresh(self, state: AppState) -> None:
        with state.lock:
            busy, status, progress = state.training_busy, state.training_status, state.training_progress
            comparison, revision, model_name = state.training_comparison, state.revision, state.model_name
            offered = state.offered_model
            method = getattr(state.model, "method", None)
        self.train.disabled = busy or state.db is None
        self.cancel.disabled = not busy
        self.progress.value = round(100.0 * progress, 1)
        shown = f"`{short_name(model_name) if model_name else 'none'}`" + (f" ({method})" if method else "")
        self.status.content = f"**Training:** {status} · shown model {shown}"
        key = (revision, id(comparison), offered)
        if key == self._seen:
            return
        self._seen = key
        self.comparison.content = (
            "**Before / after** (test frames)\n\n" + comparison_markdown(comparison) if comparison else ""
        )
        self.runs.content = runs_markdown(state)
        choices = list(model_choices(state))
        if choices and tuple(self.model.options) != tuple(choices):
            self.model.options = choices
        if offered in choices and self.model.value != offered:
            self.model.value = offered  # one click on Show this model uses the new run
        self.show_model.disabled = not choices


def build_training_panel(
    server: viser.ViserServer | viser.ClientHandle, state: AppState, worker: TrainingWorker
) -> TrainingPanel:
    with server.gui.add_folder("Training", order=40, expand_by_default=False):
        mode = server.gui.add_dropdown("Mode", list(MODES), initial_value="next round")
        controls = {
            f: add_control(server, CONTROL_BY_FIELD[f], getattr(worker.settings, f)) for f in FIRST_CONTROLS
        }
        train = server.gui.add_button(
            "Train", color="green", hint="On the corrected labels and the review verdicts, in the background"
        )
        cancel = server.gui.add_button("Cancel training", color="red", disabled=True)
        # Never animated: a browser without a GPU redraws the page for the stripes' animation, which
        # took headless Chromium most of a 2-core machine from the training it shows (the
        # walkthrough records it: docs/labelling.md).
        progress = server.gui.add_progress_bar(0.0, animated=False)
        status = server.gui.add_markdown("")
        comparison = server.gui.add_markdown("")
        runs = server.gui.add_markdown("")
        choices = list(model_choices(state)) or ["(none)"]
        model = server.gui.add_dropdown("Model", choices, initial_value=choices[0])
        show_model = server.gui.add_button("Show this model")
        with server.gui.add_folder("Settings", expand_by_default=False):
            for control in LOOP_CONTROLS:
                if control.field not in controls:
                    controls[control.field] = add_control(
                        server, control, getattr(worker.settings, control.field)
                    )
            where = worker.execution()
            ray_workers = server.gui.add_number(
                "Ray workers",
                initial_value=where.workers or 0,
                min=0,
                max=4096,
                step=1,
                hint="Propose the frames the session has not cached, and score the training frames in "
                "each mining round, on this many Ray workers (0: in the app's own process, or every "
                "CPU of the cluster below)",
            )
            ray_address = server.gui.add_text(
                "Ray address",
                initial_value=where.ray_address or "",
                hint="Blank: a Ray started on this machine; 'auto' or HOST:PORT: a running cluster "
                "(docs: Scale-out on Ray)",
            )
    panel = TrainingPanel(
        mode,
        controls,
        train,
        cancel,
        progress,
        status,
        comparison,
        runs,
        model,
        show_model,
        ray_workers,
        ray_address,
    )

    @train.on_click
    def _(event: viser.GuiEvent) -> None:
        try:
            settings = settings_of(controls, worker.settings)
            execution = panel.execution()
        except InputError as exc:
            if event.client is not None:
                event.client.add_notification("Training", str(exc), color="red", auto_close_seconds=8)
            return
        if not worker.start(MODES[mode.value], settings, execution) and event.client is not None:
            event.client.add_notification(
                "Training", "A training job is already running.", auto_close_seconds=5
            )

    cancel.on_click(lambda _: worker.cancel())

    @show_model.on_click
    def _(event: viser.GuiEvent) -> None:
        path = model_choices(state).get(model.value)
        if path is None:
            return
        try:
            loaded = DetectionModel.load(path)
        except (InputError, OSError, RuntimeError, ValueError) as exc:
            if event.client is not None:
                event.client.add_notification("Model", f"cannot load {path}: {exc}", color="red")
            return
        try:
            state.choose_model(loaded, model.value, path)
        except InputError as exc:  # shown, but the session could not record it
            if event.client is not None:
                event.client.add_notification("Model", f"not remembered in the session: {exc}", color="red")

    panel.refresh(state)
    return panel
