"""Colours and thinning for displaying clouds and labels (the app draws them; the numbers live here)."""

from __future__ import annotations

import functools

import numpy as np

from factorydet_core.types import CLASS_NAMES

COLOR_MODES = ("sensor", "height", "class", "annotated", "rgb")
"""Ways to colour a cloud; ``rgb`` uses the file's own colours and falls back to height without them."""

# One distinct colour per paper class, in CLASS_NAMES order (colour-blind-safe Okabe-Ito-like set).
_CLASS_PALETTE = np.array(
    [
        [230, 159, 0],  # barrel
        [86, 180, 233],  # bobbin
        [0, 158, 115],  # box
        [240, 228, 66],  # cone
        [0, 114, 178],  # pallet
        [213, 94, 0],  # person
        [204, 121, 167],  # truck
    ],
    dtype=np.uint8,
)
UNLABELLED_GREY = np.array([150, 150, 150], dtype=np.uint8)


def class_color(class_name: str) -> tuple[int, int, int]:
    """RGB of a class; classes outside the paper's seven get a stable colour from their name."""
    if class_name in CLASS_NAMES:
        return tuple(int(c) for c in _CLASS_PALETTE[CLASS_NAMES.index(class_name)])
    rng = np.random.default_rng(sum(ord(ch) * 31**i for i, ch in enumerate(class_name)) % 2**32)
    return tuple(int(c) for c in rng.integers(60, 230, 3))


def class_colors(class_names: tuple[str, ...]) -> np.ndarray:
    """(K, 3) uint8 colour per class of a vocabulary."""
    return np.array([class_color(name) for name in class_names], dtype=np.uint8).reshape(-1, 3)


def _hsv_wheel(num: int) -> np.ndarray:
    hue = np.arange(num) / max(num, 1)
    k = (np.array([5.0, 3.0, 1.0])[None] + hue[:, None] * 6) % 6
    rgb = 1 - np.clip(np.minimum(k, 4 - k), 0, 1) * 0.85
    return (rgb * 255).astype(np.uint8)


def colors_by_sensor(sensor_ids: np.ndarray, num_sensors: int) -> np.ndarray:
    """(N, 3) uint8: one hue per sensor."""
    return _hsv_wheel(num_sensors)[sensor_ids]


def colors_by_height(z: np.ndarray, low: float | None = None, high: float | None = None) -> np.ndarray:
    """(N, 3) uint8: a blue-green-yellow ramp over z, between the 2nd and 98th percentiles by default."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    low = float(np.percentile(z, 2)) if low is None else low
    high = float(np.percentile(z, 98)) if high is None else high
    t = np.clip((z - low) / max(high - low, 1e-6), 0, 1)[:, None]
    stops = np.array([[68, 1, 84], [33, 145, 140], [253, 231, 37]], dtype=np.float64)
    rgb = np.where(
        t < 0.5, stops[0] + (stops[1] - stops[0]) * t * 2, stops[1] + (stops[2] - stops[1]) * (t * 2 - 1)
    )
    return rgb.astype(np.uint8)


def colors_by_class(point_class_ids: np.ndarray, class_names: tuple[str, ...]) -> np.ndarray:
    """(N, 3) uint8: class colour of each point's annotated instance, grey for the rest."""
    palette = np.concatenate([class_colors(class_names), UNLABELLED_GREY[None]])
    return palette[np.where(point_class_ids >= 0, point_class_ids, len(class_names))]


def colors_by_annotation(point_instance_ids: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: green for points of annotated instances, grey for everything else."""
    return np.where((point_instance_ids > 0)[:, None], np.array([40, 200, 90], np.uint8), UNLABELLED_GREY)


def colors_by_id(ids: np.ndarray, seed: int = 0) -> np.ndarray:
    """(N, 3) uint8: a distinct, stable colour per integer id (patches, segments), bright enough to
    read against the grid; neighbouring ids get unrelated colours."""
    ids = np.asarray(ids, np.int64)
    if not len(ids):
        return np.zeros((0, 3), np.uint8)
    # A fixed hash of the id, so a patch keeps its colour however many others there are.
    hashed = (ids * 2654435761 + seed * 97) % (2**32)
    hue = (hashed % 360) / 360.0
    value = 0.75 + 0.25 * ((hashed // 360) % 2)
    h6 = hue * 6
    sector = np.floor(h6).astype(int) % 6
    f = h6 - np.floor(h6)
    p, q, t = np.zeros_like(f), 1 - f, f
    one = np.ones_like(f)
    rgb = np.select(
        [sector[:, None] == k for k in range(6)],
        [
            np.stack(c, axis=1)
            for c in ((one, t, p), (q, one, p), (p, one, t), (p, q, one), (t, p, one), (one, p, q))
        ],
    )
    return (rgb * value[:, None] * 235 + 20).clip(0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def _display_ranks(num_points: int) -> np.ndarray:
    """(num_points,) a fixed shuffle of the ranks 0 .. num_points - 1 (read only): the same cloud
    size always thins the same way."""
    ranks = np.random.default_rng(num_points).permutation(num_points)
    ranks.flags.writeable = False
    return ranks


def thin_for_display(keep_mask: np.ndarray, max_points: int | None) -> np.ndarray:
    """(N,) bool: at most ``max_points`` of the points ``keep_mask`` (N,) bool keeps, spread
    evenly at random over them; all of them when they are no more (or ``max_points`` is None),
    then ``keep_mask`` itself (as a bool array), not a copy.

    The choice is fixed for a cloud of N points: a colour mode or a layer drawn again draws the
    same points, and the points kept under a smaller budget are among those kept under a larger
    one (lowering the budget only takes points away)."""
    keep_mask = np.asarray(keep_mask, bool)
    if keep_mask.ndim != 1:
        raise ValueError(f"keep_mask must be (N,), got shape {keep_mask.shape}")
    if max_points is not None and max_points < 0:
        raise ValueError(f"max_points must be at least 0, got {max_points}")
    if max_points is None or int(keep_mask.sum()) <= max_points:
        return keep_mask
    kept = np.flatnonzero(keep_mask)
    ranks = _display_ranks(len(keep_mask))[kept]
    chosen = kept[np.argpartition(ranks, max_points - 1)[:max_points]] if max_points else kept[:0]
    out = np.zeros(len(keep_mask), bool)
    out[chosen] = True
    return out
