import numpy as np
import pytest

from factorydet_core.geometry import rotation_z
from factorydet_core.proposals.segment import SegmentationParams, knn_edges, segment
from factorydet_core.types import InputError


def box_surface(centre, size, yaw: float, spacing: float) -> np.ndarray:
    """All six faces of a box, sampled on a grid of about ``spacing``."""
    size = np.asarray(size, float)
    faces = []
    for axis in range(3):
        u_axis, v_axis = [a for a in range(3) if a != axis]
        u, v = np.meshgrid(
            np.linspace(-0.5, 0.5, max(2, round(size[u_axis] / spacing) + 1)),
            np.linspace(-0.5, 0.5, max(2, round(size[v_axis] / spacing) + 1)),
            indexing="ij",
        )
        for side in (-0.5, 0.5):
            face = np.zeros((u.size, 3))
            face[:, u_axis], face[:, v_axis], face[:, axis] = u.ravel(), v.ravel(), side
            faces.append(face * size)
    local = np.unique(np.round(np.concatenate(faces), 9), axis=0)
    return local @ rotation_z(yaw).T + centre


def cylinder_surface(centre, radius: float, height: float, spacing: float) -> np.ndarray:
    """Mantle and both caps of an upright cylinder, sampled every ``spacing``."""
    around = np.linspace(0, 2 * np.pi, round(2 * np.pi * radius / spacing), endpoint=False)
    heights = np.linspace(-height / 2, height / 2, round(height / spacing) + 1)
    a, z = np.meshgrid(around, heights)
    parts = [np.column_stack([radius * np.cos(a.ravel()), radius * np.sin(a.ravel()), z.ravel()])]
    for ring in np.arange(spacing, radius, spacing):
        t = np.linspace(0, 2 * np.pi, round(2 * np.pi * ring / spacing), endpoint=False)
        for cap in (-height / 2, height / 2):
            parts.append(np.column_stack([ring * np.cos(t), ring * np.sin(t), np.full(len(t), cap)]))
    parts.append(np.array([[0, 0, -height / 2], [0, 0, height / 2]]))
    return np.concatenate(parts) + centre


def separated_objects_scene() -> tuple[np.ndarray, np.ndarray]:
    """Six objects (boxes and cylinders) about 1 m apart, 3-4 cm spacing, 3 mm noise, no floor."""
    rng = np.random.default_rng(0)
    objects = [
        box_surface(np.array([0.0, 0.0, 0.5]), (1.2, 0.8, 1.0), 0.3, 0.04),
        box_surface(np.array([2.6, 0.0, 0.4]), (1.0, 1.0, 0.8), -0.5, 0.04),
        cylinder_surface(np.array([4.9, 0.0, 0.45]), 0.3, 0.9, 0.04),
        box_surface(np.array([0.0, 2.5, 0.3]), (1.6, 1.2, 0.6), 0.0, 0.04),
        cylinder_surface(np.array([2.6, 2.6, 0.6]), 0.4, 1.2, 0.04),
        box_surface(np.array([4.9, 2.5, 0.25]), (0.5, 0.5, 0.5), 0.8, 0.03),
    ]
    points = np.concatenate(objects) + rng.normal(0, 0.003, (sum(len(o) for o in objects), 3))
    labels = np.repeat(np.arange(len(objects)), [len(o) for o in objects])
    order = rng.permutation(len(points))
    return points[order].astype(np.float32), labels[order]


def test_scene_objects_are_about_a_metre_apart():
    from scipy.spatial import cKDTree

    points, labels = separated_objects_scene()
    gaps = [
        cKDTree(points[labels == a]).query(points[labels == b])[0].min()
        for a in range(6)
        for b in range(a + 1, 6)
    ]
    assert 0.8 < min(gaps) < 1.3


