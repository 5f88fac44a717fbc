"""``factorydet bench scale``: batch detection (and evaluation, and simulation) through the
command line users run, in this process and on 1..N Ray workers, timed and measured for memory.

Each run is a child process (``python -m factorydet_core.cli ...``), so that each peak memory is
that run's own and every Ray start-up is paid where a user pays it. Frames per second count from
the first frame handed out to the last received, the workers' own set-up (loading the model)
included; starting Ray and the driver's one-off calibration are not (``startup_seconds`` and the
child's ``wall_seconds`` hold them).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from factorydet_core.evaluation.bench_tables import fmt, register, table
from factorydet_core.evaluation.records import machine_info
from factorydet_core.io.dataset import open_dataset
from factorydet_core.scale.jobs import file_digest
from factorydet_core.scale.runner import RAY_VERSION, Execution
from factorydet_core.session.models import resolve_model
from factorydet_core.sim.simulate import SimConfig
from factorydet_core.types import InputError

SPEEDUP_TARGET = 1.7
"""Issue 28: frames per second of 2 Ray workers over 1 on this 2-core machine."""
MEMORY_GROWTH_TARGET = 0.10
"""Issue 28: the driver's peak memory may grow at most this much from the fewest to the most frames."""


def folder_mb(path: str | os.PathLike) -> float:
    """Disk use of a folder's files (MB)."""
    return round(sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file()) / 2**20, 1)


