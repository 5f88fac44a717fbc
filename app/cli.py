"""The ``factorydet`` console script: the library's commands plus ``factorydet app``."""

from __future__ import annotations

import argparse
import sys

from factorydet_core.cli import build_parser, positive_int, progress_bar, run
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.demo import DEMO_SESSION, ensure_demo
from factorydet_core.session.store import latest_model, open_session, open_session_data, session_data


def session_model(db, model, model_name: str, model_path=None) -> tuple[object, str]:
    """The model a session shows when the app opens it: the one last chosen with **Show this
    model** (``SessionDB.shown_model``). A session without a choice records one now: its latest
    run's (a session from before the choice was kept), else ``model`` (the shipped one, at
    ``model_path``), so that a retrain never changes what is shown: only a choice does."""
    from factorydet_core.detection.model import DetectionModel

    chosen = db.shown_model()
    if chosen is not None and chosen[1].is_file():
        return DetectionModel.load(chosen[1]), chosen[0]
    latest = latest_model(db.session)
    if latest is None:
        if model is not None and model_path is not None and not db.readonly:
            db.set_shown_model(model_name, model_path)
        return model, model_name
    from .trainer import run_choice

    runs = db.training_runs()
    name = run_choice(runs[-1]["id"], runs[-1]["kind"])
    if not db.readonly:
        db.set_shown_model(name, latest)
    return DetectionModel.load(latest), name


def _cmd_app(args: argparse.Namespace) -> int:
    from .viewer import serve

    db = None
    if args.data is not None and args.session is None:
        dataset = open_dataset(args.data)
        title = dataset.name
        print("factorydet: no --session given; labels are read-only", file=sys.stderr)
    else:
        args.session = args.session or DEMO_SESSION
        demo = args.data is None and args.session == DEMO_SESSION
        if demo and session_data(open_session(DEMO_SESSION, args.root)) is None:
            update, close = progress_bar("building demo")
            try:
                ensure_demo(args.root, update)
            finally:
                close()
        db, dataset = open_session_data(args.session, args.root, args.data)
        title = f"session {args.session}"
    from factorydet_core.detection.model import DEFAULT_MODEL, DetectionModel
    from factorydet_core.session.models import resolve_model

    model, model_name, path = None, "", None
    if args.model == "default" and not DEFAULT_MODEL.is_file():
        print(
            f"factorydet: no shipped model at {DEFAULT_MODEL}; showing the front half only", file=sys.stderr
        )
    elif args.model != "none":
        path = resolve_model(args.model, args.root)
        model, model_name = DetectionModel.load(path), str(path)
    if db is not None and args.model == "default":
        model, model_name = session_model(db, model, model_name, path)
    serve(
        dataset, host=args.host, port=args.port, title=title, model=model, model_name=model_name, db=db,
        points_drawn=args.points_drawn,
    )  # fmt: skip
    return 0


def add_app_command(sub) -> None:
    """``factorydet app``, beside the library's commands."""
    p = sub.add_parser("app", help="serve the browser app")
    p.add_argument(
        "--session",
        default=None,
        help="session under --root (default: demo); with --data, the session to label that data set in",
    )
    p.add_argument(
        "--data",
        default=None,
        help="data set folder or point-cloud file (read-only unless --session is given)",
    )
    p.add_argument("--root", default=None, help="sessions folder (default: ./sessions)")
    p.add_argument("--host", default="127.0.0.1", help="bind address; viser has no authentication")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument(
        "--model",
        default="default",
        help="'default' (the shipped checkpoint), a .pt checkpoint, a session name, or 'none'",
    )
    p.add_argument(
        "--points-drawn",
        type=positive_int,
        default=None,
        help="draw at most this many points of each cloud in every browser to begin with (Display > "
        "Points drawn; default: all). Fewer show every change sooner in a browser without a graphics card",
    )
    p.set_defaults(func=_cmd_app)


def build_app_parser():
    return build_parser(add_app_command)


def main(argv: list[str] | None = None) -> int:
    return run(build_app_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
