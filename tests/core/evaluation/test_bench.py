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
