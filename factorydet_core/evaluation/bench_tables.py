"""Short Markdown tables of the benchmarks' headline figures, one renderer per benchmark, and the
writer of a page's benchmark blocks (``update_readme``).

A page shows the figures people compare (times, recalls, F-scores); the whole record, every class,
setting and machine detail, goes to a JSON file beside the page (``bench/<block>.json``) that the
table links to. Every number in a table is read from the record here, never typed into a page.
"""

from __future__ import annotations

import os
import re
import statistics
from collections.abc import Callable
from pathlib import Path

from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.io.jsonfile import write_json
from factorydet_core.types import InputError

Renderer = Callable[[dict], str]
"""A pure function from a benchmark's record to Markdown (a table and a line or two of context)."""

RENDERERS: dict[str, Renderer] = {}
"""Renderers by the record's ``benchmark`` field (not by the page block: two blocks of one
benchmark, on different data, share a renderer)."""


def register(*benchmarks: str) -> Callable[[Renderer], Renderer]:
    """Decorator: render the records of ``benchmarks`` with the decorated function."""

    def decorate(render: Renderer) -> Renderer:
        for name in benchmarks:
            RENDERERS[name] = render
        return render

    return decorate


def check_readme_block(readme: str | os.PathLike, name: str) -> None:
    """Raise ``InputError`` unless ``readme`` has a ``<!-- bench:name -->`` block (checked before a
    long benchmark, not after it)."""
    if not re.fullmatch(r"[A-Za-z0-9_-]+", name):
        raise InputError(f"README block names are letters, digits, '-' and '_', got {name!r}")
    path = Path(readme)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    text = path.read_text()
    if f"<!-- bench:{name} -->" not in text or f"<!-- /bench:{name} -->" not in text:
        raise InputError(f"{path}: no '<!-- bench:{name} -->' block to update")


def record_path(readme: str | os.PathLike, name: str) -> Path:
    """Where ``update_readme`` keeps the record of block ``name``: ``bench/<name>.json`` beside the
    page, so that the page links to it as ``bench/<name>.json``."""
    return Path(readme).parent / "bench" / f"{name}.json"


def update_readme(
    readme: str | os.PathLike, result: dict, name: str | None = None, markdown: str | None = None
) -> None:
    """Replace the block between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->`` with a table of
    ``result``'s headline figures; ``name`` defaults to the result's ``benchmark`` (a second block
    of the same benchmark, on other data, takes a name of its own).

    Without ``markdown`` the table comes from the benchmark's renderer (``bench_tables``), the whole
    record goes to ``record_path(readme, name)`` and the block ends with a line linking it and
    naming the command. With ``markdown`` the block is that text alone: its caller renders the
    table and writes the record itself (``bench hitl`` and ``bench quality`` with ``--out``). A
    missing block, or a benchmark without a renderer, is refused before anything is written; each
    file is written whole or not at all.
    """
    path = Path(readme)
    name = result["benchmark"] if name is None else name
    check_readme_block(path, name)
    text = path.read_text()
    pattern = re.compile(rf"<!-- bench:{name} -->.*?<!-- /bench:{name} -->", re.S)
    if not pattern.search(text):
        raise InputError(f"{path}: no '<!-- bench:{name} -->' block to update")
    record = None
    if markdown is None:
        record = record_path(path, name)
        link = record.relative_to(path.parent).as_posix()
        markdown = render_record(result).strip() + "\n\n" + record_line(result, link)
    block = f"<!-- bench:{name} -->\n{markdown.strip()}\n<!-- /bench:{name} -->"
    if record is not None:
        write_json(record, result)
    write_text_atomic(path, pattern.sub(lambda _: block, text))


def render_record(result: dict) -> str:
    """The Markdown of ``result`` by its benchmark's renderer; ``InputError`` for a benchmark with
    none (its caller must render its own table)."""
    name = result.get("benchmark")
    if name not in RENDERERS:
        raise InputError(f"no table renderer for benchmark {name!r} (have {', '.join(sorted(RENDERERS))})")
    return RENDERERS[name](result)


def record_line(result: dict, link: str) -> str:
    """The line under a table: a link to the whole record, where it ran and the command that
    produced it."""
    parts = [f"Record: [{link}]({link})"]
    machine = result.get("machine")
    if machine:
        parts.append(f"measured on {machine_text(machine)}")
    if result.get("command"):
        parts.append(f"by `{result['command']}`")
    return ", ".join(parts) + "."


def machine_text(machine: dict) -> str:
    """``Intel(R) Xeon(R) Processor, 2 cores, 23.5 GB``: what a time was measured on."""
    text = str(machine.get("cpu", "unknown CPU"))
    if machine.get("cores"):
        text += f", {machine['cores']} cores"
    if machine.get("memory_gb"):
        text += f", {machine['memory_gb']} GB"
    return text


