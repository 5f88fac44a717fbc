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


def test_margin_sweep_scores_frames_shown_with_points_against_twice_those_without():
    from factorydet_core.evaluation.world_labels import SPURIOUS_WEIGHT, _margin_sweep, margin_score

    counts = {
        "0 cm, 5 cm": [(2, 0), (3, 0), (30, 9), (0, 0), (0, 0)],
        "2 cm, 2 cm": [(2, 1), (3, 2), (30, 12), (0, 1), (0, 0)],
    }
    sweep = _margin_sweep(counts)
    assert sweep["0 cm, 5 cm"]["frames_shown_with_points"] == 1 and sweep["0 cm, 5 cm"]["score"] == 1
    grown = sweep["2 cm, 2 cm"]
    assert (grown["frames_shown_with_points"], grown["frames_shown_without_points"]) == (3, 1)
    assert grown["score"] == 3 - SPURIOUS_WEIGHT == margin_score(3, 1)
    assert grown["shown_by_points"]["1-4"] == 1.0 and grown["shown_without_points"] == 0.5


def test_a_frame_left_out_is_put_down_to_thinning_the_poses_the_floor_or_the_margin():
    import numpy as np

    from factorydet_core.evaluation.world_labels import _miss_cause
    from factorydet_core.session.world import FLOOR_MARGIN_M, SURFACE_MARGIN_M

    true_box = np.array([5.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0])  # stands on the floor, z 0 to 1
    side = np.array([[5.5 + SURFACE_MARGIN_M / 2, 0.0, 0.5]])  # on its +x face, within the margin
    assert _miss_cause(side, true_box, true_box) == "thinning"  # the points were in the carried box
    carried = true_box + np.array([0.3, 0, 0, 0, 0, 0, 0])  # the poses put it 30 cm off
    assert _miss_cause(np.array([[4.55, 0.0, 0.5]]), carried, true_box) == "pose"
    floor = np.array([[5.0, 0.0, FLOOR_MARGIN_M / 2], [5.2, 0.1, FLOOR_MARGIN_M / 3]])
    assert _miss_cause(floor, carried, true_box) == "floor"
    beyond = np.array([[5.5 + 2 * SURFACE_MARGIN_M, 0.0, 0.5], [5.0, 0.0, FLOOR_MARGIN_M / 2]])
    assert _miss_cause(beyond, true_box + np.array([0, 2.0, 0, 0, 0, 0, 0]), true_box) == "margin"
