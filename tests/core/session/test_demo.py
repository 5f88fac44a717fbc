import pytest

from factorydet_core.io.dataset import open_dataset
from factorydet_core.session import demo
from factorydet_core.session import store as sessions
from factorydet_core.sim.simulate import SimConfig


@pytest.mark.parametrize(
    "name", ["", "..", "../etc", "/abs", "a/b", "a\\b", ".hidden", "x" * 65, "a..b", "a b"]
)
def test_unsafe_session_names_are_refused(name, tmp_path):
    with pytest.raises(sessions.SessionError, match="invalid session name"):
        sessions.open_session(name, tmp_path)


@pytest.mark.parametrize("name", ["demo", "line-3_2026.11", "A1"])
def test_safe_names_open_under_the_root(name, tmp_path):
    session = sessions.open_session(name, tmp_path)
    assert session.path == tmp_path / name and not session.has_data


def test_ensure_demo_builds_once(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "DEMO_CONFIG", SimConfig(num_frames=2, seed=0, points_per_frame=5_000))
    calls = []
    made = demo.ensure_demo(tmp_path, lambda done, total: calls.append((done, total)))
    assert made.has_data and calls[-1] == (2, 2)
    assert open_dataset(made.data_dir).num_frames == 2
    stamp = (made.data_dir / "manifest.json").stat().st_mtime_ns
    demo.ensure_demo(tmp_path)
    assert (made.data_dir / "manifest.json").stat().st_mtime_ns == stamp
    assert not (made.path / "data.partial").exists()
