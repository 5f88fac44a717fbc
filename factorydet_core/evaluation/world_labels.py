"""``bench world-labels``: how well a box labelled once is carried into every frame, against the
simulator's truth, on held-out factories (simulator seeds no setting of ``session.world`` was
chosen on).

For each static object (a class that does not move) the truth box of the frame where it has the
most points is carried into every other frame by the frames' poses (odometry alone, then ICP
chained on it, with the nominal extrinsics, with the detector's calibration and with the settled
calibration the app registers with) and compared there with the truth box: IoU where the object has
points, and whether the frame shows it (``world.place_box``'s visibility) against how many points
truth says it has there.

Boxes are compared in the frame the app draws the points in: the sensors' points merged with the
extrinsics in use, which sit off the true vehicle frame by the rig's common calibration error (a
fraction of a degree of heading: 8 mm sideways on every 1.5 m step). A person's box fits
the drawn points, so the truth boxes are moved by that offset (``_drawn_from_true``, from the
simulator's true extrinsics) before the comparison; the data set's own annotations, in the true
vehicle frame, are compared as they are.

``spread`` measures ``world.spread_objects`` on the data set's own annotations (what ``factorydet
labels spread`` adds): the labels it adds, how many box an object with points there, and their IoU
with truth.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.evaluation.quality import HELDOUT_SCRATCH, heldout_factory
from factorydet_core.evaluation.records import machine_info
from factorydet_core.geometry import points_in_box, transform_boxes
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.merge import mean_transform, merge_frame
from factorydet_core.session.store import Label
from factorydet_core.session.world import (
    FLOOR_MARGIN_M,
    MIN_POINTS,
    MOVING_CLASSES,
    SURFACE_MARGIN_M,
    WorldFrames,
    calibrated_extrinsics,
    count_points,
    counting_box,
    place_box,
    planar,
    register_frames,
    registration_extrinsics,
    spread_objects,
)
from factorydet_core.sim.truth import read_frame_truth, read_truth

POINT_BINS: tuple[tuple[int, int | None], ...] = ((1, 4), (5, 19), (20, 49), (50, None))
"""Truth points of an object in a frame, binned: how often a frame with that many shows it."""

SWEEP_MIN_POINTS: tuple[int, ...] = (1, 2, 3)
"""The least thinned points that would show an object, swept for the app's poses: what each would
show where the object has points, and where it has none."""

SWEEP_MARGINS: tuple[tuple[float, float], ...] = (
    (0.0, 0.05),
    (0.0, 0.02),
    (0.01, 0.02),
    (0.02, 0.02),
    (0.03, 0.02),
    (0.04, 0.02),
    (0.02, 0.03),
    (0.02, 0.05),
    (0.02, 0.01),
    (0.02, 0.0),
)
"""``(surface margin, floor margin)`` in metres of the box whose points count (``world.counting_box``),
swept for the app's poses; the first is the rule before the surface margin, the last two count
the points of the floor band more or less."""

MISS_CAUSES: tuple[str, ...] = ("thinning", "pose", "floor", "margin")
"""Why the app's poses leave out a frame where the object has points (``_miss_cause``): its points
lie in the carried counting box but thinning kept none of them ("thinning"); they lie in the
counting box of its true box there but not in the carried one ("pose"); every one of them lies in
the box's bottom floor margin, where the floor's points are ("floor"); or they lie outside the true
box grown by the surface margin, the LiDAR's range noise ("margin")."""

SPURIOUS_WEIGHT = 2
"""How the margins are chosen (``margin_score``): a frame shown without a point of the object
(a box on empty space, which a labeller must notice and take out) counts as much as this many
frames shown where it has points."""


def margin_score(shown_with_points: int, shown_without_points: int) -> int:
    """What ``world.SURFACE_MARGIN_M`` and ``world.FLOOR_MARGIN_M`` were chosen by, on validation
    factories: frames shown where the object has points less ``SPURIOUS_WEIGHT`` times those
    shown where it has none."""
    return int(shown_with_points) - SPURIOUS_WEIGHT * int(shown_without_points)


def _shown_shares(counts: Sequence[tuple[int, int]], min_points: int) -> tuple[dict, float]:
    """From ``(truth points, thinned points in the carried box)`` per object and frame: the share
    shown by ``min_points`` in each of ``POINT_BINS`` and where truth has no points."""
    by_bin = {}
    for low, high in POINT_BINS:
        shown = [n >= min_points for t, n in counts if t >= low and (high is None or t <= high)]
        by_bin[_bin_name(low, high)] = round(float(np.mean(shown)), 4) if shown else None
    without = [n >= min_points for t, n in counts if t == 0]
    return by_bin, round(float(np.mean(without)), 4) if without else 0.0


