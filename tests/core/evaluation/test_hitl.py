import dataclasses

from factorydet_core.evaluation.hitl import _run_plan, _seed_settings, _settings_as_run, _variant_specs, holds
from factorydet_core.training.settings import BEFORE_THEY_EXISTED, LoopSettings


def test_a_record_without_a_setting_ran_as_before_the_setting_existed():
    left_out = {*BEFORE_THEY_EXISTED, "seed", "num_threads"}  # a record keeps neither of the last two
    settings = {k: v for k, v in dataclasses.asdict(LoopSettings()).items() if k not in left_out}
    filled = _settings_as_run(settings)
    assert {k: filled[k] for k in BEFORE_THEY_EXISTED} == BEFORE_THEY_EXISTED
    assert "seed" not in filled and "num_threads" not in filled
    # A setting the record has is kept as it ran.
    assert _settings_as_run({**settings, "queue_order": "class"})["queue_order"] == "class"


def test_each_detectors_run_plan_leaves_out_what_cannot_shape_its_runs():
    settings = dataclasses.asdict(LoopSettings())
    plan = {"data": "d", "seeds": [0], "variants": ["blind"], "budgets": [50], "review_by": "place",
            "queue_max_label_iou": 0.25, "settings": settings}  # fmt: skip
    held = {**settings, "hold_places": True, "recalibrate_background": 0.5,
            "refit_box_quality": not settings["refit_box_quality"]}  # fmt: skip
    other = {**plan, "seeds": [1, 2], "variants": ["blind", "blind_safe"], "budgets": [200],
             "review_by": "item", "settings": held}  # fmt: skip
    assert _run_plan(plan, "blind") == _run_plan(other, "blind")
    assert _run_plan(plan, "full") == _run_plan(other, "full")
    assert _run_plan(plan, "blind_safe") != _run_plan(other, "blind_safe")  # holds places, recalibrates
    assert _run_plan(plan, "reviewed_200") != _run_plan(other, "reviewed_200")  # reviews by item
    # Reviews alike but the regressor refitted: the reviewed runs differ, blind's do not.
    refit = {**plan, "settings": {**settings, "refit_box_quality": not settings["refit_box_quality"]}}
    assert _run_plan(plan, "reviewed_200") != _run_plan(refit, "reviewed_200")
    assert _run_plan(plan, "full_late") != _run_plan(refit, "full_late")  # its labels change
    assert _run_plan(plan, "blind") == _run_plan(refit, "blind")
    assert _run_plan(plan, "blind") != _run_plan({**plan, "data": "e"}, "blind")
    # The regressor's size shapes every detector that fits one, and none that does not.
    smaller = {**plan, "settings": {**settings, "quality_trees": 30}}
    assert _run_plan(plan, "blind") != _run_plan(smaller, "blind")
    for no_regressor in ({"box_quality": False, "method": "paper"}, {"method": "box_head"}):
        without = {**plan, "settings": {**settings, **no_regressor}}
        assert _run_plan(without, "blind") == _run_plan(
            {**without, "settings": {**without["settings"], "quality_trees": 30}}, "blind"
        )
    # Going on from the fold models shapes every detector with folds and next rounds.
    folds = {**plan, "mining_rounds": 2, "settings": {**settings, "threshold_folds": 2, "round_epochs": 5}}
    afresh = {**folds, "settings": {**folds["settings"], "continue_folds": False}}
    assert _run_plan(folds, "blind") != _run_plan(afresh, "blind")
    for no_next in ({"mining_rounds": 0}, {"settings": {**folds["settings"], "round_epochs": 0}},
                    {"settings": {**folds["settings"], "threshold_folds": 0}}):  # fmt: skip
        other_way = {**folds, **no_next}
        flipped = {**other_way, "settings": {**other_way["settings"], "continue_folds": False}}
        assert _run_plan(other_way, "blind") == _run_plan(flipped, "blind")
    # Recalibrating by class is blind_safe's alone too.
    by_class = {**plan, "settings": {**held, "recalibrate_by_class": True}}
    assert _run_plan({**plan, "settings": held}, "blind_safe") != _run_plan(by_class, "blind_safe")
    assert _run_plan({**plan, "settings": held}, "reviewed_200") == _run_plan(by_class, "reviewed_200")
    # Whether the model's boxes are learnt from: only a reviewer's verdicts give labels with them.
    class_alone = {**plan, "settings": {**settings, "model_box_targets": not settings["model_box_targets"]}}
    for variant in ("blind", "blind_safe", "full", "full_late"):
        assert _run_plan(plan, variant) == _run_plan(class_alone, variant)
    for variant in ("reviewed_200", "reviewed_safe_200"):
        assert _run_plan(plan, variant) != _run_plan(class_alone, variant)
    # A reviewer who also holds what they leave: shaped by the reviews and by the holding both.
    holding = {**plan, "settings": {**settings, "hold_places": True, "recalibrate_background": 0.5}}
    assert _run_plan(plan, "reviewed_safe_200") != _run_plan(holding, "reviewed_safe_200")
    assert _run_plan(holding, "reviewed_safe_200") != _run_plan(
        {**holding, "review_by": "item"}, "reviewed_safe_200"
    )
    assert _run_plan(holding, "reviewed_safe_200") != _run_plan(by_class, "reviewed_safe_200")
    # The review queue's own order shapes the reviewed detectors alone.
    by_chance = {**plan, "settings": {**settings, "queue_order": "class", "review_order": "score"}}
    turns = {**plan, "settings": {**settings, "queue_order": "class", "review_order": None}}
    for variant in ("blind", "blind_safe", "full", "full_late"):
        assert _run_plan(by_chance, variant) == _run_plan(turns, variant)
    for variant in ("reviewed_200", "reviewed_safe_200"):
        assert _run_plan(by_chance, variant) != _run_plan(turns, variant)
    # None reviews in the queue order: the same runs as naming it.
    named = {**plan, "settings": {**settings, "queue_order": "class", "review_order": "class"}}
    assert _run_plan(named, "reviewed_200") == _run_plan(turns, "reviewed_200")
    # A record from before the setting reviewed in its queue order (review_order None).
    old = {k: v for k, v in turns["settings"].items() if k != "review_order"}
    assert _run_plan({**turns, "settings": _settings_as_run(old)}, "reviewed_200") == _run_plan(
        turns, "reviewed_200"
    )
    # Today's default learns the order from the verdicts: other runs than the queue order's.
    learned = {**plan, "settings": {**settings, "queue_order": "class"}}
    assert settings["review_order"] == "learned"
    assert _run_plan(learned, "reviewed_200") != _run_plan(turns, "reviewed_200")
    assert _run_plan(learned, "blind") == _run_plan(turns, "blind")
    # ... by place: by item a learned order is the cut's (the queue orders places), the same runs.
    assert _run_plan({**learned, "review_by": "item"}, "reviewed_200") == _run_plan(
        {**turns, "review_by": "item"}, "reviewed_200"
    )
    # So do the false positives queued for review alone; a record from before them queued none.
    longer = {**plan, "settings": {**settings, "review_extra": None}}
    for variant in ("blind", "blind_safe", "full", "full_late"):
        assert _run_plan(longer, variant) == _run_plan(plan, variant)
    for variant in ("reviewed_200", "reviewed_safe_200"):
        assert _run_plan(longer, variant) != _run_plan(plan, variant)
    before = {k: v for k, v in settings.items() if k != "review_extra"}
    assert _settings_as_run(before)["review_extra"] == 0


