"""``bench scale``'s bookkeeping: the order of its runs, the partial records, and a resumed run that
skips what an earlier record holds. The runs themselves (child processes, Ray) are replaced by a
recorder here; they are the commands the CLI and Ray tests exercise."""

from __future__ import annotations

import pytest

from factorydet_core.scale import bench
from factorydet_core.types import InputError


class FakeRuns:
    """Stands in for ``bench._run_cli``: records each command and answers as the command would;
    ``stop_after`` commands, the next one is interrupted."""

    def __init__(self, stop_after: int | None = None) -> None:
        self.commands: list[list[str]] = []
        self.stop_after = stop_after

    def __call__(self, arguments: list[str], parse: bool = True) -> tuple[dict, float]:
        if self.stop_after is not None and len(self.commands) == self.stop_after:
            raise KeyboardInterrupt
        self.commands.append(arguments)
        workers = int(arguments[arguments.index("--workers") + 1]) if "--workers" in arguments else 1
        frames = int(arguments[arguments.index("--frames") + 1])
        summary = {
            "num_frames": frames,
            "workers": workers,
            "frames_per_second": 0.5 * workers,
            "seconds": frames / (0.5 * workers),
            "startup_seconds": 1.0,
            "median_frame_seconds": 2.0,
            "driver_peak_rss_mb": 500.0 + frames,
            "worker_peak_rss_mb": 1000.0,
        }
        if arguments[0] == "evaluate":
            return {"batch": summary, "reference": "truth", "f1": 0.3, "map": 0.4}, 1.0
        return summary, 1.0


def _run(data, **options) -> dict:
    plan = dict(frame_counts=(1, 3), workers=(1, 2), evaluate_frames=1, command="test")
    return bench.bench_scale(data, **{**plan, **options})


def test_a_stopped_run_resumes_with_the_runs_it_lacks(small_dataset_dir, monkeypatch):
    partials: list[dict] = []
    first = FakeRuns(stop_after=3)
    monkeypatch.setattr(bench, "_run_cli", first)
    with pytest.raises(KeyboardInterrupt):
        _run(small_dataset_dir, on_partial=partials.append)
    # This process, 1 and 2 workers on the fewest frames, then evaluation, then the most frames.
    assert [(c[0], c[c.index("--frames") + 1], "--workers" in c) for c in first.commands] == [
        ("detect", "1", False),
        ("detect", "1", True),
        ("detect", "1", True),
    ]
    assert len(partials) == 3 and not any(p["complete"] for p in partials)
    assert partials[-1]["speedup"] == 2.0 and "driver_memory_growth" not in partials[-1]

    second = FakeRuns()
    monkeypatch.setattr(bench, "_run_cli", second)
    result = _run(small_dataset_dir, earlier=partials[-1])
    assert [c[0] for c in second.commands] == ["evaluate", "detect"]  # only what the record lacked
    assert second.commands[1][second.commands[1].index("--frames") + 1] == "3"
    assert result["complete"] and result["detect"][:3] == partials[-1]["detect"]
    assert [(r["frames"], r["execution"], r["workers"]) for r in result["detect"]] == [
        (1, "in-process", 1),
        (1, "ray", 1),
        (1, "ray", 2),
        (3, "ray", 2),
    ]
    assert result["driver_memory_growth"] == pytest.approx(503 / 501 - 1, abs=1e-3)
    assert result["evaluate"]["f1"] == 0.3
    assert "Speed-up from 1 to the most workers: 2.00x (meets" in bench.scale_markdown(result)

    # A record of another plan is not mixed in.
    with pytest.raises(InputError, match="another plan .*frame_counts"):
        _run(small_dataset_dir, frame_counts=(1, 2), earlier=partials[-1])
    other_model = {**partials[-1], "plan": {**partials[-1]["plan"], "model_sha256": "0" * 64}}
    with pytest.raises(InputError, match="another plan .*model_sha256"):
        _run(small_dataset_dir, earlier=other_model)
    with pytest.raises(InputError, match="not a bench scale record"):
        _run(small_dataset_dir, earlier={"benchmark": "quality"})
