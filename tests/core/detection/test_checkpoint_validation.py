"""Checkpoints are untrusted input: a malformed weights file, note or box quality file beside a
checkpoint is one line of ``InputError`` naming the file (never a traceback, a crash, a hang or a
huge allocation), and checkpoints are written whole or not at all."""

from __future__ import annotations

import dataclasses
import json
import pickle
import shutil
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import event, given, settings
from hypothesis import strategies as st

import factorydet_core.detection.checkpoint as checkpoint_module
import factorydet_core.detection.classifier as classifier_module
from factorydet_core.detection.box_head import BoxHead, symmetry_orders
from factorydet_core.detection.box_quality import BoxQuality, _evaluate_trees_numpy, num_option_features
from factorydet_core.detection.checkpoint import FILES_KEY, file_record, write_checkpoint
from factorydet_core.detection.classifier import ProposalClassifier
from factorydet_core.detection.groups import BoxSizePrior
from factorydet_core.detection.model import (
    DEFAULT_MODEL,
    PAPER_MODEL,
    DetectionModel,
    copy_checkpoint,
    quality_path,
)
from factorydet_core.proposals.settings import PRESETS
from factorydet_core.types import InputError

CLASSES = ("a", "b")


def _refused(call: Callable[[], object], where: Path, *words: str) -> str:
    """Run ``call``, expect one line of ``InputError`` naming ``where``, and return it."""
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and str(where) in message, message
    for word in words:
        assert word in message, message
    return message


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny paper-method checkpoint of two classes with every part (box prior, box quality,
    per-class thresholds); each test copies it before breaking the copy."""
    rng = np.random.default_rng(0)
    features = rng.normal(size=(12, 20, 5, 5, 5)).astype(np.float32)
    classifier = ProposalClassifier(width=0.01, epochs=1, class_names=CLASSES, geometry=False, num_threads=1)
    classifier.fit(features, np.arange(12) % 3)
    num_features = num_option_features(len(CLASSES), anchored=True, visibility=True)
    quality = BoxQuality(max_iter=3, max_leaf_nodes=4).fit(
        rng.normal(size=(60, num_features)), rng.uniform(size=60)
    )
    boxes = np.column_stack([rng.normal(size=(10, 3)), rng.uniform(0.5, 2, (10, 3)), rng.uniform(-3, 3, 10)])
    prior = BoxSizePrior.from_boxes(boxes, np.arange(10) % 2, len(CLASSES))
    model = DetectionModel(classifier, prior, box_quality=quality, class_score_thresholds={"a": 0.4})
    return model.save(tmp_path_factory.mktemp("model") / "m.pt")


@pytest.fixture
def copy(saved: Path, tmp_path: Path) -> Path:
    return copy_checkpoint(saved, tmp_path / "m.pt")


def _edit_note(path: Path, edit: Callable[[dict], object]) -> None:
    note = json.loads(path.with_suffix(".json").read_text())
    edit(note)
    path.with_suffix(".json").write_text(json.dumps(note))


def _reseal(path: Path) -> None:
    """Record the checkpoint's files as they are now in its note (dropping any missing one), as a
    crafted checkpoint would: its files' own checks must then refuse what is wrong in them."""
    files = {"weights": path, "box_quality": quality_path(path)}
    _edit_note(
        path, lambda n: n.update({FILES_KEY: {r: file_record(p) for r, p in files.items() if p.is_file()}})
    )


def test_a_checkpoint_round_trips_and_leaves_no_temporary_files(saved, copy):
    a, b = DetectionModel.load(saved), DetectionModel.load(copy)
    features = np.random.default_rng(1).normal(size=(4, 20, 5, 5, 5)).astype(np.float32)
    np.testing.assert_array_equal(a.classifier.predict_proba(features), b.classifier.predict_proba(features))
    rows = np.random.default_rng(2).normal(size=(30, a.box_quality.num_features_))
    np.testing.assert_array_equal(a.box_quality.predict(rows), b.box_quality.predict(rows))
    assert b.class_score_thresholds == {"a": 0.4}
    assert _files(copy.parent) == ["m.boxq.npz", "m.json", "m.pt"]
    # The shipped model passes every check.
    assert DetectionModel.load(DEFAULT_MODEL).box_quality is not None


