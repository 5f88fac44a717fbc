import numpy as np

from app.panels.metrics_panel import errors_markdown
from factorydet_core.metrics import error_breakdown

BOX = np.array([0, 0, 0.5, 1, 1, 1, 0.0])


def test_errors_markdown_lists_every_kind_with_its_count_and_f_if_fixed():
    frame = {
        "boxes": np.stack([BOX, BOX + [9, 0, 0, 0, 0, 0, 0]]),
        "class_ids": np.array([0, 0]),
        "scores": np.array([0.9, 0.8]),
        "reference_boxes": np.stack([BOX, BOX + [4, 0, 0, 0, 0, 0, 0]]),
        "reference_class_ids": np.array([0, 0]),
    }
    text = errors_markdown(error_breakdown([frame], ("a",), 0.6, 0.5))
    # One true positive, one background false positive, one miss without a candidate: F 0.5; with
    # the false positive gone 2 / 3, with the miss found (one more detection, a true one) 4 / 5.
    assert "F 0.50 now" in text
    assert "| FP: background | 1 | 0.67 |" in text
    assert "| missed: no candidate | 1 | 0.80 |" in text
    assert "| FP: localization | 0 | 0.50 |" in text


def test_a_class_without_detections_shows_no_precision_and_one_without_references_no_recall():
    from app.panels.metrics_panel import class_row

    missed = {"num_reference": 3, "num_detections": 0, "precision": 0.0, "recall": 0.0, "f1": 0.0, "ap": 0.0}
    assert class_row("cone", missed) == "| cone | 3 | – | 0.00 | 0.00 | 0.00 |"
    unseen = {"num_reference": 0, "num_detections": 2, "precision": 0.0, "recall": None, "f1": None,
              "ap": None}  # fmt: skip
    assert class_row("truck", unseen) == "| truck | 0 | 0.00 | – | – | – |"


def test_the_panel_says_when_its_metrics_are_being_measured_again_and_never_waits_for_them():
    from types import SimpleNamespace

    from app.panels.metrics_panel import MetricsPanel

    row = {"num_reference": 2, "num_detections": 1, "precision": 1.0, "recall": 0.5, "f1": 0.67, "ap": 0.5}
    metrics = {
        "per_class": {"cone": row}, "num_frames": 1, "iou_threshold": 0.6, "score_threshold": 0.5,
        "num_reference": 2, "num_detections": 1, "precision": 1.0, "recall": 0.5, "f1": 0.67, "map": 0.5,
        "pr_curves": {"all": {"recall": np.array([0.5]), "precision": np.array([1.0])}},
    }  # fmt: skip
    shown = [(metrics, True)]

    class State:  # only what the panel reads; ``metrics`` itself would measure (and wait)
        def shown_metrics(self):
            return shown[0]

    panel = MetricsPanel(SimpleNamespace(content=""), SimpleNamespace(data=None), SimpleNamespace(content=""))
    panel.refresh(State())
    assert "| cone | 2 | 1.00 | 0.50 | 0.67 | 0.50 |" in panel.table.content
    assert "Measuring again" in panel.table.content and panel.plot.data is None
    shown[0] = (metrics, False)  # measured: the same figures, no longer out of date, and the curve
    panel.refresh(State())
    assert "Measuring again" not in panel.table.content and panel.plot.data is not None
    shown[0] = (None, True)
    panel.refresh(State())
    assert panel.table.content == "_Measuring the metrics…_"


def test_the_total_row_shows_dashes_where_nothing_was_labelled_or_detected():
    # Frames viewed with detections but no confirmed label (pre-labels only, say): recall and F
    # rest on nothing (None), and the table once failed formatting them.
    import warnings
    from types import SimpleNamespace

    from app.panels.metrics_panel import MetricsPanel
    from factorydet_core.metrics import metrics_from_matches, pool_matches

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the warning that the figures are undefined)
        metrics = metrics_from_matches(pool_matches([], 2), ("cone", "box"), 0.6, 0.5, None)
    metrics.update(num_frames=1)
    assert metrics["recall"] is None and metrics["f1"] is None

    class State:
        def shown_metrics(self):
            return metrics, False

    panel = MetricsPanel(SimpleNamespace(content=""), SimpleNamespace(data=None), SimpleNamespace(content=""))
    panel.refresh(State())
    assert "| **total** | 0 | – | – | **–** | mAP – |" in panel.table.content
