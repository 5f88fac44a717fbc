import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.boxes import (
    box_iou_3d,
    complete_hidden_side,
    fit_box,
    fit_boxes,
    heading_gap,
    scene_heading,
)
from factorydet_core.geometry import make_transform, points_in_box, rotation_ypr, rotation_z, transform_boxes
from factorydet_core.types import InputError

coordinate = st.floats(-5, 5, allow_nan=False)
size = st.floats(0.1, 4, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
boxes = st.tuples(coordinate, coordinate, coordinate, size, size, size, angle).map(
    lambda t: np.array(t, dtype=np.float64)
)


def iou(a, b) -> float:
    return float(box_iou_3d(np.asarray(a, float)[None], np.asarray(b, float)[None])[0, 0])


def test_identical_boxes_have_iou_one_and_disjoint_zero():
    box = np.array([1.0, 2.0, 0.5, 2.0, 1.0, 1.0, 0.4])
    assert iou(box, box) == pytest.approx(1.0, abs=1e-9)
    far = box + [10, 0, 0, 0, 0, 0, 0]
    assert iou(box, far) == 0.0
    above = box + [0, 0, 1.5, 0, 0, 0, 0]  # same footprint, z ranges apart
    assert iou(box, above) == 0.0
    touching = np.array([[0, 0, 0, 1, 1, 1, 0], [1, 0, 0, 1, 1, 1, 0]], float)
    assert iou(touching[0], touching[1]) == pytest.approx(0.0, abs=1e-9)


def test_half_overlap_has_iou_one_third():
    a = np.array([0, 0, 0, 1, 1, 1, 0.0])
    b = np.array([0.5, 0, 0, 1, 1, 1, 0.0])
    assert iou(a, b) == pytest.approx(1 / 3, abs=1e-9)
    # The same along z and along a yawed axis.
    assert iou(a, [0, 0, 0.5, 1, 1, 1, 0]) == pytest.approx(1 / 3, abs=1e-9)
    yaw = 0.7
    a_yawed = np.array([1, 1, 0, 2, 1, 1, yaw])
    b_yawed = a_yawed + [np.cos(yaw), np.sin(yaw), 0, 0, 0, 0, 0]
    assert iou(a_yawed, b_yawed) == pytest.approx(1 / 3, abs=1e-9)


def test_contained_box_iou_is_the_volume_ratio():
    outer = np.array([0, 0, 0, 2, 2, 2, 0.3])
    inner = np.array([0.1, 0, 0, 1, 1, 1, 0.3 + np.pi / 4])
    assert iou(outer, inner) == pytest.approx(1 / 8, abs=1e-9)


def test_square_box_rotated_by_90_degrees_is_itself():
    box = np.array([3, -1, 0.5, 1.5, 1.5, 1.0, 0.2])
    assert iou(box, box + [0, 0, 0, 0, 0, 0, np.pi / 2]) == pytest.approx(1.0, abs=1e-9)
    # A long box rotated by 90 degrees about its centre: overlap is the central 1 x 1 square.
    long_box = np.array([0, 0, 0, 3, 1, 1, 0.0])
    assert iou(long_box, long_box + [0, 0, 0, 0, 0, 0, np.pi / 2]) == pytest.approx(1 / 5, abs=1e-9)
    # A rectangle is its own 180 degree rotation, and swapping dx/dy with a 90 degree turn.
    assert iou(long_box, [0, 0, 0, 3, 1, 1, np.pi]) == pytest.approx(1.0, abs=1e-9)
    assert iou(long_box, [0, 0, 0, 1, 3, 1, np.pi / 2]) == pytest.approx(1.0, abs=1e-9)


def test_iou_matrix_shape_and_empty_inputs():
    a = np.array([[0, 0, 0, 1, 1, 1, 0], [5, 5, 0, 1, 1, 1, 0], [0.5, 0, 0, 1, 1, 1, 0]], float)
    matrix = box_iou_3d(a, a[:2])
    assert matrix.shape == (3, 2)
    np.testing.assert_allclose(matrix, [[1, 0], [0, 1], [1 / 3, 0]], atol=1e-9)
    assert box_iou_3d(np.zeros((0, 7)), a).shape == (0, 3)
    assert box_iou_3d(a, np.zeros((0, 7))).shape == (3, 0)


@given(boxes, boxes)
@settings(max_examples=150, deadline=None)
def test_iou_is_symmetric_and_in_unit_interval(a, b):
    ab, ba = iou(a, b), iou(b, a)
    assert 0.0 <= ab <= 1.0 + 1e-9
    assert ab == pytest.approx(ba, abs=1e-9)
    assert iou(a, a) == pytest.approx(1.0, abs=1e-9)


@given(boxes, boxes, angle, coordinate, coordinate, coordinate)
@settings(max_examples=150, deadline=None)
def test_iou_is_invariant_under_a_common_rigid_motion(a, b, yaw, tx, ty, tz):
    transform = make_transform(rotation_ypr(yaw, 0, 0), np.array([tx, ty, tz]))
    moved = transform_boxes(transform, np.stack([a, b]))
    assert iou(moved[0], moved[1]) == pytest.approx(iou(a, b), abs=1e-7)


@given(boxes, boxes)
@settings(max_examples=60, deadline=None)
def test_iou_agrees_with_a_monte_carlo_estimate(a, b):
    rng = np.random.default_rng(0)
    samples = rng.uniform(-0.5, 0.5, (20000, 3)) * a[3:6] @ rotation_z(a[6]).T + a[:3]
    fraction_in_b = points_in_box(samples, b).mean()
    intersection = fraction_in_b * np.prod(a[3:6])
    expected = intersection / (np.prod(a[3:6]) + np.prod(b[3:6]) - intersection)
    assert iou(a, b) == pytest.approx(expected, abs=0.03)


def sample_faces(box: np.ndarray, faces: list[str], rng: np.random.Generator, num: int = 400) -> np.ndarray:
    """Points on the named vertical faces ('+x', '-x', '+y', '-y') of a box, 5 mm noise."""
    parts = []
    for face in faces:
        local = rng.uniform(-0.5, 0.5, (num, 3))
        axis = 0 if face[1] == "x" else 1
        local[:, axis] = 0.5 if face[0] == "+" else -0.5
        parts.append(local * box[3:6])
    local = np.concatenate(parts) + rng.normal(0, 0.005, (num * len(faces), 3))
    return local @ rotation_z(box[6]).T + box[:3]


@pytest.mark.parametrize("yaw", [0.0, 0.3, 0.7, -1.2, 1.5, 2.5])
def test_fit_box_recovers_the_heading_from_two_visible_faces(yaw):
    rng = np.random.default_rng(int(yaw * 100) % 1000)
    box = np.array([4.0, 3.0, 0.5, 2.0, 1.2, 1.0, yaw])
    two_sided = fit_box(sample_faces(box, ["-x", "-y"], rng))
    all_sides = fit_box(sample_faces(box, ["+x", "-x", "+y", "-y"], rng))
    yaw_error = (np.degrees(two_sided[6] - yaw) + 45) % 90 - 45
    assert abs(yaw_error) < 3.0
    assert two_sided[3] >= two_sided[4]
    assert -np.pi / 2 <= two_sided[6] < np.pi / 2
    assert iou(two_sided, all_sides) > 0.85
    assert iou(all_sides, box) > 0.85
    np.testing.assert_allclose(two_sided[3:6], box[3:6], atol=0.06)


def test_fit_box_longer_side_is_dx():
    rng = np.random.default_rng(1)
    box = np.array([0.0, 0.0, 1.0, 0.8, 2.4, 2.0, 0.2])  # dy > dx: the fit swaps them and turns yaw
    fitted = fit_box(sample_faces(box, ["+x", "-x", "+y", "-y"], rng))
    assert fitted[3] == pytest.approx(2.4, abs=0.05) and fitted[4] == pytest.approx(0.8, abs=0.05)
    assert abs((np.degrees(fitted[6] - (0.2 + np.pi / 2)) + 90) % 180 - 90) < 3.0


@pytest.mark.parametrize(
    "points",
    [
        np.array([[1.0, 2.0, 3.0]]),
        np.array([[1.0, 2.0, 3.0], [1.0, 2.5, 3.0]]),
        np.array([[1.0, 2.0, 3.0]] * 5),
        np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float),  # collinear
    ],
)
def test_fit_box_of_degenerate_point_sets(points):
    box = fit_box(points)
    assert box.shape == (7,) and np.isfinite(box).all()
    assert (box[3:6] >= 0.02 - 1e-12).all()
    assert points_in_box(points, box, margin=1e-6).all()