def test_each_detector_trains_with_what_its_run_plan_says_shapes_it():
    settings = LoopSettings(hold_places=True, recalibrate_background=0.5, review_extra=None)
    for name in ("blind", "full", "full_late", "blind_safe"):
        assert _seed_settings(settings, name, 3, None).review_extra == 0  # nobody reviews their queue
    for name in ("reviewed_200", "reviewed_safe_200"):
        assert _seed_settings(settings, name, 3, None).review_extra is None
    blind, safe = _seed_settings(settings, "blind", 3, None), _seed_settings(settings, "blind_safe", 3, 0.35)
    assert blind.seed == safe.seed == 3 and safe.hold_confident == 0.35
    assert (blind.hold_places, blind.recalibrate_background) == (False, None)
    assert (safe.hold_places, safe.recalibrate_background) == (True, 0.5)
    # Pseudo-labels are the holding detectors' alone, and shape their runs alone.
    pseudo = dataclasses.replace(settings, pseudo_label_confident=0.6)
    assert _seed_settings(pseudo, "blind", 3, None).pseudo_label_confident is None
    assert _seed_settings(pseudo, "reviewed_200", 3, None).pseudo_label_confident is None
    assert _seed_settings(pseudo, "blind_safe", 3, 0.35).pseudo_label_confident == 0.6
    plan = {"data": "d", "seeds": [0], "variants": ["blind"], "budgets": [200], "review_by": "place",
            "settings": dataclasses.asdict(settings)}  # fmt: skip
    with_pseudo = {**plan, "settings": dataclasses.asdict(pseudo)}
    for variant in ("blind", "full", "reviewed_200"):
        assert _run_plan(plan, variant) == _run_plan(with_pseudo, variant)
    for variant in ("blind_safe", "reviewed_safe_200"):
        assert _run_plan(plan, variant) != _run_plan(with_pseudo, variant)
    # Pseudo-labels are labels with the model's box: whether those teach boxes shapes blind_safe.
    boxes = {**with_pseudo, "settings": {**with_pseudo["settings"], "model_box_targets": True}}
    assert _run_plan(boxes, "blind_safe") != _run_plan(with_pseudo, "blind_safe")
    # Carrying them is the holding detectors' too, and shapes nothing without pseudo-labels.
    carry = dataclasses.replace(pseudo, carry_pseudo_labels=True)
    assert not _seed_settings(carry, "blind", 3, None).carry_pseudo_labels
    assert not _seed_settings(carry, "reviewed_200", 3, None).carry_pseudo_labels
    assert _seed_settings(carry, "reviewed_safe_200", 3, 0.35).carry_pseudo_labels
    with_carry = {**plan, "settings": dataclasses.asdict(carry)}
    assert _run_plan(with_carry, "blind_safe") != _run_plan(with_pseudo, "blind_safe")
    assert _run_plan(with_carry, "blind") == _run_plan(with_pseudo, "blind")
    carry_alone = {
        **plan,
        "settings": dataclasses.asdict(dataclasses.replace(settings, carry_pseudo_labels=True)),
    }
    assert _run_plan(carry_alone, "blind_safe") == _run_plan(plan, "blind_safe")
    no_pseudo_boxes = {**plan, "settings": {**plan["settings"], "model_box_targets": True}}
    assert _run_plan(no_pseudo_boxes, "blind_safe") == _run_plan(plan, "blind_safe")


