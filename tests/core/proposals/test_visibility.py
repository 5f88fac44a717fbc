"""Free space: rays mark the cells they cross free and their end cells occupied, and a box's share
of seen-free volume tells a box grown toward the viewer from the object's own box."""

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from factorydet_core.detection.box_quality import BoxQuality
from factorydet_core.detection.detector import Detector
from factorydet_core.detection.groups import ProposalGroups
from factorydet_core.io.dataset import open_dataset
from factorydet_core.proposals.visibility import FREE, OCCUPIED, UNSEEN, FreeSpace, box_visibility, free_space
from factorydet_core.types import InputError, MergedCloud


def _cloud(points: np.ndarray, sensor_position=(0.0, 0.0, 1.0), frame_ages=None) -> MergedCloud:
    transform = np.eye(4)
    transform[:3, 3] = sensor_position
    points = np.asarray(points, np.float32).reshape(-1, 3)
    return MergedCloud(
        points=points,
        sensor_ids=np.zeros(len(points), np.int16),
        point_instance_ids=np.zeros(len(points), np.int64),
        T_vehicle_sensor=transform[None],
        frame_ages=frame_ages,
    )


def _wall(x: float = 5.0) -> np.ndarray:
    """Points of a wall x metres ahead of the sensor, 4 m wide and 2 m high (every 5 cm)."""
    y, z = np.meshgrid(np.arange(-2, 2, 0.05), np.arange(0.0, 2.0, 0.05))
    return np.column_stack([np.full(y.size, x), y.ravel(), z.ravel()])


def test_a_ray_frees_the_cells_it_crosses_and_occupies_its_end():
    space = free_space(
        _cloud([[3.05, 0.05, 1.05]], sensor_position=(0.05, 0.05, 1.05)), radius_m=5, cell_size_m=0.1
    )

    def cell(x, y, z):
        return space.state[tuple(np.floor((np.array([x, y, z]) - space.origin) / 0.1).astype(int))]

    assert cell(0.05, 0.05, 1.05) == FREE  # the sensor's own cell
    assert cell(1.55, 0.05, 1.05) == FREE
    assert cell(3.05, 0.05, 1.05) == OCCUPIED
    assert cell(3.15, 0.05, 1.05) == UNSEEN  # behind the return
    assert cell(1.55, 0.25, 1.05) == UNSEEN  # beside the ray
    assert (space.state == FREE).sum() == 30 and (space.state == OCCUPIED).sum() == 1


@settings(max_examples=60, deadline=None)
@given(
    start=st.tuples(*[st.floats(-3.9, 3.9)] * 2, st.floats(0.1, 3.9)),
    end=st.tuples(*[st.floats(-3.9, 3.9)] * 2, st.floats(0.1, 3.9)),
)
@example(start=(0.05, 0.05, 1.0), end=(0.05, 0.05, 2.05))  # a vertical ray: zero x and y steps
def test_ray_cells_form_a_connected_path_through_every_cell_the_segment_touches(start, end):
    cell_size = 0.3
    space = free_space(
        _cloud([end], sensor_position=start), radius_m=4.0, z_range_m=(0.0, 4.0), cell_size_m=cell_size
    )
    # A point on a cell border belongs to either cell, depending on rounding (the cloud is float32:
    # an end at z = 2.1 m lies in the cell below 2.1 / 0.3 = 7): such cases are not this test's.
    for point in (start, end):
        in_cells = (np.array(point) - space.origin) / cell_size
        assume((np.abs(in_cells - np.round(in_cells)) > 1e-4).all())
    start_cell = np.floor((np.array(start) - space.origin) / cell_size).astype(int)
    end_cell = np.floor((np.array(end) - space.origin) / cell_size).astype(int)
    steps = int(np.abs(end_cell - start_cell).sum())
    free = space.state == FREE
    # The walk takes one face-neighbour step per crossing: exactly that many cells before the end
    # one (the start cell is freed unless it is the end cell).
    assert free.sum() == steps
    assert space.state[tuple(end_cell)] == OCCUPIED
    # Every cell a dense sampling of the segment meets (away from cell borders) is on the path.
    t = np.linspace(0.0, 1.0, 4001)[:-1]
    samples = (
        np.array(start)[None] + t[:, None] * (np.array(end) - np.array(start))[None] - space.origin
    ) / cell_size
    inside = (np.abs(samples - np.round(samples)) > 1e-6).all(axis=1)
    cells = np.unique(np.floor(samples[inside]).astype(int), axis=0)
    cells = cells[(cells != end_cell).any(axis=1)]
    assert free[tuple(cells.T)].all()


