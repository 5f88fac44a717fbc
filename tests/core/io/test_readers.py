"""Tests of ``factorydet_core.io.readers``: real scenes, round trips per format, bad input."""

from __future__ import annotations

import struct
import tempfile
from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factorydet_core.geometry import points_in_box
from factorydet_core.io.npz import save_npz
from factorydet_core.io.readers import SUPPORTED_SUFFIXES, read_frame, write_frame
from factorydet_core.types import BoxLabels, Frame, InputError

REAL_DIR = Path(__file__).resolve().parents[4] / "shared" / "data" / "real"
requires_real = pytest.mark.skipif(
    not REAL_DIR.is_dir(), reason=f"shared real data folder {REAL_DIR} is missing"
)

# (file, points, boxes) from the table of shared/data/real/README.md
REAL_SCENES = [
    ("scannet_scene0000_00.npz", 81_369, 27),
    ("scannet_scene0000_01.npz", 80_583, 29),
    ("scannet_scene0000_02.npz", 86_001, 28),
    ("s3dis_Area_1_office_2_100pts.npz", 100, 9),
    ("labelcloud_exemplary.npz", 86_357, 1),
    ("sustechpoints_000950_outdoor.npz", 68_242, 19),
    ("sustechpoints_000965_outdoor.npz", 66_781, 21),
    ("sustechpoints_000970_outdoor.npz", 66_899, 23),
    ("sustechpoints_000975_outdoor.npz", 67_153, 24),
]

# Formats that keep colours / intensity, and the coordinate precision of each format (metres).
KEEPS_COLORS = {".ply", ".pcd", ".xyz", ".txt", ".pts", ".csv", ".las", ".laz", ".npz"}
KEEPS_INTENSITY = {".ply", ".pcd", ".xyz", ".txt", ".pts", ".csv", ".las", ".laz", ".bin", ".npy", ".npz"}
PRECISION = {".xyz": 2e-6, ".txt": 2e-6, ".pts": 2e-6, ".csv": 2e-6, ".las": 1e-4, ".laz": 1e-4}


