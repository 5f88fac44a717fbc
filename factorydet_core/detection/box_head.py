"""A learned second stage: one small network reads each point set's points and returns its class,
its whole-object (amodal) box and the IoU it expects that box to have.

This replaces the paper's classifier plus the enumeration of hand-made box options
(``box_quality``) with one forward pass per point set, the way Frustum PointNets' amodal box
estimation and PointRCNN's second stage do (``shared/notes/box-head.md``).

**Canonical frame.** Each set is read in its own frame, as PointRCNN's second stage reads a
proposal: origin at the centre of its fitted box (the first proposal of the set, an L-shape fit of
its visible points), x along that box's longer side (``heading``), z up. The viewing direction
(azimuth ``phi`` of the centre seen from the vehicle) is an input, so the head knows which side is
hidden.

**Box encoding** (``encode_boxes`` / ``decode_boxes``), per class ``c``:

- centre: the box centre in the canonical frame, metres;
- size: ``log(length / L_c), log(width / W_c), log(height / H_c)`` against the class's size template
  (its median annotated size), with length >= width (the box turned by 90 degrees if needed);
- heading: the yaw relative to the frame's ``heading`` after that turn, folded by the class's
  symmetry ``k`` (2 for a rectangle: yaw and yaw + pi are the same box; 4 for classes whose
  footprint is a square, ``SQUARE_RATIO``: any quarter turn is the same box):
  ``alpha = k * (yaw - heading) mod 2 pi``, split into ``heading_bins`` bins plus a residual within
  the bin (a fraction of the bin in [-0.5, 0.5)).

``BoxHead`` follows scikit-learn: settings in ``__init__``, ``fit`` returns ``self``,
``predict_proba`` gives one column per class of ``labels_`` (background last), so that it can stand
where ``model.DetectionModel`` holds a classifier; ``predict`` also gives the boxes and IoUs.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from factorydet_core.boxes import rectangle_corners, rectangle_intersection_areas
from factorydet_core.detection.checkpoint import (
    MAX_SEED,
    check_class_names,
    check_note_record,
    read_checkpoint_note,
    write_checkpoint,
)
from factorydet_core.detection.classifier import (
    CLASS_WEIGHTS,
    FINE_TUNE_RATE,
    ClassOutputs,
    _torch_threads,
    check_init_model,
    class_weights,
    count_parameters,
)
from factorydet_core.detection.groups import DESCRIPTOR_NAMES, ProposalGroups
from factorydet_core.detection.scoring import check_exponent
from factorydet_core.settings_check import Setting, check_settings
from factorydet_core.types import CLASS_NAMES, Cancelled, Detections, InputError

SQUARE_RATIO = 0.9
"""A class whose template's width is at least this share of its length has a square footprint
(a standing barrel's, a cone's): a quarter turn is the same box (heading symmetry 4)."""

MAX_POINT_LAYERS = 8
MAX_CHANNELS = 2048
"""The per-point MLP of a ``BoxHead`` has at most ``MAX_POINT_LAYERS`` layers of at most this
width, and its MLP after pooling at most ``2 * MAX_CHANNELS`` (``hidden``): about 50M parameters
(0.2 GB) at the bounds with ``MAX_CLASSES`` classes, where the default head has 60k. A checkpoint's
note is checked against them before its network is built."""

SETTINGS: dict[str, Setting] = {
    "hidden": Setting(int, 2, 2 * MAX_CHANNELS),
    "heading_bins": Setting(int, 1, 360),
    "epochs": Setting(int, 1, 1_000_000),
    "batch_size": Setting(int, 2, 2**20),
    "learning_rate": Setting(float, 0.0, 10.0, low_open=True),
    "background_per_positive": Setting(float, 0.0, 1000.0),
    "dropout": Setting(float, 0.0, 1.0),
    "class_weight": Setting(str, optional=True, choices=tuple(w for w in CLASS_WEIGHTS if w)),
    "augment": Setting(bool),
    "square_ratio": Setting(float, 0.0, 1.0, low_open=True),
    "corner_loss": Setting(float, 0.0, 1e6),
    "seed": Setting(int, 0, MAX_SEED),
    "num_threads": Setting(int, 1, 1024, optional=True),
    "max_fit_seconds": Setting(float, 0.0, optional=True, low_open=True),
    "recalibrate_background": Setting(float, 0.0, 1.0, optional=True, low_open=True),
    "recalibrate_by_class": Setting(bool),
}
"""What each setting of ``BoxHead`` may be (checked when it is made, and so in a checkpoint's note
before its network is built); ``channels`` and ``class_names`` are checked apart."""

NUM_GLOBALS = len(DESCRIPTOR_NAMES) + 10
"""Per-set inputs besides the points: the descriptors, the log of the fitted box's length, width
and height, the viewing direction in the frame (cos and sin of ``phi - heading``), cos and sin of
2 and 4 times the frame's heading (so that the head can learn that objects stand along the
vehicle's axes), and the log range."""


