import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from factorydet_core.evaluation.records import spread_frames
from factorydet_core.types import InputError


def test_spread_frames_takes_first_last_and_evenly_between():
    assert spread_frames(range(40), 4) == [0, 13, 26, 39]
    assert spread_frames([8, 9, 10, 11], 2) == [8, 11]
    assert spread_frames([8, 9, 10, 11], None) == [8, 9, 10, 11]
    assert spread_frames([8, 9, 10, 11], 9) == [8, 9, 10, 11]
    with pytest.raises(InputError):
        spread_frames(range(5), 0)


@given(st.integers(1, 80), st.integers(1, 80))
def test_spread_frames_picks_count_distinct_frames_in_order(num_frames, count):
    frames = [3 * i + 1 for i in range(num_frames)]
    picked = spread_frames(frames, count)
    assert len(picked) == min(count, num_frames)
    assert picked == sorted(set(picked)) and set(picked) <= set(frames)
    assert picked[0] == frames[0] and (count == 1 or picked[-1] == frames[-1])


@pytest.mark.slow
def test_bench_detect_profiles_and_compares_side_by_side(small_dataset_dir, tiny_model_path):
    from factorydet_core.evaluation.bench import bench_detect
    from factorydet_core.evaluation.bench_tables import render_record

    record = bench_detect(
        small_dataset_dir, tiny_model_path, max_frames=2, compare_overrides={"voxel_size_m": 0.3}, busy=True
    )
    busy = record["busy"]
    assert set(busy["ratio_of_medians"]) == set(record["stage_ms_median"])
    assert busy["ratio_of_medians"]["total"] > 0
    stages = record["stage_ms_median"]
    assert "total" in stages and set(record["stage_ms_p90"]) == set(stages)
    assert all(record["stage_ms_p90"][s] >= stages[s] - 0.05 for s in stages)  # rounding to 0.1 ms
    assert record["peak_rss_mb"] > 0
    compare = record["compare"]
    assert compare["overrides"] == {"voxel_size_m": 0.3}
    ratio = compare["ratio_of_medians"]["total"]
    assert ratio == round(compare["stage_ms_median"]["total"] / stages["total"], 3)
    assert "compared / reference" in render_record(record)
    assert "busy / quiet" in render_record(record)


@pytest.mark.slow
def test_bench_detect_compares_another_checkout_of_the_code(small_dataset_dir, tiny_model_path, tmp_path):
    import shutil
    from pathlib import Path

    import factorydet_core
    from factorydet_core.evaluation.bench import bench_detect
    from factorydet_core.evaluation.bench_tables import render_record

    # A copy of this code as "another version" (its compiled kernels' cache copied along).
    checkout = tmp_path / "before"
    shutil.copytree(Path(factorydet_core.__path__[0]), checkout / "factorydet_core")
    record = bench_detect(small_dataset_dir, tiny_model_path, max_frames=1, compare_checkout=checkout)
    compare = record["compare"]
    assert compare["checkout"]["path"] == str(checkout.resolve())
    # The same code detects the same objects, and both are timed stage by stage.
    assert compare["detections_per_frame_median"] == record["detections_per_frame_median"]
    assert set(compare["stage_ms_median"]) == set(record["stage_ms_median"])
    assert compare["ratio_of_medians"]["total"] > 0
    assert "the project's code at" in render_record(record)
    with pytest.raises(InputError, match="no factorydet_core"):
        bench_detect(small_dataset_dir, tiny_model_path, max_frames=1, compare_checkout=tmp_path)
    with pytest.raises(InputError, match="code alone"):
        bench_detect(
            small_dataset_dir, tiny_model_path, compare_checkout=checkout, compare_overrides={"prune_m": 0.1}
        )


