"""Cut pursuit in its helper process: the library's labels, a dead helper replaced, and the helper
replaced every CALLS_PER_PROCESS calls (what bounds the library's leak)."""

from __future__ import annotations

import numpy as np
import pytest

from factorydet_core.proposals import cut_pursuit as cp


@pytest.fixture
def graph():
    """Two noisy clusters of values on a chain graph: cut pursuit splits them."""
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0, 0.01, (50, 3)), rng.normal(5, 0.01, (50, 3))]).astype(np.float32)
    source = np.arange(99, dtype=np.uint32)
    return values, np.full(99, 0.5, np.float32), source, source + 1


def test_the_helper_gives_the_library_s_labels(graph):
    labels = cp.cut_pursuit(*graph)
    assert labels.dtype == np.int64 and labels.shape == (100,)
    np.testing.assert_array_equal(labels, cp.perform(*graph))
    assert len(np.unique(labels[:50])) == 1 and labels[0] != labels[-1]


def test_a_dead_helper_is_replaced(graph):
    cp.cut_pursuit(*graph)
    process = cp._helper._process
    process.kill()
    process.wait()
    np.testing.assert_array_equal(cp.cut_pursuit(*graph), cp.perform(*graph))
    assert cp._helper._process is not process


def test_the_helper_is_replaced_after_its_calls(graph, monkeypatch):
    monkeypatch.setattr(cp, "CALLS_PER_PROCESS", 2)
    cp._helper._stop()
    pids = []
    for _ in range(5):
        cp.cut_pursuit(*graph)
        pids.append(cp._helper._process.pid)
    assert pids[0] == pids[1] != pids[2] == pids[3] != pids[4]
