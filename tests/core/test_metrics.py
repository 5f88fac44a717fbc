import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from factorydet_core.metrics import (
    CLASS_THRESHOLD_GRID,
    average_precision,
    detection_metrics,
    error_breakdown,
    match_detections,
    recognition_accuracy,
    tune_class_thresholds,
)
from factorydet_core.types import InputError

BOX = np.array([0, 0, 0.5, 1, 1, 1, 0.0])


def shifted(dx: float) -> np.ndarray:
    return BOX + [dx, 0, 0, 0, 0, 0, 0]


def test_match_is_greedy_by_score_and_class_aware():
    refs = np.stack([BOX, shifted(5)])
    ref_classes = np.array([0, 1])
    boxes = np.stack([shifted(0.1), BOX, shifted(5), shifted(10)])
    tp, matched = match_detections(
        boxes, np.array([0, 0, 0, 1]), np.array([0.5, 0.9, 0.8, 0.7]), refs, ref_classes, 0.6
    )
    # The best-scoring exact box takes reference 0; the shifted duplicate is then a false positive;
    # the box on reference 1 has the wrong class; the last box overlaps nothing.
    assert tp.tolist() == [False, True, False, False]
    assert matched.tolist() == [-1, 0, -1, -1]


def test_average_precision_hand_computed():
    # Detections by score: TP, FP, TP with 2 references: recall 0.5, 0.5, 1; precision 1, 0.5, 2/3.
    # Interpolated: 1 up to recall 0.5, then 2/3 up to 1: AP = 0.5 + 0.5 * 2/3.
    recall = np.array([0.5, 0.5, 1.0])
    precision = np.array([1.0, 0.5, 2 / 3])
    assert average_precision(recall, precision) == pytest.approx(0.5 + 1 / 3)
    assert average_precision(np.array([]), np.array([])) == 0.0


def test_detection_metrics_per_class_and_totals():
    frames = [
        {
            "boxes": np.stack([BOX, shifted(3), shifted(6)]),
            "class_ids": np.array([0, 0, 1]),
            "scores": np.array([0.9, 0.8, 0.3]),
            "reference_boxes": np.stack([BOX, shifted(6), shifted(9)]),
            "reference_class_ids": np.array([0, 1, 1]),
        },
        {
            "boxes": np.zeros((0, 7)),
            "class_ids": np.zeros(0, int),
            "scores": np.zeros(0),
            "reference_boxes": np.stack([BOX]),
            "reference_class_ids": np.array([0]),
        },
    ]
    m = detection_metrics(frames, ("a", "b", "c"), iou_threshold=0.6, score_threshold=0.5)
    a, b = m["per_class"]["a"], m["per_class"]["b"]
    assert (a["tp"], a["num_detections"], a["num_reference"]) == (1, 2, 2)
    assert a["precision"] == 0.5 and a["recall"] == 0.5 and a["f1"] == 0.5
    assert a["ap"] == pytest.approx(0.5)
    # Class b's only detection scores below the operating threshold: no detections there, but AP
    # still counts it (1 of 2 references at precision 1).
    assert (b["tp"], b["num_detections"]) == (0, 0) and b["f1"] == 0.0
    assert b["ap"] == pytest.approx(0.5)
    assert m["per_class"]["c"]["ap"] is None
    assert m["map"] == pytest.approx(0.5)
    assert m["precision"] == 0.5 and m["recall"] == pytest.approx(0.25) and m["num_reference"] == 4
    assert m["f1"] == pytest.approx(1 / 3, abs=1e-4)
    assert set(m["pr_curves"]) == {"a", "b", "all"}
    assert m["pr_curves"]["all"]["recall"][-1] == pytest.approx(0.5)


