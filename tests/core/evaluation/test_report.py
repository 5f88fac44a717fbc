"""The report's wording of how a model scores and thresholds its detections."""

import json
import types
from pathlib import Path

from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.report import operating_text


def _model(**kwargs) -> DetectionModel:
    classifier = types.SimpleNamespace(labels_=["barrel", "truck", "background"])
    return DetectionModel(classifier=classifier, score_threshold=0.35, **kwargs)


def test_operating_text_names_the_score_and_the_thresholds():
    assert operating_text(_model()) == "operating score threshold 0.35"
    quality = object()  # any regressor: only its presence changes the score
    rooted = _model(box_quality=quality, probability_exponent=0.5)
    assert operating_text(rooted) == (
        "score = class probability to the power 0.5 x predicted IoU; operating score threshold 0.35"
    )
    tuned = _model(box_quality=quality, class_score_thresholds={"truck": 0.25})
    assert operating_text(tuned) == (
        "score = class probability x predicted IoU; per-class operating score thresholds, tuned on the "
        "training frames' annotations (truck 0.25; barrel 0.35)"
    )


def test_grid_sweep_retrains_with_the_models_score_settings(monkeypatch):
    from factorydet_core.evaluation import report

    calls = []
    monkeypatch.setattr(report, "collect_proposals", lambda *args, **kwargs: [])
    monkeypatch.setattr(
        report,
        "train_with_mining",
        lambda *args, **kwargs: calls.append(kwargs) or types.SimpleNamespace(model=None),
    )
    monkeypatch.setattr(report, "measure", lambda *args, **kwargs: {"f1": 0.0, "map": 0.0, "per_class": {}})
    classifier = types.SimpleNamespace(labels_=["barrel", "background"], get_params=lambda: {"width": 0.0625})
    model = DetectionModel(classifier, score_threshold=0.35, box_quality=object(), probability_exponent=0.5,
                           class_score_thresholds={"barrel": 0.35})  # fmt: skip
    rows = report.voxel_sweep(types.SimpleNamespace(num_sensors=12), model, [0.2, 0.3], [0], [1], None, 0.6)
    assert [row["voxel_size_m"] for row in rows] == [0.2, 0.3]
    assert len(calls) == 2
    for kwargs in calls:
        assert kwargs["probability_exponent"] == 0.5 and kwargs["score_threshold"] == 0.35
        assert kwargs["tune_class_thresholds"] and kwargs["box_quality"] is not None


def test_the_report_names_the_back_half_and_shows_the_held_out_table(tmp_path):
    from factorydet_core.detection.box_head import BoxHead
    from factorydet_core.evaluation import report

    head = BoxHead(class_names=("barrel", "truck"))
    head.num_parameters_ = 1234
    assert "box head" in report.model_text(DetectionModel(head)) and "1,234" in report.model_text(
        DetectionModel(head)
    )
    with_options = DetectionModel(head, box_quality=object())
    assert with_options.method == "head_options" and "box quality" in report.model_text(with_options)
    assert report.METHOD_LABELS[with_options.method] == "box head + options"
    # The committed benchmark record, as `factorydet bench quality` wrote it.
    quality = json.loads((Path(__file__).parents[3] / "docs" / "bench" / "quality.json").read_text())
    lines = report.heldout_lines(quality)
    assert lines[1].startswith("## Held-out factories")
    assert "| " + " | ".join(quality["methods"]) + " |" in "\n".join(lines)