def fmt(value: object, digits: int | None = None) -> str:
    """A figure as recorded: thousands separated, ``digits`` decimals when given (recalls and
    F-scores line up at three), an en dash for a figure the run did not measure."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float) and digits is not None:
        return f"{value:,.{digits}f}"
    if isinstance(value, (int, float)):
        return f"{value:,}"
    return str(value).replace("|", "\\|")  # A pipe would end the table cell.


def table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table of ``rows`` under ``header``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _frames(frames: list[int]) -> str:
    """``16–23`` for a run of consecutive frames, commas between runs: twenty test frames stay short."""
    runs: list[list[int]] = []
    for i in frames:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return ", ".join(f"{run[0]}–{run[-1]}" if len(run) > 2 else ", ".join(map(str, run)) for run in runs)


@register("simulate")
def simulate_markdown(result: dict) -> str:
    """Seconds per 12-sensor frame (median, max, first), set-up time and points per frame."""
    header = [
        "frames",
        "sensors",
        "points per frame (median)",
        "s per frame (median)",
        "s per frame (max)",
        "first frame (s)",
        "set-up (s)",
        "target (s per frame)",
    ]
    row = [
        fmt(result["num_frames"]),
        fmt(result["num_sensors"]),
        fmt(result["points_per_frame_median"]),
        fmt(result["seconds_per_frame_median"]),
        fmt(result["seconds_per_frame_max"]),
        fmt(result["first_frame_s"]),
        fmt(result["setup_s"]),
        fmt(result["target_seconds_per_frame"]),
    ]
    return table(header, [row]) + "\n"


@register("pipeline", "pipeline-real")
def pipeline_markdown(result: dict) -> str:
    """Per class: instances, proposal recall and its three bounds (segment, box fit on the true
    segment, box options); then the stage times, feature throughput and ICP calibration errors."""
    recall = result["proposal_recall"]
    bounds = [
        result.get("segment_recall_point_iou"),
        result.get("oracle_box_fit_recall"),
        result.get("option_recall"),
    ]
    rows = []
    for name, entry in recall.items():
        cells = [fmt(b[name]["recall"], 3) if b and name in b else fmt(None) for b in bounds]
        rows.append(
            [f"**{name}**" if name == "all" else name, fmt(entry["num"]), fmt(entry["recall"], 3), *cells]
        )
    iou = result["iou_threshold"]
    recall_table = table(
        [
            "class",
            "instances",
            f"proposal recall, box IoU {iou}",
            f"segment recall, point IoU {iou}",
            "box fit on the true segment",
            "best box option",
        ],
        rows,
    )
    stages = result["stage_ms_median"]
    stage_table = table(
        [*stages, "target", "proposals per frame"],
        [
            [
                *(fmt(ms) for ms in stages.values()),
                fmt(result["target_total_ms"]),
                fmt(result["proposals_per_frame_median"]),
            ]
        ],
    )
    context = f"Data `{result['data']}`, frames {_frames(result['frames'])}, preset `{result['preset']}`"
    if result.get("overrides"):
        context += f", settings changed: {result['overrides']}"
    lines = [recall_table, "", "Stage times, ms per frame (median over the frames):", "", stage_table]
    notes = [context + "."]
    features = result.get("features")
    if features:
        notes.append(
            f"Features: {fmt(features['points_per_second'])} points/s, "
            f"{fmt(features['speedup_over_reference'])} times the float64 reference."
        )
    calibration = result.get("calibration")
    if calibration:
        before, after = calibration["nominal"], calibration["refined"]
        notes.append(
            "ICP calibration (median over sensors, nominal → refined): rotation "
            f"{fmt(before['rotation_deg_median'])}° → {fmt(after['rotation_deg_median'])}°, translation "
            f"{fmt(before['translation_cm_median'])} → {fmt(after['translation_cm_median'])} cm, a point "
            f"10 m ahead {fmt(before['point_10m_ahead_error_cm_median'])} → "
            f"{fmt(after['point_10m_ahead_error_cm_median'])} cm."
        )
    return "\n".join(lines) + "\n\n" + " ".join(notes) + "\n"


@register("voxel-sweep")
def voxel_sweep_markdown(result: dict) -> str:
    """A row per voxel size: proposal recall per class with the cut pursuit on voxels, the segment
    recall and the front half's time; the point-segmentation recall as the reference row."""
    sizes = result["voxel_segmentation"]
    reference = result["point_segmentation_recall"]
    classes = list(reference)
    header = ["voxel size (m)", *classes, "segment recall", "total ms (median)"]
    rows = []
    if sizes:
        counts = sizes[0]["num"]  # The same frames at every size: the same instances.
        rows.append(["instances", *(fmt(counts.get(c)) for c in classes), "", ""])
    rows.append(["points (reference)", *(fmt(reference[c], 3) for c in classes), fmt(None), fmt(None)])
    for size in sizes:
        rows.append(
            [
                fmt(size["voxel_size_m"]),
                *(fmt(size["recall"].get(c), 3) for c in classes),
                fmt(size["segment_recall"], 3),
                fmt(size["total_ms"]),
            ]
        )
    return (
        table(header, rows)
        + f"\n\nProposal recall at box IoU {result['iou_threshold']}; data `{result['data']}`, "
        f"frames {_frames(result['frames'])}.\n"
    )


@register("classifier")
def classifier_markdown(result: dict) -> str:
    """A row per configuration (feature, descriptors, width): size, training time and epochs run,
    detection F-score, mAP, precision, recall and mean recognition accuracy."""
    header = [
        "feature",
        "geometry",
        "width",
        "parameters",
        "epochs run",
        "fit (s)",
        "F-score",
        "mAP",
        "precision",
        "recall",
        "recognition (mean over classes)",
    ]
    rows = [
        [
            fmt(row["feature"]),
            fmt(row["geometry"]),
            fmt(row["width"]),
            fmt(row["num_parameters"]),
            fmt(row["epochs_run"]),
            fmt(row["fit_seconds"]),
            fmt(row["detection_f1"], 3),
            fmt(row["detection_map"], 3),
            fmt(row["detection_precision"], 3),
            fmt(row["detection_recall"], 3),
            fmt(row["recognition_mean_class_accuracy"], 3),
        ]
        for row in result["rows"]
    ]
    quality = ", with box quality" if result.get("box_quality") else ", without box quality"
    return (
        table(header, rows)
        + f"\n\nData `{result['data']}`: training frames {_frames(result['train_frames'])}, test frames "
        f"{_frames(result['test_frames'])} against the {result['reference']}; up to {fmt(result['epochs'])} "
        f"epochs or {fmt(result['max_fit_seconds'])} s per fit; score threshold "
        f"{fmt(result['score_threshold'])} (probability exponent {fmt(result['probability_exponent'])})"
        f"{quality}.\n"
    )


