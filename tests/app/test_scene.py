import numpy as np
import pytest
import viser

from app.scene import SceneView, grid_segments


@pytest.fixture
def server():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


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


def test_the_scene_asks_the_browser_for_a_light_without_shadows(server):
    calls = []
    original = server.scene.configure_default_lights
    server.scene.configure_default_lights = lambda *a, **k: (calls.append((a, k)), original(*a, **k))
    SceneView(server)
    assert calls == [((), {"enabled": True, "cast_shadow": False})]


def test_the_floor_grid_is_shown_and_hidden(server):
    view = SceneView(server)
    assert view.grid_visible and all(handle.visible for handle in view._grid)
    view.set_grid_visible(False)
    assert not view.grid_visible and not any(handle.visible for handle in view._grid)
    view.set_grid_visible(True)
    assert view.grid_visible and all(handle.visible for handle in view._grid)


def test_an_edit_sends_only_the_labels_it_changed(server):
    view = SceneView(server)
    sent = {"add_label": 0, "add_line_segments": 0}
    for method in sent:
        original = getattr(server.scene, method)

        def counting(*args, _original=original, _method=method, **kwargs):
            sent[_method] += 1
            return _original(*args, **kwargs)

        setattr(server.scene, method, counting)
    names = ("box", "cone")
    boxes = np.array([[float(k), 0.0, 0.5, 1.0, 1.0, 1.0, 0.0] for k in range(0, 30, 3)])
    class_ids = np.array([0, 1] * 5)
    view.draw_labels(boxes, class_ids, names, visible=True)
    assert sent == {"add_label": 10, "add_line_segments": 1}
    first_names = [node for node, *_ in view._name_nodes]
    # The same labels again: nothing is sent.
    view.draw_labels(boxes.copy(), class_ids, names, visible=True)
    assert sent == {"add_label": 10, "add_line_segments": 1}
    # One box moved and another relabelled: one wireframe node again, two names changed in place.
    moved, relabelled = boxes.copy(), class_ids.copy()
    moved[4, 0] += 0.01
    relabelled[7] = 0
    view.draw_labels(moved, relabelled, names, visible=True)
    assert sent == {"add_label": 10, "add_line_segments": 2}
    assert [node for node, *_ in view._name_nodes] == first_names
    assert first_names[7].text == "box" and first_names[4].position[0] == pytest.approx(12.01)
    assert first_names[3].text == "cone" and first_names[3].position[0] == pytest.approx(9.0)
    # A deleted label takes its name node with it; a pre-label gets the bracket node.
    pre = np.zeros(9, bool)
    pre[0] = True
    view.draw_labels(moved[:9], relabelled[:9], names, visible=True, prelabel_mask=pre)
    assert len(view._name_nodes) == 9 and set(view._line_nodes) == {"/labels/boxes", "/labels/pre_labels"}
    assert sent == {"add_label": 10, "add_line_segments": 4}
    # Hidden: every label node is removed.
    view.draw_labels(moved, relabelled, names, visible=False)
    assert view._name_nodes == [] and view._line_nodes == {}


def test_a_frame_drawn_again_is_not_merged_again_until_others_push_it_out(
    small_dataset_dir, monkeypatch, server
):
    import app.scene as scene_module
    from factorydet_core.io.dataset import open_dataset

    dataset = open_dataset(small_dataset_dir)
    merged = []
    merge = scene_module.merge_frame
    monkeypatch.setattr(scene_module, "merge_frame", lambda frame: merged.append(frame.name) or merge(frame))
    monkeypatch.setattr(scene_module, "MERGED_FRAMES_KEPT", 2)
    view = scene_module.SceneView(server)
    draw = lambda k: view.draw(dataset.frame(k), color_mode="height", point_size=0.05, max_height=6.0)  # noqa: E731
    for k in (0, 1, 0, 1):
        draw(k)
    assert merged == [dataset.frame(0).name, dataset.frame(1).name]
    points, _ = view._shown
    expected = merge(dataset.frame(1))
    np.testing.assert_array_equal(points, expected.points[expected.below(6.0)])
    draw(2)  # a third frame pushes out the one drawn longest ago (frame 0)
    draw(1)
    draw(0)
    assert merged[2:] == [dataset.frame(2).name, dataset.frame(0).name]


def test_a_points_budget_draws_that_many_of_the_scan_spread_over_it_and_all_of_them_again(
    small_dataset_dir, server
):
    from factorydet_core.colors import colors_by_height
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.merge import merge_frame

    frame = open_dataset(small_dataset_dir).frame(0)
    merged = merge_frame(frame)
    below = merged.below(6.0)
    budget = int(below.sum()) // 4
    view = SceneView(server)
    view.draw(frame, color_mode="height", point_size=0.05, max_height=6.0, max_points=budget)
    points, rgb = view._shown
    assert len(points) == len(rgb) == view.num_points_shown == budget
    # Drawn points are scan points below the height cut, each in its own colour.
    same = (points[:, None, :] == merged.points[None, :, :]).all(-1)
    assert same.any(1).all()
    index = same.argmax(1)
    assert below[index].all()
    assert (rgb == colors_by_height(merged.points[:, 2])[index]).all()
    # ... from all over the scan.
    lo, hi = merged.points[below, :2].min(0), merged.points[below, :2].max(0)
    margin = 0.2 * (hi - lo)
    assert (points[:, :2].min(0) - lo < margin).all() and (hi - points[:, :2].max(0) < margin).all()
    view.draw(frame, color_mode="height", point_size=0.05, max_height=6.0, max_points=None)
    assert len(view._shown[0]) == int(below.sum())
