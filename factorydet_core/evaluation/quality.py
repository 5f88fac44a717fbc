"""The held-out factory benchmark (``factorydet bench quality``): train on one simulated factory,
measure on factories of other seeds that no training, tuning or threshold choice ever saw.

A user's factory is a new one: figures on test frames of the training factory (the same racks,
the same crates, half of them also choosing the score threshold) overstate what a user gets. Here
every threshold is tuned on the training frames' annotations, the held-out factories are simulated
afresh from their seeds, and their detections are compared with the simulator's hidden truth
(``evaluate.reference_boxes``). Each learned method is trained once per training seed; the JSON
gives every seed's figures and their mean and spread.

Methods, on the same proposals of the same front half:

- ``head_options``: the box head's class probabilities, each detection boxed by the box quality
  regressor among the size prior's options (both trained here per seed);
- ``box_head``: the learned box head (``box_head.BoxHead``) boxing its own detections. With
  ``head_options`` in the run it is the same trained head (mined once, from ``head_options``'s
  detections), its thresholds tuned again for its own scores;
- ``paper``: a checkpoint of the paper's pipeline (3DmFV-Net classifier, the size prior's box
  options and the box quality regressor), by default its shipped checkpoint (one training seed: the
  benchmark does not retrain it, which takes about twenty minutes per seed).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.detection.box_head import BoxHead
from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.detector import Detector, params_for
from factorydet_core.detection.model import DetectionModel
from factorydet_core.evaluation.evaluate import ignored_boxes, measure, reference_boxes
from factorydet_core.evaluation.records import (
    check_same_plan,
    library_version,
    library_versions,
    machine_info,
    mixed_library_note,
    runs_of_this_library,
    spread_frames,
)
from factorydet_core.io.atomic import atomic_path, write_text_atomic
from factorydet_core.io.dataset import Dataset, open_dataset
from factorydet_core.io.jsonfile import write_json
from factorydet_core.proposals.settings import FrontEndParams
from factorydet_core.session.models import resolve_model
from factorydet_core.sim.simulate import SimConfig, simulate_dataset
from factorydet_core.training.loop import Proposer, proposals_cache_key
from factorydet_core.training.mining import (
    FrameProposals,
    collect_proposals,
    proposals_from_arrays,
    proposals_to_arrays,
    score_frames,
    train_with_mining,
    with_tuned_thresholds,
)
from factorydet_core.training.settings import BEFORE_THEY_EXISTED, LoopSettings
from factorydet_core.types import (
    METHODS,
    MINING_THRESHOLD,
    PROBABILITY_EXPONENT,
    SCORE_FLOOR,
    SCORE_THRESHOLD,
    InputError,
)

Progress = Callable[[str, int, int], None]

IOU_THRESHOLDS: tuple[float, ...] = (0.6, 0.5, 0.25)
"""The IoUs the benchmark measures at; the first is the paper's and the headline."""


HELDOUT_SCRATCH = Path("/tmp/factorydet_heldout")
"""Where benchmarks simulate the held-out factories and cache their proposals, by default."""


def check_not_training_factory(heldout_seeds: Sequence[int], train_dataset: Dataset) -> None:
    """``InputError`` when a held-out seed is the training factory's own simulator seed."""
    train_seed = train_dataset.manifest.get("seed")
    if train_seed is not None and int(train_seed) in heldout_seeds:
        raise InputError(f"held-out seed {train_seed} is the training factory's own seed")


def check_heldout(heldout_seeds: Sequence[int], num_frames: int, train_dataset: Dataset) -> tuple[int, ...]:
    """The held-out simulator seeds as a tuple, after checking them and the frames per factory:
    ``InputError`` unless there are one or more distinct seeds >= 0, none the training factory's
    own (``check_not_training_factory``), and ``num_frames`` >= 1."""
    seeds = tuple(int(s) for s in heldout_seeds)
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise InputError(f"held-out factories need one or more distinct seeds >= 0, got {list(seeds)}")
    if num_frames < 1:
        raise InputError(f"held-out factories need at least one frame each, got {num_frames}")
    check_not_training_factory(seeds, train_dataset)
    return seeds