@register("detect")
def detect_markdown(result: dict) -> str:
    """The whole detection's stage times (median ms per frame) and total, with detections per frame
    and the model's training time per round."""
    stages = result["stage_ms_median"]
    rows = [["median", *(fmt(ms) for ms in stages.values()), fmt(result["target_total_ms"])]]
    if "stage_ms_p90" in result:  # records from before the profile have medians only
        rows.append(["90th percentile", *(fmt(result["stage_ms_p90"].get(s)) for s in stages), ""])
    compare = result.get("compare")
    if compare:
        rows.append(["compared, median", *(fmt(compare["stage_ms_median"].get(s)) for s in stages), ""])
        rows.append(["compared / reference", *(fmt(compare["ratio_of_medians"].get(s)) for s in stages), ""])
    stage_table = table(["", *stages, "target"], rows)
    if compare and compare.get("checkout"):
        checkout = compare["checkout"]
        which = f"commit `{checkout['commit']}`" if checkout.get("commit") else f"`{checkout['path']}`"
        stage_table += (
            f"\n\nCompared: the project's code at {which} with the same model, in a child process, "
            "interleaved with the reference on the same frames."
        )
    elif compare:
        changed = ", ".join(f"{k}={v}" for k, v in compare["overrides"].items()) or "no setting changed"
        stage_table += (
            f"\n\nCompared: model `{Path(str(compare['model'])).name}`, {changed}; run interleaved "
            "with the reference on the same frames."
        )
    if "peak_rss_mb" in result:
        stage_table += f"\n\nPeak memory of the process: {fmt(result['peak_rss_mb'])} MB."
    busy = result.get("busy")
    if busy:
        stage_table += (
            "\n\nBeside one other process spinning a core (the reference, interleaved):\n\n"
            + table(
                ["", *stages],
                [
                    ["busy, median", *(fmt(busy["stage_ms_median"].get(s)) for s in stages)],
                    ["busy / quiet", *(fmt(busy["ratio_of_medians"].get(s)) for s in stages)],
                ],
            )
        )
    heldout = result.get("heldout")
    if heldout:
        names = [n for n in ("reference", "compared") if n in heldout]
        rows = [
            [name, *(fmt(heldout[name][k], 3) for k in ("f1", "map", "precision", "recall")),
             fmt(heldout[name]["back_half_ms_per_frame"])]
            for name in names
        ]  # fmt: skip
        stage_table += (
            "\n\nOn the held-out factories (seeds "
            + ", ".join(str(s) for s in heldout["seeds"])
            + f", {heldout['frames_per_factory']} frames each), IoU 0.6 against the truth:\n\n"
            + table(["", "F-score", "mAP", "precision", "recall", "back half, ms per frame"], rows)
        )
        if "f1_difference" in heldout:
            stage_table += (
                f"\n\nCompared minus reference: F-score {heldout['f1_difference']:+.4f}, "
                f"mAP {heldout['map_difference']:+.4f}."
            )
    training = result.get("training_seconds_per_round")
    if isinstance(training, list):
        training = ", ".join(fmt(s) for s in training)
    return (
        "Stage times, ms per frame over the frames:\n\n"
        + stage_table
        + f"\n\nModel `{Path(str(result['model'])).name}` (width {fmt(result['width'])}, "
        f"{fmt(result['num_parameters'])} parameters) on data `{result['data']}`, frames "
        f"{_frames(result['frames'])} ({fmt(result['points_per_frame_median'])} points per frame, "
        f"median): {fmt(result['detections_per_frame_median'])} detections per frame (median). "
        f"Training, s per round: {fmt(training)}.\n"
    )


@register("memory")
def memory_markdown(result: dict) -> str:
    """Per dense scan: its points, what crop, pruning and the cap leave, the point sets, the time and
    the child process's peak memory against the target."""
    header = [
        "points read",
        "after crop, prune, cap",
        "point sets",
        "detections",
        "seconds",
        "peak MB",
        "target MB",
    ]
    rows = []
    for run in result["runs"]:
        if "error" in run:
            rows.append([fmt(run["points"]), run["error"], "", "", "", "", fmt(result["target_peak_mb"])])
            continue
        rows.append(
            [
                fmt(run["points_read"]),
                fmt(run["points_after_crop_prune_cap"]),
                fmt(run["num_point_sets"]),
                fmt(run["num_detections"]),
                fmt(run["seconds"]),
                fmt(run["peak_rss_mb"]),
                fmt(result["target_peak_mb"]),
            ]
        )
    changed = ", ".join(f"{k}={v}" for k, v in result.get("overrides", {}).items()) or "none"
    text = (
        table(header, rows)
        + f"\n\nModel `{Path(str(result['model'])).name}`; front-half settings changed: {changed}."
    )
    if "seconds_ratio_largest_to_smallest" in result:
        text += (
            f" Largest scan against smallest: {fmt(result['points_ratio_largest_to_smallest'])} times the"
            f" points, {fmt(result['seconds_ratio_largest_to_smallest'])} times the time."
        )
    return text + "\n"