def canonical_frame(anchor_boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin (M, 3) and heading (M,) of the canonical frames of (M, 7) anchor boxes: their
    centres, and the direction of their longer side."""
    anchor_boxes = np.asarray(anchor_boxes, np.float64).reshape(-1, 7)
    origin = anchor_boxes[:, :3].copy()
    heading = anchor_boxes[:, 6] + np.where(anchor_boxes[:, 4] > anchor_boxes[:, 3], np.pi / 2, 0.0)
    return origin, heading


def to_canonical(points: np.ndarray, origin: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(M, P, 3) points of M sets in their canonical frames (``origin`` (M, 3), ``heading`` (M,))."""
    shifted = np.asarray(points, np.float64) - origin[:, None, :]
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    x = shifted[..., 0] * c + shifted[..., 1] * s
    y = -shifted[..., 0] * s + shifted[..., 1] * c
    return np.stack([x, y, shifted[..., 2]], axis=-1)


POINT_CHANNELS = 7
"""Per-point inputs: canonical x, y, z in metres; the same over the fitted box's half length,
half width and half height (where each point lies against the box's faces: LiDAR R-CNN's answer
to the size ambiguity of a set of points); and the point's height above the floor (objects stand
on the floor or on each other)."""

_BOTTOM_ABOVE_FLOOR = DESCRIPTOR_NAMES.index("bottom_above_floor_m")


def floor_heights(fitted_boxes: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """(M,) the floor's height under each of M sets, from its fitted box (M, 7) and its
    descriptors (M, len(DESCRIPTOR_NAMES)), which give that box's bottom above the floor."""
    fitted_boxes = np.asarray(fitted_boxes, np.float64).reshape(-1, 7)
    fitted_bottom = np.asarray(descriptors, np.float64).reshape(len(fitted_boxes), -1)[:, _BOTTOM_ABOVE_FLOOR]
    return fitted_boxes[:, 2] - fitted_boxes[:, 5] / 2 - fitted_bottom


def point_inputs(canonical: np.ndarray, anchor_boxes: np.ndarray, floor_z: np.ndarray) -> np.ndarray:
    """(M, P, POINT_CHANNELS) float32 inputs of M sets' (M, P, 3) canonical points in the frames of
    (M, 7) ``anchor_boxes``, over floors at (M,) ``floor_z``."""
    anchor_boxes = np.asarray(anchor_boxes, np.float64).reshape(-1, 7)
    dims = anchor_boxes[:, 3:6]
    half = (
        np.column_stack([np.maximum(dims[:, 0], dims[:, 1]), np.minimum(dims[:, 0], dims[:, 1]), dims[:, 2]])
        / 2
    )
    scaled = canonical / np.maximum(half, 0.05)[:, None, :]
    above_floor = canonical[..., 2] + (anchor_boxes[:, 2] - floor_z)[:, None]
    return np.concatenate([canonical, scaled, above_floor[..., None]], axis=2).astype(np.float32)


def symmetry_orders(templates: np.ndarray, square_ratio: float = SQUARE_RATIO) -> np.ndarray:
    """(C,) the heading symmetry of each class of (C, 3) (length, width, height) templates: 4 for
    square footprints (``SQUARE_RATIO``), 2 for the others."""
    templates = np.asarray(templates, np.float64).reshape(-1, 3)
    return np.where(templates[:, 1] >= square_ratio * templates[:, 0], 4, 2).astype(np.int64)


@dataclasses.dataclass(frozen=True)
class BoxTargets:
    """Encoded boxes (``encode_boxes``)."""

    centre: np.ndarray
    """(M, 3) box centre in the canonical frame, metres."""
    log_size: np.ndarray
    """(M, 3) log of (length, width, height) over the class template."""
    heading_bin: np.ndarray
    """(M,) int64 bin of the folded heading."""
    heading_residual: np.ndarray
    """(M,) position within the bin, in [-0.5, 0.5)."""


def encode_boxes(
    boxes: np.ndarray,
    origin: np.ndarray,
    heading: np.ndarray,
    class_ids: np.ndarray,
    templates: np.ndarray,
    symmetry: np.ndarray,
    heading_bins: int,
) -> BoxTargets:
    """Encode (M, 7) boxes of classes ``class_ids`` in the canonical frames (``origin``, ``heading``)
    against the (C, 3) size ``templates`` and the (C,) ``symmetry`` orders."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    class_ids = np.asarray(class_ids, np.int64)
    dx, dy, yaw = boxes[:, 3].copy(), boxes[:, 4].copy(), boxes[:, 6].copy()
    turn = dx < dy
    dx[turn], dy[turn] = boxes[turn, 4], boxes[turn, 3]
    yaw[turn] += np.pi / 2
    shifted = boxes[:, :2] - origin[:, :2]
    c, s = np.cos(heading), np.sin(heading)
    centre = np.column_stack(
        [
            shifted[:, 0] * c + shifted[:, 1] * s,
            -shifted[:, 0] * s + shifted[:, 1] * c,
            boxes[:, 2] - origin[:, 2],
        ]
    )
    size = np.column_stack([dx, dy, boxes[:, 5]])
    log_size = np.log(np.maximum(size, 1e-3) / templates[class_ids])
    alpha = np.mod(symmetry[class_ids] * (yaw - heading), 2 * np.pi)
    width = 2 * np.pi / heading_bins
    position = alpha / width
    heading_bin = np.minimum(np.floor(position).astype(np.int64), heading_bins - 1)
    return BoxTargets(centre, log_size, heading_bin, position - heading_bin - 0.5)


def decode_boxes(
    targets: BoxTargets,
    origin: np.ndarray,
    heading: np.ndarray,
    class_ids: np.ndarray,
    templates: np.ndarray,
    symmetry: np.ndarray,
    heading_bins: int,
) -> np.ndarray:
    """(M, 7) boxes from their encoding (``encode_boxes``' inverse, up to the box's symmetry:
    length along the heading, yaw in (-pi, pi])."""
    class_ids = np.asarray(class_ids, np.int64)
    width = 2 * np.pi / heading_bins
    alpha = (targets.heading_bin + 0.5 + targets.heading_residual) * width
    yaw = alpha / symmetry[class_ids] + heading
    yaw = np.mod(yaw + np.pi, 2 * np.pi) - np.pi
    c, s = np.cos(heading), np.sin(heading)
    x, y = targets.centre[:, 0], targets.centre[:, 1]
    size = templates[class_ids] * np.exp(targets.log_size)
    return np.column_stack(
        [
            origin[:, 0] + x * c - y * s,
            origin[:, 1] + x * s + y * c,
            origin[:, 2] + targets.centre[:, 2],
            size,
            yaw,
        ]
    )


def paired_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """(M,) 3D IoU of each box of (M, 7) ``boxes_a`` with the same row of ``boxes_b``."""
    boxes_a = np.asarray(boxes_a, np.float64).reshape(-1, 7)
    boxes_b = np.asarray(boxes_b, np.float64).reshape(-1, 7)
    if not len(boxes_a):
        return np.zeros(0)
    area = rectangle_intersection_areas(rectangle_corners(boxes_a), rectangle_corners(boxes_b))
    z_overlap = np.clip(
        np.minimum(boxes_a[:, 2] + boxes_a[:, 5] / 2, boxes_b[:, 2] + boxes_b[:, 5] / 2)
        - np.maximum(boxes_a[:, 2] - boxes_a[:, 5] / 2, boxes_b[:, 2] - boxes_b[:, 5] / 2),
        0.0,
        None,
    )
    intersection = area * z_overlap
    union = np.prod(boxes_a[:, 3:6], axis=1) + np.prod(boxes_b[:, 3:6], axis=1) - intersection
    return np.clip(np.where(union > 0, intersection / np.where(union > 0, union, 1.0), 0.0), 0.0, 1.0)


def global_inputs(anchor_boxes: np.ndarray, descriptors: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(M, NUM_GLOBALS) float32 per-set inputs of the head (``NUM_GLOBALS``)."""
    anchor_boxes = np.asarray(anchor_boxes, np.float64).reshape(-1, 7)
    phi = np.arctan2(anchor_boxes[:, 1], anchor_boxes[:, 0])
    dims = anchor_boxes[:, 3:6]
    length, width = np.maximum(dims[:, 0], dims[:, 1]), np.minimum(dims[:, 0], dims[:, 1])
    return np.column_stack(
        [
            np.asarray(descriptors, np.float64).reshape(len(anchor_boxes), -1),
            np.log(np.maximum(np.column_stack([length, width, dims[:, 2]]), 1e-2)),
            np.cos(phi - heading),
            np.sin(phi - heading),
            np.cos(2 * heading),
            np.sin(2 * heading),
            np.cos(4 * heading),
            np.sin(4 * heading),
            np.log(np.maximum(np.hypot(anchor_boxes[:, 0], anchor_boxes[:, 1]), 0.1)),
        ]
    ).astype(np.float32)


def _box_corners(centre: torch.Tensor, size: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """(B, 8, 3) corners of B boxes (centre (B, 3), size (B, 3), yaw (B,)) in a torch graph."""
    signs = torch.tensor(
        [[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (-0.5, 0.5)], dtype=size.dtype
    )
    local = signs[None] * size[:, None, :]
    c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    return torch.stack([x, y, local[..., 2]], dim=-1) + centre[:, None, :]


def _corner_loss(
    centre: torch.Tensor,
    log_size: torch.Tensor,
    residual: torch.Tensor,
    targets: BoxTargets,
    templates: torch.Tensor,
    symmetry: torch.Tensor,
    heading_bins: int,
) -> torch.Tensor:
    """Frustum PointNets' corner loss in the canonical frame: the mean distance of the predicted
    box's 8 corners to the target's, the predicted heading taken in the target's bin, the least
    over the target's equivalent turns (its symmetry), so that centre, size and heading are
    learnt together for the IoU they make."""
    width = 2 * np.pi / heading_bins
    bins = torch.from_numpy(targets.heading_bin).to(centre.dtype)
    order = symmetry.to(centre.dtype)
    predicted = _box_corners(centre, templates * torch.exp(log_size), (bins + 0.5 + residual) * width / order)
    target_size = templates * torch.exp(torch.from_numpy(targets.log_size.astype(np.float32)))
    target_yaw = (bins + 0.5 + torch.from_numpy(targets.heading_residual.astype(np.float32))) * width / order
    target_centre = torch.from_numpy(targets.centre.astype(np.float32))
    distances = []
    for turn in range(4):  # turns of 2 pi / symmetry (a rectangle's repeat: harmless in the min)
        turned = target_yaw + turn * (2 * np.pi / order)
        corners = _box_corners(target_centre, target_size, turned)
        distances.append(torch.linalg.vector_norm(predicted - corners, dim=2).mean(dim=1))
    return torch.stack(distances, dim=1).min(dim=1).values.mean()


class PointSetNet(nn.Module):
    """A PointNet on a set's canonical points (shared per-point MLP, max pooling) joined with the
    set's global inputs, then one MLP with every output: class logits (C + 1), centre (3), size
    residuals (C x 3), heading bin logits and residuals (2 x bins), and IoU logits (C)."""

    def __init__(
        self,
        num_classes: int,
        channels: tuple[int, ...],
        hidden: int,
        heading_bins: int,
        dropout: float,
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = POINT_CHANNELS
        for out in channels:
            layers += [nn.Conv1d(width, out, 1), nn.BatchNorm1d(out), nn.ReLU()]
            width = out
        self.point_mlp = nn.Sequential(*layers)
        self.register_buffer("global_mean", torch.zeros(NUM_GLOBALS))
        self.register_buffer("global_scale", torch.ones(NUM_GLOBALS))
        self.trunk = nn.Sequential(
            nn.Linear(width + NUM_GLOBALS, hidden),
            nn.BatchNorm1d(hidden),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(hidden, hidden // 2),
            nn.BatchNorm1d(hidden // 2),
            nn.ReLU(),
        )
        self.num_classes = num_classes
        self.heading_bins = heading_bins
        sizes = [num_classes + 1, 3, 3 * num_classes, heading_bins, heading_bins, num_classes]
        self.splits = sizes
        self.out = nn.Linear(hidden // 2, sum(sizes))

    def forward(self, points: torch.Tensor, globals_: torch.Tensor) -> dict[str, torch.Tensor]:
        """``points`` (B, P, POINT_CHANNELS) (``point_inputs``), ``globals_`` (B, NUM_GLOBALS) raw."""
        pooled = self.point_mlp(points.transpose(1, 2)).max(dim=2).values
        g = (globals_ - self.global_mean) / self.global_scale
        raw = self.out(self.trunk(torch.cat([pooled, g], dim=1)))
        logits, centre, size, bins, residuals, iou = torch.split(raw, self.splits, dim=1)
        return {
            "logits": logits,
            "centre": centre,
            "log_size": size.reshape(-1, self.num_classes, 3),
            "heading_logits": bins,
            "heading_residual": residuals,
            "iou_logits": iou,
        }


@dataclasses.dataclass(frozen=True)
class HeadSamples:
    """Training examples of the box head: point sets with their class and, for objects, the box."""

    points: np.ndarray
    """(M, P, 3) float32 sampled points in the vehicle frame."""
    anchor_boxes: np.ndarray
    """(M, 7) each set's fitted box (its canonical frame)."""
    descriptors: np.ndarray
    """(M, len(DESCRIPTOR_NAMES)) float32."""
    labels: np.ndarray
    """(M,) int64 class ids, ``num_classes`` for background."""
    target_boxes: np.ndarray
    """(M, 7) the object's box for objects; NaN rows for background, and for an object whose
    label teaches its class alone (its box is the model's own, accepted as it was)."""

    def __post_init__(self) -> None:
        num = len(self.labels)
        for name, shape in (
            ("points", (num, None, 3)),
            ("anchor_boxes", (num, 7)),
            ("descriptors", (num, len(DESCRIPTOR_NAMES))),
            ("target_boxes", (num, 7)),
        ):
            value = np.asarray(getattr(self, name))
            if value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
                raise InputError(f"head samples: {name} must have shape {shape}, got {value.shape}")

    @property
    def num_samples(self) -> int:
        return len(self.labels)

    @classmethod
    def concatenate(cls, parts: list[HeadSamples]) -> HeadSamples:
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(cls)))


@dataclasses.dataclass(frozen=True)
class HeadOutput:
    """What ``BoxHead.predict`` returns for M point sets."""

    probabilities: np.ndarray
    """(M, C + 1) float32 class probabilities, background last."""
    boxes: np.ndarray
    """(M, C, 7) float64: the box of each set as each object class."""
    iou: np.ndarray
    """(M, C) float32: the IoU the head expects of each of those boxes."""


def _augment(
    rng: np.random.Generator,
    points: np.ndarray,
    anchors: np.ndarray,
    targets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Randomly turned, mirrored, scaled, jittered, thinned and cut copies of a batch (the
    vehicle frame): turns by quarter turns plus a few degrees about the vehicle's z axis and
    mirroring keep the view geometry; the cut drops the far side of some sets (a shorter view)."""
    num, count, _ = points.shape
    points, anchors, targets = points.astype(np.float64), anchors.copy(), targets.copy()
    angle = rng.integers(0, 4, num) * (np.pi / 2) + rng.normal(0.0, np.radians(3.0), num)
    mirror = rng.uniform(size=num) < 0.5
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]

    def move(xy: np.ndarray) -> np.ndarray:  # (num, K, 2)
        x, y = xy[..., 0], np.where(mirror[:, None], -xy[..., 1], xy[..., 1])
        return np.stack([x * c - y * s, x * s + y * c], axis=-1)

    def move_yaw(yaw: np.ndarray) -> np.ndarray:
        return np.where(mirror, -yaw, yaw) + angle

    points[..., :2] = move(points[..., :2])
    anchors[:, :2] = move(anchors[:, None, :2])[:, 0]
    anchors[:, 6] = move_yaw(anchors[:, 6])
    has_target = np.isfinite(targets[:, 0])
    moved = move(np.nan_to_num(targets[:, None, :2]))[:, 0]
    targets[has_target, :2] = moved[has_target]
    targets[:, 6] = move_yaw(targets[:, 6])
    # Scale about the set's anchor box centre.
    scale = rng.uniform(0.95, 1.05, num)
    pivot = anchors[:, :3]
    points = pivot[:, None] + (points - pivot[:, None]) * scale[:, None, None]
    targets[:, :3] = pivot + (targets[:, :3] - pivot) * scale[:, None]
    targets[:, 3:6] *= scale[:, None]
    anchors[:, 3:6] *= scale[:, None]
    points += rng.normal(0.0, 0.01, points.shape)
    # Thinning and cutting: resample each set from a random subset of its points.
    sight = anchors[:, :2] / np.maximum(np.linalg.norm(anchors[:, :2], axis=1), 1e-6)[:, None]
    depth = ((points[..., :2] - anchors[:, None, :2]) * sight[:, None]).sum(axis=-1)
    keep = rng.uniform(size=(num, count)) < rng.uniform(0.5, 1.0, (num, 1))
    cut = rng.uniform(size=num) < 0.25
    quantile = (rng.uniform(0.5, 0.9, num) * (count - 1)).astype(np.int64)
    limit = np.sort(depth, axis=1)[np.arange(num), quantile][:, None]
    keep &= ~cut[:, None] | (depth <= limit)
    keep[keep.sum(axis=1) < 8] = True
    # Kept points first (in random order), then draw each row's samples among its kept ones.
    order = np.argsort(~keep + rng.uniform(0.0, 0.5, (num, count)), axis=1)
    picks = (rng.uniform(size=(num, count)) * keep.sum(axis=1)[:, None]).astype(np.int64)
    out = np.take_along_axis(points, np.take_along_axis(order, picks, axis=1)[..., None], axis=1)
    return out.astype(np.float32), anchors, targets


@dataclasses.dataclass
class BoxHead(ClassOutputs):
    """The learned box head (module docstring).

    Args:
        channels: widths of the per-point MLP.
        hidden: width of the MLP after pooling.
        heading_bins: bins of the folded heading.
        epochs: passes over the positives (each epoch also draws ``background_per_positive``
            background sets per positive, afresh).
        batch_size: sets per step.
        learning_rate: Adam's initial rate; cosine-annealed to 1% over the epochs.
        background_per_positive: background sets drawn per positive each epoch.
        dropout: of the MLP after pooling.
        class_weight: cross-entropy weights (``classifier.class_weights``: None, "balanced",
            "sqrt").
        augment: augment the training sets (``_augment``).
        class_names: the object classes; ``labels_`` appends "background".
        square_ratio: classes whose template is at least this square have heading symmetry 4
            (``SQUARE_RATIO``).
        seed: seeds weights, batches and augmentation.
        num_threads: torch threads while fitting and predicting (``None``: torch's default).
        max_fit_seconds: stop after the step during which this much time has passed.
        corner_loss: weight of Frustum PointNets' corner loss (``_corner_loss``) beside the
            separate centre, size and heading losses (0: off). 3 measured ahead of 0, 1 and 10 in
            the share of held-out objects some candidate boxes at IoU 0.6 (one training seed, three
            held-out factories, 8 epochs; the issue's notes give the figures).
        recalibrate_background: background recalibration: a background set drawn at random (not
            a hard negative) to which the network, as it trains, gives an object probability of
            at least this is left out of the batch's classification and IoU losses (``None``:
            off). On a partially annotated data set those are the likeliest unlabelled objects,
            which the plain loss teaches to be background. Only in a fit that goes on from a
            fitted head (mining rounds, next rounds): a network in its first epochs gives most
            sets a high object probability, and leaving them out would teach it no background at
            all. The probability is the training step's own (dropout and augmentation on), so a
            set near the threshold is left out in some steps and not others; the IoU loss keeps
            its per-set scale (its sum over the kept sets over the batch's size).
            ``history_`` counts the sets left out per epoch.
        recalibrate_by_class: with ``recalibrate_background``, a drawn set is left out only when
            its likeliest object class's probability also reaches the median that class's labelled
            sets get (their own class's probability, in the fit's previous epoch; in its first, in
            its steps so far; a class none of whose sets has been seen yet leaves nothing out). The
            network's probabilities differ in scale between classes, so one threshold leaves out
            background that looks like a high-scoring class far more often than an unlabelled
            object of it would be; this asks a set to look like a typical labelled object of its
            class. Never leaves out more than ``recalibrate_background`` alone.
    """

    channels: tuple[int, ...] = (32, 64, 128)
    hidden: int = 128
    heading_bins: int = 12
    epochs: int = 20
    batch_size: int = 256
    learning_rate: float = 2e-3
    background_per_positive: float = 3.0
    dropout: float = 0.2
    class_weight: str | None = "sqrt"
    augment: bool = True
    class_names: tuple[str, ...] = CLASS_NAMES
    square_ratio: float = SQUARE_RATIO
    corner_loss: float = 3.0
    seed: int = 0
    num_threads: int | None = None
    max_fit_seconds: float | None = None
    recalibrate_background: float | None = None
    recalibrate_by_class: bool = False

    input_kind = "points"
    ARCHITECTURE: ClassVar[tuple[str, ...]] = ("channels", "hidden", "heading_bins")
    """The settings that shape the network's weights: a fit goes on only from a head that shares
    them (``classifier.check_init_model``)."""

    def __post_init__(self) -> None:
        checked = check_settings(self.get_params(), SETTINGS)
        if isinstance(self.channels, (str, bytes)) or not isinstance(self.channels, (list, tuple)):
            raise InputError(f"channels must be a list of widths, got {self.channels!r}"[:200])
        if not 1 <= len(self.channels) <= MAX_POINT_LAYERS:
            raise InputError(f"channels must hold 1 to {MAX_POINT_LAYERS} widths, got {len(self.channels)}")
        channel = Setting(int, 1, MAX_CHANNELS)
        checked["channels"] = tuple(channel.check("channels", c) for c in self.channels)
        checked["class_names"] = check_class_names(self.class_names)
        for name, value in checked.items():
            setattr(self, name, value)

    def _new_network(self) -> PointSetNet:
        return PointSetNet(len(self.class_names), self.channels, self.hidden, self.heading_bins, self.dropout)

    def _inputs(
        self, points: np.ndarray, anchor_boxes: np.ndarray, descriptors: np.ndarray, floor_z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Point inputs (M, P, POINT_CHANNELS), globals, and the frames' origin and heading."""
        origin, heading = canonical_frame(anchor_boxes)
        canonical = point_inputs(to_canonical(points, origin, heading), anchor_boxes, floor_z)
        return canonical, global_inputs(anchor_boxes, descriptors, heading), origin, heading

    def fit(
        self,
        samples: HeadSamples,
        templates: np.ndarray,
        hard_mask: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        init_model: BoxHead | None = None,
    ) -> BoxHead:
        """Train from scratch on ``samples`` with the (C, 3) size ``templates`` (each class's
        median (length, width, height); NaN rows for classes never seen are set to 1 m), or go on
        training ``init_model`` (a fitted head of the same classes and network; it is not changed):
        its weights and input normalisation are the start, and the ``epochs`` run at
        ``classifier.FINE_TUNE_RATE`` times the learning rate. Hard-negative mining rounds after
        the first go on from the previous round's head this way.

        Every epoch sees every object set, every background set of ``hard_mask`` (M,) (hard
        negatives: mined or confirmed by a reviewer) and a fresh random draw of the other
        background sets (``background_per_positive`` per object set).

        Returns:
            self, with ``network_``, ``templates_``, ``history_`` and ``fit_seconds_``.
        """
        num_classes = len(self.class_names)
        labels = np.asarray(samples.labels, np.int64)
        if not len(labels) or labels.min() < 0 or labels.max() > num_classes:
            raise InputError(f"head samples: labels must lie in [0, {num_classes}]")
        positives = np.flatnonzero(labels < num_classes)
        hard = np.zeros(len(labels), bool) if hard_mask is None else np.asarray(hard_mask, bool)
        if hard.shape != labels.shape:
            raise InputError(f"hard_mask: expected shape {labels.shape}, got {hard.shape}")
        hard_background = np.flatnonzero(hard & (labels == num_classes))
        background = np.flatnonzero(~hard & (labels == num_classes))
        if not len(positives):
            raise InputError("the box head needs at least one object among its training sets")
        target_rows = np.isfinite(samples.target_boxes[positives])
        if not (target_rows.all(axis=1) | ~target_rows.any(axis=1)).all():
            raise InputError("head samples: an object's target box is finite, or all NaN (no box to learn)")
        templates = np.asarray(templates, np.float64).reshape(num_classes, 3)
        templates = np.where(np.isfinite(templates) & (templates > 0), templates, 1.0)
        symmetry = symmetry_orders(templates, self.square_ratio)
        learning_rate = self.learning_rate
        if init_model is not None:
            check_init_model(self, init_model)
            learning_rate *= FINE_TUNE_RATE
        start = time.perf_counter()
        rng = np.random.default_rng(self.seed)
        with _torch_threads(self.num_threads):
            torch.manual_seed(self.seed)
            network = self._new_network()
            if init_model is not None:
                network.load_state_dict(init_model.network_.state_dict())
            else:
                _, fitted_heading = canonical_frame(samples.anchor_boxes)
                globals_all = global_inputs(samples.anchor_boxes, samples.descriptors, fitted_heading)
                network.global_mean.copy_(torch.from_numpy(globals_all.mean(axis=0)))
                network.global_scale.copy_(torch.from_numpy(globals_all.std(axis=0)).clamp_min(1e-3))
            counts = np.bincount(labels, minlength=num_classes + 1).astype(np.float64)
            counts[-1] = min(counts[-1], len(positives) * self.background_per_positive + hard.sum())
            loss_fn = nn.CrossEntropyLoss(weight=class_weights(counts, self.class_weight))
            optimizer = torch.optim.AdamW(network.parameters(), lr=learning_rate, weight_decay=1e-4)
            drawn_per_epoch = min(len(background), int(len(positives) * self.background_per_positive))
            per_epoch = len(positives) + len(hard_background) + drawn_per_epoch
            # At least two warm-up steps and one after: torch's one-cycle schedule divides by
            # zero when a phase is a single step (a short fine-tune of a few batches).
            total_steps = max(3, self.epochs * max(1, -(-per_epoch // self.batch_size)))
            scheduler = torch.optim.lr_scheduler.OneCycleLR(
                optimizer, learning_rate, total_steps=total_steps, pct_start=max(0.1, 2.0 / total_steps)
            )
            history, step = [], 0
            out_of_time = False
            # (a network trained from scratch: its probabilities say little until it has learned)
            recalibrate = self.recalibrate_background if init_model is not None else None
            by_class = recalibrate is not None and self.recalibrate_by_class
            this_own: list[list[float]] = [[] for _ in range(num_classes)]
            previous_own: list[list[float]] | None = None
            for epoch in range(self.epochs):
                network.train()
                drawn = rng.choice(background, drawn_per_epoch, replace=False)
                order = rng.permutation(np.concatenate([positives, hard_background, drawn]))
                sums = {"loss": 0.0, "class": 0.0, "box": 0.0, "iou": 0.0, "correct": 0.0}
                seen, recalibrated = 0, 0
                if by_class:
                    # Each class's bar: the median own-class probability of its labelled sets in
                    # the previous epoch, else in this one's steps so far (``_class_bars``).
                    previous_own = this_own if epoch else None
                    this_own = [[] for _ in range(num_classes)]
                for lo in range(0, len(order), self.batch_size):
                    if should_stop is not None and should_stop():
                        raise Cancelled("training cancelled")
                    if (
                        self.max_fit_seconds is not None
                        and time.perf_counter() - start > self.max_fit_seconds
                    ):
                        out_of_time = True
                        break
                    batch = np.sort(order[lo : lo + self.batch_size])
                    if len(batch) < 2 or step >= total_steps:
                        continue
                    bars = _class_bars(previous_own or this_own) if by_class else None
                    losses = self._step(
                        network, samples, batch, templates, symmetry, loss_fn, rng,
                        recalibrate=recalibrate, drawn=~hard[batch], class_bars=bars,
                    )  # fmt: skip
                    recalibrated += int(losses.pop("recalibrated"))
                    own_probability = losses.pop("own_probability")
                    if by_class:
                        rows, own = own_probability
                        for c, p in zip(samples.labels[batch][rows], own):
                            this_own[int(c)].append(float(p))
                    optimizer.zero_grad()
                    losses["loss"].backward()
                    optimizer.step()
                    scheduler.step()
                    step += 1
                    seen += len(batch)
                    for key in sums:
                        sums[key] += float(losses[key].detach()) * len(batch)
                record = {"epoch": epoch + 1, **{k: round(v / max(seen, 1), 4) for k, v in sums.items()}}
                record["train_accuracy"] = record.pop("correct")
                if self.recalibrate_background is not None:
                    record["recalibrated"] = recalibrated
                history.append(record)
                if progress is not None:
                    progress(epoch + 1, self.epochs)
                if out_of_time:
                    break
        network.eval()
        self.network_ = network
        self.templates_ = templates
        self.symmetry_ = symmetry
        self.history_ = history
        self.fit_seconds_ = time.perf_counter() - start
        self.num_parameters_ = count_parameters(network)
        self.train_counts_ = {
            name: int(c) for name, c in zip(self.labels_, np.bincount(labels, minlength=num_classes + 1))
        }
        return self

    def _step(
        self,
        network: PointSetNet,
        samples: HeadSamples,
        batch: np.ndarray,
        templates: np.ndarray,
        symmetry: np.ndarray,
        loss_fn: nn.Module,
        rng: np.random.Generator,
        recalibrate: float | None = None,
        drawn: np.ndarray | None = None,
        class_bars: np.ndarray | None = None,
    ) -> dict[str, torch.Tensor]:
        """The losses of one batch: classification, box (centre, size, heading) and IoU; with
        ``recalibrate``, the background sets of ``drawn`` (B,) (drawn at random, not hard
        negatives) the network gives an object probability of at least that are left out of the
        classification and IoU losses (``recalibrated``: how many; ``drawn`` None: all are), and
        with ``class_bars`` (C,) only those whose likeliest object class's probability reaches its
        bar too (``recalibrate_by_class``). ``own_probability``: the batch's P object sets (their
        rows, (P,)) and each one's probability of its own class (P,)."""
        num_classes = len(self.class_names)
        points = samples.points[batch]
        anchors = np.asarray(samples.anchor_boxes[batch], np.float64)
        targets = np.asarray(samples.target_boxes[batch], np.float64)
        labels = samples.labels[batch]
        if self.augment:
            points, anchors, targets = _augment(rng, points, anchors, targets)
        floor_z = floor_heights(anchors, samples.descriptors[batch])
        canonical, globals_, origin, heading = self._inputs(
            points, anchors, samples.descriptors[batch], floor_z
        )
        out = network(torch.from_numpy(canonical), torch.from_numpy(globals_))
        y = torch.from_numpy(labels)
        is_object = labels < num_classes
        keep = np.ones(len(batch), bool)
        with torch.no_grad():
            probabilities = torch.softmax(out["logits"], dim=1).numpy()
        object_rows = np.flatnonzero(is_object)
        own_probability = (object_rows, probabilities[object_rows, labels[object_rows]])
        if recalibrate is not None:
            drawn = np.ones(len(batch), bool) if drawn is None else np.asarray(drawn, bool)
            object_probability = 1.0 - probabilities[:, num_classes]
            leave_out = ~is_object & drawn & (object_probability >= recalibrate)
            if class_bars is not None:
                likeliest = probabilities[:, :num_classes].argmax(axis=1)
                leave_out &= probabilities[np.arange(len(batch)), likeliest] >= class_bars[likeliest]
            keep = ~leave_out
        if keep.all():
            class_loss = loss_fn(out["logits"], y)
        else:
            # The weighted mean of the kept sets' losses, as CrossEntropyLoss's own mean weighs them.
            kept = torch.from_numpy(keep.astype(np.float32))
            per_set = nn.functional.cross_entropy(out["logits"], y, weight=loss_fn.weight, reduction="none")
            set_weights = (torch.ones(len(batch)) if loss_fn.weight is None else loss_fn.weight[y]) * kept
            class_loss = (per_set * kept).sum() / set_weights.sum().clamp_min(1e-12)
        # An object set whose label box is not to be learnt from (NaN target: a box a person
        # accepted from the model as it was) teaches its class alone: no box or IoU loss.
        rows = np.flatnonzero(is_object & np.isfinite(targets).all(axis=1))
        iou_target = np.zeros((len(batch), num_classes), np.float32)
        box_loss = torch.zeros(())
        if len(rows):
            own = labels[rows]
            encoded = encode_boxes(
                targets[rows], origin[rows], heading[rows], own, templates, symmetry, self.heading_bins
            )
            r = torch.from_numpy(rows)
            own_t = torch.from_numpy(own)
            centre_loss = nn.functional.smooth_l1_loss(
                out["centre"][r], torch.from_numpy(encoded.centre.astype(np.float32)), beta=0.05
            )
            size_pred = out["log_size"][r, own_t]
            size_loss = nn.functional.smooth_l1_loss(
                size_pred, torch.from_numpy(encoded.log_size.astype(np.float32)), beta=0.05
            )
            bin_t = torch.from_numpy(encoded.heading_bin)
            bin_loss = nn.functional.cross_entropy(out["heading_logits"][r], bin_t)
            residual_pred = out["heading_residual"][r].gather(1, bin_t[:, None])[:, 0]
            residual_loss = nn.functional.smooth_l1_loss(
                residual_pred, torch.from_numpy(encoded.heading_residual.astype(np.float32)), beta=0.05
            )
            box_loss = centre_loss + size_loss + 0.5 * bin_loss + residual_loss
            if self.corner_loss:
                box_loss = box_loss + self.corner_loss * _corner_loss(
                    out["centre"][r],
                    size_pred,
                    residual_pred,
                    encoded,
                    torch.from_numpy(templates[own].astype(np.float32)),
                    torch.from_numpy(symmetry[own]),
                    self.heading_bins,
                )
            with torch.no_grad():
                decoded = self._decode(
                    {k: v[r] for k, v in out.items()}, origin[rows], heading[rows], own, templates, symmetry
                )
            iou_target[rows, own] = paired_iou(decoded, targets[rows])
        # The IoU of an object set is learnt for its own class; a background set's is 0 for all.
        weight = np.zeros((len(batch), num_classes), np.float32)
        weight[rows, labels[rows]] = 1.0
        weight[~is_object] = 1.0 / num_classes
        weight[~keep] = 0.0
        iou_loss = (
            nn.functional.binary_cross_entropy_with_logits(
                out["iou_logits"], torch.from_numpy(iou_target), reduction="none"
            )
            * torch.from_numpy(weight)
        ).sum() / float(len(batch))
        loss = class_loss + box_loss + iou_loss
        correct = (out["logits"].argmax(1) == y).float().mean()
        return {
            "loss": loss,
            "class": class_loss,
            "box": box_loss,
            "iou": iou_loss,
            "correct": correct,
            "recalibrated": int((~keep).sum()),
            "own_probability": own_probability,
        }

    def _decode(
        self,
        out: dict[str, torch.Tensor],
        origin: np.ndarray,
        heading: np.ndarray,
        class_ids: np.ndarray,
        templates: np.ndarray,
        symmetry: np.ndarray,
    ) -> np.ndarray:
        """(M, 7) boxes of the network's outputs for M sets as ``class_ids``."""
        rows = np.arange(len(class_ids))
        bins = out["heading_logits"].argmax(1).numpy()
        residual = out["heading_residual"].numpy()[rows, bins]
        encoded = BoxTargets(
            out["centre"].numpy().astype(np.float64),
            out["log_size"].numpy()[rows, class_ids].astype(np.float64),
            bins,
            np.clip(residual, -0.5, 0.5).astype(np.float64),
        )
        return decode_boxes(encoded, origin, heading, class_ids, templates, symmetry, self.heading_bins)

    def predict(
        self,
        points: np.ndarray,
        anchor_boxes: np.ndarray,
        descriptors: np.ndarray,
        batch_size: int = 1024,
    ) -> HeadOutput:
        """Classes, boxes and IoUs of M point sets.

        Args:
            points: (M, P, 3) sampled points in the vehicle frame.
            anchor_boxes: (M, 7) each set's fitted box.
            descriptors: (M, len(DESCRIPTOR_NAMES)) geometric descriptors.
        """
        if not hasattr(self, "network_"):
            raise InputError("the box head is not fitted; call fit or load a checkpoint")
        points = np.asarray(points, np.float32)
        num = len(points)
        num_classes = len(self.class_names)
        if points.ndim != 3 or points.shape[2] != 3:
            raise InputError(f"points: expected shape (M, P, 3), got {points.shape}")
        if not np.isfinite(points).all():
            raise InputError("points hold NaN or Inf values")
        probabilities = np.zeros((num, num_classes + 1), np.float32)
        boxes = np.zeros((num, num_classes, 7))
        iou = np.zeros((num, num_classes), np.float32)
        anchor_boxes = np.asarray(anchor_boxes, np.float64).reshape(num, 7)
        descriptors = np.asarray(descriptors, np.float32).reshape(num, len(DESCRIPTOR_NAMES))
        floor_z = floor_heights(anchor_boxes, descriptors)
        with _torch_threads(self.num_threads), torch.inference_mode():
            self.network_.eval()
            for lo in range(0, num, batch_size):
                part = slice(lo, lo + batch_size)
                probabilities[part], boxes[part], iou[part] = self._forward(
                    points[part], anchor_boxes[part], descriptors[part], floor_z[part]
                )
        return HeadOutput(probabilities, boxes, iou)

    def _forward(
        self, points: np.ndarray, anchor_boxes: np.ndarray, descriptors: np.ndarray, floor_z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pass over M sets: probabilities (M, C + 1), boxes (M, C, 7) as each class, IoUs (M, C)."""
        canonical, globals_, origin, heading = self._inputs(points, anchor_boxes, descriptors, floor_z)
        out = self.network_(torch.from_numpy(canonical), torch.from_numpy(globals_))
        count = len(canonical)
        decoded = np.stack(
            [
                self._decode(out, origin, heading, np.full(count, c), self.templates_, self.symmetry_)
                for c in range(len(self.class_names))
            ],
            axis=1,
        )
        return (
            torch.softmax(out["logits"], dim=1).numpy(),
            decoded,
            torch.sigmoid(out["iou_logits"]).numpy(),
        )

    def predict_proba(self, points, anchor_boxes, descriptors) -> np.ndarray:
        """(M, C + 1) class probabilities (``predict``)."""
        return self.predict(points, anchor_boxes, descriptors).probabilities

    def save(
        self,
        path: str | os.PathLike,
        note: dict | None = None,
        companions: Mapping[str, str | os.PathLike] | None = None,
    ) -> Path:
        """Write the state dict to ``path`` (.pt) and a JSON note beside it (``path`` with .json):
        the settings, labels, size templates, parameter count, history and ``note``. The note
        records the files' sizes and hashes, with those of ``companions`` (``write_checkpoint``)."""
        if not hasattr(self, "network_"):
            raise InputError("the box head is not fitted; nothing to save")
        params = self.get_params()
        meta = {
            "format": "factorydet-box-head/1",
            "params": {
                **params,
                "channels": list(self.channels),
                "class_names": list(self.class_names),
            },
            "labels": list(self.labels_),
            "templates": self.templates_.tolist(),
            "symmetry": self.symmetry_.tolist(),
            "num_parameters": self.num_parameters_,
            "train_counts": self.train_counts_,
            "fit_seconds": round(self.fit_seconds_, 2),
            "history": self.history_,
            **(note or {}),
        }
        return write_checkpoint(self.network_, path, meta, companions)

    @classmethod
    def from_note(cls, meta: dict, note_path: Path) -> BoxHead:
        """The unfitted head a checkpoint's note describes, with its ``templates_`` and
        ``symmetry_``: every setting, the templates, the symmetries and the note's records checked;
        no network is built."""
        params = meta.get("params")
        if not isinstance(params, dict) or "class_names" not in params or "templates" not in meta:
            raise InputError(f"{note_path}: malformed box head note (no params, class_names or templates)")
        known = {f.name for f in dataclasses.fields(cls)}
        settings = {k: tuple(v) if isinstance(v, list) else v for k, v in params.items() if k in known}
        try:
            head = cls(**settings)
            num_classes = len(head.class_names)
            templates = _note_array(meta["templates"], np.float64, (num_classes, 3), "templates")
            if not (templates > 0).all():
                raise InputError("templates must be positive sizes in metres")
            default = symmetry_orders(templates, head.square_ratio).tolist()
            symmetry = _note_array(meta.get("symmetry", default), np.int64, (num_classes,), "symmetry")
            if not np.isin(symmetry, (2, 4)).all():
                raise InputError("symmetry must hold heading symmetries 2 or 4")
        except InputError as exc:
            raise InputError(f"{note_path}: {exc}") from None
        check_note_record(meta, head.class_names, str(note_path))
        head.templates_ = templates
        head.symmetry_ = symmetry
        return head

    @classmethod
    def load(cls, path: str | os.PathLike) -> BoxHead:
        """A fitted head from ``save``'s checkpoint (``torch.load(weights_only=True)``); ``note_``
        holds the JSON note. The note is checked before the network is built (``from_note``), and
        the weights' shapes against the network's."""
        meta = read_checkpoint_note(path)
        return cls.from_note(meta, Path(path).with_suffix(".json")).with_weights(path, meta)


def _note_array(value: object, dtype: type, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A note's nested lists of numbers ``value`` as a finite array of ``dtype`` and ``shape``;
    ``InputError`` naming ``name`` otherwise."""

    def numbers(v: object, dims: tuple[int, ...]) -> bool:
        if not dims:
            return isinstance(v, (int, float)) and not isinstance(v, bool)
        return isinstance(v, list) and len(v) == dims[0] and all(numbers(x, dims[1:]) for x in v)

    if not numbers(value, shape):
        raise InputError(f"{name} must be nested lists of numbers of shape {shape}")
    try:
        array = np.array(value, np.float64)
    except OverflowError:  # an integer of hundreds of digits
        raise InputError(f"{name} must hold finite numbers") from None
    if not np.isfinite(array).all():
        raise InputError(f"{name} must hold finite numbers")
    if dtype is np.int64 and not (array == np.round(array)).all():
        raise InputError(f"{name} must hold integers")
    return array.astype(dtype)


POSITIVE_SHARE = 0.8
"""A point set is an object's when at least this share of its sampled points lies in the object's
box (grown by ``BOX_MARGIN_M``): fragments of one object are that object, whose whole box the head
learns to regress from them."""

BACKGROUND_SHARE = 0.5
"""A set with less than this share in every labelled box is background; sets in between (an
object merged with a neighbour or with structure) are left out of training."""

BOX_MARGIN_M = 0.1
"""Labelled boxes are grown by this on every side before counting the points inside (range noise
and boxes drawn tight put surface points just outside)."""


def share_inside(points: np.ndarray, boxes: np.ndarray, margin_m: float = BOX_MARGIN_M) -> np.ndarray:
    """(M, R) the share of each of M sets' (M, P, 3) sampled points inside each of (R, 7) boxes
    grown by ``margin_m``."""
    points = np.asarray(points, np.float64)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    out = np.zeros((len(points), len(boxes)))
    if not len(points) or not len(boxes):
        return out
    centres = points.mean(axis=1)
    reach = np.linalg.norm(points - centres[:, None], axis=2).max(axis=1)
    for r, box in enumerate(boxes):
        radius = np.hypot(box[3], box[4]) / 2 + margin_m
        near = np.flatnonzero(np.hypot(*(centres[:, :2] - box[:2]).T) < radius + reach)
        if not len(near):
            continue
        rel = points[near] - box[:3]
        c, s = np.cos(box[6]), np.sin(box[6])
        x = rel[..., 0] * c + rel[..., 1] * s
        y = -rel[..., 0] * s + rel[..., 1] * c
        inside = (
            (np.abs(x) <= box[3] / 2 + margin_m)
            & (np.abs(y) <= box[4] / 2 + margin_m)
            & (np.abs(rel[..., 2]) <= box[5] / 2 + margin_m)
        )
        out[near, r] = inside.mean(axis=1)
    return out


def label_point_sets(
    points: np.ndarray,
    label_boxes: np.ndarray,
    label_class_ids: np.ndarray,
    background_id: int,
    positive_share: float = POSITIVE_SHARE,
    background_share: float = BACKGROUND_SHARE,
) -> tuple[np.ndarray, np.ndarray]:
    """Each set's training label by its points (``POSITIVE_SHARE``, ``BACKGROUND_SHARE``).

    Returns:
        ``(labels, owner)``: (M,) class ids, ``background_id`` for background and -1 for sets left
        out; (M,) the label box of each object set (-1 for the others).
    """
    share = share_inside(points, label_boxes)
    labels = np.full(len(share), background_id, np.int64)
    owner = np.full(len(share), -1, np.int64)
    if not share.shape[1]:
        return labels, owner
    best = share.argmax(axis=1)
    best_share = share[np.arange(len(best)), best]
    positive = best_share >= positive_share
    labels[positive] = np.asarray(label_class_ids, np.int64)[best[positive]]
    owner[positive] = best[positive]
    labels[(best_share >= background_share) & ~positive] = -1
    return labels, owner


def check_head_input(groups: ProposalGroups) -> None:
    """Raise ``InputError`` unless the point sets carry the sampled points and fitted boxes the
    head reads."""
    if groups.points is None or groups.fitted_boxes is None:
        raise InputError("the box head needs each point set's points (detection.group_proposals keeps them)")


def head_candidates(groups: ProposalGroups, head: BoxHead, probability_exponent: float = 1.0) -> Detections:
    """One candidate detection per point set: the head's most probable object class, its box as
    that class, and the score ``p ** probability_exponent * iou`` (class probability, predicted
    IoU), as ``scoring.score_groups`` scores with the box quality regressor.

    Args:
        groups: a frame's point sets, with their sampled points and fitted boxes
            (``groups.group_proposals``).
        head: a fitted ``BoxHead``.

    Returns:
        (G) candidates in point-set order, none suppressed; ``proposal_ids`` are each set's first
        proposal.
    """
    check_exponent(probability_exponent)
    num_classes = len(head.class_names)
    if not groups.num_groups:
        return Detections.empty(head.class_names)
    check_head_input(groups)
    out = head.predict(groups.points, groups.fitted_boxes, groups.descriptors)
    class_ids = out.probabilities[:, :num_classes].argmax(axis=1)
    rows = np.arange(len(class_ids))
    scores = out.probabilities[rows, class_ids] ** np.float32(probability_exponent) * out.iou[rows, class_ids]
    return Detections(
        boxes=out.boxes[rows, class_ids],
        class_ids=class_ids.astype(np.int32),
        scores=scores.astype(np.float32),
        probabilities=out.probabilities,
        proposal_ids=np.asarray(groups.representatives, np.int64),
        suppressed_by=np.full(len(class_ids), -1, np.int64),
        class_names=head.class_names,
    )


def _class_bars(own_probabilities: list[list[float]]) -> np.ndarray:
    """(C,) each class's median of ``own_probabilities`` (per class, its labelled sets' probability
    of their own class); above every probability (nothing reaches it) for a class with none."""
    return np.array([float(np.median(p)) if p else np.inf for p in own_probabilities])