def test_complete_hidden_side_extends_away_from_the_viewpoint():
    # Seen from the origin, a 2 x 0.5 box at y = 5 is cut at its back (larger y).
    fitted = np.array([[0.0, 5.0, 0.5, 2.0, 0.5, 1.0, 0.0]])
    completed = complete_hidden_side(fitted)
    np.testing.assert_allclose(completed, [[0.0, 5.75, 0.5, 2.0, 2.0, 1.0, 0.0]], atol=1e-12)
    # The near face stays where it was seen.
    assert completed[0, 1] - completed[0, 4] / 2 == pytest.approx(fitted[0, 1] - fitted[0, 4] / 2)
    # From a viewpoint behind it, the box grows the other way.
    behind = complete_hidden_side(fitted, viewpoint=np.array([0.0, 10.0, 1.0]))
    np.testing.assert_allclose(behind[0, :2], [0.0, 4.25], atol=1e-12)
    # The completed box contains the fitted one: fitted corners are inside it.
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (4.75, 5.25) for z in (0, 1)], float)
    assert points_in_box(corners, completed[0], margin=1e-9).all()


def test_complete_hidden_side_of_yawed_and_square_boxes():
    yaw = 0.6
    fitted = np.array([[10.0, 0.0, 0.0, 3.0, 1.0, 1.0, yaw], [4.0, 4.0, 0.0, 1.5, 1.5, 1.0, 0.3]])
    completed = complete_hidden_side(fitted)
    np.testing.assert_allclose(completed[:, 3], completed[:, 4])
    np.testing.assert_allclose(completed[1], fitted[1])  # already square: unchanged
    shift = completed[0, :2] - fitted[0, :2]
    short_axis = np.array([-np.sin(yaw), np.cos(yaw)])
    # Moved by (3 - 1) / 2 along the short axis, away from the origin.
    np.testing.assert_allclose(np.abs(shift @ short_axis), 1.0, atol=1e-12)
    np.testing.assert_allclose(shift @ np.array([np.cos(yaw), np.sin(yaw)]), 0.0, atol=1e-12)
    assert np.linalg.norm(completed[0, :2]) > np.linalg.norm(fitted[0, :2])
    assert complete_hidden_side(np.zeros((0, 7))).shape == (0, 7)


