"""The report's wording of how a model scores and thresholds its detections."""

import json
import types
from pathlib import Path

import numpy as np
import pytest

from factorydet_core.detection.box_quality import BoxQuality
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
    rng = np.random.default_rng(0)
    quality = BoxQuality(max_iter=7, anchored=False, visibility=False).fit(rng.normal(size=(60, 4)),
                                                                         rng.uniform(size=60))  # fmt: skip
    model = DetectionModel(classifier, score_threshold=0.35, box_quality=quality, probability_exponent=0.5,
                           class_score_thresholds={"barrel": 0.35})  # fmt: skip
    rows = report.voxel_sweep(types.SimpleNamespace(num_sensors=12), model, [0.2, 0.3], [0], [1], None, 0.6)
    assert [row["voxel_size_m"] for row in rows] == [0.2, 0.3]
    assert len(calls) == 2
    for kwargs in calls:
        assert kwargs["probability_exponent"] == 0.5 and kwargs["score_threshold"] == 0.35
        assert kwargs["tune_class_thresholds"]
        # A regressor of the model's size and inputs, fitted again at each size.
        refit = kwargs["box_quality"]
        assert (refit.max_iter, refit.anchored, refit.visibility) == (7, False, False)
        assert not hasattr(refit, "trees_")


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


def _hitl_result(f1_per_seed: dict[str, list[float]], recovered: dict | None = None) -> dict:
    """A ``bench hitl`` record of these variants (two classes, the per-seed totals given)."""
    from factorydet_core.evaluation.hitl import paired_difference

    variants = {}
    for name, values in f1_per_seed.items():
        mean = sum(values) / len(values)
        variants[name] = {
            "f1": mean,
            "map": mean,
            "f1_per_seed": values,
            "f1_std": 0.01,
            "per_class_f1": {"box": mean, "cone": None},
            "num_reviews": 0,
            "reviews": {},
            "unannotated_labelled": 0.0,
            "difference_vs_blind": paired_difference(values, f1_per_seed["blind"]),
        }
    f1 = {name: v["f1"] for name, v in variants.items()}
    gap = f1["full"] - f1["blind"] if "full" in f1 else None
    error = variants["full"]["difference_vs_blind"]["standard_error"] if "full" in f1 else None
    return {
        "command": "factorydet bench hitl x",
        "data": "x",
        "train_frames": [0],
        "test_frames": [1],
        "mining_rounds": 2,
        "iou_threshold": 0.6,
        "seeds": [0, 1, 2],
        "settings": {
            "method": "head_options",
            "epochs": 5,
            "initial_negatives": 10,
            "negatives_per_round": 5,
            "hold_places": True,
        },  # fmt: skip
        "hold_confident": 0.35,
        "queue_max_label_iou": 0.25,
        "variants": variants,
        "f1": f1,
        "recovered": recovered or {},
        "recovered_per_seed": {k: [v, v, v] for k, v in (recovered or {}).items()},
        "gap_full_minus_blind": gap,
        "gap_significant": gap is not None and gap > 2 * error,
        "per_seed": {
            name: [{"f1": f, "map": f + 0.05} for f in values] for name, values in f1_per_seed.items()
        },
    }


