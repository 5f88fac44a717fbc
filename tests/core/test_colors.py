import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.colors import _display_ranks, thin_for_display


@settings(max_examples=60, deadline=None)
@given(
    num_points=st.integers(0, 3000),
    keep_share=st.floats(0.0, 1.0),
    budgets=st.tuples(st.integers(0, 3000), st.integers(0, 3000)),
    seed=st.integers(0, 2**16),
)
def test_thinning_keeps_the_budget_of_the_kept_points_nested_and_fixed(num_points, keep_share, budgets, seed):
    keep_mask = np.random.default_rng(seed).random(num_points) < keep_share
    small, large = sorted(budgets)
    thin_small = thin_for_display(keep_mask, small)
    thin_large = thin_for_display(keep_mask, large)
    assert thin_small.shape == keep_mask.shape and thin_small.dtype == bool
    assert not (thin_small & ~keep_mask).any()  # only points that were kept
    assert thin_small.sum() == min(small, keep_mask.sum())
    assert not (thin_small & ~thin_large).any()  # a smaller budget only takes points away
    _display_ranks.cache_clear()  # the same cloud thins the same way, not by a cached draw
    assert (thin_for_display(keep_mask, small) == thin_small).all()
    assert (thin_for_display(keep_mask, None) == keep_mask).all()


def test_thinning_spreads_over_the_cloud():
    # Thinning must not keep one end of the cloud (a prefix would draw half the hall).
    keep_mask = np.ones(80_000, bool)
    thin = thin_for_display(keep_mask, 20_000)
    counts = np.bincount(np.flatnonzero(thin) // 10_000, minlength=8)
    assert counts.min() > 2_200 and counts.max() < 2_800


def test_thinning_refuses_a_negative_budget_and_a_mask_of_another_shape():
    with pytest.raises(ValueError, match="at least 0"):
        thin_for_display(np.ones(5, bool), -1)
    with pytest.raises(ValueError, match=r"\(N,\)"):
        thin_for_display(np.ones((5, 2), bool), 3)