def test_error_breakdown_gives_every_error_its_kind():
    # References: class 0 at x = 0 (found), 10 (no candidate), 20 (a candidate below the
    # threshold), 30 (a candidate above it, suppressed); class 1 at x = 40.
    refs = np.stack([shifted(0), shifted(10), shifted(20), shifted(30), shifted(40)])
    ref_classes = np.array([0, 0, 0, 0, 1])
    kept = {
        # tp on 0; a duplicate on 0; a box half off 0... shifted 0.5 m (IoU 1/3): localization;
        # class 0 on the class-1 reference: confusion; class 1 far from everything: background;
        # a low scorer below the threshold, not counted.
        "boxes": np.stack([shifted(0), shifted(0.05), shifted(0.5), shifted(40), shifted(60), shifted(80)]),
        "class_ids": np.array([0, 0, 0, 0, 1, 0]),
        "scores": np.array([0.9, 0.8, 0.7, 0.6, 0.6, 0.2]),
    }
    frame = {
        **kept,
        "reference_boxes": refs,
        "reference_class_ids": ref_classes,
        "candidate_boxes": np.stack([shifted(0), shifted(20.05), shifted(30.05), shifted(40)]),
        "candidate_class_ids": np.array([0, 0, 0, 0]),
        "candidate_scores": np.array([0.9, 0.3, 0.8, 0.6]),
    }
    errors = error_breakdown([frame], ("a", "b"), iou_threshold=0.6, score_threshold=0.5)
    assert errors["per_class"]["a"]["false_positives"] == {
        "duplicate": 1, "localization": 1, "confusion": 1, "part": 0, "background": 0
    }  # fmt: skip
    assert errors["per_class"]["b"]["false_positives"]["background"] == 1
    assert errors["per_class"]["a"]["misses"] == {"no_candidate": 1, "below_threshold": 1, "suppressed": 1}
    # The class-1 reference has only a class-0 candidate: no candidate of its class.
    assert errors["per_class"]["b"]["misses"] == {"no_candidate": 1, "below_threshold": 0, "suppressed": 0}
    assert (errors["tp"], errors["num_detections"], errors["num_reference"]) == (1, 5, 5)
    assert (errors["per_class"]["a"]["tp"], errors["per_class"]["a"]["num_reference"]) == (1, 4)
    # The same operating point as detection_metrics.
    assert errors["f1"] == pytest.approx(detection_metrics([frame], ("a", "b"), 0.6, 0.5)["f1"], abs=1e-4)
    # Removing the one background false positive: 2 * 1 / (4 + 5).
    assert errors["f1_without"]["background"] == pytest.approx(2 / 9, abs=1e-4)
    # Finding the two no-candidate misses: 2 * 3 / (7 + 5).
    assert errors["f1_without"]["no_candidate"] == pytest.approx(0.5, abs=1e-4)
    # Per-class thresholds: with class 0's at 0.1 the low scorer counts (a background FP at x = 80)
    # and the x = 20 candidate is no longer below the threshold.
    lowered = error_breakdown([frame], ("a", "b"), 0.6, 0.5, np.array([0.1, np.nan]))
    assert lowered["per_class"]["a"]["false_positives"]["background"] == 1
    assert lowered["per_class"]["a"]["misses"]["below_threshold"] == 0
    # A reference of a class the detector does not know is not counted, as in detection_metrics.
    unknown = {**frame, "reference_boxes": np.concatenate([refs, [shifted(100)]]),
               "reference_class_ids": np.append(ref_classes, 2)}  # fmt: skip
    assert error_breakdown([unknown], ("a", "b"), 0.6, 0.5)["num_reference"] == 5
    assert detection_metrics([unknown], ("a", "b"), 0.6, 0.5)["num_reference"] == 5
    # Without candidates every miss is "no candidate".
    bare = {k: v for k, v in frame.items() if not k.startswith("candidate_")}
    assert error_breakdown([bare], ("a", "b"), 0.6, 0.5)["misses"] == {
        "no_candidate": 4, "below_threshold": 0, "suppressed": 0
    }  # fmt: skip


def test_a_false_positive_inside_a_larger_object_is_a_part_not_background():
    # A 10 x 4 x 3 m truck; a 0.5 x 0.5 x 1.7 m "person" standing inside it (IoU 0.004, all of its
    # volume inside); one that pokes 60% of its width out of the truck's side (40% inside); one
    # far from everything.
    truck = np.array([0.0, 0.0, 1.5, 10.0, 4.0, 3.0, 0.3])
    inside = np.array([2.0, 0.5, 0.85, 0.5, 0.5, 1.7, 0.0])
    side = truck[:2] + np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]) @ [0, 2.05]
    poking = np.array([side[0], side[1], 0.85, 0.5, 0.5, 1.7, 0.3])
    frame = {
        "boxes": np.stack([inside, poking, inside + [30, 0, 0, 0, 0, 0, 0]]),
        "class_ids": np.array([1, 1, 1]),
        "scores": np.array([0.9, 0.8, 0.7]),
        "reference_boxes": truck[None],
        "reference_class_ids": np.array([0]),
    }
    errors = error_breakdown([frame], ("truck", "person"), iou_threshold=0.6, score_threshold=0.5)
    assert errors["per_class"]["person"]["false_positives"] == {
        "duplicate": 0, "localization": 0, "confusion": 0, "part": 1, "background": 2
    }  # fmt: skip
    # Once a reference of another class overlaps it at IoU 0.1, it is a confusion, not a part.
    small_truck = np.array([2.0, 0.5, 0.85, 0.8, 0.8, 1.7, 0.0])
    confused = error_breakdown(
        [{**frame, "reference_boxes": small_truck[None]}], ("truck", "person"), 0.6, 0.5
    )
    assert confused["per_class"]["person"]["false_positives"]["confusion"] == 1
    assert confused["per_class"]["person"]["false_positives"]["part"] == 0