def test_segment_purity_on_a_scene_of_separated_objects():
    points, labels = separated_objects_scene()
    result = segment(points, SegmentationParams())
    assert result.segment_ids.shape == result.patch_ids.shape == (len(points),)
    assert result.num_segments >= 6
    for seg in range(result.num_segments):
        members = labels[result.segment_ids == seg]
        assert len(members) > 0
        purity = np.bincount(members).max() / len(members)
        assert purity >= 0.95, (seg, purity)
    for obj in range(6):
        coverage = np.bincount(result.segment_ids[labels == obj]).max() / (labels == obj).sum()
        assert coverage >= 0.9, (obj, coverage)


def test_segmentation_is_internally_consistent():
    points, _ = separated_objects_scene()
    result = segment(points, SegmentationParams())
    assert result.patch_ids.min() == 0 and result.patch_ids.max() == result.num_patches - 1
    np.testing.assert_array_equal(result.segment_ids, result.patch_segment_ids[result.patch_ids])
    assert set(np.unique(result.patch_segment_ids)) == set(range(result.num_segments))
    # Every union in the merge history is a set of patches of one final segment.
    for union in result.merge_history:
        assert len(union) >= 2 and list(union) == sorted(set(union))
        assert len(set(result.patch_segment_ids[list(union)].tolist())) == 1


def test_a_gap_wider_than_max_edge_always_separates():
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 1, (600, 2)), np.zeros(600)])
    points = np.concatenate([plane, plane + [1.0 + 0.35, 0, 0]]).astype(np.float32)  # 35 cm gap
    result = segment(points, SegmentationParams(max_edge_m=0.3))
    assert not set(result.segment_ids[:600]) & set(result.segment_ids[600:])


def _sparse_face(distance_m: float) -> np.ndarray:
    """A 1.2 x 2.2 m face ``distance_m`` ahead, sampled as a scanner 0.7 x 1.2 degrees apart would."""
    step_y, step_z = distance_m * np.radians(0.7), distance_m * np.radians(1.2)
    y, z = np.meshgrid(np.arange(-0.6, 0.6, step_y), np.arange(0.1, 2.3, step_z))
    return np.column_stack([np.full(y.size, distance_m), y.ravel(), z.ravel()]).astype(np.float32)


def test_edges_may_grow_with_range_so_far_objects_stay_whole():
    far = _sparse_face(20.0)  # rows 0.42 m apart
    fixed = segment(far, SegmentationParams(max_edge_m=0.3))
    assert fixed.num_segments > 1  # every row is cut from the next
    ranged = segment(far, SegmentationParams(max_edge_m=0.3, max_edge_per_range=0.04))
    assert ranged.num_segments == 1
    # Near the viewer the fixed limit still rules: the same gap separates there.
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 1, (600, 2)), np.zeros(600)]) + [2.0, 0, 0]
    points = np.concatenate([plane, plane + [1.0 + 0.35, 0, 0]]).astype(np.float32)
    result = segment(points, SegmentationParams(max_edge_m=0.3, max_edge_per_range=0.04))
    assert not set(result.segment_ids[:600]) & set(result.segment_ids[600:])


def test_knn_edges_take_the_smaller_limit_of_both_ends():
    # Points 0 and 1 are 0.5 m apart; point 1's limit admits that, point 0's does not.
    neighbours = np.array([[1], [0]], np.uint32)
    sq_distances = np.array([[0.25], [0.25]], np.float32)
    source, _, _ = knn_edges(neighbours, sq_distances, 1, np.array([0.3, 0.6]))
    assert len(source) == 0
    source, target, length = knn_edges(neighbours, sq_distances, 1, np.array([0.6, 0.6]))
    assert source.tolist() == [0] and target.tolist() == [1] and length == pytest.approx([0.5])