def test_the_recovered_shares_interval_holds_the_shares_the_seeds_do_not_reject():
    from scipy import stats

    from factorydet_core.evaluation.hitl import recovered_share

    blind = np.array([0.211, 0.244, 0.214, 0.238, 0.205])
    reviewed = blind + [0.071, 0.056, 0.048, 0.051, 0.065]
    full = blind + [0.073, 0.062, 0.083, 0.041, 0.099]
    result = recovered_share(reviewed, blind, full)
    assert result["share"] == round(0.291 / 0.358, 4) and result["num_seeds"] == 5
    low, high = result["ci95"]
    assert low < result["share"] < high
    critical = stats.t.ppf(0.975, 4)

    def t_of(share):  # Student's t of the per-seed differences (reviewed - blind) - share (full - blind)
        d = (reviewed - blind) - share * (full - blind)
        return abs(d.mean()) / (d.std(ddof=1) / np.sqrt(len(d)))

    # At its ends the seeds reject the share at exactly 5%; inside they do not, outside they do.
    assert t_of(low) == pytest.approx(critical, rel=1e-3) and t_of(high) == pytest.approx(critical, rel=1e-3)
    assert t_of(result["share"]) < 0.01  # the share itself (rounded to 4 places)
    assert t_of(low - 0.05) > critical and t_of(high + 0.05) > critical
    # No gap, one seed, or a gap the seeds cannot tell from 0: no share or no interval.
    assert recovered_share(reviewed, blind, blind)["share"] is None
    assert recovered_share(reviewed[:1], blind[:1], full[:1])["ci95"] is None
    noisy = blind + [0.05, -0.04, 0.06, -0.05, 0.03]
    assert recovered_share(reviewed, blind, noisy)["ci95"] is None


