"""The ``factorydet`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable

from .types import BOX_KINDS, LEVELS, InputError


def progress_bar(desc: str) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    from tqdm import tqdm

    bar = None

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=desc, unit="frame")
        bar.update(done - bar.n)

    def close() -> None:
        if bar is not None:
            bar.close()

    return update, close


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim.simulate import SimConfig, simulate_dataset

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
    update, close = progress_bar("simulating")
    try:
        out = simulate_dataset(args.out, config, update)
    finally:
        close()
    print(f"wrote {config.num_frames} frames to {out}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .session import DEMO_SESSION, ensure_demo, open_session

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
    from .dataset import open_dataset

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


def _cmd_bench(args: argparse.Namespace) -> int:
    from .bench import bench_pipeline, bench_simulate, bench_voxel_sweep, update_readme

    command = "factorydet bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else ""
    if args.frames is None:
        args.frames = 10 if args.name == "simulate" else 4
    if args.name == "simulate":
        result = bench_simulate(num_frames=args.frames, points_per_frame=args.points, seed=args.seed)
    else:
        if not args.data:
            raise InputError(f"bench {args.name} needs a DATA folder or file")
        update, close = progress_bar(args.name)
        try:
            if args.name == "pipeline":
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
                sizes = [float(v) for v in args.voxel_sizes.split(",")]
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
        update_readme(args.readme, result)
    return 0


def _cmd_propose(args: argparse.Namespace) -> int:
    from .dataset import open_dataset
    from .detector import PRESETS, Detector

    dataset = open_dataset(args.data)
    if not 0 <= args.frame < dataset.num_frames:
        raise InputError(f"{dataset.name}: frame {args.frame} out of range [0, {dataset.num_frames})")
    preset = args.preset or ("agv" if dataset.num_sensors > 1 else "indoor")
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    detector = Detector(PRESETS[preset].replace(**parse_overrides(args.set)))
    if args.calibrate and dataset.num_sensors > 1:
        detector.calibrate(dataset.frame(args.frame))
    history_from = max(0, args.frame - detector.params.history_frames)
    history = [dataset.frame(i) for i in range(history_from, args.frame)]
    result = detector.propose(dataset.frame(args.frame), history)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="factorydet", description="Factory LiDAR detection tools.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="write a simulated factory data set")
    p.add_argument("--out", required=True, help="data set folder to write")
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
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

    p = sub.add_parser("propose", help="object proposals of one frame (the detector's front half)")
    p.add_argument("data", help="a data set folder or any point-cloud file the readers open")
    p.add_argument("--frame", type=int, default=0, help="frame index (0-based)")
    p.add_argument("--preset", default=None, help="agv or indoor (default: agv for multi-sensor data)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a parameter (repeatable)")
    p.add_argument(
        "--no-calibrate", dest="calibrate", action="store_false", help="skip the ICP extrinsic refinement"
    )
    p.add_argument("--json", action="store_true", help="print every proposal as JSON")
    p.add_argument("--limit", type=int, default=20, help="rows of the text listing")
    p.set_defaults(func=_cmd_propose)

    p = sub.add_parser("bench", help="benchmarks; each prints one JSON object")
    p.add_argument("name", choices=["simulate", "pipeline", "sweep"])
    p.add_argument(
        "data",
        nargs="*",
        help="pipeline: a simulated data set folder, or point-cloud files (recall pooled); sweep: a folder",
    )
    p.add_argument("--frames", type=int, default=None, help="frames to run (simulate: 10, others: 4)")
    p.add_argument("--points", type=int, default=80_000, help="simulate: points per frame")
    p.add_argument("--seed", type=int, default=0, help="simulate: seed")
    p.add_argument("--preset", default=None, help="pipeline: agv or indoor (default: by data)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="pipeline: override a parameter")
    p.add_argument("--voxel-sizes", default="0.1,0.15,0.2,0.3,0.4", help="sweep: comma-separated sizes (m)")
    p.add_argument("--png", default=None, help="sweep: write the plot here")
    p.add_argument("--json", action="store_true", help="print JSON (the default; kept for scripts)")
    p.add_argument("--readme", default=None, help="also write the result into this README's bench block")
    p.set_defaults(func=_cmd_bench)
    return parser


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen command; input errors print one line and return 2."""
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"factorydet {args.command}: error: {exc}", file=sys.stderr)
        return 2
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
