"""The l0 cut pursuit of ``cut_pursuit_py``, run in a helper process that is replaced every
``CALLS_PER_PROCESS`` calls.

``cut_pursuit_py`` 1.0.12 leaks native memory on every call, in proportion to the components it
finds (about 3 MB for a 35k-point AGV scan cut into 23k components): merge candidates its C++ core
allocates and never frees. Detection of a few thousand frames in one process would grow by
gigabytes (a Ray worker reached 2.6 GB after 1,000 frames). The helper process takes the leak with
it when it is replaced; the arrays it exchanges (a few MB a call) cost milliseconds.

The helper is a plain child process (``python -m factorydet_core.proposals.cut_pursuit``) that
imports only numpy and ``cut_pursuit_py`` and talks over its standard input and output: it shares
no threads, locks or numba state with its parent (a multithreaded app, a Ray worker), and unlike
``multiprocessing``'s spawn it never re-imports the parent's main script.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import threading
from typing import BinaryIO

import numpy as np

CALLS_PER_PROCESS = 64
"""Calls before the helper is replaced: at most about 200 MB leaked (64 x 3 MB) before it is freed,
and one start-up (about 0.2 s) per some 25 AGV frames."""

_HEADER = struct.Struct("<Q")


def perform(values: np.ndarray, weights: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``cut_pursuit_py.perform_cut_pursuit`` of a graph in the calling process (what the helper
    runs).

    Args:
        values: (N, D) float32 node values.
        weights: (E,) float32 edge weights (the regularization included).
        source, target: (E,) uint32 edge ends.

    Returns:
        (N,) int64 component of each node.
    """
    import cut_pursuit_py

    labels = cut_pursuit_py.perform_cut_pursuit(
        1.0,  # ignored by the library: lambda is in the weights
        values.shape[1],
        np.ascontiguousarray(values, np.float32),
        np.ascontiguousarray(weights, np.float32),
        np.ascontiguousarray(source, np.uint32),
        np.ascontiguousarray(target, np.uint32),
        False,
    )
    return labels.astype(np.int64)


def _write_array(stream: BinaryIO, array: np.ndarray) -> None:
    array = np.ascontiguousarray(array)
    header = json.dumps({"dtype": array.dtype.str, "shape": list(array.shape)}).encode()
    stream.write(_HEADER.pack(len(header)) + header)
    stream.write(array.tobytes())


def _read_exactly(stream: BinaryIO, size: int) -> bytes:
    chunks, left = [], size
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise EOFError("the cut pursuit helper's pipe closed")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _read_array(stream: BinaryIO) -> np.ndarray:
    (length,) = _HEADER.unpack(_read_exactly(stream, _HEADER.size))
    header = json.loads(_read_exactly(stream, length))
    dtype, shape = np.dtype(header["dtype"]), tuple(header["shape"])
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    return np.frombuffer(_read_exactly(stream, size), dtype).reshape(shape)


class _Helper:
    """One helper process at a time, used under a lock, replaced after ``CALLS_PER_PROCESS`` calls."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._process: subprocess.Popen | None = None
        self._calls = 0

    def _stop(self) -> None:
        process, self._process = self._process, None
        if process is not None:
            try:
                process.stdin.close()  # the helper returns on end of input
            except OSError:  # it died with our unsent bytes in the pipe's buffer
                pass
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            process.stdout.close()

    def _start(self) -> subprocess.Popen:
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__], stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )
        self._calls = 0
        return self._process

    def call(self, arrays: tuple[np.ndarray, ...]) -> np.ndarray:
        with self._lock:
            for attempt in (0, 1):
                if self._process is None or self._calls >= CALLS_PER_PROCESS:
                    self._stop()
                    self._start()
                process = self._process
                try:
                    for array in arrays:
                        _write_array(process.stdin, array)
                    process.stdin.flush()
                    labels = _read_array(process.stdout)
                except (BrokenPipeError, EOFError, ValueError):
                    # The helper died (killed, out of memory, a crash): once more in a new one.
                    self._stop()
                    if attempt:
                        raise RuntimeError("the cut pursuit helper process failed twice") from None
                    continue
                self._calls += 1
                return labels
        raise AssertionError("not reached")


_helper = _Helper()


def cut_pursuit(
    values: np.ndarray, weights: np.ndarray, source: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """``perform`` in the helper process (see the module's docstring): the same (N,) int64 labels."""
    return _helper.call(
        (
            np.ascontiguousarray(values, np.float32),
            np.ascontiguousarray(weights, np.float32),
            np.ascontiguousarray(source, np.uint32),
            np.ascontiguousarray(target, np.uint32),
        )
    )


def _serve() -> None:
    """The helper's loop: four arrays in, the labels out, until its input ends."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    while True:
        try:
            values = _read_array(stdin)
        except EOFError:
            return
        weights, source, target = (_read_array(stdin) for _ in range(3))
        _write_array(stdout, perform(values, weights, source, target))
        stdout.flush()


if __name__ == "__main__":
    _serve()