def test_the_hitl_table_states_the_shares_of_the_variants_it_ran():
    from factorydet_core.evaluation.report import hitl_markdown

    # Blind, blind_safe and full only: the gap with its interval and blind_safe's share of it.
    result = _hitl_result(
        {"blind": [0.30, 0.31, 0.29], "blind_safe": [0.31, 0.32, 0.30], "full": [0.34, 0.35, 0.33]}
    )
    text = hitl_markdown(result, heading=False)
    assert "Recovered share of the gap between blind and full labels (0.040 [+0.040, +0.040])" in text
    # Every seed's differences alike: the share's interval is the share itself.
    assert "by `blind_safe`, with no reviewer: 25% [25%, 25%] (target: at least 30%)" in text
    assert "per seed: )" not in text and "reviewer's queue" not in text and "`reviewed_K`" not in text
    assert "their places" in text and "the learned box head classifying" in text
    # The same in mAP (threshold-free), from the record's seeds.
    assert "| mAP minus blind's, per seed: mean [95% interval] | – | +0.010 [+0.010, +0.010] |" in text
    assert "In mAP, the gap between blind and full labels is +0.040 [+0.040, +0.040]" in text
    assert "recovered: blind_safe 25%." in text
    assert "pseudo-label" not in text.lower()
    # Pseudo-labels: what they do said, and how the truth judges those the sessions end with.
    result["settings"]["pseudo_label_confident"] = 0.6
    result["variants"]["blind_safe"]["pseudo_labels"] = {
        "object": 6.0, "loose_box": 2.0, "other_class": 1.0, "skip": 0.0, "background": 1.0,
    }  # fmt: skip
    text = hitl_markdown(result, heading=False)
    assert (
        "blind mining that takes the negatives scoring 0.6 or more, off every label, for labels of their"
        " predicted class until reviewed (pseudo-labels, teaching their class, not their box), holds the"
        " other negatives scoring 0.35 or more out of the background" in text
    )
    assert "their places" in text
    assert (
        "truth judges them: `blind_safe` 10.0: 60% objects of the predicted class (IoU 0.6), 20% that"
        " class's objects under a looser box, 10% another class's objects, 0% objects too sparse for"
        " the annotation policy, 10% no object." in text
    )
    assert "carried" not in text
    # Carried to the other frames that show their objects: said, and those carried judged apart.
    result["settings"]["carry_pseudo_labels"] = True
    result["variants"]["blind_safe"]["pseudo_labels_carried"] = {
        "object": 3.0, "loose_box": 0.0, "other_class": 0.0, "skip": 0.0, "background": 1.0,
    }  # fmt: skip
    text = hitl_markdown(result, heading=False)
    assert "not their box; each of an object that stands still labels it in every training frame" in text
    assert (
        "10% no object (4.0 of them carried from the frame they were mined in to another that shows"
        " their object: 75% objects of the predicted class (IoU 0.6)" in text
    )
    result["hold_confident"] = 0.6
    text = hitl_markdown(result, heading=False)
    assert "holds those on a label that score 0.6 or more" in text and "their places" not in text
    # With a reviewed budget: its share and the queue filter are stated.
    result = _hitl_result(
        {"blind": [0.30, 0.31, 0.29], "reviewed_200": [0.33, 0.34, 0.32], "full": [0.34, 0.35, 0.33]},
        recovered={"200": 0.75},
    )
    result["variants"]["reviewed_200"].update(
        num_reviews=400, reviews={"background": 250.4, "object": 40.2, "wrong_box": 60.0, "skip": 49.4}
    )
    text = hitl_markdown(result, heading=False)
    assert "by the reviews: K = 200: 75% [75%, 75%] (per seed: K = 200: 75%, 75%, 75%)" in text
    # The verdicts that gave a label, what a review order can change.
    assert "| of them, objects and wrong boxes (a label each) | 0 | 100.2 | 0 |" in text
    assert "reviewer's queue hides items" in text and "`blind_safe`" not in text
    assert "classes taking turns" not in text
    # A reviewer holding what it leaves: its share beside the plain reviewer's, what it does said;
    # per-class precision and recall in a table of their own.
    result = _hitl_result(
        {"blind": [0.30, 0.31, 0.29], "reviewed_200": [0.33, 0.34, 0.32],
         "reviewed_safe_200": [0.34, 0.35, 0.33], "reviewed_safe_50": [0.32, 0.33, 0.31],
         "full": [0.34, 0.35, 0.33]},
        recovered={"200": 0.75},
    )  # fmt: skip
    for variant in result["variants"].values():
        variant["per_class_precision"] = {"box": 0.5, "cone": None}
        variant["per_class_recall"] = {"box": 0.25, "cone": None}
    text = hitl_markdown(result, heading=False)
    assert (
        "by `reviewed_safe_200`, the reviews with the rest held: 100% [100%, 100%] (target: at least 80%"
        in text
    )
    assert "by `reviewed_safe_50`, the reviews with the rest held: 50% [50%, 50%]." in text
    assert "`reviewed_safe_K`: the reviewer of `reviewed_K` on top of `blind_safe`" in text
    assert "and the held entries the reviewer does not answer (or skips) stay held" in text
    assert "| box | " + " | ".join(["0.500 / 0.250"] * 5) + " |" in text
    # Late labels: their share too; a class-order cut is said.
    result = _hitl_result(
        {"blind": [0.30, 0.31, 0.29], "full_late": [0.32, 0.33, 0.31], "full": [0.34, 0.35, 0.33]}
    )
    result["settings"]["queue_order"] = "class"
    text = hitl_markdown(result, heading=False)
    assert "by `full_late`, every missing label given after the first fit: 50%" in text
    assert "5 mined per round, the predicted classes taking turns in the cut and in the queue" in text
    assert "refit_box_quality" not in text
    result["settings"]["refit_box_quality"] = True
    assert "every next round fitting the box quality regressor again" in hitl_markdown(result)
    # Thresholds tuned out of fold: said when on (records before the setting existed ran without).
    assert "threshold_folds" not in hitl_markdown(result)
    result["settings"]["threshold_folds"] = 2
    assert "threshold tuned on the training frames in 2 stretches of the drive" in hitl_markdown(result)
    result["settings"]["class_thresholds"] = False  # one threshold: nothing is tuned
    assert "threshold_folds" not in hitl_markdown(result)
    result["settings"].update(class_thresholds=True, threshold_folds=0)
    # The same models at their fitted frames' thresholds, when the record measured them.
    assert "fitted frames" not in hitl_markdown(result)
    from factorydet_core.evaluation.hitl import paired_difference

    blind_fitted = [0.30, 0.30, 0.30]
    for variant in result["variants"].values():
        fitted = [f - 0.01 for f in variant["f1_per_seed"]]
        variant["fitted_frame_thresholds"] = {
            "f1": sum(fitted) / 3,
            "f1_per_seed": fitted,
            "out_of_fold_minus_fitted": paired_difference(variant["f1_per_seed"], fitted),
            "difference_vs_blind": paired_difference(fitted, blind_fitted),
        }
    text = hitl_markdown(result)
    assert "| total F, the same models at thresholds tuned on their fitted frames | 0.290 |" in text
    assert "| the same, F minus blind's, per seed: mean [95% interval] | – |" in text
    row = "| F of out-of-fold thresholds minus the fitted frames', per seed: mean [95% interval] |"
    assert row + " +0.010" in text
    # And at the other objective's out-of-fold thresholds, when the record measured them.
    assert "objective total" not in text and "pooled" not in text
    for variant in result["variants"].values():
        other = [f + 0.02 for f in variant["f1_per_seed"]]
        variant["other_objective_thresholds"] = {
            "objective": "total",
            "f1": sum(other) / 3,
            "f1_per_seed": other,
            "minus_chosen": paired_difference(other, variant["f1_per_seed"]),
        }
    blind_other = result["variants"]["blind"]["other_objective_thresholds"]["f1_per_seed"]
    for variant in result["variants"].values():
        other = variant["other_objective_thresholds"]
        other["difference_vs_blind"] = paired_difference(other["f1_per_seed"], blind_other)
    text = hitl_markdown(result)
    assert "| total F, the same models at out-of-fold thresholds of objective total | 0.320 |" in text
    row = "| F of objective total's out-of-fold thresholds minus the model's, per seed: mean [95% interval] |"
    assert row + " +0.020" in text
    assert "| the same (total), F minus blind's, per seed: mean [95% interval] | – |" in text
    # And at the other objective's fitted frames' thresholds (what no folds give).
    assert "(no folds" not in text
    for variant in result["variants"].values():
        no_folds = [f - 0.03 for f in variant["f1_per_seed"]]
        variant["fitted_frame_other_objective_thresholds"] = {
            "objective": "class",
            "f1": sum(no_folds) / 3,
            "f1_per_seed": no_folds,
            "chosen_minus_these": paired_difference(variant["f1_per_seed"], no_folds),
        }
    blind_no_folds = result["variants"]["blind"]["fitted_frame_other_objective_thresholds"]["f1_per_seed"]
    for variant in result["variants"].values():
        no_folds = variant["fitted_frame_other_objective_thresholds"]
        no_folds["difference_vs_blind"] = paired_difference(no_folds["f1_per_seed"], blind_no_folds)
    text = hitl_markdown(result)
    at = "thresholds of objective class tuned on their fitted frames (no folds)"
    assert f"| total F, the same models at {at} | 0.270 |" in text
    row = "| F of the model's thresholds minus no folds' of objective class, per seed: mean [95% interval] |"
    assert row + " +0.030" in text
    assert "| the same (no folds, class), F minus blind's, per seed: mean [95% interval] | – |" in text
    # ... and the gap there, with the share each variant recovers of it, when it is significant.
    at = "At the thresholds of objective class tuned on the fitted frames (no folds)"
    assert f"{at}, the gap between blind and full labels is +0.040" in text
    assert "more than twice its standard error; recovered: full_late 50% [50%, 50%]." in text
    no_folds = result["variants"]["full"]["fitted_frame_other_objective_thresholds"]
    no_folds["f1_per_seed"] = [0.26, 0.40, 0.24]  # a gap of noise: no share stated
    assert f"{at}, the gap between blind and full labels (+0.030" in hitl_markdown(result)
    assert "is not larger than twice its standard error" in hitl_markdown(result)
    result["settings"]["threshold_objective"] = "total"
    assert "best for the F-score of all classes' detections pooled" in hitl_markdown(result)
    result["settings"]["threshold_objective"] = "class"
    # Object verdicts teaching their class alone: said where a reviewer ran, not otherwise.
    result["settings"]["model_box_targets"] = False
    assert "`model_box_targets` off" not in hitl_markdown(result)  # blind and full labels alone
    reviewed = _hitl_result({"blind": [0.30, 0.31, 0.29], "reviewed_200": [0.32] * 3, "full": [0.34] * 3})
    assert "`model_box_targets` off" not in hitl_markdown(reviewed)
    reviewed["settings"]["model_box_targets"] = False
    assert "an Object verdict's label (the mined box) teaching its class alone" in hitl_markdown(reviewed)
    # The epochs of the first fit and of the rounds that go on from it, when they differ.
    assert ", 5 epochs per fit," in hitl_markdown(result)
    result["settings"].update(epochs=20, round_epochs=5)
    assert ", 20 epochs for the first fit and 5 for each round after it" in hitl_markdown(result)
    result["settings"].update(round_epochs=0)  # every round afresh: the first fit's epochs each
    assert ", 20 epochs per fit," in hitl_markdown(result)
    # A gap within its noise: no share at all.
    result = _hitl_result({"blind": [0.30, 0.31, 0.29], "full": [0.31, 0.30, 0.30]})
    assert "no recovered share is stated" in hitl_markdown(result)
    assert "In mAP, the gap between blind and full labels (+0.003" in hitl_markdown(result)
    assert "no share is stated" in hitl_markdown(result)
    # Without full labels: no gap.
    assert "Full labels were not run here" in hitl_markdown(_hitl_result({"blind": [0.3, 0.3, 0.3]}))


