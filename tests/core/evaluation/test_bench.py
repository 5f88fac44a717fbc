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
