"""``LayerView``: the detection layers drawn into a scene (no browser)."""

import numpy as np


def test_a_points_budget_draws_the_same_points_in_every_point_layer_and_all_of_them_again(small_dataset_dir):
    import viser

    from app.layers import LayerView
    from app.state import LAYERS
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset

    result = Detector().propose(open_dataset(small_dataset_dir).frame(0))
    below = result.cloud.below(6.0)
    budget = int(below.sum()) // 3
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        view = LayerView(server)
        view.draw(result, 0, dict.fromkeys(LAYERS, True), 0.05, 6.0, max_points=budget)
        patches, segments = view.nodes["patches"], view.nodes["segments"]
        assert len(patches.points) == len(patches.colors) == budget
        np.testing.assert_array_equal(patches.points, segments.points)  # one choice for one cloud
        assert len(view.nodes["merged"].points) <= budget
        assert len(view.nodes["voxels"].points) <= budget
        view.draw(result, 0, dict.fromkeys(LAYERS, True), 0.05, 6.0, max_points=None)
        assert len(view.nodes["patches"].points) == int(below.sum())
        assert len(view.nodes["merged"].points) == int(result.merged.below(6.0).sum())
    finally:
        server.stop()


def test_a_hidden_layer_is_sent_when_first_shown_and_then_only_toggled(small_dataset_dir):
    import viser

    from app.layers import DRAWN_LAYERS, LayerView
    from app.state import LAYERS
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset

    result = Detector().propose(open_dataset(small_dataset_dir).frame(0))
    layers = {name: name == "proposals" for name in LAYERS}
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        view = LayerView(server)
        view.draw(result, 0, layers, 0.05, 6.0)
        assert set(view.nodes) == {"proposals"}
        view.set_point_size(0.08)  # a hidden layer sent later takes the size set meanwhile
        view.set_visibility({**layers, "patches": True})
        patches = view.nodes["patches"]
        assert patches.visible and patches.point_size == 0.08
        assert len(patches.points) == int(result.cloud.below(6.0).sum())
        view.set_visibility(layers)
        assert view.nodes["patches"] is patches and not patches.visible  # hidden, not sent again
        view.set_visibility({**layers, "patches": True})
        assert view.nodes["patches"] is patches and patches.visible
        # A new result: the old nodes go, hidden ones with them, and only the shown are sent.
        view.draw(result, 1, layers, 0.05, 6.0)
        assert set(view.nodes) == {"proposals"} and view.drawn_frame_index == 1
        view.set_visibility(dict.fromkeys(LAYERS, True))
        assert set(view.nodes) == set(DRAWN_LAYERS)
    finally:
        server.stop()


def test_the_voxels_layer_never_shows_another_results_colours(small_dataset_dir):
    # A result without colours (the worker makes none while the layer is hidden) gets its own
    # when the layer is sent, never those of the result drawn before it.
    import dataclasses

    import viser

    from app.layers import LayerView
    from app.state import LAYERS
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.voxels import voxel_colors

    dataset = open_dataset(small_dataset_dir)
    first, second = (Detector().propose(dataset.frame(i)) for i in (0, 1))
    painted = dataclasses.replace(first, voxel_colors=np.zeros((first.grid.num_voxels, 3), np.uint8))
    layers = {**dict.fromkeys(LAYERS, False), "voxels": True}
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        view = LayerView(server)
        view.draw(painted, 0, layers, 0.05, 50.0)
        assert not view.nodes["voxels"].colors.any()  # the worker's colours, as given
        unpainted = dataclasses.replace(second, voxel_colors=None)
        view.draw(unpainted, 1, layers, 0.05, 50.0)
        expected = voxel_colors(second.cloud, second.grid, second.voxel_features)
        np.testing.assert_array_equal(view.nodes["voxels"].colors, expected[second.grid.below(50.0)])
    finally:
        server.stop()