def _two_scale_frames() -> list[dict]:
    """Class 0 (barrels, say) scores high, right or wrong; class 1 (trucks) scores low even when
    right. Ten frames: each has a true class-0 box at 0.8, a false one at 0.5, and a true class-1
    box at 0.25 plus a false one at 0.12."""
    frames = []
    for k in range(10):
        x = 20.0 * k
        frames.append(
            {
                "boxes": np.stack([shifted(x), shifted(x + 3), shifted(x + 6), shifted(x + 9)]),
                "class_ids": np.array([0, 0, 1, 1]),
                "scores": np.array([0.8, 0.5, 0.25, 0.12]),
                "reference_boxes": np.stack([shifted(x), shifted(x + 6)]),
                "reference_class_ids": np.array([0, 1]),
            }
        )
    return frames


def test_tuned_thresholds_give_each_class_its_best_operating_point():
    frames = _two_scale_frames()
    names = ("barrel", "truck", "cone")
    tuned = tune_class_thresholds(frames, names, 0.6, grid=(0.1, 0.2, 0.3, 0.6, 0.9))
    # Barrels: 0.6 drops their false positives (0.1 to 0.3 keep them, 0.9 drops everything);
    # trucks: 0.2 keeps the true ones and drops the false; cones have no references.
    assert tuned[0] == 0.6 and tuned[1] == 0.2 and np.isnan(tuned[2])
    one = detection_metrics(frames, names, 0.6, 0.3)
    per_class = detection_metrics(frames, names, 0.6, 0.3, tuned)
    assert one["per_class"]["truck"]["f1"] == 0.0 and one["per_class"]["barrel"]["f1"] < 1.0
    assert per_class["per_class"]["truck"]["f1"] == 1.0 and per_class["per_class"]["barrel"]["f1"] == 1.0
    assert per_class["f1"] == 1.0 and one["f1"] < 0.7
    assert per_class["class_score_thresholds"] == {"barrel": 0.6, "truck": 0.2, "cone": 0.3}
    # Capped at the global threshold, barrels keep the cap; trucks still go below it.
    capped = tune_class_thresholds(frames, names, 0.6, grid=(0.1, 0.2, 0.3, 0.6, 0.9), max_threshold=0.3)
    assert capped[0] == 0.1 and capped[1] == 0.2
    # Each class's figures are those of a single threshold at its own value.
    for name, threshold in (("barrel", 0.6), ("truck", 0.2)):
        alone = detection_metrics(frames, names, 0.6, threshold)["per_class"][name]
        assert per_class["per_class"][name] == alone
    with pytest.raises(InputError, match="3 values"):
        detection_metrics(frames, names, 0.6, 0.3, np.array([0.5, 0.5]))
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        detection_metrics(frames, names, 0.6, 0.3, np.array([0.5, 1.5, np.nan]))


def _weak_class_frames() -> list[dict]:
    """Ten frames: each has a class-0 object detected right at 0.8, and a class-1 object whose
    detection misses it at 0.2; frame 0's class-1 object is also found at 0.15."""
    frames = []
    for k in range(10):
        x = 20.0 * k
        boxes = [shifted(x), shifted(x + 9)] + ([shifted(x + 6)] if k == 0 else [])
        frames.append(
            {
                "boxes": np.stack(boxes),
                "class_ids": np.array([0, 1] + ([1] if k == 0 else [])),
                "scores": np.array([0.8, 0.2] + ([0.15] if k == 0 else [])),
                "reference_boxes": np.stack([shifted(x), shifted(x + 6)]),
                "reference_class_ids": np.array([0, 1]),
            }
        )
    return frames


