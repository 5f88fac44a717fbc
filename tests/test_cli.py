import json

from app.cli import main


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
    assert "old" not in text and '"seconds_per_frame_median"' in text and text.endswith("after\n")


def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such file" in err
    assert main(["simulate", "--out", str(tmp_path / "x"), "--unlabelled-fraction", "2"]) == 2
    assert "unlabelled_fraction" in capsys.readouterr().err
    assert main(["app", "--session", "../x", "--root", str(tmp_path)]) == 2
    assert "invalid session name" in capsys.readouterr().err


def test_propose_json_on_a_simulated_frame(small_dataset_dir, capsys):
    assert main(["propose", str(small_dataset_dir), "--frame", "1", "--json", "--no-calibrate"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["frame"] == 1 and record["preset"] == "agv"
    assert len(record["proposals"]) > 10
    for proposal in record["proposals"]:
        assert len(proposal["box"]) == 7 and all(v > 0 for v in proposal["box"][3:6])
        assert proposal["num_points"] >= 30


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


def test_bench_pipeline_prints_stage_times_and_recall(small_dataset_dir, capsys):
    assert main(["bench", "pipeline", str(small_dataset_dir), "--frames", "1", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["stage_ms_median"]) >= {"merge", "prune", "voxelize", "features", "segmentation"}
    assert result["features"]["max_abs_error_vs_reference"] < 1e-5
    assert result["features"]["speedup_over_reference"] > 1
    assert 0 <= result["proposal_recall"]["all"]["recall"] <= 1
    calibration = result["calibration"]
    assert (
        calibration["refined"]["point_10m_ahead_error_cm_median"]
        < calibration["nominal"]["point_10m_ahead_error_cm_median"]
    )
