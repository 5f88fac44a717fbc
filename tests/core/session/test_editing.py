"""Label-editor geometry: gizmo poses, screen rectangles, camera framing, splitting, the model's
box for a clicked point."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.geometry import wrap_angle
from factorydet_core.session.editing import (
    BOX_FACES,
    MIN_BOX_SIZE_M,
    box_face_points,
    box_of_points,
    box_to_pose,
    camera_for_box,
    nudge_box,
    points_in_screen_rect,
    pose_to_box,
    resize_box,
    split_in_two,
    suggest_box,
)
from factorydet_core.types import InputError

finite = st.floats(-50, 50, allow_nan=False)
sizes = st.floats(0.05, 10, allow_nan=False)
yaws = st.floats(-3.1, 3.1, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(finite, finite, finite, sizes, sizes, sizes, yaws)
def test_box_pose_round_trip(cx, cy, cz, dx, dy, dz, yaw):
    box = np.array([cx, cy, cz, dx, dy, dz, yaw])
    position, wxyz = box_to_pose(box)
    assert np.linalg.norm(wxyz) == pytest.approx(1.0)
    again = pose_to_box(position, wxyz, box[3:6])
    np.testing.assert_allclose(again[:6], box[:6], atol=1e-9)
    assert abs(wrap_angle(again[6] - yaw)) < 1e-9


def test_a_tilted_gizmo_keeps_only_the_heading():
    # 30 degrees about z, then 20 degrees about x: the heading stays 30 degrees.
    def quat(axis, angle):
        return np.r_[np.cos(angle / 2), np.sin(angle / 2) * np.asarray(axis, float)]

    def mul(a, b):
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return np.array(
            [
                w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            ]
        )

    wxyz = mul(quat([0, 0, 1], np.radians(30)), quat([1, 0, 0], np.radians(20)))
    box = pose_to_box([0, 0, 0], wxyz, [1, 2, 3])
    assert np.degrees(box[6]) == pytest.approx(30.0)
    with pytest.raises(InputError, match="positive"):
        pose_to_box([0, 0, 0], wxyz, [1, 0, 3])


def test_points_in_screen_rect_follow_the_camera():
    # Camera at the origin looking down +x (OpenCV: z forward = world +x, y down = world -z).
    rotation = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # columns: camera axes in world
    w = np.sqrt(1 + np.trace(rotation)) / 2
    wxyz = np.array(
        [
            w,
            (rotation[2, 1] - rotation[1, 2]) / (4 * w),
            (rotation[0, 2] - rotation[2, 0]) / (4 * w),
            (rotation[1, 0] - rotation[0, 1]) / (4 * w),
        ]
    )
    points = np.array([[10, 0, 0], [10, 5, 0], [10, -5, 0], [-10, 0, 0], [10, 0, 4]], float)
    full = points_in_screen_rect(points, [0, 0, 0], wxyz, np.radians(90), 1.0, [0, 0], [1, 1])
    assert full.tolist() == [True, True, True, False, True]
    # The left half of the screen is world +y (the camera's -x).
    left = points_in_screen_rect(points, [0, 0, 0], wxyz, np.radians(90), 1.0, [0, 0], [0.45, 1])
    assert left.tolist() == [False, True, False, False, False]
    top = points_in_screen_rect(points, [0, 0, 0], wxyz, np.radians(90), 1.0, [0.4, 0], [0.6, 0.45])
    assert top.tolist() == [False, False, False, False, True]


def test_camera_frames_the_box():
    box = np.array([5.0, 3.0, 0.5, 1.0, 1.0, 1.0, 0.3])
    position, look_at = camera_for_box(box)
    np.testing.assert_allclose(look_at, box[:3])
    assert position[2] > box[2] and np.linalg.norm(position - look_at) >= 4.0


def test_split_in_two_separates_two_clumps(rng):
    a = rng.normal([0, 0, 0.5], 0.2, (300, 3))
    b = rng.normal([2, 1, 0.5], 0.2, (200, 3))
    labels = split_in_two(np.vstack([a, b]))
    assert set(labels[:300]) != set(labels[300:])
    assert len(set(labels[:300])) == 1 and len(set(labels[300:])) == 1
    with pytest.raises(InputError):
        split_in_two(np.zeros((1, 3)))


def test_box_of_points_covers_them(rng):
    points = rng.uniform([0, 0, 0], [2, 1, 1], (500, 3))
    box = box_of_points(points)
    np.testing.assert_allclose(box[3:6], [2, 1, 1], atol=0.1)
    with pytest.raises(InputError, match="at least 3"):
        box_of_points(points[:2])


@pytest.fixture(scope="module")
def detected(small_dataset_dir, tiny_model_path):
    from factorydet_core.detection.model import DetectionModel
    from factorydet_core.evaluation.evaluate import detector_for
    from factorydet_core.io.dataset import open_dataset

    dataset = open_dataset(small_dataset_dir)
    detector = detector_for(DetectionModel.load(tiny_model_path), dataset, calibrate=False)
    return detector.detect(dataset.frame(0))


def test_a_clicked_point_suggests_the_best_candidate_whose_point_set_holds_it(detected):
    candidates, proposals = detected.candidates, detected.proposal.proposals
    patch_ids = detected.proposal.segmentation.patch_ids
    best = int(np.argmax(candidates.scores))
    patch = proposals.patch_sets[int(candidates.proposal_ids[best])][0]
    point = int(np.flatnonzero(patch_ids == patch)[0])
    suggestion = suggest_box(detected, point)
    # The best candidate overall holds the point: it is the suggestion.
    assert suggestion.score == pytest.approx(float(candidates.scores[best]))
    np.testing.assert_allclose(suggestion.box, candidates.boxes[best])
    assert suggestion.class_name == candidates.class_names[int(candidates.class_ids[best])]
    # Any point: the suggestion's point set holds its patch, and no candidate that does scores higher.
    for point in np.random.default_rng(0).choice(len(patch_ids), 50, replace=False):
        suggestion = suggest_box(detected, int(point))
        holding = [
            k
            for k, p in enumerate(candidates.proposal_ids)
            if int(patch_ids[point]) in proposals.patch_sets[int(p)]
        ]
        if patch_ids[point] < 0 or not holding:
            assert suggestion is None
        else:
            assert suggestion.score == pytest.approx(max(float(candidates.scores[k]) for k in holding))
    with pytest.raises(InputError, match="not one of the cloud's"):
        suggest_box(detected, len(patch_ids))


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_box_views_look_at_the_box_from_above_its_side_and_its_front(yaw):
    from factorydet_core.session.editing import camera_view_of_box

    box = np.array([3.0, -2.0, 0.5, 1.2, 0.6, 1.0, yaw])
    heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    position, look_at, up = camera_view_of_box(box, "top")
    np.testing.assert_allclose(look_at, box[:3])
    np.testing.assert_allclose((position - look_at) / np.linalg.norm(position - look_at), [0, 0, 1])
    np.testing.assert_allclose(up, heading)  # the box's heading points up the screen
    position, look_at, up = camera_view_of_box(box, "front")
    np.testing.assert_allclose((position - look_at) / np.linalg.norm(position - look_at), heading, atol=1e-12)
    position, _, up = camera_view_of_box(box, "side")
    assert abs(np.dot(position - box[:3], heading)) < 1e-9 and up.tolist() == [0, 0, 1]
    assert np.linalg.norm(position - box[:3]) >= 1.5
    with pytest.raises(InputError, match="unknown box view"):
        camera_view_of_box(box, "back")


@settings(max_examples=100, deadline=None)
@given(
    finite,
    finite,
    sizes,
    sizes,
    sizes,
    yaws,
    st.floats(-0.5, 0.5),
    st.floats(-0.5, 0.5),
    st.floats(-0.5, 0.5),
)
def test_nudges_move_along_the_heading_and_resizes_keep_the_centre_and_the_bottom(
    cx, cy, dx, dy, dz, yaw, longer, wider, taller
):
    box = np.array([cx, cy, dz / 2, dx, dy, dz, yaw])
    moved = nudge_box(box, forward=0.01)
    np.testing.assert_allclose(moved[:2] - box[:2], 0.01 * np.array([np.cos(yaw), np.sin(yaw)]), atol=1e-12)
    left = nudge_box(box, left=0.01)
    np.testing.assert_allclose(left[:2] - box[:2], 0.01 * np.array([-np.sin(yaw), np.cos(yaw)]), atol=1e-12)
    turned = nudge_box(box, yaw_deg=1.0)
    assert abs(wrap_angle(turned[6] - yaw - np.radians(1.0))) < 1e-12
    grown = nudge_box(box, longer=longer, wider=wider, taller=taller)
    np.testing.assert_allclose(grown[:2], box[:2])  # length and width about the centre
    assert grown[2] - grown[5] / 2 == pytest.approx(box[2] - box[5] / 2)  # the bottom stays
    expected = np.maximum(box[3:6] + [longer, wider, taller], MIN_BOX_SIZE_M)
    np.testing.assert_allclose(grown[3:6], expected)
    assert grown[6] == yaw


@settings(max_examples=100, deadline=None)
@given(
    finite,
    finite,
    finite,
    sizes,
    sizes,
    sizes,
    yaws,
    st.sampled_from(BOX_FACES),
    st.floats(-3, 3),
    st.floats(-3, 3),
    st.floats(-3, 3),
)
def test_dragging_a_face_moves_it_alone(cx, cy, cz, dx, dy, dz, yaw, face, along, across, up):
    """A resize handle dragged anywhere: the dragged face goes through the pointer's projection on
    its normal, the opposite face and the heading stay, and the box never turns inside out."""
    box = np.array([cx, cy, cz, dx, dy, dz, yaw])
    faces = box_face_points(box)
    k = BOX_FACES.index(face)
    opposite = k + 1 if k % 2 == 0 else k - 1
    normal = (faces[k] - faces[opposite]) / np.linalg.norm(faces[k] - faces[opposite])
    point = faces[k] + np.array([along, across, up])
    resized = resize_box(box, face, point)
    again = box_face_points(resized)
    np.testing.assert_allclose(again[opposite], faces[opposite], atol=1e-9)
    assert resized[6] == yaw and (resized[3:6] >= MIN_BOX_SIZE_M - 1e-12).all()
    reach = (point - faces[opposite]) @ normal
    if reach >= MIN_BOX_SIZE_M:  # the face lands on the pointer's projection
        np.testing.assert_allclose((again[k] - point) @ normal, 0.0, atol=1e-9)
    else:  # dragged past the opposite face: the thinnest box there is
        np.testing.assert_allclose(resized[3 + k // 2], MIN_BOX_SIZE_M)
    others = [a for a in range(3) if a != k // 2]
    np.testing.assert_allclose(resized[[3 + a for a in others]], box[[3 + a for a in others]])


def test_resize_refuses_an_unknown_face():
    with pytest.raises(InputError, match="unknown face"):
        resize_box(np.zeros(7) + 1, "side", np.zeros(3))
