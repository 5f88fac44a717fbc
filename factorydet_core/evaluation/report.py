"""The results report (``factorydet report``): every figure in it comes from this run."""

from __future__ import annotations

import datetime
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.classifier import FisherNet, count_parameters
from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.groups import best_option_iou
from factorydet_core.detection.model import DetectionModel
from factorydet_core.detection.scoring import select_detections
from factorydet_core.evaluation.bench_tables import difference_text
from factorydet_core.evaluation.evaluate import (
    PAPER_TABLE2,
    PAPER_TABLE3,
    Progress,
    baseline_model,
    detector_for,
    measure,
    reference_boxes,
)
from factorydet_core.evaluation.hitl import reviewer_order
from factorydet_core.evaluation.plots import plot_error_breakdown, plot_pr_curves, plot_sweep
from factorydet_core.evaluation.quality import quality_markdown, target_lines
from factorydet_core.evaluation.records import machine_info, mixed_library_note
from factorydet_core.io.dataset import open_dataset
from factorydet_core.metrics import MISS_KINDS, OVERLAP_IOU, PART_FRACTION, recorded_false_positive_kinds
from factorydet_core.training.mining import collect_proposals, group_overlaps, train_with_mining
from factorydet_core.training.settings import folds_continue
from factorydet_core.types import InputError


