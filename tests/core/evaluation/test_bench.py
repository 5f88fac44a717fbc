import pytest
from hypothesis import given
from hypothesis import strategies as st

from factorydet_core.evaluation.bench import spread_frames
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
        small_dataset_dir, tiny_model_path, max_frames=2, compare_overrides={"voxel_size_m": 0.3}
    )
    stages = record["stage_ms_median"]
    assert "total" in stages and set(record["stage_ms_p90"]) == set(stages)
    assert all(record["stage_ms_p90"][s] >= stages[s] - 0.05 for s in stages)  # rounding to 0.1 ms
    assert record["peak_rss_mb"] > 0
    compare = record["compare"]
    assert compare["overrides"] == {"voxel_size_m": 0.3}
    ratio = compare["ratio_of_medians"]["total"]
    assert ratio == round(compare["stage_ms_median"]["total"] / stages["total"], 3)
    assert "compared / reference" in render_record(record)
