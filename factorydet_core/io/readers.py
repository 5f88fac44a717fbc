"""Read and write single point-cloud files as one-sensor ``Frame`` objects.

``read_frame`` picks a reader by the file suffix (case-insensitive, see ``SUPPORTED_SUFFIXES``):

- ``.ply``: ascii, binary_little_endian or binary_big_endian. Vertex properties ``x, y, z`` (any
  numeric type), optional ``red, green, blue`` and optional ``intensity`` / ``scalar_intensity``.
- ``.pcd``: ``DATA ascii`` and ``binary`` with any record layout that the FIELDS / SIZE / TYPE /
  COUNT header describes (padding ``_`` fields, extra fields such as timestamp or ring);
  ``x, y, z``, optional ``intensity`` and ``rgb`` / ``rgba`` (packed into a float or uint32).
  ``binary_compressed`` is decoded by Open3D (points and colours only).
- ``.xyz``, ``.txt``, ``.pts``, ``.csv``: one point a line, separated by whitespace or commas,
  ``#`` comments skipped, an optional header line of column names (``x y z intensity r g b`` ...).
  Without names the columns are ``x y z`` then: 4, 5 or 8 columns -> intensity; 6 or >= 9 ->
  ``r g b`` (when they look like colours); 7 -> intensity, ``r g b`` (Leica PTS). In ``.pts`` files
  lines holding a single integer (point counts) are skipped.
- ``.las``, ``.laz``: scaled coordinates, colours (16-bit scaled to 8-bit) and intensity (laspy).
- ``.bin``: KITTI velodyne scan, float32 records ``x, y, z, intensity``.
- ``.npy``: an (N, 3) or (N, >=4) numeric array; column 3 is the intensity.
- ``.npz``: the neutral scene format of ``shared/data/real/README.md``: ``points`` (N, 3),
  ``boxes`` (M, 7), ``labels`` (M,) str, optional ``colors`` (N, 3) and ``intensity`` (N,).

Every file becomes a frame with one sensor whose extrinsic is the identity. Coordinates larger
than ``LARGE_COORDINATE_M`` (georeferenced scans) are recentred in float64 before the points are
cast to float32; the subtracted offset is kept in ``Frame.origin_offset`` and ``write_frame`` adds
it back. Boxes are (cx, cy, cz, dx, dy, dz, yaw), z up, metres, yaw counter-clockwise about +z.

Bad input raises ``InputError`` with one line naming the file and the problem; never a traceback,
a signal or unbounded memory. Each reader checks what a header declares before it allocates (see
``io.limits``): sizes against the file's length (exactly where the format allows it; for LAZ and
``.npz`` members, inflation at most ``MAX_INFLATION`` times the compressed size), the number of
points against ``MAX_POINTS`` (``max_points=`` or ``FACTORYDET_MAX_POINTS``), and the bytes the
read will hold at its peak, the decoded records and every conversion copy up to the ``Frame``,
against ``MAX_READ_BYTES`` (8 GB; ``max_read_bytes=`` or ``FACTORYDET_MAX_READ_BYTES``). Binary
bodies are read from the file (never the whole file into memory) and text is parsed as it streams,
after its lines are counted, so that the estimate bounds the read's real peak. LAZ is decoded in a child
process whose address space is capped: the decoder (lazrs) aborts the whole process on some corrupt
chunk tables, and there such an abort becomes an ``InputError``; the child streams the decoded
records back, so the parent holds only records that really decoded. A ``MemoryError`` is never
turned into an ``InputError``: the caps are meant to prevent it, and if they fail it must show.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import itertools
import math
import os
import re
import signal
import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from factorydet_core.geometry import apply_transforms, points_in_box
from factorydet_core.io.atomic import atomic_path
from factorydet_core.io.limits import (
    FRAME_BYTES_PER_POINT,
    RAISE_HINT,
    check_inflation,
    check_read_bytes,
    resolve_max_points,
    resolve_max_read_bytes,
    too_many_points,
)
from factorydet_core.io.npz import NpyHeaders, check_npy_array, load_npz, read_npy_header, save_npz
from factorydet_core.types import CLASS_NAMES, BoxLabels, Frame, InputError

SUPPORTED_SUFFIXES: tuple[str, ...] = (
    ".ply",
    ".pcd",
    ".xyz",
    ".txt",
    ".pts",
    ".csv",
    ".las",
    ".laz",
    ".bin",
    ".npy",
    ".npz",
)
"""File suffixes that ``read_frame`` and ``write_frame`` handle (compared case-insensitively)."""

LARGE_COORDINATE_M = 1000.0
"""Clouds with any |coordinate| above this (metres) are recentred on reading."""

LAS_SCALE = 1e-4
"""Coordinate resolution (metres) of the LAS/LAZ files that ``write_frame`` writes."""

_INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "i")
_COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
_HEADER_LIMIT = 1 << 20  # bytes searched for the end of a PLY / PCD header
_MAX_LINE = 1 << 16  # characters of one text line: a point is under 200, and a line is held whole
_READ_BLOCK = 1 << 20  # bytes read at a time where a file or a pipe is streamed (counted in budgets)


@dataclasses.dataclass(frozen=True)
class _Limits:
    """What one read may take (``io.limits``)."""

    max_points: int
    max_read_bytes: int


@dataclasses.dataclass
class _RawCloud:
    """What a reader found in a file, before recentring and validation."""

    points: np.ndarray  # (N, 3) float64, source coordinates
    colors: np.ndarray | None = None  # (N, 3) uint8
    intensity: np.ndarray | None = None  # (N,) float
    boxes: np.ndarray | None = None  # (M, 7) float64, source coordinates
    labels: list[str] | None = None  # (M,) class names


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _error(path: Path, problem: str) -> InputError:
    """An ``InputError`` whose single-line message names ``path`` and ``problem``."""
    return InputError(_one_line(f"{path}: {problem}"))


def _supported_list() -> str:
    return ", ".join(SUPPORTED_SUFFIXES)


def _check_bytes(path: Path, limits: _Limits, num_points: int, decoded: int, what: str) -> None:
    """Refuse a read whose ``decoded`` bytes (what the reader holds: records, parsed values) plus
    the conversion of ``num_points`` points into a ``Frame`` exceed the byte budget."""
    check_read_bytes(path, decoded + num_points * FRAME_BYTES_PER_POINT, limits.max_read_bytes, what)


# ----------------------------------------------------------------------------------------------
# Shared helpers
# ----------------------------------------------------------------------------------------------


def _colors_to_uint8(rgb: np.ndarray) -> np.ndarray | None:
    """(N, 3) colours of any numeric type as uint8, or ``None`` when they do not look like colours.

    uint8 passes; integral values <= 255 are taken as 8-bit; floats in [0, 1] are scaled by 255;
    integral values <= 65535 are taken as 16-bit and shifted right by 8.
    """
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb
    if rgb.dtype.kind not in "fiub":
        return None
    if len(rgb) == 0:
        return np.zeros(rgb.shape, np.uint8)
    values = rgb.astype(np.float64)
    if not np.isfinite(values).all() or values.min() < 0:
        return None
    vmax = float(values.max())
    integral = bool(np.all(values == np.round(values)))
    if rgb.dtype.kind == "f" and vmax <= 1.0 and not integral:
        return np.round(values * 255.0).astype(np.uint8)
    if integral and vmax <= 255:
        return values.astype(np.uint8)
    if vmax <= 1.0:
        return np.round(values * 255.0).astype(np.uint8)
    if integral and vmax <= 65535:
        return (values.astype(np.uint16) >> 8).astype(np.uint8)
    return None


def _cloud_from_columns(path: Path, columns: dict[str, np.ndarray], what: str) -> _RawCloud:
    """Pick x, y, z, colours and intensity out of named 1-D columns (names lower-case)."""
    missing = [axis for axis in "xyz" if axis not in columns]
    if missing:
        found = ", ".join(sorted(columns)) or "none"
        raise _error(path, f"{what} has no {'/'.join(missing)} field (found: {found})")
    points = np.column_stack([np.asarray(columns[axis], dtype=np.float64) for axis in "xyz"])
    colors = None
    for names in _COLOR_NAMES:
        if all(name in columns for name in names):
            colors = _colors_to_uint8(np.column_stack([columns[name] for name in names]))
            break
    intensity = None
    for name in _INTENSITY_NAMES:
        if name in columns:
            intensity = np.asarray(columns[name], dtype=np.float32)
            break
    return _RawCloud(points=points, colors=colors, intensity=intensity)


def _read_header_lines(path: Path, data: bytes, what: str, last: str) -> Iterator[tuple[int, str, int]]:
    """Yield (line number, stripped line, offset after the line) of the text at the start of ``data``.

    Raises ``InputError`` when the header runs out before the caller has seen its ``last`` line.
    """
    pos, lineno = 0, 0
    while pos < min(len(data), _HEADER_LIMIT):
        end = data.find(b"\n", pos)
        end = len(data) if end < 0 else end
        lineno += 1
        yield lineno, data[pos:end].decode("latin-1").strip(), end + 1
        pos = end + 1
    raise _error(path, f"bad {what} header: no {last} line")


def _text_lines(path: Path, offset: int = 0, encoding: str = "utf-8") -> Iterator[str]:
    """The stripped lines of ``path`` from byte ``offset``, one at a time (only one is ever held).

    Bytes that do not decode become U+FFFD. Raises ``InputError`` for a line longer than
    ``_MAX_LINE`` characters (no point table has one, and a whole line is held in memory).
    """
    with path.open("rb") as raw:
        raw.seek(offset)
        handle = io.TextIOWrapper(raw, encoding=encoding, errors="replace")
        for lineno in itertools.count(1):
            line = handle.readline(_MAX_LINE)
            if not line:
                return
            if len(line) == _MAX_LINE and not line.endswith(("\n", "\r")):
                raise _error(path, f"text line {lineno} is longer than {_MAX_LINE} characters")
            yield line.strip()


def _count(rows: Iterator[str], stop: int) -> int:
    """How many of ``rows`` there are, counting at most ``stop`` (nothing is kept)."""
    return sum(1 for _ in itertools.islice(rows, stop))


def _count_lines(path: Path) -> int:
    """The number of lines of ``path`` (line breaks ``\\n``, ``\\r`` or ``\\r\\n``, plus one): a bound
    on its rows, found at the speed of reading the file and without keeping it."""
    breaks, last = 0, b""
    with path.open("rb") as handle:
        while block := handle.read(_READ_BLOCK):
            pairs = block.count(b"\r\n") + (last == b"\r" and block[:1] == b"\n")
            breaks += block.count(b"\n") + block.count(b"\r") - pairs
            last = block[-1:]
    return breaks + 1


def _load_rows(
    path: Path,
    rows: Iterable[str],
    num_rows: int,
    num_columns: int,
    what: str,
    delimiter: str | None = None,
) -> np.ndarray:
    """Parse at most ``num_rows`` text rows into a (rows, num_columns) float64 array.

    ``num_rows`` must be within the budget: the parser allocates all of it before reading a row.
    """
    if num_rows == 0:
        return np.zeros((0, num_columns))
    try:
        values = np.loadtxt(
            rows, dtype=np.float64, delimiter=delimiter, ndmin=2, comments=None, max_rows=num_rows
        )
    except InputError:
        raise
    except ValueError as exc:
        reason = str(exc).split("; use `usecols`")[0]  # drop numpy's advice to the programmer
        raise _error(path, f"corrupt {what}: {reason}") from exc
    if values.shape[1] != num_columns:
        raise _error(path, f"corrupt {what}: rows have {values.shape[1]} values, expected {num_columns}")
    return values


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


@dataclasses.dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str | None]]  # (name, numpy type code), None for list properties

    @property
    def has_list(self) -> bool:
        return any(code is None for _, code in self.properties)

    def dtype(self, endian: str) -> np.dtype:
        return np.dtype([(f"p{i}", endian + str(code)) for i, (_, code) in enumerate(self.properties)])


def _parse_ply_header(path: Path, data: bytes) -> tuple[str, list[_PlyElement], int]:
    """Return (format, elements, body offset) of a PLY file."""
    fmt: str | None = None
    elements: list[_PlyElement] = []
    for lineno, line, after in _read_header_lines(path, data, "PLY", "end_header"):
        tokens = line.split()
        if lineno == 1:
            if line != "ply":
                raise _error(path, "not a PLY file: the first line is not 'ply'")
            continue
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        bad = _error(path, f"bad PLY header line {lineno}: {line[:80]!r}")
        if tokens[0] == "end_header":
            if fmt is None:
                raise _error(path, "bad PLY header: no format line")
            return fmt, elements, after
        if tokens[0] == "format":
            if len(tokens) != 3 or tokens[1] not in _PLY_FORMATS:
                raise bad
            fmt = tokens[1]
        elif tokens[0] == "element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise bad
            elements.append(_PlyElement(tokens[1], int(tokens[2]), []))
        elif tokens[0] == "property":
            if not elements:
                raise bad
            is_list = len(tokens) == 5 and tokens[1] == "list"
            if is_list and tokens[2] in _PLY_TYPES and tokens[3] in _PLY_TYPES:
                elements[-1].properties.append((tokens[4], None))
            elif len(tokens) == 3 and tokens[1] in _PLY_TYPES:
                elements[-1].properties.append((tokens[2], _PLY_TYPES[tokens[1]]))
            else:
                raise bad
        else:
            raise bad
    raise _error(path, "bad PLY header: no end_header line")  # pragma: no cover - _read_header_lines raises


def _read_head(path: Path) -> tuple[bytes, int]:
    """The first ``_HEADER_LIMIT`` bytes of ``path`` (where a PLY or PCD header must end) and its size."""
    with path.open("rb") as handle:
        return handle.read(_HEADER_LIMIT), os.fstat(handle.fileno()).st_size


def _nonblank(path: Path, offset: int, encoding: str = "latin-1") -> Iterator[str]:
    return (line for line in _text_lines(path, offset, encoding) if line)


def _read_ply(path: Path, limits: _Limits) -> _RawCloud:
    head, size = _read_head(path)
    fmt, elements, body = _parse_ply_header(path, head)
    names = [element.name for element in elements]
    if "vertex" not in names:
        raise _error(path, "PLY header declares no vertex element")
    index = names.index("vertex")
    vertex = elements[index]
    if vertex.count > limits.max_points:
        raise too_many_points(path, vertex.count, limits.max_points, "the PLY header")
    if vertex.has_list:
        raise _error(path, "PLY vertex element with list properties is not supported")
    prop_names = [name.lower() for name, _ in vertex.properties]
    if fmt == "ascii":
        start = sum(element.count for element in elements[:index])
        what = f"{vertex.count} vertices of {len(prop_names)} values"
        _check_bytes(path, limits, vertex.count, len(head) + vertex.count * len(prop_names) * 8, what)
        with contextlib.closing(_nonblank(path, body)) as rows:
            vertex_rows = itertools.islice(rows, start, None)
            values = _load_rows(path, vertex_rows, vertex.count, len(prop_names), "PLY vertex lines")
        if len(values) < vertex.count:
            raise _error(
                path,
                f"truncated PLY: the header declares {vertex.count} vertices but the body has "
                f"only {len(values)} vertex lines",
            )
        columns = {name: values[:, i] for i, name in reversed(list(enumerate(prop_names)))}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        offset = body
        for element in elements[:index]:
            if element.has_list:
                raise _error(
                    path,
                    f"PLY element {element.name!r} with list properties before the vertices is not supported",
                )
            offset += element.count * element.dtype(endian).itemsize
        dtype = vertex.dtype(endian)
        available = size - offset
        if available < vertex.count * dtype.itemsize:
            raise _error(
                path,
                f"truncated PLY: the header declares {vertex.count} vertices "
                f"({vertex.count * dtype.itemsize} bytes) but only {max(available, 0)} bytes follow",
            )
        what = f"{vertex.count} vertices of {dtype.itemsize} bytes"
        _check_bytes(path, limits, vertex.count, len(head) + vertex.count * dtype.itemsize, what)
        records = np.fromfile(path, dtype=dtype, count=vertex.count, offset=offset)
        columns = {name: records[f"p{i}"] for i, name in reversed(list(enumerate(prop_names)))}
    return _cloud_from_columns(path, columns, "PLY vertex element")


# ----------------------------------------------------------------------------------------------
# PCD
# ----------------------------------------------------------------------------------------------


def _pcd_type(path: Path, kind: str, size: int) -> str:
    codes = {("F", 4): "f4", ("F", 8): "f8"}
    codes.update({(k, s): f"{k.lower()}{s}" for k in "IU" for s in (1, 2, 4, 8)})
    code = codes.get((kind.upper(), size))
    if code is None:
        raise _error(path, f"bad PCD header: unsupported field type {kind} of size {size}")
    return code


def _parse_pcd_header(path: Path, data: bytes) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    for _, line, after in _read_header_lines(path, data, "PCD", "DATA"):
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, after
    raise _error(path, "bad PCD header: no DATA line")  # pragma: no cover - _read_header_lines raises


def _read_pcd(path: Path, limits: _Limits) -> _RawCloud:
    head, size = _read_head(path)
    header, body = _parse_pcd_header(path, head)
    try:
        fields = [name.lower() for name in header["FIELDS"]]
        sizes = [int(v) for v in header["SIZE"]]
        kinds = header["TYPE"]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        width, height = int(header["WIDTH"][0]), int(header.get("HEIGHT", ["1"])[0])
        num_points = int(header["POINTS"][0]) if "POINTS" in header else width * height
        mode = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as exc:
        raise _error(path, f"bad PCD header: missing or invalid entry ({type(exc).__name__}: {exc})") from exc
    if not fields or not len(fields) == len(sizes) == len(kinds) == len(counts):
        raise _error(path, "bad PCD header: FIELDS, SIZE, TYPE and COUNT differ in length")
    if num_points < 0 or min(counts) < 0:
        raise _error(path, "bad PCD header: negative POINTS or COUNT")
    if num_points > limits.max_points:
        raise too_many_points(path, num_points, limits.max_points, "the PCD header")
    codes = [_pcd_type(path, kind, nbytes) for kind, nbytes in zip(kinds, sizes, strict=True)]

    if mode == "binary_compressed":
        record_size = sum(nbytes * count for nbytes, count in zip(sizes, counts, strict=True))
        uncompressed = _check_pcd_compressed(path, size, body, num_points, record_size)
        # Open3D holds the file, the inflated body and float64 points and colours (48 bytes a point).
        what = f"{num_points} compressed points"
        _check_bytes(path, limits, num_points, size + uncompressed + 48 * num_points, what)
        return _read_with_open3d(path)
    if mode == "binary":
        layout = [
            (f"f{i}", "<" + code, (count,)) if count > 1 else (f"f{i}", "<" + code)
            for i, (code, count) in enumerate(zip(codes, counts, strict=True))
            if count > 0
        ]
        dtype = np.dtype(layout)
        available = size - body
        if available < num_points * dtype.itemsize:
            raise _error(
                path,
                f"truncated PCD: the header declares {num_points} points of {dtype.itemsize} bytes "
                f"but only {available} bytes follow",
            )
        what = f"{num_points} points of {dtype.itemsize} bytes"
        _check_bytes(path, limits, num_points, len(head) + num_points * dtype.itemsize, what)
        records = np.fromfile(path, dtype=dtype, count=num_points, offset=body)
        raw_columns = {i: records[f"f{i}"] for i, count in enumerate(counts) if count == 1}
    elif mode == "ascii":
        what = f"{num_points} points of {sum(counts)} values"
        _check_bytes(path, limits, num_points, len(head) + num_points * sum(counts) * 8, what)
        with contextlib.closing(_nonblank(path, body)) as rows:
            values = _load_rows(path, rows, num_points, sum(counts), "PCD ascii data")
        if len(values) < num_points:
            raise _error(
                path,
                f"truncated PCD: the header declares {num_points} points but the body has only "
                f"{len(values)} lines",
            )
        starts = np.cumsum([0, *counts])
        raw_columns = {i: values[:, starts[i]] for i, count in enumerate(counts) if count == 1}
    else:
        raise _error(path, f"bad PCD header: unknown DATA mode {mode!r} (ascii, binary, binary_compressed)")

    columns: dict[str, np.ndarray] = {}
    for i, column in reversed(list(raw_columns.items())):
        name = fields[i]
        if name in ("rgb", "rgba"):
            packed = (
                np.ascontiguousarray(column, dtype=np.float32).view(np.uint32)
                if codes[i] == "f4"
                else np.asarray(column).astype(np.uint32)
            )
            columns["red"] = ((packed >> 16) & 255).astype(np.uint8)
            columns["green"] = ((packed >> 8) & 255).astype(np.uint8)
            columns["blue"] = (packed & 255).astype(np.uint8)
        elif name != "_":
            columns[name] = column
    return _cloud_from_columns(path, columns, "PCD")


_LZF_MAX_RATIO = 100
"""LZF expands at most about 88-fold (a 3-byte back reference copies up to 264 bytes)."""


def _check_pcd_compressed(path: Path, size: int, body: int, num_points: int, record_size: int) -> int:
    """Check the sizes that open3d allocates from before it reads a ``binary_compressed`` body.

    The body is u32 compressed size, u32 uncompressed size, then LZF data that inflates to
    ``num_points`` records of ``record_size`` bytes (stored field after field).

    Returns:
        The uncompressed size.
    """
    available = size - body - 8
    if available < 0:
        raise _error(
            path, f"truncated PCD: {size - body} bytes after the header, too few for a compressed body"
        )
    with path.open("rb") as handle:
        handle.seek(body)
        compressed, uncompressed = struct.unpack("<II", handle.read(8))
    if compressed > available:
        raise _error(
            path,
            f"truncated PCD: the body declares {compressed} compressed bytes but only {available} follow",
        )
    if uncompressed != num_points * record_size:
        raise _error(
            path,
            f"corrupt PCD: the body declares {uncompressed} uncompressed bytes, but {num_points} points of "
            f"{record_size} bytes take {num_points * record_size}",
        )
    if uncompressed > max(compressed, 1) * _LZF_MAX_RATIO:
        raise _error(
            path, f"corrupt PCD: {compressed} LZF-compressed bytes cannot inflate to {uncompressed} bytes"
        )
    return uncompressed


def _read_with_open3d(path: Path) -> _RawCloud:
    """Read a file with Open3D (used for ``binary_compressed`` PCD): points and colours."""
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format=path.suffix.lower().lstrip("."))
    if cloud.is_empty():
        raise _error(path, "open3d could not read this binary_compressed PCD, or it holds no points")
    colors = None
    if cloud.has_colors():
        colors = np.round(np.clip(np.asarray(cloud.colors), 0.0, 1.0) * 255.0).astype(np.uint8)
    return _RawCloud(points=np.asarray(cloud.points, dtype=np.float64), colors=colors)


# ----------------------------------------------------------------------------------------------
# ASCII tables, LAS/LAZ, KITTI, numpy
# ----------------------------------------------------------------------------------------------

_TOKEN_SPLIT = re.compile(r"[,;\s]+")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _read_text(path: Path, limits: _Limits) -> _RawCloud:
    is_pts = path.suffix.lower() == ".pts"

    def rows() -> Iterator[str]:
        # Bytes that are not UTF-8 become U+FFFD: a bad row then fails to parse with its line
        # shown, and a stray Latin-1 byte in a comment or a header of names does no harm.
        for line in _text_lines(path):
            if line and not line.startswith("#") and not (is_pts and line.isdigit()):
                yield line

    # The first rows give the column names and the layout, and the line count bounds the rows, so
    # that the budget is checked before the parser allocates its (rows, columns) array.
    with contextlib.closing(rows()) as stream:
        first = next(stream, None)
        if first is None:
            return _RawCloud(points=np.zeros((0, 3)))
        tokens = [token for token in _TOKEN_SPLIT.split(first) if token]
        names = None
        if not any(_is_number(token) for token in tokens):  # a header line of column names
            names = [token.lstrip("/").lower() for token in tokens]
            first = next(stream, None)
            if first is None:
                return _RawCloud(points=np.zeros((0, 3)))
        delimiter = "," if "," in first else (";" if ";" in first else None)
        num_columns = len([token for token in _TOKEN_SPLIT.split(first) if token])
        if num_columns < 3:
            raise _error(path, f"expected at least 3 columns (x y z) per line, got {num_columns}")
        num_rows = _count_lines(path)
        if num_rows > limits.max_points:  # comments and blank lines may explain it: count rows
            num_rows = 1 + _count(stream, limits.max_points)
    if num_rows > limits.max_points:
        limit = f"the limit of {limits.max_points} points per file"
        raise _error(path, f"the file holds more points than {limit} ({RAISE_HINT})")
    what = f"{num_rows} rows of {num_columns} values"
    _check_bytes(path, limits, num_rows, num_rows * num_columns * 8 + _READ_BLOCK, what)
    with contextlib.closing(rows()) as stream:
        if names is not None:
            next(stream)
        values = _load_rows(path, stream, num_rows, num_columns, "point table", delimiter)
    if names is not None and len(names) == num_columns and all(axis in names for axis in "xyz"):
        columns = {name: values[:, i] for i, name in reversed(list(enumerate(names)))}
        return _cloud_from_columns(path, columns, "point table")
    cloud = _RawCloud(points=values[:, :3].copy())
    if num_columns in (4, 5, 7, 8):
        cloud.intensity = values[:, 3].astype(np.float32)
    if num_columns == 6 or num_columns >= 9:
        cloud.colors = _colors_to_uint8(values[:, 3:6])
    elif num_columns == 7:
        cloud.colors = _colors_to_uint8(values[:, 4:7])
    return cloud


_VLR_HEADER_SIZE = 54
"""Bytes of a LAS variable length record before its data."""

_LAZ_CHILD_MEMORY = 1 << 30
"""Address space of the LAZ decoding child beyond its buffers and input (interpreter, threads)."""

_LAZ_STEP_BYTES = 1 << 24
"""Decoded bytes the LAZ child hands back at a time (16 MiB): it never holds more than this."""

_LAZ_BUFFER_BYTES = 1.125
"""The parent's buffer of decoded records takes this many bytes a decoded byte at most (a growing
``bytearray`` over-allocates an eighth)."""

# Runs in a child interpreter that imports only lazrs (about 50 ms). The address-space cap turns
# a huge allocation from a corrupt chunk table into an abort of the child alone. The records are
# decoded and written back a step at a time, so the child's memory does not grow with the file.
_LAZ_CHILD = """
import sys
try:
    import resource
    limit = int(sys.argv[5])
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        limit = min(limit, soft)  # never raise a cap inherited from the parent
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
except (ImportError, ValueError, OSError):
    pass  # no address-space cap on this platform: an abort still ends only the child