@pytest.mark.parametrize("num_points", [0, 1, 2, 3])
def test_tiny_inputs_do_not_crash(num_points):
    points = np.array([[0, 0, 0], [0.05, 0, 0], [5, 5, 5]], np.float32)[:num_points]
    result = segment(points, SegmentationParams())
    assert result.patch_ids.shape == result.segment_ids.shape == (num_points,)
    if num_points:
        assert result.num_patches >= 1 and result.num_segments >= 1
        assert result.segment_ids.max() < result.num_segments
    else:
        assert result.num_patches == result.num_segments == 0
    if num_points == 3:  # the far point is its own patch
        assert result.patch_ids[2] != result.patch_ids[0] and result.patch_ids[0] == result.patch_ids[1]


def test_duplicated_points_do_not_crash():
    rng = np.random.default_rng(2)
    points = np.repeat(rng.uniform(0, 1, (40, 3)), 3, axis=0).astype(np.float32)
    result = segment(points, SegmentationParams())
    assert result.segment_ids.shape == (120,)


@pytest.mark.parametrize(
    "changes",
    [
        {"k_features": 0},
        {"k_graph": 0},
        {"min_patch_points": 0},
        {"max_edge_m": 0.0},
        {"max_edge_m": -1.0},
        {"regularization": 0.0},
        {"merge_threshold": -0.1},
        {"merge_threshold": 1.5},
        {"spatial_weight": -1.0},
        {"max_edge_per_range": -0.01},
        {"max_edge_per_range": float("nan")},
    ],
)
def test_invalid_params_raise(changes):
    name = next(iter(changes))
    with pytest.raises(InputError, match=name):
        SegmentationParams(**changes)


def test_invalid_points_raise():
    with pytest.raises(InputError, match="NaN"):
        segment(np.array([[0, 0, np.nan]] * 5, np.float32))
    with pytest.raises(InputError, match="shape"):
        segment(np.zeros((5, 2), np.float32))


def test_convexity_keeps_an_object_apart_from_what_it_stands_on():
    from factorydet_core.proposals.segment import SegmentationParams, _mergeable_connections

    rng = np.random.default_rng(5)
    # A crate's front face at y = -2 (facing the viewer at the origin), its top (+z) behind it, and
    # the shelf it stands on, reaching out in front of it at the crate's bottom.
    front = np.column_stack([rng.uniform(-0.3, 0.3, 300), np.full(300, -2.0), rng.uniform(0.5, 1.0, 300)])
    top = np.column_stack([rng.uniform(-0.3, 0.3, 300), rng.uniform(-2.6, -2.0, 300), np.full(300, 1.0)])
    shelf = np.column_stack([rng.uniform(-0.3, 0.3, 300), rng.uniform(-2.0, -1.4, 300), np.full(300, 0.5)])
    points = np.concatenate([front, top, shelf]).astype(np.float32)
    patch_ids = np.repeat([0, 1, 2], 300)
    source = np.array([0, 300, 0])  # front-top, top-... (point indices)
    target = np.array([300, 0, 600])  # front-top (again), front-shelf
    keep = _mergeable_connections(points, patch_ids, source, target, SegmentationParams())
    assert keep[0] and keep[1], "the crate's front and top meet at a convex edge"
    assert not keep[2], "the crate and the shelf it stands on meet at a concave edge"


def _flush_stacks() -> tuple[np.ndarray, np.ndarray]:
    """Two columns of three crates of one footprint, flush side by side and on top of each other,
    seen as a sensor sees them: the fronts, the tops of the columns and one outer side."""
    parts = [
        box_surface(np.array([x, 0.0, z]), (0.8, 0.5, height), 0.0, 0.04)
        for x in (0.0, 0.8)
        for z, height in ((0.2, 0.4), (0.6, 0.4), (0.95, 0.3))
    ]
    labels = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
    points, first = np.unique(np.round(np.concatenate(parts), 6), axis=0, return_index=True)
    labels = labels[first]
    visible = (points[:, 1] < -0.24) | (points[:, 2] > 1.09) | (points[:, 0] < -0.39)
    rng = np.random.default_rng(0)
    points = points[visible] + rng.normal(0, 0.003, (int(visible.sum()), 3))
    return points.astype(np.float32), labels[visible]