def test_an_interrupted_write_or_export_leaves_the_old_checkpoint(copy, saved, monkeypatch):
    before = {name: (copy.parent / name).read_bytes() for name in _files(copy.parent)}

    def cut_off(source, target):
        Path(target).write_bytes(Path(source).read_bytes()[:10])
        raise KeyboardInterrupt

    monkeypatch.setattr(shutil, "copyfile", cut_off)
    with pytest.raises(KeyboardInterrupt):
        copy_checkpoint(saved, copy)
    monkeypatch.undo()

    def cut_off_save(obj, target):
        Path(target).write_bytes(b"PK")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", cut_off_save)
    with pytest.raises(KeyboardInterrupt):
        write_checkpoint(torch.nn.Linear(2, 2), copy, {})
    assert {name: (copy.parent / name).read_bytes() for name in _files(copy.parent)} == before


def _another_save(saved: Path, folder: Path) -> Path:
    """The model at ``saved`` with other weights and another box quality regressor, saved whole
    in ``folder`` as ``m.pt``."""
    model = DetectionModel.load(saved)
    with torch.no_grad():
        next(model.classifier.network_.parameters()).add_(1.0)
    rng = np.random.default_rng(7)
    rows = rng.normal(size=(60, model.box_quality.num_features_))
    model.box_quality = BoxQuality(max_iter=3, max_leaf_nodes=4).fit(rows, rng.uniform(size=60))
    folder.mkdir()
    return model.save(folder / "m.pt")


@pytest.mark.parametrize(
    "how", ["save interrupted", "export interrupted", "new box quality only", "new weights only"]
)
def test_files_of_different_saves_are_refused(copy, saved, tmp_path, monkeypatch, how):
    """The files are replaced one by one; an interruption between them leaves new files beside the
    old note, which must not load as one model."""
    other = _another_save(saved, tmp_path / "other")
    if how == "save interrupted":  # the weights and box quality are written, the note is not

        def interrupted(path, text):
            raise KeyboardInterrupt

        monkeypatch.setattr(checkpoint_module, "write_text_atomic", interrupted)
        with pytest.raises(KeyboardInterrupt):
            DetectionModel.load(other).save(copy)
    elif how == "export interrupted":
        copyfile = shutil.copyfile

        def note_cut_off(source, target):
            if str(source).endswith(".json"):
                raise KeyboardInterrupt
            copyfile(source, target)

        monkeypatch.setattr(shutil, "copyfile", note_cut_off)
        with pytest.raises(KeyboardInterrupt):
            copy_checkpoint(other, copy)
    elif how == "new box quality only":
        shutil.copyfile(quality_path(other), quality_path(copy))
    else:
        shutil.copyfile(other, copy)
    monkeypatch.undo()
    _refused(lambda: DetectionModel.load(copy), copy.with_suffix(".json"), "different saves", "re-export")
    # Each save on its own loads.
    assert DetectionModel.load(other).box_quality is not None and DetectionModel.load(saved)


def test_a_save_records_its_own_files(saved, tmp_path):
    note = json.loads(saved.with_suffix(".json").read_text())
    assert note[FILES_KEY] == {"weights": file_record(saved), "box_quality": file_record(quality_path(saved))}
    # A loaded model's record of its old files, passed on in a note, gives way to the new files'.
    model = DetectionModel.load(saved)
    stale = {FILES_KEY: model.note[FILES_KEY]}
    again = dataclasses.replace(model, box_quality=None).save(tmp_path / "again.pt", stale)
    assert json.loads(again.with_suffix(".json").read_text())[FILES_KEY] == {"weights": file_record(again)}
    assert DetectionModel.load(again).box_quality is None


def test_notes_without_file_records_still_load(copy):
    """Checkpoints saved before the notes recorded their files: the shipped ones, older sessions'."""
    _edit_note(copy, lambda n: n.pop(FILES_KEY))
    assert DetectionModel.load(copy).box_quality is not None
    # The paper checkpoint predates the record; the default one has it.
    assert FILES_KEY not in json.loads(PAPER_MODEL.with_suffix(".json").read_text())
    assert FILES_KEY in json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    for shipped in (DEFAULT_MODEL, PAPER_MODEL):
        model = DetectionModel.load(shipped)
        assert model.box_quality is not None and model.front_end is not None