def test_pooled_objective_holds_a_weak_class_up_where_its_own_f_floods():
    frames, names, grid = _weak_class_frames(), ("barrel", "pallet", "cone"), (0.1, 0.2, 0.3, 0.6, 0.9)
    own = tune_class_thresholds(frames, names, 0.6, grid=grid)
    pooled = tune_class_thresholds(frames, names, 0.6, grid=grid, objective="total", untuned_threshold=0.3)
    # Pallets' own F is best at 0.1 (1 match among 11 detections); pooled, the 10 misses
    # cost more than the match gives, so 0.3 (none of them) is best. Barrels stay; cones untuned.
    assert own[1] == 0.1 and pooled[1] == 0.3
    assert own[0] == pooled[0] == 0.1 and np.isnan(own[2]) and np.isnan(pooled[2])
    at_own = detection_metrics(frames, names, 0.6, 0.3, own)
    at_pooled = detection_metrics(frames, names, 0.6, 0.3, pooled)
    assert at_pooled["f1"] == pytest.approx(2 * 10 / (10 + 20), abs=1e-4)
    assert at_own["f1"] == pytest.approx(2 * 11 / (21 + 20), abs=1e-4) and at_own["f1"] < at_pooled["f1"]
    assert at_own["per_class"]["pallet"]["f1"] > at_pooled["per_class"]["pallet"]["f1"] == 0.0
    with pytest.raises(InputError, match="untuned_threshold"):
        tune_class_thresholds(frames, names, 0.6, objective="total")
    with pytest.raises(InputError, match="class, total"):
        tune_class_thresholds(frames, names, 0.6, objective="micro")


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 2), st.booleans(), st.floats(0.05, 0.95), st.integers(0, 2)),
        min_size=1,
        max_size=30,
    ),
    st.sampled_from([0.1, 0.35, 0.5]),
)
def test_pooled_objective_never_lowers_the_pooled_f(detections, untuned):
    """Whatever the detections, the pooled objective's thresholds give a pooled F at least that of
    each class's own best: it starts from them and moves only upwards in pooled F."""
    frames = []
    for k, (class_id, is_true, score, num_extra_references) in enumerate(detections):
        x = 20.0 * k
        references = [shifted(x)] if is_true else []
        references += [shifted(x + 6 + 3 * j) for j in range(num_extra_references)]
        frames.append(
            {
                "boxes": shifted(x)[None],
                "class_ids": np.array([class_id]),
                "scores": np.array([score]),
                "reference_boxes": np.stack(references) if references else np.zeros((0, 7)),
                "reference_class_ids": np.full(len(references), class_id),
            }
        )
    assume(any(len(frame["reference_class_ids"]) for frame in frames))
    names = ("barrel", "pallet", "cone")
    own = tune_class_thresholds(frames, names, 0.6)
    pooled = tune_class_thresholds(frames, names, 0.6, objective="total", untuned_threshold=untuned)
    assert np.array_equal(np.isnan(own), np.isnan(pooled))
    f_own = detection_metrics(frames, names, 0.6, untuned, own)["f1"]
    f_pooled = detection_metrics(frames, names, 0.6, untuned, pooled)["f1"]
    assert f_pooled >= f_own - 1e-4  # the metrics are rounded to 4 decimals
    # And no single class's move along the grid raises the pooled F that detection_metrics gives.
    for c in np.flatnonzero(np.isfinite(pooled)):
        for threshold in CLASS_THRESHOLD_GRID:
            moved = pooled.copy()
            moved[c] = threshold
            assert detection_metrics(frames, names, 0.6, untuned, moved)["f1"] <= f_pooled + 1e-4


def test_pooled_objective_keeps_the_ceiling_and_an_empty_grid():
    frames, names = _weak_class_frames(), ("barrel", "pallet", "cone")
    grid = (0.1, 0.2, 0.3, 0.6, 0.9)
    capped = tune_class_thresholds(
        frames, names, 0.6, grid=grid, max_threshold=0.2, objective="total", untuned_threshold=0.2
    )
    # Under a ceiling of 0.2 pallets cannot climb above their misses at 0.2 (as they do without
    # it, to 0.3); 0.2 keeps the misses and drops the match, so they stay at 0.1.
    assert capped[0] == 0.1 and capped[1] == 0.1
    # No grid value under the ceiling: nothing is tuned, as with each class's own objective.
    for objective in ("class", "total"):
        none = tune_class_thresholds(
            frames, names, 0.6, grid=grid, max_threshold=0.05, objective=objective, untuned_threshold=0.05
        )
        assert np.isnan(none).all()


def test_recognition_accuracy_table():
    table = recognition_accuracy(np.array([0, 0, 1, 2, 2]), np.array([0, 1, 1, 2, 0]), ("a", "b", "bg"))
    assert table["per_class"]["a"] == {"num": 2, "accuracy": 0.5}
    assert table["per_class"]["b"]["accuracy"] == 1.0
    assert table["mean_class_accuracy"] == pytest.approx((0.5 + 1 + 0.5) / 3, abs=1e-4)
    assert table["overall_accuracy"] == pytest.approx(0.6)


