import copy
import json
import re
import statistics
from pathlib import Path

import pytest

from factorydet_core.evaluation.bench import record_path, update_readme
from factorydet_core.evaluation.bench_tables import RENDERERS, fmt, record_line, render_record
from factorydet_core.types import InputError

DOCS = Path(__file__).parents[3] / "docs"
BLOCKS = (
    ("benchmarks.md", "simulate"),
    ("benchmarks.md", "pipeline"),
    ("benchmarks.md", "pipeline-corpus"),
    ("benchmarks.md", "pipeline-real"),
    ("benchmarks.md", "voxel-sweep"),
    ("benchmarks.md", "classifier"),
    ("performance.md", "detect"),
    ("performance.md", "memory"),
    ("performance.md", "mining-demo-reviewed"),
    ("performance.md", "mining-demo-reviewed-folds"),
    ("labelling.md", "world-labels"),
    ("labelling.md", "walkthrough"),
    ("labelling.md", "walkthrough-object-verdicts"),
    ("labelling.md", "walkthrough-object-verdicts-metrics-at-once"),
    ("labelling.md", "walkthrough-object-verdicts-metrics-quiet"),
    ("labelling.md", "walkthrough-edits-points-all"),
    ("labelling.md", "walkthrough-edits-no-shadows"),
    ("labelling.md", "walkthrough-edits-points-20k-no-grid"),
    ("labelling.md", "walkthrough-edits-page-clock"),
    ("labelling.md", "walkthrough-edits-page-clock-20k-no-grid"),
    ("labelling.md", "walkthrough-edits-page-clock-settled"),
    ("labelling.md", "walkthrough-page-clock"),
    ("labelling.md", "walkthrough-edits-points-20k"),
    ("labelling.md", "walkthrough-edits-points-20k-swiftshader"),
    ("review-loop.md", "hitl-50-class-vs-place"),
    ("review-loop.md", "hitl-50-refit-vs-class"),
    ("review-loop.md", "hitl-50-refit100-vs-refit"),
    ("review-loop.md", "hitl-50-safe-recal-vs-hold"),
    ("review-loop.md", "hitl-pool-tune-sparse-twelve"),
)


def _record(name: str) -> dict:
    """A benchmark's real record, migrated from the page (a fixture that is also the page's source)."""
    return json.loads((DOCS / "bench" / f"{name}.json").read_text())


def _rows(markdown: str, first_cell: str) -> list[list[str]]:
    """The cells of every table row whose first cell is ``first_cell``."""
    rows = [
        [c.strip() for c in line.strip("|").split("|")]
        for line in markdown.splitlines()
        if line.startswith("|")
    ]
    return [row for row in rows if row[0] == first_cell]


def test_every_benchmark_on_the_page_has_a_renderer():
    assert {_record(name)["benchmark"] for _, name in BLOCKS} <= set(RENDERERS)
    with pytest.raises(InputError, match="no table renderer for benchmark 'nope'"):
        render_record({"benchmark": "nope"})


def test_simulate_table_gives_seconds_per_frame_and_points():
    record = _record("simulate")
    (row,) = _rows(render_record(record), fmt(record["num_frames"]))
    assert fmt(record["seconds_per_frame_median"]) in row and fmt(record["seconds_per_frame_max"]) in row
    assert fmt(record["points_per_frame_median"]) in row


@pytest.mark.parametrize("name", ["pipeline", "pipeline-corpus", "pipeline-real"])
def test_pipeline_table_gives_recall_and_bounds_per_class_and_stage_times(name):
    record = _record(name)
    text = render_record(record)
    for cls, entry in record["proposal_recall"].items():
        (row,) = _rows(text, f"**{cls}**" if cls == "all" else cls)
        segment = record["segment_recall_point_iou"][cls]["recall"]
        option = record["option_recall"][cls]["recall"] if record["option_recall"] else None
        assert row[1:4] == [fmt(entry["num"]), fmt(entry["recall"], 3), fmt(segment, 3)]
        assert row[-1] == fmt(option, 3)
    (stage_row,) = _rows(text, fmt(record["stage_ms_median"]["merge"]))
    assert fmt(record["stage_ms_median"]["total"]) in stage_row
    assert fmt(record["features"]["points_per_second"]) in text
    assert (record["calibration"] is None) == ("ICP calibration" not in text)