try:
    import lazrs
    count, record_length = int(sys.argv[3]), int(sys.argv[4])
    step = max(1, int(sys.argv[6]) // record_length)
    with open(sys.argv[1], "rb") as source:
        source.seek(int(sys.argv[2]))
        selection = lazrs.DecompressionSelection(lazrs.SELECTIVE_DECOMPRESS_ALL)
        decompressor = lazrs.ParLasZipDecompressor(source, bytes.fromhex(sys.stdin.read()), selection)
        out, done = bytearray(min(step, count) * record_length), 0
        while done < count:
            if count - done < step:
                out = bytearray((count - done) * record_length)
            decompressor.decompress_many(out)
            sys.stdout.buffer.write(out)
            done += len(out) // record_length
        sys.stdout.buffer.flush()
except BaseException as exc:  # lazrs panics are BaseExceptions
    sys.stderr.write(" ".join(f"{type(exc).__name__}: {exc}".split())[:300])
    sys.exit(1)
"""


def _check_las_header(path: Path, limits: _Limits) -> tuple[int, int, int, bool]:
    """Check the fixed LAS header against the file's length and the caps before laspy or lazrs
    allocate from it.

    Returns:
        ``(point count, point record length, offset to the point data, compressed)``.
    """
    size = path.stat().st_size
    with path.open("rb") as handle:
        head = handle.read(375)  # the LAS 1.4 header; 1.0-1.3 headers are 227-235 bytes
    if head[:4] != b"LASF":
        raise _error(path, "not a LAS/LAZ file (no LASF signature)")
    minor = head[25] if len(head) > 25 else 0
    if len(head) < (255 if minor >= 4 else 227):
        raise _error(path, f"truncated LAS/LAZ: {size} bytes is too short for a LAS 1.{minor} header")
    header_size, offset, num_vlrs, point_format, record_length, count = struct.unpack_from(
        "<HIIBHI", head, 94
    )
    if minor >= 4:  # laspy takes the 64-bit count of LAS 1.4
        count = struct.unpack_from("<Q", head, 247)[0]
    compressed = bool(point_format & 0xC0)
    if offset > size:
        raise _error(path, f"truncated LAS/LAZ: the points start at byte {offset} but the file has {size}")
    # laspy reads as many VLRs as declared, past the end of the data: 4e9 empty ones for 0xFFFFFFFF.
    if num_vlrs * _VLR_HEADER_SIZE > offset - header_size:
        raise _error(
            path,
            f"corrupt LAS/LAZ header: {num_vlrs} VLRs do not fit in the {max(offset - header_size, 0)} bytes "
            "before the points",
        )
    if count > limits.max_points:
        raise too_many_points(path, count, limits.max_points, "the LAS header")
    available = size - offset
    # laspy's scaled x, y, z (24 bytes a point) and, for LAZ, the growing buffer of decoded records
    # and the block being read into it.
    held = count * (24 + record_length * (_LAZ_BUFFER_BYTES if compressed else 1))
    held += _READ_BLOCK if compressed else 0
    what = f"{count} points of {record_length} bytes"
    if not compressed:
        if count * record_length > available:
            raise _error(
                path,
                f"truncated LAS: the header declares {count} points of {record_length} bytes "
                f"({count * record_length} bytes) but only {available} bytes follow the header",
            )
        _check_bytes(path, limits, count, int(held), what)
        return count, record_length, offset, compressed
    check_inflation(path, count * record_length, available, f"corrupt LAZ: {count} point records")
    _check_bytes(path, limits, count, int(held), what)
    if available >= 8:
        with path.open("rb") as handle:
            handle.seek(offset)
            (table,) = struct.unpack("<q", handle.read(8))
            if table != -1:  # -1: written by a streaming writer, no chunk table
                if not offset + 8 <= table <= size - 8:
                    raise _error(path, f"corrupt LAZ: chunk table at byte {table}, outside the point data")
                handle.seek(table + 4)
                (num_chunks,) = struct.unpack("<I", handle.read(4))
                # lazrs reserves 16 bytes a chunk from this count (a corrupt count aborted it).
                # Every chunk holds at least one point and one byte.
                if num_chunks > max(count, 1) or num_chunks > table - offset:
                    raise _error(
                        path,
                        f"corrupt LAZ: the chunk table lists {num_chunks} chunks for {count} points "
                        f"in {table - offset} bytes",
                    )
    return count, record_length, offset, compressed


def _decode_laz(path: Path, offset: int, count: int, record_length: int, laszip_vlr: bytes) -> bytearray:
    """The (count * record_length) bytes of uncompressed point records of a LAZ file, decoded by
    lazrs in a child process with a capped address space and streamed back a step at a time.

    The buffer grows only with records the child really decoded, so a header that lies about its
    count costs what its data decodes to, not what it claims.

    Raises:
        InputError: the decoder failed, aborted or returned too few records.
        MemoryError: the child ran out of memory in Python (its cap leaves room for its steps).
    """
    num_bytes = count * record_length
    step = max(_LAZ_STEP_BYTES, record_length)
    limit = _LAZ_CHILD_MEMORY + 2 * step + 2 * (path.stat().st_size - offset)
    command = [sys.executable, "-P", "-c", _LAZ_CHILD, str(path), str(offset), str(count), str(record_length)]
    out = bytearray()
    # stderr goes to a file: a pipe that nobody reads could fill and stall the child.
    with tempfile.TemporaryFile() as errors:
        proc = subprocess.Popen(
            [*command, str(limit), str(step)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=errors,
            env={**os.environ, "RUST_BACKTRACE": "0"},  # keep a panic's report short
        )
        try:
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.write(laszip_vlr.hex().encode())
            proc.stdin.close()
            while len(out) < num_bytes:
                chunk = proc.stdout.read(min(_READ_BLOCK, num_bytes - len(out)))
                if not chunk:
                    break
                out += chunk
            code = proc.wait()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            for stream in (proc.stdin, proc.stdout):
                if stream is not None:
                    stream.close()
        errors.seek(0)
        lines = errors.read().decode("utf-8", "replace").splitlines()
        detail = " ".join(" ".join(line for line in lines if not line.startswith("note: ")).split())
    done = len(out)
    if code != 0 or done < num_bytes:
        if detail.startswith("MemoryError"):
            raise MemoryError(f"{path}: the LAZ decoder ran out of memory: {detail[:200]}")
        if code < 0:
            try:
                how = f"was killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"was killed by signal {-code}"
        else:
            how = f"failed (exit code {code})" if code else f"returned {done} of {num_bytes} bytes"
        raise _error(path, f"cannot decode LAZ (corrupt or truncated): the decoder {how}: {detail[-300:]}")
    return out


def _read_las(path: Path, limits: _Limits) -> _RawCloud:
    import laspy

    count, record_length, offset, compressed = _check_las_header(path, limits)
    try:
        # No EVLRs (their 64-bit lengths would be trusted) and no strict decoding of names.
        with laspy.open(path, read_evlrs=False, encoding_errors="replace") as reader:
            header = reader.header
            consistent = (
                header.point_count == count
                and header.offset_to_point_data == offset
                and header.point_format.size == record_length
                and header.are_points_compressed == compressed
            )
            if not consistent:
                raise _error(
                    path, "corrupt LAS/LAZ header: its point count, offset or record length disagree"
                )
            if compressed:
                vlrs = header.vlrs.get("LasZipVlr")
                if not vlrs:
                    raise _error(path, "corrupt LAZ: compressed points but no laszip VLR")
                if count:
                    buffer = _decode_laz(path, offset, count, record_length, vlrs[0].record_data)
                    packed = laspy.PackedPointRecord.from_buffer(buffer, header.point_format, count)
                    points = laspy.ScaleAwarePointRecord(
                        packed.array, header.point_format, header.scales, header.offsets
                    )
                else:
                    points = reader.read_points(0)
            else:
                points = reader.read_points(-1)
        las = laspy.LasData(header=header, points=points)
    except (InputError, MemoryError):
        raise
    except Exception as exc:  # laspy raises several types for corrupt files
        reason = f"{type(exc).__name__}: {exc}"
        raise _error(path, f"cannot read LAS/LAZ (corrupt or truncated): {reason}") from exc
    declared = int(las.header.point_count)
    points = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    points = points.astype(np.float64, copy=False)
    if len(points) != declared:
        raise _error(path, f"truncated LAS/LAZ: the header declares {declared} points, read {len(points)}")
    dims = set(las.point_format.dimension_names)
    colors = None
    if {"red", "green", "blue"} <= dims:
        colors = _colors_to_uint8(
            np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])
        )
    intensity = np.asarray(las.intensity, dtype=np.float32) if "intensity" in dims else None
    return _RawCloud(points=points, colors=colors, intensity=intensity)


def _read_kitti_bin(path: Path, limits: _Limits) -> _RawCloud:
    size = path.stat().st_size
    if size % 16:
        raise _error(
            path,
            f"not a KITTI velodyne scan: {size} bytes is not a multiple of 16 "
            "(float32 x, y, z, intensity records)",
        )
    if size // 16 > limits.max_points:
        raise too_many_points(path, size // 16, limits.max_points, "the file size")
    _check_bytes(path, limits, size // 16, size, f"{size // 16} points of 16 bytes")
    values = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    return _RawCloud(points=values[:, :3].astype(np.float64), intensity=values[:, 3].copy())


def _check_magic(path: Path, magic: bytes, problem: str) -> None:
    """Raise unless the file starts with ``magic``: a clear error before a dependency's cryptic one."""
    with path.open("rb") as handle:
        if handle.read(len(magic)) != magic:
            raise _error(path, problem)


def _read_npy(path: Path, limits: _Limits) -> _RawCloud:
    _check_magic(path, b"\x93NUMPY", "not a .npy file (bad magic bytes)")
    with path.open("rb") as handle:
        try:
            shape, dtype = read_npy_header(handle)
        except MemoryError:
            raise
        except Exception as exc:  # ValueError, SyntaxError from a mangled header dict, ...
            raise _error(path, f"corrupt .npy header: {type(exc).__name__}: {exc}") from exc
        available = path.stat().st_size - handle.tell()
        nbytes = check_npy_array(path, "the array", shape, dtype, available, limits.max_points)
        rows = shape[0] if shape else 1
        _check_bytes(path, limits, rows, nbytes, f"an array of shape {shape} {dtype}")
        handle.seek(0)
        try:
            array = np.lib.format.read_array(handle, allow_pickle=False)
        except MemoryError:
            raise
        except Exception as exc:  # truncated or corrupt .npy
            raise _error(path, f"corrupt .npy file: {type(exc).__name__}: {exc}") from exc
    if array.dtype.kind not in "fiu" or array.ndim != 2 or array.shape[1] < 3:
        raise _error(
            path, f"expected a numeric array of shape (N, 3) or (N, >=4), got {array.dtype} {array.shape}"
        )
    intensity = array[:, 3].astype(np.float32) if array.shape[1] >= 4 else None
    return _RawCloud(points=array[:, :3].astype(np.float64), intensity=intensity)


def _npz_conversion_bytes(headers: NpyHeaders) -> int:
    """What ``_read_npz`` and ``_build_frame`` allocate from the arrays: a converted copy of each
    (to float64 points, uint8 colours, float32 intensity) and the ``Frame`` of its points."""
    shape = headers["points"][0] if "points" in headers else ()
    num_points = shape[0] if shape else 0
    copies = sum(math.prod(shape) * dtype.itemsize for shape, dtype in headers.values())
    return copies + num_points * FRAME_BYTES_PER_POINT


def _read_npz(path: Path, limits: _Limits) -> _RawCloud:
    _check_magic(path, b"PK\x03\x04", "not an .npz archive (no zip signature)")
    wanted = ("points", "boxes", "labels", "colors", "intensity")
    keys, arrays = load_npz(
        path,
        wanted,
        max_points=limits.max_points,
        max_read_bytes=limits.max_read_bytes,
        conversion_bytes=_npz_conversion_bytes,
    )

    if "points" not in arrays:
        raise _error(path, f"the .npz has no 'points' array (keys: {', '.join(keys) or 'none'})")
    points = arrays["points"]
    if points.dtype.kind not in "fiu" or points.ndim != 2 or points.shape[1] != 3:
        raise _error(path, f"points: expected a numeric (N, 3) array, got {points.dtype} {points.shape}")
    num = len(points)
    cloud = _RawCloud(points=points.astype(np.float64, copy=False))

    if ("boxes" in arrays) != ("labels" in arrays):
        raise _error(path, "the .npz must hold both 'boxes' and 'labels' or neither")
    if "boxes" in arrays:
        boxes, labels = arrays["boxes"], arrays["labels"]
        if boxes.dtype.kind not in "fiu" or boxes.ndim != 2 or boxes.shape[1] != 7:
            raise _error(path, f"boxes: expected a numeric (M, 7) array, got {boxes.dtype} {boxes.shape}")
        if labels.dtype.kind not in "US" or labels.ndim != 1:
            raise _error(path, f"labels: expected a 1-D string array, got {labels.dtype} {labels.shape}")
        if len(labels) != len(boxes):
            raise _error(path, f"labels: {len(labels)} labels for {len(boxes)} boxes")
        names = [
            label.decode("utf-8", "replace") if isinstance(label, bytes) else str(label)
            for label in labels.tolist()
        ]
        empty = [i for i, name in enumerate(names) if not name.strip()]
        if empty:
            raise _error(path, f"labels: {len(empty)} empty class names (boxes {empty[:10]})")
        cloud.boxes, cloud.labels = boxes.astype(np.float64), names

    if "colors" in arrays:
        colors = arrays["colors"]
        if colors.ndim != 2 or colors.shape != (num, 3):
            raise _error(path, f"colors: expected shape ({num}, 3) for {num} points, got {colors.shape}")
        cloud.colors = _colors_to_uint8(colors)
        if cloud.colors is None:
            raise _error(path, "colors: expected uint8 RGB, integers 0-255 or floats in [0, 1]")
    if "intensity" in arrays:
        intensity = arrays["intensity"]
        if intensity.dtype.kind not in "fiu" or intensity.shape != (num,):
            raise _error(
                path, f"intensity: expected a numeric ({num},) array, got {intensity.dtype} {intensity.shape}"
            )
        cloud.intensity = intensity.astype(np.float32, copy=False)
    return cloud


_READERS: dict[str, Callable[[Path, _Limits], _RawCloud]] = {
    ".ply": _read_ply,
    ".pcd": _read_pcd,
    ".xyz": _read_text,
    ".txt": _read_text,
    ".pts": _read_text,
    ".csv": _read_text,
    ".las": _read_las,
    ".laz": _read_las,
    ".bin": _read_kitti_bin,
    ".npy": _read_npy,
    ".npz": _read_npz,
}


# ----------------------------------------------------------------------------------------------
# Frame assembly
# ----------------------------------------------------------------------------------------------


def _vocabulary(path: Path, labels: list[str], class_names: Sequence[str] | None) -> tuple[str, ...]:
    if class_names is not None:
        vocab = tuple(str(name) for name in class_names)
        unknown = sorted(set(labels) - set(vocab))
        if unknown:
            raise _error(path, f"unknown class names {unknown}; known class names: {list(vocab)}")
        return vocab
    return tuple(sorted(set(labels))) if labels else CLASS_NAMES


def _near_box(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(N,) bool: the (N, 3) points within the box's bounding cylinder (radius half its xy
    diagonal) grown by 1 mm, a superset of ``points_in_box``. Computed a column at a time in
    float64, the differences are the ones ``points_in_box`` rotates, so no point inside is lost."""
    radius = float(np.hypot(box[3], box[4])) / 2 + 1e-3
    near = np.abs(np.subtract(points[:, 2], box[2], dtype=np.float64)) <= box[5] / 2 + 1e-3
    near &= np.abs(np.subtract(points[:, 0], box[0], dtype=np.float64)) <= radius
    near &= np.abs(np.subtract(points[:, 1], box[1], dtype=np.float64)) <= radius
    return near


def _build_frame(path: Path, cloud: _RawCloud, class_names: Sequence[str] | None) -> Frame:
    points = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    num = len(points)
    if num == 0:
        raise _error(path, "empty point cloud (0 points)")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise _error(path, f"{int(bad.sum())} of {num} points have NaN or Inf coordinates")
    if cloud.intensity is not None and not np.isfinite(cloud.intensity).all():
        count = int((~np.isfinite(cloud.intensity)).sum())
        raise _error(path, f"{count} of {num} intensity values are NaN or Inf")

    offset = np.zeros(3)
    span = max(float(points.max()), -float(points.min()))  # max |coordinate| without an (N, 3) copy
    local = np.empty(points.shape, np.float32)
    with np.errstate(over="ignore", invalid="ignore"):  # coordinates near 1e308: checked below
        if span > LARGE_COORDINATE_M:
            offset = np.round(points.mean(axis=0))
        # Subtracted in float64 and rounded once into float32, without a float64 temporary.
        np.subtract(points, offset, out=local, casting="same_kind")
    if not (np.isfinite(local).all() and np.isfinite(offset).all()):
        raise _error(path, f"coordinates up to {span:.3g} m are too far apart for float32 points")

    labels = cloud.labels or []
    vocab = _vocabulary(path, labels, class_names)
    boxes = np.zeros((0, 7)) if cloud.boxes is None else np.array(cloud.boxes, dtype=np.float64)
    if len(boxes):
        bad_boxes = ~np.isfinite(boxes).all(axis=1)
        if bad_boxes.any():
            raise _error(path, f"{int(bad_boxes.sum())} of {len(boxes)} boxes hold NaN or Inf values")
        if (boxes[:, 3:6] < 0).any():
            raise _error(path, f"{int((boxes[:, 3:6] < 0).any(axis=1).sum())} boxes have negative sizes")
        boxes[:, :3] -= offset
    index = {name: i for i, name in reversed(list(enumerate(vocab)))}
    point_instance_ids = np.zeros(num, np.int64)
    num_inside = np.zeros(len(boxes), np.int64)
    for i, box in enumerate(boxes):
        # The exact test on the points near the box only: it costs about 80 bytes a point given.
        near = np.flatnonzero(_near_box(local, box))
        inside = near[points_in_box(local[near], box)]
        num_inside[i] = len(inside)
        inside = inside[point_instance_ids[inside] == 0]
        point_instance_ids[inside] = i + 1
    sensor_ids = np.zeros(num, np.int16)
    # Read-only arrays that own their memory are shared by the Frame, not copied again.
    for array in (local, point_instance_ids, sensor_ids):
        array.flags.writeable = False
    box_labels = BoxLabels(
        boxes=boxes,
        class_ids=np.array([index[name] for name in labels], dtype=np.int32),
        instance_ids=np.arange(1, len(boxes) + 1, dtype=np.int64),
        num_points=num_inside,
    )
    try:
        return Frame(
            name=path.name,
            points=local,
            sensor_ids=sensor_ids,
            T_vehicle_sensor=np.eye(4)[None],
            T_world_vehicle=np.eye(4),
            labels=box_labels,
            point_instance_ids=point_instance_ids,
            class_names=vocab,
            colors=cloud.colors,
            intensity=cloud.intensity,
            origin_offset=offset,
        )
    except InputError as exc:
        raise _error(path, str(exc)) from exc


def read_frame(
    path: str | os.PathLike,
    *,
    class_names: Sequence[str] | None = None,
    max_points: int | None = None,
    max_read_bytes: int | None = None,
) -> Frame:
    """Read one point-cloud file as a one-sensor ``Frame``.

    Args:
        path: a file whose suffix is in ``SUPPORTED_SUFFIXES`` (case-insensitive).
        class_names: class vocabulary for the boxes of an ``.npz`` scene. ``None`` takes the sorted
            unique labels of the file (``CLASS_NAMES`` when the file has no boxes).
        max_points: refuse files declaring more points; ``None`` takes ``$FACTORYDET_MAX_POINTS``,
            else ``io.limits.MAX_POINTS`` (50 million).
        max_read_bytes: refuse files whose read would allocate more bytes at its peak (decoded
            records and every conversion copy); ``None`` takes ``$FACTORYDET_MAX_READ_BYTES``, else
            ``io.limits.MAX_READ_BYTES`` (8 GB).

    Returns:
        A frame named after the file with ``points`` (N, 3) float32 (recentred by
        ``origin_offset`` (3,) float64 when a coordinate exceeds ``LARGE_COORDINATE_M``),
        ``sensor_ids`` (N,) all 0, identity ``T_vehicle_sensor`` (1, 4, 4) and ``T_world_vehicle``
        (4, 4), optional ``colors`` (N, 3) uint8 and ``intensity`` (N,) float32. For ``.npz`` the
        boxes become ``labels`` (M, 7) with instance ids 1..M, and ``point_instance_ids`` (N,) holds
        the id of the first box containing each point, 0 for none.

    Raises:
        InputError: one line naming the file and the problem (missing, unsupported suffix,
            truncated or corrupt, NaN/Inf coordinates, no points, more than ``max_points``, more
            than ``max_read_bytes``, wrong array shapes, unknown classes).
        MemoryError: never turned into an ``InputError`` (the caps are meant to prevent it).
    """
    path = Path(path)
    limits = _Limits(resolve_max_points(max_points), resolve_max_read_bytes(max_read_bytes))
    suffix = path.suffix.lower()
    if suffix not in _READERS:
        kind = suffix or "(no suffix)"
        raise _error(path, f"unsupported file type {kind!r}; supported: {_supported_list()}")
    if not path.exists():
        raise _error(path, "file not found")
    if not path.is_file():
        raise _error(path, "not a regular file")
    try:
        # Casting hostile values (signalling NaNs, 1e300 into float32) warns; _build_frame reports
        # non-finite values itself, in one line.
        with np.errstate(invalid="ignore", over="ignore"):
            cloud = _READERS[suffix](path, limits)
    except (InputError, MemoryError):
        raise
    except OSError as exc:
        raise _error(path, f"cannot read: {exc.strerror or exc}") from exc
    except Exception as exc:  # any dependency failure on a corrupt file becomes one line
        raise _error(path, f"cannot read {suffix} file: {type(exc).__name__}: {exc}") from exc
    return _build_frame(path, cloud, class_names)


# ----------------------------------------------------------------------------------------------
# Writers
# ----------------------------------------------------------------------------------------------


def _world_points(frame: Frame) -> np.ndarray:
    """(N, 3) float64 points in the vehicle frame with ``origin_offset`` added back."""
    return apply_transforms(frame.T_vehicle_sensor, frame.sensor_ids, frame.points) + frame.origin_offset


def _float_dtype(frame: Frame) -> type[np.floating]:
    """float64 when the frame was recentred (so the offset survives), else float32."""
    return np.float64 if np.any(frame.origin_offset != 0) else np.float32


def _write_ply(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    fields: list[tuple[str, str, str]] = [(axis, "<f8", "double") for axis in "xyz"]
    if frame.colors is not None:
        fields += [(name, "u1", "uchar") for name in ("red", "green", "blue")]
    if frame.intensity is not None:
        fields.append(("intensity", "<f4", "float"))
    records = np.empty(len(points), dtype=[(name, code) for name, code, _ in fields])
    for axis, name in enumerate("xyz"):
        records[name] = points[:, axis]
    if frame.colors is not None:
        for channel, name in enumerate(("red", "green", "blue")):
            records[name] = frame.colors[:, channel]
    if frame.intensity is not None:
        records["intensity"] = frame.intensity
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by factorydet_core",
        f"element vertex {len(points)}",
    ]
    header += [f"property {ply_type} {name}" for name, _, ply_type in fields]
    header.append("end_header\n")
    with atomic_path(path) as tmp, tmp.open("wb") as handle:
        handle.write("\n".join(header).encode("ascii"))
        handle.write(records.tobytes())


def _write_pcd(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    coord = "<f8" if _float_dtype(frame) is np.float64 else "<f4"
    fields: list[tuple[str, str]] = [("x", coord), ("y", coord), ("z", coord)]
    if frame.intensity is not None:
        fields.append(("intensity", "<f4"))
    if frame.colors is not None:
        fields.append(("rgb", "<u4"))
    records = np.empty(len(points), dtype=fields)
    for axis, name in enumerate("xyz"):
        records[name] = points[:, axis]
    if frame.intensity is not None:
        records["intensity"] = frame.intensity
    if frame.colors is not None:
        rgb = frame.colors.astype(np.uint32)
        records["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    sizes = " ".join(str(np.dtype(code).itemsize) for _, code in fields)
    # rgb is declared as a float (TYPE F), the PCL convention for packed colour.
    types = " ".join("F" for _ in fields)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (written by factorydet_core)\nVERSION 0.7\n"
        f"FIELDS {' '.join(name for name, _ in fields)}\nSIZE {sizes}\nTYPE {types}\n"
        f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {len(points)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n"
    )
    with atomic_path(path) as tmp, tmp.open("wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(records.tobytes())


def _write_text(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    columns, formats, names = [points], ["%.6f"] * 3, ["x", "y", "z"]
    if frame.intensity is not None:
        columns.append(frame.intensity.astype(np.float64)[:, None])
        formats.append("%.9g")
        names.append("intensity")
    if frame.colors is not None:
        columns.append(frame.colors.astype(np.float64))
        formats += ["%d"] * 3
        names += ["red", "green", "blue"]
    suffix = path.suffix.lower()
    delimiter = "," if suffix == ".csv" else " "
    with atomic_path(path) as tmp, tmp.open("w", encoding="utf-8") as handle:
        if suffix == ".pts":
            handle.write(f"{len(points)}\n")
        else:
            handle.write(f"# {' '.join(names)}\n")
        np.savetxt(handle, np.hstack(columns), fmt=formats, delimiter=delimiter)


def _write_las(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    import laspy

    header = laspy.LasHeader(point_format=2 if frame.colors is not None else 0, version="1.2")
    offsets = np.round(points.mean(axis=0)) if len(points) else np.zeros(3)
    if len(points) and np.abs(points - offsets).max() / LAS_SCALE >= 2**31 - 1:
        raise _error(path, f"the cloud spans too far for LAS integer coordinates at scale {LAS_SCALE} m")
    header.scales = np.full(3, LAS_SCALE)
    header.offsets = offsets
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if frame.intensity is not None:
        las.intensity = np.clip(np.round(frame.intensity), 0, 65535).astype(np.uint16)
    if frame.colors is not None:
        colors16 = frame.colors.astype(np.uint16) * 257
        las.red, las.green, las.blue = colors16[:, 0], colors16[:, 1], colors16[:, 2]
    with atomic_path(path) as tmp:
        las.write(str(tmp), do_compress=path.suffix.lower() == ".laz")


def _write_kitti_bin(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    intensity = np.zeros(len(points)) if frame.intensity is None else frame.intensity
    with atomic_path(path) as tmp:
        np.column_stack([points, intensity]).astype("<f4").tofile(tmp)


def _write_npy(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    array = points if frame.intensity is None else np.column_stack([points, frame.intensity])
    with atomic_path(path) as tmp, tmp.open("wb") as handle:
        np.save(handle, array.astype(_float_dtype(frame)), allow_pickle=False)


def _write_npz(path: Path, frame: Frame, points: np.ndarray, boxes: np.ndarray) -> None:
    dtype = _float_dtype(frame)
    labels = [frame.class_names[i] for i in frame.labels.class_ids.tolist()]
    arrays: dict[str, np.ndarray] = {
        "points": points.astype(dtype),
        "boxes": boxes.astype(dtype),
        "labels": np.array(labels, dtype=np.str_),
    }
    if frame.colors is not None:
        arrays["colors"] = np.asarray(frame.colors, dtype=np.uint8)
    if frame.intensity is not None:
        arrays["intensity"] = np.asarray(frame.intensity, dtype=np.float32)
    arrays["point_instance"] = np.asarray(frame.point_instance_ids, dtype=np.int64)
    arrays["coordinate_note"] = np.array(
        "written by factorydet_core; boxes are (cx, cy, cz, dx, dy, dz, yaw), z up, metres, "
        "yaw counter-clockwise about +z"
    )
    save_npz(path, arrays)


_WRITERS: dict[str, Callable[[Path, Frame, np.ndarray, np.ndarray], None]] = {
    ".ply": _write_ply,
    ".pcd": _write_pcd,
    ".xyz": _write_text,
    ".txt": _write_text,
    ".pts": _write_text,
    ".csv": _write_text,
    ".las": _write_las,
    ".laz": _write_las,
    ".bin": _write_kitti_bin,
    ".npy": _write_npy,
    ".npz": _write_npz,
}


def write_frame(path: str | os.PathLike, frame: Frame) -> None:
    """Write ``frame`` to one file, the format picked by the suffix of ``path``.

    Points (N, 3) are moved into the vehicle frame with ``T_vehicle_sensor`` and get
    ``origin_offset`` added back in float64; boxes (M, 7) get the same offset. What each format keeps:

    - ``.ply``: binary little endian, x, y, z double, red/green/blue uchar, intensity float.
    - ``.pcd``: binary, x, y, z float (double when the frame was recentred), intensity, packed rgb.
    - ``.xyz``, ``.txt``, ``.csv``, ``.pts``: ascii ``x y z [intensity] [r g b]`` (6 decimals).
    - ``.las``, ``.laz``: scale ``LAS_SCALE``, colours as 16-bit, intensity rounded to uint16.
    - ``.bin``: KITTI float32 (N, 4), intensity 0 when the frame has none.
    - ``.npy``: (N, 3) or (N, 4) with intensity, float64 when the frame was recentred.
    - ``.npz``: the neutral scene format (points, boxes, labels, colors, intensity) via ``save_npz``.

    Only ``.npz`` keeps boxes and labels. The file is replaced atomically.

    Raises:
        InputError: unsupported suffix, a cloud too large for the format, or the file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _WRITERS:
        kind = suffix or "(no suffix)"
        raise _error(path, f"cannot write file type {kind!r}; supported: {_supported_list()}")
    points = _world_points(frame)
    boxes = np.array(frame.labels.boxes, dtype=np.float64)
    boxes[:, :3] += frame.origin_offset
    try:
        _WRITERS[suffix](path, frame, points, boxes)
    except OSError as exc:
        raise _error(path, f"cannot write: {exc.strerror or exc}") from exc
