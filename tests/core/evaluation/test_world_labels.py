from factorydet_core.evaluation.world_labels import _shown_shares


def test_shown_shares_count_frames_by_truth_points_at_each_least_count():
    # (truth points, thinned points in the carried box) per object and frame.
    counts = [(1, 0), (2, 1), (4, 2), (10, 3), (60, 40), (0, 0), (0, 1), (0, 0), (0, 0)]
    by_bin, without = _shown_shares(counts, 1)
    assert by_bin == {"1-4": round(2 / 3, 4), "5-19": 1.0, "20-49": None, "50+": 1.0}
    assert without == 0.25
    by_bin, without = _shown_shares(counts, 2)
    assert by_bin["1-4"] == round(1 / 3, 4) and without == 0.0
    by_bin, _ = _shown_shares(counts, 4)
    assert by_bin["1-4"] == 0.0 and by_bin["5-19"] == 0.0 and by_bin["50+"] == 1.0
