"""Figures of the benchmarks and the report (matplotlib, imported only when drawing)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from factorydet_core.metrics import MISS_KINDS, recorded_false_positive_kinds


def save_figure(fig, png: str | os.PathLike) -> None:
    """Write a matplotlib figure as a PNG (creating its folder) and free it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def plot_voxel_sweep(summary: dict, png: str | os.PathLike) -> None:
    """Recall per class against voxel size, one line per class and a dashed 'all' reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["voxel_segmentation"]
    sizes = [r["voxel_size_m"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    classes = [c for c in rows[0]["recall"] if c != "all"]
    for name in classes:
        label = f"{name} (n={rows[0]['num'][name]})"
        ax.plot(sizes, [r["recall"].get(name, np.nan) for r in rows], marker="o", label=label, alpha=0.8)
    ax.plot(sizes, [r["recall"]["all"] for r in rows], "k-", marker="s", lw=2.5, label="all (voxel segments)")
    ax.axhline(summary["point_segmentation_recall"]["all"], color="k", ls="--", label="all (point segments)")
    ax.set_xlabel("voxel size (m)")
    ax.set_ylabel(f"proposal recall @ IoU {summary['iou_threshold']}")
    ax.set_ylim(0, 1)
    ax.set_title(f"Proposal recall against grid resolution ({summary['data']}, frames {summary['frames']})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    save_figure(fig, png)


def plot_pr_curves(metrics: dict, png: str | os.PathLike, title: str = "") -> None:
    """Precision against recall per class (the paper's Fig. 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    for name, curve in metrics["pr_curves"].items():
        if name == "all":
            continue
        ap = metrics["per_class"][name]["ap"]
        ax.plot(curve["recall"], curve["precision"], label=f"{name} (AP {ap:.2f})", lw=1.8)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(title or f"Precision-recall at IoU {metrics['iou_threshold']}")
    ax.legend(fontsize=8, loc="upper right")
    save_figure(fig, png)


def plot_error_breakdown(errors: dict, png: str | os.PathLike, title: str = "") -> None:
    """Per class, stacked bars of the detections (true positives, then each kind of false
    positive) beside the references (found, then each kind of miss): ``metrics.error_breakdown``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(errors["per_class"])
    positions = np.arange(len(names))
    found = np.array([errors["per_class"][n]["tp"] for n in names], float)
    fig, ax = plt.subplots(figsize=(8.0, 4.8))
    width = 0.38
    fp_kinds = recorded_false_positive_kinds(errors)
    for side, (group, kinds, shades) in enumerate(
        (("false_positives", fp_kinds, plt.cm.Reds), ("misses", MISS_KINDS, plt.cm.Blues))
    ):
        x = positions + (side - 0.5) * width
        ax.bar(x, found, width, color="#4c9a2a", label="true positives" if side == 0 else None)
        bottom = found.copy()
        for k, kind in enumerate(kinds):
            counts = np.array([errors["per_class"][n][group][kind] for n in names], float)
            label = f"{'FP' if group == 'false_positives' else 'miss'}: {kind.replace('_', ' ')}"
            ax.bar(
                x,
                counts,
                width,
                bottom=bottom,
                color=shades(0.35 + 0.5 * k / max(len(kinds) - 1, 1)),
                label=label,
            )
            bottom += counts
    ax.set_xticks(positions, names)
    ax.set_ylabel("count (left bar: detections; right bar: references)")
    ax.set_title(title or f"Errors at the operating point, IoU {errors['iou_threshold']}")
    ax.legend(fontsize=7, ncol=2, loc="upper right")
    ax.grid(axis="y", alpha=0.3)
    save_figure(fig, png)


def plot_sweep(rows: list[dict], png: str | os.PathLike, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [r["voxel_size_m"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name in rows[0]["per_class_f1"]:
        f1 = [np.nan if r["per_class_f1"][name] is None else r["per_class_f1"][name] for r in rows]
        ax.plot(sizes, f1, marker="o", alpha=0.7, label=name)
    ax.plot(sizes, [r["f1"] for r in rows], "k-", marker="s", lw=2.5, label="total")
    ax.set_xlabel("voxel size (m)")
    ax.set_ylabel("detection F-score vs truth")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(fontsize=8, ncol=2)
    save_figure(fig, png)