@register("mining")
def mining_markdown(result: dict) -> str:
    """Per configuration of one more mining round: where its seconds went, its peak memory, the
    ratio to the round trained afresh and, when measured, its held-out figures."""
    heldout = "heldout" in result
    full = any("full_run" in c for c in result["configs"])
    # Records from before the regressor fitted alongside the networks waited for all of it, and
    # counted the fold models' fits in the scoring.
    overlapped = any("box_quality_wait_seconds" in c for c in result["configs"])
    # Compared settings (--compare-set) have no round afresh to compare with.
    afresh = "comparison" not in result
    header = ["round", "seconds", "box quality s"]
    header += ["waited for it s", "fit s", "folds fit s"] if overlapped else ["fit s"]
    header += ["score s", "other s", "peak MB", *(["speed-up"] if afresh else [])]
    if full:
        header += ["full run s", "full run peak MB"]
    if heldout:
        header += ["held-out F", "held-out mAP", *(["F minus afresh"] if afresh else [])]
    rows = []
    for config in result["configs"]:
        name = (
            f"continued, {config['epochs']} epochs"
            if config["continued"]
            else f"afresh, {config['epochs']} epochs"
        )
        if config.get("box_quality"):  # records from before it: the regressor's fate unsaid
            name += f" (box quality {config['box_quality']})"
        if config.get("setting"):  # a compared round (--compare-set)
            name = f"{config['setting']}, seed {config['seed']}: {name}"
        row = [
            name,
            fmt(config["seconds"]),
            fmt(config["box_quality_seconds"]),
            *(
                [
                    fmt(config["box_quality_wait_seconds"]),
                    fmt(config["fit_seconds"]),
                    fmt(config["folds_fit_seconds"]),
                ]
                if overlapped
                else [fmt(config["fit_seconds"])]
            ),  # fmt: skip
            fmt(config["score_seconds"]),
            fmt(config["other_seconds"]),
            fmt(config["peak_rss_mb"]),
            *([fmt(config.get("speedup_vs_afresh"))] if afresh else []),
        ]
        if full:
            row += [fmt(config["full_run"]["seconds"]), fmt(config["full_run"]["peak_rss_mb"])]
        if heldout:
            row += [fmt(config["heldout"]["f1"], 3), fmt(config["heldout"]["map"], 3)]
            row += [fmt(config.get("heldout_f1_minus_afresh"), 4)] if afresh else []
        rows.append(row)
    frames = result["configs"][0]["num_train_frames"]
    start = (
        "after a full retrain, its rounds trained as each configuration says"
        if full
        else f"going on from its run {result['continues_run']}"
    )
    measured = (
        ", and measuring the models before and after on the test frames" if result.get("before_after") else ""
    )
    text = (
        table(header, rows)
        + f"\n\nOne more round of session `{result['session']}` ({start}) on its {frames} training"
        " frames, each configuration on a fresh copy of the session in a child process; target"
        f" {fmt(result['target_seconds'])} s per round"
        + (
            f" and {fmt(result['target_full_run_seconds'])} s per full run"
            if full and result.get("target_full_run_seconds") is not None
            else ""
        )
        + ". 'other' is reading the cached proposals,"
        f" mining and storing the run{measured}."
    )
    if overlapped:
        text += (
            " The box quality regressor fits on a thread of its own alongside the network's fit (and"
            " the fold models'); 'waited for it' is how long the round's model then waited for it"
            " before scoring, and the round's seconds are the sum of that wait, the fits, the"
            " scoring and 'other'."
        )
    if result.get("verdicts"):
        text += (
            f" Before the round, the first {fmt(result['verdicts'])} items of each copy's review queue"
            " were answered Object with their predicted class, as a reviewer's round would: the labels"
            " changed."
        )
    if heldout:
        seeds = ", ".join(str(s) for s in result["heldout"]["seeds"])
        text += (
            f" Held-out: F-score and mAP at IoU 0.6 on {result['heldout']['frames_per_factory']} frames"
            f" of each held-out factory (seeds {seeds})"
            + ("." if result.get("comparison") else ", one training seed.")
        )
    if result.get("comparison"):
        text += " " + _compared_rounds_text(result)
    return text + "\n"


def _compared_rounds_text(result: dict) -> str:
    """``bench mining --compare-set``'s summary: what the compared rounds changed, their median
    seconds against the reference's and, when measured, the held-out F-scores over seeds."""
    comparison = result["comparison"]
    reference, compared = comparison["reference"], comparison["compared"]
    changed = result.get("compare_set") or {}
    what = ", ".join(f"`{k}={v}`" for k, v in changed.items()) or "the compared setting"
    seeds = ", ".join(str(s) for s in comparison["seeds"])
    text = (
        f"'reference' rounds ran the settings given (else the defaults), 'compared' ones with {what};"
        f" one of each per training seed ({seeds}), interleaved. Median round:"
        f" {fmt(compared['median_seconds'])} s compared, {fmt(reference['median_seconds'])} s reference"
        " (the ratio seed by seed,"
        f" median: {fmt(comparison['seconds_ratio_median'], 3)}); the regressor's fit"
        f" {fmt(compared['median_box_quality_seconds'])} s against"
        f" {fmt(reference['median_box_quality_seconds'])} s."
    )
    if "heldout_f1_difference" in comparison:
        difference = comparison["heldout_f1_difference"]
        interval = difference.get("ci95")

        def score(side: dict) -> str:
            return f"{fmt(side['heldout_f1_mean'], 4)} (spread {fmt(side['heldout_f1_std'], 4)})"

        text += (
            f" Held-out F: {score(compared)} compared, {score(reference)} reference; compared minus"
            f" reference, seed by seed: {difference['mean']:+.4f}"
            + (f" [{interval[0]:+.4f}, {interval[1]:+.4f}] (95% interval)." if interval else ".")
        )
    return text


