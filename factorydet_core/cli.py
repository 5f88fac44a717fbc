"""The ``factorydet`` command line."""

from __future__ import annotations

import argparse
import getpass
import json
import sys
from collections.abc import Callable, Collection
from pathlib import Path
from typing import TYPE_CHECKING

from factorydet_core.threads import configure_threads
from factorydet_core.training.settings import (
    CONTROL_BY_FIELD,
    LOOP_CONTROLS,
    LoopSettings,
    loop_arguments,
    loop_settings_from,
)
from factorydet_core.types import (
    BOX_KINDS,
    LEVELS,
    METHODS,
    MINING_THRESHOLD,
    PRELABEL_SCORE,
    PROBABILITY_EXPONENT,
    SCORE_THRESHOLD,
    FrameLostError,
    InputError,
)

if TYPE_CHECKING:
    from factorydet_core.scale.runner import Execution


def progress_bar(desc: str, unit: str = "frame") -> tuple[Callable[[int, int], None], Callable[[], None]]:
    from tqdm import tqdm

    bar = None

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=desc, unit=unit)
        bar.update(done - bar.n)

    def close() -> None:
        if bar is not None:
            bar.close()

    return update, close


def _cmd_simulate(args: argparse.Namespace) -> int:
    from factorydet_core.sim.simulate import SimConfig, simulate_dataset

    try:
        config = SimConfig(
            num_frames=args.frames,
            seed=args.seed,
            unlabelled_fraction=args.unlabelled_fraction,
            min_annotated_points=args.min_points,
            points_per_frame=args.points,
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None
    execution = execution_from_args(args)
    update, close = progress_bar("simulating")
    try:
        if execution.uses_ray:
            from factorydet_core.scale.jobs import simulate_batch

            run = simulate_batch(args.out, config, execution, update)
            out, note = run.out_dir, f" ({len(run.skipped)} there already, {run.workers} workers)"
        else:
            out, note = simulate_dataset(args.out, config, update), ""
    finally:
        close()
    print(f"wrote {config.num_frames} frames to {out}{note}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from factorydet_core.session.demo import DEMO_SESSION, ensure_demo
    from factorydet_core.session.store import open_session

    session = open_session(DEMO_SESSION, args.root)
    if session.has_data:
        print(f"demo session ready: {session.data_dir}")
        return 0
    update, close = progress_bar("building demo")
    try:
        ensure_demo(args.root, update)
    finally:
        close()
    print(f"demo session built: {session.data_dir}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from factorydet_core.io.dataset import open_dataset

    dataset = open_dataset(args.path)
    frame = dataset.frame(0)
    print(
        json.dumps(
            {
                "name": dataset.name,
                "num_frames": dataset.num_frames,
                "num_sensors": dataset.num_sensors,
                "class_names": list(dataset.class_names),
                "splits": {k: len(v) for k, v in dataset.splits.items()},
                "frame_0": {"num_points": frame.num_points, "num_labels": len(frame.labels)},
            },
            indent=2,
        )
    )
    return 0


def parse_overrides(pairs: list[str] | None) -> dict:
    """``["regularization=0.1", "segment_on=voxels"]`` -> a dict of parameter overrides; values are
    read as JSON when they parse (numbers, true/false, lists) and as text otherwise."""
    overrides = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise InputError(f"--set expects KEY=VALUE, got {pair!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
        if isinstance(overrides[key], list):
            overrides[key] = tuple(overrides[key])
    return overrides


def positive_int(text: str) -> int:
    """An argparse ``type``: a whole number of at least 1 (refused with argparse's usage line)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _choices(text: str, flag: str, allowed: tuple[str, ...]) -> list[str]:
    """Comma-separated values of ``flag``, each one of ``allowed``."""
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in allowed]
    if bad or not values:
        raise InputError(f"{flag}: expected a comma-separated list of {', '.join(allowed)}, got {text!r}")
    return values


BENCH_ON_RAY = ("hitl", "quality", "mining")
"""The benchmarks whose per-frame work ``--workers`` / ``--ray`` move to Ray workers; the others
time or check this one process (``scale`` has worker counts of its own)."""


def _bench_execution(args: argparse.Namespace) -> Execution:
    """``bench``'s execution flags, checked against the benchmark (``BENCH_ON_RAY``)."""
    from factorydet_core.scale.runner import Execution

    execution = Execution(
        workers=args.workers,
        ray_address=args.ray_address,
        threads=1 if args.worker_threads is None else args.worker_threads,
        # Ray's files go under the scratch folder of quality's held-out factories: one every node sees.
        scratch=args.scratch if args.name == "quality" else None,
    )
    if args.name == "scale":
        if execution.uses_ray:
            raise InputError(
                "bench scale starts its own Ray workers (--worker-counts); --workers and --ray do not apply"
            )
        return execution
    if execution.uses_ray and args.name not in BENCH_ON_RAY:
        raise InputError(
            f"bench {args.name} measures this process alone; --workers and --ray apply to bench "
            f"{', '.join(BENCH_ON_RAY)}"
        )
    if not execution.uses_ray and args.worker_threads is not None:
        raise InputError("--worker-threads applies to Ray workers: add --workers N or --ray ADDRESS")
    return execution


def hitl_settings(args: argparse.Namespace) -> LoopSettings:
    """The ``LoopSettings`` ``bench hitl`` trains with, from its parsed flags (``make bench``'s
    lines resume their records only when these are the settings the records ran)."""
    return loop_settings_from(
        {
            "epochs": args.epochs,
            "negatives_per_round": args.negatives,
            "initial_negatives": args.initial_negatives,
            "score_threshold": (SCORE_THRESHOLD if args.score_threshold is None else args.score_threshold),
            "probability_exponent": args.probability_exponent,
            "mining_threshold": args.mining_threshold,
            "box_quality": args.box_quality,
            **_bench_loop_values(args),
        }
    )


def _bench_loop_values(args: argparse.Namespace) -> dict[str, object]:
    """The raw values of ``factorydet bench``'s ``add_loop_flags`` flags by field
    (``BENCH_LOOP_FIELDS``)."""
    return {field: getattr(args, field) for field in BENCH_LOOP_FIELDS}


def _earlier_record(args: argparse.Namespace) -> dict | None:
    """With ``--resume``, the (partial) record at ``--out`` to go on from; ``None`` when there is none yet."""
    from factorydet_core.io.jsonfile import read_json

    if not args.resume:
        return None
    if not args.out:
        raise InputError(f"bench {args.name} --resume continues the result at --out; give --out")
    if not Path(args.out).is_file():
        return None
    try:
        return read_json(args.out, what=f"bench {args.name} result")
    except InputError as exc:
        raise InputError(f"bench {args.name} --resume: --out is not a result: {exc}") from None


def _cmd_bench(args: argparse.Namespace) -> int:
    from factorydet_core.evaluation.bench import (
        bench_pipeline,
        bench_simulate,
        bench_voxel_sweep,
        machine_info,
        update_readme,
    )

    command = "factorydet bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else ""
    # (checked here, as the Training panel's control checks it, before any work is done)
    args.quality_trees = CONTROL_BY_FIELD["quality_trees"].parse(args.quality_trees)
    if args.resume and args.name not in ("hitl", "quality", "scale"):
        raise InputError(f"--resume applies to bench hitl, quality and scale, not bench {args.name}")
    if args.resume_other_library and not (args.resume and args.name in ("hitl", "quality")):
        raise InputError("--resume-other-library goes with bench hitl or quality --resume")
    if args.resume_also is not None:
        paths = [path.strip() for path in args.resume_also.split(",") if path.strip()]
        if not paths:
            raise InputError(f"--resume-also names no record: {args.resume_also!r}")
        args.resume_also = paths
        if not (args.resume and args.name == "hitl"):
            raise InputError("--resume-also goes with bench hitl --resume")
    if args.readme and (args.readme_block or args.name in ("hitl", "quality")):
        from factorydet_core.evaluation.bench import check_readme_block

        check_readme_block(args.readme, args.readme_block or args.name)  # before a long run, not after
    execution = _bench_execution(args)
    if args.frames is None:
        args.frames = {"simulate": 10, "hitl": None, "import": 3}.get(args.name, 4)
    if args.name == "simulate":
        result = bench_simulate(num_frames=args.frames, points_per_frame=args.points, seed=args.seed)
    elif args.name == "import":
        from factorydet_core.evaluation.bench import bench_label_import

        result = {"command": command, **bench_label_import(args.boxes, args.frames, large_box=args.large_box)}
        if args.out:
            from factorydet_core.io.atomic import write_text_atomic

            write_text_atomic(Path(args.out), json.dumps(result, indent=2) + "\n")
    elif args.name == "hitl-compare":
        from factorydet_core.evaluation.hitl import compare_hitl_records
        from factorydet_core.io.jsonfile import read_json

        pair = None if args.variants is None else tuple(v.strip() for v in args.variants.split(","))
        if pair is not None and (len(pair) != 2 or not all(pair)):
            raise InputError("bench hitl-compare --variants takes two detectors: A,B (A minus B)")
        if not (len(args.data) == 2 or (len(args.data) == 1 and pair is not None)):
            raise InputError(
                "bench hitl-compare needs two bench hitl records, RECORD BASELINE, or one record and "
                "--variants A,B"
            )
        records = [read_json(path, what="bench hitl record") for path in args.data]
        names = [Path(path).name for path in args.data]
        if len(records) == 1:  # one record: the same object is its own baseline
            records, names = records * 2, names * 2
        result = {
            **compare_hitl_records(*records, names=tuple(names), pair=pair),
            "command": command,
        }
    elif args.name == "hitl-pool":
        from factorydet_core.evaluation.hitl import pool_hitl_records
        from factorydet_core.io.jsonfile import read_json

        records = [read_json(path, what="bench hitl record") for path in args.data]
        result = {
            **pool_hitl_records(records, names=[Path(path).name for path in args.data]),
            "command": command,
        }
    elif args.name == "fuzz":
        from factorydet_core.evaluation.fuzz import (
            TARGETS,
            fuzz_campaign,
            fuzz_markdown,
            write_fuzz_outputs,
        )

        update, close = progress_bar("fuzz", unit="case")
        try:
            result = fuzz_campaign(
                num_cases=args.cases,
                seed=args.seed,
                targets=tuple(_choices(args.targets, "--targets", TARGETS)) if args.targets else TARGETS,
                model=None if args.model == "default" else args.model,
                memory_limit_mb=args.memory_limit_mb,
                keep=args.keep,
                progress=update,
            )
        finally:
            close()
        result["command"] = command
        result["machine"] = machine_info()
        if args.out:
            write_fuzz_outputs(result, args.out)
        print(json.dumps(result, indent=2))
        print(fuzz_markdown(result), file=sys.stderr)
        return 0 if result["num_failures"] == 0 else 1
    elif args.name == "quality":
        from factorydet_core.evaluation.quality import (
            QualityPlan,
            bench_quality,
            quality_markdown,
            write_outputs,
        )
        from factorydet_core.scale.jobs import proposer

        if len(args.data) != 1:
            raise InputError("bench quality needs one DATA folder: the training factory")
        plan = QualityPlan(
            train_data=Path(args.data[0]),
            heldout_seeds=tuple(parse_ints(args.heldout_seeds, "--heldout-seeds")),
            heldout_frames=args.heldout_frames,
            train_frames=args.train_frames,
            seeds=tuple(parse_ints(args.seeds, "--seeds")),
            epochs=args.epochs,
            rounds=args.rounds,
            methods=tuple(_choices(args.methods, "--methods", METHODS)),
            paper_model=args.model,
            overrides=tuple(parse_overrides(args.set).items()),
            scratch=Path(args.scratch),
            calibrate=args.calibrate,
            quality_trees=args.quality_trees,
        )
        earlier = _earlier_record(args)
        update, close = _training_progress()
        try:
            result = bench_quality(
                plan, command=command, progress=update, earlier=earlier,
                # Only a resumable run replaces --out before it is complete.
                on_partial=(lambda partial: write_outputs(partial, args.out)) if args.resume else None,
                propose=proposer(execution), resume_other_library=args.resume_other_library,
            )  # fmt: skip
        finally:
            close()
        result["proposals_on"] = execution.describe()
        if args.out:
            write_outputs(result, args.out)
        print(json.dumps(result, indent=2))
        print(quality_markdown(result), file=sys.stderr)
        if args.readme:
            update_readme(args.readme, result, args.readme_block, quality_markdown(result))
        return 0
    elif args.name == "mining":
        from factorydet_core.evaluation.bench import bench_mining

        if args.session is None:
            raise InputError("bench mining needs --session: the session whose next round is timed")
        if len(args.data) > 1:
            raise InputError("bench mining takes at most one DATA folder (default: the session's)")
        # The training settings given go to every timed ``train`` (round epochs are the bench's own).
        given = _bench_loop_values(args)
        del given["round_epochs"]
        training = loop_arguments(loop_settings_from(given))
        # With --compare-set: the continued round with the settings given and with these changed,
        # per training seed, interleaved (which of the two runs first alternates from seed to seed,
        # so that neither always meets the machine as the other left it).
        changed = parse_overrides(args.compare_set)
        own = sorted(set(changed) & {"seed", "round_epochs"})
        if own:
            raise InputError(
                f"bench mining --compare-set: {', '.join(own)} is the benchmark's own"
                " (--seeds, --round-epochs)"
            )
        if changed and loop_settings_from({**given, **changed}) == loop_settings_from(given):
            raise InputError(
                f"bench mining --compare-set {args.compare_set}: the settings given already say so"
            )
        compared = [
            (
                {"setting": side, "seed": seed},
                [
                    *execution.arguments(),
                    *loop_arguments(loop_settings_from({**given, "seed": seed, **extra})),
                ],
            )
            for k, seed in enumerate(parse_ints(args.seeds, "--seeds") if changed else ())
            for side, extra in (("reference", {}), ("compared", changed))[:: 1 if k % 2 == 0 else -1]
        ]
        if changed and not args.round_epochs:
            raise InputError(
                "bench mining --compare-set compares rounds that go on from a model: --round-epochs > 0"
            )
        update, close = progress_bar("mining", unit="round")
        try:
            result = bench_mining(
                args.session,
                root=args.root,
                data=args.data[0] if args.data else None,
                round_epochs=(0, args.round_epochs) if args.round_epochs else (0,),
                full_run=args.full_run,
                before_after=args.before_after,
                heldout_seeds=parse_ints(args.heldout_seeds, "--heldout-seeds") if args.heldout else (),
                heldout_frames=args.heldout_frames,
                train_args=[*execution.arguments(), *training],
                verdicts=args.verdicts,
                compared=compared,
                compare_set=changed,
                command=command,
                progress=update,
            )
        finally:
            close()
    elif args.name == "world-labels":
        from factorydet_core.evaluation.world_labels import bench_world_labels

        update, close = progress_bar("world labels", unit="factory x poses")
        try:
            result = bench_world_labels(
                seeds=parse_ints(args.heldout_seeds, "--heldout-seeds"),
                num_frames=args.heldout_frames,
                command=command,
                progress=update,
            )
        finally:
            close()
    elif args.name == "scale":
        from factorydet_core.io.jsonfile import write_json
        from factorydet_core.scale.bench import bench_scale
        from factorydet_core.sim.simulate import SimConfig

        if len(args.data) != 1:
            raise InputError("bench scale takes one DATA folder")
        simulate = None
        if args.simulate_frames is not None:
            try:
                simulate = SimConfig(
                    num_frames=args.simulate_frames, seed=args.seed, points_per_frame=args.points
                )
            except ValueError as exc:
                raise InputError(str(exc)) from None
        earlier = _earlier_record(args)
        update, close = progress_bar("scale", unit="run")
        try:
            result = bench_scale(
                args.data[0],
                model=args.model,
                frame_counts=parse_ints(args.frame_counts, "--frame-counts"),
                workers=parse_ints(args.worker_counts, "--worker-counts"),
                in_process=args.in_process,
                evaluate_frames=args.evaluate_frames,
                simulate=simulate,
                worker_threads=execution.threads,
                command=command,
                progress=update,
                earlier=earlier,
                # Only a resumable run replaces --out before it is complete.
                on_partial=(lambda partial: write_json(args.out, partial)) if args.resume else None,
            )
        finally:
            close()
        if args.out:
            write_json(args.out, result)
    elif args.name == "memory":
        from factorydet_core.evaluation.bench import bench_memory
        from factorydet_core.session.models import resolve_model

        update, close = progress_bar("memory", unit="scan")
        try:
            result = bench_memory(
                resolve_model(args.model),
                points=parse_ints(args.sizes, "--sizes"),
                seed=args.seed,
                overrides=parse_overrides(args.set),
                command=command,
                progress=update,
            )
        finally:
            close()
    else:
        if not args.data:
            raise InputError(f"bench {args.name} needs a DATA folder or file")
        # What each benchmark's progress counts: a hitl step is one detector's fit of a round, a
        # classifier step one configuration's training run.
        unit = {"hitl": "fit", "classifier": "run"}.get(args.name, "frame")
        update, close = progress_bar(args.name, unit=unit)
        try:
            if args.name == "classifier":
                from factorydet_core.evaluation.bench import bench_classifier

                result = bench_classifier(
                    args.data[0],
                    widths=parse_floats(args.widths, "--widths"),
                    features=_choices(args.features, "--features", ("aggregated", "direct")),
                    geometry=[
                        {"on": True, "off": False}[v]
                        for v in _choices(args.geometry, "--geometry", ("on", "off"))
                    ],
                    epochs=args.epochs,
                    max_fit_seconds=args.max_fit_seconds,
                    max_train_frames=args.train_frames,
                    max_test_frames=args.frames,
                    score_threshold=SCORE_THRESHOLD if args.score_threshold is None else args.score_threshold,
                    probability_exponent=args.probability_exponent,
                    box_quality=args.box_quality,
                    command=command,
                    progress=update,
                    quality_trees=args.quality_trees,
                )
            elif args.name == "hitl":
                from factorydet_core.evaluation.hitl import bench_hitl
                from factorydet_core.io.jsonfile import read_json, write_json
                from factorydet_core.scale.jobs import proposer

                earlier = _earlier_record(args)
                also = {path: read_json(path, what="bench hitl result") for path in args.resume_also or ()}
                result = bench_hitl(
                    args.data[0],
                    budgets=parse_ints(args.budgets, "--budgets"),
                    rounds=args.rounds,
                    settings=hitl_settings(args),
                    seeds=parse_ints(args.seeds, "--seeds"),
                    variants=None if args.variants is None else [v.strip() for v in args.variants.split(",")],
                    max_label_iou=args.hide_labelled,
                    review_by=args.review_by,
                    max_train_frames=args.train_frames,
                    max_test_frames=args.frames,
                    calibrate=args.calibrate,
                    command=command,
                    progress=update,
                    propose=proposer(execution),
                    earlier=earlier,
                    # Only a resumable run replaces --out before it is complete.
                    on_partial=(lambda partial: write_json(args.out, partial)) if args.resume else None,
                    heldout_seeds=parse_ints(args.heldout_seeds, "--heldout-seeds") if args.heldout else (),
                    heldout_frames=args.heldout_frames,
                    heldout_scratch=args.scratch,
                    best_view=args.review_best_view,
                    resume_other_library=args.resume_other_library,
                    also=also,
                )
                result["proposals_on"] = execution.describe()
                if args.out:
                    from factorydet_core.evaluation.report import hitl_markdown
                    from factorydet_core.io.atomic import write_text_atomic

                    write_json(args.out, result)
                    write_text_atomic(Path(args.out).with_suffix(".md"), hitl_markdown(result))
            elif args.name == "detect":
                from factorydet_core.evaluation.bench import bench_detect
                from factorydet_core.session.models import resolve_model

                result = bench_detect(
                    args.data[0],
                    resolve_model(args.model),
                    max_frames=args.frames,
                    repeats=args.repeats,
                    compare_model=resolve_model(args.compare_model) if args.compare_model else None,
                    compare_overrides=parse_overrides(args.compare_set),
                    compare_checkout=args.compare_checkout,
                    heldout_seeds=parse_ints(args.heldout_seeds, "--heldout-seeds") if args.heldout else (),
                    heldout_frames=args.heldout_frames,
                    busy=args.busy,
                    command=command,
                    progress=update,
                )
            elif args.name == "pipeline":
                result = bench_pipeline(
                    args.data if len(args.data) > 1 else args.data[0],
                    preset=args.preset,
                    overrides=parse_overrides(args.set),
                    max_frames=args.frames,
                    command=command,
                    progress=update,
                )
                result.pop("T_vehicle_sensor", None)
            else:
                sizes = parse_floats(args.voxel_sizes, "--voxel-sizes")
                result = bench_voxel_sweep(
                    args.data[0],
                    sizes,
                    max_frames=args.frames,
                    png=args.png,
                    command=command,
                    progress=update,
                )
        finally:
            close()
    print(json.dumps(result, indent=2))
    if args.readme:
        markdown = None
        # hitl renders its own table and writes its record at --out; the others' tables come from
        # their renderers (bench_tables), with the record at bench/<block>.json beside the page.
        if args.name == "hitl":
            from factorydet_core.evaluation.report import hitl_markdown

            markdown = hitl_markdown(result, heading=False)
        update_readme(args.readme, result, args.readme_block, markdown)
    return 0


def _propose_detector(args: argparse.Namespace, dataset, calibration_frame: int):
    """``propose``'s front half: ``--preset`` (the data's by default) with ``--set``'s overrides,
    its extrinsics refined by ICP on ``calibration_frame`` unless ``--no-calibrate``; and the preset."""
    from factorydet_core.detection.detector import Detector
    from factorydet_core.proposals.settings import front_end_params, preset_for

    preset = args.preset or preset_for(dataset.num_sensors)
    detector = Detector(front_end_params(preset, parse_overrides(args.set)))
    if args.calibrate and dataset.num_sensors > 1:
        detector.calibrate(dataset.frame(calibration_frame))
    return detector, preset


def _cmd_propose(args: argparse.Namespace) -> int:
    from factorydet_core.io.dataset import open_dataset

    if args.out is not None:
        return _cmd_propose_all(args)
    _refuse_batch_flags(args, "propose")
    dataset = open_dataset(args.data)
    if not 0 <= args.frame < dataset.num_frames:
        raise InputError(f"{dataset.name}: frame {args.frame} out of range [0, {dataset.num_frames})")
    detector, preset = _propose_detector(args, dataset, args.frame)
    result = detector.propose(dataset.frame(args.frame), detector.history(dataset, args.frame))
    proposals = result.proposals
    record = {
        "data": dataset.name,
        "frame": args.frame,
        "preset": preset,
        "num_points": result.merged.num_points,
        "num_points_segmented": result.cloud.num_points,
        "num_voxels": result.grid.num_voxels,
        "num_patches": result.segmentation.num_patches,
        "num_segments": result.segmentation.num_segments,
        "timings_ms": {k: round(v, 1) for k, v in result.timings_ms.items()},
        "box_format": "cx, cy, cz, dx, dy, dz, yaw (vehicle frame, metres, radians)",
        "proposals": [
            {
                "box": [round(float(v), 4) for v in proposals.boxes[i]],
                "num_points": int(proposals.num_points[i]),
                "num_voxels": int(proposals.num_voxels[i]),
                "level": LEVELS[int(proposals.level[i])],
                "box_kind": BOX_KINDS[int(proposals.box_kind[i])],
            }
            for i in range(len(proposals))
        ],
    }
    if args.json:
        print(json.dumps(record, indent=1))
    else:
        print(
            f"{dataset.name} frame {args.frame}: {len(proposals)} proposals from {record['num_segments']} "
            f"segments ({record['num_patches']} patches, {record['num_voxels']} voxels) in "
            f"{record['timings_ms']['total']:.0f} ms"
        )
        for row in record["proposals"][: args.limit]:
            box = ", ".join(f"{v:7.2f}" for v in row["box"])
            print(f"  [{box}]  {row['num_points']:6d} pts  {row['level']:<7} {row['box_kind']}")
        if len(proposals) > args.limit:
            print(f"  ... {len(proposals) - args.limit} more (--json prints all)")
    return 0


def parse_floats(text: str, option: str) -> list[float]:
    """``"0.1,0.2"`` -> ``[0.1, 0.2]``; anything else is an input error naming the option."""
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option} expects comma-separated numbers, got {text!r}") from None


def parse_ints(text: str, option: str = "--ids") -> list[int]:
    """``"3,4"`` -> ``[3, 4]``; anything else is an input error naming the option."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option} expects comma-separated integers, got {text!r}") from None
    if not values:
        raise InputError(f"{option} is empty")
    return values


def _open_session_db(args: argparse.Namespace, readonly: bool = False):
    """The session's database and data set (``session.store.open_session_data``); ``readonly``
    for the commands that only read, so that they never wait for a writer nor need write access."""
    from factorydet_core.session.store import open_session_data

    return open_session_data(args.session, args.root, getattr(args, "data", None), readonly=readonly)


SHARED_LOGINS = ("root",)
"""Logins people share (a container, a lab machine): never taken as a reviewer's name."""


def _author(args: argparse.Namespace) -> str:
    """``--author``, else the login name. The conflict rule of ``review`` and the undo stack are
    per author, so on a login people share (root) the login would make every reviewer one person:
    one would replace another's verdicts and undo another's edits without a word. There the name
    must be given."""
    if args.author is not None:
        return args.author
    try:
        login = getpass.getuser()
    except (OSError, KeyError):  # no login name in this environment (a bare container)
        login = None
    if login is None or login in SHARED_LOGINS:
        who = "no login name" if login is None else f"the login {login!r}, which people share"
        raise InputError(
            f"pass --author NAME: {who} cannot tell reviewers apart (verdicts and undo are per author)"
        )
    return login


def _training_progress() -> tuple[Callable[[str, int, int], None], Callable[[], None]]:
    bars: dict = {}
    names = {
        "fit": ("training", "epoch"),
        "proposals": ("proposals", "frame"),
        "compare": ("test frames", "frame"),
        "box quality": ("box quality regressor", "tree"),
    }
    started: set[str] = set()  # ("compare" says its start once)

    def progress(what: str, done: int, total: int) -> None:
        # ("compare" reports (0, 1) as it starts, then the test frames it proposes; on Ray workers
        # their first report is (0, N))
        # (the regressor's trees are reported while the run waits for them)
        if what in ("fit", "proposals") or (what in ("compare", "box quality") and done):
            if what not in bars:
                bars[what] = progress_bar(*names[what])
            bars[what][0](done, total)
            if done == total:
                bars.pop(what)[1]()
        elif what == "box quality" and done == 0:
            print("fitting the box quality regressor ...", file=sys.stderr)
        elif what == "round":
            print(f"round {done - 1} of {total - 1} done", file=sys.stderr)
        elif what == "calibrate":
            print("calibrating the extrinsics by ICP ...", file=sys.stderr)
        elif what == "compare" and what not in started:  # its start
            started.add(what)
            print("measuring before and after on the test frames ...", file=sys.stderr)

    def close() -> None:
        for _, finish in bars.values():
            finish()

    return progress, close


def _cmd_train(args: argparse.Namespace) -> int:
    from factorydet_core.detection.model import DetectionModel, copy_checkpoint
    from factorydet_core.evaluation.measure import unlearned_classes
    from factorydet_core.proposals.settings import front_end_from_record, front_end_params
    from factorydet_core.workflows import retrain_session

    db, dataset = _open_session_db(args)
    runs = db.training_runs()
    previous = runs[-1] if runs else None
    if args.mode == "next" and previous is None:
        raise InputError(f"session {args.session!r} has no training run to continue; use --mode full")
    if args.compare and not dataset.splits.get("test"):
        raise InputError("--compare needs test frames (the data set has no test split)")
    front_end = None
    if args.mode == "next" and args.preset is None and not args.set:
        # The same front half as the run it continues, so that the point sets compare. The record is
        # read from the session database: checked like a checkpoint's note.
        config = previous["config"]
        try:
            front_end = front_end_from_record(config.get("front_end") if isinstance(config, dict) else config)
        except InputError as exc:
            raise InputError(f"the front-half settings of run {previous['id']}: {exc}") from None
    if front_end is None:
        front_end = front_end_params(args.preset, parse_overrides(args.set), dataset.num_sensors)
    settings = loop_settings_from_args(args)
    before = {}
    if args.compare and previous is not None:
        before = {f"run {previous['id']}": DetectionModel.load(db.session.path / previous["model_path"])}
    progress, close = _training_progress()
    try:
        done = retrain_session(
            db, dataset, settings, front_end, mode=args.mode, before=before, compare=args.compare,
            calibrate=args.calibrate, max_train_frames=args.frames, max_test_frames=args.test_frames,
            progress=progress, command=args.command_line, execution=execution_from_args(args),
        )  # fmt: skip
    finally:
        close()
    run_id, run = done.run_id, done.run
    summary = {
        "session": db.session.name,
        "run_id": run_id,
        "mode": args.mode,
        "train_frames": run.train_frames,
        "rounds": [
            {
                k: r[k]
                for k in ("round", "num_positives", "num_background", "fit_seconds", "num_false_positives")
                if k in r
            }
            | {
                "train_f1": r["train_metrics"]["f1"],
                "num_mined": len(r["mined"]),
                "num_queued": len(r.get("queued", [])),  # for review alone (review_extra)
            }
            for r in run.rounds
        ],
        "review_queue": len(db.review_queue(run_id)),
        "model": str(db.session.models_dir / f"run_{run_id:03d}" / "final.pt"),
        # Classes labelled on the training frames that the model finds none of there.
        "unlearned_classes": unlearned_classes(run.rounds[-1]["train_metrics"]),
        # What the run did otherwise than its settings asked (trained afresh, folds skipped).
        "notes": list(done.notes),
    }
    if done.comparison is not None:
        summary["compare"] = {
            name: {k: m[k] for k in ("precision", "recall", "f1")} for name, m in done.comparison.items()
        }
    if args.export:
        # The run's final checkpoint as it is, with its note (settings, rounds, command), each file
        # replaced whole (an interrupted export over default.pt leaves the old one).
        copy_checkpoint(summary["model"], args.export)
        summary["exported"] = args.export
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_queue(args: argparse.Namespace) -> int:
    db, _ = _open_session_db(args, readonly=True)
    queue = db.review_queue(
        args.run, predicted_class=args.class_name, frame_index=args.frame, pending_only=args.pending
    )
    progress = db.review_progress(args.run)
    if args.json:
        print(json.dumps({"progress": progress, "items": queue[: args.limit or None]}, indent=2))
        return 0
    counts = ", ".join(f"{v.replace('_', ' ')} {progress[v]}" for v in ("background", "object", "wrong_box"))
    print(f"{progress['reviewed']} of {progress['total']} reviewed ({counts})")
    for item in queue[: args.limit or None]:
        verdict = item["verdict"] or "-"
        if item["verdict_class"]:
            verdict += f" ({item['verdict_class']})"
        alone = "" if item["in_background"] else "  (for review alone)"
        print(f"{item['id']:6d}  frame {item['frame_index']:3d}  {item['predicted_class']:8s} "
              f"{item['score']:.3f}  {verdict}{alone}")  # fmt: skip
    return 0


def _cmd_review(args: argparse.Namespace) -> int:
    from factorydet_core.session.store import EditConflictError

    db, _ = _open_session_db(args)
    try:
        ids, author = parse_ints(args.ids), _author(args)
        edit_id = db.review(ids, args.verdict, author, class_name=args.class_name, override=args.override)
    except EditConflictError as exc:
        # Every refused item on stdout (the one-line error on stderr says why, for the first few).
        print(json.dumps({"edit": None, "conflicts": exc.conflicts}))
        raise
    print(json.dumps({"edit": edit_id, "progress": db.review_progress()}))
    return 0


def _cmd_labels(args: argparse.Namespace) -> int:
    from factorydet_core.session.labels_io import export_labels, import_labels

    db, _ = _open_session_db(args, readonly=args.action == "export")
    if args.action == "spread":
        from factorydet_core.session.world import session_world, spread_session

        update, close = progress_bar("placing the frames")
        try:
            world, _ = session_world(db.session, db.dataset, progress=update)
        finally:
            close()
        added = spread_session(db, world, args.author)
        print(json.dumps({"added": len(added), "objects": len({lab.instance_id for lab in added}),
                          "edit": added.edit_id}))  # fmt: skip
        return 0
    if args.action == "prelabel":
        return _prelabel(db, args)
    if args.path is None:
        raise InputError(f"labels {args.action}: give the path to {args.action} (a file or folder)")
    frames = parse_ints(args.frames, "--frames") if args.frames else None
    if args.action == "export":
        paths = export_labels(db, args.format or "json", args.path, frames)
        print(json.dumps({"exported": [str(p) for p in paths], "format": args.format or "json"}))
        return 0
    report = import_labels(db, args.path, args.author, args.format)
    print(json.dumps(report, indent=2))
    return 0


def _prelabel(db, args: argparse.Namespace) -> int:
    """``labels prelabel``: the model's detections of each frame become pre-labels, one undoable
    edit per frame, as the app's *Pre-label this frame* makes them (``editing.prelabel_frame``)."""
    from factorydet_core.detection.detector import Detector
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.session.editing import prelabel_frame
    from factorydet_core.session.models import resolve_model
    from factorydet_core.session.world import calibrated_extrinsics

    if not 0.0 <= args.min_score <= 1.0:
        raise InputError(f"--min-score must lie in [0, 1], got {args.min_score:g}")
    dataset = db.dataset
    chosen = db.shown_model() if args.model is None else None
    if chosen is not None and chosen[1].is_file():
        path = chosen[1]
    else:
        path = resolve_model(args.model or "default", args.root)
    model = DetectionModel.load(path)
    # The extrinsics the app detects with (refined between the sensors), so that the boxes are the
    # ones a person sees there.
    detector = Detector.for_model(model, dataset.num_sensors, calibrated_extrinsics(dataset))
    frames = parse_ints(args.frames, "--frames") if args.frames else list(range(dataset.num_frames))
    report = {"model": str(path), "min_score": args.min_score, "frames": {}}
    update, close = progress_bar("pre-labelling")
    try:
        for n, index in enumerate(frames):
            update(n, len(frames))
            history = detector.history(dataset, index)
            detections = detector.detect(
                dataset.frame(index), history, score_threshold=args.min_score
            ).detections
            added = prelabel_frame(db, index, detections, args.author, args.min_score)
            report["frames"][str(index)] = len(added)
        update(len(frames), len(frames))
    finally:
        close()
    report["added"] = sum(report["frames"].values())
    print(json.dumps(report))
    return 0


def _cmd_undo(args: argparse.Namespace) -> int:
    author = _author(args)
    db, _ = _open_session_db(args)
    edit = db.redo(author) if args.redo else db.undo(author)
    if edit is None:
        print(f"nothing to {'redo' if args.redo else 'undo'} for {author}")
        return 1
    print(f"{'redid' if args.redo else 'undid'} edit {edit.id}: {edit.summary}")
    return 0


def _detection_rows(detections, keep_suppressed: bool) -> list[dict]:
    rows = []
    for k in range(len(detections)):
        if not keep_suppressed and detections.suppressed_by[k] >= 0:
            continue
        rows.append(
            {
                "class": detections.class_names[int(detections.class_ids[k])],
                "score": round(float(detections.scores[k]), 4),
                "box": [round(float(v), 4) for v in detections.boxes[k]],
                "proposal": int(detections.proposal_ids[k]),
                "suppressed_by": int(detections.suppressed_by[k]),
                "probabilities": {
                    name: round(float(p), 4)
                    for name, p in zip((*detections.class_names, "background"), detections.probabilities[k])
                },
            }
        )
    return rows


def add_batch_flags(parser: argparse.ArgumentParser, verb: str, files: str, what: str) -> None:
    """A one-frame command's batch mode (``detect``, ``propose``): ``--out`` with ``--split`` and
    ``--frames``, and the execution switch (``add_execution_flags``, ``what`` the workers do)."""
    parser.add_argument(
        "--out",
        default=None,
        help=f"{verb} every frame of --split into this folder, one .npz per frame{files}; a re-run "
        "skips the frames already there",
    )
    parser.add_argument(
        "--split", default="all", help="with --out: 'all' or a split of the data set (test, train)"
    )
    parser.add_argument(
        "--frames", type=int, default=None, help="with --out: only the first N frames of the split"
    )
    add_execution_flags(parser, what)


def add_execution_flags(
    parser: argparse.ArgumentParser, what: str = "its work", scratch: bool = True
) -> None:
    """The batch commands' switch between this process and Ray workers (``scale.runner.Execution``);
    ``what`` says what the workers do; ``scratch``: also ``--scratch`` (a command with a scratch
    folder of its own has not)."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"run {what} on N Ray workers (a local Ray unless --ray names a cluster); default: this "
        "process alone, no Ray needed",
    )
    parser.add_argument(
        "--ray",
        dest="ray_address",
        default=None,
        metavar="ADDRESS",
        help="run on Ray: 'local' (start one here), 'auto' (the cluster this machine joined with "
        "ray start) or HOST:PORT; workers default to the cluster's CPUs",
    )
    parser.add_argument(
        "--worker-threads", type=int, default=None, help="with Ray: threads of each worker (default 1)"
    )
    if scratch:
        parser.add_argument(
            "--scratch",
            default=None,
            help="with Ray: a folder every node sees, for the frames' files of work without an output "
            "folder of its own (default: $TMPDIR, enough on one machine)",
        )


def execution_from_args(args: argparse.Namespace) -> Execution:
    """The ``Execution`` of ``add_execution_flags``' flags; Ray's own flags without Ray are refused."""
    from factorydet_core.scale.runner import Execution

    execution = Execution(
        workers=args.workers,
        ray_address=args.ray_address,
        threads=1 if args.worker_threads is None else args.worker_threads,
        scratch=args.scratch,
    )
    if not execution.uses_ray and (args.worker_threads is not None or args.scratch is not None):
        raise InputError(
            "--worker-threads and --scratch apply to Ray workers: add --workers N or --ray ADDRESS"
        )
    return execution


def frames_of(dataset, split: str, max_frames: int | None) -> list[int]:
    """The frame indices of ``split`` ("all", or a split of the data set's manifest), the first
    ``max_frames`` of them when given."""
    if split == "all":
        frames = list(range(dataset.num_frames))
    elif split in dataset.splits:
        frames = list(dataset.splits[split])
    else:
        raise InputError(f"{dataset.name} has no split {split!r} (it has: all, {', '.join(dataset.splits)})")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--frames must be at least 1, got {max_frames}")
    return frames[:max_frames] if max_frames else frames


def _cmd_detect_all(args: argparse.Namespace) -> int:
    """``detect --out``: every frame of a split, one detection file per frame, resumable."""
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.evaluation.evaluate import detector_for
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import DetectJob
    from factorydet_core.session.models import resolve_model

    execution = execution_from_args(args)
    dataset = open_dataset(args.data)
    frames = frames_of(dataset, args.split, args.frames)
    model_path = resolve_model(args.model, args.root)
    # Calibrated once here: every worker merges with the same extrinsics.
    detector = detector_for(DetectionModel.load(model_path), dataset, calibrate=args.calibrate)
    job = DetectJob(
        str(dataset.path),
        str(model_path),
        detector.T_vehicle_sensor,
        score_threshold=args.score_threshold,
        nms_iou=args.nms_iou,
    )
    return _run_batch(job, frames, args, execution, "detecting", "detected")


def _refuse_batch_flags(args: argparse.Namespace, verb: str) -> None:
    """A one-frame ``detect`` or ``propose`` (no ``--out``) given a batch's flags: say so rather
    than ignore them."""
    given = [
        flag
        for flag, value, default in (
            ("--workers", args.workers, None),
            ("--ray", args.ray_address, None),
            ("--worker-threads", args.worker_threads, None),
            ("--scratch", args.scratch, None),
            ("--split", args.split, "all"),
            ("--frames", args.frames, None),
        )
        if value != default
    ]
    if given:
        raise InputError(f"{', '.join(given)} {verb} a batch: give --out DIR for its files")


def _run_batch(job, frames: list[int], args: argparse.Namespace, execution, doing: str, done: str) -> int:
    """A batch command's run (``detect --out``, ``propose --out``): the frames through
    ``scale.runner.run_frames`` into ``args.out`` with a progress bar, then its summary."""
    from factorydet_core.scale.runner import run_frames

    update, close = progress_bar(doing)
    try:
        run = run_frames(job, frames, args.out, execution, update)
    finally:
        close()
    summary = run.summary()
    print(
        json.dumps(summary, indent=1)
        if args.json
        else (
            f"{summary['num_computed']} frames {done}, {summary['num_skipped']} already done, "
            f"{summary['frames_per_second']} frames/s on {summary['workers']} workers: {run.out_dir}"
        )
    )
    return 0


def _cmd_propose_all(args: argparse.Namespace) -> int:
    """``propose --out``: the front half of every frame of a split, one file per frame (the
    training cache's format, ``training.mining.proposals_from_arrays``), resumable."""
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.scale.jobs import ProposeJob

    execution = execution_from_args(args)
    dataset = open_dataset(args.data)
    frames = frames_of(dataset, args.split, args.frames)
    # Calibrated once here, on the first frame: every worker merges with the same extrinsics.
    detector, _ = _propose_detector(args, dataset, frames[0] if frames else 0)
    job = ProposeJob(str(dataset.path), detector.params, detector.T_vehicle_sensor)
    return _run_batch(job, frames, args, execution, "proposing", "proposed")


def _cmd_detect(args: argparse.Namespace) -> int:
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.evaluation.evaluate import detector_for
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.session.models import resolve_model

    if args.out is not None:
        return _cmd_detect_all(args)
    _refuse_batch_flags(args, "detect")
    dataset = open_dataset(args.data)
    if not 0 <= args.frame < dataset.num_frames:
        raise InputError(f"{dataset.name}: frame {args.frame} out of range [0, {dataset.num_frames})")
    model_path = resolve_model(args.model, args.root)
    model = DetectionModel.load(model_path)
    detector = detector_for(model, dataset, calibrate=args.calibrate)
    result = detector.detect(
        dataset.frame(args.frame),
        detector.history(dataset, args.frame),
        score_threshold=args.score_threshold,
        nms_iou=args.nms_iou,
    )
    detections = result.detections
    record = {
        "data": dataset.name,
        "frame": args.frame,
        "model": str(model_path),
        "score_threshold": model.score_threshold if args.score_threshold is None else args.score_threshold,
        "class_score_thresholds": model.class_score_thresholds if args.score_threshold is None else None,
        "nms_iou": model.nms_iou if args.nms_iou is None else args.nms_iou,
        "num_proposals": len(result.proposal.proposals),
        "num_point_sets": result.groups.num_groups,
        "num_detections": int(detections.kept_mask.sum()),
        "num_suppressed": int((~detections.kept_mask).sum()),
        "timings_ms": {k: round(v, 1) for k, v in result.timings_ms.items()},
        "box_format": "cx, cy, cz, dx, dy, dz, yaw (vehicle frame, metres, radians)",
        "detections": _detection_rows(detections, args.suppressed),
    }
    if args.json:
        print(json.dumps(record, indent=1))
    else:
        print(
            f"{dataset.name} frame {args.frame}: {record['num_detections']} detections "
            f"({record['num_suppressed']} suppressed by NMS) in {record['timings_ms']['total']:.0f} ms"
        )
        for row in record["detections"]:
            box = ", ".join(f"{v:7.2f}" for v in row["box"])
            print(f"  {row['class']:<7} {row['score']:.2f}  [{box}]")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from factorydet_core.evaluation.evaluate import evaluate, strip_curves
    from factorydet_core.evaluation.plots import plot_pr_curves
    from factorydet_core.scale.evaluate import evaluate_batch
    from factorydet_core.session.models import resolve_model

    model_path = resolve_model(args.model, args.root)
    execution = execution_from_args(args)
    options = {
        "iou_threshold": args.iou,
        "max_frames": args.frames,
        "calibrate": args.calibrate,
        "command": args.command_line,
        "score_thresholds": parse_floats(args.thresholds, "--thresholds") if args.thresholds else (),
    }
    if args.out is None and not execution.uses_ray:
        update, close = progress_bar("proposals")
        try:
            result = evaluate(
                args.data, model_path, with_baseline=args.baseline, progress=lambda _, d, n: update(d, n),
                **options,
            )  # fmt: skip
        finally:
            close()
    else:
        # Per-frame work in a folder (--out, or a temporary one under the scratch folder), on Ray
        # workers when asked.
        if args.baseline:
            raise InputError("--baseline trains in this process: leave out --out, --workers and --ray")
        with execution.scratch_folder("factorydet-evaluate-") as scratch:
            update, close = progress_bar("evaluating")
            try:
                out = args.out if args.out is not None else Path(scratch) / "frames"
                result = evaluate_batch(args.data, model_path, out, execution, progress=update, **options)
            finally:
                close()
        if args.out is None:
            result["batch"]["out"] = None  # the temporary folder is gone
    if args.png:
        headline = result["against"][result["reference"]]
        plot_pr_curves(headline, args.png, f"{result['data']}: PR at IoU {args.iou} vs {result['reference']}")
        result["png"] = args.png
    print(json.dumps(strip_curves(result), indent=2))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from factorydet_core.evaluation.report import write_report
    from factorydet_core.session.models import resolve_model

    model_path = resolve_model(args.model, args.root)
    update, close = progress_bar("report")
    try:
        out = write_report(
            args.data,
            model_path,
            args.out,
            iou_threshold=args.iou,
            max_frames=args.frames,
            sweep_sizes=parse_floats(args.sweep, "--sweep") if args.sweep else [],
            sweep_frames=args.sweep_frames,
            calibrate=args.calibrate,
            command="factorydet " + " ".join(sys.argv[1:]),
            progress=lambda _, d, n: update(d, n),
            train_data=args.train_data,
        )
    finally:
        close()
    print(f"wrote {out}")
    return 0


BENCH_LOOP_FIELDS = (
    "method", "class_weight", "round_epochs", "hold_places", "class_thresholds", "queue_order",
    "review_order", "review_extra", "refit_box_quality", "refit_trees", "refit_row_share",
    "model_box_targets",
    "recalibrate_background", "recalibrate_by_class", "hold_confident", "pseudo_label_confident",
    "carry_pseudo_labels", "threshold_folds", "threshold_objective", "quality_trees", "continue_folds",
    "label_min_points", "threshold_label_min_points",
)  # fmt: skip
"""The ``LoopSettings`` fields ``factorydet bench`` takes as ``add_loop_flags``' flags (its other
training flags are the benchmarks' own, with defaults of their own)."""


def add_loop_flags(parser: argparse.ArgumentParser, fields: Collection[str] | None = None) -> None:
    """A flag per ``training.settings.LOOP_CONTROLS`` entry (those of ``fields`` only, when given),
    its default ``LoopSettings()``'s."""
    for control in LOOP_CONTROLS:
        if fields is not None and control.field not in fields:
            continue
        default = control.default
        shown = control.shown(default)
        if control.kind is bool:
            parser.add_argument(
                control.cli_flag,
                dest=control.field,
                action="store_false" if default else "store_true",
                help=f"{control.help} ({'on; this flag turns it off' if default else 'off by default'})",
            )
        elif control.choices is not None:
            parser.add_argument(
                control.cli_flag,
                dest=control.field,
                choices=[text for text, _ in control.choices],
                default=shown,
                help=f"{control.help} (default {shown})",
            )
        else:
            parser.add_argument(
                control.cli_flag,
                dest=control.field,
                type=control.kind,
                default=default,
                help=f"{control.help} (default {shown})",
            )


def loop_settings_from_args(args: argparse.Namespace) -> LoopSettings:
    """The ``LoopSettings`` of ``add_loop_flags``' flags (checked by ``LOOP_CONTROLS``)."""
    return loop_settings_from({control.field: getattr(args, control.field) for control in LOOP_CONTROLS})


def build_parser(
    add_commands: Callable[[argparse._SubParsersAction], None] | None = None,
) -> argparse.ArgumentParser:
    """The ``factorydet`` parser; ``add_commands(subparsers)`` adds more commands (the app's)."""
    parser = argparse.ArgumentParser(prog="factorydet", description="Factory LiDAR detection tools.")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="threads of every pool (numba, torch, OpenMP, BLAS; default: FACTORYDET_THREADS, "
        "OMP_NUM_THREADS or the cores this process may use)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    if add_commands is not None:
        add_commands(sub)

    p = sub.add_parser("simulate", help="write a simulated factory data set")
    p.add_argument(
        "--out",
        required=True,
        help="data set folder to write (with Ray workers a re-run finishes an interrupted one; in "
        "this process it is written afresh)",
    )
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    add_execution_flags(p, "the ray casting of the frames")
    p.add_argument(
        "--unlabelled-fraction", type=float, default=0.3, help="share of eligible objects left unannotated"
    )
    p.add_argument(
        "--min-points", type=int, default=50, help="instances with fewer points are never annotated"
    )
    p.add_argument("--points", type=int, default=80_000, help="approximate points per merged frame")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("demo", help="build the demo session if it is missing")
    p.add_argument("--session", default="demo", choices=["demo"])
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("info", help="summarise a data set folder or point-cloud file")
    p.add_argument("path")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser(
        "propose",
        help="object proposals of one frame, or (--out) of every frame of a split into files "
        "(the detector's front half)",
    )
    p.add_argument("data", help="a data set folder or any point-cloud file the readers open")
    p.add_argument("--frame", type=int, default=0, help="frame index (0-based)")
    p.add_argument("--preset", default=None, help="agv or indoor (default: agv for multi-sensor data)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a parameter (repeatable)")
    p.add_argument(
        "--no-calibrate", dest="calibrate", action="store_false", help="skip the ICP extrinsic refinement"
    )
    p.add_argument("--json", action="store_true", help="print every proposal as JSON")
    p.add_argument("--limit", type=int, default=20, help="rows of the text listing")
    add_batch_flags(p, "propose", " (the training cache's format)", "the proposals of the frames")
    p.set_defaults(func=_cmd_propose)

    p = sub.add_parser(
        "train",
        help="train the classifier into a session: a full run with blind hard-negative mining, or the"
        " next round on the session's corrected labels and review verdicts",
    )
    p.add_argument("data", nargs="?", default=None, help="data set folder (default: the session's)")
    p.add_argument("--session", required=True, help="session to read labels from and write models into")
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.add_argument(
        "--mode",
        default="full",
        choices=["full", "next"],
        help="full: retrain from scratch with --rounds mining rounds; next: one more round",
    )
    # One flag per LOOP_CONTROLS entry: the flags and the app's Training panel cannot disagree.
    add_loop_flags(p)
    p.add_argument("--frames", type=int, default=None, help="use only the first N training frames")
    p.add_argument("--preset", default=None)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a front-half parameter")
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false")
    p.add_argument(
        "--compare",
        action="store_true",
        help="measure the previous and the new model on the test frames against the session's labels",
    )
    p.add_argument("--test-frames", type=int, default=None, help="with --compare: the first N test frames")
    p.add_argument("--export", default=None, help="also save the final model to this .pt path")
    # The frames the session's proposals cache lacks are proposed there; the fits run here.
    add_execution_flags(
        p, "the proposals of the frames the session has not cached and each mining round's scoring"
    )
    p.set_defaults(func=_cmd_train)

    def session_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--session", required=True)
        p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
        p.add_argument("--data", default=None, help="data set folder (default: the session's)")

    p = sub.add_parser(
        "queue",
        help="list the review queue: negatives mined by a run (and the false positives it "
        "queued for review alone), in its review order",
    )
    session_args(p)
    p.add_argument("--run", type=int, default=None, help="training run (default: the latest)")
    p.add_argument("--class", dest="class_name", default=None, help="only this predicted class")
    p.add_argument("--frame", type=int, default=None, help="only this frame")
    p.add_argument("--pending", action="store_true", help="only items without a decided verdict")
    p.add_argument("--limit", type=int, default=50, help="items to list (0: all)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_queue)

    p = sub.add_parser(
        "review",
        help="give a verdict on mined negatives (one undoable edit)",
        description="Give a verdict on mined negatives, as one undoable edit. Verdicts are told apart "
        "by author name: an item another author has decided is refused unless --override, while the "
        "same author may change their own verdicts freely. The name defaults to the login, so on an "
        "account people share every reviewer would be the same author and replace each other's "
        "verdicts without a conflict; as root, --author is therefore required.",
    )
    session_args(p)
    p.add_argument("--ids", required=True, help="comma-separated queue item ids")
    p.add_argument("--verdict", required=True, choices=["background", "object", "wrong_box", "skip"])
    p.add_argument("--class", dest="class_name", default=None, help="the object's class (verdict object)")
    p.add_argument(
        "--author",
        default=None,
        help="who reviews: verdicts and undo are per author name (default: the login name; required "
        "as root, a login people share)",
    )
    p.add_argument(
        "--override",
        action="store_true",
        help="replace verdicts other reviewers gave (without it they are reported and nothing is written)",
    )
    p.set_defaults(func=_cmd_review)

    p = sub.add_parser(
        "labels",
        help="export a session's labels, import labels into it, spread them (label once: each "
        "object that stands still labelled in every frame that shows it), or pre-label frames with "
        "the model (its detections as labels a person confirms in the app)",
    )
    p.add_argument("action", choices=["export", "import", "spread", "prelabel"])
    p.add_argument(
        "path", nargs="?", help="export: a .json file or a folder (kitti, npz); import: a file or folder"
    )
    session_args(p)
    p.add_argument("--format", default=None, choices=["json", "kitti", "npz"], help="default: json / guessed")
    p.add_argument(
        "--frames", default=None, help="export, prelabel: comma-separated frame indices (default: all)"
    )
    p.add_argument(
        "--author", default=getpass.getuser(), help="import, spread, prelabel: who the labels are signed by"
    )
    p.add_argument(
        "--model", default=None,
        help="prelabel: a checkpoint, 'default' or a session (default: the model the session shows)",
    )  # fmt: skip
    p.add_argument(
        "--min-score", type=float, default=PRELABEL_SCORE,
        help=f"prelabel: the lowest detection score that becomes a pre-label (default {PRELABEL_SCORE})",
    )  # fmt: skip
    p.set_defaults(func=_cmd_labels)

    p = sub.add_parser("undo", help="undo (or --redo) an author's latest edit of a session")
    session_args(p)
    p.add_argument(
        "--author",
        default=None,
        help="whose edit (default: the login name; required as root, a shared login)",
    )
    p.add_argument("--redo", action="store_true")
    p.set_defaults(func=_cmd_undo)

    p = sub.add_parser(
        "detect", help="detections of one frame, or (--out) of every frame of a split into files"
    )
    p.add_argument("data")
    p.add_argument("--model", default="default", help="'default', a .pt checkpoint, or a session name")
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.add_argument("--frame", type=int, default=0, help="the frame to detect (without --out)")
    add_batch_flags(p, "detect", "", "the detection of the frames")
    p.add_argument("--score-threshold", type=float, default=None, help="default: the model's")
    p.add_argument("--nms-iou", type=float, default=None, help="default: the model's")
    p.add_argument("--suppressed", action="store_true", help="also list what NMS suppressed")
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_detect)

    p = sub.add_parser("evaluate", help="precision, recall, F1 and AP per class on the test frames")
    p.add_argument("data")
    p.add_argument("--model", default="default", help="'default', a .pt checkpoint, or a session name")
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.add_argument("--iou", type=float, default=0.6)
    p.add_argument("--frames", type=int, default=None, help="only the first N test frames")
    p.add_argument("--baseline", action="store_true", help="also train and measure the baseline")
    p.add_argument(
        "--thresholds",
        default=None,
        help="comma-separated score thresholds: also print precision, recall and F-score at each "
        "(operating_points), to choose the operating threshold",
    )
    p.add_argument("--png", default=None, help="write the precision-recall curves here")
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false")
    p.add_argument("--json", action="store_true", help="print JSON (the default; kept for scripts)")
    p.add_argument(
        "--out",
        default=None,
        help="keep each frame's measurements in this folder (a re-run resumes); with --workers or "
        "--ray and no --out, a temporary folder",
    )
    add_execution_flags(p, "the measurement of the frames")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("report", help="write the results report (tables, PR curve, grid sweep)")
    p.add_argument("data")
    p.add_argument("--model", default="default")
    p.add_argument("--root", default=None)
    p.add_argument("--out", default="docs/results.md")
    p.add_argument("--iou", type=float, default=0.6)
    p.add_argument("--frames", type=int, default=None, help="only the first N test frames")
    p.add_argument("--sweep", default="0.1,0.2,0.3", help="voxel sizes of the grid sweep ('' skips it)")
    p.add_argument("--sweep-frames", type=int, default=4, help="train frames per sweep point")
    p.add_argument(
        "--train-data",
        default=None,
        help="data set whose training frames train the baseline and the sweep (the model's; default: DATA)",
    )
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("bench", help="benchmarks; each prints one JSON object")
    p.add_argument(
        "name",
        choices=[
            "simulate",
            "pipeline",
            "sweep",
            "detect",
            "classifier",
            "hitl",
            "hitl-compare",
            "hitl-pool",
            "quality",
            "fuzz",
            "import",
            "memory",
            "mining",
            "world-labels",
            "scale",
        ],
    )
    p.add_argument(
        "data",
        nargs="*",
        help="pipeline: a simulated data set folder, or point-cloud files (recall pooled); sweep: a folder; "
        "hitl-compare: two bench hitl records, RECORD BASELINE (seed by seed, RECORD minus BASELINE), or one "
        "record with --variants A,B; hitl-pool: two or more bench hitl records of one plan on disjoint "
        "held-out factories",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames to run (simulate: 10, hitl: all test frames, spread evenly if fewer; others: 4)",
    )
    p.add_argument("--points", type=int, default=80_000, help="simulate: points per frame")
    p.add_argument("--seed", type=int, default=0, help="simulate, fuzz, memory: seed")
    p.add_argument(
        "--sizes",
        default="1000000,5000000",
        help="memory: points of the dense simulated scans, comma-separated (each detected in a child "
        "process)",
    )
    p.add_argument("--cases", type=int, default=1000, help="fuzz: mutated files to try")
    p.add_argument("--boxes", type=int, default=10_000, help="import: boxes in the imported file")
    p.add_argument(
        "--large-box", action="store_true", help="import: add one 100 x 100 m box to the first frame"
    )
    p.add_argument("--targets", default=None, help="fuzz: comma-separated targets (default: all)")
    p.add_argument(
        "--memory-limit-mb", type=float, default=2048.0, help="fuzz: a case using more fails (default 2048)"
    )
    p.add_argument("--keep", default=None, help="fuzz: copy the failing cases' files into this folder")
    p.add_argument("--preset", default=None, help="pipeline: agv or indoor (default: by data)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="pipeline, quality, memory: override a front-half parameter (quality: e.g. history_frames=2; "
        "memory: e.g. max_points=null)",
    )
    p.add_argument("--voxel-sizes", default="0.1,0.15,0.2,0.3,0.4", help="sweep: comma-separated sizes (m)")
    p.add_argument("--png", default=None, help="sweep: write the plot here")
    p.add_argument(
        "--model",
        default="default",
        help="detect: checkpoint, session name, 'default' or 'paper'; quality: the paper pipeline's "
        "checkpoint ('paper': the shipped one)",
    )
    p.add_argument("--repeats", type=int, default=1, help="detect: runs of each frame")
    p.add_argument(
        "--compare-model",
        default=None,
        help="detect: a second model run on the same frames, interleaved; the record gives the ratios",
    )
    p.add_argument(
        "--compare-set",
        action="append",
        metavar="KEY=VALUE",
        help="detect: a second configuration with this setting changed, interleaved (a front-half "
        "setting; the box quality screen: screen_trees, screen_keep; interleaved_walk=0: the "
        "reference tree walk, one row at a time; skip_unread_features=0: the proposals' 3DmFV "
        "computed for a model that reads none); mining: a training setting (e.g. "
        "refit_row_share=1.0), the continued round timed with and without it for each of --seeds",
    )
    p.add_argument(
        "--compare-checkout",
        default=None,
        metavar="DIR",
        help="detect: compare with another version of the project's code (a folder holding its "
        "factorydet_core, e.g. 'git worktree add /tmp/before <commit>'), run in a child process "
        "on the same frames, interleaved; the record gives the ratios",
    )
    p.add_argument(
        "--busy",
        action="store_true",
        help="detect: also run each reference frame beside a process spinning one core; the record "
        "gives the slowdown",
    )
    p.add_argument(
        "--heldout",
        action="store_true",
        help="detect, mining: also measure both configurations on the held-out factories "
        "(--heldout-seeds, --heldout-frames); hitl: measure on them instead of the test frames",
    )
    p.add_argument(
        "--session",
        default=None,
        help="mining: the session whose next round is timed (a copy of it: the session is not changed)",
    )
    p.add_argument("--root", default=None, help="mining: sessions folder (default: ./sessions)")
    p.add_argument(
        "--full-run",
        action="store_true",
        help="mining: first time a full retrain on each copy, which the next round continues (what the "
        "app's Train does on a session without a run)",
    )
    p.add_argument(
        "--before-after",
        action="store_true",
        help="mining: each run also measures the models before and after on the test frames, as the app's "
        "retrain does",
    )
    p.add_argument(
        "--verdicts",
        type=int,
        default=0,
        help="mining: answer the first N review queue items 'object' before the timed round, as a "
        "reviewer would (the labels change, so the box quality regressor is fitted again)",
    )
    p.add_argument("--widths", default="0.0625,1.0", help="classifier: network widths to compare")
    p.add_argument("--features", default="aggregated,direct", help="classifier: proposal features")
    p.add_argument(
        "--geometry",
        default="on,off",
        help="classifier: network inputs to compare (on: 3DmFV and descriptors, off: 3DmFV alone)",
    )
    p.add_argument("--epochs", type=int, default=20, help="classifier, hitl, quality: epochs per fit")
    p.add_argument("--max-fit-seconds", type=float, default=None, help="classifier: time budget per fit")
    p.add_argument(
        "--train-frames",
        type=int,
        default=None,
        help="classifier: first N training frames; hitl: N training frames spread over the split",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="hitl, quality: continue the (partial) result at --out, training only the seeds (hitl: "
        "the seeds' detectors) it lacks; scale: running only the runs it lacks; with it, --out is "
        "also written after every detector of a seed (hitl), training seed (quality) or run (scale)",
    )
    p.add_argument(
        "--resume-also",
        default=None,
        metavar="PATHS",
        help="hitl, with --resume: also read back the finished runs of these records (comma-separated; "
        "the same benchmark's other seeds run by another process, say), so that --out holds them all",
    )
    p.add_argument(
        "--resume-other-library",
        action="store_true",
        help="hitl, quality, with --resume: read back the runs of another version of the library too (by "
        "default they train again when there is training to do; the record then says it mixes versions)",
    )
    p.add_argument(
        "--seeds",
        default="0",
        help="hitl, quality, mining --compare-set: training seeds, comma-separated (F is their mean)",
    )
    p.add_argument("--budgets", default="50,200", help="hitl: reviews per round K, comma-separated")
    p.add_argument(
        "--review-by", default="item", choices=["item", "place"],
        help="hitl: the reviewer answers queue items one by one, or places as the app shows them by "
        "default (one verdict per object mined in several frames, objects labelled once)",
    )  # fmt: skip
    p.add_argument(
        "--review-best-view", action="store_true",
        help="hitl, with --review-by place: a place with too few points for the annotation policy is "
        "judged where the frames see it best, as the review panel's 'Look where it is seen best' [I]",
    )  # fmt: skip
    p.add_argument("--rounds", type=int, default=2, help="hitl, quality: mining rounds after the first fit")
    p.add_argument("--negatives", type=int, default=500, help="hitl: mined negatives per round")
    p.add_argument("--initial-negatives", type=int, default=2000, help="hitl: first random background set")
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="classifier, hitl: operating score; with box quality a score is probability to "
        f"--probability-exponent x predicted IoU (default {SCORE_THRESHOLD})",
    )
    p.add_argument(
        "--probability-exponent",
        type=float,
        default=PROBABILITY_EXPONENT,
        help="classifier, hitl: with box quality, the class probability's power in the score "
        f"(default {PROBABILITY_EXPONENT})",
    )
    p.add_argument(
        "--mining-threshold",
        type=float,
        default=MINING_THRESHOLD,
        help=f"hitl: mine and queue false positives scoring at least this (default {MINING_THRESHOLD})",
    )
    p.add_argument(
        "--no-box-quality",
        dest="box_quality",
        action="store_false",
        help="classifier, hitl: detect without the box quality regressor",
    )
    p.add_argument(
        "--hide-labelled",
        type=float,
        default=None,
        metavar="IOU",
        help="hitl: the reviewer's queue hides items whose box overlaps a label at this IoU or more, "
        "as the review panel's filter (default: the plain score order)",
    )
    p.add_argument(
        "--variants",
        default=None,
        help="hitl: run only these detectors, comma-separated (blind, blind_safe, reviewed_K, full; "
        "reviewed_safe_K: reviewed_K holding what the reviewer leaves, as blind_safe; full_late: full "
        "labels added after the first fit; blind always runs); default blind, blind_safe, reviewed_K, full; "
        "hitl-compare: A,B compares detector A with detector B (of one record, or RECORD's A with "
        "BASELINE's B)",
    )
    p.add_argument("--no-calibrate", dest="calibrate", action="store_false", help="hitl: skip ICP")
    p.add_argument(
        "--out",
        default=None,
        help="hitl, quality, fuzz: also write the JSON here, and its table beside it (.md); import, "
        "scale: the JSON",
    )
    p.add_argument(
        "--heldout-seeds",
        default="101,102,103",
        help="quality, detect/hitl --heldout, world-labels: simulator seeds of the held-out factories (never "
        "the training factory's)",
    )
    p.add_argument(
        "--heldout-frames",
        type=int,
        default=12,
        help="quality, detect, hitl, world-labels: frames per held-out factory",
    )
    # hitl: what the loop trains; mining: round epochs of the continued round timed against 0 (afresh),
    # the others passed on to every timed train
    add_loop_flags(p, fields=BENCH_LOOP_FIELDS)
    p.add_argument(
        "--methods",
        default="head_options,box_head,paper",
        help="quality: head_options, box_head (trained per seed; both read the same head), paper "
        "(the --model)",
    )
    p.add_argument(
        "--scratch",
        default="/tmp/factorydet_heldout",
        help="quality, hitl --heldout: held-out factories and caches",
    )
    p.add_argument(
        "--frame-counts",
        default="100",
        help="scale: comma-separated frame counts of the detection runs (every worker count on the "
        "first; the most workers on the others, for the driver's memory)",
    )
    p.add_argument("--worker-counts", default="1,2", help="scale: comma-separated Ray worker counts")
    p.add_argument(
        "--no-in-process", dest="in_process", action="store_false", help="scale: skip the run without Ray"
    )
    p.add_argument(
        "--evaluate-frames", type=int, default=0, help="scale: also evaluate this many test frames (0: no)"
    )
    p.add_argument(
        "--simulate-frames",
        type=int,
        default=None,
        help="scale: first simulate the DATA folder with this many frames (--seed, --points) on Ray "
        "workers; a partly simulated folder resumes",
    )
    add_execution_flags(
        p,
        "hitl, quality: the frames' proposals; mining: the training runs' proposals; scale: "
        "--worker-threads only (its --worker-counts give the workers)",
        scratch=False,
    )
    p.add_argument("--json", action="store_true", help="print JSON (the default; kept for scripts)")
    p.add_argument(
        "--readme",
        default=None,
        help="also write a table of the result into this page's bench block, and the whole record "
        "to bench/BLOCK.json beside the page (hitl and quality: their record goes to --out)",
    )
    p.add_argument(
        "--readme-block",
        default=None,
        help="the README block's name (default: the benchmark's; e.g. a second pipeline block on other data)",
    )
    p.set_defaults(func=_cmd_bench)
    return parser


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen command; input errors print one line and return 2."""
    args = parser.parse_args(argv)
    # The command line as typed (for the records that say how to reproduce a result).
    args.command_line = "factorydet " + " ".join(sys.argv[1:] if argv is None else argv)
    try:
        configure_threads(args.threads)  # before any command loads numba, torch or open3d
        return args.func(args)
    except InputError as exc:
        print(f"factorydet {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except FrameLostError as exc:
        print(f"factorydet {args.command}: error: {exc}", file=sys.stderr)
        return 3
    except MemoryError as exc:
        # The readers' caps (io.limits) are meant to prevent this; when they do not, one line
        # says what ran out and how to lower the footprint, instead of a traceback.
        what = " ".join(str(exc).split())[:200] or "an allocation failed"
        print(
            f"factorydet {args.command}: error: out of memory ({what}); lower FACTORYDET_MAX_READ_BYTES "
            "or free memory",
            file=sys.stderr,
        )
        return 3
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head and friends
        sys.stderr.close()
        return 0


def main(argv: list[str] | None = None) -> int:
    """The GUI-free commands; ``app.cli`` adds ``factorydet app`` on top of them."""
    return run(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
