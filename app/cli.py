"""The ``factorydet`` console script: the library's commands plus ``factorydet app``."""

from __future__ import annotations

import argparse
import sys

from factorydet_core.cli import build_parser, progress_bar, run
from factorydet_core.dataset import open_dataset
from factorydet_core.session import DEMO_SESSION, ensure_demo, open_session
from factorydet_core.types import InputError


def _cmd_app(args: argparse.Namespace) -> int:
    from .viewer import serve

    if args.data is not None:
        dataset = open_dataset(args.data)
        title = dataset.name
    else:
        session = open_session(args.session, args.root)
        if not session.has_data:
            if args.session != DEMO_SESSION:
                raise InputError(f"session {args.session!r} has no data set; pass --data DIR or FILE")
            update, close = progress_bar("building demo")
            try:
                ensure_demo(args.root, update)
            finally:
                close()
        dataset = open_dataset(session.data_dir)
        title = f"session {session.name}"
    from factorydet_core.model import DEFAULT_MODEL, DetectionModel
    from factorydet_core.results import resolve_model

    model, model_name = None, ""
    if args.model == "default" and not DEFAULT_MODEL.is_file():
        print(
            f"factorydet: no shipped model at {DEFAULT_MODEL}; showing the front half only", file=sys.stderr
        )
    elif args.model != "none":
        path = resolve_model(args.model, args.root)
        model, model_name = DetectionModel.load(path), str(path)
    serve(dataset, host=args.host, port=args.port, title=title, model=model, model_name=model_name)
    return 0


def build_app_parser() -> argparse.ArgumentParser:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    p = sub.add_parser("app", help="serve the browser app")
    p.add_argument("--session", default=DEMO_SESSION, help="session under --root (default: demo)")
    p.add_argument("--data", default=None, help="data set folder or point-cloud file to open instead")
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.add_argument("--host", default="127.0.0.1", help="bind address; viser has no authentication")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument(
        "--model",
        default="default",
        help="'default' (the shipped checkpoint), a .pt checkpoint, a session name, or 'none'",
    )
    p.set_defaults(func=_cmd_app)
    return parser


def main(argv: list[str] | None = None) -> int:
    return run(build_app_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
