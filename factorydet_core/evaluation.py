"""Measuring proposals against reference boxes and instances (truth comes from the caller)."""

from __future__ import annotations

import numpy as np

from .boxes import box_iou_3d
from .proposals import point_sets
from .types import MergedCloud, Proposals, Segmentation


def proposal_point_lists(segmentation: Segmentation, proposals: Proposals) -> list[np.ndarray]:
    """Point indices (into the segmented cloud) of every proposal."""
    return point_sets(segmentation.patch_ids, proposals.patch_sets)


def best_box_iou(reference_boxes: np.ndarray, proposal_boxes: np.ndarray) -> np.ndarray:
    """(R,) the highest 3D IoU of each reference box with any proposal box (0 without proposals)."""
    iou = box_iou_3d(reference_boxes, proposal_boxes)
    return iou.max(axis=1) if iou.shape[1] else np.zeros(len(reference_boxes))


def best_point_iou(cloud: MergedCloud, instance_ids: np.ndarray, point_lists: list[np.ndarray]) -> np.ndarray:
    """(R,) the highest point-set IoU of each instance (its points in ``cloud``, by
    ``cloud.point_instance_ids``) with any proposal's point set: segmentation quality without boxes."""
    best = np.zeros(len(instance_ids))
    if not point_lists:
        return best
    row_of = {int(i): r for r, i in enumerate(instance_ids)}
    sizes = np.array([np.sum(cloud.point_instance_ids == i) for i in instance_ids])
    for points in point_lists:
        ids, counts = np.unique(cloud.point_instance_ids[points], return_counts=True)
        for inst, inter in zip(ids.tolist(), counts.tolist()):
            r = row_of.get(inst)
            if r is not None:
                best[r] = max(best[r], inter / (sizes[r] + len(points) - inter))
    return best


def recall_table(
    class_ids: np.ndarray, hit_mask: np.ndarray, class_names: tuple[str, ...]
) -> dict[str, dict[str, float | int]]:
    """Per-class ``{"num": n, "recall": r}`` and an ``"all"`` row."""
    table: dict[str, dict[str, float | int]] = {}
    for c, name in enumerate(class_names):
        mask = class_ids == c
        if mask.any():
            table[name] = {"num": int(mask.sum()), "recall": round(float(hit_mask[mask].mean()), 3)}
    table["all"] = {
        "num": int(len(hit_mask)),
        "recall": round(float(hit_mask.mean()), 3) if len(hit_mask) else float("nan"),
    }
    return table