@pytest.mark.slow
def test_bench_detect_compares_the_box_quality_screen(small_dataset_dir, tmp_path):
    import dataclasses

    from factorydet_core.detection.box_quality import BoxQuality
    from factorydet_core.detection.classifier import ProposalClassifier
    from factorydet_core.detection.detector import Detector
    from factorydet_core.evaluation.bench import bench_detect
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.settings import front_end_params
    from factorydet_core.training.mining import collect_proposals, train_with_mining

    frames = collect_proposals(open_dataset(small_dataset_dir), [0, 1], Detector("agv"))
    run = train_with_mining(
        frames,
        ProposalClassifier(width=0.0625, epochs=2, num_threads=1),
        rounds=0,
        initial_negatives=100,
        box_quality=BoxQuality(max_iter=20, visibility=False),
    )
    model = dataclasses.replace(run.model, front_end=front_end_params("agv"))
    path = model.save(tmp_path / "with_quality.pt")
    record = bench_detect(
        small_dataset_dir, path, max_frames=1, compare_overrides={"screen_trees": 5, "screen_keep": 4}
    )
    compare = record["compare"]
    assert compare["overrides"] == {"screen_trees": 5, "screen_keep": 4}
    assert compare["ratio_of_medians"]["classification"] > 0
    # The reference tree walk (one row at a time) gives the same detections as the fast one.
    frame = open_dataset(small_dataset_dir).frame(0)
    fast = Detector("agv", model=model).detect(frame)
    reference = Detector("agv", model=model.with_box_quality(interleaved_walk=False)).detect(frame)
    assert len(fast.candidates) and len(fast.candidates) == len(reference.candidates)
    np.testing.assert_array_equal(fast.candidates.boxes, reference.candidates.boxes)
    np.testing.assert_array_equal(fast.candidates.scores, reference.candidates.scores)
    record = bench_detect(small_dataset_dir, path, max_frames=1, compare_overrides={"interleaved_walk": 0})
    assert record["compare"]["detections_per_frame_median"] == record["detections_per_frame_median"]
    # A screen needs a regressor to screen with.
    plain = dataclasses.replace(model, box_quality=None).save(tmp_path / "plain.pt")
    with pytest.raises(InputError, match="screen"):
        bench_detect(small_dataset_dir, plain, max_frames=1, compare_overrides={"screen_trees": 5})


@pytest.mark.slow
def test_bench_memory_detects_dense_scans_in_child_processes(tiny_model_path, tmp_path):
    from factorydet_core.evaluation.bench import bench_memory
    from factorydet_core.evaluation.bench_tables import render_record

    record = bench_memory(
        tiny_model_path, points=(20_000, 40_000), scratch=tmp_path, overrides={"max_points": 5_000}
    )
    assert [r["points"] for r in record["runs"]] == [20_000, 40_000]
    for run in record["runs"]:
        assert "error" not in run, run
        assert run["points_read"] >= 0.9 * run["points"]
        assert 0 < run["points_after_crop_prune_cap"] <= 5_000
        assert run["peak_rss_mb"] > 100  # the child's own peak: it imports torch
    assert record["points_ratio_largest_to_smallest"] == 2.0
    assert "peak" in render_record(record).lower()


