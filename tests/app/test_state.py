import numpy as np
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
    state.set_display(color_mode="class", point_size=0.1, show_boxes=False, max_height=3.0)
    assert (state.color_mode, state.point_size, state.show_boxes, state.max_height) == (
        "class",
        0.1,
        False,
        3.0,
    )
    with pytest.raises(ValueError, match="unknown colour mode"):
        state.set_display(color_mode="rainbow")


def test_real_files_open_in_their_own_colours():
    from app.scene import point_colors
    from tests.conftest import SHARED_REAL

    path = SHARED_REAL / "scannet_scene0000_00.npz"
    if not path.exists():
        pytest.skip(f"{SHARED_REAL} is not beside the repository")
    state = AppState(open_dataset(path))
    assert state.color_mode == "rgb" and state.dataset.num_frames == 1
    frame = state.frame
    assert (point_colors(frame, frame.points[:, 2], "rgb") == frame.colors).all()
    by_class = point_colors(frame, frame.points[:, 2], "class")
    assert by_class.shape == (frame.num_points, 3) and len(np.unique(by_class, axis=0)) > 5


def test_rgb_mode_falls_back_to_height_without_colours(small_dataset_dir):
    from app.scene import point_colors
    from factorydet_core.colors import colors_by_height

    frame = open_dataset(small_dataset_dir).frame(0)
    z = frame.points[:, 2]
    assert (point_colors(frame, z, "rgb") == colors_by_height(z)).all()
