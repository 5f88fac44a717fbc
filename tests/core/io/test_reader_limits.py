"""Tests of the readers' guards against hostile files: header-driven memory bombs, the points cap,
the byte budget of a read, compression bombs (deflate, LAZ), LAZ decoder aborts and undecodable
text all give one-line ``InputError``s, and a ``MemoryError`` is never disguised as one.

The files are small on disk; the caps are tested with lowered limits rather than big arrays, and
the bombs (49 million zero rows, 20 million LAZ records) are refused before anything inflates.
"""

from __future__ import annotations

import io
import json
import math
import struct
import tempfile
import time
import tracemalloc
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import laspy
import lazrs
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import factorydet_core.io.npz as npz_module
import factorydet_core.io.readers as readers_module
from factorydet_core.cli import main as cli_main
from factorydet_core.io.dataset import open_dataset
from factorydet_core.io.limits import (
    MAX_INFLATION,
    MAX_POINTS,
    MAX_POINTS_ENV,
    MAX_READ_BYTES,
    MAX_READ_BYTES_ENV,
    check_read_bytes,
    resolve_max_points,
    resolve_max_read_bytes,
)
from factorydet_core.io.npz import load_npz, save_npz
from factorydet_core.io.readers import read_frame, write_frame
from factorydet_core.sim.truth import read_frame_truth, read_truth
from factorydet_core.types import Frame, InputError

from .test_readers import make_frame


def refused(path: Path, **kwargs) -> str:
    """The one-line ``InputError`` message that reading ``path`` gives."""
    with pytest.raises(InputError) as info:
        read_frame(path, **kwargs)
    message = str(info.value)
    assert "\n" not in message and path.name in message, message
    return message


T = TypeVar("T")


def traced_peak(call: Callable[[], T]) -> tuple[T, int]:
    """``call()``'s result and the peak bytes Python allocated while it ran (tracemalloc)."""
    tracemalloc.start()
    try:
        result = call()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return result, peak


def written(folder: Path, name: str, num: int = 200) -> Path:
    path = folder / name
    write_frame(path, make_frame(num))
    return path


def npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def patch(path: Path, at: int, fmt: str, *values: int) -> Path:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, at, *values)
    path.write_bytes(bytes(data))
    return path


# ------------------------------------------------------------------------------------------------
# The cap and how to raise it
# ------------------------------------------------------------------------------------------------