def _fmt(value, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


METHOD_LABELS = {"paper": "3DmFV-Net", "box_head": "box head", "head_options": "box head + options"}
"""How the report names each back half (``model.DetectionModel.method``) in its tables."""


def model_text(model: DetectionModel) -> str:
    """What the model's back half is, in one clause."""
    if model.method == "paper":
        return (
            f"3DmFV-Net width {model.classifier.width} ({model.classifier.num_parameters_:,} parameters; "
            f"width 1.0, the paper's network, has "
            f"{count_parameters(FisherNet(len(model.classifier.labels_), 1.0)):,})"
        )
    num_parameters = model.classifier.num_parameters_
    head = f"learned box head, a PointNet on each point set's points ({num_parameters:,} parameters)"
    if model.method == "head_options":
        return (
            head
            + ", whose class probabilities the box quality regressor boxes among the size prior's options"
        )
    return head + ", which boxes its own detections"


def heldout_lines(quality: dict, method: str | None = None) -> list[str]:
    """The held-out factory benchmark's table (``quality.quality_markdown``) under its heading, and
    ``method``'s figures (the shipped model's) against the learned stage's targets."""

    lines = [
        "",
        "## Held-out factories: the paper's method and the learned stages side by side",
        "",
        "The headline. Every method classifies the same proposals of factories no training, tuning "
        "or threshold choice saw (`factorydet bench quality`, `docs/bench/quality.json`):",
        "",
        quality_markdown(quality).rstrip(),
    ]
    if method is not None and method in quality.get("methods", {}):
        lines += [
            "",
            f"Against the targets ({method}, the shipped model's method; means over the training seeds):",
            "",
            *target_lines(quality, method),
        ]
    return lines


def operating_text(model: DetectionModel) -> str:
    """How a model's detections are scored and thresholded, in words, for the report."""
    score = ""
    if model.box_quality is not None:
        power = "" if model.probability_exponent == 1 else f" to the power {model.probability_exponent:g}"
        score = f"score = class probability{power} x predicted IoU; "
    tuned = model.class_score_thresholds
    if not tuned:
        return f"{score}operating score threshold {model.score_threshold:g}"
    per_class = ", ".join(f"{name} {tuned[name]:g}" for name in model.class_names if name in tuned)
    rest = [name for name in model.class_names if name not in tuned]
    return (
        f"{score}per-class operating score thresholds, tuned on the training frames' annotations ({per_class}"
        + (f"; {', '.join(rest)} {model.score_threshold:g}" if rest else "")
        + ")"
    )


def _proposal_recall(dataset, frames, iou_threshold: float, model: DetectionModel) -> dict:
    """Per class, the share of truth instances that some proposal box matches (``proposals``: the
    bound on recall of boxes fitted to segments), and that some box option of the instance's own
    class matches (``options``: the model's size prior grows the boxes and, with anchored box
    quality, sets class sizes into their corners; the bound of a classifier that is always right).

    Then where the model loses the rest, instance by instance (no one-to-one matching, so these
    are shares of instances some box reaches, not the evaluation's recall): ``chosen`` some point
    set's candidate names the instance's class and its chosen box reaches the IoU, at any score;
    ``scored`` the same at the operating score; ``kept`` the same among the detections NMS keeps.
    Each is a subset of the one before (``chosen`` of ``options``: a chosen box is one of the
    options of its set and class)."""

    anchored = model.box_quality is not None and model.box_quality.anchored
    hits, option_hits, classes = [], [], []
    funnel: dict[str, list[np.ndarray]] = {"chosen": [], "scored": [], "kept": []}
    for frame in frames:
        boxes, class_ids = reference_boxes(dataset, frame.frame_index, use_truth=True)
        overlap = group_overlaps(frame, boxes)
        hits.append(overlap.max(axis=0) >= iou_threshold if overlap.shape[0] else np.zeros(len(boxes), bool))
        if model.box_prior is not None:
            best = best_option_iou(
                boxes,
                class_ids,
                frame.proposal_boxes,
                frame.groups.group_ids,
                model.box_prior,
                anchored,
                frame.groups.anchor_mask,
            )
            option_hits.append(best >= iou_threshold)
        candidates = model.candidates(frame.proposal_boxes, frame.groups)
        scored = select_detections(  # all of them
            candidates,
            model.score_threshold,
            model.nms_iou,
            class_score_thresholds=model.class_thresholds(),
            vote_iou=model.vote_iou,
        )
        for name, chosen in (
            ("chosen", candidates),
            ("scored", scored),
            ("kept", scored.subset(np.flatnonzero(scored.kept_mask))),
        ):
            match = (box_iou_3d(chosen.boxes, boxes) >= iou_threshold) & (
                chosen.class_ids[:, None] == class_ids[None, :]
            )
            funnel[name].append(match.any(axis=0) if len(chosen.boxes) else np.zeros(len(boxes), bool))
        classes.append(class_ids)
    classes = np.concatenate(classes)

    def table(hit_lists) -> dict:
        hit = np.concatenate(hit_lists)
        out = {
            name: round(float(hit[classes == c].mean()), 3)
            for c, name in enumerate(dataset.class_names)
            if (classes == c).any()
        }
        out["total"] = round(float(hit.mean()), 3) if len(hit) else None
        return out

    return {
        "proposals": table(hits),
        "options": table(option_hits) if option_hits else None,
        **{name: table(lists) for name, lists in funnel.items()},
    }


FEATURE_TEXT = {
    "aggregated": "points-weighted mean of each point set's voxel features (the paper's Eq. 7)",
    "direct": "3DmFV of each point set's own points (`feature=direct`)",
}
"""How the report names each proposal feature (``FrontEndParams.feature``)."""


def _error_lines(errors: dict, reference: str, png: Path, method_label: str = "3DmFV-Net") -> list[str]:
    """The report's section on the kinds of errors (``metrics.error_breakdown``)."""
    names = list(errors["per_class"])
    fp_kinds = recorded_false_positive_kinds(errors)
    rows = [("true positives", lambda r: r["tp"], errors["tp"])]
    rows += [
        (f"false positive: {k}", lambda r, k=k: r["false_positives"][k], errors["false_positives"][k])
        for k in fp_kinds
    ]
    rows += [
        (f"missed: {k.replace('_', ' ')}", lambda r, k=k: r["misses"][k], errors["misses"][k])
        for k in MISS_KINDS
    ]
    without = errors["f1_without"]
    worst_fp = max(fp_kinds, key=lambda k: without[k])
    worst_miss = max(MISS_KINDS, key=lambda k: without[k])
    return [
        "",
        "## Where the errors are",
        "",
        f"Every {method_label} detection at the operating thresholds and every {reference} instance, "
        "sorted by kind (after Hoiem et al., *Diagnosing error in object detectors*, 2012). A false "
        "positive is a *duplicate* when an instance of its class fits it at the IoU but was already "
        f"matched, *localization* when one of its class overlaps it at IoU {OVERLAP_IOU} or more but "
        "less than the threshold, *confusion* when only an instance of another class overlaps it, "
        + (
            f"*part* when none overlaps it but at least {PART_FRACTION:.0%} of its volume lies inside "
            "one (a piece of a larger object, such as the upright of a pallet truck), and "
            "*background* otherwise. "
            if "part" in fp_kinds
            else "and *background* when none does. "
        )
        + "A missed instance has *no candidate* when no point set's "
        "candidate of its class fits it at the IoU, whatever the score (no point set covers it, its "
        "point set has a wrong class, or a wrong box was chosen among the options); is *below "
        "threshold* when some do but all score below the operating threshold; and is *suppressed* "
        "when one scored above it but NMS or the one-to-one matching took it, or box voting moved "
        "its box below the IoU.",
        "",
        "| | " + " | ".join(names) + " | total |",
        "|---|" + "---|" * (len(names) + 1),
        *[
            f"| {label} | " + " | ".join(str(get(errors["per_class"][n])) for n in names) + f" | {total} |"
            for label, get, total in rows
        ],
        "",
        f"Total F-score {errors['f1']:.3f}; with every false positive of one kind removed: "
        + ", ".join(f"{k} {without[k]:.3f}" for k in fp_kinds)
        + "; with every miss of one kind found: "
        + ", ".join(f"{k.replace('_', ' ')} {without[k]:.3f}" for k in MISS_KINDS)
        + f". The largest single gains: removing the {worst_fp} false positives "
        f"({without[worst_fp]:.3f}), and finding the misses of kind "
        f'"{worst_miss.replace("_", " ")}" ({without[worst_miss]:.3f}).',
        "",
        f"![errors by kind]({png.name})",
    ]


def voxel_sweep(
    dataset,
    model: DetectionModel,
    sizes: list[float],
    train_indices: list[int],
    test_indices: list[int],
    T_vehicle_sensor: np.ndarray | None,
    iou_threshold: float,
    progress: Progress | None = None,
    train_dataset=None,
    train_T_vehicle_sensor: np.ndarray | None = None,
) -> list[dict]:
    """F-score against the truth for each voxel size, retraining the classifier (one round, no
    mining) on ``train_indices`` with the model's settings each time (the paper's Fig. 7): its
    classifier settings, its operating threshold and score exponent, and a box quality regressor
    when it has one.

    The training frames are ``train_dataset``'s (with its own extrinsics ``train_T_vehicle_sensor``)
    when given, else ``dataset``'s."""
    if train_dataset is None:
        train_dataset, train_T_vehicle_sensor = dataset, T_vehicle_sensor

    base = params_for(model, train_dataset.num_sensors)
    rows = []
    for n, size in enumerate(sizes):
        params = base.replace(voxel_size_m=size)
        train = collect_proposals(train_dataset, train_indices, Detector(params, train_T_vehicle_sensor))
        test = collect_proposals(dataset, test_indices, Detector(params, T_vehicle_sensor))
        run = train_with_mining(
            train,
            type(model.classifier)(**model.classifier.get_params()),  # its settings, unfitted
            rounds=0,
            score_threshold=model.score_threshold,
            tune_class_thresholds=model.class_score_thresholds is not None,
            box_quality=None if model.box_quality is None else _unfitted(model.box_quality),
            probability_exponent=model.probability_exponent,
        )
        metrics = measure(run.model, dataset, test, iou_threshold=iou_threshold, use_truth=True)
        rows.append({"voxel_size_m": size, "f1": metrics["f1"], "map": metrics["map"],
                     "per_class_f1": {k: v["f1"] for k, v in metrics["per_class"].items()}})  # fmt: skip
        if progress is not None:
            progress("sweep", n + 1, len(sizes))
    return rows


def _unfitted(quality: BoxQuality) -> BoxQuality:
    """A regressor of ``quality``'s size and inputs (its trees, anchored options, free space),
    unfitted: what the sweep fits again at each voxel size."""
    return BoxQuality(
        max_iter=len(quality.trees_["roots"]), anchored=quality.anchored, visibility=quality.visibility
    )


def write_report(
    data: str | os.PathLike,
    model_path: str | os.PathLike,
    out: str | os.PathLike = "docs/results.md",
    *,
    iou_threshold: float = 0.6,
    max_frames: int | None = None,
    sweep_sizes: list[float] | None = None,
    sweep_frames: int = 4,
    calibrate: bool = True,
    command: str = "",
    progress: Progress | None = None,
    train_data: str | os.PathLike | None = None,
) -> Path:
    """Measure the model and the baseline and write the Markdown report, its PNGs and a JSON copy
    of every number next to ``out``.

    The baseline and the grid sweep are trained on the training frames of ``train_data`` (the data
    set the model was trained on, so that both classifiers learn from the same frames), or of
    ``data`` when it is not given."""
    out = Path(out)
    dataset = open_dataset(data)
    model = DetectionModel.load(model_path)
    label = METHOD_LABELS[model.method]
    simulated = (Path(data) / "truth").is_dir()
    train_dataset = dataset if train_data is None else open_dataset(train_data)
    train_idx = train_dataset.splits.get("train") or []
    test_idx = dataset.splits.get("test") or list(range(dataset.num_frames))
    test_idx = test_idx[:max_frames] if max_frames else test_idx
    detector = detector_for(model, dataset, calibrate)
    train_detector = detector if train_data is None else detector_for(model, train_dataset, calibrate)
    test = collect_proposals(dataset, test_idx, detector, progress)
    train = collect_proposals(train_dataset, train_idx, train_detector, progress)
    baseline = baseline_model(model, train)
    references = ["annotations", "truth"] if simulated else ["annotations"]
    results = {
        ref: {
            "deep": measure(model, dataset, test, iou_threshold=iou_threshold, use_truth=ref == "truth"),
            "baseline": measure(
                baseline, dataset, test, iou_threshold=iou_threshold, use_truth=ref == "truth"
            ),
        }
        for ref in references
    }
    headline = references[-1]
    stem = out.with_suffix("")
    pr_png = Path(f"{stem}_pr.png")
    errors_png = Path(f"{stem}_errors.png")
    plot_error_breakdown(
        results[headline]["deep"]["errors"],
        errors_png,
        f"{label} errors vs {headline} at the operating point, IoU {iou_threshold}",
    )
    plot_pr_curves(
        results[headline]["deep"], pr_png, f"{label} detections vs {headline}, IoU {iou_threshold}"
    )
    sweep_rows, sweep_png = [], Path(f"{stem}_grid_sweep.png")
    if sweep_sizes:
        sweep_rows = voxel_sweep(
            dataset, model, sweep_sizes, train_idx[:sweep_frames], test_idx, detector.T_vehicle_sensor,
            iou_threshold, progress, train_dataset, train_detector.T_vehicle_sensor,
        )  # fmt: skip
        plot_sweep(
            sweep_rows,
            sweep_png,
            f"F-score against voxel size ({len(train_idx[:sweep_frames])} train frames)",
        )
    bound = _proposal_recall(dataset, test, iou_threshold, model) if simulated else None
    note = model.note
    rounds = int(note.get("rounds", 1))
    machine = machine_info()
    quality_path = out.parent / "bench" / "quality.json"  # written by `factorydet bench quality`
    class_names = model.class_names

    lines = [
        "# Results against the paper",
        "",
        f"Generated by `{command or 'factorydet report'}` on {datetime.date.today().isoformat()}; "
        "do not edit by hand. Every figure below comes from that run.",
        "",
        f"- Data: `{data}`, test frames {test_idx} ({len(test_idx)}); training frames "
        f"{note.get('train_frames', train_idx)} of `{train_data if train_data is not None else data}` "
        "(the model's, the baseline's and the grid sweep's).",
        f"- Instances in the test frames: {results[headline]['deep']['num_reference']} against the {headline}"
        + (f" ({results['annotations']['deep']['num_reference']} annotated)" if simulated else ""),
        f"- Model: `{model_path}`: {model_text(model)}, "
        f"on the {FEATURE_TEXT[detector.params.feature]}, "
        f"{rounds} training rounds ({max(rounds - 1, 0)} of hard-negative mining), "
        f"training time of the final round {note.get('fit_seconds', 0):.0f} s; command: "
        f"`{note.get('config', {}).get('command', '?')}`.",
        f"- Matching: IoU ≥ {iou_threshold} with a reference of the same class; {operating_text(model)}, "
        f"NMS IoU {model.nms_iou}. AP is the area under the interpolated PR curve.",
        f"- Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory_gb']} GB, no GPU.",
        *(
            heldout_lines(json.loads(quality_path.read_text()), model.method)
            if quality_path.is_file()
            else []
        ),
        "",
        "## Table 2: recognition accuracy (%) of held-out point sets",
        "",
        "Test-frame point sets that match a reference instance at the IoU threshold take its class; "
        "those that overlap none are background.",
        "",
        f"| class | n | {label} | baseline | paper |",
        "|---|---|---|---|---|",
    ]
    rec_deep = results[headline]["deep"]["recognition"]
    rec_base = results[headline]["baseline"]["recognition"]
    if not rec_deep["per_class"]:
        raise InputError("the test frames hold no point set to recognise")
    for name, row in rec_deep["per_class"].items():
        base_row = rec_base["per_class"].get(name, {})
        lines.append(
            f"| {name} | {row['num']} | {100 * row['accuracy']:.2f} | "
            f"{_fmt(100 * base_row['accuracy'] if base_row else None, 2)} | – |"
        )
    lines.append(
        f"| **mean over classes** | | **{100 * rec_deep['mean_class_accuracy']:.2f}** | "
        f"{100 * rec_base['mean_class_accuracy']:.2f} | {PAPER_TABLE2['mean']:.2f} |"
    )
    lines += [
        "",
        f"## Table 3: detection F-score at IoU {iou_threshold}",
        "",
        f"| class | n | {label} P | R | **F** | AP | baseline F | baseline AP | paper F (IoU 0.6) "
        "| paper 3D-DPM F (IoU 0.6) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for ref in references:
        deep, base = results[ref]["deep"], results[ref]["baseline"]
        lines.append(f"| *against the {ref}* | | | | | | | | | |")
        for name in class_names:
            d, b = deep["per_class"][name], base["per_class"][name]
            lines.append(
                f"| {name} | {d['num_reference']} | {_fmt(d['precision'])} | {_fmt(d['recall'])} | "
                f"**{_fmt(d['f1'])}** | {_fmt(d['ap'])} | {_fmt(b['f1'])} | {_fmt(b['ap'])} | "
                f"{_fmt(PAPER_TABLE3['ours'].get(name))} | – |"
            )
        lines.append(
            f"| **total** | {deep['num_reference']} | {_fmt(deep['precision'])} | {_fmt(deep['recall'])} | "
            f"**{_fmt(deep['f1'])}** | mAP {_fmt(deep['map'])} | {_fmt(base['f1'])} | "
            f"mAP {_fmt(base['map'])} | "
            f"{_fmt(PAPER_TABLE3['ours']['total'])} | {_fmt(PAPER_TABLE3['baseline_3d_dpm']['total'])} |"
        )
    deep = results[headline]["deep"]
    base = results[headline]["baseline"]
    below = [
        n for n in class_names if deep["per_class"][n]["num_reference"] and deep["per_class"][n]["f1"] <= 0.5
    ]
    lines += [
        "",
        f"![precision-recall curves]({pr_png.name})",
        "",
        "## Targets",
        "",
        (
            f"- Total F-score against the {headline}: {deep['f1']:.3f} against the paper's "
            f"{PAPER_TABLE3['ours']['total']}: "
            + (
                "above."
                if deep["f1"] > PAPER_TABLE3["ours"]["total"]
                else f"short by {PAPER_TABLE3['ours']['total'] - deep['f1']:.3f}."
            )
            if iou_threshold == 0.6
            else f"- Total F-score against the {headline}: {deep['f1']:.3f} (the paper's figures are at "
            "IoU 0.6 and are not compared at this threshold)."
        ),
        f"- Classes at or below F = 0.5: {', '.join(below) if below else 'none'}.",
        f"- {label} against the baseline (total F): {deep['f1']:.3f} against {base['f1']:.3f}"
        + (" (ahead)." if deep["f1"] > base["f1"] else " (not ahead)."),
    ]
    if bound is not None:
        lines += [
            "",
            "Why: no detection can be better than its proposal. The share of truth instances for which "
            f"some proposal box reaches IoU {iou_threshold} on these test frames (the recall bound), and "
            "for which some box option of the instance's own class does (the bound of a classifier "
            "that is always right and picks the best option), is:",
            "",
            "| bound | " + " | ".join(bound["proposals"]) + " |",
            "|---|" + "---|" * len(bound["proposals"]),
            "| proposal boxes | " + " | ".join(_fmt(v) for v in bound["proposals"].values()) + " |",
        ]
        if bound["options"] is not None:
            lines.append("| box options | " + " | ".join(_fmt(v) for v in bound["options"].values()) + " |")
        for key, row in (
            ("chosen", "chosen box of its class, any score"),
            ("scored", "the same, at the operating threshold"),
            ("kept", "the same, kept by NMS"),
        ):
            lines.append(f"| {row} | " + " | ".join(_fmt(v) for v in bound[key].values()) + " |")
        lines += [
            "",
            "The options are each point set's boxes, the same grown to its class's typical sizes behind "
            "the visible side"
            + (
                ", and boxes of those sizes placed by the fitted box and by the box at the scene's "
                "heading (round objects' own boxes have no heading): set into each of its corners "
                "(objects in a segment of several, flush stacks), standing on the floor under it "
                "(objects whose lower part the vehicle does not see) and one object up from its "
                "bottom or down from its top (the middle of a stack)"
                if model.box_quality is not None and model.box_quality.anchored
                else ""
            )
            + "."
            + (
                " The box quality regressor picks among them the one of highest predicted IoU "
                "and multiplies the class probability by that IoU (for both classifiers)."
                if model.box_quality is not None
                else ""
            ),
            "",
            f"The last three rows follow the {label}'s detections down from that bound: the share "
            "of instances for which some point set's candidate names the instance's class and its "
            "chosen box reaches the IoU, at any score (a wrong class on the set, or a wrong choice "
            "among its options, loses an instance here), then at the operating score, then among "
            "the detections NMS keeps. No one-to-one matching, so the last row can exceed the "
            "recall of Table 3.",
        ]
    background_row = rec_deep["per_class"].get("background")
    if background_row is not None:
        lines += [
            "",
            f"The classifier is the other limit: it keeps {100 * background_row['accuracy']:.1f}% of "
            f"the {background_row['num']} background point sets of the test frames as background "
            f"(the baseline {100 * rec_base['per_class']['background']['accuracy']:.1f}%); "
            f"{100 * (1 - deep['precision']):.0f}% of its detections at the operating thresholds "
            f"are false positives (precision {deep['precision']:.3f}), and it recognises "
            f"{100 * rec_deep['mean_class_accuracy']:.1f}% "
            "of held-out point sets per class on average against the paper's "
            f"{PAPER_TABLE2['mean']}%.",
        ]
    lines += _error_lines(deep["errors"], headline, errors_png, label)
    if sweep_rows:
        lines += [
            "",
            "## Fig. 7: F-score against grid resolution",
            "",
            "One training round (no mining) per voxel size on the first "
            f"{len(train_idx[:sweep_frames])} training frames, with the model's settings (score "
            f"threshold {model.score_threshold}"
            + (
                f", probability exponent {model.probability_exponent:g}"
                if model.probability_exponent != 1
                else ""
            )
            + (", per-class thresholds tuned on those frames" if model.class_score_thresholds else "")
            + (", box quality" if model.box_quality is not None else "")
            + "), measured on the test frames against the truth.",
            "",
            "| voxel size (m) | total F | mAP |",
            "|---|---|---|",
            *[f"| {r['voxel_size_m']} | {_fmt(r['f1'])} | {_fmt(r['map'])} |" for r in sweep_rows],
            "",
            f"![grid sweep]({sweep_png.name})",
        ]
    hitl_path = out.parent / "bench" / "hitl.json"
    if hitl_path.is_file():  # written by `factorydet bench hitl --out docs/bench/hitl.json`
        lines += ["", hitl_markdown(json.loads(hitl_path.read_text()))]
    lines.append("")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    record = {
        "command": command,
        "data": str(Path(data).name),
        "model": str(model_path),
        "test_frames": test_idx,
        "results": {
            ref: {k: {m: v for m, v in d.items() if m != "pr_curves"} for k, d in r.items()}
            for ref, r in results.items()
        },
        "proposal_recall_bound": bound,
        "grid_sweep": sweep_rows,
        "machine": machine,
    }
    Path(f"{stem}.json").write_text(json.dumps(record, indent=2))
    return out


def _recovered_text(result: dict, recovered: str) -> str:
    """The gap between blind mining and full labels, and the share of it each reviewed budget,
    ``blind_safe``, ``reviewed_safe_K`` and ``full_late`` recover, stated only where the gap is
    larger than twice its standard error over the seeds (a share of noise is no result)."""
    if result["gap_full_minus_blind"] is None:
        return "Full labels were not run here: no gap, no recovered share."
    gap = _fmt(result["gap_full_minus_blind"])
    full = result["variants"]["full"].get("difference_vs_blind", {})
    interval = difference_text(full, with_mean=False)
    if not result.get("gap_significant", True):
        return (
            f"The gap between blind and full labels ({gap}{interval}) is not larger than twice its standard"
            f" error over the seeds ({_fmt(full.get('standard_error'))}): these seeds cannot tell whether"
            " full labels help, so no recovered share is stated."
        )
    parts = []
    if recovered:
        parts.append(f"by the reviews: {recovered} (target: at least 80% at K = 200)")
    f1, gap_f1 = result["f1"], result["gap_full_minus_blind"]

    def share(name: str) -> str:  # the percentage of the gap ``name`` recovers
        return f"{100 * (f1[name] - f1['blind']) / gap_f1:.0f}%"

    # (a gap of 0 or less, significant: full labels worse than blind mining, no share of it)
    named = [n for n in f1 if n in ("blind_safe", "full_late") or n.startswith("reviewed_safe_")]
    for name in named if gap_f1 > 0 else []:
        if name == "blind_safe":
            parts.append(
                f"by `blind_safe`, with no reviewer: {share(name)}{_share_interval(result, name)}"
                " (target: at least 30%)"
            )
        elif name == "full_late":
            parts.append(f"by `full_late`, every missing label given after the first fit: {share(name)}")
        else:
            parts.append(
                f"by `{name}`, the reviews with the rest held: {share(name)}{_share_interval(result, name)}"
                + (" (target: at least 80% at K = 200)" if name == "reviewed_safe_200" else "")
            )
    shares = "; ".join(parts) if parts else "no reviewed, held or late variant was run"
    return f"Recovered share of the gap between blind and full labels ({gap}{interval}): {shares}."


def _share_interval(result: dict, name: str) -> str:
    """`` [lo%, hi%]``: the 95% interval of the share of the blind-to-full gap ``name`` recovers
    (``hitl.recovered_share``, from the record's seeds), `` [interval unbounded]`` when the seeds
    cannot bound it, ``""`` for a record without seeds or with one."""
    from factorydet_core.evaluation.hitl import recovered_share

    per_seed = result.get("per_seed") or {}
    if not all(n in per_seed for n in ("blind", "full", name)) or len(per_seed["blind"]) < 2:
        return ""
    share = recovered_share(*([r["f1"] for r in per_seed[n]] for n in (name, "blind", "full")))
    return _interval_text(share["ci95"])


def _interval_text(ci: list[float] | None) -> str:
    """`` [lo%, hi%]`` of a recovered share's 95% interval (``hitl.recovered_share``'s ``ci95``),
    `` [interval unbounded]`` when the seeds cannot bound it."""
    return " [interval unbounded]" if ci is None else f" [{100 * ci[0]:.0f}%, {100 * ci[1]:.0f}%]"


def _difference_row(what: str, differences: dict, names: list[str]) -> list[str]:
    """The table row of each variant's paired difference from blind mining (``[]`` when some
    variant has no interval: fewer than two seeds)."""
    if not differences or not all(differences.get(n, {}).get("ci95") for n in names):
        return []
    cells = ("–" if n == "blind" else difference_text(differences[n]) for n in names)
    return [f"| {what}, per seed: mean [95% interval] | " + " | ".join(cells) + " |"]


def _map_differences(result: dict) -> dict:
    """Each ``bench hitl`` variant's per-seed (paired) mAP difference from blind mining's
    (``hitl.paired_difference``), from the record's seeds; ``{}`` for a record without them."""
    from factorydet_core.evaluation.hitl import paired_difference

    per_seed = result.get("per_seed") or {}
    if "blind" not in per_seed:
        return {}
    blind = [r["map"] for r in per_seed["blind"]]
    return {name: paired_difference([r["map"] for r in runs], blind) for name, runs in per_seed.items()}


def _map_recovered_text(result: dict, differences: dict) -> str:
    """The blind-to-full gap in mAP (threshold-free: the F-score also moves with the operating
    thresholds training tunes on its own frames) and the share of it each variant recovers, stated
    only where the gap is larger than twice its standard error."""
    full = differences["full"]
    return _gap_text(
        "In mAP",
        full,
        lambda: [
            f"{name} {100 * differences[name]['mean'] / full['mean']:.0f}%"
            for name in differences
            if name not in ("blind", "full")
        ],
    )


def _gap_text(where: str, gap: dict, shares: Callable[[], list[str]]) -> str:
    """ "``where``, the gap between blind and full labels ..." (``gap``: their paired difference,
    ``hitl.paired_difference``) with the ``shares`` of it recovered, or, where the gap is not larger
    than twice its standard error, that no share is stated."""
    if gap.get("standard_error") is None or not gap["mean"] > 2 * gap["standard_error"]:
        return (
            f"{where}, the gap between blind and full labels ({difference_text(gap)}) is not larger than"
            f" twice its standard error ({_fmt(gap.get('standard_error'))}): no share is stated."
        )
    stated = shares()
    return (
        f"{where}, the gap between blind and full labels is {difference_text(gap)}, more than twice its"
        " standard error" + (f"; recovered: {', '.join(stated)}." if stated else ".")
    )


def _no_folds_recovered_text(variants: dict) -> str:
    """With thresholds tuned out of fold, the blind-to-full gap at the thresholds the same networks
    get without folds (``fitted_frame_other_objective_thresholds``) and the share of it each
    reviewed variant recovers there, with its 95% interval, stated only where that gap is larger
    than twice its standard error; ``""`` when the record did not measure them."""
    from factorydet_core.evaluation.hitl import paired_difference, recovered_share

    key = "fitted_frame_other_objective_thresholds"
    if not all(n in variants and key in variants[n] for n in ("blind", "full")):
        return ""
    per_seed = {n: v[key]["f1_per_seed"] for n, v in variants.items() if key in v}
    objective = variants["full"][key]["objective"]

    def shares() -> list[str]:
        out = []
        for name in per_seed:
            if name not in ("blind", "full"):
                share = recovered_share(per_seed[name], per_seed["blind"], per_seed["full"])
                out.append(f"{name} {100 * share['share']:.0f}%{_interval_text(share['ci95'])}")
        return out

    return _gap_text(
        f"At the thresholds of objective {objective} tuned on the fitted frames (no folds)",
        paired_difference(per_seed["full"], per_seed["blind"]),
        shares,
    )


def _order_text(queue_order: str | None, review_order: str | None) -> str:
    """How a hitl record's runs cut the mined negatives and ordered the review queue."""
    cut_turns = queue_order == "class"
    review_turns = (review_order or queue_order) == "class"
    if review_order == "learned":
        learned = (
            " the review queue's places ordered by what the session's verdicts so far say will give a"
            " label (`review_order` learned)"
        )
        return (
            f", the predicted classes taking turns in the cut (`queue_order` class) and{learned}"
            if cut_turns
            else f",{learned}"
        )
    if cut_turns and review_turns:
        return ", the predicted classes taking turns in the cut and in the queue (`queue_order` class)"
    if cut_turns:
        return (
            ", the predicted classes taking turns in the cut (`queue_order` class) and the review queue"
            " most likely an object first (`review_order` score)"
        )
    if review_turns:
        return ", the predicted classes taking turns in the review queue (`review_order` class)"
    return ""


def _extra_text(review_extra: int | None) -> str:
    """What a hitl record's review queue held beyond the mined negatives (``review_extra``)."""
    if review_extra == 0:
        return ""
    what = "every other false positive"
    if review_extra is not None:
        what = f"the next {review_extra} false positives"
    return (
        f", the reviewed detectors' queue also holding {what} of the last mining for review alone"
        " (`review_extra`: no background until a verdict)"
    )


def _epochs_text(settings: dict) -> str:
    """How long a hitl record's fits ran: the first fit's epochs and, when they differ, those of
    each fit that goes on from the last model (every round after a full run's first fit and
    every next round, ``LoopSettings.round_epochs``)."""
    epochs, later = settings["epochs"], settings.get("round_epochs")
    if not later or later == epochs:
        return f"{epochs} epochs per fit"
    return (
        f"{epochs} epochs for the first fit and {later} for each round after it"
        " (going on from the last model)"
    )


def _hitl_method(settings: dict) -> str:
    """What ``bench hitl`` trained, in a few words (records before ``method`` was kept: the paper's)."""
    method = settings.get("method", "paper")
    if method == "paper":
        return f"the paper's 3DmFV-Net (width {settings['width']})"
    return {
        "box_head": "the learned box head",
        "head_options": "the learned box head classifying, the box quality regressor boxing",
    }.get(method, method)


def _holding_text(result: dict) -> str:
    """What the holding detectors of ``bench hitl`` (``blind_safe``, ``reviewed_safe_K``) do with
    their confident mined negatives, as the rest of a sentence."""
    settings = result["settings"]
    pseudo = settings.get("pseudo_label_confident")
    return (
        (
            f"takes the negatives scoring {pseudo:g} or more, off every label, for labels of their"
            " predicted class until reviewed (pseudo-labels"
            + ("" if settings.get("model_box_targets") else ", teaching their class, not their box")
            + (
                "; each of an object that stands still labels it in every training frame that shows it"
                if settings.get("carry_pseudo_labels")
                else ""
            )
            + "), "
            if pseudo is not None
            else ""
        )
        + (
            f"holds the negatives scoring {result['hold_confident']:g} or more"
            if pseudo is None
            else f"holds the other negatives scoring {result['hold_confident']:g} or more"
            if pseudo > result["hold_confident"]
            else f"holds those on a label that score {result['hold_confident']:g} or more"
        )
        + " out of the background (neither object nor background) until reviewed"
        + (
            ", and every point set on their boxes (their places) with them"
            # (held places are off the labels: with pseudo-labels from the hold score on, none)
            if settings.get("hold_places") and (pseudo is None or pseudo > result["hold_confident"])
            else ""
        )
        + (
            ", and leaves out of the losses of the fits that go on from the previous model the"
            " background sets drawn at random that the"
            f" network, as it trains, finds {settings['recalibrate_background']:g} or more likely"
            " an object"
            + (
                " and its likeliest class at least as likely as the median labelled set of that class"
                if settings.get("recalibrate_by_class")
                else ""
            )
            + " (background recalibration)"
            if settings.get("recalibrate_background")
            else ""
        )
    )


def _hitl_where(result: dict) -> str:
    """Which frames ``bench hitl``'s figures are measured on, as a sentence."""
    factories = result.get("heldout_factories")
    if not factories:
        return "on test frames of the training frames' factory (in-factory figures)."
    seeds = ", ".join(str(f["seed"]) for f in factories)
    frames = sum(int(f["frames"]) for f in factories)
    each = int(factories[0]["frames"])
    return (
        f"on {frames} frame{'s' if frames != 1 else ''} of held-out factories (simulator seeds {seeds},"
        f" {each} frame{'s' if each != 1 else ''} each) that no training or choice saw (headline figures)."
    )


def _library_note(versions: dict[str, int]) -> str:
    """What a hitl record's ``library_versions`` say of its runs' code ("" for a record whose
    runs did not keep it)."""
    known = {v: n for v, n in versions.items() if v != "unknown"}
    if not known:
        return ""
    if len(versions) == 1:
        return " Every run ran one version of the library."
    return mixed_library_note(
        versions,
        f"The {sum(versions.values())} runs",
        "paired differences between them include what changed in the code",
    )


PARTIAL_ROWS: dict[str, str] = {
    "per_class_precision": "the per-class precision / recall table",
    "in_factory": "the in-factory F-score",
    "fitted_frame_thresholds": "the same networks at their fitted frames' thresholds",
    "other_objective_thresholds": "the same networks at the other objective's thresholds",
    "fitted_frame_other_objective_thresholds": "the same networks at the thresholds without folds",
}
"""What ``hitl_markdown`` calls each of ``hitl.OPTIONAL_RUN_FIGURES`` when it leaves it out."""


def _partial_rows_note(variants: dict[str, dict]) -> str:
    """The rows a hitl table left out because some of its runs, but not all, measured them (runs
    read back from a record made before they were kept), with how many did; "" for none."""
    left_out = []
    runs = {n: len(v["f1_per_seed"]) for n, v in variants.items()}
    for key, what in PARTIAL_ROWS.items():
        counts = {n: v.get("runs_measuring", {}).get(key) for n, v in variants.items()}
        if any(c is None for c in counts.values()):
            continue  # (a record from before the counts were kept: unknown)
        measured, total = sum(counts.values()), sum(runs.values())
        if 0 < measured < total:
            short = [f"{n} {counts[n]} of {runs[n]}" for n in variants if counts[n] < runs[n]]
            left_out.append(f"{what} (measured by {', '.join(short)} runs)")
    if not left_out:
        return ""
    return (
        " Left out, as not every run measured them (runs read back from records made before they"
        f" were kept): {'; '.join(left_out)}."
    )


def _same_network_rows(
    measured: dict[str, dict], names: list[str], at: str, short: str, paired: tuple[str, str]
) -> list[str]:
    """``hitl_markdown``'s rows of the same networks at other thresholds (``measured``: per
    detector, a variant's ``fitted_frame_thresholds`` or ``other_objective_thresholds``): their
    total F ("... at ``at``"), its difference from blind's ("``short``, F minus blind's") and,
    where every detector has an interval, the paired difference ``paired`` (key, row text)."""
    rows = [
        f"| total F, the same models at {at} | " + " | ".join(_fmt(measured[n]["f1"]) for n in names) + " |"
    ]
    rows += _difference_row(
        f"{short}, F minus blind's", {n: measured[n].get("difference_vs_blind", {}) for n in names}, names
    )
    key, text = paired
    if all(measured[n][key].get("ci95") for n in names):
        rows.append(
            f"| {text}, per seed: mean [95% interval] | "
            + " | ".join(difference_text(measured[n][key]) for n in names)
            + " |"
        )
    return rows


def _mean_count(value: float) -> str:
    """A count averaged over seeds: whole as it is, else to one decimal (487.7)."""
    return f"{int(value)}" if float(value).is_integer() else f"{value:.1f}"


def hitl_markdown(result: dict, heading: bool = True) -> str:
    """The ``bench hitl`` table: F-score per class and in total of blind mining, mining with
    reviews, and full labels (means over the seeds, with each seed's total), the recovered
    fraction of the gap and the reviews it took (measured on held-out factories, the record's
    ``heldout_factories``, with each detector's in-factory F beside); ``heading=False`` leaves out
    the section title (the README's block sits under a section of its own)."""
    variants = result["variants"]
    names = list(variants)
    seeds = result.get("seeds", [result["settings"].get("seed", 0)])
    classes = list(next(iter(variants.values()))["per_class_f1"])
    head = "| class | " + " | ".join(names) + " |\n|---|" + "---|" * len(names)
    rows = [
        f"| {c} | " + " | ".join(_fmt(variants[n]["per_class_f1"][c]) for n in names) + " |" for c in classes
    ]
    rows.append("| **total F** | " + " | ".join(f"**{_fmt(variants[n]['f1'])}**" for n in names) + " |")
    if all(variants[n].get("f1_std") is not None for n in names):
        rows.append(
            "| standard deviation over seeds | "
            + " | ".join(_fmt(variants[n]["f1_std"]) for n in names)
            + " |"
        )
    if len(seeds) > 1:
        rows.append(
            "| total F per seed | "
            + " | ".join(", ".join(_fmt(f) for f in variants[n]["f1_per_seed"]) for n in names)
            + " |"
        )
    f1_differences = {n: variants[n].get("difference_vs_blind", {}) for n in names}
    rows += _difference_row("F minus blind's", f1_differences, names)
    # Thresholds tuned out of fold: the same networks at other thresholds, each set by the key
    # its record has and its rows' texts (of its objective): those their fitted frames give (never
    # above the operating score) and what the folds changed, seed by seed; the other objective's
    # out of fold; and what the settings without folds give (the other objective's on the fitted
    # frames: with the objective "total" chosen, the defaults).
    same_networks = (
        ("fitted_frame_thresholds", "thresholds tuned on their fitted frames", "the same",
         "out_of_fold_minus_fitted", "F of out-of-fold thresholds minus the fitted frames'"),
        ("other_objective_thresholds", "out-of-fold thresholds of objective {o}", "the same ({o})",
         "minus_chosen", "F of objective {o}'s out-of-fold thresholds minus the model's"),
        ("fitted_frame_other_objective_thresholds",
         "thresholds of objective {o} tuned on their fitted frames (no folds)", "the same (no folds, {o})",
         "chosen_minus_these", "F of the model's thresholds minus no folds' of objective {o}"),
    )  # fmt: skip
    for key, at, short, paired_key, paired_text in same_networks:
        if all(key in variants[n] for n in names):
            o = variants[names[0]][key].get("objective")
            rows += _same_network_rows(
                {n: variants[n][key] for n in names},
                names,
                at.format(o=o),
                short.format(o=o),
                (paired_key, paired_text.format(o=o)),
            )
    rows.append("| mAP | " + " | ".join(_fmt(variants[n]["map"]) for n in names) + " |")
    map_differences = _map_differences(result)
    rows += _difference_row("mAP minus blind's", map_differences, names)
    if all("in_factory" in variants[n] for n in names):
        # The same models on the training factory's own test frames, for comparison.
        rows.append(
            "| total F on the training factory's test frames (in-factory) | "
            + " | ".join(_fmt(variants[n]["in_factory"]["f1"]) for n in names)
            + " |"
        )
    rows.append(
        "| verdicts (skips too) | " + " | ".join(f"{variants[n]['num_reviews']:g}" for n in names) + " |"
    )
    if any(variants[n]["num_reviews"] for n in names):
        useful = [
            sum(variants[n].get("reviews", {}).get(v) or 0 for v in ("object", "wrong_box")) for n in names
        ]
        rows.append(
            "| of them, objects and wrong boxes (a label each) | "
            + " | ".join(f"{round(u, 1):g}" for u in useful)  # (means over seeds: 78.2, not 78.1666)
            + " |"
        )
    if any(variants[n].get("reviews", {}).get("hidden") for n in names):
        rows.append(
            "| queue items passed over by the filter | "
            + " | ".join(f"{variants[n]['reviews'].get('hidden', 0):.0f}" for n in names)
            + " |"
        )
    for key, what in (
        ("unannotated_in_queue", "unannotated training objects in the reviewed rounds' queues"),
        ("unannotated_in_top_k", "unannotated training objects in the first K entries reviewed"),
    ):
        if any(variants[n].get(key) is not None for n in names):
            shares = (
                "–" if variants[n].get(key) is None else f"{100 * variants[n][key]:.0f}%" for n in names
            )
            rows.append(f"| {what} | " + " | ".join(shares) + " |")
    if any(variants[n].get("reach_share_estimated") is not None for n in names):
        shares = (
            "–"
            if variants[n].get("reach_share_estimated") is None
            else f"{100 * variants[n]['reach_share_estimated']:.0f}% / "
            + (
                "–"
                if variants[n].get("reach_share_true") is None
                else f"{100 * variants[n]['reach_share_true']:.0f}%"
            )
            for n in names
        )
        rows.append(
            "| of a queue's reach, in its first K entries: the scores' estimate / truth | "
            + " | ".join(shares)
            + " |"
        )
    for key, what in (
        ("sparse_labels_ignored", "a person's labels too sparse to learn from (ignored places, last fit)"),
        (
            "labels_tuning_ignored",
            "a person's labels trained on but too sparse for the thresholds' tuning (last fit)",
        ),
    ):
        if any(variants[n].get(key) for n in names):
            counts = ("–" if variants[n].get(key) is None else _mean_count(variants[n][key]) for n in names)
            rows.append(f"| {what} | " + " | ".join(counts) + " |")
    if all("unannotated_labelled" in variants[n] for n in names):
        rows.append(
            "| unannotated training objects labelled | "
            + " | ".join(f"{100 * variants[n]['unannotated_labelled']:.0f}%" for n in names)
            + " |"
        )

    def share(v: float | None) -> str:
        return "–" if v is None else f"{100 * v:.0f}%"

    # Which classes the reviews gave back: per class, the share of the unannotated training
    # objects each reviewed detector's session labels at the end.
    reviewed_names = [
        n for n in names if n.startswith("reviewed_") and variants[n].get("unannotated_labelled_per_class")
    ]
    class_coverage = []
    if reviewed_names:
        per_class = {n: variants[n]["unannotated_labelled_per_class"] for n in reviewed_names}
        coverage_rows = [
            f"| {c} | {per_class[reviewed_names[0]][c]['total']:g} | "
            + " | ".join(share(per_class[n][c]["share"]) for n in reviewed_names)
            + " |"
            for c in per_class[reviewed_names[0]]
            if per_class[reviewed_names[0]][c]["total"]
        ]
        if coverage_rows:  # a data set with every object annotated has nothing to give back
            class_coverage = [
                "Of the training frames' unannotated objects, the share labelled at the end, per class:",
                "",
                "| class | unannotated | " + " | ".join(reviewed_names) + " |",
                "|---|---|" + "---|" * len(reviewed_names),
                *coverage_rows,
                "",
            ]

    # Whether a class's F moves by false positives or by misses (records before these were kept
    # have no such table).
    precision_recall = []
    if all("per_class_precision" in variants[n] and "per_class_recall" in variants[n] for n in names):
        precision_recall = [
            "Per class, precision / recall at the operating scores (means over the seeds):",
            "",
            "| class | " + " | ".join(names) + " |",
            "|---|" + "---|" * len(names),
            *(
                f"| {c} | "
                + " | ".join(
                    _fmt(variants[n]["per_class_precision"][c])
                    + " / "
                    + _fmt(variants[n]["per_class_recall"][c])
                    for n in names
                )
                + " |"
                for c in classes
            ),
            "",
        ]

    recovered = ", ".join(
        f"K = {k}: {share(v)}{_share_interval(result, f'reviewed_{k}')}"
        for k, v in result["recovered"].items()
    )
    if recovered and len(seeds) > 1:
        recovered += (
            " (per seed: "
            + "; ".join(
                f"K = {k}: " + ", ".join(share(v) for v in values)
                for k, values in result["recovered_per_seed"].items()
            )
            + ")"
        )
    settings = result["settings"]
    hide = result.get("queue_max_label_iou")
    reviewed = any(n.startswith("reviewed_") for n in names)
    queue_note = (
        f" The reviewer's queue hides items whose box overlaps a label at IoU {hide:g} or more (the "
        'review panel\'s "hide items on labelled objects"); hidden items cost no budget.'
        if hide and reviewed
        else ""
    )
    mean_note = f" Means over seeds {', '.join(map(str, seeds))}." if len(seeds) > 1 else ""
    mean_note += _library_note(result.get("library_versions") or {})
    mean_note += _partial_rows_note(variants)
    return "\n".join(
        [
            *(["## Human in the loop: does reviewing the mined negatives help?", ""] if heading else []),
            f"Generated by `{result.get('command') or 'factorydet bench hitl'}`. Data `{result['data']}`, "
            f"training frames {result['train_frames']}, test frames {result['test_frames']}; "
            f"{result['mining_rounds']} mining rounds after the first fit for every detector; "
            f"{_hitl_method(settings)}, {_epochs_text(settings)}, "
            + ("" if settings.get("class_thresholds", True) else "one score threshold for every class, ")
            + (
                f"each class's threshold tuned on the training frames in {settings['threshold_folds']}"
                " stretches of the drive, each scored by a model fitted on the others, with no ceiling"
                " (`threshold_folds`), "
                + (
                    "each next round's fold models going on from the last round's (`continue_folds`), "
                    if folds_continue(settings, bool(result.get("mining_rounds")))
                    else ""
                )
                if settings.get("class_thresholds", True) and settings.get("threshold_folds")
                else ""
            )
            + (
                "each class's threshold the best for the F-score of all classes' detections pooled"
                " (`threshold_objective` total), "
                if settings.get("class_thresholds", True) and settings.get("threshold_objective") == "total"
                else ""
            )
            + f"{settings['initial_negatives']} first negatives, {settings['negatives_per_round']} mined "
            + "per round"
            + _order_text(
                settings.get("queue_order"),
                # Nobody reviews: the queue's order is not part of the runs (records before the
                # review order was a setting said the cut's order alone then).
                reviewer_order(settings, result.get("review_by")) if reviewed else None,
            )
            + _extra_text(settings.get("review_extra", 0) if reviewed else 0)
            + (
                ", every next round fitting the box quality regressor again on the labels it has"
                " (`refit_box_quality`)"
                if settings.get("refit_box_quality")
                else ""
            )
            + (
                ", an Object verdict's label (the mined box) teaching its class alone, no box"
                " (`model_box_targets` off)"
                if reviewed and settings.get("model_box_targets", True) is False
                else ""
            )
            + ". F-score at IoU "
            f"{result['iou_threshold']} against the full truth, "
            + _hitl_where(result)
            + " `blind`: mining on the partial labels (the paper)."
            + (
                " `reviewed_K`: a simulated reviewer answers the top K "
                + (
                    "places of each round's queue (one verdict per place, as the review panel shows them"
                    " by default; an object labelled once in every frame that shows it"
                    + (
                        "; a place that shows too few points for the policy judged where the frames"
                        " see it best, as the panel's *Look where it is seen best*"
                        if result.get("review_best_view")
                        else ""
                    )
                    + ")"
                    if result.get("review_by") == "place"
                    else "items of each round's queue"
                )
                + " from the truth through the review panel's own call, labelling to the data set's"
                " annotation policy."
                if reviewed
                else ""
            )
            + (
                " `full_late`: the same labels added after the first fit, when a reviewer's arrive."
                if "full_late" in variants
                else ""
            )
            + (" `full`: every object of the annotation policy labelled." if "full" in variants else "")
            + (
                f" `blind_safe`: blind mining that {_holding_text(result)}; nobody reviews them here."
                if "blind_safe" in variants
                else ""
            )
            + (
                " `reviewed_safe_K`: the reviewer of `reviewed_K` on top of `blind_safe`: mining that"
                f" {_holding_text(result)}; a verdict moves a held entry to the background or to a"
                " label, and the held entries the reviewer does not answer (or skips) stay held."
                if any(n.startswith("reviewed_safe_") for n in names)
                else ""
            )
            + queue_note
            + mean_note,
            "",
            head,
            *rows,
            "",
            _recovered_text(result, recovered),
            "",
            *([_map_recovered_text(result, map_differences), ""] if "full" in map_differences else []),
            *([text, ""] if (text := _no_folds_recovered_text(variants)) else []),
            *_pseudo_label_text(variants, names),
            *class_coverage,
            *precision_recall,
        ]
    )


def _pseudo_label_text(variants: dict, names: list[str]) -> list[str]:
    """What the detectors that pseudo-label ended with, as the truth judges the labels
    (``hitl.pseudo_label_truth``): a paragraph and a blank line, or nothing."""
    kinds = (
        ("object", "objects of the predicted class (IoU 0.6)"),
        ("loose_box", "that class's objects under a looser box"),
        ("other_class", "another class's objects"),
        ("skip", "objects too sparse for the annotation policy"),
        ("background", "no object"),
    )

    def shares(counts: dict, total: float) -> str:
        return ", ".join(f"{100 * counts[kind] / total:.0f}% {text}" for kind, text in kinds)

    parts = []
    for name in names:
        counts = variants[name].get("pseudo_labels")
        if not counts:
            continue
        total = sum(counts.values())
        if not total:
            parts.append(f"`{name}` none")
            continue
        part = f"`{name}` {total:.1f}: " + shares(counts, total)
        carried = variants[name].get("pseudo_labels_carried")
        num_carried = sum(carried.values()) if carried else 0
        if num_carried:
            part += (
                f" ({num_carried:.1f} of them carried from the frame they were mined in to another"
                f" that shows their object: {shares(carried, num_carried)})"
            )
        parts.append(part)
    if not parts:
        return []
    return [
        "Pseudo-labels the training sessions end with (means over the seeds), as the simulator's"
        " truth judges them: " + "; ".join(parts) + ".",
        "",
    ]
