"""The held-out factory benchmark: its plan's checks, a tiny run end to end, and its table."""

import dataclasses
import json

import numpy as np
import pytest

from factorydet_core.evaluation.quality import (
    QualityPlan,
    bench_quality,
    check_heldout,
    quality_markdown,
    write_outputs,
)
from factorydet_core.evaluation.records import library_version
from factorydet_core.io.dataset import open_dataset
from factorydet_core.training.mining import collect_proposals
from factorydet_core.types import InputError


def test_the_plan_refuses_the_training_factory_as_held_out(small_dataset_dir, tmp_path):
    with pytest.raises(InputError, match="training factory's own seed"):
        QualityPlan(train_data=small_dataset_dir, heldout_seeds=(7,), scratch=tmp_path)  # its seed is 7
    with pytest.raises(InputError, match="methods"):
        QualityPlan(train_data=small_dataset_dir, methods=("magic",), scratch=tmp_path)
    with pytest.raises(InputError):
        QualityPlan(train_data=small_dataset_dir, seeds=(), scratch=tmp_path)
    with pytest.raises(InputError, match="distinct"):
        QualityPlan(train_data=small_dataset_dir, heldout_seeds=(101, 101), scratch=tmp_path)


def test_check_heldout_gives_the_seeds_or_says_what_is_wrong(small_dataset_dir):
    dataset = open_dataset(small_dataset_dir)  # simulated with seed 7
    assert check_heldout([101, "102"], 3, dataset) == (101, 102)
    for seeds, frames, message in [
        ((), 3, "one or more distinct seeds"),
        ((101, 101), 3, "distinct"),
        ((-1,), 3, ">= 0"),
        ((101,), 0, "at least one frame"),
        ((101, 7), 3, "training factory's own seed"),
    ]:
        with pytest.raises(InputError, match=message):
            check_heldout(seeds, frames, dataset)


@pytest.mark.slow
def test_a_tiny_run_measures_every_method_on_the_same_held_out_frames(small_dataset_dir, tmp_path):
    plan = QualityPlan(
        train_data=small_dataset_dir,
        heldout_seeds=(501,),
        heldout_frames=1,
        train_frames=2,
        seeds=(0, 1),
        epochs=1,
        rounds=0,
        scratch=tmp_path,
        quality_trees=30,
        calibrate=False,  # (ICP, about a third of the run, is not what this tests)
    )
    partials, proposed = [], []

    def propose(dataset, frames, detector, progress=None):  # what --workers swaps in, recorded
        proposed.append((dataset.name, list(frames)))
        return collect_proposals(dataset, frames, detector, progress)

    result = bench_quality(plan, command="test", on_partial=partials.append, propose=propose)
    # Every frame was proposed through the given proposer, each once (then read from the cache).
    expected = [("factory_seed501_1frames", [0]), (result["train_data"], result["train_frames"])]
    assert sorted(proposed) == sorted(expected)
    assert [p["training_seeds"] for p in partials] == [[0], [0, 1]] and result["complete"]
    assert result["library_versions"] == {library_version(): 4}  # two learned methods, two seeds
    assert not any(p["complete"] for p in partials)
    # Stopped after seed 0 and resumed: seed 0 is read back, only seed 1 is trained again.
    resumed = bench_quality(plan, command="test", earlier=partials[0], propose=propose)
    assert len(proposed) == 2
    head_runs = resumed["methods"]["box_head"]["runs"]
    assert head_runs[0] == partials[0]["methods"]["box_head"]["runs"][0]
    assert head_runs[1]["finished"] >= head_runs[0]["finished"] and resumed["training_seeds"] == [0, 1]
    with pytest.raises(InputError, match="another plan .*epochs"):
        bench_quality(dataclasses.replace(plan, epochs=2), earlier=partials[0])
    # A record from before the regressor's size was a setting ran the default's (500 trees).
    assert partials[0]["plan"]["quality_trees"] == 30
    older = {**partials[0], "plan": {k: v for k, v in partials[0]["plan"].items() if k != "quality_trees"}}
    with pytest.raises(InputError, match="another plan .*quality_trees"):
        bench_quality(plan, earlier=older)
    assert result["num_heldout_frames"] == 1 and result["train_seed"] == 7
    options, head, paper = (result["methods"][m] for m in ("head_options", "box_head", "paper"))
    assert [r["seed"] for r in head["runs"]] == [0, 1] and len(paper["runs"]) == 1
    # Both learned methods read the same head, trained once per seed.
    assert [r["train_seconds"] for r in options["runs"]] == [r["train_seconds"] for r in head["runs"]]
    for method in (options, head, paper):
        run = method["runs"][0]
        assert {"iou_0.6", "iou_0.5", "iou_0.25", "candidate_bound", "iou_0.6_without_ignore"} <= set(run)
        # Every figure says how many truth objects it rests on, the same for both methods.
        assert run["iou_0.6"]["num_reference"] == paper["runs"][0]["iou_0.6"]["num_reference"] > 0
        f1 = [r["iou_0.6"]["f1"] for r in method["runs"]]
        assert method["summary"]["f1"]["mean"] == pytest.approx(np.mean(f1), abs=1e-4)
        assert method["summary"]["f1"]["std"] == pytest.approx(np.std(f1), abs=1e-4)
    # The held-out factory was simulated once and its proposals cached: a second run reuses both.
    assert len(list((tmp_path / "proposals").glob("*.npz"))) == 2
    write_outputs(result, tmp_path / "bench" / "quality.json")
    assert json.loads((tmp_path / "bench" / "quality.json").read_text())["benchmark"] == "quality"
    table = (tmp_path / "bench" / "quality.md").read_text()
    assert "| F-score, IoU 0.6 |" in table and "seeds 501" in table
    assert "box_head" in table and "head_options" in table
    assert table == quality_markdown(result)