def test_cap_default_env_and_argument(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    assert MAX_POINTS >= 5_000_000  # a dense scan must read
    monkeypatch.delenv(MAX_POINTS_ENV, raising=False)
    assert resolve_max_points() == MAX_POINTS
    path = written(tmp_path, "scan.ply")
    assert "limit of 100 points" in refused(path, max_points=100)
    monkeypatch.setenv(MAX_POINTS_ENV, "150")
    message = refused(path)
    assert "limit of 150 points" in message and MAX_POINTS_ENV in message
    assert read_frame(path, max_points=200).num_points == 200  # the argument wins
    monkeypatch.setenv(MAX_POINTS_ENV, "lots")
    with pytest.raises(InputError, match=MAX_POINTS_ENV):
        read_frame(path)
    with pytest.raises(InputError, match="positive"):
        resolve_max_points(0)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz", ".csv", ".las", ".laz", ".bin", ".npy", ".npz"])
def test_every_format_honours_the_cap(tmp_path: Path, suffix: str) -> None:
    path = written(tmp_path, f"scan{suffix}")
    assert "limit of 199 points" in refused(path, max_points=199)
    assert read_frame(path, max_points=200).num_points == 200


# ------------------------------------------------------------------------------------------------
# The byte budget of one read
# ------------------------------------------------------------------------------------------------


def test_byte_budget_default_env_and_argument(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(MAX_READ_BYTES_ENV, raising=False)
    assert resolve_max_read_bytes() == MAX_READ_BYTES
    for text, value in [
        ("4000000000", 4 * 10**9),
        ("4e9", 4 * 10**9),
        ("4G", 4 * 10**9),
        ("2500MB", 25 * 10**8),
    ]:
        monkeypatch.setenv(MAX_READ_BYTES_ENV, text)
        assert resolve_max_read_bytes() == value
    path = written(tmp_path, "scan.ply", 2000)
    monkeypatch.setenv(MAX_READ_BYTES_ENV, "100k")
    message = refused(path)
    assert "allowed for one read" in message and MAX_READ_BYTES_ENV in message
    assert read_frame(path, max_read_bytes=10**8).num_points == 2000  # the argument wins
    monkeypatch.setenv(MAX_READ_BYTES_ENV, "lots")
    with pytest.raises(InputError, match=MAX_READ_BYTES_ENV):
        read_frame(path)
    with pytest.raises(InputError, match="positive"):
        resolve_max_read_bytes(0)


FORMATS = (".ply", ".pcd", ".xyz", ".csv", ".pts", ".las", ".laz", ".bin", ".npy", ".npz")


@pytest.mark.parametrize("suffix", FORMATS)
def test_every_reader_estimates_at_least_its_peak(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str
) -> None:
    """The estimate each reader checks before allocating covers what the read really allocates
    (numpy and Python memory, traced), and is not wildly above it."""
    path = tmp_path / f"scan{suffix}"
    write_frame(path, make_frame(60_000))
    estimates: list[int] = []

    def spy(path: Path, needed: int, max_read_bytes: int, what: str) -> None:
        estimates.append(needed)
        check_read_bytes(path, needed, max_read_bytes, what)

    monkeypatch.setattr(readers_module, "check_read_bytes", spy)
    monkeypatch.setattr(npz_module, "check_read_bytes", spy)
    read_frame(path)  # imports and caches first
    estimates.clear()
    _, peak = traced_peak(lambda: read_frame(path))
    (estimate,) = estimates
    assert peak <= estimate <= 4 * peak, (peak, estimate)
    assert "allowed for one read" in refused(path, max_read_bytes=estimate - 1)
    assert read_frame(path, max_read_bytes=estimate).num_points == 60_000


def test_text_is_parsed_as_it_streams(tmp_path: Path) -> None:
    path = tmp_path / "mac.xyz"
    path.write_bytes(b"x y z\r1 2 3\r4 5 6\r\r7 8 9")  # old Mac line ends, a blank line, no final one
    np.testing.assert_array_equal(read_frame(path).points, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    path = tmp_path / "long.xyz"
    path.write_bytes(b"1 2 3\n" + b"4 " * 40_000 + b"\n")
    assert "longer than" in refused(path)
    path = tmp_path / "rows.csv"
    path.write_text("# comment\n" * 300 + "1,2,3\n" * 100)
    assert read_frame(path, max_points=100).num_points == 100  # comment lines are not points
    assert "limit of 99 points" in refused(path, max_points=99)


# ------------------------------------------------------------------------------------------------
# Headers that claim more than the file holds
# ------------------------------------------------------------------------------------------------


def test_las_header_claiming_2e8_points_is_refused_before_reading(tmp_path: Path) -> None:
    path = patch(written(tmp_path, "bomb.las"), 107, "<I", 200_000_000)
    start = time.perf_counter()
    assert "limit of" in refused(path)
    # Even under a raised cap the size check refuses it without reading: 2e8 * 26 bytes > the file.
    message = refused(path, max_points=10**9)
    assert "truncated LAS" in message and "200000000 points" in message
    assert time.perf_counter() - start < 2.0


def test_las_vlr_count_beyond_the_header(tmp_path: Path) -> None:
    # laspy would read 4e9 empty VLRs past the end of the header (900 MB for 16 million).
    path = patch(written(tmp_path, "vlrs.las"), 100, "<I", 0xFFFFFFFF)
    assert "4294967295 VLRs do not fit" in refused(path)


def test_las_14_64_bit_count(tmp_path: Path) -> None:
    path = tmp_path / "big14.las"
    header = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.arange(10.0), np.zeros(10), np.zeros(10)
    las.write(str(path))
    assert read_frame(path).num_points == 10
    assert "18446744073709551615 points" in refused(patch(path, 247, "<Q", 2**64 - 1))


def test_laz_with_a_huge_point_count_or_chunk_count(tmp_path: Path) -> None:
    path = written(tmp_path, "scan.laz")
    size = path.stat().st_size
    message = refused(patch(path, 107, "<I", 40_000_000))  # under the cap, but 3 KB cannot hold it
    assert "corrupt LAZ" in message and "compressed bytes" in message
    path = written(tmp_path, "chunks.laz")
    offset = struct.unpack_from("<I", path.read_bytes(), 96)[0]
    (table,) = struct.unpack_from("<q", path.read_bytes(), offset)
    # The chunk count lazrs reserved 16 bytes each for: 0x64000001 chunks aborted the process.
    assert "chunk table lists" in refused(patch(path, table + 4, "<I", 0x64000001))
    patch(path, offset, "<q", size + 100)
    assert "outside the point data" in refused(path)


def test_laz_decoder_abort_becomes_input_error(tmp_path: Path) -> None:
    """A chunk table entry claiming 2 GB of compressed bytes makes lazrs allocate them and abort
    on failure; read in a capped child process, the abort is one line."""
    path = written(tmp_path, "abort.laz")
    data = path.read_bytes()
    header = laspy.open(path).header
    vlr = lazrs.LazVlr(header.vlrs.get("LasZipVlr")[0].record_data)
    (table,) = struct.unpack_from("<q", data, header.offset_to_point_data)
    with path.open("rb") as source:
        source.seek(header.offset_to_point_data)
        chunks = lazrs.read_chunk_table(source, vlr)
    hostile = io.BytesIO()
    lazrs.write_chunk_table(hostile, [(chunks[0][0], 2_141_036_189)], vlr)
    path.write_bytes(data[:table] + hostile.getvalue())
    message = refused(path)
    assert "cannot decode LAZ" in message and "decoder" in message


def test_laz_truncated_in_the_points(tmp_path: Path) -> None:
    path = written(tmp_path, "cut.laz", 5000)
    data = path.read_bytes()
    offset = struct.unpack_from("<I", data, 96)[0]
    (table,) = struct.unpack_from("<q", data, offset)
    path.write_bytes(data[: offset + 508] + data[table:])  # the chunk table survives, the points do not
    patch(path, offset, "<q", offset + 508)
    assert "LAZ" in refused(path)


@pytest.mark.parametrize(
    ("name", "header"),
    [
        ("huge.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\n"
         b"property float y\nproperty float z\nend_header\n"),
        ("huge.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000000\nHEIGHT 1\n"
         b"POINTS 1000000000000\nDATA binary\n"),
    ],
)  # fmt: skip
def test_ply_and_pcd_headers_over_the_cap(tmp_path: Path, name: str, header: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(header + bytes(24))
    assert "1000000000000 points" in refused(path)


def test_pcd_binary_compressed_sizes_are_checked(tmp_path: Path) -> None:
    header = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 5\nPOINTS 5\nDATA binary_compressed\n"
    path = tmp_path / "c.pcd"
    path.write_bytes(header + struct.pack("<II", 4_000_000_000, 60) + bytes(8))
    assert "truncated PCD" in refused(path)
    path.write_bytes(header + struct.pack("<II", 8, 4_000_000_000) + bytes(8))
    assert "uncompressed bytes" in refused(path)


def test_npy_header_claiming_more_than_the_file(tmp_path: Path) -> None:
    path = tmp_path / "claims.npy"
    path.write_bytes(npy_header((10**10, 3)) + bytes(64))
    message = refused(path)
    assert "bytes follow" in message and "(10000000000, 3)" in message


def test_pickled_arrays_are_refused(tmp_path: Path) -> None:
    objects = np.array([{"a": 1}, None], dtype=object)
    np.save(tmp_path / "objects.npy", objects, allow_pickle=True)
    assert "Python objects" in refused(tmp_path / "objects.npy")
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, objects, allow_pickle=True)
    with zipfile.ZipFile(tmp_path / "objects.npz", "w") as archive:
        archive.writestr("points.npy", buffer.getvalue())
    assert "Python objects" in refused(tmp_path / "objects.npz")


# ------------------------------------------------------------------------------------------------
# .npz: zip bombs, lying members, broken archives
# ------------------------------------------------------------------------------------------------


def test_npz_deflate_bomb_is_refused_before_inflating(tmp_path: Path) -> None:
    # 2.4 MB of zeros deflate to a few KB; with a cap of 1000 points that is far over budget.
    path = tmp_path / "bomb.npz"
    save_npz(path, {"points": np.zeros((100_000, 3))})
    assert path.stat().st_size < 10_000
    assert "limit of 1000 points" in refused(path, max_points=1000)
    assert read_frame(path, max_points=100_000).num_points == 100_000


def test_npz_member_header_claiming_more_than_its_member(tmp_path: Path) -> None:
    path = tmp_path / "claims.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("points.npy", npy_header((10**10, 3)) + bytes(64))
    message = refused(path, max_points=10**11)
    assert "member 'points'" in message and "bytes follow" in message


def test_npz_member_declaring_a_false_size(tmp_path: Path) -> None:
    # The central directory says 1 GB inflated; the array header agrees, the data is 64 bytes.
    path = tmp_path / "liar.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr("points.npy", npy_header((1000, 3)) + bytes(64))
    data = bytearray(path.read_bytes())
    central = data.rindex(b"PK\x01\x02")
    struct.pack_into("<I", data, central + 24, 1 << 30)
    path.write_bytes(bytes(data))
    assert f"claim {1 << 30} bytes inflated" in refused(path)  # a stored member "inflating" 5 million-fold


@pytest.mark.parametrize("cut", [30, 200, -30])
def test_npz_bad_zip(tmp_path: Path, cut: int) -> None:
    path = written(tmp_path, "cut.npz")
    data = path.read_bytes()
    path.write_bytes(data[:cut])
    assert "npz" in refused(path)


def zero_npz(path: Path, members: dict[str, tuple[tuple[int, ...], str]]) -> Path:
    """A valid .npz whose members are zero arrays of the given shapes and dtypes, written without
    compressing gigabytes: a block of 16 MiB of zeros is deflated once and repeated (a full flush
    makes each block independent), the same bytes a deflating writer would give in a few seconds."""
    block = 1 << 24
    compressor = zlib.compressobj(6, zlib.DEFLATED, -15)
    zeros = compressor.compress(bytes(block)) + compressor.flush(zlib.Z_FULL_FLUSH)
    with path.open("wb") as out:
        central = []
        for name, (shape, descr) in members.items():
            header = npy_header(shape, descr)
            size = len(header) + math.prod(shape) * np.dtype(descr).itemsize
            head = zlib.compressobj(6, zlib.DEFLATED, -15)
            data = [head.compress(header) + head.flush(zlib.Z_FULL_FLUSH)]
            crc, left = zlib.crc32(header), size - len(header)
            whole, rest = divmod(left, block)
            data += [zeros] * whole
            tail = zlib.compressobj(6, zlib.DEFLATED, -15)
            data.append(tail.compress(bytes(rest)) + tail.flush())
            for _ in range(whole):
                crc = zlib.crc32(bytes(block), crc)
            crc = zlib.crc32(bytes(rest), crc)
            compressed = sum(len(d) for d in data)
            filename = f"{name}.npy".encode()
            fields = struct.pack("<HHHHHIII", 20, 0, 8, 0, 33, crc, compressed, size)
            central.append((out.tell(), filename, fields))
            out.write(b"PK\x03\x04" + fields + struct.pack("<HH", len(filename), 0) + filename)
            for chunk in data:
                out.write(chunk)
        start = out.tell()
        for offset, filename, fields in central:
            # made by, the local header's fields, name, extra, comment, disk, attributes, offset
            out.write(b"PK\x01\x02" + struct.pack("<H", 20) + fields)
            out.write(struct.pack("<HHHHHII", len(filename), 0, 0, 0, 0, 0o644 << 16, offset))
            out.write(filename)
        end = out.tell()
        count = len(central)
        out.write(b"PK\x05\x06" + struct.pack("<HHHHIIH", 0, 0, count, count, end - start, start, 0))
    return path


def test_zero_filled_npz_bomb_is_refused_before_inflating(tmp_path: Path) -> None:
    """49 million rows of zero (N, 3) float64 points and colours and (N,) intensity: 2.7 GB in a
    2.7 MB file. It once passed every check and took 6.3 GB; now it is refused from the central
    directory, allocating nothing."""
    n = 49_000_000
    members = {"points": ((n, 3), "<f8"), "colors": ((n, 3), "<f8"), "intensity": ((n,), "<f8")}
    path = zero_npz(tmp_path / "bomb1.npz", members)
    assert path.stat().st_size < 4_000_000
    with zipfile.ZipFile(path) as archive:  # a valid archive, as a writer would make it
        assert archive.getinfo("points.npy").file_size > n * 24
        with archive.open("intensity.npy") as member:
            assert member.read(1 << 20).count(0) > (1 << 20) - 200
    message, peak = traced_peak(lambda: refused(path))
    assert "bytes inflated" in message and f"more than {MAX_INFLATION}x" in message
    assert peak < 10 * 2**20
    # Even where the ratio allows it, the byte budget refuses what the arrays and copies need.
    small = zero_npz(tmp_path / "small.npz", {"points": ((2_000_000, 3), "<f8")})
    assert "allowed for one read" in refused(small, max_read_bytes=200_000_000)


def test_npz_bomb_from_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = zero_npz(tmp_path / "bomb.npz", {"points": ((20_000_000, 3), "<f8")})
    assert cli_main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "bytes inflated" in err and "\n" not in err


def test_laz_claiming_20_million_records_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 2000-point LAZ of 234-byte records whose header claims 20 million points (4.7 GB): no
    decoding child is started and nothing is allocated for the records."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.add_extra_dims([laspy.ExtraBytesParams(f"pad{i}", "f8") for i in range(25)])  # 200 bytes
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 50, (3, 2000))
    path = tmp_path / "bomb.laz"
    las.write(str(path))
    assert struct.unpack_from("<H", path.read_bytes(), 105)[0] == 234
    assert read_frame(path).num_points == 2000
    patch(path, 107, "<I", 20_000_000)

    def no_child(*args: object, **kwargs: object) -> None:
        raise AssertionError("the decoder was started")

    monkeypatch.setattr(readers_module.subprocess, "Popen", no_child)
    message, peak = traced_peak(lambda: refused(path))
    assert "corrupt LAZ: 20000000 point records claim 4680000000 bytes inflated" in message
    assert peak < 10 * 2**20


def test_memory_errors_are_never_called_bad_input(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = written(tmp_path, "scan.npz")

    def exhausted(*args: object, **kwargs: object) -> None:
        raise MemoryError("Unable to allocate 2.5 GiB")

    monkeypatch.setattr(npz_module.np.lib.format, "read_array", exhausted)
    with pytest.raises(MemoryError):
        load_npz(path)
    with pytest.raises(MemoryError):
        read_frame(path)
    assert cli_main(["info", str(path)]) == 3
    err = capsys.readouterr().err.strip()
    assert "out of memory" in err and "\n" not in err
    monkeypatch.setitem(readers_module._READERS, ".ply", exhausted)
    with pytest.raises(MemoryError):
        read_frame(written(tmp_path, "scan.ply"))


def test_load_npz_reads_selected_members(tmp_path: Path) -> None:
    path = tmp_path / "a.npz"
    save_npz(path, {"points": np.ones((4, 3)), "other": np.arange(3)})
    names, arrays = load_npz(path, ["points", "missing"])
    assert names == ["points", "other"] and list(arrays) == ["points"]
    np.testing.assert_array_equal(arrays["points"], np.ones((4, 3)))


# ------------------------------------------------------------------------------------------------
# Text, data sets and the command line
# ------------------------------------------------------------------------------------------------


def test_non_utf8_text(tmp_path: Path) -> None:
    path = tmp_path / "latin.xyz"
    path.write_bytes(b"# r\xe9sum\xe9 \xff\xfe\n1 2 3\n4 5 6\n")  # bad bytes in a comment do no harm
    assert read_frame(path).num_points == 2
    path.write_bytes(b"1 2 3\n4 \xff\xfe 6\n")
    assert "corrupt point table" in refused(path)
    path = tmp_path / "binary.csv"
    path.write_bytes(bytes(range(256)) * 4)
    refused(path)


def _manifest(folder: Path, frames: list[str]) -> Path:
    folder.mkdir(exist_ok=True)
    manifest = {"classes": ["box"], "frames": frames, "sensors": [{"T_vehicle_sensor": np.eye(4).tolist()}]}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def test_data_set_without_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = _manifest(tmp_path / "empty", [])
    with pytest.raises(InputError, match="no frames"):
        open_dataset(folder)
    assert cli_main(["info", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no frames" in err and "\n" not in err
    assert cli_main(["info", str(tmp_path / "nothing_here")]) == 2
    assert cli_main(["info", str(tmp_path)]) == 2  # a folder without a manifest
    assert len(capsys.readouterr().err.strip().splitlines()) == 2


def test_data_set_frame_bomb(tmp_path: Path) -> None:
    folder = _manifest(tmp_path / "bomb", ["frame_00000.npz"])
    save_npz(folder / "frame_00000.npz", {"points": np.zeros((100_000, 3), np.float32)})
    with pytest.raises(InputError, match="unreadable frame .*limit of 1000 points"):
        open_dataset(folder, max_points=1000).frame(0)


def test_deeply_nested_manifest(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "nested"
    folder.mkdir()
    (folder / "manifest.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(InputError, match="nested too deeply"):
        open_dataset(folder)
    assert cli_main(["info", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "manifest" in err and "\n" not in err
    (folder / "manifest.json").write_bytes(b'{"classes": ["\xff"]}')
    with pytest.raises(InputError, match="malformed manifest"):
        open_dataset(folder)
    (folder / "manifest.json").write_text(json.dumps({"classes": ["box"], "frames": {"a": 1}, "sensors": 5}))
    with pytest.raises(InputError, match="malformed manifest"):
        open_dataset(folder)


def test_simulator_truth_is_read_through_the_guards(tmp_path: Path) -> None:
    truth = tmp_path / "truth"
    truth.mkdir()
    (truth / "truth.json").write_text("[" * 100_000)
    with pytest.raises(InputError, match="truth record"):
        read_truth(tmp_path)
    (truth / "truth.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="not a JSON object"):
        read_truth(tmp_path)
    with zipfile.ZipFile(truth / "frame_00000.npz", "w") as archive:
        archive.writestr("point_instance_ids.npy", npy_header((10**10,), "<i8") + bytes(64))
    with pytest.raises(InputError, match="bytes follow"):
        read_frame_truth(tmp_path, 0)
    save_npz(truth / "frame_00001.npz", {"T_world_vehicle": np.eye(4)})
    with pytest.raises(InputError, match="lacks the arrays point_instance_ids"):
        read_frame_truth(tmp_path, 1)


# ------------------------------------------------------------------------------------------------
# Property: any mutation of a valid file reads or gives a one-line InputError
# ------------------------------------------------------------------------------------------------

FUZZ_SUFFIXES = (".ply", ".pcd", ".xyz", ".csv", ".pts", ".las", ".laz", ".bin", ".npy", ".npz")
EXTREME_WORDS = (
    b"\x00" * 8, b"\xff" * 8, b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80", b"\xff\xff\xff\xff\xff\xff\xff\x7f",
    np.float32(np.nan).tobytes(), np.float64(1e300).tobytes(), np.int64(10**12).tobytes(), b"99999999999",
)  # fmt: skip
_SEEDS: dict[str, bytes] = {}


def _seed(suffix: str) -> bytes:
    """A small valid file of each format (40 points; text formats with an ascii header)."""
    if suffix not in _SEEDS:
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / f"seed{suffix}"
            write_frame(path, make_frame(40))
            _SEEDS[suffix] = path.read_bytes()
    return _SEEDS[suffix]


@st.composite
def mutated_files(draw: st.DrawFn) -> tuple[str, bytes]:
    suffix = draw(st.sampled_from(FUZZ_SUFFIXES))
    data = _seed(suffix)
    # Headers decide allocations, so most offsets fall in the first 400 bytes.
    at = st.integers(0, len(data) - 1) | st.integers(0, min(len(data), 400) - 1)
    kind = draw(st.sampled_from(["truncate", "flip", "word"]))
    if kind == "truncate":
        return suffix, data[: draw(st.integers(0, len(data) - 1))]
    out = bytearray(data)
    if kind == "flip":
        for spot, value in draw(st.lists(st.tuples(at, st.integers(0, 255)), min_size=1, max_size=8)):
            out[spot] = value
        return suffix, bytes(out)
    word, spot = draw(st.sampled_from(EXTREME_WORDS)), draw(at)
    return suffix, bytes(out[:spot] + word + out[spot + len(word) :])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=mutated_files())
def test_mutated_files_read_or_give_one_line_errors(case: tuple[str, bytes]) -> None:
    suffix, data = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"fuzz{suffix}"
        path.write_bytes(data)
        try:
            # A lowered cap bounds what any surviving header can make a reader allocate.
            frame = read_frame(path, max_points=100_000)
        except InputError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc), str(exc)
            return
    assert isinstance(frame, Frame) and frame.num_points > 0
    assert np.isfinite(frame.points).all()
