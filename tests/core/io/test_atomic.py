"""Atomic writes: whole or not at all, one temporary file per call, synced, errors naming the target."""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

import pytest

from factorydet_core.io.atomic import atomic_path, write_text_atomic


def test_a_file_is_replaced_whole_or_left_as_it_was(tmp_path):
    path = tmp_path / "result.json"
    write_text_atomic(path, "first")
    assert path.read_text() == "first"
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half of the sec")
        raise RuntimeError("stopped while writing")
    assert path.read_text() == "first" and sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]
    write_text_atomic(path, "second")
    assert path.read_text() == "second" and len(list(tmp_path.iterdir())) == 1


def test_each_call_writes_its_own_hidden_temporary_beside_the_target(tmp_path):
    path = tmp_path / "scene.npz"
    with atomic_path(path) as first, atomic_path(path) as second:
        assert first != second
        for tmp in (first, second):
            assert tmp.parent == tmp_path and tmp.name.startswith(".") and tmp.suffix == ".npz"
            tmp.write_text(tmp.name)
    assert path.read_text() == first.name  # the outer write finished last, so it won
    assert [p.name for p in tmp_path.iterdir()] == ["scene.npz"]


def test_threads_writing_one_target_never_collide(tmp_path):
    path = tmp_path / "shared.json"
    texts = {f"thread {t} write {i} " * 200 for t in range(8) for i in range(25)}
    errors: list[BaseException] = []

    def writer(t: int) -> None:
        try:
            for i in range(25):
                write_text_atomic(path, f"thread {t} write {i} " * 200)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(t,)) for t in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors
    assert path.read_text() in texts  # one writer's text, whole
    assert [p.name for p in tmp_path.iterdir()] == ["shared.json"]


def test_the_file_and_its_folder_are_synced(tmp_path, monkeypatch):
    synced: list[str] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    path = tmp_path / "result.json"
    write_text_atomic(path, "data")
    assert len(synced) == 2
    assert Path(synced[0]).parent == tmp_path and Path(synced[0]).name.startswith(".result.tmp")
    assert Path(synced[1]) == tmp_path


def test_write_errors_name_the_target_not_the_temporary(tmp_path):
    target = tmp_path / "missing_folder" / "out.json"
    with pytest.raises(FileNotFoundError) as info:
        write_text_atomic(target, "data")
    assert info.value.filename == str(target) and info.value.errno == errno.ENOENT
    assert info.value.strerror == "No such file or directory"  # "cannot write <target>: <reason>"

    # An error without a file name (a full disk in write) is the target's too, with its type.
    target = tmp_path / "full.json"
    with pytest.raises(OSError) as info, atomic_path(target):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert ".tmp" not in str(info.value)

    # A directory in the way: the rename fails, and says so of the target.
    (tmp_path / "taken.json").mkdir()
    with pytest.raises(IsADirectoryError) as info:
        write_text_atomic(tmp_path / "taken.json", "data")
    assert info.value.filename == str(tmp_path / "taken.json")
    assert [p.name for p in tmp_path.iterdir()] == ["taken.json"]  # no temporary left behind


def test_errors_of_other_files_in_the_body_pass_unchanged(tmp_path):
    source = tmp_path / "no_such_source.txt"
    with pytest.raises(FileNotFoundError) as info, atomic_path(tmp_path / "out.txt") as tmp:
        tmp.write_text(source.read_text())
    assert info.value.filename == str(source)
    assert list(tmp_path.iterdir()) == []