def test_a_run_that_trains_nothing_says_so_and_names_its_front_half():
    from pathlib import Path

    record = Path(__file__).parents[3] / "docs" / "bench" / "quality_history2.json"
    result = json.loads(record.read_text())
    table = quality_markdown(result)
    assert "| paper |" in table and "spread" not in table
    assert "{'history_frames': 2}" in table
    assert table == (record.with_suffix(".md")).read_text()


def test_target_lines_say_what_is_met_and_by_how_much_the_rest_is_short():
    from factorydet_core.evaluation.quality import target_lines

    def stat(mean):
        return {"mean": mean, "std": 0.0}

    summary = {
        "f1": stat(0.61),
        "map": stat(0.30),
        "per_class_f1": {"barrel": stat(0.5), "pallet": stat(0.1), "cone": stat(None)},
        "recognition_mean": stat(0.96),
        "recognition_per_class": {"background": stat(0.9)},
        "back_half_ms_per_frame": stat(400.0),
    }
    lines = target_lines({"methods": {"m": {"summary": summary}}}, "m")
    assert lines[0] == "- Total F-score at IoU 0.6: 0.610 against 0.600: met."
    assert lines[1] == "- mAP at IoU 0.6: 0.300 against 0.550: short by 0.250."
    assert lines[2] == "- Every class at F 0.4 or more: short for pallet (0.100), cone (n/a)."
    assert lines[3].endswith(": met.") and lines[4].endswith("short by 0.070.")
    assert lines[5].endswith("400 ms against 150 ms: over by 250 ms.")


def test_a_resume_with_seeds_to_train_reads_back_only_the_seeds_this_library_ran(small_dataset_dir):
    import warnings

    from factorydet_core.evaluation.quality import resumable_runs
    from factorydet_core.evaluation.records import library_version, mixed_library_note

    plan = QualityPlan(train_data=small_dataset_dir, seeds=(0, 1, 2), methods=("box_head", "paper"))
    runs = [{"seed": 0, "library": library_version()}, {"seed": 1, "library": "0123456789ab"}]
    earlier = {"plan": plan.record(), "methods": {"box_head": {"runs": runs}, "paper": {"runs": []}}}
    # Seed 2 is to train: seed 1, which ran other code, trains again too, with a warning.
    with pytest.warns(UserWarning, match="1 of the earlier record's training seeds ran another version"):
        assert set(resumable_runs(plan, earlier)) == {0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert set(resumable_runs(plan, earlier, other_library=True)) == {0, 1}
        # Nothing to train: rendered as it is.
        assert set(resumable_runs(dataclasses.replace(plan, seeds=(0, 1)), earlier)) == {0, 1}

    def _library_note(versions):  # as quality_markdown says it
        return mixed_library_note(versions, "Its training runs", "the spread over seeds includes it")

    assert _library_note({"a": 2}) == "" and "2 versions of the library" in _library_note({"a": 1, "b": 1})
