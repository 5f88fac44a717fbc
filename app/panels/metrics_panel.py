"""Metrics of the detections over the frames viewed so far, against their annotations: the
per-class table, the kinds of errors and the precision-recall curve."""

from __future__ import annotations

import dataclasses

import numpy as np
import viser
import viser.uplot

from ..state import AppState


def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def errors_markdown(errors: dict) -> str:
    """The kinds of errors at the operating point (``metrics.error_breakdown``) as a table: how
    many of each kind, and the total F-score if every error of that kind were fixed."""
    without = errors["f1_without"]
    rows = [
        f"| {group} {kind.replace('_', ' ')} | {count} | {without[kind]:.2f} |"
        for group, counts in (("FP:", errors["false_positives"]), ("missed:", errors["misses"]))
        for kind, count in counts.items()
    ]
    return "\n".join(
        [
            f"Errors by kind (F {errors['f1']:.2f} now; the last column: F with that kind fixed):",
            "",
            "| kind | n | F if fixed |",
            "|---|---|---|",
            *rows,
        ]
    )


def class_row(name: str, row: dict) -> str:
    """A class's row of the table: references, precision, recall, F-score and AP; a dash where a
    figure is undefined (precision without a detection of the class, recall without a reference)."""
    precision = row["precision"] if row["num_detections"] else None
    return (
        f"| {name} | {row['num_reference']} | {_fmt(precision)} | {_fmt(row['recall'])} | "
        f"{_fmt(row['f1'])} | {_fmt(row['ap'])} |"
    )


@dataclasses.dataclass
class MetricsPanel:
    table: viser.GuiMarkdownHandle
    plot: viser.GuiUplotHandle
    errors: viser.GuiMarkdownHandle
    _shown: tuple = ()

    def refresh(self, state: AppState) -> None:
        # Never waits for a measurement: an edit's redraw shows the last metrics, said to be out of
        # date, and the background thread's redraw the new ones.
        metrics, stale = state.shown_metrics()
        if metrics is None:
            self.table.content = (
                "_Measuring the metrics…_"
                if stale
                else "_Metrics appear once a frame with annotations has detections._"
            )
            self.errors.content = ""
            self._shown = ()
            return
        if (id(metrics), stale) == self._shown:
            return
        self._shown = (id(metrics), stale)
        rows = [
            class_row(name, row)
            for name, row in metrics["per_class"].items()
            if row["num_reference"] or row["num_detections"]
        ]
        # Undefined figures show as a dash, as a class's do: precision without a detection, recall
        # and F without a reference (frames viewed whose labels are all pre-labels, say).
        total_precision = metrics["precision"] if metrics["num_detections"] else None
        self.table.content = "\n".join(
            [
                f"Against the annotations of the {metrics['num_frames']} frame(s) viewed, IoU "
                f"{metrics['iou_threshold']}, "
                + (
                    "each class's own score threshold:"
                    if "class_score_thresholds" in metrics
                    else f"score ≥ {metrics['score_threshold']:.2f}:"
                ),
                "",
                "| class | n | P | R | F | AP |",
                "|---|---|---|---|---|---|",
                *rows,
                f"| **total** | {metrics['num_reference']} | {_fmt(total_precision)} | "
                f"{_fmt(metrics['recall'])} | **{_fmt(metrics['f1'])}** | mAP "
                f"{_fmt(metrics['map'])} |",
                *(["", "_Measuring again after the last change…_"] if stale else []),
            ]
        )
        self.errors.content = errors_markdown(metrics["errors"]) if "errors" in metrics else ""
        if stale:  # the rest is as shown already
            return
        curve = metrics["pr_curves"].get("all")
        if curve and len(curve["recall"]):
            recall = np.concatenate([[0.0], curve["recall"]])
            precision = np.concatenate([[1.0], curve["precision"]])
            self.plot.data = (recall, precision)


def build_metrics_panel(server: viser.ViserServer | viser.ClientHandle, state: AppState) -> MetricsPanel:
    with server.gui.add_folder("Metrics", order=80, expand_by_default=False):
        table = server.gui.add_markdown("")
        errors = server.gui.add_markdown("")
        plot = server.gui.add_uplot(
            data=(np.array([0.0, 1.0]), np.array([1.0, 0.0])),
            series=(
                viser.uplot.Series(label="recall"),
                viser.uplot.Series(label="precision (all classes)", stroke="#1f77b4", width=2),
            ),
            scales={
                "x": viser.uplot.Scale(time=False, auto=False, range=(0.0, 1.0)),
                "y": viser.uplot.Scale(auto=False, range=(0.0, 1.0)),
            },  # fmt: skip
            title="Precision-recall",
            aspect=1.2,
        )
    panel = MetricsPanel(table, plot, errors)
    panel.refresh(state)
    return panel
