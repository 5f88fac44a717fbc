"""The Frame panel (in-process, a viser server without a browser)."""

import pytest
import viser

from app.panels.frame_panel import build_frame_panel
from app.state import AppState
from factorydet_core.io.dataset import open_dataset


@pytest.fixture
def server():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def test_the_frame_slider_counts_from_one_as_the_status_line_does(server, small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    panel = build_frame_panel(server, state)
    num_frames = state.dataset.num_frames
    assert (panel.slider.min, panel.slider.max, panel.slider.value) == (1, num_frames, 1)
    assert f"frame **1 / {num_frames}**" in panel.status.content
    state.set_frame(num_frames - 1)
    panel.refresh(state)
    assert panel.slider.value == num_frames
    assert f"frame **{num_frames} / {num_frames}**" in panel.status.content
    assert panel.next.disabled and not panel.previous.disabled


def test_the_frames_computation_shows_its_progress_in_the_frame_panel(server, small_dataset_dir):
    # Where a labeller waiting for a frame looks (it was buried in the Segmentation folder).
    state = AppState(open_dataset(small_dataset_dir))
    panel = build_frame_panel(server, state)
    state.set_pipeline_progress("frame 2: segmenting", 0.55, busy=True)
    panel.refresh(state)
    assert panel.progress.value == 55.0 and not panel.progress.animated
    assert panel.work.content == "⏳ frame 2: segmenting"
    state.set_pipeline_progress("frame 2 done", 1.0, busy=False)
    panel.refresh(state)
    assert (panel.progress.value, panel.work.content) == (100.0, "frame 2 done")