def _clip_reference(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman, one pair at a time: the slow, obvious form of the vectorised clip."""
    output = subject
    for i in range(len(clipper)):
        if len(output) == 0:
            break
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        side = (b - a)[0] * (output[:, 1] - a[1]) - (b - a)[1] * (output[:, 0] - a[0])
        new = []
        for j in range(len(output)):
            p, q = output[j], output[(j + 1) % len(output)]
            sp, sq = side[j], side[(j + 1) % len(output)]
            if sp >= 0:
                new.append(p)
            if (sp >= 0) != (sq >= 0):
                new.append(p + sp / (sp - sq) * (q - p))
        output = np.array(new).reshape(-1, 2)
    return output


def _iou_reference(a: np.ndarray, b: np.ndarray) -> float:
    from factorydet_core.boxes import rectangle_corners

    polygon = _clip_reference(rectangle_corners(a[None])[0], rectangle_corners(b[None])[0])
    area = 0.0
    if len(polygon) >= 3:
        x, y = polygon[:, 0], polygon[:, 1]
        area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    height = max(0.0, min(a[2] + a[5] / 2, b[2] + b[5] / 2) - max(a[2] - a[5] / 2, b[2] - b[5] / 2))
    inter = area * height
    return inter / (np.prod(a[3:6]) + np.prod(b[3:6]) - inter)


@settings(max_examples=200, deadline=None)
@given(boxes, boxes)
def test_vectorised_iou_matches_one_pair_clipping(a, b):
    assert iou(a, b) == pytest.approx(_iou_reference(a, b), abs=1e-9)


def test_iou_hand_computed_cases():
    unit = np.array([0, 0, 0, 2, 1, 1, 0.0])
    # The same box turned by 90 degrees: footprints 2x1 and 1x2 share a 1x1 square.
    assert iou(unit, unit + [0, 0, 0, 0, 0, 0, np.pi / 2]) == pytest.approx(1 / 3, abs=1e-9)
    # A box nested in another: IoU is the volume ratio.
    inner = np.array([0.1, 0, 0, 1, 0.5, 0.5, 0.0])
    assert iou(unit, inner) == pytest.approx(0.25 / 2, abs=1e-9)
    # A unit square turned 45 degrees over another: octagon of area 2 (sqrt 2 - 1).
    square = np.array([0, 0, 0, 1, 1, 1, 0.0])
    octagon = 2 * (np.sqrt(2) - 1)
    assert iou(square, square + [0, 0, 0, 0, 0, 0, np.pi / 4]) == pytest.approx(
        octagon / (2 - octagon), abs=1e-9
    )


def test_iou_blocks_give_the_same_matrix():
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.uniform(-3, 3, (40, 3)), rng.uniform(0.2, 2, (40, 3)), rng.uniform(-3, 3, 40)])
    np.testing.assert_allclose(box_iou_3d(a, a, max_block=7), box_iou_3d(a, a), atol=0)


def test_heading_gap_is_the_angle_modulo_a_quarter_turn():
    d = np.radians
    cases = [
        (0.0, 0.0, 0.0),
        (d(10), 0.0, d(10)),
        (d(-10), 0.0, d(10)),
        (d(95), 0.0, d(5)),
        (d(85), 0.0, d(5)),
        (d(45), 0.0, d(45)),
        (d(190), d(5), d(5)),
        (d(-89), d(1), 0.0),
    ]
    for yaw, heading, gap in cases:
        assert float(heading_gap(yaw, heading)) == pytest.approx(gap, abs=1e-12)
    yaws = np.linspace(-7, 7, 101).reshape(1, 101)
    assert heading_gap(yaws, 0.4).shape == (1, 101)
    assert (heading_gap(yaws, 0.4) <= np.pi / 4 + 1e-12).all()


@given(st.floats(0.0, 2 * np.pi), st.integers(0, 2**31 - 1))
@settings(max_examples=100, deadline=None)
def test_scene_heading_finds_the_grid_of_the_heavy_boxes(heading, seed):
    rng = np.random.default_rng(seed)
    # Walls and racks (many points) along the grid, either way round; a few light boxes at random.
    num_grid, num_random = 12, 30
    yaws = np.concatenate(
        [
            heading + rng.integers(0, 4, num_grid) * np.pi / 2 + rng.normal(0, np.radians(0.3), num_grid),
            rng.uniform(-np.pi, np.pi, num_random),
        ]
    )
    boxes = np.zeros((len(yaws), 7))
    boxes[:, 3:6] = 1.0
    boxes[:, 6] = yaws
    weights = np.concatenate([rng.uniform(500, 2000, num_grid), rng.uniform(10, 100, num_random)])
    found = scene_heading(boxes, weights)
    assert 0.0 <= found < np.pi / 2
    assert heading_gap(found, heading) < np.radians(1.0)
    # Turning the whole scene turns its heading.
    turned = boxes.copy()
    turned[:, 6] += 0.3
    assert heading_gap(scene_heading(turned, weights), heading + 0.3) < np.radians(1.0)


def test_scene_heading_of_no_boxes_is_zero():
    assert scene_heading(np.zeros((0, 7))) == 0.0


def _fit_box_reference(points, min_size=0.02, angle_step_deg=1.0, max_search_points=256, heading=None):
    """``fit_box`` written plainly in numpy, one point set at a time (the compiled kernel's reference)."""
    xy = np.asarray(points[:, :2], np.float64)
    z_lo, z_hi = float(points[:, 2].min()), float(points[:, 2].max())
    search = xy[:: max(1, -(-len(xy) // max_search_points))] - xy.mean(axis=0)
    angle = 0.0 if heading is None else float(heading) % (np.pi / 2)
    if heading is None and len(search) >= 3:
        angles = np.radians(np.arange(0.0, 90.0, angle_step_deg))
        u = search[:, 0, None] * np.cos(angles) + search[:, 1, None] * np.sin(angles)
        v = -search[:, 0, None] * np.sin(angles) + search[:, 1, None] * np.cos(angles)
        du = np.minimum(u - u.min(axis=0), u.max(axis=0) - u)
        dv = np.minimum(v - v.min(axis=0), v.max(axis=0) - v)
        angle = float(angles[int(np.argmax((1.0 / np.maximum(np.minimum(du, dv), 0.01)).sum(axis=0)))])
    c, s = np.cos(angle), np.sin(angle)
    u, v = xy[:, 0] * c + xy[:, 1] * s, -xy[:, 0] * s + xy[:, 1] * c
    centre_u, centre_v = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    size = np.maximum([u.max() - u.min(), v.max() - v.min()], min_size)
    yaw = angle
    if size[1] > size[0]:
        size, yaw = size[::-1], angle + np.pi / 2
    return np.array(
        [
            c * centre_u - s * centre_v,
            s * centre_u + c * centre_v,
            (z_lo + z_hi) / 2,
            size[0],
            size[1],
            max(z_hi - z_lo, min_size),
            (yaw + np.pi / 2) % np.pi - np.pi / 2,
        ]
    )


def test_fit_boxes_matches_the_plain_fit_of_each_set():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(3000, 3)) * [4, 2, 1]
    # Sets of every size the search treats differently: 1 and 2 points (no search), a few, more
    # than max_search_points (strided), and an L-shaped corner.
    corner = np.concatenate(
        [
            np.column_stack([np.linspace(0, 2, 40), np.zeros(40)]),
            np.column_stack([np.zeros(30), np.linspace(0, 1, 30)]),
        ]
    )
    corner = np.column_stack([corner @ rotation_z(0.4)[:2, :2].T + [5, 5], rng.uniform(0, 1, 70)])
    points = np.concatenate([points, corner])
    lists = [rng.choice(3000, n, replace=False) for n in (1, 2, 3, 7, 50, 256, 257, 900)]
    lists.append(np.arange(3000, 3070))
    boxes = fit_boxes(points, lists)
    expected = np.array([_fit_box_reference(points[idx]) for idx in lists])
    np.testing.assert_allclose(boxes, expected, rtol=0, atol=1e-12)
    assert np.isclose(heading_gap(boxes[-1, 6], 0.4), 0, atol=np.radians(1))  # the corner's heading
    headings = np.array([np.nan, 0.3, -2.0, np.nan, 7.5, 0.0, np.pi / 2, -0.1, np.nan])
    boxes = fit_boxes(points, lists, headings, max_search_points=64)
    expected = [
        _fit_box_reference(points[idx], max_search_points=64, heading=None if np.isnan(h) else h)
        for idx, h in zip(lists, headings)
    ]
    np.testing.assert_allclose(boxes, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        fit_box(points[lists[5]], heading=0.3), fit_boxes(points, lists[5:6], [0.3])[0]
    )
    assert fit_boxes(points, []).shape == (0, 7)
    with pytest.raises(InputError, match="empty"):
        fit_boxes(points, [np.arange(3), np.arange(0)])
    with pytest.raises(InputError, match="outside"):
        fit_boxes(points, [np.array([len(points)])])
    with pytest.raises(InputError, match="headings"):
        fit_boxes(points, lists, np.zeros(2))
    with pytest.raises(InputError, match="boolean mask"):
        fit_boxes(points, [np.arange(len(points)) < 10])


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-2, 2),
            st.floats(-2, 2),
            st.floats(0.01, 3),
            st.floats(0.01, 3),
            st.floats(-4, 4),
            st.sampled_from(["random", "same", "flush", "inside"]),
        ),
        min_size=1,
        max_size=20,
    )
)
def test_the_compiled_intersection_areas_equal_the_numpy_reference(pairs):
    from factorydet_core.boxes import (
        _intersection_areas_numpy,
        rectangle_corners,
        rectangle_intersection_areas,
    )

    boxes_a, boxes_b = [], []
    for x, y, dx, dy, yaw, kind in pairs:
        a = [x, y, 0.0, dx, dy, 1.0, yaw]
        b = {
            "random": [y, x, 0.0, dy, dx, 1.0, -yaw],
            "same": a,
            "flush": [x + dx * np.cos(yaw), y + dx * np.sin(yaw), 0.0, dx, dy, 1.0, yaw],  # sharing an edge
            "inside": [x, y, 0.0, dx / 2, dy / 2, 1.0, yaw],
        }[kind]
        boxes_a.append(a)
        boxes_b.append(b)
    corners_a, corners_b = rectangle_corners(np.array(boxes_a)), rectangle_corners(np.array(boxes_b))
    fast = rectangle_intersection_areas(corners_a, corners_b)
    np.testing.assert_allclose(fast, _intersection_areas_numpy(corners_a, corners_b), atol=1e-9)
    for (_x, _y, dx, dy, _yaw, kind), area in zip(pairs, fast):
        if kind == "same":
            assert area == pytest.approx(dx * dy, rel=1e-9)
        elif kind == "inside":
            assert area == pytest.approx(dx * dy / 4, rel=1e-9)
        elif kind == "flush":
            assert area == pytest.approx(0.0, abs=1e-9)