class _Payload:
    """Unpickling it would call a function: what a crafted checkpoint does."""

    def __reduce__(self):
        return (print, ("this ran",))


def _bad_weights(kind: str, copy: Path) -> None:
    state = torch.load(copy, weights_only=True)
    if kind == "empty":
        copy.write_bytes(b"")
    elif kind == "text":
        copy.write_bytes(b"not a checkpoint")
    elif kind == "truncated":
        copy.write_bytes(copy.read_bytes()[: copy.stat().st_size // 2])
    elif kind == "bare tensor":
        torch.save(torch.zeros(3), copy)
    elif kind == "plain pickle":
        copy.write_bytes(pickle.dumps(dict(state)))
    elif kind == "code":
        torch.save({**state, "extra": _Payload()}, copy)
    elif kind == "missing key":
        torch.save({k: v for i, (k, v) in enumerate(state.items()) if i}, copy)
    elif kind == "extra key":
        torch.save({**state, "extra": torch.zeros(1)}, copy)
    elif kind == "not a tensor":
        torch.save({**state, next(iter(state)): 3}, copy)
    elif kind == "wrong shape":
        first = next(iter(state))
        torch.save({**state, first: torch.zeros(state[first].numel() + 1)}, copy)
    elif kind == "wrong dtype":
        first = next(iter(state))
        torch.save({**state, first: state[first].double()}, copy)
    elif kind == "nan":
        first = next(iter(state))
        torch.save({**state, first: torch.full_like(state[first], float("nan"))}, copy)
    elif kind == "huge":
        # Declares far more bytes than the network's weights (a few stored bytes could claim GBs).
        with zipfile.ZipFile(copy, "a") as archive:
            archive.writestr("m/data/999", b"\0" * (8 * 2**20), compress_type=zipfile.ZIP_DEFLATED)


@pytest.mark.parametrize(
    "kind",
    ["empty", "text", "truncated", "bare tensor", "plain pickle", "code", "missing key", "extra key",
     "not a tensor", "wrong shape", "wrong dtype", "nan", "huge"],
)  # fmt: skip
def test_malformed_weights_are_refused_in_one_line(copy, kind, capsys):
    _bad_weights(kind, copy)
    _reseal(copy)
    message = _refused(lambda: DetectionModel.load(copy), copy)
    assert "weights_only" not in message and "this ran" not in capsys.readouterr().out
    if kind == "code":
        assert "refused for safety" in message


NOTE_EDITS: dict[str, Callable[[dict], object]] = {
    "width 64": lambda n: n["params"].update(width=64),
    "width text": lambda n: n["params"].update(width="wide"),
    "width negative": lambda n: n["params"].update(width=-1),
    "width nan": lambda n: n["params"].update(width=float("nan")),
    "width of 400 digits": lambda n: n["params"].update(width=10**400),
    "threads of 400 digits": lambda n: n["params"].update(num_threads=10**400),
    "width of other weights": lambda n: n["params"].update(width=0.125),
    "epochs fraction": lambda n: n["params"].update(epochs=1.5),
    "dropout": lambda n: n["params"].update(dropout=2),
    "geometry text": lambda n: n["params"].update(geometry="yes"),
    "class weight": lambda n: n["params"].update(class_weight="heavy"),
    "seed negative": lambda n: n["params"].update(seed=-1),
    "no classes": lambda n: n["params"].update(class_names=[]),
    "class names text": lambda n: n["params"].update(class_names="ab"),
    "class names numbers": lambda n: n["params"].update(class_names=[1, 2]),
    "class names repeated": lambda n: n["params"].update(class_names=["a", "a"]),
    "class background": lambda n: n["params"].update(class_names=["a", "background"]),
    "too many classes": lambda n: n["params"].update(class_names=[f"c{i}" for i in range(300)]),
    "no params": lambda n: n.pop("params"),
    "params list": lambda n: n.update(params=[1]),
    "labels": lambda n: n.update(labels=["x", "y", "background"]),
    "history": lambda n: n.update(history="long"),
    "fit seconds": lambda n: n.update(fit_seconds="slow"),
    "train counts": lambda n: n.update(train_counts={"a": -1}),
    "format": lambda n: n.update(format="someone-else/3"),
    "prior rows": lambda n: n.update(box_prior={"median": [[1, 1, 1]]}),
    "prior negative": lambda n: n["box_prior"]["median"].__setitem__(0, [-1, 1, 1]),
    "prior text": lambda n: n["box_prior"]["median"].__setitem__(0, ["1", 1, 1]),
    "prior half range": lambda n: n["box_prior"].pop("lower"),
    "prior modes": lambda n: n["box_prior"].update(modes=[[[1, 1, 1]]]),
    "prior many modes": lambda n: n["box_prior"]["modes"].__setitem__(0, [[1, 1, 1]] * 100),
    "prior kind": lambda n: n.update(box_prior="big"),
    "prior of 400 digits": lambda n: n["box_prior"]["median"].__setitem__(0, [10**400, 1, 1]),
    "threshold of 400 digits": lambda n: n.update(class_score_thresholds={"a": 10**400}),
    "exponent of 400 digits": lambda n: n.update(probability_exponent=10**400),
    "score threshold": lambda n: n.update(score_threshold=2),
    "nms iou": lambda n: n.update(nms_iou=0),
    "unknown class threshold": lambda n: n.update(class_score_thresholds={"zzz": 0.5}),
    "front end kind": lambda n: n.update(front_end="fast"),
    "front end value": lambda n: n.update(front_end={"history_frames": "x"}),
    # The review's cases: each ran for a minute and took gigabytes, or ended in a traceback.
    "front end k_graph 1e8": lambda n: n.update(front_end={"preset": "agv", "overrides": {"k_graph": 1e8}}),
    "front end k_features 1e8": lambda n: n.update(
        front_end={"preset": "agv", "overrides": {"k_features": 10**8}}
    ),
    "front end crop 1e300": lambda n: n.update(
        front_end={"preset": "agv", "overrides": {"crop_z_m": [0, 1e300]}}
    ),
    "front end count true": lambda n: n.update(
        front_end={"preset": "agv", "overrides": {"min_proposal_points": True}}
    ),
    "front end whole k_graph": lambda n: n.update(
        front_end={**PRESETS["agv"].to_dict(), "segmentation": {"k_graph": 10**8}}
    ),
    "front end overrides list": lambda n: n.update(
        front_end={"preset": "agv", "overrides": [["k_graph", 5]]}
    ),
    "front end preset number": lambda n: n.update(front_end={"preset": 3}),
    "files kind": lambda n: n.update(files=[1]),
    "files role": lambda n: n.update(files={"optimizer": {"bytes": 1, "sha256": "0" * 64}}),
    "files record": lambda n: n.update(files={"weights": {"bytes": 1}}),
    "files bytes": lambda n: n["files"]["weights"].update(bytes=-1),
    "files bytes bool": lambda n: n["files"]["weights"].update(bytes=True),
    "files hash": lambda n: n["files"]["weights"].update(sha256="not hex"),
    "files other hash": lambda n: n["files"]["box_quality"].update(sha256="0" * 64),
    "files other size": lambda n: n["files"]["weights"].update(bytes=n["files"]["weights"]["bytes"] + 1),
    "box quality kind": lambda n: n.update(box_quality=5),
    "exponent": lambda n: n.update(probability_exponent=-1),
    "vote iou": lambda n: n.update(vote_iou=2),
}


@pytest.mark.parametrize("edit", NOTE_EDITS)
def test_malformed_notes_are_refused_before_any_network_is_built(copy, edit, monkeypatch):
    _edit_note(copy, NOTE_EDITS[edit])
    if edit != "width of other weights":  # that one builds its network, then compares the weights

        def no_network(*args, **kwargs):
            raise AssertionError("a network was built from a malformed note")

        monkeypatch.setattr(classifier_module, "FisherNet", no_network)
        _refused(lambda: DetectionModel.load(copy), copy.with_suffix(".json"))
    else:
        _refused(lambda: DetectionModel.load(copy), copy, "is (")


@pytest.mark.parametrize(
    "text", [b"", b"{", b"[1, 2]", b"\xff\xfe\xfa", b"[" * 100_000, b'{"params": {"width": 1e999}}']
)
def test_unreadable_notes_are_refused(copy, text):
    copy.with_suffix(".json").write_bytes(text)
    _refused(lambda: DetectionModel.load(copy), copy.with_suffix(".json"))


def _head_checkpoint(folder: Path) -> Path:
    """A tiny untrained box head saved as a checkpoint (the loader does not care how it was fitted)."""
    head = BoxHead(channels=(4,), hidden=4, heading_bins=2, epochs=1, class_names=CLASSES)
    head.network_ = head._new_network()
    head.templates_ = np.array([[1.0, 1.0, 1.0], [2.0, 0.5, 0.5]])
    head.symmetry_ = symmetry_orders(head.templates_)
    head.num_parameters_, head.train_counts_, head.fit_seconds_, head.history_ = 0, {}, 0.0, []
    return head.save(folder / "head.pt")


HEAD_EDITS: dict[str, Callable[[dict], object]] = {
    "channels huge": lambda n: n["params"].update(channels=[100_000]),
    "channels text": lambda n: n["params"].update(channels="wide"),
    "channels empty": lambda n: n["params"].update(channels=[]),
    "channels many": lambda n: n["params"].update(channels=[4] * 50),
    "hidden huge": lambda n: n["params"].update(hidden=10**9),
    "heading bins": lambda n: n["params"].update(heading_bins=0),
    "templates shape": lambda n: n.update(templates=[[1, 1, 1]]),
    "templates negative": lambda n: n.update(templates=[[1, 1, 1], [-1, 1, 1]]),
    "templates text": lambda n: n.update(templates=[[1, 1, 1], ["x", 1, 1]]),
    "templates of 400 digits": lambda n: n.update(templates=[[1, 1, 1], [10**400, 1, 1]]),
    "hidden of 400 digits": lambda n: n["params"].update(hidden=10**400),
    "symmetry": lambda n: n.update(symmetry=[3, 0]),
    "no templates": lambda n: n.pop("templates"),
}


@pytest.mark.parametrize("edit", HEAD_EDITS)
def test_malformed_box_head_notes_are_refused(tmp_path, edit):
    path = _head_checkpoint(tmp_path)
    assert DetectionModel.load(path).method == "box_head"
    _edit_note(path, HEAD_EDITS[edit])
    _refused(lambda: DetectionModel.load(path), path.with_suffix(".json"))


def _valid_arrays(saved: Path) -> dict[str, np.ndarray]:
    with np.load(quality_path(saved)) as archive:
        return {k: archive[k] for k in archive.files}


def _huge_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``arrays`` with a ``left`` whose header declares 10^12 values (and holds none)."""
    np.savez(path, **{k: v for k, v in arrays.items() if k != "left"})
    with zipfile.ZipFile(path, "a") as archive, archive.open("left.npy", "w") as file:
        np.lib.format.write_array_header_1_0(
            file, {"descr": "<i4", "fortran_order": False, "shape": (10**12,)}
        )


def _tree_edit(key: str, change: Callable[[np.ndarray], object]) -> Callable[[dict], None]:
    def edit(arrays: dict[str, np.ndarray]) -> None:
        arrays[key] = arrays[key].copy()
        change(arrays[key])

    return edit


def _first_split(arrays: dict[str, np.ndarray]) -> int:
    return int(np.flatnonzero(~arrays["is_leaf"])[0])


ARRAY_EDITS: dict[str, Callable[[dict], object]] = {
    "no roots": lambda a: a.pop("roots"),
    "children float": lambda a: a.update(left=a["left"].astype(np.float64)),
    "children 2-D": lambda a: a.update(left=a["left"].reshape(1, -1)),
    "short value": lambda a: a.update(value=a["value"][:-1]),
    "leaf flags int": lambda a: a.update(is_leaf=a["is_leaf"].astype(np.int8)),
    "self loop": lambda a: a["left"].__setitem__(_first_split(a), _first_split(a)),
    "back edge": lambda a: a["right"].__setitem__(np.flatnonzero(~a["is_leaf"])[1], 0),
    "child out of range": lambda a: a["left"].__setitem__(0, 10**6),
    "child negative": lambda a: a["right"].__setitem__(0, -5),
    "child in the next tree": lambda a: a["left"].__setitem__(0, a["roots"][1]),
    "feature out of range": lambda a: a["feature"].__setitem__(0, 10**6),
    "feature negative": lambda a: a["feature"].__setitem__(0, -1),
    "root out of range": lambda a: a["roots"].__setitem__(-1, 10**6),
    "root negative": lambda a: a["roots"].__setitem__(0, -1),
    "roots not rising": lambda a: a["roots"].__setitem__(1, 0),
    "nan threshold": lambda a: a["threshold"].__setitem__(0, np.nan),
    "inf value": lambda a: a["value"].__setitem__(-1, np.inf),
    "no baseline": lambda a: a.update(baseline=np.zeros(0)),
    "no features": lambda a: a.update(num_features=np.array(0)),
    "features of other classes": lambda a: a.update(num_features=np.array(int(a["num_features"]) + 1)),
    "flag int": lambda a: a.update(anchored=np.array(3)),
    "object array": lambda a: a.update(value=np.array([None] * len(a["value"]), object)),
}


@pytest.mark.parametrize("edit", [*ARRAY_EDITS, "empty", "text", "huge", "missing"])
def test_malformed_box_quality_files_are_refused(copy, saved, edit):
    path = quality_path(copy)
    arrays = _valid_arrays(saved)
    if edit == "empty":
        path.write_bytes(b"")
    elif edit == "text":
        path.write_bytes(b"trees")
    elif edit == "huge":
        _huge_npz(path, arrays)
    elif edit == "missing":
        path.unlink()
    else:
        ARRAY_EDITS[edit](arrays)
        np.savez(path, **arrays)
    _reseal(copy)
    _refused(lambda: DetectionModel.load(copy), path)


INDEX_KEYS = ("feature", "left", "right", "roots")


@st.composite
def _mutations(draw: st.DrawFn) -> list[tuple[str, int, object]]:
    """One to three changes (array, position, new value) of a box quality file's tree arrays: any
    index, indices near the node's own (self loops, back edges, one past the end), flipped leaves
    and non-finite numbers."""
    changes = []
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from([*INDEX_KEYS, "is_leaf", "threshold", "value", "num_features"]))
        position = draw(st.integers(0, 10**6))
        if key in INDEX_KEYS or key == "num_features":
            value = draw(
                st.one_of(
                    st.integers(-(2**40), 2**40),
                    st.sampled_from(["self", "before", "end", "last"]),
                    st.integers(-3, 40),
                )
            )
        elif key == "is_leaf":
            value = "flip"
        else:
            value = draw(st.floats(allow_nan=True, allow_infinity=True))
        changes.append((key, position, value))
    return changes


@settings(max_examples=60, deadline=None)
@given(changes=_mutations())
def test_mutated_box_quality_arrays_load_refused_or_walk_to_finite_predictions(saved, changes):
    arrays = _valid_arrays(saved)
    num_nodes = len(arrays["is_leaf"])
    for key, position, value in changes:
        array = arrays[key].copy()
        if key == "num_features":
            array = np.array(value if isinstance(value, int) else num_nodes, np.int64)
        else:
            at = position % len(array)
            relative = {"self": at, "before": at - 1, "end": num_nodes, "last": num_nodes - 1}
            value = relative.get(value, value) if isinstance(value, str) else value
            if key == "is_leaf":
                array[at] = not array[at]
            else:
                if array.dtype.kind == "i" and not np.can_cast(np.min_scalar_type(value), array.dtype):
                    array = array.astype(np.int64)
                array[at] = value
        arrays[key] = array
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "m.boxq.npz"
        np.savez(path, **arrays)
        try:
            quality = BoxQuality.load(path)
        except InputError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)
            event("refused")
            return
    event("loaded")
    rows = np.random.default_rng(0).normal(size=(40, quality.num_features_)) * 3
    predicted = quality.predict(rows)
    assert predicted.shape == (40,) and np.isfinite(predicted).all()
    np.testing.assert_allclose(predicted, np.clip(_evaluate_trees_numpy(quality.trees_, rows), 0, 1))
