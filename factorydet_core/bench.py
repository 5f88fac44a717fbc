"""Benchmark commands: each prints one JSON object; figures in the README come from here."""

from __future__ import annotations

import json
import os
import platform
import re
import statistics
import time
from pathlib import Path

import numpy as np

from .sim.simulate import FactorySimulator, SimConfig


def machine_info() -> dict:
    """Where a benchmark ran: CPU model, cores, memory, Python and the main libraries."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory_gb = None
    try:
        memory_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    import open3d

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gb": memory_gb,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "open3d": open3d.__version__,
        "os": platform.platform(),
    }


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


def update_readme(readme: str | os.PathLike, result: dict) -> None:
    """Replace the block between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->`` with ``result``."""
    path = Path(readme)
    name = result["benchmark"]
    text = path.read_text()
    block = f"<!-- bench:{name} -->\n```json\n{json.dumps(result, indent=2)}\n```\n<!-- /bench:{name} -->"
    pattern = re.compile(rf"<!-- bench:{name} -->.*?<!-- /bench:{name} -->", re.S)
    if not pattern.search(text):
        raise ValueError(f"{path}: no '<!-- bench:{name} -->' block to update")
    path.write_text(pattern.sub(lambda _: block, text))