def _miss_cause(object_points: np.ndarray, carried_box, true_box) -> str:
    """One of ``MISS_CAUSES`` for a frame that does not show an object it has ``object_points``
    (K, 3) of: ``carried_box`` (7,) is where the poses carried its box, ``true_box`` (7,) its truth
    box there (both in the frame the points are drawn in)."""
    if points_in_box(object_points, counting_box(carried_box)).any():
        return "thinning"
    if points_in_box(object_points, counting_box(true_box)).any():
        return "pose"
    bottom = float(true_box[2]) - float(true_box[5]) / 2
    if len(object_points) and bool((object_points[:, 2] < bottom + FLOOR_MARGIN_M).all()):
        return "floor"
    return "margin"


def _bin_name(low: int, high: int | None) -> str:
    return f"{low}+" if high is None else f"{low}-{high}"


def _quantiles(values: Sequence[float]) -> dict:
    values = np.asarray(values, np.float64)
    if not len(values):
        return {"count": 0}
    return {
        "count": int(len(values)),
        "median": round(float(np.median(values)), 4),
        "p10": round(float(np.percentile(values, 10)), 4),
        "share_at_least_0.6": round(float(np.mean(values >= 0.6)), 4),
    }


def _pose_errors(poses: np.ndarray, true_poses: np.ndarray) -> dict:
    """Step (frame to frame) and drift (frame 0 to each frame) errors of ``poses`` (F, 4, 4)."""

    def error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
        d = np.linalg.inv(a) @ b
        return float(np.linalg.norm(d[:3, 3])), abs(float(np.degrees(np.arctan2(d[1, 0], d[0, 0]))))

    steps, drifts = [], []
    for k in range(1, len(poses)):
        steps.append(
            error(np.linalg.inv(true_poses[k - 1]) @ true_poses[k], np.linalg.inv(poses[k - 1]) @ poses[k])
        )
        drifts.append(error(np.linalg.inv(true_poses[0]) @ true_poses[k], np.linalg.inv(poses[0]) @ poses[k]))
    steps_arr, drifts_arr = np.array(steps).reshape(-1, 2), np.array(drifts).reshape(-1, 2)
    return {
        "step_error_m_median": round(float(np.median(steps_arr[:, 0])), 4) if len(steps) else 0.0,
        "step_error_deg_median": round(float(np.median(steps_arr[:, 1])), 4) if len(steps) else 0.0,
        "drift_m_max": round(float(drifts_arr[:, 0].max()), 4) if len(drifts) else 0.0,
        "drift_deg_max": round(float(drifts_arr[:, 1].max()), 4) if len(drifts) else 0.0,
    }


def _drawn_from_true(extrinsics: np.ndarray, folder: Path) -> np.ndarray:
    """(4, 4) the rig's common calibration offset: from the true vehicle frame to the frame the
    points are merged in with ``extrinsics`` (S, 4, 4), the mean over sensors, heading only."""
    true = np.asarray(read_truth(folder)["T_vehicle_sensor_true"], np.float64)
    return planar(mean_transform(np.asarray(extrinsics, np.float64) @ np.linalg.inv(true)))


APP_METHOD = "ICP, settled calibration (the app)"
METHODS: dict[str, tuple[bool, str]] = {
    "odometry": (False, "calibrated"),
    "ICP, nominal extrinsics": (True, "nominal"),
    "ICP, the detector's calibration": (True, "calibrated"),
    APP_METHOD: (True, "registration"),
}
"""How the frames are placed: ``(ICP between frames, the extrinsics they are merged with)``, the
extrinsics ``nominal`` (the data set's), ``calibrated`` (``world.calibrated_extrinsics``: the
detector's three passes) or ``registration`` (``world.registration_extrinsics``: refined until
they settle); ``APP_METHOD`` is the app's way (``world.session_world``)."""

_EXTRINSICS: dict[str, Callable] = {
    "nominal": lambda dataset: np.asarray(dataset.T_vehicle_sensor, np.float64),
    "calibrated": calibrated_extrinsics,
    "registration": registration_extrinsics,
}


