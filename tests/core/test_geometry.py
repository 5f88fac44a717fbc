import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.geometry import (
    box_corner_segments,
    box_corners,
    box_dashed_segments,
    box_wireframe_segments,
    group_bounds,
    invert_transform,
    make_transform,
    points_in_box,
    rotation_angle_deg,
    rotation_ypr,
    transform_boxes,
    wrap_angle,
)

finite = st.floats(-50, 50, allow_nan=False)
size = st.floats(0.05, 10, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
boxes = st.tuples(finite, finite, finite, size, size, size, angle).map(
    lambda t: np.array(t, dtype=np.float64)
)


@given(boxes)
def test_corners_lie_on_the_box_surface(box):
    corners = box_corners(box[None])[0]
    assert points_in_box(corners, box, margin=1e-6).all()
    assert not points_in_box(corners, box, margin=-1e-3).any()
    np.testing.assert_allclose(corners.mean(0), box[:3], atol=1e-9)


@given(boxes)
def test_yaw_turns_the_dx_edge_counter_clockwise(box):
    corners = box_corners(box[None])[0]
    dx_edge = corners[0] - corners[1]  # corners 0 and 1 differ along the box's x axis
    np.testing.assert_allclose(np.linalg.norm(dx_edge), box[3], rtol=1e-9)
    assert abs(wrap_angle(np.arctan2(dx_edge[1], dx_edge[0]) - box[6])) < 1e-6


@given(boxes, finite, finite, angle)
@settings(max_examples=50)
def test_moving_a_box_moves_its_points_with_it(box, tx, ty, yaw):
    rng = np.random.default_rng(0)
    local = (rng.uniform(-0.49, 0.49, (50, 3))) * box[3:6]
    points = local @ rotation_ypr(box[6], 0, 0).T + box[:3]
    assert points_in_box(points, box).all()
    transform = make_transform(rotation_ypr(yaw, 0, 0), np.array([tx, ty, 0.3]))
    moved_points = points @ transform[:3, :3].T + transform[:3, 3]
    assert points_in_box(moved_points, transform_boxes(transform, box[None])[0], margin=1e-6).all()


@given(angle, st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), finite, finite, finite)
def test_inverse_transform_composes_to_identity(yaw, pitch, roll, x, y, z):
    transform = make_transform(rotation_ypr(yaw, pitch, roll), np.array([x, y, z]))
    np.testing.assert_allclose(invert_transform(transform) @ transform, np.eye(4), atol=1e-9)
    assert rotation_angle_deg(transform[:3, :3], transform[:3, :3]) < 1e-5


def test_wireframe_has_twelve_edges_per_box():
    segments = box_wireframe_segments(np.array([[0, 0, 0, 2, 1, 1, 0.0], [5, 5, 0, 1, 1, 1, 1.0]]))
    assert segments.shape == (24, 2, 3)
    lengths = np.linalg.norm(segments[:12, 1] - segments[:12, 0], axis=1)
    assert sorted(np.round(lengths, 9).tolist()) == [1.0] * 8 + [2.0] * 4


@settings(max_examples=50, deadline=None)
@given(finite, finite, size, size, size, angle, st.integers(1, 6), st.floats(0.05, 0.5))
def test_dashes_and_corner_brackets_lie_on_the_edges_and_cover_their_share(
    cx, cy, dx, dy, dz, yaw, num_dashes, fraction
):
    box = np.array([[cx, cy, 0.5, dx, dy, dz, yaw]])
    edges = box_wireframe_segments(box)
    edge_length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1).sum()
    for pieces, share in (
        (box_dashed_segments(box, num_dashes), 0.5),
        (box_corner_segments(box, fraction), 2 * fraction),
    ):
        lengths = np.linalg.norm(pieces[:, 1] - pieces[:, 0], axis=1)
        assert lengths.sum() == pytest.approx(share * edge_length, rel=1e-9)
        # Every piece's ends lie on the box's surface: inside the box grown by a hair.
        ends = pieces.reshape(-1, 3)
        assert points_in_box(ends, box[0], margin=1e-6).all()
    assert box_dashed_segments(box, num_dashes).shape == (12 * num_dashes, 2, 3)
    assert box_corner_segments(box, fraction).shape == (24, 2, 3)


def test_dash_and_bracket_settings_are_checked():
    with pytest.raises(ValueError, match="num_dashes"):
        box_dashed_segments(np.zeros((1, 7)) + 1, 0)
    with pytest.raises(ValueError, match="fraction"):
        box_corner_segments(np.zeros((1, 7)) + 1, 0.7)


def test_transform_boxes_refuses_tilting_transforms():
    import pytest

    with pytest.raises(ValueError, match="z up"):
        transform_boxes(make_transform(rotation_ypr(0, 0.3, 0), np.zeros(3)), np.zeros((1, 7)) + 1)


@given(st.integers(0, 2**31 - 1), st.integers(0, 200), st.integers(1, 30))
@settings(max_examples=60, deadline=None)
def test_group_bounds_are_each_groups_min_and_max(seed, num_points, num_groups):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(num_points, 3)).astype(rng.choice([np.float32, np.float64]))
    group_ids = rng.integers(0, num_groups, num_points)
    lo, hi = group_bounds(points, group_ids, num_groups)
    for group in range(num_groups):
        members = points[group_ids == group]
        if len(members):
            np.testing.assert_array_equal(lo[group], members.min(axis=0))
            np.testing.assert_array_equal(hi[group], members.max(axis=0))
        else:  # empty groups keep +inf / -inf
            assert np.isposinf(lo[group]).all() and np.isneginf(hi[group]).all()
    with pytest.raises(ValueError, match="group ids"):
        group_bounds(points, np.zeros(num_points + 1, np.int64), num_groups)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 6), st.integers(0, 10_000))
def test_point_box_ids_give_the_first_box_holding_each_point(num_boxes, seed):
    from factorydet_core.geometry import point_box_ids, points_in_box

    rng = np.random.default_rng(seed)
    boxes = np.c_[
        rng.uniform(-3, 3, (num_boxes, 3)), rng.uniform(0.2, 3, (num_boxes, 3)), rng.uniform(-3, 3, num_boxes)
    ]
    points = rng.uniform(-5, 5, (300, 3))
    ids = point_box_ids(points, boxes)
    inside = np.array([points_in_box(points, b) for b in boxes]).reshape(num_boxes, len(points))
    expected = np.where(inside.any(axis=0), inside.argmax(axis=0), -1) if num_boxes else np.full(300, -1)
    np.testing.assert_array_equal(ids, expected)
