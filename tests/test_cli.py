import argparse
import json
import shutil

import numpy as np
import pytest

from app.cli import main
from factorydet_core.detection.model import DetectionModel
from factorydet_core.types import InputError


def test_simulate_info_and_bench(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["simulate", "--out", str(out), "--frames", "2", "--seed", "1", "--points", "8000"]) == 0
    assert (out / "manifest.json").is_file()
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_frames"] == 2 and info["num_sensors"] == 12
    assert main(["bench", "simulate", "--frames", "2", "--points", "8000"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["benchmark"] == "simulate" and result["seconds_per_frame_median"] > 0
    assert result["machine"]["cores"] >= 1


def test_bench_writes_the_readme_block(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("before\n<!-- bench:simulate -->\nold\n<!-- /bench:simulate -->\nafter\n")
    assert main(["bench", "simulate", "--frames", "1", "--points", "4000", "--readme", str(readme)]) == 0
    text = readme.read_text()
    # The block gets a table and a link to the record, written beside the page in bench/.
    assert "old" not in text and "| s per frame (median) |" in text and text.endswith("after\n")
    assert "[bench/simulate.json](bench/simulate.json)" in text
    record = json.loads((tmp_path / "bench" / "simulate.json").read_text())
    assert record["benchmark"] == "simulate" and f"| {record['seconds_per_frame_median']} |" in text
    # A block of its own name: the default block is left alone.
    readme.write_text(text + "<!-- bench:sim-b -->\nold\n<!-- /bench:sim-b -->\n")
    args = ["bench", "simulate", "--frames", "1", "--points", "4000", "--readme", str(readme)]
    assert main([*args, "--readme-block", "sim-b"]) == 0
    assert readme.read_text().startswith(text) and "old" not in readme.read_text()
    assert (tmp_path / "bench" / "sim-b.json").is_file()
    assert main([*args, "--readme-block", "missing"]) == 2
    assert "no '<!-- bench:missing -->' block" in capsys.readouterr().err
    assert main([*args, "--readme-block", "a b"]) == 2
    assert sorted(p.name for p in (tmp_path / "bench").iterdir()) == ["sim-b.json", "simulate.json"]


def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such file" in err
    assert main(["simulate", "--out", str(tmp_path / "x"), "--unlabelled-fraction", "2"]) == 2
    assert "unlabelled_fraction" in capsys.readouterr().err
    assert main(["app", "--session", "../x", "--root", str(tmp_path)]) == 2
    assert "invalid session name" in capsys.readouterr().err


def test_bench_hitl_compare_pairs_two_detectors_of_one_record(tmp_path, capsys):
    seeds = [0, 1, 2]
    record = {
        "benchmark": "hitl",
        "complete": True,
        "data": "x",
        "train_frames": [0],
        "test_frames": [1],
        "iou_threshold": 0.6,
        "seeds": seeds,
        "plan": {"data": "x"},
        "per_seed": {
            name: [{"seed": s, "f1": f + 0.01 * s, "map": f} for s in seeds]
            for name, f in (("blind", 0.2), ("full", 0.25))
        },
    }
    path = tmp_path / "r.json"
    path.write_text(json.dumps(record))
    assert main(["bench", "hitl-compare", str(path), "--variants", "full,blind"]) == 0
    row = json.loads(capsys.readouterr().out)["variants"]["full minus blind"]
    assert row["f1"]["mean"] == pytest.approx(0.05) and row["f1"]["ci95"] == [0.05, 0.05]
    assert main(["bench", "hitl-compare", str(path)]) == 2
    assert (
        "two bench hitl records, RECORD BASELINE, or one record and --variants A,B" in capsys.readouterr().err
    )
    for bad in ("full", "full,"):
        assert main(["bench", "hitl-compare", str(path), "--variants", bad]) == 2
        assert "takes two detectors" in capsys.readouterr().err
    assert main(["bench", "hitl-compare", str(path), "--variants", "full,reviewed_200"]) == 2
    assert "r.json did not run 'reviewed_200'" in capsys.readouterr().err


def test_bench_hitl_pool_takes_records_on_disjoint_factories_together(tmp_path, capsys):
    def record(factories, offset):
        per_seed = {
            name: [{"seed": s, "f1": f + offset + 0.01 * s} for s in range(3)]
            for name, f in (("blind", 0.2), ("reviewed_200", 0.23), ("full", 0.25))
        }
        plan = {"data": "x", "heldout": {"seeds": factories, "frames": 12}}
        return {"benchmark": "hitl", "complete": True, "plan": plan, "per_seed": per_seed}

    paths = []
    for name, factories, offset in (("a.json", [111], 0.0), ("b.json", [121], 0.1)):
        paths.append(tmp_path / name)
        paths[-1].write_text(json.dumps(record(factories, offset)))
    page = tmp_path / "docs" / "p.md"
    page.parent.mkdir()
    page.write_text("<!-- bench:pooled -->\n<!-- /bench:pooled -->\n")
    args = ["bench", "hitl-pool", *map(str, paths), "--readme", str(page), "--readme-block", "pooled"]
    assert main(args) == 0
    pooled = json.loads(capsys.readouterr().out)
    assert pooled["f1"]["blind"] == pytest.approx(0.26) and pooled["records"] == ["a.json", "b.json"]
    assert "recovered: reviewed_200 60%" in page.read_text()
    assert json.loads((page.parent / "bench" / "pooled.json").read_text())["f1"] == pooled["f1"]
    assert main(["bench", "hitl-pool", str(paths[0])]) == 2
    assert "needs two or more bench hitl records" in capsys.readouterr().err


def test_propose_json_on_a_simulated_frame(small_dataset_dir, capsys):
    assert main(["propose", str(small_dataset_dir), "--frame", "1", "--json", "--no-calibrate"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["frame"] == 1 and record["preset"] == "agv"
    assert len(record["proposals"]) > 10
    for proposal in record["proposals"]:
        assert len(proposal["box"]) == 7 and all(v > 0 for v in proposal["box"][3:6])
        assert proposal["num_points"] >= 30


@pytest.mark.slow
def test_propose_on_a_real_scan_picks_the_indoor_preset(capsys):
    import pytest

    from tests.conftest import SHARED_REAL

    path = SHARED_REAL / "scannet_scene0000_00.npz"
    if not path.exists():
        pytest.fail(f"{path} is missing: the real scans live in ../shared/data/real beside the repository")
    assert main(["propose", str(path), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["preset"] == "indoor" and record["num_points"] == 81_369
    assert len(record["proposals"]) > 20


def test_propose_bad_input(small_dataset_dir, capsys):
    assert main(["propose", str(small_dataset_dir), "--frame", "99"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main(["propose", str(small_dataset_dir), "--set", "regularization=-1"]) == 2
    assert "regularization" in capsys.readouterr().err
    assert main(["propose", str(small_dataset_dir), "--preset", "nope"]) == 2
    assert "unknown preset" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_pipeline_prints_stage_times_and_recall(small_dataset_dir, capsys):
    assert main(["bench", "pipeline", str(small_dataset_dir), "--frames", "1", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["stage_ms_median"]) >= {"merge", "prune", "voxelize", "features", "segmentation"}
    assert result["features"]["max_abs_error_vs_reference"] < 1e-5
    # A ratio of two timings: its value is the benchmark's business (README), and on a loaded
    # shared machine it swings by an order of magnitude; the test checks that it is measured.
    assert result["features"]["speedup_over_reference"] > 0
    assert 0 <= result["proposal_recall"]["all"]["recall"] <= 1
    calibration = result["calibration"]
    assert (
        calibration["refined"]["point_10m_ahead_error_cm_median"]
        < calibration["nominal"]["point_10m_ahead_error_cm_median"]
    )


@pytest.mark.slow
def test_train_detect_evaluate(small_dataset_dir, tmp_path, capsys):
    root = tmp_path / "sessions"
    args = ["train", str(small_dataset_dir), "--session", "s", "--root", str(root), "--rounds", "1",
            "--epochs", "2", "--frames", "2", "--initial-negatives", "150", "--negatives", "30",
            "--score-threshold", "0.05", "--no-calibrate", "--visibility", "off", "--quality-trees", "30",
            "--export", str(tmp_path / "out" / "m.pt")]  # fmt: skip
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["run_id"] == 1 and [r["round"] for r in summary["rounds"]] == [0, 1]
    assert (root / "s" / "models" / "run_001" / "final.pt").is_file()
    note = json.loads((root / "s" / "models" / "run_001" / "final.json").read_text())
    assert note["config"]["command"].startswith("factorydet train ")
    # --export is the final checkpoint with the same note.
    final = root / "s" / "models" / "run_001" / "final.pt"
    assert (tmp_path / "out" / "m.pt").read_bytes() == final.read_bytes()
    assert json.loads((tmp_path / "out" / "m.json").read_text()) == note
    assert (root / "s" / "session.db").is_file()

    # The model has box quality (the default): scores are probability x predicted IoU, low for a
    # two-epoch classifier, so every candidate above 0 is shown.
    assert (tmp_path / "out" / "m.boxq.npz").is_file() and note["box_quality"] is not None
    # --visibility off: this multi-sensor data would otherwise give the regressor free space.
    exported_quality = DetectionModel.load(tmp_path / "out" / "m.pt").box_quality
    assert not exported_quality.visibility
    assert len(exported_quality.trees_["roots"]) == 30  # --quality-trees
    detect = ["detect", str(small_dataset_dir), "--model", "s", "--root", str(root), "--frame", "2",
              "--score-threshold", "0.0", "--no-calibrate", "--json"]  # fmt: skip
    assert main(detect) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["num_detections"] == len(record["detections"]) > 0
    first = record["detections"][0]
    assert len(first["box"]) == 7 and first["class"] in first["probabilities"]
    assert sum(first["probabilities"].values()) == pytest.approx(1.0, abs=1e-3)

    model = str(root / "s" / "models" / "run_001" / "final.pt")
    assert main(["evaluate", str(small_dataset_dir), "--model", model, "--iou", "0.6", "--no-calibrate",
                 "--json", "--png", str(tmp_path / "pr.png")]) == 0  # fmt: skip
    result = json.loads(capsys.readouterr().out)
    assert {"per_class", "f1", "map", "against", "errors"} <= set(result)
    kinds = {"duplicate", "localization", "confusion", "part", "background"}
    assert set(result["errors"]["false_positives"]) == kinds
    assert result["reference"] == "truth" and set(result["against"]) == {"annotations", "truth"}
    for row in result["per_class"].values():
        assert {"precision", "recall", "f1", "ap"} <= set(row)
    assert (tmp_path / "pr.png").is_file()


@pytest.mark.slow
def test_the_labelling_loop_from_the_command_line(small_dataset_dir, tmp_path, capsys):
    root = str(tmp_path / "sessions")
    common = ["--session", "s", "--root", root]
    train = ["train", str(small_dataset_dir), *common, "--rounds", "0", "--epochs", "2", "--frames", "2",
             "--initial-negatives", "150", "--negatives", "20", "--score-threshold", "0.05",
             "--no-calibrate", "--no-box-quality", "--method", "paper"]  # fmt: skip
    assert main(train) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["mode"] == "full" and first["review_queue"] > 0
    assert isinstance(first["unlearned_classes"], dict)

    assert main(["queue", *common, "--json", "--limit", "0"]) == 0
    queue = json.loads(capsys.readouterr().out)
    assert queue["progress"] == {"total": first["review_queue"], "reviewed": 0, "background": 0,
                                 "object": 0, "wrong_box": 0, "skip": 0}  # fmt: skip
    scores = [item["score"] for item in queue["items"]]
    assert scores == sorted(scores, reverse=True)
    ids = [item["id"] for item in queue["items"][:3]]
    review = [
        "review",
        *common,
        "--ids",
        ",".join(map(str, ids[:2])),
        "--verdict",
        "background",
        "--author",
        "ann",
    ]
    assert main(review) == 0
    assert json.loads(capsys.readouterr().out)["progress"]["background"] == 2
    assert main(["review", *common, "--ids", str(ids[2]), "--verdict", "object", "--class", "box",
                 "--author", "ann"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["undo", *common, "--author", "ann"]) == 0
    assert "review 1 mined negative(s) as object (box)" in capsys.readouterr().out
    assert main(["undo", *common, "--author", "bob"]) == 1
    assert main(["review", *common, "--ids", "x", "--verdict", "skip"]) == 2
    assert main(["review", *common, "--ids", str(ids[0]), "--verdict", "object", "--author", "ann"]) == 2
    assert "needs a class" in capsys.readouterr().err

    assert main([*train, "--mode", "next", "--compare", "--test-frames", "1"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert second["run_id"] == 2 and second["mode"] == "next"
    assert set(second["compare"]) == {"run 1", "run 2"}
    assert 0 <= second["compare"]["run 2"]["f1"] <= 1


def test_detect_without_a_model_is_an_input_error(small_dataset_dir, tmp_path, capsys):
    assert main(["detect", str(small_dataset_dir), "--model", "nosuch", "--root", str(tmp_path)]) == 2
    assert "no trained model" in capsys.readouterr().err


@pytest.mark.slow
def test_report_writes_tables_plots_and_numbers(small_dataset_dir, tiny_model_path, tmp_path, capsys):
    out = tmp_path / "docs" / "results.md"
    # The baseline and the sweep train on another data set's frames (the model's training data).
    train_copy = shutil.copytree(small_dataset_dir, tmp_path / "train_copy")
    args = ["report", str(small_dataset_dir), "--model", str(tiny_model_path), "--out", str(out),
            "--sweep", "0.3", "--sweep-frames", "1", "--no-calibrate",
            "--train-data", str(train_copy)]  # fmt: skip
    assert main(args) == 0
    text = out.read_text()
    assert f"of `{train_copy}`" in text
    assert "voxel features (the paper's Eq. 7)" in text  # the tiny model's proposal feature
    for heading in ("Table 2", "Table 3", "Targets", "Where the errors are", "Fig. 7"):
        assert heading in text, heading
    assert "| **mean over classes** |" in text and "| **total** |" in text
    assert "99.84" in text and "0.793" in text and "0.417" in text  # the paper's figures beside ours
    assert (tmp_path / "docs" / "results_pr.png").is_file()
    assert (tmp_path / "docs" / "results_grid_sweep.png").is_file()
    assert (tmp_path / "docs" / "results_errors.png").is_file()
    record = json.loads((tmp_path / "docs" / "results.json").read_text())
    assert set(record["results"]) == {"annotations", "truth"}
    # Every detection and every instance has exactly one kind, at Table 3's operating point.
    deep = record["results"]["truth"]["deep"]
    errors = deep["errors"]
    assert errors["f1"] == pytest.approx(deep["f1"], abs=1e-3)
    assert errors["num_reference"] == deep["num_reference"]
    assert errors["num_detections"] == deep["num_detections"]
    for name, row in errors["per_class"].items():
        assert row["tp"] + sum(row["misses"].values()) == deep["per_class"][name]["num_reference"]
        assert row["tp"] + sum(row["false_positives"].values()) == deep["per_class"][name]["num_detections"]
    assert "| true positives | " in text and "| missed: no candidate |" in text
    assert record["grid_sweep"][0]["voxel_size_m"] == 0.3
    # Where recall goes: each row of the funnel is a subset of the one before.
    bound = record["proposal_recall_bound"]
    assert "| the same, kept by NMS |" in text
    for name in bound["kept"]:
        chain = [bound[k][name] for k in ("options", "chosen", "scored", "kept") if bound[k] is not None]
        assert len(chain) >= 3 and chain == sorted(chain, reverse=True), (name, chain)
    assert main(["report", str(small_dataset_dir), "--model", str(tiny_model_path), "--sweep", "x"]) == 2


@pytest.mark.slow
def test_bench_hitl_with_threshold_folds_measures_each_model_at_both_thresholds(small_dataset_dir, tmp_path):
    out = tmp_path / "hitl.json"
    args = ["bench", "hitl", str(small_dataset_dir), "--budgets", "5", "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--seeds", "0", "--train-frames", "2",
            "--frames", "1", "--no-calibrate", "--no-box-quality", "--method", "paper", "--variants", "full",
            "--threshold-folds", "2", "--threshold-objective", "class", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    result = json.loads(out.read_text())
    assert result["plan"]["settings"]["threshold_folds"] == 2
    for name in ("blind", "full"):
        variant = result["variants"][name]["fitted_frame_thresholds"]
        runs = result["per_seed"][name]
        for run in runs:
            fitted = run["fitted_frame_thresholds"]
            # Thresholds on the fitted frames never exceed the operating score; out of fold they may.
            assert all(t <= 0.35 for t in fitted["thresholds"].values())
            assert set(fitted) >= {"f1", "map", "per_class_f1", "thresholds", "out_of_fold_thresholds"}
            assert fitted["map"] == run["map"]  # the same network: only the thresholds differ
        assert variant["f1_per_seed"] == [r["fitted_frame_thresholds"]["f1"] for r in runs]
        difference = variant["out_of_fold_minus_fitted"]  # (one seed: no interval)
        gained = runs[0]["f1"] - runs[0]["fitted_frame_thresholds"]["f1"]
        assert difference["mean"] == pytest.approx(gained, abs=1e-4)
    assert "difference_vs_blind" in result["variants"]["full"]["fitted_frame_thresholds"]
    assert "the same models at thresholds tuned on their fitted frames" in out.with_suffix(".md").read_text()
    # ... and at the other objective's out-of-fold thresholds, on the same network.
    for name in ("blind", "full"):
        for run in result["per_seed"][name]:
            other = run["other_objective_thresholds"]
            # The same network (mAP reads no threshold), at thresholds of its own.
            assert other["objective"] == "total" and other["map"] == run["map"]
            assert set(other["thresholds"]) <= set(run["per_class_f1"])
        variant = result["variants"][name]["other_objective_thresholds"]
        assert variant["f1_per_seed"] == [
            r["other_objective_thresholds"]["f1"] for r in result["per_seed"][name]
        ]
    assert "out-of-fold thresholds of objective total" in out.with_suffix(".md").read_text()
    # ... and at the other objective's thresholds on the fitted frames (what no folds give).
    for name in ("blind", "full"):
        runs = result["per_seed"][name]
        for run in runs:
            no_folds = run["fitted_frame_other_objective_thresholds"]
            assert no_folds["objective"] == "total" and no_folds["map"] == run["map"]
            assert all(t <= 0.35 for t in no_folds["thresholds"].values())  # under the ceiling
        variant = result["variants"][name]["fitted_frame_other_objective_thresholds"]
        assert variant["f1_per_seed"] == [r["fitted_frame_other_objective_thresholds"]["f1"] for r in runs]
        gained = runs[0]["f1"] - runs[0]["fitted_frame_other_objective_thresholds"]["f1"]
        assert variant["chosen_minus_these"]["mean"] == pytest.approx(gained, abs=1e-4)
    assert "difference_vs_blind" in result["variants"]["full"]["fitted_frame_other_objective_thresholds"]
    assert "thresholds of objective total tuned on their fitted frames (no folds)" in (
        out.with_suffix(".md").read_text()
    )


@pytest.mark.slow
def test_bench_hitl_prints_each_variants_f_score_and_the_paired_differences(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    out = tmp_path / "hitl.json"
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n<!-- bench:hitl -->\nold\n<!-- /bench:hitl -->\n\nend\n")
    # A README without the block is refused before the long run, not after it.
    (tmp_path / "other.md").write_text("# no block\n")
    with monkeypatch.context() as patch:
        patch.setattr(
            "factorydet_core.evaluation.hitl.bench_hitl", lambda *a, **k: pytest.fail("ran before the check")
        )
        assert main(["bench", "hitl", str(small_dataset_dir), "--readme", str(tmp_path / "other.md")]) == 2
    capsys.readouterr()
    args = ["bench", "hitl", str(small_dataset_dir), "--budgets", "5", "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--score-threshold", "0.05",
            "--seeds", "0,1", "--train-frames", "1", "--no-calibrate", "--no-box-quality",
            "--method", "paper", "--class-weight", "balanced", "--out", str(out),
            "--readme", str(readme), "--hide-labelled", "0.25", "--review-by", "place"]  # fmt: skip
    assert main(args) == 0
    # The README gets the table (no JSON, no section title of its own), the rest untouched.
    text = readme.read_text()
    assert text.startswith("# x\n\n<!-- bench:hitl -->\nGenerated by `factorydet bench")
    assert (
        "| **total F** |" in text
        and "## Human" not in text
        and text.endswith("<!-- /bench:hitl -->\n\nend\n")
    )
    result = json.loads(capsys.readouterr().out)
    assert result == json.loads(out.read_text())
    assert set(result["f1"]) == {"blind", "blind_safe", "reviewed_5", "full"}
    # blind_safe holds what the model scores at its operating score (0.05 here) or more.
    assert result["hold_confident"] == 0.05 and result["variants"]["blind_safe"]["num_reviews"] == 0
    # Paired per-seed differences against blind, with their 95% intervals.
    for name in ("blind_safe", "reviewed_5", "full"):
        difference = result["variants"][name]["difference_vs_blind"]
        per_seed = [
            a - b
            for a, b in zip(
                result["variants"][name]["f1_per_seed"], result["variants"]["blind"]["f1_per_seed"]
            )
        ]
        assert difference["mean"] == pytest.approx(sum(per_seed) / 2, abs=1e-4)
        low, high = difference["ci95"]
        assert low <= difference["mean"] <= high and difference["num_seeds"] == 2
    assert result["gap_significant"] == (
        result["gap_full_minus_blind"]
        > 2 * result["variants"]["full"]["difference_vs_blind"]["standard_error"]
    )
    assert all(0 <= f <= 1 for f in result["f1"].values())
    assert set(result["recovered"]) == {"5"}
    reviewed = result["variants"]["reviewed_5"]
    assert 0 < reviewed["num_reviews"] <= 5  # one review round (rounds=1), at most K items
    assert result["queue_max_label_iou"] == 0.25 and reviewed["reviews"]["hidden"] >= 0
    assert result["review_by"] == "place"  # one verdict per place, as the app's queue
    assert result["variants"]["blind"]["num_reviews"] == 0
    assert result["variants"]["full"]["truth_labels_added"] > 0
    assert set(reviewed["per_class_f1"]) >= {"barrel", "truck"}
    # Every variant trains once per seed; its F is their mean, and the gap is that of the means.
    assert result["seeds"] == [0, 1]
    for name, variant in result["variants"].items():
        runs = result["per_seed"][name]
        assert [r["seed"] for r in runs] == [0, 1]
        assert variant["f1_per_seed"] == [r["f1"] for r in runs]
        assert variant["f1"] == pytest.approx(sum(variant["f1_per_seed"]) / 2, abs=1e-4)
    f1 = result["f1"]
    assert result["gap_full_minus_blind"] == pytest.approx(f1["full"] - f1["blind"], abs=1e-4)
    assert len(result["recovered_per_seed"]["5"]) == 2
    markdown = out.with_suffix(".md").read_text()
    assert "| total F per seed |" in markdown and "Means over seeds 0, 1." in markdown
    assert "| F minus blind's, per seed: mean [95% interval] |" in markdown
    assert ("Recovered share" in markdown) == result["gap_significant"]
    # What the reviews gave back: full labels cover every unannotated object, blind ones none.
    assert result["variants"]["full"]["unannotated_labelled"] == 1.0
    assert result["variants"]["blind"]["unannotated_labelled"] == 0.0
    # Reviews give back at most what the reviewed queues reach.
    assert result["variants"]["full"]["unannotated_in_queue"] is None
    assert 0 <= reviewed["unannotated_labelled"] <= reviewed["unannotated_in_queue"] <= 1
    assert 0 <= reviewed["unannotated_in_top_k"] <= reviewed["unannotated_in_queue"]
    # What the review panel estimates of the first K entries' reach, beside the truth's.
    for key in ("reach_share_estimated", "reach_share_true"):
        assert reviewed[key] is None or 0 <= reviewed[key] <= 1
    assert reviewed["reach_share_estimated"] is not None
    assert result["variants"]["blind"]["reach_share_estimated"] is None
    assert result["variants"]["blind"]["unannotated_in_top_k"] is None
    assert "| unannotated training objects in the reviewed rounds' queues |" in markdown
    assert "| unannotated training objects labelled |" in markdown
    # ... and per class, for the reviewed detectors: the counts add up to the totals.
    for run in result["per_seed"]["reviewed_5"]:
        per_class = run["unannotated_labelled_per_class"]
        assert sum(covered for covered, _ in per_class.values()) == run["unannotated_labelled"]
        assert sum(total for _, total in per_class.values()) == run["unannotated_total"] > 0
    full_per_class = result["variants"]["full"]["unannotated_labelled_per_class"]
    assert all(v["share"] in (1.0, None) for v in full_per_class.values())
    assert "the share labelled at the end, per class:" in markdown
    assert "| class | unannotated | reviewed_5 |" in markdown
    assert "answers the top K places of each round's queue (one verdict per place" in markdown
    assert main(["bench", "hitl", str(small_dataset_dir), "--seeds", "1,1"]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--seeds", "-1"]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--budgets", "200,200"]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--budgets", "0"]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--hide-labelled", "0"]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--variants", "blind,nobody"]) == 2
    assert (
        main(["bench", "hitl", str(small_dataset_dir), "--budgets", "50", "--variants", "reviewed_200"]) == 2
    )
    assert main(["bench", "hitl", str(small_dataset_dir), "--variants", "full", "--hold-places"]) == 2
    assert (
        main(
            ["bench", "hitl", str(small_dataset_dir), "--variants", "full", "--recalibrate-background", "0.5"]
        )
        == 2
    )
    by_class = ["--recalibrate-background", "0.5", "--recalibrate-by-class"]
    assert main(["bench", "hitl", str(small_dataset_dir), "--variants", "full", *by_class]) == 2
    assert main(["bench", "hitl", str(small_dataset_dir), "--recalibrate-by-class"]) == 2  # refines nothing
    # Reading back runs of other code is a resume's choice, and bench hitl's alone.
    assert main(["bench", "hitl", str(small_dataset_dir), "--resume-other-library"]) == 2
    assert "--resume-other-library goes with bench hitl or quality --resume" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_hitl_runs_the_variants_asked_for_with_blind_always(small_dataset_dir, tmp_path, capsys):
    out = tmp_path / "hitl.json"
    args = ["bench", "hitl", str(small_dataset_dir), "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--score-threshold", "0.05",
            "--seeds", "0", "--train-frames", "1", "--no-calibrate", "--no-box-quality",
            "--method", "paper", "--class-weight", "balanced", "--variants", "full_late,blind_safe",
            "--hold-places", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert list(result["variants"]) == ["blind", "blind_safe", "full_late"]
    # full_late: every missing label added after the first fit, none before it.
    late = result["variants"]["full_late"]
    assert late["truth_labels_added"] > 0 and late["unannotated_labelled"] == 1.0
    assert result["plan"]["variants"] == ["blind", "blind_safe", "full_late"]
    assert result["settings"]["hold_places"] is True
    assert result["gap_full_minus_blind"] is None and result["recovered"] == {}
    markdown = out.with_suffix(".md").read_text()
    assert "and every point set on their boxes (their places) with them" in markdown
    assert "Full labels were not run here" in markdown and "Recovered share" not in markdown
    assert "`full_late`: the same labels added after the first fit" in markdown
    assert "the paper's 3DmFV-Net (width 0.0625)" in markdown


@pytest.mark.slow
def test_bench_hitl_reviewed_safe_reviews_and_holds_what_its_reviewer_leaves(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    import factorydet_core.evaluation.hitl as hitl

    out = tmp_path / "hitl.json"
    args = ["bench", "hitl", str(small_dataset_dir), "--budgets", "3", "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--score-threshold", "0.05",
            "--seeds", "0", "--train-frames", "1", "--frames", "1", "--no-calibrate", "--no-box-quality",
            "--method", "paper", "--class-weight", "balanced", "--variants", "reviewed_safe_3,full",
            "--hold-places", "--out", str(out)]  # fmt: skip
    fitted, held = {}, {}  # each detector's settings, and the negatives its mining held
    train_session = hitl.train_session

    def recording(db, frames, settings, **kwargs):
        fitted[db.session.name] = settings
        run_id, run = train_session(db, frames, settings, **kwargs)
        held[db.session.name] = held.get(db.session.name, 0) + sum(r["num_held"] for r in run.rounds)
        return run_id, run

    monkeypatch.setattr(hitl, "train_session", recording)
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert list(result["variants"]) == ["blind", "reviewed_safe_3", "full"]
    safe = fitted["reviewed_safe_3_seed0"]
    assert safe.hold_confident == result["hold_confident"] == 0.05 and safe.hold_places
    assert held["reviewed_safe_3_seed0"] > 0 and held["blind_seed0"] == held["full_seed0"] == 0
    assert fitted["blind_seed0"].hold_confident is None and not fitted["blind_seed0"].hold_places
    reviewed = result["variants"]["reviewed_safe_3"]
    assert 0 < reviewed["num_reviews"] <= 3 and reviewed["unannotated_in_top_k"] is not None
    markdown = out.with_suffix(".md").read_text()
    assert "`reviewed_safe_K`: the reviewer of `reviewed_K` on top of `blind_safe`" in markdown
    assert "and every point set on their boxes (their places) with them" in markdown
    # Per class, whether F moves by false positives or by misses.
    blind = result["variants"]["blind"]
    assert set(blind["per_class_precision"]) == set(blind["per_class_recall"]) == set(blind["per_class_f1"])
    assert "Per class, precision / recall" in markdown
    # The holding settings shape the holding detectors alone: without one among the variants, refused.
    no_holding = [a if a != "reviewed_safe_3,full" else "reviewed_3,full" for a in args]
    assert main(no_holding) == 2
    assert "blind_safe and reviewed_safe_K alone" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_hitl_resume_trains_only_the_detectors_the_record_lacks(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    import factorydet_core.evaluation.hitl as hitl

    out = tmp_path / "hitl.json"
    args = ["bench", "hitl", str(small_dataset_dir), "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--score-threshold", "0.05",
            "--seeds", "0", "--train-frames", "1", "--frames", "1", "--no-calibrate", "--no-box-quality",
            "--method", "paper", "--class-weight", "balanced", "--variants", "blind_safe",
            "--out", str(out), "--resume"]  # fmt: skip
    fits = []
    train_session = hitl.train_session
    monkeypatch.setattr(
        hitl, "train_session", lambda db, *a, **k: fits.append(db) or train_session(db, *a, **k)
    )
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["complete"] and len(fits) == 4  # two detectors, a first fit and one round each
    # Each run keeps the code it ran; the record counts its runs per version of the library.
    from factorydet_core.evaluation.records import library_version

    assert {run["library"] for runs in first["per_seed"].values() for run in runs} == {library_version()}
    assert first["library_versions"] == {library_version(): 2}
    assert "Every run ran one version of the library." in out.with_suffix(".md").read_text()
    # Stopped after blind: the partial record --out held then.
    partial = {key: first[key] for key in ("benchmark", "command", "plan", "machine")}
    # Written before queue_order was a setting: it ran with the default, and resumes.
    partial["plan"] = {**partial["plan"], "settings": dict(partial["plan"]["settings"])}
    assert partial["plan"]["settings"].pop("queue_order") == "score"
    # ... and before held-out factories and background recalibration: it ran without either.
    assert partial["plan"].pop("heldout") is None
    assert partial["plan"]["settings"].pop("recalibrate_background") is None
    out.write_text(
        json.dumps({**partial, "complete": False, "per_seed": {"blind": first["per_seed"]["blind"]}})
    )
    fits.clear()
    assert main(args) == 0
    resumed = json.loads(capsys.readouterr().out)
    assert len(fits) == 2  # blind_safe alone trained again
    assert resumed["per_seed"]["blind"] == first["per_seed"]["blind"]  # read back, fit time included
    # Each detector trains in a session of its own from its seed: the same F as the whole run's.
    assert resumed["f1"] == first["f1"] and resumed == json.loads(out.read_text())
    # A record of another plan gives the runs its differences do not touch: holding places
    # changes blind_safe alone, so blind is read back and blind_safe trained again.
    fits.clear()
    assert main([*args, "--hold-places"]) == 0
    held = json.loads(capsys.readouterr().out)
    assert len(fits) == 2 and held["per_seed"]["blind"] == first["per_seed"]["blind"]
    assert held["plan"]["settings"]["hold_places"] is True
    out.write_text(json.dumps(resumed))
    # A whole record resumed is only rendered again: nothing trained, nothing proposed.
    fits.clear()
    monkeypatch.setattr(hitl, "cached_proposals", lambda *a, **k: pytest.fail("proposed"))
    assert main(args) == 0
    again = json.loads(capsys.readouterr().out)
    assert not fits and again["f1"] == resumed["f1"] and again["proposal_seconds"] is None
    # Runs finished in other records (another process's detectors or seeds) are read back too,
    # into a record at --out that did not exist.
    parts = []
    for name in ("blind", "blind_safe"):
        parts.append(tmp_path / f"{name}.json")
        part = {**resumed, "complete": False, "per_seed": {name: resumed["per_seed"][name]}}
        parts[-1].write_text(json.dumps(part))
    joined = tmp_path / "joined.json"
    at_joined = [*args[:-2], str(joined), "--resume"]
    assert main([*at_joined, "--resume-also", ",".join(map(str, parts))]) == 0
    assert not fits and json.loads(capsys.readouterr().out)["per_seed"] == resumed["per_seed"]
    assert json.loads(joined.read_text())["complete"]
    assert main([*args[:-1], "--resume-also", str(parts[0])]) == 2  # (only with --resume)
    assert "--resume-also goes with bench hitl --resume" in capsys.readouterr().err
    assert main([*at_joined, "--resume-also", " , "]) == 2
    assert "--resume-also names no record" in capsys.readouterr().err
    # A record of another plan is refused before any work; so is --resume where nothing resumes.
    fits.clear()
    assert args[5] == "--epochs" and main([*args[:6], "2", *args[7:]]) == 2
    assert "another plan (settings)" in capsys.readouterr().err and not fits
    assert main([*args, "--queue-order", "class"]) == 2  # not the default the record ran with
    assert "another plan (settings)" in capsys.readouterr().err and not fits
    assert main(["bench", "detect", str(small_dataset_dir), "--resume", "--out", str(out)]) == 2
    assert "--resume applies to bench hitl, quality and scale" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_classifier_measures_rows_with_the_models_box_quality(small_dataset_dir, capsys):
    args = ["bench", "classifier", str(small_dataset_dir), "--widths", "0.0625", "--features", "aggregated",
            "--geometry", "on,off", "--epochs", "1", "--train-frames", "1", "--frames", "1",
            "--quality-trees", "30"]  # fmt: skip
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    # Scored as the loop and the shipped model score: the square root of the probability at 0.35.
    assert result["box_quality"] is True and result["score_threshold"] == 0.35
    assert result["quality_trees"] == 30
    assert result["probability_exponent"] == 0.5
    rows = [(r["feature"], r["geometry"]) for r in result["rows"]]
    assert rows == [("aggregated", True), ("aggregated", False)]
    for row in result["rows"]:
        assert row["epochs_run"] == 1
        assert 0 <= row["detection_precision"] <= 1 and 0 <= row["detection_f1"] <= 1
    assert main(["bench", "classifier", str(small_dataset_dir), "--features", "voxels"]) == 2


def test_bench_quality_checks_its_arguments_and_readme_before_running(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    monkeypatch.setattr(
        "factorydet_core.evaluation.quality.bench_quality", lambda *a, **k: pytest.fail("ran")
    )
    base = ["bench", "quality", str(small_dataset_dir), "--scratch", str(tmp_path)]
    assert main([*base, "--methods", "magic"]) == 2
    assert "methods" in capsys.readouterr().err
    assert main([*base, "--heldout-seeds", "7"]) == 2  # the training factory's own seed
    assert "own seed" in capsys.readouterr().err
    (tmp_path / "other.md").write_text("# no block\n")
    assert main([*base, "--readme", str(tmp_path / "other.md")]) == 2
    assert "bench:quality" in capsys.readouterr().err
    assert main(["bench", "quality", "--scratch", str(tmp_path)]) == 2
    assert main([*base, "--set", "no_such_setting=1"]) == 2
    assert "unknown parameter" in capsys.readouterr().err
    assert main([*base, "--resume"]) == 2
    assert "give --out" in capsys.readouterr().err
    (tmp_path / "cut.json").write_text('{"benchmark": "qual')  # a run killed while writing, before
    assert main([*base, "--resume", "--out", str(tmp_path / "cut.json")]) == 2
    assert "is not a result" in capsys.readouterr().err


def test_the_train_flags_default_to_the_loop_settings():
    import dataclasses

    from factorydet_core.cli import build_parser, loop_settings_from_args
    from factorydet_core.training.settings import LOOP_CONTROLS, LoopSettings

    args = build_parser().parse_args(["train", "--session", "s"])
    assert loop_settings_from_args(args) == LoopSettings()
    # Every setting but the machine's thread count has a flag (and so a control in the app).
    assert {c.field for c in LOOP_CONTROLS} | {"num_threads"} == {
        f.name for f in dataclasses.fields(LoopSettings)
    }


def test_the_train_flags_set_and_check_the_loop_settings():
    from factorydet_core.cli import build_parser, loop_settings_from_args

    argv = ["train", "--session", "s", "--negatives", "30", "--class-weight", "none", "--no-geometry",
            "--visibility", "off", "--fragments-per-frame", "7", "--method", "box_head"]  # fmt: skip
    settings = loop_settings_from_args(build_parser().parse_args(argv))
    assert settings.negatives_per_round == 30 and settings.class_weight is None and not settings.geometry
    assert (
        settings.visibility is False and settings.fragments_per_frame == 7 and settings.method == "box_head"
    )
    with pytest.raises(InputError, match="Score threshold"):
        loop_settings_from_args(
            build_parser().parse_args(["train", "--session", "s", "--score-threshold", "3"])
        )


@pytest.mark.slow
def test_labels_spread_places_the_frames_and_labels_each_object_in_every_frame_that_shows_it(
    small_dataset_dir, tmp_path, capsys
):
    common = ["--session", "s", "--root", str(tmp_path), "--data", str(small_dataset_dir), "--author", "ann"]
    assert main(["labels", "spread", *common]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["added"] > 0 and first["objects"] > 0 and first["edit"] is not None
    assert (tmp_path / "s" / "cache").is_dir()  # the poses, for the next time
    assert main(["labels", "spread", *common]) == 0
    assert json.loads(capsys.readouterr().out) == {"added": 0, "objects": 0, "edit": None}
    assert main(["labels", "export", *common]) == 2
    assert "give the path" in capsys.readouterr().err


@pytest.mark.slow
def test_labels_prelabel_adds_the_models_detections_as_pre_labels_once(
    small_dataset_dir, tiny_model_path, tmp_path, capsys
):
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.session.store import SessionDB, open_session

    common = ["--session", "s", "--root", str(tmp_path), "--data", str(small_dataset_dir), "--author", "ann"]
    argv = [
        "labels",
        "prelabel",
        *common,
        "--model",
        str(tiny_model_path),
        "--frames",
        "0",
        "--min-score",
        "0.05",
    ]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == {"0": report["added"]} and report["added"] > 0
    db = SessionDB(open_session("s", tmp_path), open_dataset(small_dataset_dir))
    unreviewed = db.unreviewed_labels()
    assert len(unreviewed) == report["added"] and all(lab.score >= 0.05 for lab in unreviewed)
    assert main(argv) == 0  # every detection is labelled now: nothing twice
    assert json.loads(capsys.readouterr().out)["added"] == 0
    assert main([*argv[:-1], "2"]) == 2
    assert "--min-score must lie in [0, 1], got 2" in capsys.readouterr().err


@pytest.mark.slow
def test_detect_a_split_into_files_and_resume(small_dataset_dir, tmp_path, capsys):
    out = tmp_path / "detections"
    common = ["detect", str(small_dataset_dir), "--out", str(out), "--no-calibrate", "--json"]
    assert main([*common, "--frames", "1"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["num_computed"] == 1 and first["workers"] == 1 and first["num_nodes"] == 0
    assert main(common) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["num_skipped"] == 1 and again["num_computed"] == 2
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_0000{i}.npz" for i in range(3)]
    # Another operating point into the same folder would mix two jobs' files.
    assert main([*common, "--score-threshold", "0.5"]) == 2
    assert "another job" in capsys.readouterr().err
    assert main(["detect", str(small_dataset_dir), "--workers", "2"]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["detect", str(small_dataset_dir), "--split", "test"]) == 2  # a batch option, no batch
    assert main([*common, "--split", "nope"]) == 2
    assert main([*common, "--worker-threads", "2"]) == 2  # a Ray option without Ray
    assert "apply to Ray workers" in capsys.readouterr().err


@pytest.mark.slow
def test_propose_a_split_into_files_and_resume(small_dataset_dir, tmp_path, capsys):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.io.npz import load_npz
    from factorydet_core.proposals.settings import front_end_params, preset_for
    from factorydet_core.scale.runner import frame_path
    from factorydet_core.training.mining import collect_proposals, proposals_from_arrays

    out = tmp_path / "proposals"
    common = ["propose", str(small_dataset_dir), "--out", str(out), "--no-calibrate", "--json"]
    assert main([*common, "--split", "test", "--frames", "1"]) == 0
    assert json.loads(capsys.readouterr().out)["num_computed"] == 1
    assert main([*common, "--split", "test"]) == 0
    again = json.loads(capsys.readouterr().out)
    test = open_dataset(small_dataset_dir).splits["test"]
    assert again["num_skipped"] == 1 and again["num_computed"] == len(test) - 1
    # Each file is the frame's front half as training proposes it (its cache's format).
    (written,) = proposals_from_arrays(load_npz(frame_path(out, test[0]))[1])
    dataset = open_dataset(small_dataset_dir)
    detector = Detector(front_end_params(preset_for(dataset.num_sensors)))  # the command's default
    (plain,) = collect_proposals(dataset, [test[0]], detector)
    np.testing.assert_array_equal(written.proposal_boxes, plain.proposal_boxes)
    assert written.patch_sets == plain.patch_sets
    assert main([*common, "--set", "voxel_size_m=0.25"]) == 2  # other settings: another job's folder
    assert "another job" in capsys.readouterr().err
    assert main(["propose", str(small_dataset_dir), "--workers", "2"]) == 2
    assert "--out" in capsys.readouterr().err
    # Every batch flag is refused without --out, not ignored (zero frames too).
    for flag in (["--worker-threads", "2"], ["--scratch", str(tmp_path)], ["--frames", "0"]):
        for verb in ("propose", "detect"):
            assert main([verb, str(small_dataset_dir), *flag]) == 2
            assert f"{flag[0]} {verb} a batch" in capsys.readouterr().err


def test_bench_takes_the_execution_switch_where_frames_are_proposed(
    small_dataset_dir, tmp_path, monkeypatch, capsys
):
    from factorydet_core.training.mining import collect_proposals

    seen = {}

    def fake_hitl(*args, **kwargs):
        seen["hitl"] = kwargs["propose"]
        return {"benchmark": "hitl"}

    def fake_mining(*args, **kwargs):
        seen["mining"] = kwargs["train_args"]
        return {"benchmark": "mining"}

    monkeypatch.setattr("factorydet_core.evaluation.hitl.bench_hitl", fake_hitl)
    monkeypatch.setattr("factorydet_core.evaluation.bench.bench_mining", fake_mining)
    assert main(["bench", "hitl", str(small_dataset_dir)]) == 0
    assert seen["hitl"] is collect_proposals  # no Ray: proposed here
    assert json.loads(capsys.readouterr().out)["proposals_on"] == {
        "ray": False,
        "workers": None,
        "address": None,
    }
    assert main(["bench", "hitl", str(small_dataset_dir), "--workers", "3", "--worker-threads", "2"]) == 0
    assert seen["hitl"] is not collect_proposals  # on Ray workers (scale.jobs.proposer)
    assert json.loads(capsys.readouterr().out)["proposals_on"] == {"ray": True, "workers": 3, "address": None}
    # The mining benchmark's child `train` commands get the same flags.
    assert main(["bench", "mining", "--session", "s", "--ray", "auto"]) == 0
    assert seen["mining"] == ["--worker-threads", "1", "--ray", "auto"]
    capsys.readouterr()
    # Benchmarks that time this one process refuse the switch; scale has worker counts of its own.
    assert main(["bench", "detect", str(small_dataset_dir), "--workers", "2"]) == 2
    assert "measures this process alone" in capsys.readouterr().err
    assert main(["bench", "scale", str(tmp_path), "--workers", "2"]) == 2
    assert "--worker-counts" in capsys.readouterr().err
    assert main(["bench", "hitl", str(small_dataset_dir), "--worker-threads", "2"]) == 2
    assert "applies to Ray workers" in capsys.readouterr().err


def test_bench_mining_passes_its_training_settings_to_every_timed_train(monkeypatch, capsys):
    from factorydet_core.cli import build_parser, loop_settings_from_args
    from factorydet_core.training.settings import LoopSettings

    seen = {}

    def fake_mining(*args, **kwargs):
        seen["train_args"] = kwargs["train_args"]
        seen["round_epochs"] = kwargs["round_epochs"]
        return {"benchmark": "mining"}

    monkeypatch.setattr("factorydet_core.evaluation.bench.bench_mining", fake_mining)
    assert main(["bench", "mining", "--session", "s"]) == 0
    assert seen["train_args"] == []  # the defaults: nothing to pass on (the records' commands)
    flags = ["--threshold-folds", "2", "--no-continue-folds", "--threshold-objective", "total"]
    assert main(["bench", "mining", "--session", "s", "--round-epochs", "3", *flags]) == 0
    assert seen["round_epochs"] == (0, 3)  # the bench's own, not passed on
    assert "--round-epochs" not in seen["train_args"]
    # `factorydet train` reads them back as the same settings.
    train_args = build_parser().parse_args(["train", "--session", "s", *seen["train_args"]])
    expected = LoopSettings(threshold_folds=2, continue_folds=False, threshold_objective="total")
    assert loop_settings_from_args(train_args) == expected
    # --compare-set: per seed, the round with the settings given and with the setting changed.
    seen.clear()

    def fake_compared(*args, **kwargs):
        seen.update(kwargs)
        return {"benchmark": "mining"}

    monkeypatch.setattr("factorydet_core.evaluation.bench.bench_mining", fake_compared)
    argv = ["bench", "mining", "--session", "s", "--seeds", "1,2", "--compare-set", "refit_row_share=1.0"]
    assert main([*argv, *flags]) == 0
    labels = [label for label, _ in seen["compared"]]
    # Interleaved, which side runs first alternating from seed to seed.
    assert labels == [
        {"setting": "reference", "seed": 1},
        {"setting": "compared", "seed": 1},
        {"setting": "compared", "seed": 2},
        {"setting": "reference", "seed": 2},
    ]
    assert seen["compare_set"] == {"refit_row_share": 1.0}
    for label, train_flags in seen["compared"]:
        read = loop_settings_from_args(build_parser().parse_args(["train", "--session", "s", *train_flags]))
        share = 1.0 if label["setting"] == "compared" else LoopSettings().refit_row_share
        assert read == LoopSettings(
            threshold_folds=2, continue_folds=False, threshold_objective="total", seed=label["seed"],
            refit_row_share=share,
        )  # fmt: skip
    refused = {
        "no_such_setting=1": "unknown training settings",
        "seed=1": "the benchmark's own",
        "threshold_folds=2": "already say so",  # the value the flags above give
    }
    for pair, message in refused.items():
        assert main(["bench", "mining", "--session", "s", "--compare-set", pair, *flags]) == 2
        assert message in capsys.readouterr().err
    argv = ["bench", "mining", "--session", "s", "--compare-set", "refit_row_share=1", "--round-epochs", "0"]
    assert main(argv) == 2
    assert "--round-epochs > 0" in capsys.readouterr().err


def test_an_execution_gives_back_the_flags_it_was_read_from():
    from factorydet_core.cli import add_execution_flags, execution_from_args
    from factorydet_core.scale.runner import Execution

    parser = argparse.ArgumentParser()
    add_execution_flags(parser)
    for execution in (
        Execution(),
        Execution(workers=2),
        Execution(workers=4, threads=3, scratch="/shared/tmp"),
        Execution(ray_address="auto"),
        Execution(workers=8, ray_address="head:6379", threads=2),
    ):
        assert execution_from_args(parser.parse_args(execution.arguments())) == execution


@pytest.mark.slow
def test_bench_hitl_heldout_measures_the_same_models_on_held_out_factories(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    import factorydet_core.evaluation.hitl as hitl

    args = ["bench", "hitl", str(small_dataset_dir), "--rounds", "1", "--epochs", "1",
            "--negatives", "15", "--initial-negatives", "60", "--score-threshold", "0.05",
            "--seeds", "0", "--train-frames", "1", "--frames", "1", "--no-calibrate", "--no-box-quality",
            "--method", "paper", "--class-weight", "balanced", "--variants", "full"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "in.json")]) == 0
    in_factory = json.loads(capsys.readouterr().out)
    out = tmp_path / "heldout.json"
    heldout_measures, measure = [], hitl.measure

    def spy(model, dataset, frames, **kwargs):
        metrics = measure(model, dataset, frames, **kwargs)
        if dataset is None:  # the held-out frames: references given, no data set
            assert [f.frame_index for f in frames] == [0] and list(kwargs["references"]) == [0]
            heldout_measures.append(metrics)
        return metrics

    monkeypatch.setattr(hitl, "measure", spy)
    heldout_args = [*args, "--heldout", "--heldout-seeds", "501", "--heldout-frames", "1",
                    "--scratch", str(tmp_path / "heldout"), "--out", str(out), "--resume"]  # fmt: skip
    assert main(heldout_args) == 0
    heldout = json.loads(capsys.readouterr().out)
    assert (
        heldout["heldout_factories"] == [{"seed": 501, "frames": 1}]
        and in_factory["heldout_factories"] is None
    )
    assert heldout["plan"]["heldout"] == {"seeds": [501], "frames": 1}
    assert (tmp_path / "heldout" / "factory_seed501_1frames" / "manifest.json").is_file()
    for name in ("blind", "full"):
        # The same models (each run trains from its seed alone), measured elsewhere: the figures on
        # the training factory's test frames are the in-factory run's, the headline ones are not.
        run, reference = heldout["per_seed"][name][0], in_factory["per_seed"][name][0]
        assert run["in_factory"] == {k: reference[k] for k in ("f1", "precision", "recall", "map")}
        assert heldout["variants"][name]["in_factory"]["f1"] == reference["f1"]
        assert 0.0 <= run["f1"] <= 1.0 and run["unannotated_total"] == reference["unannotated_total"]
    # ... and the headline figures are those measured on the held-out factory's frame.
    assert [run["f1"] for run in heldout_measures] == [
        heldout["per_seed"][n][0]["f1"] for n in ("blind", "full")
    ]
    markdown = out.with_suffix(".md").read_text()
    assert "on 1 frame of held-out factories (simulator seeds 501, 1 frame each)" in markdown
    assert "| total F on the training factory's test frames (in-factory) |" in markdown
    assert "in-factory figures)" not in markdown
    # Another place of measurement is another plan: neither record resumes the other.
    (tmp_path / "copy.json").write_text((tmp_path / "in.json").read_text())
    assert main([*heldout_args[:-3], "--out", str(tmp_path / "copy.json"), "--resume"]) == 2
    assert "another plan (heldout)" in capsys.readouterr().err
    assert main([*args, "--out", str(out), "--resume"]) == 2
    # A held-out factory of the training factory's own seed is refused.
    assert main([*args, "--heldout", "--heldout-seeds", "7"]) == 2
    assert "training factory's own seed" in capsys.readouterr().err


def test_train_shows_the_comparisons_test_frames_as_a_bar_after_one_line(capsys):
    from factorydet_core.cli import _training_progress

    progress, close = _training_progress()
    progress("compare", 0, 1)  # the comparison starts
    progress("compare", 0, 3)  # (Ray workers' first report: none done yet)
    for done in (1, 2, 3):
        progress("compare", done, 3)  # the test frames' proposals, one by one
    close()
    err = capsys.readouterr().err
    assert err.count("measuring before and after on the test frames") == 1
    assert "test frames: 100%" in err and "3/3" in err