def _factory(
    dataset, frames, truths, folder: Path, extrinsics: np.ndarray, use_icp: bool, sweep_margins: bool = False
) -> tuple[dict, WorldFrames]:
    """One factory's figures for one way of placing the frames (merged with ``extrinsics``); with
    ``sweep_margins`` (the app's way), also ``(truth points, thinned points counted)`` per object
    and frame for each of ``SWEEP_MARGINS``, and per ``POINT_BINS`` bin the frames left out by
    ``MISS_CAUSES`` (``misses``)."""
    offset = _drawn_from_true(extrinsics, folder)
    names = dataset.class_names
    start = time.perf_counter()
    world = register_frames(frames, extrinsics, use_icp=use_icp)
    register_seconds = time.perf_counter() - start
    # Every static object's truth box and points in every frame that has points of it.
    objects: dict[int, dict[int, tuple[np.ndarray, int]]] = {}
    for f, truth in enumerate(truths):
        for instance_id, class_id, box, num_points in zip(
            truth.instance_ids, truth.instance_class_ids, truth.instance_boxes, truth.instance_num_points
        ):
            if class_id >= 0 and names[class_id] not in MOVING_CLASSES:
                drawn = transform_boxes(offset, np.asarray(box, np.float64)[None])[0]
                objects.setdefault(int(instance_id), {})[f] = (drawn, int(num_points))
    ious: list[float] = []
    shown = {_bin_name(*b): [0, 0] for b in POINT_BINS}
    shown_without = [0, 0]
    point_counts: list[tuple[int, int]] = []  # (truth points, thinned points in the carried box)
    margin_counts: dict[str, list[tuple[int, int]]] = {_margin_name(*m): [] for m in SWEEP_MARGINS}
    place_ms = []
    misses = {_bin_name(*b): dict.fromkeys(MISS_CAUSES, 0) for b in POINT_BINS}
    merged: dict[int, np.ndarray] = {}  # each frame's points, unthinned, as drawn
    for instance_id, per_frame in objects.items():
        source = max(per_frame, key=lambda f: (per_frame[f][1], -f))
        start = time.perf_counter()
        placement = place_box(world, source, per_frame[source][0])
        place_ms.append(1000 * (time.perf_counter() - start))
        swept = {
            _margin_name(surface, floor): count_points(
                world, placement.boxes, surface_margin_m=surface, floor_margin_m=floor
            )
            for surface, floor in (SWEEP_MARGINS if sweep_margins else ())
        }
        for f in range(world.num_frames):
            if f == source:
                continue
            truth_points = per_frame[f][1] if f in per_frame else 0
            point_counts.append((truth_points, int(placement.num_points[f])))
            for name, counts in swept.items():
                margin_counts[name].append((truth_points, int(counts[f])))
            if f not in per_frame:
                shown_without[0] += 1
                shown_without[1] += int(placement.visible_mask[f])
                continue
            box, num_points = per_frame[f]
            ious.append(float(box_iou_3d(placement.boxes[f][None], box[None])[0, 0]))
            for low, high in POINT_BINS:
                if num_points >= low and (high is None or num_points <= high):
                    counts = shown[_bin_name(low, high)]
                    counts[0] += 1
                    counts[1] += int(placement.visible_mask[f])
                    if sweep_margins and not placement.visible_mask[f]:
                        if f not in merged:
                            merged[f] = merge_frame(frames[f], extrinsics).points
                        mine = merged[f][truths[f].point_instance_ids == instance_id]
                        misses[_bin_name(low, high)][_miss_cause(mine, placement.boxes[f], box)] += 1
    # The true poses of the frame the points are drawn in (the offset conjugates them).
    true_poses = np.stack([t.T_world_vehicle @ np.linalg.inv(offset) for t in truths])
    record = {
        **_pose_errors(world.T_world_vehicle, true_poses),
        "register_seconds_per_frame": round(register_seconds / len(frames), 3),
        "place_box_ms_median": round(float(np.median(place_ms)), 2) if place_ms else None,
        "num_objects": len(objects),
        "iou": ious,
        "shown": shown,
        "shown_without_points": shown_without,
        "point_counts": point_counts,
    }
    if sweep_margins:
        record["margin_counts"] = margin_counts
        record["misses"] = misses
    return record, world


def _margin_name(surface_m: float, floor_m: float) -> str:
    return f"{round(100 * surface_m)} cm, {round(100 * floor_m)} cm"


def _margin_sweep(counts: dict[str, list[tuple[int, int]]]) -> dict:
    """Per ``SWEEP_MARGINS`` entry: the shares shown by ``POINT_BINS`` (``MIN_POINTS``), the
    frames shown with and without the object's points, and their ``margin_score``."""
    out = {}
    for name, pairs in counts.items():
        by_bin, without = _shown_shares(pairs, MIN_POINTS)
        with_points = sum(1 for t, n in pairs if t > 0 and n >= MIN_POINTS)
        without_points = sum(1 for t, n in pairs if t == 0 and n >= MIN_POINTS)
        out[name] = {
            "shown_by_points": by_bin,
            "shown_without_points": without,
            "frames_shown_with_points": with_points,
            "frames_shown_without_points": without_points,
            "score": margin_score(with_points, without_points),
        }
    return out


