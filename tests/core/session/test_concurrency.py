"""Two processes on one session at once: the ``factorydet`` command line in a child process and the
library in this one review the same queue, import the same label file and edit the same labels.
Every write is either applied or reported as a conflict; none is lost or doubled silently."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.labels_io import import_labels
from factorydet_core.session.store import EditConflictError, SessionDB, open_session
from factorydet_core.training.mining import TrainingRun
from tests.fakes import mined_item

NUM_ITEMS = 16
NUM_LABELS = 4
ROUNDS = 12
NUM_IMPORTED = 60


class _StubModel:
    """Saves a note where a checkpoint would go: the queue needs a stored run, not a real model."""

    def save(self, path: Path, note: dict) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(note))


# One process's part. Reviews go through the command line (exit 0: applied, 2: refused with the
# items named); label edits and the import go through the library, as the app makes them.
_WORKER = """
import contextlib, io, json, sys, time
from factorydet_core.cli import main
from factorydet_core.io.dataset import open_dataset
from factorydet_core.session.labels_io import import_labels
from factorydet_core.session.store import EditConflictError, SessionDB, open_session

root, data, labels_file, author, verdict = sys.argv[1:6]
item_ids, label_ids, rounds = json.loads(sys.argv[6]), json.loads(sys.argv[7]), int(sys.argv[8])
db = SessionDB(open_session("s", root), open_dataset(data))
record = {"reviews": {}, "edits": [], "import": None, "errors": []}
print("READY", flush=True)
sys.stdin.readline()
start = time.time()
for step in range(max(len(item_ids), rounds)):
    # A label is looked at first and changed after the step's other work, as a person would.
    label_id = label_ids[step % len(label_ids)]
    seen = db.label(label_id)
    if step < len(item_ids):
        err = io.StringIO()
        args = ["review", "--session", "s", "--root", root, "--data", data, "--ids", str(item_ids[step]),
                "--verdict", verdict, "--author", author]
        if verdict == "object":
            args += ["--class", "box"]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            code = main(args)
        outcome = {0: "applied", 2: "conflict"}.get(code, f"exit {code}")
        if outcome == "conflict" and f"mined negative {item_ids[step]} already has" not in err.getvalue():
            outcome = "unexplained: " + err.getvalue().strip()
        record["reviews"][str(item_ids[step])] = outcome
    if step == len(item_ids) // 2:
        try:
            report = import_labels(db, labels_file, author)
            record["import"] = {"imported": report["imported"], "duplicates": len(report["duplicates"])}
        except Exception as exc:
            record["errors"].append(repr(exc))
    try:
        new_class = "cone" if seen.class_name != "cone" else "barrel"
        done = db.update_label(label_id, author, expected_version=seen.version, class_name=new_class)
        record["edits"].append([label_id, seen.version, done.version, new_class])
    except EditConflictError:
        record["edits"].append([label_id, None, None, None])
    except Exception as exc:
        record["errors"].append(repr(exc))