def test_only_the_current_frame_casts_rays():
    points = np.array([[3.0, 0.0, 1.0], [0.0, 3.0, 1.0]])
    space = free_space(_cloud(points, frame_ages=np.array([0, 1], np.int16)), radius_m=5)
    assert (space.state == OCCUPIED).sum() == 1


def test_box_visibility_tells_seen_empty_space_from_hidden_space():
    space = free_space(_cloud(_wall(5.0)), radius_m=8, z_range_m=(-0.5, 3.0), cell_size_m=0.1)
    boxes = np.array(
        [
            [3.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0],  # in front of the wall: seen empty
            [6.5, 0.0, 1.0, 1.0, 1.0, 1.0, 0.3],  # behind it: hidden
            [5.0, 0.0, 1.0, 0.3, 1.0, 1.0, 0.0],  # holding the wall
            [30.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0],  # outside the grid
        ]
    )
    shares = box_visibility(space, boxes)
    assert shares.shape == (4, 2)
    assert shares[0, 0] == pytest.approx(1.0) and shares[0, 1] == 0
    assert shares[1].sum() == 0
    assert shares[2, 1] > 0.3
    assert shares[3].sum() == 0
    with pytest.raises(InputError):
        box_visibility(space, np.full((1, 7), np.nan))


def test_free_space_round_trips_through_arrays():
    space = free_space(_cloud(_wall(4.0)), radius_m=6, cell_size_m=0.25)
    back = FreeSpace.from_arrays(space.to_arrays())
    np.testing.assert_array_equal(back.state, space.state)
    np.testing.assert_array_equal(back.origin, space.origin)
    assert back.cell_size == space.cell_size


def test_bad_grids_are_refused():
    cloud = _cloud(_wall())
    with pytest.raises(InputError):
        free_space(cloud, radius_m=0)
    with pytest.raises(InputError):
        free_space(cloud, cell_size_m=-1)
    with pytest.raises(InputError):
        free_space(cloud, z_range_m=(2.0, 1.0))


def test_an_empty_cloud_saw_nothing():
    space = free_space(_cloud(np.zeros((0, 3))), radius_m=2)
    assert (space.state == UNSEEN).all()


def test_simulated_objects_hold_less_seen_free_space_than_their_boxes_moved_toward_the_vehicle(
    small_dataset_dir,
):
    frame = open_dataset(small_dataset_dir).frame(0)
    result = Detector("agv").propose(frame)
    space = free_space(result.merged)
    boxes = np.array(frame.labels.boxes)
    boxes = boxes[np.linalg.norm(boxes[:, :2], axis=1) < 15]
    toward = boxes.copy()
    direction = boxes[:, :2] / np.linalg.norm(boxes[:, :2], axis=1, keepdims=True)
    toward[:, :2] -= direction * 0.6 * boxes[:, 3:4]
    own, moved = box_visibility(space, boxes), box_visibility(space, toward)
    assert len(boxes) >= 5
    assert np.median(moved[:, 0] - own[:, 0]) > 0.1


def test_a_visibility_regressor_refuses_point_sets_without_free_space():
    groups = ProposalGroups(
        np.zeros(1, np.int64),
        np.zeros(1, np.int64),
        np.zeros((1, 20, 5, 5, 5), np.float32),
        np.zeros((1, 14)),
    )
    assert BoxQuality(visibility=False).free_space_of(groups) is None
    with pytest.raises(InputError, match="free space"):
        BoxQuality(visibility=True).free_space_of(groups)


def test_a_return_beyond_the_grid_frees_its_ray_inside_it_and_occupies_nothing():
    far = np.array([[1e7, 0.05, 1.05]])  # a point thrown far away (bad extrinsics, say)
    space = free_space(_cloud(far, sensor_position=(0.05, 0.05, 1.05)), radius_m=5, cell_size_m=0.1)
    assert (space.state == OCCUPIED).sum() == 0
    # Every cell from the sensor's to the grid's border at x = 5 m.
    assert (space.state == FREE).sum() == 50
    assert space.state[-1, 50, 15] == FREE


def test_free_space_arrays_cannot_be_changed_through_it():
    origin = np.zeros(3)
    space = FreeSpace(origin, 0.5, np.zeros((2, 2, 2), np.uint8))
    origin[0] = 9.0
    assert space.origin[0] == 0.0
    with pytest.raises(ValueError):
        space.origin[0] = 1.0
    with pytest.raises(ValueError):
        space.state[0, 0, 0] = 1
    with pytest.raises(InputError):
        FreeSpace([np.nan, 0, 0], 0.5, np.zeros((2, 2, 2), np.uint8))