@register("import")
def import_markdown(result: dict) -> str:
    """Seconds to import the boxes into a fresh session, and to import them again (all duplicates)."""
    header = ["boxes", "frames", "import (s, median)", "again, all duplicates (s, median)", "target (s)"]
    row = [
        fmt(result["num_boxes"]),
        fmt(result["num_frames"]),
        fmt(result["import_seconds_median"]),
        fmt(result["reimport_all_duplicates_seconds_median"]),
        fmt(result["target_seconds"]),
    ]
    return table(header, [row]) + f"\n\nMedians over {fmt(result['repeats'])} fresh sessions.\n"


@register("world-labels")
def world_labels_markdown(result: dict) -> str:
    """Label once: how a box carried between frames by odometry and by ICP matches truth, and how
    often a frame shows the object, by the object's points there."""
    methods = result["methods"]
    bins = list(next(iter(methods.values()))["shown_by_points"])
    header = ["poses", "drift max (m)", "drift max (deg)", "IoU median", "IoU p10", "IoU >= 0.6"]
    header += [f"shown, {b} points" for b in bins] + ["shown, no points"]
    rows = []
    for name, method in methods.items():
        factories = method["per_factory"]
        rows.append(
            [
                name,
                fmt(max(f["drift_m_max"] for f in factories), 3),
                fmt(max(f["drift_deg_max"] for f in factories), 2),
                fmt(method["transfer_iou"]["median"], 3),
                fmt(method["transfer_iou"]["p10"], 3),
                fmt(method["transfer_iou"]["share_at_least_0.6"], 3),
                *[fmt(method["shown_by_points"][b], 3) for b in bins],
                fmt(method["shown_without_points"], 3),
            ]
        )
    spread = result["spread"]
    seeds = ", ".join(str(s) for s in result["seeds"])
    return (
        table(header, rows)
        + f"\n\nEvery static object of {len(result['seeds'])} simulated factories (seeds {seeds},"
        f" {result['frames_per_factory']} frames each): its truth box where it has the most points,"
        " carried into every other frame and compared with the truth box there; 'shown' is the share"
        f" of frames the app labels it in (at least {result['min_points']}"
        f" point{'' if result['min_points'] == 1 else 's'} in the box), by"
        " the points truth says it has there. `factorydet labels spread` on the same factories"
        f" adds {fmt(spread['labels_added'])} labels to {fmt(spread['annotations'])} annotations"
        f" ({fmt(spread['objects'])} objects); {fmt(100 * spread['share_with_points'], 1)}% box an"
        f" object with points there, at a median IoU of {fmt(spread['iou'].get('median'), 3)} with"
        f" truth ({fmt(100 * spread['iou'].get('share_at_least_0.6', 0), 1)}% at 0.6 or more).\n"
        + _min_points_sweep(result)
    )


def _min_points_sweep(result: dict) -> str:
    """The app's poses again, by the least thinned points that would show an object (records from
    before the sweep: nothing)."""
    sweeps = [m["shown_by_min_points"] for m in result["methods"].values() if "shown_by_min_points" in m]
    sweep = sweeps[0] if sweeps else None
    if not sweep:
        return ""
    bins = list(next(iter(sweep.values()))["shown_by_points"])
    header = ["least points that show", *[f"shown, {b} points" for b in bins], "shown, no points"]
    rows = [
        [
            f"{m}{' (the app)' if int(m) == result['min_points'] else ''}",
            *[fmt(shares["shown_by_points"][b], 3) for b in bins],
            fmt(shares["shown_without_points"], 3),
        ]
        for m, shares in sweep.items()
    ]
    # Records from before the surface margin counted the box as it is, its bottom 5 cm left out.
    surface, floor = result.get("surface_margin_m", 0.0), result.get("floor_margin_m", 0.05)
    grown = f" the box grown by {round(100 * surface)} cm on every side but the bottom," if surface else ""
    return (
        "\nThe app's poses, by the least thinned points (5 cm) in the carried box that show the"
        f" object in a frame,{grown} its bottom {round(100 * floor)} cm (the floor) left out:\n\n"
        + table(header, rows)
        + "\n"
        + _margin_sweep_table(result)
        + _misses_table(result)
    )


def _misses_table(result: dict) -> str:
    """Why the app's poses leave out frames that have points of the object, by the points truth
    says it has there (records from before the count: nothing)."""
    app = next((m for m in result["methods"].values() if "misses_by_cause" in m), None)
    if app is None:
        return ""
    header = [
        "truth points",
        "frames",
        "left out",
        "thinning kept none",
        "the poses",
        "floor band only",
        "beyond the surface margin",
    ]
    rows = []
    for name, causes in app["misses_by_cause"].items():
        frames = app["frames_by_points"][name]
        missed = sum(causes.values())
        rows.append(
            [
                name,
                fmt(frames),
                fmt(missed),
                *(fmt(causes[c]) for c in ("thinning", "pose", "floor", "margin")),
            ]
        )
    floor = round(100 * result["floor_margin_m"])
    surface = round(100 * result["surface_margin_m"])
    return (
        "\nThe frames the app's poses leave out although the object has points there, by why: its"
        " points lie in the carried box but thinning kept none of them; they lie in the true box"
        f" (grown as above) but not in the carried one (the poses); every one lies in the box's bottom"
        f" {floor} cm, where the floor's points are; or they lie more than {surface} cm outside the"
        " true box (the LiDAR's range noise):\n\n" + table(header, rows) + "\n"
    )


