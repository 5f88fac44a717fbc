"""Benchmark commands: each prints one JSON object, its record; ``update_readme`` writes the record to
``bench/<block>.json`` beside a page and a table of its headline figures into the page's block."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import statistics
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.detection.box_quality import INFERENCE_SETTINGS, BoxQuality
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.groups import BoxSizePrior, best_option_iou
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.bench_tables import (  # noqa: F401 - the page writers, re-exported
    check_readme_block,
    record_path,
    update_readme,
)
from factorydet_core.evaluation.evaluate import detector_for, measure
from factorydet_core.evaluation.plots import plot_voxel_sweep
from factorydet_core.evaluation.records import machine_info
from factorydet_core.geometry import rotation_angle_deg
from factorydet_core.io.dataset import open_dataset
from factorydet_core.metrics import best_box_iou, best_point_iou, proposal_point_lists, recall_table
from factorydet_core.proposals.candidates import box_hypotheses
from factorydet_core.proposals.features import fisher_vectors, fisher_vectors_reference
from factorydet_core.proposals.settings import front_end_params, preset_for
from factorydet_core.proposals.voxels import voxel_local_points
from factorydet_core.sim.simulate import FactorySimulator, SimConfig, simulate_dataset
from factorydet_core.sim.truth import read_frame_truth, read_truth
from factorydet_core.training.mining import collect_proposals, train_with_mining
from factorydet_core.training.settings import LoopSettings
from factorydet_core.types import PROBABILITY_EXPONENT, SCORE_THRESHOLD, InputError


def bench_simulate(num_frames: int = 10, points_per_frame: int = 80_000, seed: int = 0) -> dict:
    """Seconds to ray-cast one 12-sensor frame, measured over ``num_frames`` frames."""
    config = SimConfig(num_frames=num_frames, seed=seed, points_per_frame=points_per_frame)
    start = time.perf_counter()
    simulator = FactorySimulator(config)
    setup_s = time.perf_counter() - start
    seconds, num_points = [], []
    for i in range(num_frames):
        start = time.perf_counter()
        frame = simulator.render(i)
        seconds.append(time.perf_counter() - start)
        num_points.append(len(frame.points))
    return {
        "benchmark": "simulate",
        "command": f"factorydet bench simulate --frames {num_frames} --points {points_per_frame}"
        f" --seed {seed}",
        "num_frames": num_frames,
        "num_sensors": simulator.rig.num_sensors,
        "points_per_frame_median": int(statistics.median(num_points)),
        "setup_s": round(setup_s, 3),
        "seconds_per_frame_median": round(statistics.median(seconds), 4),
        "seconds_per_frame_max": round(max(seconds), 4),
        "first_frame_s": round(seconds[0], 4),
        "target_seconds_per_frame": 0.5,
        "machine": machine_info(),
    }


def _median(values: list[float]) -> float:
    return round(float(statistics.median(values)), 1) if values else float("nan")


def bench_features(points: np.ndarray, grid, reference_voxels: int = 200, seed: int = 0) -> dict:
    """Feature throughput on a whole frame (the median of three runs), and the speed-up over the
    float64 reference measured on the same subset of voxels in the same run."""

    local = voxel_local_points(points, grid)
    full = []
    for _ in range(3):  # the median of three: the first call also starts the kernel's threads
        start = time.perf_counter()
        fisher_vectors(local, grid.point_voxel_ids, grid.num_voxels)
        full.append(time.perf_counter() - start)
    full_s = statistics.median(full)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(grid.num_voxels, min(reference_voxels, grid.num_voxels), replace=False)
    remap = np.full(grid.num_voxels, -1)
    remap[chosen] = np.arange(len(chosen))
    mask = remap[grid.point_voxel_ids] >= 0
    subset_points, subset_ids = local[mask], remap[grid.point_voxel_ids[mask]]
    fast, slow = [], []
    for _ in range(3):
        start = time.perf_counter()
        fast_fv = fisher_vectors(subset_points, subset_ids, len(chosen))
        fast.append(time.perf_counter() - start)
        start = time.perf_counter()
        slow_fv = fisher_vectors_reference(subset_points, subset_ids, len(chosen))
        slow.append(time.perf_counter() - start)
    return {
        "points": int(len(points)),
        "voxels": int(grid.num_voxels),
        "seconds": round(full_s, 3),
        "points_per_second": int(len(points) / full_s),
        "voxels_per_second": int(grid.num_voxels / full_s),
        "reference_subset_voxels": int(len(chosen)),
        "speedup_over_reference": round(statistics.median(slow) / statistics.median(fast), 1),
        "max_abs_error_vs_reference": float(np.abs(fast_fv - slow_fv).max()),
    }


def bench_pipeline(
    data: str | os.PathLike | list,
    *,
    preset: str | None = None,
    overrides: dict | None = None,
    max_frames: int = 4,
    iou_threshold: float | None = None,
    min_points: int = 50,
    calibrate: bool = True,
    T_vehicle_sensor: np.ndarray | None = None,
    command: str = "",
    progress=None,
) -> dict:
    """Stage times, feature throughput and per-class proposal recall of the front half.

    On a simulated data set (a folder with ``truth/``) the reference is the hidden truth: every
    instance of the seven classes with at least ``min_points`` points in the frame, annotated or not,
    on the first ``max_frames`` test frames. On single files (one or a list, pooled) it is each
    file's own boxes.
    """
    import dataclasses

    paths = [Path(p) for p in data] if isinstance(data, (list, tuple)) else [Path(data)]
    if not paths:
        raise InputError("bench pipeline: no data given")
    simulated = (paths[0] / "truth").is_dir()
    if simulated and len(paths) > 1:
        raise InputError("bench pipeline: give one simulated data set, or several single files")
    data = paths[0]
    dataset = open_dataset(data)
    if preset is None:
        preset = preset_for(dataset.num_sensors)
    if iou_threshold is None:
        iou_threshold = 0.6 if simulated else 0.25
    params = front_end_params(preset, overrides)
    detector = Detector(params, T_vehicle_sensor)
    calibration = None
    size_prior = None
    if simulated:
        test_frames = dataset.splits.get("test") or list(range(dataset.num_frames))
        frame_indices = test_frames[:max_frames]
        if calibrate and T_vehicle_sensor is None and dataset.num_sensors > 1:
            T_true = np.array(read_truth(data)["T_vehicle_sensor_true"])
            start = time.perf_counter()
            detector.calibrate(dataset.frame(frame_indices[0]))
            calib_s = time.perf_counter() - start

            def errors(T: np.ndarray) -> dict:
                rot = [rotation_angle_deg(T[s, :3, :3], T_true[s, :3, :3]) for s in range(len(T))]
                trans = np.linalg.norm(T[:, :3, 3] - T_true[:, :3, 3], axis=1)
                # Where a point 10 m in front of each sensor lands, against where it should.
                ahead = np.array([10.0, 0.0, 0.0, 1.0])
                shift = np.linalg.norm((T[:, :3] @ ahead) - (T_true[:, :3] @ ahead), axis=1)
                return {
                    "rotation_deg_median": round(float(np.median(rot)), 3),
                    "translation_cm_median": round(float(np.median(trans)) * 100, 2),
                    "point_10m_ahead_error_cm_median": round(float(np.median(shift)) * 100, 2),
                }

            calibration = {
                "nominal": errors(dataset.T_vehicle_sensor),
                "refined": errors(detector.T_vehicle_sensor),
                "residual_rmse_cm_before": round(
                    float(np.nanmedian(detector.calibration_.rmse_before)) * 100, 2
                ),
                "residual_rmse_cm_after": round(
                    float(np.nanmedian(detector.calibration_.rmse_after)) * 100, 2
                ),
                "seconds": round(calib_s, 2),
            }
        items = [(dataset, index) for index in frame_indices]
        # The class sizes a detector trained on this data set's annotated training frames knows.
        train_frames = dataset.splits.get("train") or []
        annotated = [dataset.frame(i).labels for i in train_frames]
        size_prior = (
            BoxSizePrior.from_boxes(
                np.concatenate([labels.boxes for labels in annotated]),
                np.concatenate([labels.class_ids for labels in annotated]),
                len(dataset.class_names),
            )
            if annotated
            else None
        )
    else:
        items = [(open_dataset(path), 0) for path in paths]

    def with_truth_ids(index: int):
        frame = dataset.frame(index)
        if not simulated:
            return frame
        truth = read_frame_truth(data, index)
        return dataclasses.replace(frame, point_instance_ids=truth.point_instance_ids)

    timings: dict[str, list[float]] = {}
    class_ids, box_hits, point_hits, oracle_hits, option_hits = [], [], [], [], []
    num_proposals, features = [], None
    for n, (dataset, index) in enumerate(items):
        history = [with_truth_ids(i) for i in range(max(0, index - params.history_frames), index)]
        result = detector.propose(with_truth_ids(index), history)
        for stage, ms in result.timings_ms.items():
            timings.setdefault(stage, []).append(ms)
        num_proposals.append(len(result.proposals))
        if features is None:
            features = bench_features(result.cloud.points, result.grid)
        if simulated:
            truth = read_frame_truth(data, index)
            keep = (truth.instance_class_ids >= 0) & (truth.instance_num_points >= min_points)
            ref_boxes, ref_ids, ref_classes = (
                truth.instance_boxes[keep],
                truth.instance_ids[keep],
                truth.instance_class_ids[keep],
            )
        else:
            frame = dataset.frame(index)
            ref_boxes, ref_ids, ref_classes = (
                frame.labels.boxes,
                frame.labels.instance_ids,
                frame.labels.class_ids,
            )
        class_ids.append(np.array(dataset.class_names, dtype=object)[ref_classes].astype(str))
        box_hits.append(best_box_iou(ref_boxes, result.proposals.boxes) >= iou_threshold)
        if size_prior is not None:
            set_of: dict[tuple[int, ...], int] = {}
            set_ids = np.array([set_of.setdefault(p, len(set_of)) for p in result.proposals.patch_sets])
            option_iou = best_option_iou(
                ref_boxes,
                ref_classes,
                result.proposals.boxes,
                set_ids,
                size_prior,
                anchor_mask=result.proposals.anchor_mask,
            )
            option_hits.append(option_iou >= iou_threshold)
        point_lists = proposal_point_lists(result.segmentation, result.proposals)
        point_hits.append(best_point_iou(result.cloud, ref_ids, point_lists) >= iou_threshold)
        # Upper bound of box fitting: the boxes the front half would propose for a segment that is
        # exactly the instance's own points.
        oracle = np.zeros(len(ref_ids), bool)
        for r, (inst, box) in enumerate(zip(ref_ids, ref_boxes)):
            own = result.cloud.points[result.cloud.point_instance_ids == inst]
            if len(own):
                hypotheses = box_hypotheses(
                    own,
                    result.floor_plane,
                    complete_boxes=params.complete_boxes,
                    heading=result.proposals.scene_heading,
                )
                oracle[r] = best_box_iou(box[None], hypotheses)[0] >= iou_threshold
        oracle_hits.append(oracle)
        if progress is not None:
            progress(n + 1, len(items))
    class_names = np.concatenate(class_ids)
    names = tuple(sorted(set(class_names.tolist()), key=lambda c: (c not in dataset.class_names, c)))
    class_ids = np.array([names.index(c) for c in class_names], np.int64)
    return {
        "benchmark": "pipeline" if simulated else "pipeline-real",
        "command": command,
        "data": ", ".join(p.name for p in paths),
        "preset": preset,
        "overrides": overrides or {},
        "frames": [int(i) for _, i in items],
        "iou_threshold": iou_threshold,
        "stage_ms_median": {stage: _median(v) for stage, v in timings.items()},
        "target_total_ms": 100,
        "proposals_per_frame_median": int(statistics.median(num_proposals)),
        "features": features,
        "proposal_recall": recall_table(class_ids, np.concatenate(box_hits), names),
        "segment_recall_point_iou": recall_table(class_ids, np.concatenate(point_hits), names),
        "oracle_box_fit_recall": recall_table(class_ids, np.concatenate(oracle_hits), names),
        "option_recall": (
            recall_table(class_ids, np.concatenate(option_hits), names) if option_hits else None
        ),
        "calibration": calibration,
        "T_vehicle_sensor": None if detector.T_vehicle_sensor is None else detector.T_vehicle_sensor.tolist(),
        "machine": machine_info(),
    }


def bench_voxel_sweep(
    data: str | os.PathLike,
    voxel_sizes: list[float],
    *,
    max_frames: int = 2,
    png: str | os.PathLike | None = None,
    command: str = "",
    progress=None,
) -> dict:
    """Proposal recall against voxel size (the paper's Fig. 7 for the front half), with the cut
    pursuit run on the voxels; point-based segmentation, which does not depend on the voxel size,
    is the reference line."""
    base = bench_pipeline(data, max_frames=max_frames, command=command)
    extrinsics = None if base["T_vehicle_sensor"] is None else np.array(base["T_vehicle_sensor"])
    rows = []
    for n, size in enumerate(voxel_sizes):
        result = bench_pipeline(
            data,
            overrides={"voxel_size_m": size, "segment_on": "voxels"},
            max_frames=max_frames,
            T_vehicle_sensor=extrinsics,
        )
        rows.append(
            {
                "voxel_size_m": size,
                "recall": {k: v["recall"] for k, v in result["proposal_recall"].items()},
                "num": {k: v["num"] for k, v in result["proposal_recall"].items()},
                "segment_recall": result["segment_recall_point_iou"]["all"]["recall"],
                "total_ms": result["stage_ms_median"]["total"],
            }
        )
        if progress is not None:
            progress(n + 1, len(voxel_sizes))
    summary = {
        "benchmark": "voxel-sweep",
        "command": command,
        "data": Path(data).name,
        "frames": base["frames"],
        "iou_threshold": base["iou_threshold"],
        "point_segmentation_recall": {k: v["recall"] for k, v in base["proposal_recall"].items()},
        "voxel_segmentation": rows,
        "machine": machine_info(),
    }
    if png is not None:
        plot_voxel_sweep(summary, png)
        summary["png"] = str(png)
    return summary


def _percentile(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 1)


def _child_json(script: str, args: Sequence[str]) -> tuple[dict | None, str]:
    """Run ``script`` in a fresh Python process with ``args`` (its peak memory is its own), and
    read the JSON object it prints last: ``(result, "")``, or ``(None, why)`` when it failed."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True)
    lines = out.stdout.strip().splitlines()
    if out.returncode != 0 or not lines:
        tail = (out.stderr.strip().splitlines() or ["no message"])[-1]
        return None, f"exit {out.returncode}: {tail[:300]}"
    return json.loads(lines[-1]), ""


def _peak_rss_mb() -> float:
    """This process's peak resident memory so far (MB)."""
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def bench_detect(
    data: str | os.PathLike,
    model_path: str | os.PathLike,
    *,
    max_frames: int = 4,
    repeats: int = 1,
    compare_model: str | os.PathLike | None = None,
    compare_overrides: dict[str, object] | None = None,
    compare_checkout: str | os.PathLike | None = None,
    heldout_seeds: Sequence[int] = (),
    heldout_frames: int = 12,
    busy: bool = False,
    command: str = "",
    progress=None,
) -> dict:
    """Time of the whole detection of a frame (front half, grouping, classification, NMS) per
    stage, median and 90th percentile over the first ``max_frames`` test frames (each run
    ``repeats`` times), the process's peak memory, and the model's recorded training time per round.

    With ``compare_model`` and/or ``compare_overrides`` (front-half settings changed from the
    model's), a second configuration runs on the same frames, interleaved frame by frame with the
    first so that both see the same machine load, and the record gives each stage's ratio of
    medians (compared / reference): a speed claim is a ratio measured side by side. Overrides
    named in ``BACK_HALF_SETTINGS`` change the compared model's box quality screen instead, and
    those in ``DETECTOR_SETTINGS`` the compared ``Detector``'s own.

    With ``compare_checkout`` (a folder holding another version of this project: a ``git worktree``
    of an earlier commit, say), the compared configuration is that version's code detecting with
    the same model on the same frames, in a child process that imports it, interleaved frame by
    frame with this one (``CheckoutDetector``): the ratio of a change against the code before it,
    measured side by side.

    With ``busy``, each reference run is repeated beside one other process that keeps a core busy
    (what the app's server or a browser does to a detection on a shared machine), and the record
    gives the slowdown per stage: with the thread pools sized by ``threads``, it should be about
    proportional, not a collapse.

    With ``heldout_seeds``, both configurations are also measured on those held-out simulated
    factories (``quality.measure_heldout``: F-score, mAP, precision and recall at IoU 0.6 against
    the truth), so that a faster path shows what it costs in quality in the same run.
    """
    if compare_checkout is not None and (compare_model is not None or compare_overrides or heldout_seeds):
        raise InputError(
            "--compare-checkout compares code alone: not with --compare-model, --compare-set or --heldout"
        )
    dataset = open_dataset(data)
    model = DetectionModel.load(model_path)
    configs = {"reference": detector_for(model, dataset)}
    front_overrides = dict(compare_overrides or {})
    back_overrides = {k: front_overrides.pop(k) for k in list(front_overrides) if k in BACK_HALF_SETTINGS}
    detector_overrides = {k: front_overrides.pop(k) for k in list(front_overrides) if k in DETECTOR_SETTINGS}
    if compare_model is not None or compare_overrides:
        other = DetectionModel.load(compare_model) if compare_model is not None else model
        if back_overrides:
            if other.box_quality is None:
                raise InputError(f"{', '.join(back_overrides)} need a model with a box quality regressor")
            other = other.with_box_quality(
                **{
                    name: _flag(value) if name == "interleaved_walk" else int(value)
                    for name, value in back_overrides.items()
                }
            )
        detector = detector_for(other, dataset, calibrate=False)
        detector.params = detector.params.replace(**front_overrides)
        for name, value in detector_overrides.items():
            setattr(detector, name, _flag(value))
        # The same extrinsics as the reference, so that only the compared change differs.
        detector.T_vehicle_sensor = configs["reference"].T_vehicle_sensor
        detector.calibration_ = configs["reference"].calibration_
        configs["compared"] = detector
    if compare_checkout is not None:
        configs["compared"] = CheckoutDetector(compare_checkout, data, model_path)
    test = (dataset.splits.get("test") or list(range(dataset.num_frames)))[:max_frames]
    runs = dict(configs)
    if busy:
        runs["busy"] = configs["reference"]  # the reference again, beside a busy process
    try:
        timings, counts = _time_runs(runs, dataset, test, repeats, progress)
    finally:
        if compare_checkout is not None:
            checkout = configs["compared"].describe()
            configs["compared"].close()

    def summary(name: str) -> dict:
        return {
            "stage_ms_median": {stage: _median(v) for stage, v in timings[name].items()},
            "stage_ms_p90": {stage: _percentile(v, 90) for stage, v in timings[name].items()},
            "detections_per_frame_median": int(statistics.median(counts[name])),
        }

    note = model.note
    record = {
        "benchmark": "detect",
        "command": command,
        "data": Path(data).name,
        "model": str(model_path),
        "method": model.method,
        "width": getattr(model.classifier, "width", None),
        "num_parameters": model.classifier.num_parameters_,
        "frames": test,
        "repeats": repeats,
        "points_per_frame_median": int(statistics.median(len(dataset.frame(i).points) for i in test)),
        **summary("reference"),
        "target_total_ms": 100,
        "peak_rss_mb": _peak_rss_mb(),
        "training_seconds_per_round": [r.get("fit_seconds") for r in note.get("rounds_record", [])]
        or note.get("fit_seconds"),
        "machine": machine_info(),
    }

    def against_reference(name: str) -> dict:
        """``name``'s summary and each stage's ratio of its median to the reference's."""
        reference = record["stage_ms_median"]
        out = summary(name)
        out["ratio_of_medians"] = {
            stage: round(ms / reference[stage], 3)
            for stage, ms in out["stage_ms_median"].items()
            if reference.get(stage)
        }
        return out

    if busy:
        record["busy"] = {
            "what": "the reference beside one other process spinning a core, interleaved with the quiet runs",
            **against_reference("busy"),
        }
    if heldout_seeds:
        record["heldout"] = _heldout_pair(data, configs, heldout_seeds, heldout_frames)
    if "compared" in configs:
        record["compare"] = {
            "model": str(compare_model or model_path),
            "overrides": compare_overrides or {},
            **against_reference("compared"),
        }
        if compare_checkout is not None:
            record["compare"]["checkout"] = checkout
    return record


def _time_runs(runs: dict, dataset, test: list[int], repeats: int, progress) -> tuple[dict, dict]:
    """Each of ``runs`` (name: detector) on each frame of ``test``, ``repeats`` times, interleaved
    frame by frame: ``(timings, counts)``, per name each stage's milliseconds and the detections
    kept, run after run. "busy" runs beside a process spinning a core."""
    # One untimed run of each configuration first: numba compiles (or loads) its kernels and torch
    # builds its pools on first use, which would otherwise be timed as the first frame's work.
    for name, detector in runs.items():
        if name != "busy":
            _timed_detection(detector, dataset, test[0])
    timings: dict[str, dict[str, list[float]]] = {name: {} for name in runs}
    counts: dict[str, list[int]] = {name: [] for name in runs}
    total_runs = len(test) * repeats * len(runs)
    done = 0
    for index in test:
        for _ in range(repeats):
            for name, detector in runs.items():
                with _busy_process() if name == "busy" else contextlib.nullcontext():
                    stage_ms, num_detections = _timed_detection(detector, dataset, index)
                for stage, ms in stage_ms.items():
                    timings[name].setdefault(stage, []).append(ms)
                counts[name].append(num_detections)
                done += 1
                if progress is not None:
                    progress(done, total_runs)
    return timings, counts


def _timed_detection(detector, dataset, index: int) -> tuple[dict[str, float], int]:
    """Detect frame ``index`` of ``dataset`` with ``detector`` (a ``Detector`` or a
    ``CheckoutDetector``): its stage times (ms) and the number of detections kept."""
    if isinstance(detector, CheckoutDetector):
        return detector.detect_frame(index)
    result = detector.detect(dataset.frame(index), detector.history(dataset, index))
    return result.timings_ms, int(result.detections.kept_mask.sum())


_CHECKOUT_SCRIPT = """
import json, sys
from factorydet_core.threads import configure_threads
configure_threads()
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.bench import detector_for
from factorydet_core.io.dataset import open_dataset
import factorydet_core
dataset = open_dataset(sys.argv[1])
detector = detector_for(DetectionModel.load(sys.argv[2]), dataset)
print("RESULT " + json.dumps({"package": factorydet_core.__path__[0]}), flush=True)
for line in sys.stdin:
    index = int(line)
    result = detector.detect(dataset.frame(index), detector.history(dataset, index))
    kept = int(result.detections.kept_mask.sum())
    print("RESULT " + json.dumps({"timings_ms": result.timings_ms, "kept": kept}), flush=True)
"""
"""What a ``CheckoutDetector``'s child runs: only calls that every version of the project since
the stage budget has (open a data set, load a model, ``detector_for``, ``detect``)."""


class CheckoutDetector:
    """Another version of this project's code detecting in a child process: ``checkout`` (a
    folder with a ``factorydet_core`` package) comes first on the child's import path, and the
    child loads the model (a shipped one: the checkout's own copy) and the data once, then detects
    the frames it is sent, one at a time.

    Args:
        checkout: the other version's folder.
        data: the data set.
        model_path: the checkpoint both versions detect with.
    """

    def __init__(self, checkout: str | os.PathLike, data: str | os.PathLike, model_path: str | os.PathLike):
        import subprocess
        import sys

        self.checkout = Path(checkout).resolve()
        if not (self.checkout / "factorydet_core" / "__init__.py").is_file():
            raise InputError(f"--compare-checkout: {self.checkout} holds no factorydet_core package")
        path = os.pathsep.join([str(self.checkout), os.environ.get("PYTHONPATH", "")])
        env = {**os.environ, "PYTHONPATH": path}
        self._errors = tempfile.TemporaryFile("w+")  # the child's messages, for its last words
        paths = [str(Path(data).resolve()), str(self._model_for_checkout(model_path))]
        self._child = subprocess.Popen(
            [sys.executable, "-c", _CHECKOUT_SCRIPT, *paths],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._errors,
            text=True,
            env=env,
            cwd=self.checkout,
        )
        try:
            package = Path(self._read()["package"]).resolve()
        except InputError:
            self.close()
            raise
        if package.parent != self.checkout:
            self.close()
            raise InputError(f"--compare-checkout: the child imported {package}, not the checkout's package")

    def _model_for_checkout(self, model_path: str | os.PathLike) -> Path:
        """The checkpoint the child loads (an absolute path: it runs elsewhere). A model shipped in
        this package is the checkout's own copy when it has one: the same weights, with the note
        that version reads (a newer note may name settings it does not know)."""
        import factorydet_core

        path = Path(model_path).resolve()
        package = Path(factorydet_core.__path__[0]).resolve()
        if path.is_relative_to(package):
            own = self.checkout / "factorydet_core" / path.relative_to(package)
            if own.is_file():
                return own
        return path

    def _read(self) -> dict:
        for line in self._child.stdout:
            if line.startswith("RESULT "):
                return json.loads(line[len("RESULT ") :])
        code = self._child.wait()
        self._errors.seek(0)
        last = (self._errors.read().strip().splitlines() or ["no message"])[-1][:300]
        raise InputError(f"--compare-checkout: the child of {self.checkout} ended (exit {code}): {last}")

    def detect_frame(self, index: int) -> tuple[dict[str, float], int]:
        """Stage times (ms) and detections kept of frame ``index``, detected by the other code."""
        self._child.stdin.write(f"{int(index)}\n")
        self._child.stdin.flush()
        out = self._read()
        return {stage: float(ms) for stage, ms in out["timings_ms"].items()}, int(out["kept"])

    def describe(self) -> dict:
        """The checkout's folder and, when it is a git work tree, its commit."""
        import subprocess

        commit = subprocess.run(
            ["git", "-C", str(self.checkout), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
        )
        return {"path": str(self.checkout), "commit": commit.stdout.strip() or None}

    def close(self) -> None:
        """End the child (asked first, killed after a minute) and drop its messages."""
        import subprocess

        if self._child.poll() is None:
            try:
                self._child.stdin.close()
                self._child.wait(timeout=60)
            except (OSError, subprocess.TimeoutExpired):
                self._child.kill()
                self._child.wait()
        self._child.stdout.close()
        self._errors.close()


def _dense_scan(num_points: int, seed: int, scratch: Path) -> Path:
    """A simulated one-frame factory of ``num_points`` points (written to ``scratch`` once)."""
    folder = Path(scratch) / f"dense_seed{seed}_{num_points}pts"
    if not (folder / "manifest.json").is_file():
        simulate_dataset(folder, SimConfig(num_frames=1, seed=seed, points_per_frame=num_points))
    return folder


def detect_once(data: str | os.PathLike, model_path: str | os.PathLike) -> dict:
    """Detect frame 0 of ``data`` with the checkpoint at ``model_path``: the points at each step, the
    stage times, and this process's peak memory (what ``bench_memory`` runs in a child process)."""
    dataset = open_dataset(data)
    model = DetectionModel.load(model_path)
    detector = detector_for(model, dataset, calibrate=False)
    frame = dataset.frame(0)
    start = time.perf_counter()
    result = detector.detect(frame)
    return {
        "points_read": len(frame.points),
        "points_after_crop_prune_cap": result.proposal.cloud.num_points,
        "num_voxels": result.proposal.grid.num_voxels,
        "num_proposals": len(result.proposal.proposals),
        "num_point_sets": result.groups.num_groups,
        "num_detections": int(result.detections.kept_mask.sum()),
        "stage_ms": {stage: round(ms, 1) for stage, ms in result.timings_ms.items()},
        "seconds": round(time.perf_counter() - start, 2),
        "peak_rss_mb": _peak_rss_mb(),
    }


def bench_memory(
    model_path: str | os.PathLike,
    *,
    points: Sequence[int] = (1_000_000, 5_000_000),
    seed: int = 5,
    scratch: str | os.PathLike = "/tmp/factorydet_dense",
    overrides: dict[str, object] | None = None,
    command: str = "",
    progress=None,
) -> dict:
    """Peak memory and time of detecting one dense simulated frame of each size in ``points``, each
    in a fresh child process (its peak is its own: reading, merging and detecting), with the
    front-half settings of the model changed by ``overrides`` (e.g. ``max_points`` to compare the
    uncapped path)."""

    script = (
        "import json, sys\n"
        "from factorydet_core.threads import configure_threads\n"
        "configure_threads()\n"
        "from factorydet_core.evaluation.bench import detect_once\n"
        "print(json.dumps(detect_once(sys.argv[1], sys.argv[2])))\n"
    )
    model = Path(model_path)
    if overrides:
        # The child reads a checkpoint: a copy whose note carries the changed front half.
        changed = DetectionModel.load(model_path)
        changed = dataclasses.replace(
            changed,
            front_end=(changed.front_end or front_end_params(preset_for(12))).replace(**overrides),
        )
        model = Path(scratch) / "overridden" / "model.pt"
        model.parent.mkdir(parents=True, exist_ok=True)
        changed.save(model)
    runs = []
    for done, num_points in enumerate(points):
        folder = _dense_scan(int(num_points), seed, Path(scratch))
        result, error = _child_json(script, [str(folder), str(model)])
        runs.append({"points": int(num_points), **(result if result is not None else {"error": error})})
        if progress is not None:
            progress(done + 1, len(points))
    timed = [r for r in runs if "seconds" in r]
    record = {
        "benchmark": "memory",
        "command": command,
        "model": str(model_path),
        "overrides": overrides or {},
        "runs": runs,
        "target_peak_mb": 2048,
        "machine": machine_info(),
    }
    if len(timed) >= 2:
        first, last = timed[0], timed[-1]
        record["seconds_ratio_largest_to_smallest"] = round(last["seconds"] / first["seconds"], 2)
        record["points_ratio_largest_to_smallest"] = round(last["points"] / first["points"], 2)
    return record


@contextlib.contextmanager
def _busy_process():
    """A child process spinning one core for the duration of the block."""
    import subprocess
    import sys

    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    time.sleep(0.2)  # let it start spinning before the timed work
    try:
        yield
    finally:
        spinner.kill()
        spinner.wait()


BACK_HALF_SETTINGS = INFERENCE_SETTINGS
"""``bench_detect``'s compared settings that belong to the model's back half (the box quality
regressor's inference settings, ``box_quality.INFERENCE_SETTINGS``), not to its front half."""


def _flag(value: object) -> bool:
    """A yes/no setting given on the command line ("0", "false", "no", "off": no)."""
    return str(value).lower() not in ("0", "false", "no", "off")


DETECTOR_SETTINGS = ("skip_unread_features",)
"""``bench_detect``'s compared settings of the ``Detector`` itself (0 computes the proposals' 3DmFV
even for a model that reads none: the path before it was skipped)."""


def _heldout_pair(data: str | os.PathLike, configs: dict, seeds: Sequence[int], num_frames: int) -> dict:
    """Each configuration's headline figures on the held-out factories, and their differences."""
    from factorydet_core.evaluation.quality import (
        HELDOUT_SCRATCH,
        check_heldout,
        heldout_set,
        measure_heldout,
    )

    seeds = check_heldout(seeds, num_frames, open_dataset(data))
    out = {"seeds": list(seeds), "frames_per_factory": num_frames}
    for name, detector in configs.items():
        # Proposed as the configuration's own detections are (``Detector.detect_params``).
        measured = measure_heldout(
            detector.model, heldout_set(seeds, num_frames, HELDOUT_SCRATCH, detector.detect_params)
        )
        head = measured["iou_0.6"]
        out[name] = {key: head[key] for key in ("f1", "map", "precision", "recall")}
        out[name]["back_half_ms_per_frame"] = measured["back_half_ms_per_frame"]
    if "compared" in out:
        out["f1_difference"] = round(out["compared"]["f1"] - out["reference"]["f1"], 4)
        out["map_difference"] = round(out["compared"]["map"] - out["reference"]["map"], 4)
    return out


MINING_TARGET_SECONDS = 300.0
"""The speed issue's target for one hard-negative mining round on the shipped model's 40 training
frames."""
DEMO_NEXT_ROUND_TARGET_SECONDS = 180.0
"""The labelling issue's target for the app's next round on the demo (its 8 training frames)."""
DEMO_FULL_RUN_TARGET_SECONDS = 600.0
"""... and for a full run there."""


def mining_targets(session_name: str) -> dict[str, float]:
    """The targets ``bench mining`` holds a session's round (and full run) to: the labelling
    issue's for the demo's session, the speed issue's round otherwise."""
    from factorydet_core.session.demo import DEMO_SESSION

    if session_name == DEMO_SESSION:
        return {
            "target_seconds": DEMO_NEXT_ROUND_TARGET_SECONDS,
            "target_full_run_seconds": DEMO_FULL_RUN_TARGET_SECONDS,
        }
    return {"target_seconds": MINING_TARGET_SECONDS}


def bench_mining(
    session_name: str,
    *,
    root: str | os.PathLike | None = None,
    data: str | os.PathLike | None = None,
    round_epochs: Sequence[int] = (0, 5),
    full_run: bool = False,
    before_after: bool = False,
    heldout_seeds: Sequence[int] = (),
    heldout_frames: int = 12,
    scratch: str | os.PathLike = "/tmp/factorydet_mining",
    train_args: Sequence[str] = (),
    verdicts: int = 0,
    compared: Sequence[tuple[dict, Sequence[str]]] = (),
    compare_set: Mapping[str, object] | None = None,
    command: str = "",
    progress=None,
) -> dict:
    """Time one more hard-negative mining round of a session (``factorydet train --mode next``),
    once per value of ``round_epochs``, each on a fresh copy of the session (its proposals' cache
    included, so the frames are not proposed again) in a child process of its own, one after the
    other: 0 trains the round afresh and refits the box quality regressor (the paper's round), a
    positive value goes on from the session's model (``loop.continued_model``). The session itself
    is not changed.

    Per configuration: the wall-clock seconds of the whole command and the child's peak memory;
    from the run's record, the seconds of the box quality fit, the classifier's fit and the scoring
    of the training frames (what remains is reading the cached proposals, mining and storing); and,
    with ``heldout_seeds``, the new model's figures on those held-out factories (the quality
    benchmark's, ``quality.heldout_set``). ``train_args`` are more ``factorydet train`` flags for
    both (other training settings).

    Args:
        full_run: first time a full retrain (``--mode full``) on each copy, which the next round
            then continues: what the app's Train does on a session without a run (the demo's).
        before_after: each command also measures the models before and after on the test frames
            (``--compare``), as the app's retrain does.
        verdicts: before the timed round, answer the first this many items of each copy's review
            queue 'object' with their predicted class, as a reviewer's round would: the labels
            change, so the round fits the box quality regressor again (``LoopSettings.refit_box_quality``).
            0: the labels the session has, which a refit meets as they were and keeps.
        compared: instead of ``round_epochs``' configurations, these: each a label (``setting``,
            'reference' or 'compared', and the training ``seed``) and the ``factorydet train``
            flags of its round (in place of ``train_args``), every one going on from the
            session's model for the last of ``round_epochs``. The record then gives, per setting,
            the rounds' median seconds and, with ``heldout_seeds``, the held-out F-scores' mean
            and spread over seeds, and the compared minus the reference seed by seed
            (``hitl.paired_difference``).
        compare_set: what the compared rounds changed (field -> value), for the record.
    """

    from factorydet_core.evaluation.quality import (
        HELDOUT_SCRATCH,
        check_heldout,
        heldout_set,
        measure_heldout,
    )
    from factorydet_core.session.store import copy_session, open_session, training_runs

    values = [int(k) for k in round_epochs]
    if not values or len(set(values)) != len(values) or min(values) < 0:
        raise InputError(
            f"bench mining: round epochs must be distinct integers >= 0, got {list(round_epochs)}"
        )
    session = open_session(session_name, root)
    runs = training_runs(session)
    if not runs and not full_run:
        raise InputError(
            f"bench mining: session {session_name!r} has no training run to go on from (--full-run makes one)"
        )
    script = (
        "import json, sys, time\n"
        "from factorydet_core.cli import main\n"
        "start = time.perf_counter()\n"
        "code = main(sys.argv[1:])\n"
        # Imported after the command: it sizes the thread pools before torch and numba load.
        "from factorydet_core.evaluation.bench import _peak_rss_mb\n"
        "print(json.dumps({'exit': code, 'seconds': round(time.perf_counter() - start, 1),"
        " 'peak_rss_mb': _peak_rss_mb()}))\n"
    )

    def train(copy, mode: str, epochs: int, flags: Sequence[str]) -> dict:
        argv = ["train", *([str(data)] if data is not None else []), "--session", copy.name,
                "--root", str(copy.root), "--mode", mode, *flags,
                *(["--compare"] if before_after else []), "--round-epochs", str(epochs)]  # fmt: skip
        result, error = _child_json(script, argv)
        if result is None:
            raise InputError(f"bench mining: the {mode} run with {epochs} round epochs failed: {error}")
        return result

    # (label, round epochs, train flags, the copy's folder) per configuration
    plan = [({}, epochs, list(train_args), f"round_epochs_{epochs}") for epochs in values]
    if compared:
        if values[-1] == 0:
            raise InputError(
                "bench mining: compared settings go on from the session's model: round epochs > 0"
            )
        plan = [
            (dict(label), values[-1], list(flags), f"compared_{k}")
            for k, (label, flags) in enumerate(compared)
        ]
    configs = []
    heldout = None
    for done, (label, epochs, flags, folder) in enumerate(plan):
        copy = copy_session(session, Path(scratch) / folder)
        full = None
        if full_run:
            child = train(copy, "full", epochs, flags)
            first = training_runs(copy)[-1]
            full = {
                "seconds": child["seconds"],
                "peak_rss_mb": child["peak_rss_mb"],
                "rounds": len(first["rounds"]),
                "run": first["id"],
            }
        if verdicts:
            from factorydet_core.session.store import open_session_data

            db, _ = open_session_data(copy.name, copy.root)
            items = db.review_queue()[:verdicts]
            for item in items:  # one edit each, as the review panel's keys make them
                db.review([item["id"]], "object", "bench", class_name=item["predicted_class"])
            if len(items) < verdicts:
                raise InputError(f"bench mining: the review queue holds {len(items)} items, not {verdicts}")
        child = train(copy, "next", epochs, flags)
        run = training_runs(copy)[-1]
        if epochs and run["config"].get("continued_run") is None:
            why = run["config"].get("afresh_because", "unknown")
            raise InputError(f"bench mining: the round with {epochs} round epochs trained afresh: {why}")
        model = DetectionModel.load(copy.path / run["model_path"])
        (record,) = model.classifier.note_["rounds_record"]
        # The round's own time, one after the other: waiting for the box quality regressor (fitted
        # on a thread of its own alongside the fits), the network's fit, the fold models' fits,
        # the scoring (with the fold models' and the thresholds' tuning).
        parts = {
            key: float(record.get(key) or 0.0)
            for key in ("box_quality_wait_seconds", "fit_seconds", "folds_fit_seconds", "score_seconds")
        }
        config = {
            **label,
            **({"train_args": list(flags)} if compared else {}),  # (the record's own are the base's)
            "round_epochs": epochs,
            "box_quality": record.get("box_quality"),
            "continued": bool(record.get("continued")),
            "epochs": record.get("epochs"),
            "continued_run": run["config"].get("continued_run"),
            "seconds": child["seconds"],
            "box_quality_seconds": round(float(record.get("box_quality_seconds") or 0.0), 1),
            **{key: round(value, 1) for key, value in parts.items()},
            "other_seconds": round(child["seconds"] - sum(parts.values()), 1),
            "peak_rss_mb": child["peak_rss_mb"],
            "num_positives": record["num_positives"],
            "num_background": record["num_background"],
            "train_f1": record["train_f1"],
            "num_train_frames": len(run["train_frames"]),
        }
        if full is not None:
            config["full_run"] = full
        if heldout_seeds:
            if heldout is None:
                seeds = check_heldout(heldout_seeds, heldout_frames, open_dataset(run["data"]))
                params = Detector(model.front_end or "agv", model=model).detect_params
                heldout = heldout_set(seeds, heldout_frames, HELDOUT_SCRATCH, params)
            measured = measure_heldout(model, heldout)["iou_0.6"]
            config["heldout"] = {key: measured[key] for key in ("f1", "map", "precision", "recall")}
        configs.append(config)
        if progress is not None:
            progress(done + 1, len(plan))
    record = {
        "benchmark": "mining",
        "command": command,
        "session": session_name,
        "train_args": list(train_args),
        "before_after": before_after,
        "verdicts": int(verdicts),
        "continues_run": runs[-1]["id"] if runs else None,
        "configs": configs,
        **mining_targets(session_name),
        "machine": machine_info(),
    }
    if heldout_seeds:
        record["heldout"] = {"seeds": [int(s) for s in heldout_seeds], "frames_per_factory": heldout_frames}
    if compared:
        record["compare_set"] = dict(compare_set or {})
        record["comparison"] = _compared_rounds(configs)
    afresh = [c for c in configs if c["round_epochs"] == 0]
    if afresh:
        for config in configs:
            config["speedup_vs_afresh"] = round(afresh[0]["seconds"] / config["seconds"], 2)
            if "heldout" in config:
                config["heldout_f1_minus_afresh"] = round(
                    config["heldout"]["f1"] - afresh[0]["heldout"]["f1"], 4
                )
    return record


def _compared_rounds(configs: Sequence[dict]) -> dict:
    """``bench_mining``'s comparison of its 'reference' and 'compared' rounds: per setting, the
    median seconds and, when measured, the held-out F-score's mean and spread (population
    standard deviation) over seeds; the compared minus the reference, seed by seed."""
    from factorydet_core.evaluation.hitl import paired_difference

    out: dict = {}
    by_seed: dict[str, dict] = {}
    for side in ("reference", "compared"):
        mine = [c for c in configs if c.get("setting") == side]
        by_seed[side] = {c["seed"]: c for c in mine}
        out[side] = {
            "rounds": len(mine),
            "median_seconds": round(float(np.median([c["seconds"] for c in mine])), 1) if mine else None,
            "median_box_quality_seconds": round(float(np.median([c["box_quality_seconds"] for c in mine])), 1)
            if mine
            else None,
        }
        scores = [c["heldout"]["f1"] for c in mine if "heldout" in c]
        if scores:
            out[side]["heldout_f1_mean"] = round(float(np.mean(scores)), 4)
            out[side]["heldout_f1_std"] = round(float(np.std(scores)), 4)
    seeds = sorted(set(by_seed["reference"]) & set(by_seed["compared"]))
    pairs = [(by_seed["compared"][s], by_seed["reference"][s]) for s in seeds]
    out["seeds"] = seeds
    out["seconds_ratio_median"] = (
        round(float(np.median([a["seconds"] / b["seconds"] for a, b in pairs])), 3) if pairs else None
    )
    if pairs and all("heldout" in a and "heldout" in b for a, b in pairs):
        out["heldout_f1_difference"] = paired_difference(
            [a["heldout"]["f1"] for a, _ in pairs], [b["heldout"]["f1"] for _, b in pairs]
        )
    return out


def bench_label_import(
    num_boxes: int = 10_000, num_frames: int = 3, repeats: int = 3, *, large_box: bool = False
) -> dict:
    """Time to import ``num_boxes`` labels (a JSON file, boxes spread over ``num_frames`` frames of
    a small simulated data set) into a fresh session, and to import the same file again (every box
    then repeats a label and is screened out); medians over ``repeats`` fresh sessions.

    Args:
        large_box: add one 100 x 100 m box to the first frame (a hall outline), the case that
            made a screen with one search radius for all boxes quadratic.
    """
    import tempfile

    from factorydet_core.session.labels_io import import_labels
    from factorydet_core.session.store import SessionDB, open_session

    if num_boxes < 1 or num_frames < 1 or repeats < 1:
        raise InputError("bench import: --boxes, --frames and repeats must be at least 1")
    per_frame = -(-num_boxes // num_frames)
    side = int(np.ceil(np.sqrt(per_frame)))
    first, fresh, again = [], [], []
    with tempfile.TemporaryDirectory(prefix="factorydet_import_") as scratch:
        root = Path(scratch)
        config = SimConfig(num_frames=num_frames, seed=0, points_per_frame=4000)
        dataset = open_dataset(simulate_dataset(root / "data", config))
        frames = []
        for frame in range(num_frames):
            count = min(per_frame, num_boxes - frame * per_frame)
            grid = np.arange(max(count, 0))
            boxes = [[3.0 * (g % side) - 1.5 * side, 3.0 * (g // side) - 1.5 * side, 0.5, 1.0, 1.5, 1.0, 0.2]
                     for g in grid]  # fmt: skip
            if large_box and frame == 0:
                boxes.append([0.0, 0.0, 5.0, 100.0, 100.0, 10.0, 0.0])
            frames.append({"frame_index": frame, "boxes": boxes, "labels": ["box"] * len(boxes)})
        labels_file = root / "labels.json"
        labels_file.write_text(json.dumps({"format": "factorydet-labels", "version": 1, "frames": frames}))
        for repeat in range(repeats):
            db = SessionDB(open_session(f"s{repeat}", root / "sessions"), dataset)
            db.ensure_frames(range(num_frames))  # the data set's own labels, imported on first use
            start = time.perf_counter()
            report = import_labels(db, labels_file, "bench")
            fresh.append(time.perf_counter() - start)
            first.append(report["imported"])
            start = time.perf_counter()
            repeat_report = import_labels(db, labels_file, "bench")
            again.append(time.perf_counter() - start)
            if repeat_report["imported"] != 0:
                raise RuntimeError("bench import: a repeated import added labels")
    return {
        "benchmark": "import",
        "num_boxes": num_boxes + int(large_box),
        "large_box": large_box,
        "num_frames": num_frames,
        "repeats": repeats,
        "imported": first,
        "import_seconds_median": round(statistics.median(fresh), 3),
        "reimport_all_duplicates_seconds_median": round(statistics.median(again), 3),
        "target_seconds": 5.0,
        "machine": machine_info(),
    }


def bench_classifier(
    data: str | os.PathLike,
    *,
    widths: list[float],
    features: list[str],
    geometry: Sequence[bool] = (True, False),
    epochs: int = 20,
    max_fit_seconds: float | None = None,
    max_train_frames: int | None = None,
    max_test_frames: int | None = None,
    score_threshold: float = SCORE_THRESHOLD,
    box_quality: bool = True,
    command: str = "",
    progress=None,
    probability_exponent: float = PROBABILITY_EXPONENT,
    quality_trees: int = LoopSettings.quality_trees,
) -> dict:
    """Recognition accuracy (the paper's Table 2) and detection F-score of classifiers of several
    widths, proposal features and inputs (the 3DmFV tensor with or without the geometric
    descriptors), trained on the same training frames (one round, no mining) and measured on the
    same test frames against the truth; with the time per epoch. Every feature and input is
    measured at ``widths[0]``, the other widths on ``features[0]`` with ``geometry[0]``.

    Detections are made as the shipped model makes them: at ``score_threshold``, scored with
    ``probability_exponent``, with one box
    quality regressor (``box_quality``) fitted per feature on the training frames and shared by
    every classifier of that feature, so that the rows differ only in the class probabilities;
    ``quality_trees`` is its size (``LoopSettings.quality_trees``)."""

    dataset = open_dataset(data)
    simulated = (Path(data) / "truth").is_dir()
    train = (dataset.splits.get("train") or [])[:max_train_frames]
    test = (dataset.splits.get("test") or [])[:max_test_frames]
    if not train or not test:
        raise InputError(f"{dataset.name}: bench classifier needs train and test frames")
    preset = preset_for(dataset.num_sensors)
    calibrated = (
        Detector(preset).calibrate(dataset.frame(train[0])).T_vehicle_sensor
        if dataset.num_sensors > 1
        else None
    )
    rows = []
    # Every feature at the first width; the other widths on the first feature only (a full-width
    # network takes minutes per epoch here, and its inference is slow too).
    runs = [(feature, widths[0], g) for feature in features for g in geometry]
    runs += [(features[0], w, geometry[0]) for w in widths[1:]]
    for feature in features:
        detector = Detector(front_end_params(preset, {"feature": feature}), calibrated)
        train_frames = collect_proposals(dataset, train, detector)
        test_frames = collect_proposals(dataset, test, detector)
        quality = None  # fitted with the feature's first classifier, then shared
        for _, width, with_geometry in [r for r in runs if r[0] == feature]:
            classifier = ProposalClassifier(
                width=width, epochs=epochs, max_fit_seconds=max_fit_seconds, geometry=with_geometry
            )
            run = train_with_mining(
                train_frames,
                classifier,
                rounds=0,
                score_threshold=score_threshold,
                box_quality=(BoxQuality(max_iter=quality_trees) if box_quality and quality is None else None),
                probability_exponent=probability_exponent,
            )
            quality = quality or run.model.box_quality
            model = dataclasses.replace(run.model, box_quality=quality)
            fitted = model.classifier
            metrics = measure(model, dataset, test_frames, use_truth=simulated)
            rows.append(
                {
                    "feature": feature,
                    "geometry": with_geometry,
                    "width": width,
                    "num_parameters": fitted.num_parameters_,
                    "epochs_run": len(fitted.history_),
                    "fit_seconds": round(fitted.fit_seconds_, 1),
                    "seconds_per_epoch": round(fitted.fit_seconds_ / max(len(fitted.history_), 1), 1),
                    "final_train_loss": fitted.history_[-1]["loss"],
                    "recognition_mean_class_accuracy": metrics["recognition"]["mean_class_accuracy"],
                    "recognition_overall_accuracy": metrics["recognition"]["overall_accuracy"],
                    "recognition_per_class": {
                        k: v["accuracy"] for k, v in metrics["recognition"]["per_class"].items()
                    },
                    "detection_precision": metrics["precision"],
                    "detection_recall": metrics["recall"],
                    "detection_f1": metrics["f1"],
                    "detection_map": metrics["map"],
                }
            )
            if progress is not None:
                progress(len(rows), len(runs))
    return {
        "benchmark": "classifier",
        "command": command,
        "data": Path(data).name,
        "train_frames": train,
        "test_frames": test,
        "reference": "truth" if simulated else "annotations",
        "epochs": epochs,
        "max_fit_seconds": max_fit_seconds,
        "score_threshold": score_threshold,
        "probability_exponent": probability_exponent,
        "box_quality": box_quality,
        "quality_trees": quality_trees,
        "rows": rows,
        "machine": machine_info(),
    }