def _spread(dataset, frames, truths, world) -> dict:
    """What ``spread_objects`` adds to the data set's annotations, against truth."""
    names = dataset.class_names
    labels_by_frame = {
        f: [
            Label(None, f, tuple(box), names[c], "dataset", int(i), "", "", "", "", 1, False)
            for box, c, i in zip(frame.labels.boxes, frame.labels.class_ids, frame.labels.instance_ids)
        ]
        for f, frame in enumerate(frames)
    }
    items = spread_objects(labels_by_frame, world)
    with_points, ious = 0, []
    for f, box, _, instance_id in items:
        truth = truths[f]
        where = np.flatnonzero(truth.instance_ids == instance_id)
        if len(where):
            with_points += 1
            ious.append(float(box_iou_3d(np.asarray(box)[None], truth.instance_boxes[where])[0, 0]))
    return {
        "annotations": int(sum(len(fr.labels) for fr in frames)),
        "labels_added": len(items),
        "objects": len({item[3] for item in items}),
        "with_points": with_points,
        "iou": ious,
    }


def bench_world_labels(
    seeds: Sequence[int] = (101, 102, 103),
    num_frames: int = 12,
    scratch: str | Path = HELDOUT_SCRATCH,
    command: str = "",
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Carry every static object's box through the frames of each held-out factory, by each of
    ``METHODS``, and compare with truth (module docstring). Returns the JSON record."""
    methods: dict[str, list] = {}
    spread: list[dict] = []
    total = len(METHODS) * len(seeds)
    done = 0
    for seed in seeds:
        folder = heldout_factory(int(seed), num_frames, Path(scratch))
        dataset = open_dataset(folder)
        frames = [dataset.frame(i) for i in range(dataset.num_frames)]
        truths = [read_frame_truth(folder, i) for i in range(dataset.num_frames)]
        extrinsics_of: dict[str, tuple[np.ndarray, float]] = {}
        for kind in sorted({kind for _, kind in METHODS.values()}):
            start = time.perf_counter()
            extrinsics_of[kind] = (_EXTRINSICS[kind](dataset), time.perf_counter() - start)
        for method, (use_icp, kind) in METHODS.items():
            extrinsics, calibrate_seconds = extrinsics_of[kind]
            result, world = _factory(
                dataset, frames, truths, folder, extrinsics, use_icp, sweep_margins=method == APP_METHOD
            )
            result["calibrate_seconds"] = round(calibrate_seconds, 2) if kind != "nominal" else 0.0
            methods.setdefault(method, []).append(result)
            if method == APP_METHOD:
                spread.append(_spread(dataset, frames, truths, world))
            done += 1
            if progress is not None:
                progress(done, total)
    out = {}
    for method, results in methods.items():
        shown = {
            name: round(
                sum(r["shown"][name][1] for r in results) / max(1, sum(r["shown"][name][0] for r in results)),
                4,
            )
            for name in results[0]["shown"]
        }
        without = [sum(r["shown_without_points"][i] for r in results) for i in (0, 1)]
        out[method] = {
            "per_factory": [
                {
                    key: value
                    for key, value in r.items()
                    if key
                    not in ("iou", "shown", "shown_without_points", "point_counts", "margin_counts", "misses")
                }
                for r in results
            ],
            "transfer_iou": _quantiles([v for r in results for v in r["iou"]]),
            "shown_by_points": shown,
            "frames_by_points": {
                name: sum(r["shown"][name][0] for r in results) for name in results[0]["shown"]
            },
            "shown_without_points": round(without[1] / max(1, without[0]), 4),
        }
        if method == APP_METHOD:
            counts = [tuple(c) for r in results for c in r["point_counts"]]
            out[method]["shown_by_min_points"] = {
                str(m): dict(zip(("shown_by_points", "shown_without_points"), _shown_shares(counts, m)))
                for m in SWEEP_MIN_POINTS
            }
            if all("misses" in r for r in results):
                out[method]["misses_by_cause"] = {
                    name: {cause: sum(r["misses"][name][cause] for r in results) for cause in MISS_CAUSES}
                    for name in results[0]["misses"]
                }
            out[method]["shown_by_margins"] = _margin_sweep(
                {
                    name: [c for r in results for c in r["margin_counts"][name]]
                    for name in results[0]["margin_counts"]
                }
            )
    return {
        "benchmark": "world-labels",
        "command": command,
        "machine": machine_info(),
        "seeds": [int(s) for s in seeds],
        "frames_per_factory": int(num_frames),
        "min_points": MIN_POINTS,
        "surface_margin_m": SURFACE_MARGIN_M,
        "floor_margin_m": FLOOR_MARGIN_M,
        "spurious_weight": SPURIOUS_WEIGHT,
        "methods": out,
        "spread": {
            "annotations": sum(s["annotations"] for s in spread),
            "labels_added": sum(s["labels_added"] for s in spread),
            "objects": sum(s["objects"] for s in spread),
            "share_with_points": round(
                sum(s["with_points"] for s in spread) / max(1, sum(s["labels_added"] for s in spread)), 4
            ),
            "iou": _quantiles([v for s in spread for v in s["iou"]]),
        },
    }