def _margin_sweep_table(result: dict) -> str:
    """The app's poses again, by the margins of the box whose points count (records from before
    the sweep: nothing)."""
    sweep = next((m["shown_by_margins"] for m in result["methods"].values() if "shown_by_margins" in m), None)
    if not sweep:
        return ""
    bins = list(next(iter(sweep.values()))["shown_by_points"])
    app = f"{round(100 * result['surface_margin_m'])} cm, {round(100 * result['floor_margin_m'])} cm"
    header = [
        "surface, floor margin",
        *[f"shown, {b} points" for b in bins],
        "shown, no points",
        "frames shown with points",
        "without",
        f"with - {result['spurious_weight']} x without",
    ]
    rows = [
        [
            f"{name}{' (the app)' if name == app else ''}",
            *[fmt(shares["shown_by_points"][b], 3) for b in bins],
            fmt(shares["shown_without_points"], 3),
            fmt(shares["frames_shown_with_points"]),
            fmt(shares["frames_shown_without_points"]),
            fmt(shares["score"]),
        ]
        for name, shares in sweep.items()
    ]
    return (
        "\nThe app's poses, by the margins of the box whose points count (at least"
        f" {result['min_points']}): grown by the surface margin on every side but the bottom (the"
        " LiDAR's range noise puts half of an object's surface points outside its box), its bottom"
        " floor margin left out:\n\n" + table(header, rows) + "\n"
    )


@register("walkthrough")
def walkthrough_markdown(result: dict) -> str:
    """A labeller's edits and frame changes, timed to the server and to the page, against the targets."""
    rows = []
    # (records before the page's own clock timed the steps: no such columns)
    paged = any("page_median_ms" in figures for figures in result["steps"].values())
    for step, figures in result["steps"].items():
        if step.startswith("frame change"):
            target = result["target_frame_ms"]
        elif step.startswith("review verdict") and "target_verdict_ms" in result:
            target = result["target_verdict_ms"]  # the next queue item shown (records before it: none)
        else:
            target = result["target_edit_ms"]
        rows.append(
            [
                step,
                fmt(figures["stored_median_ms"]),
                fmt(figures.get("server_median_ms")),
                fmt(figures["shown_median_ms"]),
                fmt(figures["shown_max_ms"]),
                *((fmt(figures["page_median_ms"]), fmt(figures["page_max_ms"])) if paged else ()),
                fmt(target),
            ]
        )
        if step.startswith("review verdict"):
            rows += _verdict_rows_by_key(result.get("verdict_keys"), figures.get("runs") or {}, target, paged)
    render = result.get("browser_render") or {}
    header = [
        "step",
        "stored (server), median ms",
        "server's share, median ms",
        "shown (page), median ms",
        "shown, max ms",
        *(("drawn (page's clock), median ms", "drawn, max ms") if paged else ()),
        "target ms",
    ]
    scene = render.get("scene_render_ms")
    alone, with_scene = (
        render.get("notification_alone_median_ms"),
        render.get("with_a_scene_change_median_ms"),
    )
    # (records before the Display panel's budget drew all of the demo's 80k points and said nothing)
    shown, drawn = result.get("points_shown"), result.get("points_drawn")
    points = "80k points" if shown is None else f"{shown:,} points"
    if drawn is not None:
        points += f", at most {drawn:,} by Display's Points drawn"
    # (records before the Floor grid setting drew the grid)
    points += ", the boxes" if result.get("show_grid", True) else ", the boxes, no floor grid"
    scene_text = (
        f" One render of the scene takes this browser {fmt(scene)} ms (the median time between renders"
        " while the camera moves), and a change shows after the renders it causes."
        if scene is not None
        else ""
    )
    if render.get("scene_render_ms_few_points") is not None:  # (records before it: not measured)
        scene_text += (
            f" With at most {render['few_points']:,} points drawn, one render still takes"
            f" {fmt(render['scene_render_ms_few_points'])} ms."
        )
    shadows = render.get("shadows")
    if shadows is not None and shadows.get("shadows_paired_difference_median_ms") is not None:
        # (records before it: not measured; None: no pair timed on both sides)
        turns = [
            sum(ms is not None for ms in shadows[f"scene_render_ms_shadows_{side}"]) for side in ("on", "off")
        ]
        scene_text += (
            f" viser's default light casts shadows, which the app turns off: with them, one render"
            f" takes {fmt(shadows['shadows_on_median_ms'])} ms against"
            f" {fmt(shadows['shadows_off_median_ms'])} ms without (medians of {turns[0]} and {turns[1]}"
            f" turns in the same page), {fmt(shadows['shadows_paired_difference_median_ms'])} ms more a"
            f" render (the median of the {shadows['shadows_pairs']} paired differences; more in"
            f" {shadows['shadows_slower_pairs']} of them)."
        )
    if "renders_after_a_scene_change_median" in render:  # (records before it did not count them)
        window = render["render_window_s"]
        idle_renders, alone_renders, scene_renders = (
            _renders(render[key])
            for key in (
                "renders_idle_median",
                "renders_after_a_notification_median",
                "renders_after_a_scene_change_median",
            )
        )
        scene_text += (
            f" In {fmt(window)} s the page begins {idle_renders} of the scene with nothing sent,"
            f" {alone_renders} after a notification alone and {scene_renders} after a scene change"
            " (medians): viser draws the scene"
            " on a heartbeat when idle and keeps drawing it for a moment after every scene change,"
            " which costs a browser with a GPU nothing and this one a render's time each."
        )
    click, clicked, or_click = ("", "", "")
    if any("(click)" in step for step in result["steps"]):
        click, or_click = " (and a click)", " (or click)"
        clicked = "; for a click, the server the selection"
    return (
        table(header, rows) + f"\n\n{result['repeats']} rounds of key presses{click} in headless Chromium on"
        f" `{result['data']}` with the shipped model and label once on (an edit reaches every frame"
        " that shows the object), once the frames ahead are computed; 'stored' is when the database"
        f" holds the edit (for a frame change: its cached detections drawn into the scene{clicked})"
        f" and 'shown' when the page shows it, both from the key press{or_click}; 'server's share'"
        " is the app's own latency, from the server receiving the key to its having sent the"
        " browser everything the key changed (one batch of updates); the"
        " rest is the browser's (delivering the key, rendering, showing)."
        + (_page_clock_text(result) if paged else "")
        + f" In this browser a notification alone takes {fmt(alone)}"
        f" ms to show and {fmt(with_scene)} ms with a scene change in the"
        f" same update: headless Chromium renders the scene ({points}) in {_renderer(result)},"
        " on the two cores the server uses too; a browser with a GPU does that in milliseconds."
        + scene_text
        + _retrain_text(result)
        + "\n"
    )