def test_pipeline_table_without_calibration_or_options():
    record = copy.deepcopy(_record("pipeline"))
    record["option_recall"], record["calibration"], record["overrides"] = None, None, {"voxel_size_m": 0.2}
    text = render_record(record)
    (row,) = _rows(text, "barrel")
    assert row[-1] == "–" and "ICP" not in text and "{'voxel_size_m': 0.2}" in text


def test_voxel_sweep_table_has_a_row_per_voxel_size():
    record = _record("voxel-sweep")
    text = render_record(record)
    classes = list(record["point_segmentation_recall"])
    for size in record["voxel_segmentation"]:
        (row,) = _rows(text, fmt(size["voxel_size_m"]))
        assert row[1:] == [
            *(fmt(size["recall"][c], 3) for c in classes),
            fmt(size["segment_recall"], 3),
            fmt(size["total_ms"]),
        ]
    (reference,) = _rows(text, "points (reference)")
    assert reference[1 : 1 + len(classes)] == [
        fmt(record["point_segmentation_recall"][c], 3) for c in classes
    ]


def test_classifier_table_has_a_row_per_configuration():
    record = _record("classifier")
    text = render_record(record)
    rows = [r for r in (_rows(text, "aggregated") + _rows(text, "direct"))]
    assert len(rows) == len(record["rows"])
    for configuration in record["rows"]:
        key = [fmt(configuration[k]) for k in ("feature", "geometry", "width")]
        (row,) = [r for r in rows if r[:3] == key]
        assert fmt(configuration["detection_f1"], 3) in row and fmt(configuration["detection_map"], 3) in row
        assert fmt(configuration["epochs_run"]) == row[4]


def test_detect_table_gives_each_stage_and_the_total():
    record = _record("detect")
    text = render_record(record)
    stages = record["stage_ms_median"]
    header = next(line for line in text.splitlines() if "| merge |" in line)
    assert "| total |" in header and "| classification |" in header
    (row,) = _rows(text, "median")
    assert row[1 : 1 + len(stages)] == [fmt(ms) for ms in stages.values()]
    assert f"{record['detections_per_frame_median']} detections per frame" in text


def test_detect_table_gives_the_90th_percentile_peak_memory_and_the_comparison():
    record = {
        **_record("detect"),
        "stage_ms_median": {"merge": 10.0, "total": 40.0},
        "stage_ms_p90": {"merge": 12.5, "total": 44.0},
        "peak_rss_mb": 812.5,
        "compare": {
            "model": "m.pt", "overrides": {"voxel_size": 0.2},
            "stage_ms_median": {"merge": 5.0, "total": 30.0},
            "ratio_of_medians": {"merge": 0.5, "total": 0.75},
        },
    }  # fmt: skip
    text = render_record(record)
    assert _rows(text, "90th percentile")[0][1:3] == [fmt(12.5), fmt(44.0)]
    assert _rows(text, "compared / reference")[0][1:3] == ["0.5", "0.75"]
    assert "voxel_size=0.2" in text and "812.5 MB" in text


def test_import_table_gives_both_times():
    record = json.loads((DOCS / "bench" / "label_import.json").read_text())
    (row,) = _rows(render_record(record), fmt(record["num_boxes"]))
    assert fmt(record["import_seconds_median"]) in row
    assert fmt(record["reimport_all_duplicates_seconds_median"]) in row


def test_figures_are_formatted_as_recorded():
    assert fmt(None) == "–" and fmt(True) == "yes" and fmt(1638) == "1,638" and fmt(1645.5) == "1,645.5"
    assert fmt(0.5, 3) == "0.500" and fmt(0.0642) == "0.0642" and fmt("a|b") == "a\\|b"


@pytest.mark.parametrize(("page_name", "name"), BLOCKS)
def test_the_page_shows_what_its_records_render_to(page_name, name):
    # No figure on the page is typed by hand: each block is its record's rendering. After changing a
    # renderer, re-render with update_readme(page, json.loads(record.read_text()), name).
    page = (DOCS / page_name).read_text()
    block = re.search(rf"<!-- bench:{name} -->\n(.*?)\n<!-- /bench:{name} -->", page, re.S).group(1)
    record = _record(name)
    assert block == render_record(record).strip() + "\n\n" + record_line(record, f"bench/{name}.json")


def _page(tmp_path: Path) -> Path:
    page = tmp_path / "docs" / "benchmarks.md"
    page.parent.mkdir()
    page.write_text(
        "# B\n\n<!-- bench:simulate -->\nold\n<!-- /bench:simulate -->\n\n"
        "<!-- bench:sim-b -->\nold b\n<!-- /bench:sim-b -->\nend\n"
    )
    return page