def test_the_holding_detectors_are_asked_for_by_name_and_hold_at_the_plans_score():
    default = [name for name, _, _ in _variant_specs([50, 200], 0.3, default=True)]
    assert default == ["blind", "blind_safe", "reviewed_50", "reviewed_200", "full"]
    every = {name: (budget, hold) for name, budget, hold in _variant_specs([50, 200], 0.3, default=False)}
    assert every["reviewed_safe_200"] == (200, 0.3) and every["blind_safe"] == (0, 0.3)
    assert every["reviewed_200"] == (200, None) and every["full_late"] == (0, None)
    assert [name for name in every if holds(name)] == ["blind_safe", "reviewed_safe_50", "reviewed_safe_200"]


def test_the_reviewers_best_view_shapes_the_reviewed_runs_alone_and_old_records_reviewed_without_it():
    from factorydet_core.evaluation.hitl import REVIEW_COUNTS, VERDICTS, compare_hitl_records

    settings = dataclasses.asdict(LoopSettings())
    plan = {"data": "d", "seeds": [0], "variants": ["blind"], "budgets": [200], "review_by": "place",
            "queue_max_label_iou": 0.25, "settings": settings, "review_best_view": False}  # fmt: skip
    best = {**plan, "review_best_view": True}
    for variant in ("blind", "blind_safe", "full", "full_late"):
        assert _run_plan(best, variant) == _run_plan(plan, variant)
    for variant in ("reviewed_200", "reviewed_safe_200"):
        assert _run_plan(best, variant) != _run_plan(plan, variant)
    # A record from before the field: resumed as reviewed without the best view (``_resumable_runs``).
    old = {k: v for k, v in plan.items() if k != "review_best_view"}
    assert _run_plan({"review_best_view": False, **old}, "reviewed_200") == _run_plan(plan, "reviewed_200")
    # The best view is a count beside the verdicts, not a verdict of its own.
    assert set(VERDICTS) < set(REVIEW_COUNTS) and "best_view" not in VERDICTS
    runs = {
        "blind": [{"seed": 0, "f1": 0.2, "map": 0.3}],
        "reviewed_200": [{"seed": 0, "f1": 0.25, "map": 0.3}],
    }
    record = {"benchmark": "hitl", "data": "d", "train_frames": [0], "test_frames": [1], "seeds": [0],
              "per_seed": runs, "plan": best}  # fmt: skip
    older = {**record, "plan": old}
    assert compare_hitl_records(record, older)["differs"] == {"review_best_view": [True, False]}
    assert compare_hitl_records({**record, "plan": plan}, older)["differs"] == {}