def _page_clock_text(result: dict) -> str:
    """How the walkthrough's 'drawn' column is timed, for a record that has one."""
    settle = result.get("settle_ms") or 0.0
    when = (
        f" Each key was pressed once the page had drawn nothing for {fmt(settle)} ms (a labeller who"
        " looks at each edit before the next key)."
        if settle > 0
        else " Each key was pressed as soon as the page showed the step before (viser keeps"
        " rendering for a quarter of a second after a scene change: a key pressed meanwhile waits"
        " for the render in flight)."
    )
    return (
        " 'Shown' is polled by the test driver, which checks the page at growing intervals (20,"
        " 50, 100, 100, then 500 ms) and so adds up to the next check's time; 'drawn' is timed in"
        " the page's own clock, from the key's (or click's) input event until the text showing its"
        " effect is in the page and the next animation frame has begun after the one that draws"
        " it, as a person at this browser sees it." + when
    )


VERDICT_KEY_NAMES = {"b": "background", "o": "Object", "x": "skip"}
"""The walkthrough's verdict keys (``app.walkthrough.VERDICT_KEY_CHOICES``), by the verdict's name."""


def _verdict_rows_by_key(keys: str | None, runs: dict, target, paged: bool = False) -> list[list[str]]:
    """The walkthrough's review verdicts, one row per key where the verdicts had more than one
    (the k-th verdict was given with ``keys[k % len(keys)]``): an Object verdict writes labels
    into every frame that shows the object, a background or skip verdict writes one row; with
    ``paged``, the times in the page's own clock too. Records before the keys were recorded: none."""
    if not keys or len(set(keys)) < 2 or not runs.get("shown"):
        return []
    rows = []
    for key in sorted(set(keys), key=keys.index):
        picked = [k for k in range(len(runs["shown"])) if keys[k % len(keys)] == key]
        rows.append(
            [
                f"of them, {VERDICT_KEY_NAMES.get(key, key)} ({key.upper()}; {len(picked)})",
                *(
                    fmt(round(float(statistics.median([runs[name][k] for k in picked])), 1))
                    if runs.get(name)
                    else "–"
                    for name in ("stored", "server", "shown")
                ),
                fmt(max(runs["shown"][k] for k in picked)),
                *(
                    (
                        fmt(round(float(statistics.median([runs["page"][k] for k in picked])), 1)),
                        fmt(max(runs["page"][k] for k in picked)),
                    )
                    if paged
                    else ()
                ),
                fmt(target),
            ]
        )
    return rows


def _renderer(result: dict) -> str:
    """What drew the walkthrough's WebGL, in words (records from before it was recorded all ran
    Chromium's SwiftShader: the browser was started with --disable-gpu)."""
    renderer = result.get("webgl_renderer", "SwiftShader")
    if renderer is None:
        return "WebGL (its renderer unknown)"
    if "llvmpipe" in renderer:
        return "software WebGL (Mesa's llvmpipe through ANGLE)"
    if "SwiftShader" in renderer:
        return "software WebGL (Chromium's SwiftShader)"
    return f"WebGL ({fmt(renderer)})"


def _renders(count: float) -> str:
    """A median count of renders in words: '1 render', '3 renders', '2.5 renders'."""
    shown = f"{int(count)}" if float(count).is_integer() else f"{count:g}"
    return f"{shown} render" + ("" if shown == "1" else "s")


def _retrain_text(result: dict) -> str:
    """The walkthrough's retrain from the page, in a sentence (records before it had none)."""
    retrain = result.get("retrain") or {}
    if "next_round_shown_s" not in retrain:
        return ""
    full = retrain.get("full_run_shown_s")
    first = f" Train ran a full run (the session's first) in {fmt(full)} s;" if full is not None else ""
    verdicts = result.get("num_verdicts")
    those = f"the {verdicts} review verdicts above, in a row" if verdicts else "the review verdicts above"
    keys = result.get("verdict_keys")  # (records before it: background and skip)
    if verdicts and keys:
        objects = sum(keys[k % len(keys)] == "o" for k in range(verdicts))
        those += f", {objects} of them Object (the labels changed)" if objects else ", background and skip"
    return (
        f" Then, from the page:{first} after {those} (keyboard), a next round took"
        f" {fmt(retrain['next_round_shown_s'])} s until its before/after"
        f" table showed (target {fmt(result.get('target_next_round_s'))} s)." + _browser_cores_text(retrain)
    )


def _browser_cores_text(retrain: dict) -> str:
    """What the browser spent with nothing sent to it, in a sentence (records before it: none)."""
    if retrain.get("browser_cores_training_open") is None:
        return ""
    return (
        f" With nothing sent to it the browser used {fmt(retrain['browser_cores_idle'])} of the"
        f" machine's cores, {fmt(retrain['browser_cores_training_open'])} with the Training panel open"
        " (its bar still, as the app draws it) and"
        f" {fmt(retrain['browser_cores_training_open_animated_bar'])} with the bar animated (as the"
        " app drew it before): cores the run shown there competes for."
    )


