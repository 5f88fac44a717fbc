"""Where a model comes from: ``resolve_model`` turns what a user typed (a path, a session's name,
``default`` or ``paper``) into a checkpoint file."""

from __future__ import annotations

import os
from pathlib import Path

from factorydet_core.detection.model import DEFAULT_MODEL, PAPER_MODEL
from factorydet_core.session.store import latest_model, open_session
from factorydet_core.types import (
    InputError,
)


def resolve_model(spec: str | os.PathLike, root: str | os.PathLike | None = None) -> Path:
    """A checkpoint path from "default" (the shipped model), "paper" (the shipped checkpoint of the
    paper's pipeline, ``model.PAPER_MODEL``), a ``.pt`` path, or a session name (its latest model)."""

    if str(spec) == "default":
        path = DEFAULT_MODEL
    elif str(spec) == "paper":
        path = PAPER_MODEL
    elif str(spec).endswith(".pt"):
        path = Path(spec)
    else:
        path = latest_model(open_session(str(spec), root))
        if path is None:
            raise InputError(f"session {spec!r} has no trained model; run factorydet train first")
    if not path.is_file():
        raise InputError(f"{path}: no such checkpoint")
    return path