def test_the_best_view_is_refused_without_places(small_dataset_dir):
    import pytest

    from factorydet_core.evaluation.hitl import bench_hitl
    from factorydet_core.types import InputError

    with pytest.raises(InputError, match="--review-by place"):
        bench_hitl(small_dataset_dir, best_view=True, review_by="item")


def test_a_resume_with_training_to_do_reads_back_only_the_runs_of_this_library():
    import warnings

    import pytest

    from factorydet_core.evaluation.hitl import _HitlPlan, _resumable_runs
    from factorydet_core.evaluation.records import library_version, library_versions

    version = library_version()
    assert len(version) == 12 and int(version, 16) >= 0 and library_version() == version
    plan = _HitlPlan(None, "d", [0], [1], [200], 2, LoopSettings(), [0, 1, 2], None, True, "",
                     variants=["blind", "full"])  # fmt: skip

    def run(seed, library):
        return {"seed": seed, "f1": 0.2, **({"library": library} if library else {})}

    other = "0123456789ab"
    per_seed = {
        "blind": [run(0, version), run(1, other), run(2, None)],
        "full": [run(0, version), run(1, other)],  # seed 2's full labels still to train
    }
    earlier = {"benchmark": "hitl", "plan": plan.record(), "per_seed": per_seed}
    counted = library_versions([*per_seed["blind"], *per_seed["full"]])
    assert counted == {version: 2, other: 2, "unknown": 1} and list(counted.values()) == [2, 2, 1]
    # Training to do: the runs of other code (or of code the record did not keep) train again,
    # and the user is told why.
    with pytest.warns(UserWarning, match="3 of the earlier record's runs ran another version"):
        kept = _resumable_runs(plan, earlier)
    assert set(kept) == {(0, "blind"), (0, "full")}
    # ... unless asked to read them back.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert set(_resumable_runs(plan, earlier, other_library=True)) == {
            (0, "blind"), (1, "blind"), (2, "blind"), (0, "full"), (1, "full")
        }  # fmt: skip
        # A record with nothing to train is rendered as it is, whatever code its runs ran.
        one_seed = dataclasses.replace(plan, seeds=[1])
        assert set(_resumable_runs(one_seed, earlier)) == {(1, "blind"), (1, "full")}


def test_runs_of_other_records_of_the_plan_join_the_earlier_ones():
    import pytest

    from factorydet_core.evaluation.hitl import _HitlPlan, _resumable_runs
    from factorydet_core.evaluation.records import library_version
    from factorydet_core.types import InputError

    plan = _HitlPlan(None, "d", [0], [1], [200], 2, LoopSettings(), [0, 1, 2], None, True, "",
                     variants=["blind", "full"])  # fmt: skip

    def run(seed, f1, library=None):
        return {"seed": seed, "f1": f1, "library": library or library_version()}

    def record(per_seed, **changes):
        return {"benchmark": "hitl", "plan": {**plan.record(), **changes}, "per_seed": per_seed}

    here = record({"blind": [run(0, 0.1), run(2, 0.5, "0123456789ab")]})
    there = record(
        {"blind": [run(0, 0.9), run(1, 0.2), run(2, 0.6)], "full": [run(1, 0.3), run(2, 0.4)]}, seeds=[1]
    )
    runs = _resumable_runs(plan, here, also={"b.json": there})
    # The earlier record's own run comes first, a run of this library before one of another; the
    # others' runs it lacks join it (what is left to train: seed 0's full labels).
    assert {key: run["f1"] for key, run in runs.items()} == {
        (0, "blind"): 0.1, (1, "blind"): 0.2, (2, "blind"): 0.6, (1, "full"): 0.3, (2, "full"): 0.4
    }  # fmt: skip
    assert [r["f1"] for r in here["per_seed"]["blind"]] == [0.1, 0.5]  # (the records are not changed)
    # No record at --out yet: the others' runs alone.
    assert set(_resumable_runs(plan, None, also={"b.json": there})) == set(runs)
    # A record of another plan (one that touches every detector) is refused, by its name.
    other = record({"blind": [run(1, 0.2)]}, mining_rounds=3)
    with pytest.raises(InputError, match="other.json ran another plan"):
        _resumable_runs(plan, here, also={"other.json": other})
    # A record with no runs adds nothing, whatever it ran (the earlier record's run of another
    # library, with training to do, trains again).
    with pytest.warns(UserWarning, match="1 of the earlier record's runs ran another version"):
        alone = _resumable_runs(plan, here, also={"empty.json": record({}, variants=["blind"])})
    assert set(alone) == {(0, "blind")}
    # One that is not a hitl record is refused.
    with pytest.raises(InputError, match="q.json is not a resumable bench hitl record"):
        _resumable_runs(plan, here, also={"q.json": {"benchmark": "quality", "plan": {}}})
    with pytest.raises(InputError, match="q.json is not a resumable"):
        _resumable_runs(plan, here, also={"q.json": [1, 2]})