def _as_given(field: str, value: object) -> object:
    """A record's ``LoopSettings`` ``field`` value as its flag and the app's control give it
    (``review_extra`` -1 for all, not ``None``); a plan field (not a setting) as it is."""
    from factorydet_core.training.settings import CONTROL_BY_FIELD

    control = CONTROL_BY_FIELD.get(field)
    if control is None:
        return value
    try:
        return control.shown(value)
    except InputError:  # a choice a record was written with that the controls no longer offer
        return value


@register("hitl-compare")
def hitl_compare_table(result: dict) -> str:
    """``bench hitl-compare``: per detector, the paired differences of one record from another."""

    differs = "; ".join(
        f"{key}: {_as_given(key, mine)} against {_as_given(key, theirs)}"
        for key, (mine, theirs) in result["differs"].items()
    )
    seeds = ", ".join(map(str, result["seeds"]))
    same = result.get("one_record", False)
    what = f"`{result['record']}`" if same else f"`{result['record']}` minus `{result['baseline']}`"
    rows = result["variants"]
    in_factory = any("in_factory_f1" in row for row in rows.values())
    fitted_frames = any("fitted_frame_f1" in row for row in rows.values())
    precision_recall = any("precision" in row and "recall" in row for row in rows.values())
    heldout = " on the held-out factories" if result.get("heldout") else ""
    lines = [
        f"{what}, seed by seed (seeds {seeds}): mean [95% interval]{heldout}."
        + ("" if same else f" What differs: {differs or 'nothing'}."),
        "",
        "| detector | F-score | mAP | F gain over its own blind mining |"
        + (" F-score in-factory |" if in_factory else "")
        + (" F-score at the fitted frames' thresholds |" if fitted_frames else "")
        + (" precision | recall |" if precision_recall else ""),
        "|---|---|---|---|"
        + ("---|" if in_factory else "")
        + ("---|" if fitted_frames else "")
        + ("---|---|" if precision_recall else ""),
    ]
    for name, row in rows.items():
        # A detector against itself over the same blind mining: its gain is its F difference.
        gain = "–" if name == "blind" else difference_text(row["gain_over_blind"])
        cells = [name, difference_text(row["f1"]), difference_text(row["map"]), gain]
        if in_factory:
            cells.append(difference_text(row["in_factory_f1"]) if "in_factory_f1" in row else "–")
        if fitted_frames:
            cells.append(difference_text(row["fitted_frame_f1"]) if "fitted_frame_f1" in row else "–")
        if precision_recall:
            cells += [difference_text(row[key]) if key in row else "–" for key in ("precision", "recall")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + _library_pairs_text(rows)


@register("hitl-pool")
def hitl_pool_table(result: dict) -> str:
    """``bench hitl-pool``: several records' held-out factory sets taken together, per detector,
    and the share of the blind-to-full gap each recovers (stated where the gap is significant)."""
    sets = "; ".join(
        f"`{name}` (factories {', '.join(map(str, heldout['seeds']))}, {heldout['frames']} frames each)"
        for name, heldout in zip(result["records"], result["heldout"])
    )
    seeds = ", ".join(map(str, result["seeds"]))
    rows = [
        [name, fmt(result["f1"][name], 3), ", ".join(fmt(value, 3) for value in result["f1_per_seed"][name])]
        for name in result["variants"]
    ]
    gap = result["gap"]
    text = (
        f"{sets}, taken together: per training seed (seeds {seeds}), the mean of the sets' F-scores"
        " weighted by their frames (the mean over the sets, not the F-score of their frames pooled).\n\n"
        + table(["detector", "F-score (mean over seeds)", "per seed"], rows)
        + f"\n\nThe gap between blind and full labels: {difference_text(gap)}"
    )
    if not result["gap_significant"]:
        return text + (
            f", not larger than twice its standard error ({fmt(gap['standard_error'])}): no recovered"
            " share is stated."
        )
    shares = []
    for name, share in result["recovered"].items():
        if share["share"] is None:
            continue
        interval = (
            " [{:.0f}%, {:.0f}%]".format(*(100 * bound for bound in share["ci95"]))
            if share["ci95"]
            else " [interval unbounded]"
        )
        shares.append(f"{name} {100 * share['share']:.0f}%{interval}")
    return text + ", more than twice its standard error; recovered: " + ("; ".join(shares) or "–") + "."


def _library_pairs_text(rows: dict) -> str:
    """Whether a compare's paired runs ran one version of the library ("" when the records did
    not keep it)."""
    counts = [row["library"] for row in rows.values() if "library" in row]
    same, other = (sum(c[key] for c in counts) for key in ("same", "other"))
    pairs = same + other + sum(c["unknown"] for c in counts)
    if other:
        return (
            f"\n\n**{other} of the {pairs} pairs of runs ran two versions of the library**: their "
            "differences include what changed in the code."
        )
    if same and same == pairs:
        return "\n\nEvery pair of runs ran one version of the library."
    return ""


def difference_text(difference: dict, with_mean: bool = True) -> str:
    """A paired difference (``hitl.paired_difference``) as "+0.017 [-0.001, +0.034]"; without
    ``with_mean`` the interval alone, " [-0.001, +0.034]" ("" when it has none)."""
    interval = " [{:+.3f}, {:+.3f}]".format(*difference["ci95"]) if difference.get("ci95") else ""
    return f"{difference['mean']:+.3f}{interval}" if with_mean else interval