def test_a_hitl_record_says_how_it_cut_and_how_it_ordered_the_review_queue():
    from factorydet_core.evaluation.report import _order_text, hitl_markdown

    assert _order_text("score", None) == "" and _order_text("score", "score") == ""
    assert "in the cut and in the queue" in _order_text("class", None)
    assert "in the cut and in the queue" in _order_text("class", "class")
    split = _order_text("class", "score")
    assert "taking turns in the cut" in split
    assert "most likely an object first (`review_order` score)" in split
    assert "in the review queue (`review_order` class)" in _order_text("score", "class")
    learned = _order_text("class", "learned")
    assert "taking turns in the cut" in learned and "(`review_order` learned)" in learned
    assert _order_text("score", "learned").startswith(", the review queue's places ordered by")
    # A record says what its reviewer saw: nothing of a review order when nobody reviews, and a
    # learned order by item is the cut's (the queue orders places).
    unreviewed = _hitl_result({"blind": [0.2, 0.2, 0.2], "full": [0.3, 0.3, 0.3]})
    unreviewed["settings"] = {**unreviewed["settings"], "queue_order": "score", "review_order": "learned"}
    assert "review_order" not in hitl_markdown(unreviewed)
    by_item = _hitl_result({"blind": [0.2, 0.2, 0.2], "reviewed_200": [0.25] * 3, "full": [0.3] * 3})
    by_item["settings"] = {**by_item["settings"], "queue_order": "class", "review_order": "learned"}
    assert "(`review_order` learned)" in hitl_markdown({**by_item, "review_by": "place"})
    text = hitl_markdown({**by_item, "review_by": "item"})
    assert "review_order" not in text and "taking turns in the cut and in the queue" in text
    # A reviewer by place who looks where the frames see a sparse place best says so.
    assert "see it best" not in hitl_markdown({**by_item, "review_by": "place"})
    best = hitl_markdown({**by_item, "review_by": "place", "review_best_view": True})
    assert "judged where the frames see it best" in best


