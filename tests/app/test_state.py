import pytest

from app.state import AppState
from factorydet_core.dataset import open_dataset


def test_frame_changes_are_clamped_counted_and_announced(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    seen = []
    state.on_change(lambda: seen.append(state.frame_index))
    state.step_frame(+1)
    state.set_frame(99)
    state.step_frame(+1)  # already at the last frame: no change
    state.set_frame(-5)
    assert seen == [1, 2, 0] and state.num_frame_changes == 3
    assert state.frame.name == "frame_00000"


def test_display_settings_are_validated(small_dataset_dir):
    state = AppState(open_dataset(small_dataset_dir))
    assert state.color_mode == "sensor"
    state.set_display(color_mode="class", point_size=0.1, show_boxes=False)
    assert (state.color_mode, state.point_size, state.show_boxes) == ("class", 0.1, False)
    with pytest.raises(ValueError, match="unknown colour mode"):
        state.set_display(color_mode="rainbow")
