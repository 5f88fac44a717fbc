import numpy as np

from app.scene import grid_segments


def test_the_floor_grid_draws_every_line_once_on_the_floor():
    cells = grid_segments(30.0, 1.0, skip_every=5)
    sections = grid_segments(30.0, 5.0)
    lines = np.concatenate([cells, sections])
    assert lines.shape[1:] == (2, 3) and np.all(lines[:, :, 2] == 0.0)
    assert np.abs(lines[:, :, :2]).max() == 30.0
    # A line along y has one x at both ends (and the reverse); together the two grids have each
    # whole metre from -30 to 30 once in each direction, the sections every 5 m.
    along_y = lines[lines[:, 0, 0] == lines[:, 1, 0]]
    along_x = lines[lines[:, 0, 1] == lines[:, 1, 1]]
    assert len(along_y) + len(along_x) == len(lines)
    for offsets in (along_y[:, 0, 0], along_x[:, 0, 1]):
        assert sorted(offsets.tolist()) == list(range(-30, 31))
    section_offsets = sections[sections[:, 0, 0] == sections[:, 1, 0]][:, 0, 0]
    assert sorted(section_offsets.tolist()) == list(range(-30, 31, 5))