@dataclasses.dataclass(frozen=True)
class QualityPlan:
    """What ``bench_quality`` runs, checked when made."""

    train_data: Path
    """The training factory (its train split's annotations are all the methods learn from)."""
    heldout_seeds: tuple[int, ...] = (101, 102, 103)
    """Simulator seeds of the held-out factories."""
    heldout_frames: int = 12
    """Frames simulated per held-out factory; every one is measured."""
    train_frames: int | None = None
    """Training frames spread over the train split (``None``: all)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Training seeds of the learned methods."""
    epochs: int = 20
    rounds: int = 1
    """Hard-negative mining rounds after the first fit."""
    methods: tuple[str, ...] = ("head_options", "box_head", "paper")
    paper_model: str = "paper"
    """The paper pipeline's checkpoint (``models.resolve_model``); its front half is the one
    every method uses, so that they classify the same proposals."""
    overrides: tuple[tuple[str, object], ...] = ()
    """Front-half settings changed for every method (``FrontEndParams.replace``), e.g.
    ``(("history_frames", 2),)`` to measure multi-frame accumulation; the paper checkpoint then
    classifies the proposals of that front half."""
    scratch: Path = HELDOUT_SCRATCH
    """Where the held-out factories and the proposal caches are written."""
    calibrate: bool = True
    quality_trees: int = LoopSettings.quality_trees
    """Trees of head_options' box quality regressor (``LoopSettings.quality_trees``)."""

    def record(self) -> dict:
        """The plan as JSON: a result is resumed only by a run of the same plan (its seeds aside)."""
        values = dataclasses.asdict(self)
        values.pop("scratch")
        values["train_data"] = Path(self.train_data).name
        return json.loads(json.dumps(values))

    def __post_init__(self) -> None:
        if not self.seeds:
            raise InputError("bench quality needs at least one training seed")

        FrontEndParams().replace(**dict(self.overrides))  # unknown names and bad values fail here
        if self.epochs < 1 or self.rounds < 0:
            raise InputError("epochs must be >= 1, rounds >= 0")
        LoopSettings(quality_trees=self.quality_trees)  # (its check)
        unknown = set(self.methods) - set(METHODS)
        if unknown or not self.methods:
            raise InputError(f"methods must be among {', '.join(METHODS)}; got {', '.join(self.methods)}")
        # The held-out seeds and frames (one or more distinct seeds, not the training factory's).
        check_heldout(self.heldout_seeds, self.heldout_frames, open_dataset(self.train_data))


def heldout_factory(seed: int, num_frames: int, scratch: Path) -> Path:
    """The held-out factory of ``seed`` (simulated into ``scratch`` unless already there)."""

    folder = Path(scratch) / f"factory_seed{seed}_{num_frames}frames"
    if (folder / "manifest.json").is_file():
        return folder
    return Path(simulate_dataset(folder, SimConfig(num_frames=num_frames, seed=seed)))