def test_update_readme_writes_the_record_beside_and_its_table_in_the_block(tmp_path):
    page = _page(tmp_path)
    record = _record("simulate")
    update_readme(page, record)
    assert record_path(page, "simulate") == tmp_path / "docs" / "bench" / "simulate.json"
    assert json.loads(record_path(page, "simulate").read_text()) == record
    text = page.read_text()
    assert "old\n" not in text and "old b" in text and text.endswith("<!-- /bench:sim-b -->\nend\n")
    assert f"| {fmt(record['seconds_per_frame_median'])} |" in text
    assert "[bench/simulate.json](bench/simulate.json)" in text and f"`{record['command']}`" in text
    assert '"seconds_per_frame_median"' not in text  # The JSON is in its file, not on the page.
    # A second block of the same benchmark gets its own record.
    update_readme(page, record, "sim-b")
    assert record_path(page, "sim-b").is_file() and "old b" not in page.read_text()
    assert "[bench/sim-b.json](bench/sim-b.json)" in page.read_text()


def test_update_readme_with_its_callers_markdown_writes_no_record(tmp_path):
    page = _page(tmp_path)
    update_readme(page, {"benchmark": "simulate"}, markdown="| a |\n|---|\n| 1 |\n")
    assert "<!-- bench:simulate -->\n| a |\n|---|\n| 1 |\n<!-- /bench:simulate -->" in page.read_text()
    assert not (tmp_path / "docs" / "bench").exists()


@pytest.mark.parametrize(
    ("record", "name", "message"),
    [
        ({"benchmark": "simulate"}, "missing", "no '<!-- bench:missing -->' block"),
        ({"benchmark": "simulate"}, "a b", "letters, digits"),
        ({"benchmark": "fuzz"}, "simulate", "no table renderer"),
    ],
)
def test_update_readme_refuses_before_writing_anything(tmp_path, record, name, message):
    page = _page(tmp_path)
    before = page.read_text()
    with pytest.raises(InputError, match=re.escape(message)):
        update_readme(page, record, name)
    assert page.read_text() == before and not (tmp_path / "docs" / "bench").exists()


def test_the_demo_s_mining_records_hold_it_to_the_labelling_issue_s_targets():
    from factorydet_core.evaluation.bench import mining_targets

    assert mining_targets("demo") == {"target_seconds": 180.0, "target_full_run_seconds": 600.0}
    assert mining_targets("corpus-head") == {"target_seconds": 300.0}
    demo = _record("mining-demo-reviewed-folds")
    assert demo["session"] == "demo" and demo["target_seconds"] == 180.0
    assert "target 180.0 s per round and 600.0 s per full run." in render_record(demo)
    corpus = _record("mining")
    assert corpus["session"] != "demo" and "full_run" not in corpus["configs"][0]
    assert f"target {fmt(corpus['target_seconds'])} s per round." in render_record(corpus)


def test_mining_table_gives_each_configurations_time_parts_and_heldout_figures():
    record = _record("mining")
    text = render_record(record)
    for config in record["configs"]:
        kind = "continued" if config["continued"] else "afresh"
        (row,) = _rows(text, f"{kind}, {config['epochs']} epochs")
        assert row[1:5] == [fmt(config[k]) for k in ("seconds", "box_quality_seconds", "fit_seconds",
                                                     "score_seconds")]  # fmt: skip
        assert fmt(config["peak_rss_mb"]) in row and fmt(config["speedup_vs_afresh"]) in row
        if "heldout" in record:
            assert fmt(config["heldout"]["f1"], 3) in row
    assert f"target {fmt(record['target_seconds'])} s" in text
    # A round after verdicts says so, and what became of the box quality regressor.
    record = copy.deepcopy(record)
    record["verdicts"] = 20
    for config in record["configs"]:
        config["box_quality"] = "fitted"
    text = render_record(record)
    assert "the first 20 items of each copy's review queue were answered Object" in text
    config = record["configs"][0]
    kind = "continued" if config["continued"] else "afresh"
    assert _rows(text, f"{kind}, {config['epochs']} epochs (box quality fitted)")


