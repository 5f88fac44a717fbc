import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from factorydet_core.proposals.features import NUM_CHANNELS, NUM_GAUSSIANS
from factorydet_core.proposals.voxels import (
    fisher_vector_colors,
    voxel_fisher_vectors,
    voxel_local_points,
    voxelize,
)
from factorydet_core.types import InputError, MergedCloud


def make_cloud(points: np.ndarray) -> MergedCloud:
    num = len(points)
    return MergedCloud(
        points=np.asarray(points, np.float32),
        sensor_ids=np.zeros(num, np.int16),
        point_instance_ids=np.zeros(num, np.int64),
        T_vehicle_sensor=np.eye(4)[None],
    )


def test_voxel_counts_on_a_constructed_cloud():
    # Cells of 0.5 m: (0,0,0) x 3 points, (1,0,0) x 1, (0,2,1) x 2, (-1,-1,0) x 4.
    size = 0.5
    cells_and_counts = {(0, 0, 0): 3, (1, 0, 0): 1, (0, 2, 1): 2, (-1, -1, 0): 4}
    rng = np.random.default_rng(0)
    points = np.concatenate(
        [(np.array(cell) + rng.uniform(0.05, 0.95, (n, 3))) * size for cell, n in cells_and_counts.items()]
    )
    grid = voxelize(points.astype(np.float32), size)
    assert grid.num_voxels == 4
    assert grid.num_points.sum() == len(points) == 10
    np.testing.assert_allclose(grid.origin, [-0.5, -0.5, 0.0])
    # Coordinates are relative to the lowest cell and sorted lexicographically.
    expected = sorted((c[0] + 1, c[1] + 1, c[2]) for c in cells_and_counts)
    assert [tuple(c) for c in grid.coords.tolist()] == expected
    counts = {tuple(c): n for c, n in zip(grid.coords.tolist(), grid.num_points.tolist())}
    assert counts == {(c[0] + 1, c[1] + 1, c[2]): n for c, n in cells_and_counts.items()}
    np.testing.assert_array_equal(np.bincount(grid.point_voxel_ids, minlength=4), grid.num_points)
    # Points of one cell share a voxel.
    assert len(np.unique(grid.point_voxel_ids[:3])) == 1
    assert len(np.unique(grid.point_voxel_ids[3:])) == 3
    np.testing.assert_allclose(grid.centres[grid.point_voxel_ids[0]], [0.25, 0.25, 0.25])


def test_a_point_keeps_its_cell_whatever_else_is_in_the_cloud():
    point = np.array([[1.23, -4.56, 0.78]], np.float32)
    alone = voxelize(point, 0.2)
    other = voxelize(np.concatenate([point, [[-7.1, 3.3, -2.0]]]).astype(np.float32), 0.2)
    np.testing.assert_allclose(
        alone.centres[alone.point_voxel_ids[0]], other.centres[other.point_voxel_ids[0]], atol=1e-9
    )


points_strategy = hnp.arrays(
    np.float32,
    st.tuples(st.integers(1, 60), st.just(3)),
    elements=st.floats(-20, 20, width=32),
)


@given(points_strategy, st.sampled_from([0.05, 0.1, 0.2, 0.37, 1.0]))
@settings(max_examples=80, deadline=None)
def test_every_point_lies_inside_its_voxel(points, voxel_size):
    grid = voxelize(points, voxel_size)
    assert grid.num_points.sum() == len(points)
    assert (grid.num_points >= 1).all()
    assert grid.point_voxel_ids.shape == (len(points),)
    assert len(np.unique(grid.coords, axis=0)) == grid.num_voxels
    lower = grid.origin + grid.coords[grid.point_voxel_ids] * voxel_size
    tol = 1e-9 * (1 + np.abs(points).max())
    assert (points >= lower - tol).all()
    assert (points <= lower + voxel_size + tol).all()
    centres = grid.centres[grid.point_voxel_ids]
    assert (np.abs(points - centres) <= voxel_size / 2 + tol).all()
    local = voxel_local_points(points, grid)
    assert (np.abs(local) <= 1 + 1e-5).all()