def test_records_and_compares_say_when_their_runs_ran_other_code():
    from factorydet_core.evaluation.bench_tables import hitl_compare_table
    from factorydet_core.evaluation.hitl import compare_hitl_records
    from factorydet_core.evaluation.report import _library_note

    assert _library_note({}) == _library_note({"unknown": 4}) == ""  # records before the field
    assert _library_note({"aaaaaaaaaaaa": 6}) == " Every run ran one version of the library."
    mixed = _library_note({"aaaaaaaaaaaa": 4, "unknown": 2})
    assert "The 6 runs ran 2 versions of the library" in mixed and "2 of a version not kept" in mixed

    def record(libraries):
        runs = [{"seed": s, "f1": 0.2, "map": 0.3, "library": lib} for s, lib in enumerate(libraries)]
        return {"benchmark": "hitl", "data": "d", "train_frames": [0], "test_frames": [1],
                "seeds": [0, 1], "per_seed": {"blind": runs}, "plan": {}}  # fmt: skip

    ours = record(["aaaaaaaaaaaa", "aaaaaaaaaaaa"])
    same = compare_hitl_records(ours, record(["aaaaaaaaaaaa", "aaaaaaaaaaaa"]))
    assert same["variants"]["blind"]["library"] == {"same": 2, "other": 0, "unknown": 0}
    assert hitl_compare_table(same).endswith("Every pair of runs ran one version of the library.")
    other = compare_hitl_records(ours, record(["aaaaaaaaaaaa", "bbbbbbbbbbbb"]))
    assert other["variants"]["blind"]["library"] == {"same": 1, "other": 1, "unknown": 0}
    assert "1 of the 2 pairs of runs ran two versions of the library" in hitl_compare_table(other)
    unknown = compare_hitl_records(ours, record([None, None]))
    assert unknown["variants"]["blind"]["library"]["unknown"] == 2
    assert "version of the library" not in hitl_compare_table(unknown)


def test_the_label_points_floor_shapes_the_reviewers_runs_alone():
    # Only a reviewer makes labels the floor checks: blind mining and full labels have the data
    # set's and imported ones.
    settings = dataclasses.asdict(LoopSettings(label_min_points=None))  # the policy's floor
    plan = {"data": "d", "seeds": [0], "variants": ["blind"], "budgets": [50], "review_by": "place",
            "queue_max_label_iou": 0.25, "settings": settings}  # fmt: skip
    every_label = {**plan, "settings": {**settings, "label_min_points": 0, "threshold_label_min_points": 0}}
    # (the thresholds' floor on every label's training: a floor of its own)
    tuned = {**every_label, "settings": {**every_label["settings"], "threshold_label_min_points": None}}
    untuned = {**tuned, "settings": {**tuned["settings"], "class_thresholds": False}}
    for variant in ("blind", "blind_safe", "full", "full_late"):
        assert _run_plan(plan, variant) == _run_plan(every_label, variant) == _run_plan(every_label, variant)
        assert _run_plan(every_label, variant) == _run_plan(tuned, variant)
    for variant in ("reviewed_200", "reviewed_safe_200"):
        assert _run_plan(plan, variant) != _run_plan(every_label, variant)
        assert _run_plan(every_label, variant) != _run_plan(tuned, variant)
        # Without per-class thresholds nothing is tuned: the floor cannot shape the run.
        no_floor = {**untuned, "settings": {**untuned["settings"], "threshold_label_min_points": 0}}
        assert _run_plan(untuned, variant) == _run_plan(no_floor, variant)


