"""Made-up training records for tests that need a review queue without training first."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Sequence
from pathlib import Path

from factorydet_core.detection.model import DetectionModel
from factorydet_core.training.mining import TrainingRun


def mined_item(
    frame_index: int, group: int, box, score: float, predicted_class: str = "box", probabilities=None
) -> dict:
    """One mined negative as ``train_with_mining`` records it (the group is also its proposal and
    its one patch)."""
    return {
        "frame_index": frame_index,
        "group": group,
        "proposal": group,
        "box": [float(v) for v in box],
        "patch_set": [group],
        "score": score,
        "predicted_class": predicted_class,
        "probabilities": probabilities,
        "best_annotated_iou": 0.0,
    }


def queue_run(model_path, rounds_mined: Sequence[list[dict]], train_frames=(0,)) -> TrainingRun:
    """A real model with a made-up record: one round per list of mined items."""
    model = DetectionModel.load(model_path)
    record = {"num_positives": 5, "num_background": 9, "fit_seconds": 1.0}
    rounds = [
        {**record, "round": r, "train_metrics": {"f1": 0.1 * (r + 1)}, "mined": mined}
        for r, mined in enumerate(rounds_mined)
    ]
    return TrainingRun(model, rounds, [model] * len(rounds), list(train_frames))


@contextlib.contextmanager
def unwritable(path: Path):
    """``path`` (a file or a folder) made unwritable for this process: read-only mode, and for
    root, who writes anything, the immutable attribute as well (``chattr``); undone on exit."""
    folder = path.is_dir()
    path.chmod(0o555 if folder else 0o444)
    immutable = os.geteuid() == 0
    if immutable:
        subprocess.run(["chattr", "+i", str(path)], check=True)
    try:
        yield
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(path)], check=True)
        path.chmod(0o755 if folder else 0o644)