record["span"] = [start, time.time()]
print(json.dumps(record), flush=True)
"""


def _launch(args: list[str]) -> subprocess.Popen:
    worker = subprocess.Popen(
        [sys.executable, "-c", _WORKER, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert worker.stdout.readline().strip() == "READY"
    return worker


def test_two_processes_reviewing_importing_and_editing_at_once(small_dataset_dir, tmp_path):
    dataset = open_dataset(small_dataset_dir)
    db = SessionDB(open_session("s", tmp_path), dataset)
    items = [
        mined_item(k % 2, k, [2.0 * k - 16, -12.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9 - 0.01 * k)
        for k in range(NUM_ITEMS)
    ]
    record = {"num_positives": 1, "num_background": 1, "fit_seconds": 0.0, "train_metrics": {"f1": 0.0}}
    run = TrainingRun(_StubModel(), [{**record, "round": 0, "mined": items}], [_StubModel()], [0, 1])
    db.save_training_run(run, "small", {})
    item_ids = [q["id"] for q in db.review_queue()]
    shared = db.add_labels(
        [(0, (3.0 * k, 12.0, 0.5, 1.0, 1.0, 1.0, 0.0), "box") for k in range(NUM_LABELS)], "setup", "user"
    )
    initial = {lab.id: lab.version for lab in shared}
    boxes = [[2.0 * k - 30, 20.0, 0.5, 1.2, 0.8, 1.0, 0.1] for k in range(NUM_IMPORTED // 2)]
    labels_file = tmp_path / "labels.json"
    labels_file.write_text(
        json.dumps(
            {"frames": [{"frame_index": f, "boxes": boxes, "labels": ["box"] * len(boxes)} for f in (0, 1)]}
        )
    )
    before = {f: len(db.labels(f)) for f in (0, 1)}

    common = [str(tmp_path), str(small_dataset_dir), str(labels_file)]
    ids = [json.dumps(item_ids), json.dumps(list(initial)), str(ROUNDS * NUM_LABELS)]
    worker = _launch([*common, "cli", "background", *ids])
    worker.stdin.write("GO\n")
    worker.stdin.flush()
    # Meanwhile, this process: the other end of the queue, the same file, the same labels.
    mine = {"reviews": {}, "edits": [], "import": None, "errors": []}
    start = time.time()
    for step in range(max(NUM_ITEMS, ROUNDS * NUM_LABELS)):
        label_id = list(initial)[step % NUM_LABELS]
        seen = db.label(label_id)
        if step < NUM_ITEMS:
            item_id = item_ids[::-1][step]
            try:
                db.review([item_id], "object", "lib", class_name="box")
                mine["reviews"][str(item_id)] = "applied"
            except EditConflictError as exc:
                assert [c["id"] for c in exc.conflicts] == [item_id]
                mine["reviews"][str(item_id)] = "conflict"
        if step == NUM_ITEMS // 2:
            report = import_labels(db, labels_file, "lib")
            mine["import"] = {"imported": report["imported"], "duplicates": len(report["duplicates"])}
        new_class = "cone" if seen.class_name != "cone" else "barrel"
        try:
            done = db.update_label(label_id, "lib", expected_version=seen.version, class_name=new_class)
            mine["edits"].append([label_id, seen.version, done.version, new_class])
        except EditConflictError:
            mine["edits"].append([label_id, None, None, None])
    mine["span"] = [start, time.time()]
    out, _ = worker.communicate(timeout=60)
    theirs = json.loads(out.strip().splitlines()[-1])
    assert worker.returncode == 0 and theirs["errors"] == [] and mine["errors"] == []
    assert max(mine["span"][0], theirs["span"][0]) < min(mine["span"][1], theirs["span"][1])  # at once

    # Reviews: each item was decided by exactly one of the two; the other was told so, by name.
    assert set(theirs["reviews"]) == set(mine["reviews"]) == {str(i) for i in item_ids}
    assert all(v in ("applied", "conflict") for v in theirs["reviews"].values()), theirs["reviews"]
    for item_id in item_ids:
        outcomes = {theirs["reviews"][str(item_id)], mine["reviews"][str(item_id)]}
        assert outcomes == {"applied", "conflict"}, (item_id, outcomes)
    queue = {q["id"]: q for q in db.review_queue()}
    for item_id in item_ids:
        applier = "cli" if theirs["reviews"][str(item_id)] == "applied" else "lib"
        assert queue[item_id]["reviewer"] == applier
        assert queue[item_id]["verdict"] == ("background" if applier == "cli" else "object")
    num_objects = sum(v == "applied" for v in mine["reviews"].values())

    # The import: every box of the file added once, by one of the two; the other saw duplicates.
    imports = [theirs["import"], mine["import"]]
    assert sum(i["imported"] for i in imports) == NUM_IMPORTED
    assert sum(i["duplicates"] for i in imports) == NUM_IMPORTED
    after = {f: db.labels(f) for f in (0, 1)}
    origins = [lab.origin for f in (0, 1) for lab in after[f]]
    assert origins.count("import") == NUM_IMPORTED and origins.count("review") == num_objects
    assert sum(len(after[f]) for f in (0, 1)) == sum(before.values()) + NUM_IMPORTED + num_objects
    stored = [(lab.frame_index, lab.class_name, lab.box) for f in (0, 1) for lab in after[f]]
    assert len(stored) == len(set(stored))  # no box twice

    # The edits: every applied one moved its label on by one version from the version it saw, no
    # two from the same version (which would be a lost update), and the last one is what is stored.
    applied: dict[int, list] = {label_id: [] for label_id in initial}
    for label_id, seen_version, new_version, new_class in mine["edits"] + theirs["edits"]:
        if seen_version is not None:
            assert new_version == seen_version + 1
            applied[label_id].append((seen_version, new_class))
    num_attempts = len(mine["edits"]) + len(theirs["edits"])
    assert sum(map(len, applied.values())) + sum(e[1] is None for e in mine["edits"] + theirs["edits"]) == (
        num_attempts
    )
    for label_id, writes in applied.items():
        label = db.label(label_id)
        assert sorted(v for v, _ in writes) == list(range(initial[label_id], label.version))
        assert label.class_name == max(writes)[1]


def test_the_commands_while_another_process_holds_the_write_lock(
    small_dataset_dir, tmp_path, capsys, monkeypatch
):
    import sqlite3

    from factorydet_core import cli
    from factorydet_core.session import store

    db = SessionDB(open_session("s", tmp_path), open_dataset(small_dataset_dir))
    items = [mined_item(0, k, [2.0 * k, -12.0, 0.5, 1.0, 1.0, 1.0, 0.0], 0.9 - 0.1 * k) for k in range(3)]
    record = {"num_positives": 1, "num_background": 1, "fit_seconds": 0.0, "train_metrics": {"f1": 0.0}}
    db.save_training_run(
        TrainingRun(_StubModel(), [{**record, "round": 0, "mined": items}], [_StubModel()], [0]), "small", {}
    )
    first, second = [q["id"] for q in db.review_queue()][:2]
    common = ["--session", "s", "--root", str(tmp_path), "--data", str(small_dataset_dir)]
    assert (
        cli.main(
            [
                "review",
                *common,
                "--ids",
                str(first),
                "--verdict",
                "object",
                "--class",
                "box",
                "--author",
                "ann",
            ]
        )
        == 0
    )
    # Someone else's verdict: refused and named, nothing written, unless overridden.
    capsys.readouterr()
    bob = ["review", *common, "--ids", f"{first},{second}", "--verdict", "background", "--author", "bob"]
    assert cli.main(bob) == 2
    out, err = capsys.readouterr()
    assert [c["id"] for c in json.loads(out)["conflicts"]] == [first]
    assert (
        f"mined negative {first} already has the verdict object (box) by ann" in err and err.count("\n") == 1
    )
    assert {q["id"]: q["verdict"] for q in db.review_queue()}[second] is None
    assert cli.main([*bob, "--override"]) == 0
    capsys.readouterr()

    holder = sqlite3.connect(db.path, isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    holder.execute("UPDATE meta SET value = value WHERE key = 'created'")
    try:
        before = db.path.read_bytes()
        start = time.perf_counter()
        assert cli.main(["queue", *common, "--json"]) == 0
        assert len(json.loads(capsys.readouterr().out)["items"]) == 3
        assert cli.main(["labels", "export", str(tmp_path / "out.json"), *common, "--frames", "0,2"]) == 0
        assert time.perf_counter() - start < 5.0  # neither waited for the writer
        assert json.loads((tmp_path / "out.json").read_text())["frames"][1]["label_ids"][0] is None
        assert db.path.read_bytes() == before
        capsys.readouterr()
        monkeypatch.setattr(store, "BUSY_TIMEOUT", 0.3)
        assert (
            cli.main(["review", *common, "--ids", str(second), "--verdict", "skip", "--author", "bob"]) == 2
        )
        err = capsys.readouterr().err
        assert "is busy" in err and err.count("\n") == 1
    finally:
        holder.execute("ROLLBACK")
        holder.close()