def _cached_proposals(
    dataset: Dataset,
    detector: Detector,
    frames: Sequence[int],
    scratch: Path,
    progress: Progress | None,
    propose: Proposer = collect_proposals,
) -> list[FrameProposals]:
    """``collect_proposals`` (or ``propose``: on Ray workers, ``scale.jobs.proposer``) through an
    ``.npz`` cache in ``scratch``, keyed by the data, the front half's settings and calibration, and
    the frames."""

    key = proposals_cache_key(dataset, detector) + "_" + "-".join(str(i) for i in frames)
    path = Path(scratch) / "proposals" / f"{dataset.name}_{key[:80]}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as arrays:
            return proposals_from_arrays({k: arrays[k] for k in arrays.files})
    out = propose(dataset, frames, detector, progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        np.savez(tmp, **proposals_to_arrays(out))
    return out


@dataclasses.dataclass(frozen=True)
class HeldoutSet:
    """All held-out frames, re-indexed 0..F-1 across factories, with their truth."""

    frames: list[FrameProposals]
    references: dict[int, tuple[np.ndarray, np.ndarray]]
    """Frame -> truth boxes (R, 7) and classes (R,) of the annotation policy's objects."""
    ignored: dict[int, np.ndarray]
    """Frame -> truth boxes of objects below the policy (``evaluate.ignored_boxes``)."""
    sources: list[tuple[str, int]]
    """Frame -> (factory, its own frame index)."""
    class_names: tuple[str, ...] = ()
    """The factories' classes, the order of ``references``' class ids."""


def heldout_set(
    seeds: Sequence[int],
    num_frames: int,
    scratch: Path,
    params,
    progress: Progress | None = None,
    propose: Proposer = collect_proposals,
    calibrate: bool = True,
) -> HeldoutSet:
    """The held-out factories of simulator ``seeds`` (``num_frames`` each, simulated once into
    ``scratch``), proposed with the front-half settings ``params`` (cached per settings; by
    ``propose``; each factory's sensors calibrated on its first frame with ``calibrate``), with
    their truth."""
    frames, references, ignored, sources, class_names = [], {}, {}, [], None
    for seed in seeds:
        folder = heldout_factory(int(seed), num_frames, scratch)
        dataset = open_dataset(folder)
        if class_names is not None and tuple(dataset.class_names) != class_names:
            raise InputError(f"{folder.name}: its classes are not the other held-out factories'")
        class_names = tuple(dataset.class_names)
        detector = Detector(params)
        if calibrate and dataset.num_sensors > 1:
            detector.calibrate(dataset.frame(0))
        every = list(range(dataset.num_frames))
        for frame in _cached_proposals(dataset, detector, every, scratch, progress, propose):
            k = len(frames)
            references[k] = reference_boxes(dataset, frame.frame_index, use_truth=True)
            ignored[k] = ignored_boxes(dataset, frame.frame_index)
            sources.append((folder.name, frame.frame_index))
            frames.append(dataclasses.replace(frame, frame_index=k))
    return HeldoutSet(frames, references, ignored, sources, class_names or ())


def candidate_bound(
    class_names: Sequence[str], heldout: HeldoutSet, candidates: dict, iou_threshold: float = 0.6
) -> dict:
    """Per class, the share of truth objects some candidate of their class boxes at
    ``iou_threshold`` (before thresholds and NMS): what a perfect ranking could find.

    Args:
        candidates: frame index -> the model's candidates (``DetectionModel.candidates``).
    """
    hits = {name: [] for name in class_names}
    for frame in heldout.frames:
        boxes, classes = heldout.references[frame.frame_index]
        if not len(boxes):
            continue
        frame_candidates = candidates[frame.frame_index]
        if len(frame_candidates):
            iou = box_iou_3d(frame_candidates.boxes, boxes)
            iou[frame_candidates.class_ids[:, None] != classes[None, :]] = 0.0
            best = iou.max(axis=0)
        else:
            best = np.zeros(len(boxes))
        for c, value in zip(classes, best):
            hits[class_names[int(c)]].append(value >= iou_threshold)
    out = {name: round(float(np.mean(v)), 4) if v else None for name, v in hits.items()}
    every = [x for v in hits.values() for x in v]
    out["all"] = round(float(np.mean(every)), 4) if every else None
    return out


def measure_heldout(model: DetectionModel, heldout: HeldoutSet) -> dict:
    """Detection metrics at each of ``IOU_THRESHOLDS`` (with and without the ignore rule for
    objects below the annotation policy), recognition accuracy per class (Table 2), the candidate
    bound, and the back half's time per frame (median; classification and boxes, before NMS)."""

    candidates, times = {}, []
    for frame in heldout.frames:
        start = time.perf_counter()
        candidates[frame.frame_index] = model.candidates(frame.proposal_boxes, frame.groups)
        times.append((time.perf_counter() - start) * 1000.0)
    out: dict = {"back_half_ms_per_frame": round(float(np.median(times)), 1)}
    common = {"references": heldout.references, "candidates": candidates}
    for iou in IOU_THRESHOLDS:
        metrics = measure(model, None, heldout.frames, iou_threshold=iou, ignored=heldout.ignored, **common)
        metrics.pop("pr_curves", None)
        out[f"iou_{iou}"] = metrics
    plain = measure(model, None, heldout.frames, iou_threshold=IOU_THRESHOLDS[0], **common)
    out["iou_0.6_without_ignore"] = {k: plain[k] for k in ("precision", "recall", "f1", "map")}
    out["candidate_bound"] = candidate_bound(model.class_names, heldout, candidates, IOU_THRESHOLDS[0])
    return out


def _mean_std(values: list[float | None]) -> dict:
    given = [v for v in values if v is not None]
    if not given:
        return {"mean": None, "std": None}
    return {"mean": round(float(np.mean(given)), 4), "std": round(float(np.std(given)), 4)}


def summarize(runs: list[dict], class_names: Sequence[str]) -> dict:
    """Mean and spread over training seeds of the headline figures."""
    head = [r["iou_0.6"] for r in runs]
    return {
        "f1": _mean_std([m["f1"] for m in head]),
        "map": _mean_std([m["map"] for m in head]),
        "precision": _mean_std([m["precision"] for m in head]),
        "recall": _mean_std([m["recall"] for m in head]),
        "f1_iou_0.5": _mean_std([r["iou_0.5"]["f1"] for r in runs]),
        "f1_iou_0.25": _mean_std([r["iou_0.25"]["f1"] for r in runs]),
        "per_class_f1": {c: _mean_std([m["per_class"][c]["f1"] for m in head]) for c in class_names},
        "per_class_ap": {c: _mean_std([m["per_class"][c]["ap"] for m in head]) for c in class_names},
        "recognition_per_class": {
            c: _mean_std([m["recognition"]["per_class"].get(c, {}).get("accuracy") for m in head])
            for c in (*class_names, "background")
        },
        "recognition_mean": _mean_std([m["recognition"]["mean_class_accuracy"] for m in head]),
        "back_half_ms_per_frame": _mean_std([r["back_half_ms_per_frame"] for r in runs]),
    }


def resumable_runs(
    plan: QualityPlan, earlier: dict | None, other_library: bool = False
) -> dict[int, dict[str, dict]]:
    """The finished training seeds of an earlier (partial) result of the same plan, as
    ``{seed: {method: run}}``; nothing when the plans differ in anything but their seeds. When
    some of the plan's seeds are missing (there is training to do), only the seeds whose runs ran
    this version of the library (``records.library_version``) are read back, unless
    ``other_library``; the others train again, with a warning that says so (the spread over
    seeds would otherwise hold what changed in the code).

    Raises:
        InputError: when ``earlier`` is a record of another plan (it would mix two benchmarks).
    """
    if not earlier:
        return {}
    # A record from before the regressor's size was a setting ran what was fitted then.
    theirs = {"quality_trees": BEFORE_THEY_EXISTED["quality_trees"], **(earlier.get("plan") or {})}
    check_same_plan("quality", plan.record(), theirs)
    learned = [m for m in plan.methods if m != "paper"]
    done: dict[int, dict[str, dict]] = {}
    for seed in plan.seeds:
        found = {
            m: next((r for r in earlier["methods"][m]["runs"] if r["seed"] == seed), None) for m in learned
        }
        if learned and all(found.values()):
            done[seed] = found
    if other_library or set(plan.seeds) <= set(done):
        return done  # (nothing to train: the record is rendered as it is)
    kept = runs_of_this_library(
        {s: list(found.values()) for s, found in done.items()}, "quality", "training seeds"
    )
    return {s: done[s] for s in kept}


def bench_quality(
    plan: QualityPlan,
    command: str = "",
    progress: Progress | None = None,
    earlier: dict | None = None,
    on_partial: Callable[[dict], None] | None = None,
    propose: Proposer = collect_proposals,
    resume_other_library: bool = False,
) -> dict:
    """Run ``plan``: the JSON record of every method on the held-out factories.

    The frames' proposals (held-out and training, each cached in the plan's scratch folder) are
    made by ``propose``: here by default, on Ray workers with ``scale.jobs.proposer``; the same
    proposals either way, so it is not part of the plan.

    Training seeds are run one after the other; after each one the result so far
    (``"complete": false``) goes to ``on_partial``, so a long run can be stopped and resumed:
    ``earlier`` (a partial result of the same plan, ``resumable_runs``) gives the seeds already
    done, which are not trained again (those of another version of the library only with
    ``resume_other_library``, ``resumable_runs``). Each run keeps the version it ran (``library``),
    and the record counts its runs per version (``library_versions``).
    """

    start = time.perf_counter()
    # a plan mismatch fails here, before any work
    resumed = resumable_runs(plan, earlier, other_library=resume_other_library)
    paper = DetectionModel.load(resolve_model(plan.paper_model))
    train_dataset = open_dataset(plan.train_data)
    if tuple(paper.class_names) != tuple(train_dataset.class_names):
        raise InputError("the paper model's classes differ from the training data's")
    params = params_for(paper, train_dataset.num_sensors).replace(**dict(plan.overrides))
    heldout = heldout_set(
        plan.heldout_seeds, plan.heldout_frames, plan.scratch, params, progress, propose, plan.calibrate
    )
    train_split = train_dataset.splits.get("train") or list(range(train_dataset.num_frames))
    train_indices = spread_frames(train_split, plan.train_frames)
    learned = [m for m in plan.methods if m != "paper"]
    train = []
    if learned and set(plan.seeds) - set(resumed):  # only what trains needs the training proposals
        detector = Detector(params)
        if plan.calibrate and train_dataset.num_sensors > 1:
            detector.calibrate(train_dataset.frame(train_indices[0]))
        train = _cached_proposals(train_dataset, detector, train_indices, plan.scratch, progress, propose)
    result: dict = {
        "benchmark": "quality",
        "command": command,
        "plan": plan.record(),
        "train_data": train_dataset.name,
        "train_seed": train_dataset.manifest.get("seed"),
        "train_frames": train_indices,
        "heldout_factories": [{"seed": s, "frames": plan.heldout_frames} for s in plan.heldout_seeds],
        "num_heldout_frames": len(heldout.frames),
        "reference": "truth: objects of at least the annotation policy's points (detections on "
        "sparser ones are ignored; iou_0.6_without_ignore counts them)",
        "front_end": None if paper.front_end is None else paper.front_end.to_dict(),
        "front_end_overrides": dict(plan.overrides),
        "training_seeds": list(plan.seeds),
        "methods": {},
    }

    runs: dict[str, list[dict]] = {m: [] for m in plan.methods}
    if "paper" in runs:
        runs["paper"].append(
            {"seed": None, "checkpoint": plan.paper_model, **measure_heldout(paper, heldout)}
        )

    def summarized(complete: bool) -> dict:
        out = dict(result, complete=complete, methods={})
        out["library_versions"] = library_versions([r for m in learned for r in runs[m]])
        if learned:  # the seeds measured so far
            out["training_seeds"] = [r["seed"] for r in runs[learned[0]]]
        for method in plan.methods:
            out["methods"][method] = {
                "summary": summarize(runs[method], paper.class_names),
                "runs": list(runs[method]),
            }
        return out

    for seed in plan.seeds if learned else ():
        if seed in resumed:
            for method in learned:
                runs[method].append(resumed[seed][method])
            continue
        fit_start = time.perf_counter()
        run = train_with_mining(
            train,
            BoxHead(class_names=paper.class_names, epochs=plan.epochs, seed=seed),
            rounds=plan.rounds,
            score_threshold=SCORE_THRESHOLD,
            probability_exponent=PROBABILITY_EXPONENT,
            mining_threshold=MINING_THRESHOLD,
            seed=seed,
            progress=progress,
            box_quality=(
                BoxQuality(
                    seed=seed,
                    visibility=LoopSettings().quality_visibility(train_dataset),
                    max_iter=plan.quality_trees,
                )
                if "head_options" in learned
                else None
            ),
        )
        fit_seconds = time.perf_counter() - fit_start
        for method in learned:
            model = run.model
            if method == "box_head" and model.box_quality is not None:
                # The same head boxing its own detections: its scores differ, so do its thresholds.
                model = dataclasses.replace(model, box_quality=None, class_score_thresholds=None)
                scored = score_frames(model, train, SCORE_FLOOR)
                model = with_tuned_thresholds(model, scored, max_threshold=SCORE_THRESHOLD)
            runs[method].append(
                {
                    "seed": seed,
                    "train_seconds": round(fit_seconds, 1),
                    "class_score_thresholds": model.class_score_thresholds,
                    "finished": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                    "library": library_version(),  # the code this run ran
                    **measure_heldout(model, heldout),
                }
            )
        if on_partial is not None:
            on_partial(summarized(complete=False))
    result["seconds"] = round(time.perf_counter() - start, 1)
    result["machine"] = machine_info()
    return summarized(complete=True)


HELDOUT_TARGETS: dict[str, float] = {
    "f1": 0.60,
    "per_class_f1": 0.40,
    "map": 0.55,
    "recognition_mean": 0.95,
    "recognition_background": 0.97,
    "back_half_ms_per_frame": 150.0,
}
"""The learned stage's targets on the held-out factories (the box head issue): total F and mAP at
IoU 0.6, every class's F, recognition (Table 2) mean and background, and the back half's time."""


def target_lines(result: dict, method: str) -> list[str]:
    """One line per ``HELDOUT_TARGETS`` entry: ``method``'s mean over training seeds against the
    target, met or short by how much."""
    summary = result["methods"][method]["summary"]
    targets = HELDOUT_TARGETS

    def line(
        what: str, value: float | None, target: float, higher_is_better: bool = True, unit: str = ""
    ) -> str:
        def shown(x: float) -> str:
            return f"{x:,.0f}{unit}" if unit else f"{x:.3f}"

        if value is None:
            return f"- {what}: not measured (target {shown(target)})."
        met = value >= target if higher_is_better else value <= target
        gap = shown(abs(target - value))
        verdict = "met" if met else f"short by {gap}" if higher_is_better else f"over by {gap}"
        return f"- {what}: {shown(value)} against {shown(target)}: {verdict}."

    per_class = summary["per_class_f1"]
    below = [
        c for c, stat in per_class.items() if stat["mean"] is None or stat["mean"] < targets["per_class_f1"]
    ]
    background = summary["recognition_per_class"].get("background", {}).get("mean")
    return [
        line("Total F-score at IoU 0.6", summary["f1"]["mean"], targets["f1"]),
        line("mAP at IoU 0.6", summary["map"]["mean"], targets["map"]),
        f"- Every class at F {targets['per_class_f1']:g} or more: "
        + (
            "met."
            if not below
            else "short for "
            + ", ".join(
                f"{c} ({'n/a' if per_class[c]['mean'] is None else format(per_class[c]['mean'], '.3f')})"
                for c in below
            )
            + "."
        ),
        line(
            "Recognition, mean over classes", summary["recognition_mean"]["mean"], targets["recognition_mean"]
        ),
        line("Recognition, background", background, targets["recognition_background"]),
        line(
            "Back half (classification and boxes), ms per frame",
            summary["back_half_ms_per_frame"]["mean"],
            targets["back_half_ms_per_frame"],
            higher_is_better=False,
            unit=" ms",
        ),
    ]


def quality_markdown(result: dict) -> str:
    """A short table of ``bench_quality``'s result: per method, the mean (and spread over training
    seeds) of the total and per-class F-score at IoU 0.6, mAP, recognition and the back half's
    time."""
    methods = result["methods"]
    classes = list(next(iter(methods.values()))["summary"]["per_class_f1"])

    def cell(stat: dict, digits: int = 3) -> str:
        if stat["mean"] is None:
            return "n/a"
        return f"{stat['mean']:.{digits}f}" + (f" ± {stat['std']:.{digits}f}" if stat["std"] else "")

    header = "| | " + " | ".join(methods) + " |"
    lines = [header, "|---" * (len(methods) + 1) + "|"]
    rows = [
        ("F-score, IoU 0.6", lambda s: cell(s["f1"])),
        ("mAP, IoU 0.6", lambda s: cell(s["map"])),
        ("precision", lambda s: cell(s["precision"])),
        ("recall", lambda s: cell(s["recall"])),
        ("F-score, IoU 0.5", lambda s: cell(s["f1_iou_0.5"])),
        ("F-score, IoU 0.25", lambda s: cell(s["f1_iou_0.25"])),
        *((f"F-score {c}", _per_class_cell(cell, c)) for c in classes),
        ("recognition, mean over classes", lambda s: cell(s["recognition_mean"])),
        ("recognition, background", lambda s: cell(s["recognition_per_class"]["background"])),
        ("back half, ms per frame (median)", lambda s: cell(s["back_half_ms_per_frame"], 0)),
    ]
    for name, get in rows:
        lines.append(f"| {name} | " + " | ".join(get(m["summary"]) for m in methods.values()) + " |")
    seeds = ", ".join(str(s["seed"]) for s in result["heldout_factories"])
    trained = any(m != "paper" for m in methods)
    spread = (
        f" ± is the spread (standard deviation) over training seeds "
        f"{', '.join(str(s) for s in result['training_seeds'])}; the paper column is one checkpoint."
        if trained
        else " The paper column is one checkpoint."
    )
    overrides = result.get("front_end_overrides") or {}
    front = f" Front half changed for every method: {overrides}." if overrides else ""
    lines += [
        "",
        f"Trained on {result['train_data']} (seed {result['train_seed']}, {len(result['train_frames'])} "
        f"annotated training frames); measured on {result['num_heldout_frames']} frames of held-out "
        f"factories (seeds {seeds}) against the truth.{spread}{front}"
        + mixed_library_note(
            result.get("library_versions") or {},
            "Its training runs",
            "the spread over seeds includes what changed in the code",
        ),
    ]
    return "\n".join(lines) + "\n"


def _per_class_cell(cell: Callable[[dict], str], name: str) -> Callable[[dict], str]:
    return lambda summary: cell(summary["per_class_f1"][name])


def write_outputs(result: dict, out: str | os.PathLike) -> None:
    """The JSON at ``out`` and its table beside it (``.md``), each written whole or not at all (a
    run stopped while writing leaves the previous file)."""
    write_json(out, result)
    write_text_atomic(Path(out).with_suffix(".md"), quality_markdown(result))
