import numpy as np
import pytest

from factorydet_core.evaluation import (
    average_precision,
    detection_metrics,
    match_detections,
    recognition_accuracy,
)

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


def test_recognition_accuracy_table():
    table = recognition_accuracy(np.array([0, 0, 1, 2, 2]), np.array([0, 1, 1, 2, 0]), ("a", "b", "bg"))
    assert table["per_class"]["a"] == {"num": 2, "accuracy": 0.5}
    assert table["per_class"]["b"]["accuracy"] == 1.0
    assert table["mean_class_accuracy"] == pytest.approx((0.5 + 1 + 0.5) / 3, abs=1e-4)
    assert table["overall_accuracy"] == pytest.approx(0.6)