def _hitl_record(f1: dict[str, list[float]], settings: dict, seeds=(0, 1, 2)) -> dict:
    """A complete bench hitl record with these per-seed F-scores (mAP = F + 0.1)."""
    return {
        "benchmark": "hitl",
        "complete": True,
        "command": "factorydet bench hitl x",
        "data": "x",
        "train_frames": [0],
        "test_frames": [1],
        "iou_threshold": 0.6,
        "seeds": list(seeds),
        "plan": {"data": "x", "review_by": "place", "settings": settings, "seeds": list(seeds)},
        "per_seed": {
            name: [{"seed": s, "f1": f, "map": f + 0.1} for s, f in zip(seeds, values)]
            for name, values in f1.items()
        },
    }


def test_two_hitl_records_are_compared_seed_by_seed_on_what_they_share():
    from factorydet_core.evaluation.hitl import compare_hitl_records

    record = _hitl_record(
        {"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.26, 0.27, 0.25], "full": [0.3, 0.3, 0.3]},
        {"queue_order": "class", "epochs": 5},
    )
    # Written before queue_order existed: it ran with the default (score), and one seed more.
    baseline = _hitl_record(
        {"blind": [0.20, 0.22, 0.21, 0.2], "reviewed_200": [0.24, 0.25, 0.24, 0.2], "reviewed_50": [0.2] * 4},
        {"epochs": 5},
        seeds=(0, 1, 2, 3),
    )
    result = compare_hitl_records(record, baseline, names=("a.json", "b.json"))
    # The review followed the queue order in both (review_order None): it differs with it.
    assert result["differs"] == {"queue_order": ["class", "score"], "review_order": ["class", "score"]}
    assert result["seeds"] == [0, 1, 2] and not result["one_record"]
    assert list(result["variants"]) == ["blind", "reviewed_200"]  # full and reviewed_50: one record each
    reviewed = result["variants"]["reviewed_200"]
    assert reviewed["f1"]["mean"] == pytest.approx(0.0167, abs=1e-4)
    assert reviewed["map"]["mean"] == reviewed["f1"]["mean"]
    assert reviewed["gain_over_blind"]["mean"] == reviewed["f1"]["mean"]  # the same blind mining
    table = render_record(result)
    assert "`a.json` minus `b.json`, seed by seed (seeds 0, 1, 2)" in table
    assert "What differs: queue_order: class against score; review_order: class against score." in table
    # A setting is said as its flag gives it: review_extra "all" is -1 (stored as None).
    longer = _hitl_record(
        {"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.26, 0.27, 0.25]},
        {"queue_order": "class", "epochs": 5, "review_extra": None},
    )
    shorter = _hitl_record(
        {"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.26, 0.27, 0.25]},
        {"queue_order": "class", "epochs": 5, "review_extra": 0},
    )
    differs = compare_hitl_records(longer, shorter, names=("a.json", "b.json"))
    assert "What differs: review_extra: -1 against 0." in render_record(differs)
    # A choice the controls no longer offer is said as stored, not refused.
    gone = render_record({**differs, "differs": {"queue_order": ["gone", "class"]}})
    assert "What differs: queue_order: gone against class." in gone
    assert _rows(table, "blind")[0][3] == "–" and _rows(table, "reviewed_200")[0][1].startswith("+0.017 [")
    with pytest.raises(InputError, match="b.json: not a complete bench hitl record"):
        compare_hitl_records(record, {**baseline, "complete": False}, names=("a.json", "b.json"))
    with pytest.raises(InputError, match="ran on other test frames"):
        compare_hitl_records(record, {**baseline, "test_frames": [2]}, names=("a.json", "b.json"))
    with pytest.raises(InputError, match="share no seed"):
        compare_hitl_records(record, _hitl_record({"blind": [0.2]}, {}, seeds=(9,)), names=("a", "b"))
    # A broken record is an error, not a traceback: no blind mining, or a detector short a seed.
    without_blind = {**baseline, "per_seed": {k: v for k, v in baseline["per_seed"].items() if k != "blind"}}
    with pytest.raises(InputError, match="b.json: no blind mining runs"):
        compare_hitl_records(record, without_blind, names=("a.json", "b.json"))
    short = {
        **baseline,
        "per_seed": {**baseline["per_seed"], "reviewed_200": baseline["per_seed"]["reviewed_200"][1:]},
    }
    with pytest.raises(InputError, match="b.json: reviewed_200 has no run of seed 0"):
        compare_hitl_records(record, short, names=("a.json", "b.json"))


def test_two_detectors_of_one_hitl_record_are_compared_seed_by_seed_with_their_in_factory_scores():
    from factorydet_core.evaluation.hitl import compare_hitl_records

    record = _hitl_record(
        {
            "blind": [0.20, 0.22, 0.21],
            "reviewed_200": [0.24, 0.25, 0.24],
            "reviewed_safe_200": [0.26, 0.25, 0.27],
        },
        {"epochs": 5},
    )
    for runs, in_factory in zip(
        record["per_seed"].values(), ([0.3] * 3, [0.31, 0.30, 0.32], [0.31, 0.32, 0.32])
    ):
        for run, value in zip(runs, in_factory):
            run["in_factory"] = {"f1": value}
    record["heldout_factories"] = [{"seed": 101, "frames": 12}]
    result = compare_hitl_records(
        record, record, names=("a.json", "a.json"), pair=("reviewed_safe_200", "reviewed_200")
    )
    assert result["differs"] == {} and result["heldout"]
    (name,) = result["variants"]
    assert name == "reviewed_safe_200 minus reviewed_200"
    row = result["variants"][name]
    assert (row["variant"], row["baseline_variant"]) == ("reviewed_safe_200", "reviewed_200")
    assert row["f1"]["mean"] == pytest.approx(0.0167, abs=1e-4)
    assert row["gain_over_blind"]["mean"] == row["f1"]["mean"]  # one record: the same blind mining
    assert row["in_factory_f1"]["mean"] == pytest.approx(0.0067, abs=1e-4)
    table = render_record(result)
    assert "`a.json`, seed by seed (seeds 0, 1, 2): mean [95% interval] on the held-out factories." in table
    assert "What differs" not in table and "F-score in-factory" in table
    (cells,) = _rows(table, name)
    assert cells[1].startswith("+0.017 [") and cells[4].startswith("+0.007 [")
    with pytest.raises(InputError, match="against itself in one record"):
        compare_hitl_records(record, record, names=("a.json", "a.json"), pair=("blind", "blind"))
    # Two copies of one record are two records: what differs is said (nothing here).
    twin = compare_hitl_records(
        record, copy.deepcopy(record), names=("a.json", "a.json"), pair=("reviewed_safe_200", "reviewed_200")
    )
    assert not twin["one_record"] and "What differs: nothing." in render_record(twin)
    with pytest.raises(InputError, match="a.json did not run 'reviewed_50'; it ran blind, reviewed_200"):
        compare_hitl_records(record, record, names=("a.json", "a.json"), pair=("reviewed_50", "blind"))
    # Runs without in-factory scores (older records) leave the column out.
    plain = _hitl_record({"blind": [0.2, 0.2, 0.2], "full": [0.3, 0.31, 0.3]}, {})
    table = render_record(compare_hitl_records(plain, plain, names=("b", "b"), pair=("full", "blind")))
    assert "in-factory" not in table and _rows(table, "full minus blind")
    assert "fitted frames" not in table
    # Runs with thresholds tuned out of fold: the same networks at their fitted frames' thresholds.
    for runs, fitted in zip(plain["per_seed"].values(), ([0.19, 0.2, 0.2], [0.25, 0.26, 0.24])):
        for run, value in zip(runs, fitted):
            run["fitted_frame_thresholds"] = {"f1": value}
    result = compare_hitl_records(plain, plain, names=("b", "b"), pair=("full", "blind"))
    assert result["variants"]["full minus blind"]["fitted_frame_f1"]["mean"] == pytest.approx(
        0.0533, abs=1e-4
    )
    table = render_record(result)
    (cells,) = _rows(table, "full minus blind")
    assert "F-score at the fitted frames' thresholds" in table and cells[4].startswith("+0.053 [")


def test_world_labels_table_sweeps_the_least_points_that_show_an_object():
    record = copy.deepcopy(_record("world-labels"))
    app = next(m for name, m in record["methods"].items() if "(the app)" in name)
    bins = list(app["shown_by_points"])
    app["shown_by_min_points"] = {
        str(m): {"shown_by_points": dict.fromkeys(bins, 0.5 / m), "shown_without_points": 0.01 * m}
        for m in (1, 2, 3)
    }
    text = render_record(record)
    names = {m: f"{m} (the app)" if m == record["min_points"] else str(m) for m in (1, 2, 3)}
    assert _rows(text, names[3]) == [[names[3], *[fmt(0.5 / 3, 3)] * len(bins), fmt(0.03, 3)]]
    assert record["min_points"] in names and _rows(text, names[record["min_points"]])
    # Why frames with points of the object are left out, where the record counted it.
    app["misses_by_cause"] = {
        b: {"thinning": 0, "pose": 1, "floor": 2 * k, "margin": 3} for k, b in enumerate(bins)
    }
    text = render_record(record)
    first = bins[0]
    assert _rows(text, first) == [
        [first, fmt(app["frames_by_points"][first]), fmt(4), fmt(0), fmt(1), fmt(0), fmt(3)]
    ]
    assert "floor band only" in text
    del app["misses_by_cause"]
    assert "floor band only" not in render_record(record)
    # Records from before the sweep render without it.
    del app["shown_by_min_points"]
    assert "least points that show" not in render_record(record)


def test_every_resumed_hitl_command_of_the_makefile_reviews_in_the_order_its_record_ran():
    # A `make bench` line whose reviewer's order (its flag, else today's default) is not the one
    # its record ran with would train the reviewed detectors again instead of resuming them.
    import shlex

    from factorydet_core.cli import build_parser
    from factorydet_core.evaluation.hitl import _settings_as_run, reviewer_order
    from factorydet_core.training.settings import loop_settings_from

    makefile = (DOCS.parent / "Makefile").read_text().replace("\\\n", " ")
    commands = [line.split(" bench hitl ", 1)[1] for line in makefile.splitlines() if " bench hitl " in line]
    checked = 0
    for command in commands:
        words = shlex.split(command.replace("$(", "").replace(")", ""))  # $(CORPUS): a data set name
        args = build_parser().parse_args(["bench", "hitl", *words])
        variants = None if args.variants is None else args.variants.split(",")
        if not args.resume or (variants is not None and not any(v.startswith("reviewed_") for v in variants)):
            continue  # trained afresh, or nobody reviews
        record = json.loads(Path(DOCS.parent / args.out).read_text())
        settings = loop_settings_from({"queue_order": args.queue_order, "review_order": args.review_order})
        ours = reviewer_order(
            {"queue_order": settings.queue_order, "review_order": settings.review_order}, args.review_by
        )
        plan = record["plan"]
        assert ours == reviewer_order(_settings_as_run(plan["settings"]), plan["review_by"]), args.out
        checked += 1
    assert checked >= 15  # the reviewed held-out records and the place-by-place ones


def test_every_resumed_hitl_command_of_the_makefile_trains_its_reviewer_as_its_record_ran():
    # The reviewer's runs of a `make bench` line resume from its record only when the line's flags
    # (else today's defaults) give the settings those runs had: a default changed since, without a
    # flag that keeps the record's value, would train them again.
    import dataclasses
    import shlex

    from factorydet_core.cli import build_parser, hitl_settings
    from factorydet_core.evaluation.hitl import _run_plan, _settings_as_run

    makefile = (DOCS.parent / "Makefile").read_text().replace("\\\n", " ")
    commands = [line.split(" bench hitl ", 1)[1] for line in makefile.splitlines() if " bench hitl " in line]
    checked = 0
    for command in commands:
        words = shlex.split(command.replace("$(", "").replace(")", ""))
        args = build_parser().parse_args(["bench", "hitl", *words])
        if not args.resume:
            continue
        plan = json.loads(Path(DOCS.parent / args.out).read_text())["plan"]
        # (bench_hitl keeps the mining rounds in the plan, its settings' rounds at 0)
        ours = json.loads(json.dumps(dataclasses.asdict(dataclasses.replace(hitl_settings(args), rounds=0))))
        ours = {k: v for k, v in ours.items() if k not in ("seed", "num_threads")}
        reviewed = [v for v in plan["variants"] if v.startswith("reviewed_")]
        for variant in reviewed:
            theirs = {**plan, "settings": _settings_as_run(plan["settings"])}
            differs = {
                k: (v, theirs["settings"].get(k)) for k, v in ours.items() if theirs["settings"].get(k) != v
            }
            assert _run_plan({**plan, "settings": ours}, variant) == _run_plan(theirs, variant), (
                args.out,
                variant,
                differs,
            )
            checked += 1
    assert checked >= 15


def test_the_walkthrough_says_what_drew_its_webgl():
    record = _record("walkthrough-swiftshader")  # from before the renderer was recorded
    assert "in software WebGL (Chromium's SwiftShader)" in render_record(record)
    llvmpipe = {
        **record,
        "webgl_renderer": "ANGLE (Mesa/X.org, llvmpipe (LLVM 15.0.6 256 bits), OpenGL ES 3.2)",
    }
    assert "in software WebGL (Mesa's llvmpipe through ANGLE)" in render_record(llvmpipe)
    assert "in WebGL (NVIDIA GeForce)" in render_record({**record, "webgl_renderer": "NVIDIA GeForce"})
    assert "in WebGL (its renderer unknown)" in render_record({**record, "webgl_renderer": None})


def test_the_walkthrough_says_how_many_points_it_drew_and_under_what_budget():
    record = _record("walkthrough-swiftshader")
    assert "(80k points, the boxes)" in render_record(record)  # a record from before the budget
    budgeted = {**record, "points_drawn": 20_000, "points_shown": 19_873}
    assert "(19,873 points, at most 20,000 by Display's Points drawn, the boxes)" in render_record(budgeted)
    every_point = {**record, "points_drawn": None, "points_shown": 81_002}
    assert "(81,002 points, the boxes)" in render_record(every_point)
    no_grid = {**every_point, "show_grid": False}
    assert "(81,002 points, the boxes, no floor grid)" in render_record(no_grid)


def test_the_walkthrough_says_how_often_the_page_renders_where_its_record_counted_it():
    record = _record("walkthrough-swiftshader")
    assert "of the scene with nothing sent" not in render_record(record)  # a record from before the count
    counted = {
        **record,
        "browser_render": {
            **record["browser_render"],
            "render_window_s": 1.0,
            "renders_idle_median": 1.0,
            "renders_after_a_notification_median": 1.0,
            "renders_after_a_scene_change_median": 3.0,
            "few_points": 1000,
            "scene_render_ms_few_points": 120.5,
            "notification_alone_median_ms": 64.2,
        },
    }
    # (the render counts once took the notification's milliseconds' place: "takes 1 render ms")
    assert "a notification alone takes 64.2 ms to show" in render_record(counted)
    assert "With at most 1,000 points drawn, one render still takes 120.5 ms." in render_record(counted)
    assert (
        "In 1.0 s the page begins 1 render of the scene with nothing sent, 1 render after a notification"
        " alone and 3 renders after a scene change (medians)"
    ) in render_record(counted)


def test_the_walkthrough_says_what_viser_s_shadows_would_cost_where_it_measured_them():
    record = _record("walkthrough-swiftshader")
    assert "casts shadows" not in render_record(record)  # a record from before the measurement
    shadows = {
        "scene_render_ms_shadows_on": [150.0, 140.0, 160.0],
        "scene_render_ms_shadows_off": [130.0, 145.0, 140.0],
        "shadows_on_median_ms": 150.0,
        "shadows_off_median_ms": 140.0,
        "shadows_paired_difference_median_ms": 20.0,
        "shadows_pairs": 3,
        "shadows_slower_pairs": 2,
    }
    measured = {**record, "browser_render": {**record["browser_render"], "shadows": shadows}}
    assert (
        "with them, one render takes 150.0 ms against 140.0 ms without (medians of 3 and 3 turns in the"
        " same page), 20.0 ms more a render (the median of the 3 paired differences; more in 2 of them)."
    ) in render_record(measured)
    # A turn too short to time is not counted; with no pair timed on both sides, nothing is said.
    one_short = {**shadows, "scene_render_ms_shadows_off": [130.0, None, 140.0], "shadows_pairs": 2}
    measured["browser_render"]["shadows"] = one_short
    assert "(medians of 3 and 2 turns in the same page)" in render_record(measured)
    assert "the median of the 2 paired differences" in render_record(measured)
    none_paired = {**one_short, "shadows_paired_difference_median_ms": None, "shadows_pairs": 0}
    measured["browser_render"]["shadows"] = none_paired
    assert "casts shadows" not in render_record(measured)


def test_the_walkthrough_says_what_the_browser_spent_with_the_training_panel_open_where_measured():
    record = _record("walkthrough")
    before = {**record, "retrain": {"full_run_shown_s": 600.0, "next_round_shown_s": 150.0}}
    assert "with the Training panel open" not in render_record(before)  # a record from before it
    measured = {
        **record,
        "retrain": {
            **before["retrain"],
            "browser_cores_idle": 0.31,
            "browser_cores_training_open": 0.33,
            "browser_cores_training_open_animated_bar": 1.72,
        },
    }
    assert (
        "the browser used 0.31 of the machine's cores, 0.33 with the Training panel open (its bar still,"
        " as the app draws it) and 1.72 with the bar animated"
    ) in render_record(measured)
    assert "after the 20 review verdicts above, in a row, background and skip (keyboard)" in render_record(
        {**measured, "num_verdicts": 20, "verdict_keys": "bxbbx"}
    )
    objects = render_record({**measured, "num_verdicts": 20, "verdict_keys": "bobxo"})
    assert "in a row, 8 of them Object (the labels changed) (keyboard)" in objects


def test_a_hitl_compare_says_how_precision_and_recall_moved_where_both_records_kept_them():
    from factorydet_core.evaluation.hitl import compare_hitl_records

    record = _hitl_record({"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.26, 0.27, 0.25]}, {"epochs": 5})
    baseline = _hitl_record({"blind": [0.20, 0.22, 0.21], "reviewed_200": [0.26, 0.27, 0.25]}, {"epochs": 5})
    assert "precision" not in render_record(compare_hitl_records(record, baseline, names=("a", "b")))
    for rec, (precision, recall) in ((record, (0.4, 0.2)), (baseline, (0.3, 0.25))):
        for runs in rec["per_seed"].values():
            for run in runs:
                run["precision"], run["recall"] = precision, recall
    result = compare_hitl_records(record, baseline, names=("a", "b"))
    reviewed = result["variants"]["reviewed_200"]
    assert reviewed["precision"]["mean"] == pytest.approx(0.1) and reviewed["recall"][
        "mean"
    ] == pytest.approx(-0.05)
    table = render_record(result)
    assert "| precision | recall |" in table
    assert _rows(table, "reviewed_200")[0][-2:] == ["+0.100 [+0.100, +0.100]", "-0.050 [-0.050, -0.050]"]


def test_the_walkthrough_splits_its_review_verdicts_by_key_where_they_had_several():
    record = _record("walkthrough-object-verdicts")  # keys bobxo: 8 background, 8 Object, 4 skip
    runs = record["steps"]["review verdict (B / O / X)"]["runs"]
    markdown = render_record(record)
    object_row = _rows(markdown, "of them, Object (O; 8)")[0]
    picked = [k for k in range(len(runs["shown"])) if "bobxo"[k % 5] == "o"]
    assert float(object_row[2].replace(",", "")) == round(
        statistics.median(runs["server"][k] for k in picked), 1
    )
    assert float(object_row[4].replace(",", "")) == max(runs["shown"][k] for k in picked)
    assert len(_rows(markdown, "of them, skip (X; 4)")) == 1
    # One key, or none recorded: the verdicts' row alone.
    for keys in ("b", None):
        alone = render_record({**record, "verdict_keys": keys})
        assert "of them," not in alone and "| review verdict (B / O / X) |" in alone


def test_the_walkthrough_gives_the_times_in_the_pages_own_clock_where_it_timed_them():
    record = _record("walkthrough-object-verdicts")  # from before the page's clock: no such column
    markdown = render_record(record)
    assert "drawn (page's clock)" not in markdown and "the page's own clock" not in markdown
    steps = {}
    for k, (step, figures) in enumerate(record["steps"].items()):
        runs = figures["runs"]
        page = [shown - 50.0 - k for shown in runs["shown"]]
        steps[step] = {
            **figures,
            "page_seen_median_ms": 1.0,
            "page_median_ms": round(statistics.median(page), 1),
            "page_max_ms": max(page),
            "runs": {**runs, "page_seen": [1.0] * len(page), "page": page},
        }
    markdown = render_record({**record, "steps": steps})
    assert "| drawn (page's clock), median ms | drawn, max ms | target ms |" in markdown
    assert "the page's own clock" in markdown and "as soon as the page showed the step before" in markdown
    settled = render_record({**record, "steps": steps, "settle_ms": 300.0})
    assert "once the page had drawn nothing for 300.0 ms" in settled
    verdicts = steps["review verdict (B / O / X)"]
    row = _rows(markdown, "review verdict (B / O / X)")[0]
    assert float(row[5].replace(",", "")) == verdicts["page_median_ms"] and len(row) == 8
    object_row = _rows(markdown, "of them, Object (O; 8)")[0]
    picked = [k for k in range(len(verdicts["runs"]["page"])) if "bobxo"[k % 5] == "o"]
    assert float(object_row[6].replace(",", "")) == max(verdicts["runs"]["page"][k] for k in picked)