def test_empty_input_gives_an_empty_grid():
    grid = voxelize(np.zeros((0, 3), np.float32), 0.2)
    assert grid.num_voxels == 0
    assert grid.coords.shape == (0, 3)
    assert grid.point_voxel_ids.shape == (0,)
    assert voxel_fisher_vectors(make_cloud(np.zeros((0, 3))), grid).shape == (0, 20, 5, 5, 5)


@pytest.mark.parametrize("voxel_size", [0.0, -0.2, np.nan, np.inf])
def test_invalid_voxel_size_raises(voxel_size):
    with pytest.raises(InputError, match="voxel_size"):
        voxelize(np.zeros((3, 3), np.float32), voxel_size)


def test_invalid_points_raise():
    with pytest.raises(InputError, match="NaN"):
        voxelize(np.array([[0, 0, np.nan]], np.float32), 0.2)
    with pytest.raises(InputError, match="shape"):
        voxelize(np.zeros((3, 2), np.float32), 0.2)


def test_voxel_fisher_vectors_are_finite_and_normalised():
    rng = np.random.default_rng(2)
    points = np.concatenate(
        [
            rng.uniform(0, 1, (400, 3)),  # many points in few cells
            [[5.05, 5.05, 5.05]],  # a voxel with one point
            [[-3.0, 2.0, 1.0], [-3.01, 2.02, 1.03]],  # a voxel with two points
        ]
    )
    cloud = make_cloud(points)
    grid = voxelize(cloud.points, 0.25)
    features = voxel_fisher_vectors(cloud, grid)
    assert features.shape == (grid.num_voxels, 20, 5, 5, 5)
    assert features.dtype == np.float32
    assert np.isfinite(features).all()
    norms = np.linalg.norm(features.reshape(grid.num_voxels, NUM_CHANNELS, NUM_GAUSSIANS), axis=2)
    assert (np.isclose(norms, 1, atol=1e-5) | np.isclose(norms, 0, atol=1e-5)).all()
    single = grid.point_voxel_ids[400]
    assert grid.num_points[single] == 1
    assert np.isfinite(features[single]).all() and norms[single].max() == pytest.approx(1, abs=1e-5)


def test_voxel_fisher_vectors_refuse_a_grid_of_another_cloud():
    cloud = make_cloud(np.random.default_rng(0).uniform(0, 1, (20, 3)))
    grid = voxelize(cloud.points[:10], 0.2)
    with pytest.raises(InputError, match="grid was built from 10 points"):
        voxel_fisher_vectors(cloud, grid)


def test_fisher_vector_colors_are_one_rgb_triple_per_voxel():
    rng = np.random.default_rng(3)
    cloud = make_cloud(rng.uniform(0, 2, (600, 3)))
    grid = voxelize(cloud.points, 0.5)
    features = voxel_fisher_vectors(cloud, grid)
    colors = fisher_vector_colors(features)
    assert colors.shape == (grid.num_voxels, 3) and colors.dtype == np.uint8
    assert colors.max() > colors.min()  # a spread of colours, not one flat value
    # Equal features get equal colours.
    doubled = fisher_vector_colors(np.concatenate([features, features[:1]]))
    np.testing.assert_array_equal(doubled[0], doubled[-1])
    assert fisher_vector_colors(features[:0]).shape == (0, 3)
    assert fisher_vector_colors(features[:1]).shape == (1, 3)


def test_voxel_colors_are_the_colours_of_the_voxels_3dmfv(small_dataset_dir):
    from factorydet_core.detection.detector import Detector
    from factorydet_core.io.dataset import open_dataset
    from factorydet_core.proposals.voxels import fisher_vector_colors, voxel_colors, voxel_fisher_vectors

    detector = Detector("agv")
    result = detector.propose(
        open_dataset(small_dataset_dir).frame(0), params=detector.params.replace(feature="none")
    )
    features = voxel_fisher_vectors(result.cloud, result.grid)
    colours = voxel_colors(result.cloud, result.grid)
    assert colours.shape == (result.grid.num_voxels, 3) and colours.dtype == np.uint8
    np.testing.assert_array_equal(colours, fisher_vector_colors(features))
    np.testing.assert_array_equal(voxel_colors(result.cloud, result.grid, features), colours)