def test_metrics_without_references_are_undefined_not_zero():
    frames = [
        {
            "boxes": np.array([[0, 0, 0.5, 1, 1, 1, 0.0]]),
            "class_ids": np.array([0]),
            "scores": np.array([0.9]),
            "reference_boxes": np.zeros((0, 7)),
            "reference_class_ids": np.zeros(0, np.int64),
        }
    ]
    with pytest.warns(UserWarning, match="undefined"):
        metrics = detection_metrics(frames, ("a", "b"), 0.6, 0.5)
    assert metrics["f1"] is None and metrics["recall"] is None and metrics["map"] is None
    assert metrics["precision"] == 0.0 and metrics["num_reference"] == 0
    assert metrics["per_class"]["a"]["f1"] is None and metrics["per_class"]["a"]["num_detections"] == 1


def test_detections_on_ignored_objects_are_neither_right_nor_wrong():
    reference = np.array([[0, 0, 0.5, 1, 1, 1, 0.0]])
    sparse = np.array([[5, 0, 0.5, 1, 1, 1, 0.0]])
    frame = {
        "boxes": np.vstack([reference, sparse + [0.1, 0, 0, 0, 0, 0, 0], [[9, 9, 0.5, 1, 1, 1, 0]]]),
        "class_ids": np.array([0, 0, 0]),
        "scores": np.array([0.9, 0.8, 0.7]),
        "reference_boxes": reference,
        "reference_class_ids": np.array([0]),
    }
    plain = detection_metrics([frame], ("a",), 0.6, 0.5)
    assert plain["num_detections"] == 3 and plain["precision"] == pytest.approx(1 / 3, abs=1e-4)
    ignored = detection_metrics([frame | {"ignore_boxes": sparse}], ("a",), 0.6, 0.5)
    # The detection on the sparse object is dropped; the one on nothing stays a false positive.
    assert ignored["num_detections"] == 2 and ignored["precision"] == pytest.approx(0.5)
    assert ignored["recall"] == plain["recall"] == 1.0
    # A true positive is never dropped, even where an ignored box overlaps it.
    tp_only = detection_metrics([frame | {"ignore_boxes": reference}], ("a",), 0.6, 0.5)
    assert tp_only["per_class"]["a"]["tp"] == 1


def _empty_frame(num_references: int = 0) -> dict:
    return {
        "boxes": np.zeros((0, 7)),
        "class_ids": np.zeros(0, np.int64),
        "scores": np.zeros(0),
        "reference_boxes": np.tile([0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0], (num_references, 1)),
        "reference_class_ids": np.zeros(num_references, np.int64),
    }


def test_the_per_frame_parts_pool_to_the_whole_measurement_and_nothing_pools_to_nothing():
    from factorydet_core.metrics import (
        errors_from_counts,
        frame_error_counts,
        frame_matches,
        metrics_from_matches,
        pool_matches,
    )

    box = [0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0]
    found = {
        **_empty_frame(1),
        "boxes": np.array([box, [5.0, 5.0, 0.5, 1.0, 1.0, 1.0, 0.0]]),
        "class_ids": np.array([0, 1]),
        "scores": np.array([0.9, 0.7]),
    }
    frames = [found, _empty_frame(2)]  # a true and a false positive; two misses
    parts = [frame_matches(f, 2, 0.6) for f in frames]
    assert parts[0][1].tolist() == [True, False] and parts[1][3].tolist() == [2, 0]
    assert metrics_from_matches(pool_matches(parts, 2), ("a", "b")) == detection_metrics(frames, ("a", "b"))
    thresholds = np.full(2, 0.5)
    counts = [frame_error_counts(f, 2, 0.6, thresholds) for f in frames]
    assert errors_from_counts(counts, ("a", "b"), 0.6) == error_breakdown(frames, ("a", "b"), 0.6, 0.5)
    assert errors_from_counts(counts, ("a", "b"), 0.6)["misses"]["no_candidate"] == 2
    scores, tps, classes, num_reference = pool_matches([], 2)
    assert (len(scores), len(tps), len(classes), num_reference.tolist()) == (0, 0, 0, [0, 0])
    assert errors_from_counts([], ("a", "b"), 0.6)["num_reference"] == 0


def test_metrics_without_references_warn_at_their_caller():
    from factorydet_core.metrics import metrics_from_matches, pool_matches

    for measure in (
        lambda: detection_metrics([_empty_frame()], ("a",)),
        lambda: metrics_from_matches(pool_matches([], 1), ("a",)),
    ):
        with pytest.warns(UserWarning, match="without any reference instance") as caught:
            measure()
        assert caught[0].filename == __file__