def _run_cli(arguments: list[str], parse: bool = True) -> tuple[dict, float]:
    """Run ``factorydet ARGUMENTS`` in a child process; its JSON output (``{}`` unless ``parse``)
    and its wall time."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "factorydet_core.cli", *arguments],
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(
            f"factorydet {' '.join(arguments)} failed ({done.returncode}):\n{done.stderr[-3000:]}"
        )
    return (json.loads(done.stdout) if parse else {}), seconds


def _execution_arguments(workers: int | None, worker_threads: int) -> list[str]:
    return Execution(workers=workers, threads=worker_threads).arguments()


def _row(summary: dict, frames: int, workers: int | None, wall_seconds: float) -> dict:
    return {
        "frames": frames,
        "execution": "in-process" if workers is None else "ray",
        "workers": summary["workers"],
        "frames_per_second": summary["frames_per_second"],
        "seconds": summary["seconds"],
        "startup_seconds": summary["startup_seconds"],
        "wall_seconds": round(wall_seconds, 1),
        "median_frame_seconds": summary["median_frame_seconds"],
        "driver_peak_rss_mb": summary["driver_peak_rss_mb"],
        "worker_peak_rss_mb": summary["worker_peak_rss_mb"],
    }


def bench_scale(
    data: str | os.PathLike,
    *,
    model: str = "default",
    frame_counts: Sequence[int] = (100,),
    workers: Sequence[int] = (1, 2),
    in_process: bool = True,
    evaluate_frames: int = 0,
    simulate: SimConfig | None = None,
    worker_threads: int = 1,
    command: str = "",
    progress: Callable[[int, int], None] | None = None,
    earlier: dict | None = None,
    on_partial: Callable[[dict], None] | None = None,
) -> dict:
    """Detection frames per second in this process and on each count of ``workers`` for the first
    of ``frame_counts`` frames; the most workers on every further count (the driver's memory
    against the frame count); optionally evaluation of the first ``evaluate_frames`` test frames,
    and the simulation of ``data`` itself (``simulate``) on the most workers.

    The runs go in that order (simulation, the first count's runs, evaluation, the longer runs),
    each a child process of its own. After each one the record so far (``"complete": false``) goes
    to ``on_partial``; ``earlier``, such a record of the same plan, gives the runs already done,
    which are not run again (a paper-scale run takes hours: it can be done in parts).

    Args:
        data: the data set folder (written first when ``simulate`` is given; an interrupted
            simulation resumes).
        model: what ``--model`` takes.
        frame_counts: increasing frame counts of the detection runs (the first frames of the set).
        workers: Ray worker counts, increasing.
        in_process: also time the plain path (no Ray; the process's own thread pools).
        worker_threads: threads of each Ray worker.
    """
    frame_counts, workers = sorted(set(frame_counts)), sorted(set(workers))
    if not frame_counts or frame_counts[0] < 1 or not workers or workers[0] < 1:
        raise InputError("bench scale needs frame counts and worker counts of at least 1")
    most = workers[-1]
    plan = {
        "data": str(Path(data).resolve()),
        "model": model,
        # By content: a resumed run must not mix the rows of two versions of a named model.
        "model_sha256": file_digest(resolve_model(model)),
        "frame_counts": frame_counts,
        "workers": workers,
        "in_process": in_process,
        "evaluate_frames": evaluate_frames,
        "simulate": None if simulate is None else dataclasses.asdict(simulate),
        "worker_threads": worker_threads,
    }
    done_before = _resumable(plan, earlier)
    runs = [(frame_counts[0], None)] if in_process else []
    runs += [(frame_counts[0], w) for w in workers]
    later = [(n, most) for n in frame_counts[1:]]
    steps = int(simulate is not None) + len(runs) + len(later) + int(evaluate_frames > 0)
    done = 0
    report = progress or (lambda d, n: None)
    report(0, steps)
    result: dict = {
        "benchmark": "scale",
        "command": command,
        "plan": plan,
        "complete": False,
        "machine": machine_info(),
        "ray_version": RAY_VERSION,
        "worker_threads": worker_threads,
        "detect": [],
    }

    def step_done() -> None:
        nonlocal done
        done += 1
        report(done, steps)
        if on_partial is not None:
            on_partial(_finished(result, frame_counts, most))

    if simulate is not None:
        if "simulate" in done_before:
            result["simulate"] = done_before["simulate"]
        else:
            start = time.perf_counter()
            _run_cli(
                ["simulate", "--out", str(data), "--frames", str(simulate.num_frames),
                 "--seed", str(simulate.seed), "--points", str(simulate.points_per_frame),
                 *_execution_arguments(most, worker_threads)],
                parse=False,
            )  # fmt: skip
            summary = json.loads((Path(data) / "summary.json").read_text())
            result["simulate"] = {
                "frames": simulate.num_frames,
                "seed": simulate.seed,
                "points_per_frame": simulate.points_per_frame,
                "workers": summary["workers"],
                "frames_computed": summary["num_computed"],
                "frames_per_second": summary["frames_per_second"],
                "wall_seconds": round(time.perf_counter() - start, 1),
            }
        step_done()
    dataset = open_dataset(data)
    if frame_counts[-1] > dataset.num_frames:
        raise InputError(f"{dataset.name} has {dataset.num_frames} frames, fewer than {frame_counts[-1]}")
    result.update(
        data=dataset.name,
        data_frames=dataset.num_frames,
        data_splits={k: len(v) for k, v in dataset.splits.items()},
        data_points_frame_0=dataset.frame(0).num_points,
        data_disk_mb=folder_mb(data),
    )
    with tempfile.TemporaryDirectory(prefix="factorydet-bench-scale-") as scratch:

        def detect(n: int, w: int | None) -> None:
            key = _run_key(n, w)
            if key in done_before:
                result["detect"].append(done_before[key])
            else:
                out = Path(scratch) / f"detect-{n}-{w or 0}"
                summary, wall = _run_cli(
                    ["detect", str(data), "--model", model, "--out", str(out), "--frames", str(n), "--json",
                     *_execution_arguments(w, worker_threads)],
                )  # fmt: skip
                row = _row(summary, n, w, wall)
                row["output_mb"] = folder_mb(out)
                result["detect"].append(row)
                shutil.rmtree(out, ignore_errors=True)
            step_done()

        for n, w in runs:
            detect(n, w)
        if evaluate_frames > 0:
            if "evaluate" in done_before:
                result["evaluate"] = done_before["evaluate"]
            else:
                out = Path(scratch) / "evaluate"
                evaluation, wall = _run_cli(
                    ["evaluate", str(data), "--model", model, "--out", str(out), "--frames",
                     str(evaluate_frames), *_execution_arguments(most, worker_threads)],
                )  # fmt: skip
                result["evaluate"] = {
                    **_row(evaluation["batch"], evaluation["batch"]["num_frames"], most, wall),
                    "output_mb": folder_mb(out),
                    "reference": evaluation["reference"],
                    "f1": evaluation["f1"],
                    "map": evaluation["map"],
                }
                shutil.rmtree(out, ignore_errors=True)
            step_done()
        for n, w in later:
            detect(n, w)
    result["complete"] = True
    return _finished(result, frame_counts, most)


def _run_key(frames: int, workers: int | None) -> str:
    return f"detect {frames} frames on {'this process' if workers is None else f'{workers} workers'}"


def _resumable(plan: dict, earlier: dict | None) -> dict:
    """What ``earlier`` (a partial record) holds of ``plan``'s runs: "simulate", "evaluate" and
    ``_run_key`` of each detection run -> its entry. A record of another plan is refused."""
    if earlier is None:
        return {}
    if earlier.get("benchmark") != "scale" or not isinstance(earlier.get("plan"), dict):
        raise InputError("bench scale --resume: the earlier record is not a bench scale record")
    if earlier["plan"] != json.loads(json.dumps(plan)):
        changed = sorted(k for k in set(plan) | set(earlier["plan"]) if earlier["plan"].get(k) != plan.get(k))
        raise InputError(
            "bench scale --resume: the earlier record is of another plan (it differs in: "
            f"{', '.join(changed)})"
        )
    done = {k: earlier[k] for k in ("simulate", "evaluate") if k in earlier}
    for row in earlier.get("detect", []):
        done[_run_key(row["frames"], None if row["execution"] == "in-process" else row["workers"])] = row
    return done


def _finished(result: dict, frame_counts: Sequence[int], most: int) -> dict:
    """A copy of ``result`` with the figures derived from its detection runs (the speed-up; the
    driver's memory growth, once the most frames have run)."""
    rows = list(result["detect"])
    out = {**result, "detect": rows}
    ray_first = {r["workers"]: r for r in rows if r["execution"] == "ray" and r["frames"] == frame_counts[0]}
    if 1 in ray_first and most in ray_first and most > 1:
        out["speedup"] = round(ray_first[most]["frames_per_second"] / ray_first[1]["frames_per_second"], 3)
    by_count = [r for r in rows if r["execution"] == "ray" and r["workers"] == most]
    if len(by_count) > 1:
        out["driver_memory_growth"] = round(
            by_count[-1]["driver_peak_rss_mb"] / by_count[0]["driver_peak_rss_mb"] - 1.0, 3
        )
    return out


@register("scale")
def scale_markdown(result: dict) -> str:
    """The runs' table and the two targets' lines."""
    rows = [
        [
            fmt(r["frames"]),
            "this process"
            if r["execution"] == "in-process"
            else f"Ray, {r['workers']} worker{'s' if r['workers'] > 1 else ''}",
            fmt(r["frames_per_second"], 2),
            fmt(r["median_frame_seconds"], 2),
            fmt(r["startup_seconds"], 1),
            fmt(r["driver_peak_rss_mb"], 0),
            fmt(r["worker_peak_rss_mb"], 0),
        ]
        for r in result["detect"]
    ]
    text = table(
        ["frames", "detection on", "frames/s", "s per frame (median)", "start-up s", "driver peak MB",
         "worker peak MB"],
        rows,
    )  # fmt: skip
    lines = [
        text,
        "",
        f"Data: {result['data']}, {fmt(result['data_frames'])} frames of "
        f"{fmt(result['data_points_frame_0'])} points (frame 0), "
        f"{fmt(result['data_disk_mb'], 0)} MB on disk. Ray {result['ray_version']}, "
        f"{result['worker_threads']} thread per worker.",
    ]
    if "speedup" in result:
        verdict = "meets" if result["speedup"] >= SPEEDUP_TARGET else "misses"
        lines.append(
            f"Speed-up from 1 to the most workers: {result['speedup']:.2f}x ({verdict} the "
            f"{SPEEDUP_TARGET}x target)."
        )
    if "driver_memory_growth" in result:
        growth = result["driver_memory_growth"]
        verdict = "meets" if growth <= MEMORY_GROWTH_TARGET else "misses"
        lines.append(
            f"Driver peak memory from the fewest to the most frames: {growth:+.1%} ({verdict} the "
            f"{MEMORY_GROWTH_TARGET:.0%} target)."
        )
    if "simulate" in result:
        sim = result["simulate"]
        lines.append(
            f"Simulating it: {fmt(sim['frames_computed'])} frames at "
            f"{fmt(sim['frames_per_second'], 1)} frames/s on {sim['workers']} workers."
        )
    if "evaluate" in result:
        ev = result["evaluate"]
        lines.append(
            f"Evaluation of {fmt(ev['frames'])} test frames on {ev['workers']} workers: "
            f"{fmt(ev['frames_per_second'], 2)} frames/s, driver peak {fmt(ev['driver_peak_rss_mb'], 0)} MB "
            f"(F {fmt(ev['f1'], 3)}, mAP {fmt(ev['map'], 3)} against the {ev['reference']}; "
            "one shipped model, not a headline figure)."
        )
    return "\n".join(lines)