def test_a_hitl_record_says_what_its_reviewers_queue_held_beyond_the_mined_negatives():
    from factorydet_core.evaluation.report import _extra_text

    assert _extra_text(0) == ""
    assert "every other false positive" in _extra_text(None)
    assert "the next 300 false positives" in _extra_text(300)
    assert "review alone" in _extra_text(None)


def test_the_errors_section_reads_the_kinds_its_record_has(tmp_path):
    from factorydet_core.evaluation.plots import plot_error_breakdown
    from factorydet_core.evaluation.report import _error_lines
    from factorydet_core.metrics import error_breakdown

    # A person inside a truck: a part, now; a record written before the kind existed has none.
    frame = {
        "boxes": np.array([[2.0, 0.5, 0.85, 0.5, 0.5, 1.7, 0.0]]),
        "class_ids": np.array([1]),
        "scores": np.array([0.9]),
        "reference_boxes": np.array([[0.0, 0.0, 1.5, 10.0, 4.0, 3.0, 0.0]]),
        "reference_class_ids": np.array([0]),
    }
    errors = error_breakdown([frame], ("truck", "person"), 0.6, 0.5)
    text = "\n".join(_error_lines(errors, "full truth", tmp_path / "errors.png"))
    assert "| false positive: part | 0 | 1 | 1 |" in text and "*part* when none overlaps it" in text
    old = json.loads(json.dumps(errors))
    for counts in [old["false_positives"], *(row["false_positives"] for row in old["per_class"].values())]:
        counts["background"] += counts.pop("part")
    del old["f1_without"]["part"]
    old_text = "\n".join(_error_lines(old, "full truth", tmp_path / "errors.png"))
    assert (
        "*part*" not in old_text
        and "positive: part" not in old_text
        and "| false positive: background | 0 | 1 | 1 |" in old_text
    )
    for record, png in ((errors, "new.png"), (old, "old.png")):
        plot_error_breakdown(record, tmp_path / png)
        assert (tmp_path / png).stat().st_size > 0