def make_frame(
    num: int = 500,
    *,
    seed: int = 0,
    colors: bool = True,
    intensity: bool = True,
    offset: np.ndarray | None = None,
) -> Frame:
    """A seeded random one-sensor frame with two labelled boxes."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-20, 20, size=(num, 3)).astype(np.float32)
    near = min(num, 40)
    points[:near] = rng.uniform(-0.5, 0.5, size=(near, 3)) + np.array([5.0, 5.0, 1.0])
    boxes = np.array([[5.0, 5.0, 1.0, 1.2, 1.2, 1.2, 0.3], [-5.0, 2.0, 0.5, 2.0, 1.0, 1.0, -1.0]])
    inside = [points_in_box(points, box) for box in boxes]
    point_instance_ids = np.where(inside[0], 1, np.where(inside[1], 2, 0))
    return Frame(
        name="random",
        points=points,
        sensor_ids=np.zeros(num, np.int16),
        T_vehicle_sensor=np.eye(4)[None],
        T_world_vehicle=np.eye(4),
        labels=BoxLabels(
            boxes=boxes,
            class_ids=np.array([4, 5]),
            instance_ids=np.array([1, 2]),
            num_points=np.array([m.sum() for m in inside]),
        ),
        point_instance_ids=point_instance_ids,
        colors=rng.integers(0, 256, size=(num, 3), dtype=np.uint8) if colors else None,
        intensity=rng.integers(0, 256, size=num).astype(np.float32) if intensity else None,
        origin_offset=np.zeros(3) if offset is None else offset,
    )


def world(frame: Frame) -> np.ndarray:
    return frame.points.astype(np.float64) + frame.origin_offset


def check_input_error(path: Path, **kwargs) -> str:
    """Read ``path``, expect an InputError with one line naming the file; return the message."""
    with pytest.raises(InputError) as info:
        read_frame(path, **kwargs)
    message = str(info.value)
    assert path.name in message
    assert str(path) in message
    assert "\n" not in message
    assert "Traceback" not in message
    return message


# ------------------------------------------------------------------------------------------------
# Real scenes
# ------------------------------------------------------------------------------------------------


@requires_real
@pytest.mark.parametrize(("file_name", "num_points", "num_boxes"), REAL_SCENES)
def test_real_scene_opens(file_name: str, num_points: int, num_boxes: int) -> None:
    frame = read_frame(REAL_DIR / file_name)
    assert frame.name == file_name
    assert frame.num_points == num_points
    assert len(frame.labels) == num_boxes > 0
    assert frame.points.dtype == np.float32
    assert np.all(frame.sensor_ids == 0)
    np.testing.assert_array_equal(frame.T_vehicle_sensor, np.eye(4)[None])
    np.testing.assert_array_equal(frame.T_world_vehicle, np.eye(4))
    np.testing.assert_array_equal(frame.origin_offset, np.zeros(3))
    np.testing.assert_array_equal(frame.labels.instance_ids, np.arange(1, num_boxes + 1))
    with np.load(REAL_DIR / file_name) as archive:
        labels = archive["labels"].tolist()
        np.testing.assert_allclose(frame.labels.boxes, archive["boxes"], atol=1e-6)
    assert frame.class_names == tuple(sorted(set(labels)))
    assert [frame.class_names[i] for i in frame.labels.class_ids] == labels
    if not file_name.startswith("s3dis"):
        assert frame.labels.num_points.min() >= 1
    # Each point carries the id of the first box that contains it.
    for i, box in enumerate(frame.labels.boxes):
        inside = points_in_box(frame.points, box)
        assert inside.sum() == frame.labels.num_points[i]
        assert np.all(frame.point_instance_ids[inside] <= i + 1)
        assert np.all(frame.point_instance_ids[inside] > 0)
    labelled = frame.point_instance_ids > 0
    assert np.all(frame.point_class_ids[labelled] >= 0)
    assert np.all(frame.point_class_ids[~labelled] == -1)


@requires_real
def test_real_scene_colours_and_intensity() -> None:
    scannet = read_frame(REAL_DIR / "scannet_scene0000_00.npz")
    assert scannet.colors is not None and scannet.colors.shape == (81_369, 3)
    assert scannet.intensity is None
    sustech = read_frame(REAL_DIR / "sustechpoints_000950_outdoor.npz")
    assert sustech.colors is None
    assert sustech.intensity is not None and sustech.intensity.shape == (68_242,)


@requires_real
def test_real_scene_with_given_vocabulary() -> None:
    names = ["person", "cart", "box"]
    frame = read_frame(REAL_DIR / "labelcloud_exemplary.npz", class_names=names)
    assert frame.class_names == tuple(names)
    assert frame.labels.class_ids.tolist() == [1]
    path = REAL_DIR / "sustechpoints_000950_outdoor.npz"
    message = check_input_error(path, class_names=["Car", "Bus"])
    assert "Pedestrian" in message and "Car" in message


@requires_real
def test_real_scene_round_trip_keeps_boxes(tmp_path: Path) -> None:
    frame = read_frame(REAL_DIR / "sustechpoints_000950_outdoor.npz")
    write_frame(tmp_path / "copy.npz", frame)
    again = read_frame(tmp_path / "copy.npz")
    np.testing.assert_array_equal(again.points, frame.points)
    np.testing.assert_array_equal(again.intensity, frame.intensity)
    np.testing.assert_allclose(again.labels.boxes, frame.labels.boxes)
    np.testing.assert_array_equal(again.labels.num_points, frame.labels.num_points)
    np.testing.assert_array_equal(again.point_instance_ids, frame.point_instance_ids)


# ------------------------------------------------------------------------------------------------
# Round trips
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", SUPPORTED_SUFFIXES)
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    frame = make_frame()
    path = tmp_path / f"cloud{suffix}"
    write_frame(path, frame)
    again = read_frame(path)
    assert again.name == path.name
    assert again.num_points == frame.num_points
    np.testing.assert_allclose(world(again), world(frame), rtol=0, atol=PRECISION.get(suffix, 0.0))
    if suffix in KEEPS_COLORS:
        np.testing.assert_array_equal(again.colors, frame.colors)
    else:
        assert again.colors is None
    if suffix in KEEPS_INTENSITY:
        np.testing.assert_array_equal(again.intensity, frame.intensity)
    if suffix == ".npz":
        np.testing.assert_allclose(again.labels.boxes, frame.labels.boxes)
        assert [again.class_names[i] for i in again.labels.class_ids] == ["pallet", "person"]
        np.testing.assert_array_equal(again.point_instance_ids, frame.point_instance_ids)
        np.testing.assert_array_equal(again.labels.num_points, frame.labels.num_points)
    else:
        assert len(again.labels) == 0
        assert np.all(again.point_instance_ids == 0)


@pytest.mark.parametrize("suffix", SUPPORTED_SUFFIXES)
def test_round_trip_without_colours_or_intensity(tmp_path: Path, suffix: str) -> None:
    frame = make_frame(120, seed=3, colors=False, intensity=False)
    path = tmp_path / f"plain{suffix}"
    write_frame(path, frame)
    again = read_frame(path)
    np.testing.assert_allclose(world(again), world(frame), rtol=0, atol=PRECISION.get(suffix, 0.0))
    assert again.colors is None
    if suffix == ".bin":
        np.testing.assert_array_equal(again.intensity, np.zeros(120, np.float32))
    elif suffix not in (".las", ".laz"):  # LAS always has an intensity dimension
        assert again.intensity is None


def test_upper_case_suffix(tmp_path: Path) -> None:
    frame = make_frame(50)
    write_frame(tmp_path / "CLOUD.PLY", frame)
    again = read_frame(tmp_path / "CLOUD.PLY")
    np.testing.assert_array_equal(again.points, frame.points)


def write_georeferenced_las(path: Path, num: int = 2000, seed: int = 1) -> np.ndarray:
    """Write a LAS file at UTM-like coordinates (scale 1 mm); return the (N, 3) float64 coordinates."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack(
        [
            rng.uniform(412_300.0, 412_380.0, num),
            rng.uniform(5_012_700.0, 5_012_760.0, num),
            rng.uniform(95.0, 110.0, num),
        ]
    )
    xyz = np.round(xyz, 3)
    header = laspy.LasHeader(point_format=2, version="1.2")
    header.scales = np.full(3, 0.001)
    header.offsets = np.array([412_000.0, 5_012_000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = rng.integers(0, 4000, num).astype(np.uint16)
    colors = rng.integers(0, 256, (num, 3)).astype(np.uint16) * 256
    las.red, las.green, las.blue = colors[:, 0], colors[:, 1], colors[:, 2]
    las.write(str(path))
    return xyz


@pytest.mark.parametrize("suffix", [".las", ".laz", ".ply", ".npz", ".pcd", ".npy", ".xyz"])
def test_georeferenced_las_round_trip(tmp_path: Path, suffix: str) -> None:
    source = tmp_path / "survey.las"
    xyz = write_georeferenced_las(source)
    frame = read_frame(source)
    assert np.abs(frame.points).max() < 100.0
    assert np.all(frame.origin_offset != 0)
    np.testing.assert_array_equal(frame.origin_offset, np.round(frame.origin_offset))
    np.testing.assert_allclose(world(frame), xyz, rtol=0, atol=1e-3)
    with laspy.open(source) as reader:
        red = reader.read().red
    np.testing.assert_array_equal(frame.colors[:, 0], red >> 8)

    copy = tmp_path / f"copy{suffix}"
    write_frame(copy, frame)
    again = read_frame(copy)
    np.testing.assert_allclose(world(again), xyz, rtol=0, atol=1e-3)
    if suffix in (".las", ".laz"):
        with laspy.open(copy) as reader:
            data = reader.read()
        np.testing.assert_allclose(np.column_stack([data.x, data.y, data.z]), xyz, rtol=0, atol=1e-3)
        np.testing.assert_array_equal(again.colors, frame.colors)
        np.testing.assert_array_equal(again.intensity, frame.intensity)


def test_georeferenced_npz_boxes_share_the_offset(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-10, 10, (300, 3)) + np.array([412_345.0, 5_012_345.0, 100.0])
    box = np.array([[412_345.0, 5_012_345.0, 100.0, 6.0, 6.0, 6.0, 0.2]])
    path = tmp_path / "geo.npz"
    save_npz(path, {"points": points, "boxes": box, "labels": np.array(["box"])})
    frame = read_frame(path)
    expected_inside = points_in_box(points - box[0, :3], np.r_[0, 0, 0, box[0, 3:]])
    assert frame.labels.num_points[0] == expected_inside.sum() > 0
    np.testing.assert_allclose(frame.labels.boxes[0, :3] + frame.origin_offset, box[0, :3])
    write_frame(tmp_path / "geo_copy.npz", frame)
    with np.load(tmp_path / "geo_copy.npz") as archive:
        np.testing.assert_allclose(archive["points"], points, rtol=0, atol=1e-3)
        np.testing.assert_allclose(archive["boxes"], box, rtol=0, atol=1e-9)


def test_writer_applies_sensor_extrinsic(tmp_path: Path) -> None:
    base = make_frame(60, colors=False, intensity=False)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    moved = Frame(
        name="moved",
        points=base.points,
        sensor_ids=np.zeros(60, np.int16),
        T_vehicle_sensor=T[None],
        T_world_vehicle=np.eye(4),
        labels=BoxLabels.empty(),
        point_instance_ids=np.zeros(60, np.int64),
    )
    write_frame(tmp_path / "moved.ply", moved)
    again = read_frame(tmp_path / "moved.ply")
    np.testing.assert_allclose(again.points, base.points + np.float32([1, 2, 3]), atol=1e-6)


@settings(max_examples=20, deadline=None)
@given(
    num=st.integers(1, 60),
    seed=st.integers(0, 2**16),
    suffix=st.sampled_from([".ply", ".pcd", ".xyz", ".npy", ".bin"]),
)
def test_round_trip_property(num: int, seed: int, suffix: str) -> None:
    frame = make_frame(num, seed=seed)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"p{suffix}"
        write_frame(path, frame)
        again = read_frame(path)
    np.testing.assert_allclose(world(again), world(frame), rtol=0, atol=PRECISION.get(suffix, 0.0))


# ------------------------------------------------------------------------------------------------
# Hand-written files in the formats other tools write
# ------------------------------------------------------------------------------------------------


def test_ascii_ply_with_faces(tmp_path: Path) -> None:
    path = tmp_path / "mesh.ply"
    path.write_text(
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\n"
        "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property float scalar_Intensity\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n"
        "0 0 0 255 0 0 1.5\n1 0 0 0 255 0 2.5\n0 1 0.5 0 0 255 3.5\n3 0 1 2\n"
    )
    frame = read_frame(path)
    np.testing.assert_array_equal(frame.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]])
    np.testing.assert_array_equal(frame.colors, [[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    np.testing.assert_array_equal(frame.intensity, [1.5, 2.5, 3.5])


def test_big_endian_ply_with_extra_properties(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    dtype = np.dtype(
        [
            ("x", ">f4"),
            ("y", ">f4"),
            ("z", ">f4"),
            ("nx", ">f4"),
            ("intensity", ">u2"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
        ]
    )
    records = np.zeros(30, dtype)
    for name in ("x", "y", "z", "nx"):
        records[name] = rng.normal(size=30)
    records["intensity"] = rng.integers(0, 60000, 30)
    for name in ("red", "green", "blue"):
        records[name] = rng.integers(0, 256, 30)
    header = (
        "ply\r\nformat binary_big_endian 1.0\r\nelement vertex 30\r\nproperty float x\r\nproperty float y\r\n"
        "property float z\r\nproperty float nx\r\nproperty ushort intensity\r\nproperty uchar red\r\n"
        "property uchar green\r\nproperty uchar blue\r\nend_header\r\n"
    )
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + records.tobytes())
    frame = read_frame(path)
    np.testing.assert_array_equal(frame.points[:, 0], records["x"].astype(np.float32))
    np.testing.assert_array_equal(frame.intensity, records["intensity"].astype(np.float32))
    np.testing.assert_array_equal(frame.colors[:, 2], records["blue"])


def test_pcd_with_48_byte_records(tmp_path: Path) -> None:
    """A Hesai-style layout as in SUSTechPOINTS: x y z, 4 padding bytes, intensity at 16, extras."""
    rng = np.random.default_rng(5)
    dtype = np.dtype(
        [
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("pad0", "u1", (4,)),
            ("intensity", "<f4"),
            ("pad1", "u1", (4,)),
            ("timestamp", "<f8"),
            ("ring", "<u2"),
            ("pad2", "u1", (14,)),
        ]
    )
    assert dtype.itemsize == 48
    records = np.zeros(100, dtype)
    for name in ("x", "y", "z"):
        records[name] = rng.uniform(-80, 80, 100)
    records["intensity"] = rng.integers(0, 256, 100)
    records["timestamp"] = 1.6e9 + np.arange(100)
    records["ring"] = np.arange(100) % 32
    records["pad0"] = 255
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        "FIELDS x y z _ intensity _ timestamp ring _\n"
        "SIZE 4 4 4 1 4 1 8 2 1\nTYPE F F F U F U F U U\nCOUNT 1 1 1 4 1 4 1 1 14\nWIDTH 100\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 100\nDATA binary\n"
    )
    path = tmp_path / "000950.pcd"
    path.write_bytes(header.encode() + records.tobytes())
    frame = read_frame(path)
    np.testing.assert_array_equal(frame.points, np.column_stack([records[a] for a in "xyz"]))
    np.testing.assert_array_equal(frame.intensity, records["intensity"])
    assert frame.colors is None


def test_ascii_pcd_with_packed_float_rgb(tmp_path: Path) -> None:
    packed = [(255 << 16) | (128 << 8) | 7, (1 << 16) | (2 << 8) | 3]
    as_float = [struct.unpack("<f", struct.pack("<I", value))[0] for value in packed]
    lines = [f"1.5 2.5 3.5 10 {as_float[0]!r}", f"-1 -2 -3 20 {as_float[1]!r}"]
    path = tmp_path / "rgb.pcd"
    path.write_text(
        "VERSION .7\nFIELDS x y z intensity rgb\nSIZE 4 4 4 4 4\nTYPE F F F F F\nCOUNT 1 1 1 1 1\n"
        "WIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n" + "\n".join(lines) + "\n"
    )
    frame = read_frame(path)
    np.testing.assert_array_equal(frame.points, [[1.5, 2.5, 3.5], [-1, -2, -3]])
    np.testing.assert_array_equal(frame.colors, [[255, 128, 7], [1, 2, 3]])
    np.testing.assert_array_equal(frame.intensity, [10, 20])


def test_binary_compressed_pcd_via_open3d(tmp_path: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(6)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-5, 5, (200, 3))))
    cloud.colors = o3d.utility.Vector3dVector(rng.integers(0, 256, (200, 3)) / 255.0)
    path = tmp_path / "compressed.pcd"
    assert o3d.io.write_point_cloud(str(path), cloud, compressed=True)
    assert b"binary_compressed" in path.read_bytes()[:400]
    frame = read_frame(path)
    np.testing.assert_allclose(frame.points, np.asarray(cloud.points), atol=1e-5)
    np.testing.assert_array_equal(frame.colors, np.round(np.asarray(cloud.colors) * 255).astype(np.uint8))


def test_text_formats(tmp_path: Path) -> None:
    csv = tmp_path / "scan.csv"
    csv.write_text("//X,Y,Z,Intensity,R,G,B\n1,2,3,0.5,10,20,30\n4, 5, 6, 0.25, 40, 50, 60\n")
    frame = read_frame(csv)
    np.testing.assert_array_equal(frame.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(frame.intensity, [0.5, 0.25])
    np.testing.assert_array_equal(frame.colors, [[10, 20, 30], [40, 50, 60]])

    pts = tmp_path / "leica.pts"
    pts.write_text("2\n1 2 3 -100 255 0 0\n4 5 6 200 0 255 0\n")
    frame = read_frame(pts)
    np.testing.assert_array_equal(frame.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(frame.intensity, [-100, 200])
    np.testing.assert_array_equal(frame.colors, [[255, 0, 0], [0, 255, 0]])

    xyz = tmp_path / "plain.xyz"
    xyz.write_text("# exported\n1 2 3 0.1 0.2 0.3\n\n4\t5\t6 1.0 0.0 0.5\n")
    frame = read_frame(xyz)
    np.testing.assert_array_equal(frame.colors, [[26, 51, 76], [255, 0, 128]])
    assert frame.intensity is None

    normals = tmp_path / "normals.txt"
    normals.write_text("1 2 3 -0.5 0.5 0.7\n4 5 6 0.1 -0.9 0.1\n")
    assert read_frame(normals).colors is None


def test_kitti_bin(tmp_path: Path) -> None:
    values = np.random.default_rng(7).uniform(-30, 30, (64, 4)).astype(np.float32)
    path = tmp_path / "000000.bin"
    values.tofile(path)
    frame = read_frame(path)
    np.testing.assert_array_equal(frame.points, values[:, :3])
    np.testing.assert_array_equal(frame.intensity, values[:, 3])


def test_npz_without_boxes_and_point_instance_ids(tmp_path: Path) -> None:
    path = tmp_path / "unlabelled.npz"
    save_npz(path, {"points": np.zeros((5, 3), np.float32)})
    frame = read_frame(path)
    assert len(frame.labels) == 0 and frame.num_points == 5

    overlap = tmp_path / "overlap.npz"
    points = np.array([[0, 0, 0], [0.9, 0, 0], [5, 5, 5]], np.float32)
    boxes = np.array([[0, 0, 0, 1, 1, 1, 0], [0.5, 0, 0, 1, 1, 1, 0]], np.float32)
    save_npz(overlap, {"points": points, "boxes": boxes, "labels": np.array(["b", "a"])})
    frame = read_frame(overlap)
    assert frame.class_names == ("a", "b")
    assert frame.labels.class_ids.tolist() == [1, 0]
    assert frame.point_instance_ids.tolist() == [1, 2, 0]
    assert frame.labels.num_points.tolist() == [1, 2]
    assert frame.point_class_ids.tolist() == [1, 0, -1]


def test_write_unsupported_suffix(tmp_path: Path) -> None:
    path = tmp_path / "cloud.e57"
    with pytest.raises(InputError, match="cloud.e57"):
        write_frame(path, make_frame(10))
    assert not path.exists()


@pytest.mark.parametrize("suffix", SUPPORTED_SUFFIXES)
def test_write_into_missing_folder(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / "no_such_folder" / f"cloud{suffix}"
    with pytest.raises(InputError) as info:
        write_frame(path, make_frame(10))
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------


def _ply_header(num: int, fmt: str = "binary_little_endian", props: str = "x y z") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {num}"]
    lines += [f"property float {name}" for name in props.split()]
    return ("\n".join([*lines, "end_header"]) + "\n").encode()


def _pcd_header(num: int, mode: str = "binary", fields: str = "x y z", sizes: str | None = None) -> bytes:
    count = len(fields.split())
    sizes = sizes or " ".join(["4"] * count)
    return (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {' '.join(['F'] * count)}\n"
        f"COUNT {' '.join(['1'] * count)}\nWIDTH {num}\nHEIGHT 1\nPOINTS {num}\nDATA {mode}\n"
    ).encode()


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    save_npz(path, arrays)
    return path


def _npz_scene(path: Path, **changes: np.ndarray | None) -> Path:
    arrays = {
        "points": np.random.default_rng(0).uniform(-1, 1, (10, 3)).astype(np.float32),
        "boxes": np.array([[0, 0, 0, 1, 1, 1, 0], [0.5, 0.5, 0, 1, 1, 1, 0]], np.float32),
        "labels": np.array(["box", "pallet"]),
    }
    arrays.update(changes)
    return _npz(path, **{key: value for key, value in arrays.items() if value is not None})


def _write(name: str, content: bytes | str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / name
        if isinstance(content, str):
            path.write_text(content)
        else:
            path.write_bytes(content)
        return path

    return make


def _truncated(name: str, cut: int) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / name
        write_frame(path, make_frame(200))
        data = path.read_bytes()
        path.write_bytes(data[:cut] if cut > 0 else data[:cut])
        return path

    return make


def _npy(name: str, array: np.ndarray) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / name
        np.save(path, array)
        return path

    return make


NAN_POINTS = np.zeros((6, 3))
NAN_POINTS[1, 0] = np.nan
NAN_POINTS[4, 2] = np.inf

BAD_INPUTS: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing file": (lambda folder: folder / "nothing_here.ply", "not found"),
    "unknown suffix": (_write("scan.e57", b"abc"), ".ply"),
    "no suffix": (_write("scan", b"abc"), "supported"),
    "directory": (lambda folder: (folder / "dir.ply").mkdir() or folder / "dir.ply", "not a regular file"),
    "ply not ply": (_write("bad.ply", b"hello\nworld\n"), "not a PLY"),
    "ply no end_header": (_write("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 1\n"), "header"),
    "ply bad format": (_write("bad.ply", b"ply\nformat binary_middle_endian 1.0\nend_header\n"), "header"),
    "ply unknown property type": (
        _write("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n1\n"),
        "header",
    ),
    "ply no vertex": (_write("bad.ply", b"ply\nformat ascii 1.0\nelement face 0\nend_header\n"), "vertex"),
    "ply missing z": (_write("bad.ply", _ply_header(1, "ascii", "x y") + b"1 2\n"), "z"),
    "ply truncated binary": (_truncated("cut.ply", -100), "truncated"),
    "ply truncated ascii": (_write("cut.ply", _ply_header(3, "ascii") + b"1 2 3\n4 5 6\n"), "truncated"),
    "ply corrupt ascii": (_write("bad.ply", _ply_header(2, "ascii") + b"1 2 3\n4 five 6\n"), "corrupt"),
    "ply empty": (_write("empty.ply", _ply_header(0)), "0 points"),
    "ply inf": (
        _write("inf.ply", _ply_header(2) + np.array([[0, 0, 0], [np.inf, 0, 0]], "<f4").tobytes()),
        "1 of 2",
    ),
    "pcd truncated binary": (_truncated("cut.pcd", -10), "truncated"),
    "pcd no DATA": (_write("bad.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"), "header"),
    "pcd field mismatch": (_write("bad.pcd", _pcd_header(1, sizes="4 4") + bytes(12)), "header"),
    "pcd bad size": (_write("bad.pcd", _pcd_header(1, sizes="4 4 3") + bytes(12)), "unsupported field type"),
    "pcd bad width": (
        _write("bad.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH many\nDATA ascii\n"),
        "header",
    ),
    "pcd no x": (_write("bad.pcd", _pcd_header(1, fields="a b c") + bytes(12)), "x/y/z"),
    "pcd unknown mode": (_write("bad.pcd", _pcd_header(1, mode="zipped") + bytes(12)), "DATA"),
    "pcd corrupt ascii": (_write("bad.pcd", _pcd_header(2, mode="ascii") + b"1 2 3\n4 5\n"), "corrupt"),
    "pcd truncated ascii": (_write("bad.pcd", _pcd_header(3, mode="ascii") + b"1 2 3\n"), "truncated"),
    "pcd compressed short body": (
        _write("bad.pcd", _pcd_header(5, mode="binary_compressed") + b"\x01" * 7),
        "truncated PCD",
    ),
    "pcd compressed garbage": (
        _write("bad.pcd", _pcd_header(5, mode="binary_compressed") + struct.pack("<II", 7, 60) + b"\x01" * 7),
        "open3d",
    ),
    "pcd nan": (
        _write("nan.pcd", _pcd_header(3) + np.array([[0, 0, 0], [np.nan] * 3, [1, 1, 1]], "<f4").tobytes()),
        "1 of 3",
    ),
    "xyz two columns": (_write("bad.xyz", "1 2\n3 4\n"), "3 columns"),
    "xyz ragged": (_write("bad.xyz", "1 2 3\n4 5 6 7\n"), "corrupt"),
    "xyz words": (_write("bad.txt", "1 2 3\n4 five 6\n"), "corrupt"),
    "xyz empty": (_write("empty.xyz", "# only a comment\n"), "0 points"),
    "csv nan": (_write("nan.csv", "1,2,3\nnan,2,3\n4,5,inf\n"), "2 of 3"),
    "pts only count": (_write("empty.pts", "0\n"), "0 points"),
    "las garbage": (_write("bad.las", b"LASF" + bytes(50)), "LAS"),
    "las not las": (_write("bad.las", b"this is not a las file at all" * 20), "LAS"),
    "las truncated": (_truncated("cut.las", 2000), "LAS"),
    "laz truncated": (_truncated("cut.laz", 600), "LAZ"),
    "kitti size": (_write("0001.bin", bytes(30)), "multiple of 16"),
    "kitti empty": (_write("0002.bin", b""), "0 points"),
    "npy two columns": (_npy("two.npy", np.zeros((4, 2), np.float32)), "(N, 3)"),
    "npy 1-d": (_npy("flat.npy", np.zeros(12, np.float32)), "(N, 3)"),
    "npy strings": (_npy("words.npy", np.array([["a", "b", "c"]])), "(N, 3)"),
    "npy garbage": (_write("bad.npy", b"not numpy at all"), "not a .npy"),
    "npy truncated": (_truncated("cut.npy", 300), "corrupt"),
    "npy empty": (_npy("empty.npy", np.zeros((0, 3), np.float32)), "0 points"),
    "npy nan": (_npy("nan.npy", NAN_POINTS), "2 of 6 points"),
    "npz not zip": (_write("bad.npz", b"not a zip archive"), "npz"),
    "npz truncated zip": (_truncated("cut.npz", 500), "npz"),
    "npz no points": (lambda folder: _npz(folder / "nopoints.npz", xyz=np.zeros((3, 3))), "points"),
    "npz points shape": (lambda folder: _npz_scene(folder / "s.npz", points=np.zeros((10, 4))), "points"),
    "npz boxes shape": (lambda folder: _npz_scene(folder / "s.npz", boxes=np.zeros((2, 6))), "(M, 7)"),
    "npz boxes without labels": (lambda folder: _npz_scene(folder / "s.npz", labels=None), "labels"),
    "npz labels length": (
        lambda folder: _npz_scene(folder / "s.npz", labels=np.array(["box"])),
        "1 labels for 2",
    ),
    "npz labels numbers": (lambda folder: _npz_scene(folder / "s.npz", labels=np.array([1, 2])), "string"),
    "npz empty label": (lambda folder: _npz_scene(folder / "s.npz", labels=np.array(["box", " "])), "empty"),
    "npz colors length": (
        lambda folder: _npz_scene(folder / "s.npz", colors=np.zeros((9, 3), np.uint8)),
        "colors",
    ),
    "npz colors values": (
        lambda folder: _npz_scene(folder / "s.npz", colors=np.full((10, 3), -4.0)),
        "colors",
    ),
    "npz intensity length": (
        lambda folder: _npz_scene(folder / "s.npz", intensity=np.zeros(3, np.float32)),
        "intensity",
    ),
    "npz nan intensity": (
        lambda folder: _npz_scene(folder / "s.npz", intensity=np.full(10, np.nan, np.float32)),
        "intensity",
    ),
    "npz nan box": (
        lambda folder: _npz_scene(folder / "s.npz", boxes=np.array([[0, 0, 0, 1, 1, 1, np.nan]] * 2)),
        "NaN",
    ),
    "npz negative box": (
        lambda folder: _npz_scene(folder / "s.npz", boxes=np.array([[0, 0, 0, 1, -1, 1, 0]] * 2)),
        "negative",
    ),
    "npz empty": (
        lambda folder: _npz_scene(folder / "s.npz", points=np.zeros((0, 3), np.float32)),
        "0 points",
    ),
    "npz nan points": (lambda folder: _npz_scene(folder / "s.npz", points=NAN_POINTS), "2 of 6 points"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_raises_one_line_input_error(tmp_path: Path, case: str) -> None:
    make, expected = BAD_INPUTS[case]
    path = make(tmp_path)
    message = check_input_error(path)
    assert expected.lower() in message.lower(), message


def test_unknown_class_names(tmp_path: Path) -> None:
    path = _npz_scene(tmp_path / "scene.npz", labels=np.array(["box", "forklift"]))
    message = check_input_error(path, class_names=["box", "pallet"])
    assert "forklift" in message and "pallet" in message
    frame = read_frame(path, class_names=["forklift", "pallet", "box"])
    assert frame.labels.class_ids.tolist() == [2, 0]