def _best_point_iou(segmentation, labels: np.ndarray) -> np.ndarray:
    from factorydet_core.proposals.candidates import candidate_patch_sets, point_sets

    sets, _ = candidate_patch_sets(segmentation)
    lists = point_sets(segmentation.patch_ids, sets)
    best = []
    for label in np.unique(labels):
        own = labels == label
        best.append(max(own[m].sum() / (own.sum() + len(m) - own[m].sum()) for m in lists))
    return np.array(best)


def test_crate_sized_passes_propose_crates_of_a_flush_stack():
    points, labels = _flush_stacks()
    without = segment(points, SegmentationParams(proposal_sizes_m=()))
    with_sizes = segment(points, SegmentationParams())
    # The extra passes only add candidates.
    assert set(without.merge_history) <= set(with_sizes.merge_history)
    found_without = (_best_point_iou(without, labels) >= 0.6).sum()
    found_with = (_best_point_iou(with_sizes, labels) >= 0.6).sum()
    assert found_with >= 4, "most crates of the stack get a proposal of their own"
    assert found_with > found_without


@pytest.mark.parametrize("sizes", [[[1.0, 0.0]], [1.0], [[1.0, 0.5, 0.2]], 3.0])
def test_invalid_proposal_sizes_raise(sizes):
    with pytest.raises(InputError, match="proposal_sizes_m"):
        SegmentationParams(proposal_sizes_m=sizes)


def test_every_merge_pass_starts_from_the_same_patches():
    """The passes share the patches' adjacency and bounds; none may see another's merges."""
    import dataclasses

    from factorydet_core.proposals.segment import merge_patches, over_segment

    points, _ = _flush_stacks()
    params = SegmentationParams(patch_regularizations=())
    patch_ids, structure_mask, (source, target, _), _ = over_segment(points, params)
    assert not structure_mask.any()
    expected = merge_patches(points, patch_ids, source, target, params)[1]
    sizes = [(scale, params.max_object_size_m[1]) for scale in params.proposal_scales_m]
    for size in sizes + list(params.proposal_sizes_m):
        alone = dataclasses.replace(params, max_object_size_m=size)
        expected += merge_patches(points, patch_ids, source, target, alone)[1]
    assert segment(points, params).merge_history == expected


def _wall_and_crate() -> np.ndarray:
    """A wall 8 m long and 3 m high, and a crate standing 1 m in front of it."""
    rng = np.random.default_rng(1)
    x, z = np.meshgrid(np.arange(-4, 4, 0.05), np.arange(0.05, 3, 0.05))
    wall = np.column_stack([x.ravel(), np.zeros(x.size), z.ravel()])
    crate = box_surface(np.array([0.0, -1.4, 0.3]), (0.8, 0.6, 0.6), 0.3, 0.04)
    points = np.concatenate([wall, crate]) + rng.normal(0, 0.003, (len(wall) + len(crate), 3))
    return points.astype(np.float32)


def test_structure_keeps_the_first_pass_surfaces_as_patches_unless_split():
    points = _wall_and_crate()
    whole = segment(points, SegmentationParams())
    split = segment(points, SegmentationParams(split_structure=True))
    on_wall = np.abs(points[:, 1]) < 0.05
    structure = whole.patch_is_structure[whole.patch_ids]
    # The same structure either way: most of the wall (its rim's local shape is not a plane's),
    # nothing of the crate.
    np.testing.assert_array_equal(structure, split.patch_is_structure[split.patch_ids])
    assert structure[on_wall].mean() > 0.9 and not structure[~on_wall].any()
    # The first pass's few wall surfaces, against the second pass's hundreds of patches.
    assert whole.patch_is_structure.sum() <= 5 < 100 < split.patch_is_structure.sum()
    # The crate is still proposed whole.
    is_crate = points[:, 1] < -0.5
    for segmentation in (whole, split):
        assert _best_point_iou(segmentation, is_crate.astype(int))[1] > 0.95
