"""The report's wording of how a model scores and thresholds its detections."""

import types

from factorydet_core.model import DetectionModel
from factorydet_core.report import operating_text


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