@given(
    st.lists(
        st.tuples(
            st.integers(0, 8), st.integers(0, 8), st.integers(0, 2), st.integers(1, 4), st.integers(0, 7)
        ),
        max_size=30,
    ),
    st.sampled_from([0.01, 0.25, 0.6]),
)
@settings(max_examples=60, deadline=None)
def test_overlapping_pairs_are_the_iou_matrix_above_the_threshold(entries, min_iou):
    from factorydet_core.boxes import overlapping_box_pairs

    # Boxes on a coarse grid of centres, sizes and headings: many overlap, some exactly.
    boxes = np.array(
        [[0.3 * x, 0.3 * y, 0.2 * z, 0.4 * s, 0.3 * s, 0.5, 0.4 * h] for x, y, z, s, h in entries]
    ).reshape(-1, 7)
    first, second = overlapping_box_pairs(boxes, min_iou)
    expected = np.argwhere(np.triu(box_iou_3d(boxes, boxes) >= min_iou, k=1))
    np.testing.assert_array_equal(np.column_stack([first, second]).reshape(-1, 2), expected)


def test_overlapping_pairs_refuse_a_threshold_of_zero():
    from factorydet_core.boxes import overlapping_box_pairs

    with pytest.raises(InputError, match="min_iou"):
        overlapping_box_pairs(np.zeros((2, 7)), 0.0)