@pytest.mark.slow
def test_bench_mining_times_a_round_afresh_and_continued_on_session_copies(small_dataset_dir, tmp_path):
    from factorydet_core.evaluation.bench import bench_mining
    from factorydet_core.evaluation.bench_tables import render_record
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.settings import front_end_params
    from factorydet_core.session.store import SessionDB, open_session
    from factorydet_core.training.settings import LoopSettings
    from factorydet_core.workflows import retrain_session

    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("timed", tmp_path / "sessions"), dataset)
    settings = LoopSettings(epochs=1, round_epochs=1, rounds=0, method="paper", box_quality=False,
                            initial_negatives=100)  # fmt: skip
    retrain_session(db, dataset, settings, front_end_params("agv"), mode="full", compare=False,
                    calibrate=False, max_train_frames=2)  # fmt: skip
    before = db.training_runs()
    record = bench_mining(
        "timed", root=tmp_path / "sessions", round_epochs=(0, 1), scratch=tmp_path / "scratch",
        train_args=["--epochs", "1", "--method", "paper", "--no-box-quality", "--frames", "2",
                    "--no-calibrate", "--initial-negatives", "100"],
    )  # fmt: skip
    afresh, continued = record["configs"]
    assert (afresh["continued"], afresh["continued_run"]) == (False, None)
    assert (continued["continued"], continued["epochs"]) == (True, 1)
    assert continued["continued_run"] == before[-1]["id"]
    for config in record["configs"]:
        assert config["num_train_frames"] == 2 and config["peak_rss_mb"] > 100  # the child's own: torch
        assert config["fit_seconds"] > 0 and config["box_quality_seconds"] == 0.0  # no regressor here
        assert config["seconds"] >= config["fit_seconds"] + config["score_seconds"]
    assert continued["speedup_vs_afresh"] == round(afresh["seconds"] / continued["seconds"], 2)
    assert len(db.training_runs()) == len(before)  # the session itself is not changed
    assert "continued, 1 epochs" in render_record(record)
    assert (record["target_seconds"], "target_full_run_seconds" in record) == (300.0, False)  # not the demo
    with pytest.raises(InputError, match="distinct"):
        bench_mining("timed", root=tmp_path / "sessions", round_epochs=(1, 1))
    # A session without a run: a full retrain first (the app's first Train), then the next round.
    SessionDB(open_session("fresh", tmp_path / "sessions"), dataset)
    with pytest.raises(InputError, match="--full-run"):
        bench_mining("fresh", root=tmp_path / "sessions")
    record = bench_mining(
        "fresh", root=tmp_path / "sessions", round_epochs=(1,), full_run=True, scratch=tmp_path / "scratch",
        train_args=["--epochs", "1", "--method", "paper", "--no-box-quality", "--frames", "2",
                    "--no-calibrate", "--initial-negatives", "100", "--rounds", "1"],
        verdicts=2,
    )  # fmt: skip
    (config,) = record["configs"]
    assert config["full_run"]["rounds"] == 2 and config["continued_run"] == config["full_run"]["run"]
    # Two of the full run's queue items answered Object on the copy before its next round.
    copied = SessionDB(open_session("fresh", tmp_path / "scratch" / "round_epochs_1"), dataset)
    assert record["verdicts"] == 2 and copied.review_progress(config["full_run"]["run"])["object"] == 2
    assert not SessionDB(open_session("fresh", tmp_path / "sessions"), dataset).training_runs()
    assert config["full_run"]["seconds"] > 0 and "full run s" in render_record(record)
    # Compared settings: the continued round, each configuration its own flags, from one model.
    base = ["--epochs", "1", "--method", "paper", "--no-box-quality", "--frames", "2", "--no-calibrate",
            "--initial-negatives", "100"]  # fmt: skip
    compared = [
        ({"setting": "reference", "seed": 0}, base),
        ({"setting": "compared", "seed": 0}, [*base, "--negatives", "7"]),
    ]
    record = bench_mining(
        "timed", root=tmp_path / "sessions", round_epochs=(1,), scratch=tmp_path / "scratch",
        compared=compared, compare_set={"negatives_per_round": 7},
    )  # fmt: skip
    reference, other = record["configs"]
    assert (reference["setting"], other["setting"]) == ("reference", "compared")
    assert reference["continued_run"] == other["continued_run"] == before[-1]["id"]
    comparison = record["comparison"]
    assert comparison["seeds"] == [0] and comparison["compared"]["median_seconds"] == other["seconds"]
    assert comparison["seconds_ratio_median"] == round(other["seconds"] / reference["seconds"], 3)
    assert "heldout_f1_difference" not in comparison  # not measured on held-out factories
    text = render_record(record)
    assert "compared, seed 0" in text and "`negatives_per_round=7`" in text
    with pytest.raises(InputError, match="round epochs > 0"):
        bench_mining("timed", root=tmp_path / "sessions", round_epochs=(0,), compared=compared)
