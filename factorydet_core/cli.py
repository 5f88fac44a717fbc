"""The ``factorydet`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable

from .types import InputError


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


def _cmd_bench(args: argparse.Namespace) -> int:
    from .bench import bench_simulate, update_readme

    result = bench_simulate(num_frames=args.frames, points_per_frame=args.points, seed=args.seed)
    print(json.dumps(result, indent=2))
    if args.readme:
        update_readme(args.readme, result)
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

    p = sub.add_parser("bench", help="benchmarks that print JSON")
    p.add_argument("name", choices=["simulate"])
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--points", type=int, default=80_000)
    p.add_argument("--seed", type=int, default=0)
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


def main(argv: list[str] | None = None) -> int:
    """The GUI-free commands; ``app.cli`` adds ``factorydet app`` on top of them."""
    return run(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
