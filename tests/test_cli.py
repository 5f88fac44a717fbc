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