def test_the_hitl_table_counts_a_persons_labels_left_out_as_too_sparse():
    from factorydet_core.evaluation.report import hitl_markdown

    f1 = {"blind": [0.30, 0.31, 0.29], "reviewed_200": [0.32, 0.33, 0.31], "full": [0.34] * 3}
    result = _hitl_result(f1)
    assert "too sparse to learn from" not in hitl_markdown(result, heading=False)
    result["variants"]["reviewed_200"]["sparse_labels_ignored"] = 431.5
    result["variants"]["full"]["sparse_labels_ignored"] = 0.0
    text = hitl_markdown(result, heading=False)
    row = "| a person's labels too sparse to learn from (ignored places, last fit) | – | 431.5 | 0 |"
    assert row in text
    assert "too sparse for the thresholds' tuning" not in text
    result["variants"]["reviewed_200"]["labels_tuning_ignored"] = 120.0
    text = hitl_markdown(result, heading=False)
    tuning = "| a person's labels trained on but too sparse for the thresholds' tuning (last fit) |"
    assert f"{tuning} – | 120 | – |" in text


def test_the_hitl_table_names_the_rows_it_left_out_for_runs_that_lack_them():
    """A row needs every run's figure; runs read back from an older record may lack one, and the
    table says which rows it left out and how many runs measured them."""
    from factorydet_core.evaluation.hitl import OPTIONAL_RUN_FIGURES
    from factorydet_core.evaluation.report import PARTIAL_ROWS, hitl_markdown

    assert set(PARTIAL_ROWS) == set(OPTIONAL_RUN_FIGURES)  # (each named when left out)
    result = _hitl_result({"blind": [0.30, 0.31, 0.29], "full": [0.34, 0.35, 0.33]})
    plain = hitl_markdown(result, heading=False)
    assert "Left out" not in plain  # (no counts: a record from before they were kept)
    for variant in result["variants"].values():
        variant["runs_measuring"] = dict.fromkeys(
            ("per_class_precision", "in_factory", "fitted_frame_thresholds"), 3
        ) | {"other_objective_thresholds": 0, "fitted_frame_other_objective_thresholds": 0}
        variant["in_factory"] = {"f1": 0.4, "map": 0.4, "f1_per_seed": [0.4] * 3}
    assert "Left out" not in hitl_markdown(result, heading=False)  # every run, or none, measured them
    result["variants"]["full"]["runs_measuring"]["in_factory"] = 1
    del result["variants"]["full"]["in_factory"]
    text = hitl_markdown(result, heading=False)
    assert "(in-factory)" not in text
    assert (
        "Left out, as not every run measured them (runs read back from records made before they were"
        " kept): the in-factory F-score (measured by full 1 of 3 runs)." in text
    )