def _pool_record(factories, per_seed_f1, frames=12, **settings_changes):
    """A complete bench hitl record on held-out ``factories`` with these F-scores per detector."""
    settings = {**dataclasses.asdict(LoopSettings()), **settings_changes}
    plan = {"data": "d", "seeds": [0, 1, 2], "variants": list(per_seed_f1), "budgets": [200],
            "review_by": "place", "queue_max_label_iou": 0.25, "settings": settings,
            "heldout": {"seeds": list(factories), "frames": frames}}  # fmt: skip
    per_seed = {
        name: [{"seed": seed, "f1": f1} for seed, f1 in enumerate(values)]
        for name, values in per_seed_f1.items()
    }
    return {"benchmark": "hitl", "complete": True, "plan": plan, "per_seed": per_seed}


def test_records_on_disjoint_factories_pool_their_f_scores_seed_by_seed():
    import pytest

    from factorydet_core.evaluation.bench_tables import render_record
    from factorydet_core.evaluation.hitl import pool_hitl_records, recovered_share
    from factorydet_core.types import InputError

    first = _pool_record(
        [111, 112],
        {"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.23, 0.25, 0.24], "full": [0.24, 0.26, 0.25]},
    )
    second_f1 = {"blind": [0.30, 0.28, 0.29], "reviewed_200": [0.31, 0.30, 0.30], "full": [0.34, 0.32, 0.33]}
    second = _pool_record([121, 122], second_f1, frames=24)
    pooled = pool_hitl_records([first, second], names=["a.json", "b.json"])
    # Weighted by frames: the second set has twice the first's.
    assert pooled["f1_per_seed"]["blind"] == pytest.approx(
        [(0.20 + 2 * 0.30) / 3, (0.22 + 2 * 0.28) / 3, 0.2633], abs=1e-4
    )
    assert pooled["seeds"] == [0, 1, 2] and pooled["variants"] == ["blind", "reviewed_200", "full"]
    expected = recovered_share(*(pooled["f1_per_seed"][n] for n in ("reviewed_200", "blind", "full")))
    assert pooled["recovered"] == {"reviewed_200": expected} and pooled["gap_significant"]
    assert pooled["gap"]["mean"] == pytest.approx(0.04, abs=1e-4)
    text = render_record(pooled)
    assert (
        "`a.json` (factories 111, 112, 12 frames each); `b.json` (factories 121, 122, 24 frames each)" in text
    )
    assert f"recovered: reviewed_200 {100 * expected['share']:.0f}%" in text
    # A gap inside its noise states no share.
    noisy = _pool_record(
        [131], {"blind": [0.2, 0.3, 0.2], "reviewed_200": [0.2, 0.3, 0.2], "full": [0.3, 0.2, 0.21]}
    )
    flat = pool_hitl_records([first, noisy])
    assert not flat["gap_significant"] and "no recovered share is stated" in render_record(flat)
    # Refused: one record, a shared factory, a partial record, another plan, no held-out factories.
    with pytest.raises(InputError, match="two or more"):
        pool_hitl_records([first])
    with pytest.raises(InputError, match="share held-out factories"):
        pool_hitl_records([first, _pool_record([112], {"blind": [0.2], "full": [0.3]})])
    with pytest.raises(InputError, match="b.json is a partial record"):
        pool_hitl_records([first, {**second, "complete": False}], names=["a.json", "b.json"])
    with pytest.raises(
        InputError, match="b.json planned blind differently from a.json \\(settings.epochs\\)"
    ):
        other = _pool_record([121], {"blind": [0.3], "full": [0.4]}, epochs=3)
        pool_hitl_records([first, other], names=["a.json", "b.json"])
    with pytest.raises(InputError, match="not measured on held-out factories"):
        pool_hitl_records([first, {**second, "plan": {**second["plan"], "heldout": None}}])
