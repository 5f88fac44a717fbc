"""Export and import of a session's labels: JSON in the neutral box format of the shared real
data, KITTI-style label text files, and neutral ``.npz`` scenes with per-point labels.

Boxes everywhere are ``(cx, cy, cz, dx, dy, dz, yaw)`` in the vehicle frame, z up, metres, yaw
counter-clockwise about +z. The KITTI files use KITTI's camera axes (x right, y down, z forward)
with the identity extrinsic between the vehicle and the camera:

    x_cam = -y,  y_cam = -z,  z_cam = x,
    dimensions = (height, width, length) = (dz, dy, dx),
    location = the centre of the box's bottom face, rotation_y = -yaw - pi/2.

Import never drops a box silently: one that repeats a label (same class, IoU >= 0.95) is skipped and
listed; one that overlaps a label of another class (IoU >= 0.5) is imported and listed as a
conflict for a person to resolve.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from factorydet_core.boxes import box_iou_3d
from factorydet_core.geometry import points_in_box, wrap_angle
from factorydet_core.proposals.merge import merge_frame
from factorydet_core.session.store import SessionDB
from factorydet_core.types import InputError

FORMATS = ("json", "kitti", "npz")
BOX_CONVENTION = (
    "cx, cy, cz, dx, dy, dz, yaw in the vehicle frame; right-handed, z up, metres; dx, dy, dz are full "
    "edge lengths; yaw in radians in [-pi, pi), counter-clockwise about +z from +x to the box's x axis"
)
DUPLICATE_IOU = 0.95
CONFLICT_IOU = 0.5


def _frames(db: SessionDB, frame_indices) -> list[int]:
    if frame_indices is None:
        return list(range(db.dataset.num_frames))
    return [int(i) for i in frame_indices]


def export_json(db: SessionDB, path: str | os.PathLike, frame_indices=None) -> dict:
    """Write every frame's labels to one JSON file; returns what was written."""
    frames = []
    for index in _frames(db, frame_indices):
        labels = db.labels(index)
        frames.append(
            {
                "frame_index": index,
                "frame": db.dataset.frame(index).name,
                "boxes": [[round(v, 6) for v in lab.box] for lab in labels],
                "labels": [lab.class_name for lab in labels],
                "label_ids": [lab.id for lab in labels],
                "origins": [lab.origin for lab in labels],
            }
        )
    record = {
        "format": "factorydet-labels",
        "version": 1,
        "data": db.meta().get("data"),
        "data_hash": db.meta().get("data_hash"),
        "class_names": list(db.class_names),
        "box_convention": BOX_CONVENTION,
        "frames": frames,
    }
    Path(path).write_text(json.dumps(record, indent=1) + "\n")
    return record


def kitti_line(box, class_name: str) -> str:
    """One KITTI label line for a box (2D box, truncation, occlusion and alpha left 0)."""
    cx, cy, cz, dx, dy, dz, yaw = (float(v) for v in box)
    x_cam, y_cam, z_cam = -cy, -(cz - dz / 2), cx
    rotation_y = float(wrap_angle(-yaw - np.pi / 2))
    return (
        f"{class_name} 0.00 0 0.00 0.00 0.00 0.00 0.00 {dz:.4f} {dy:.4f} {dx:.4f} "
        f"{x_cam:.4f} {y_cam:.4f} {z_cam:.4f} {rotation_y:.6f}"
    )


def parse_kitti_line(line: str, where: str = "") -> tuple[str, np.ndarray]:
    """``(class_name, box (7,))`` of a KITTI label line."""
    parts = line.split()
    if len(parts) < 15:
        raise InputError(f"{where}: a KITTI label line has 15 fields, got {len(parts)}: {line!r}")
    try:
        h, w, length, x_cam, y_cam, z_cam, rotation_y = (float(v) for v in parts[8:15])
    except ValueError:
        raise InputError(f"{where}: non-numeric KITTI fields in {line!r}") from None
    yaw = float(wrap_angle(-rotation_y - np.pi / 2))
    return parts[0], np.array([z_cam, -x_cam, -y_cam + h / 2, length, w, h, yaw])


def export_kitti(db: SessionDB, folder: str | os.PathLike, frame_indices=None) -> list[Path]:
    """One ``NNNNNN.txt`` per frame (its index) in ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in _frames(db, frame_indices):
        lines = [kitti_line(lab.box, lab.class_name) for lab in db.labels(index)]
        path = folder / f"{index:06d}.txt"
        path.write_text("".join(line + "\n" for line in lines))
        paths.append(path)
    return paths


def scene_arrays(db: SessionDB, frame_index: int) -> dict[str, np.ndarray]:
    """A frame in the neutral ``.npz`` scene format: merged points in the vehicle frame, the
    session's boxes and classes, and per-point instance (index into the boxes, plus 1; 0 none)
    and class (into ``semantic_names``, 0 none) labels from the boxes."""
    frame = db.dataset.frame(frame_index)
    points = merge_frame(frame).points
    labels = db.labels(frame_index)
    boxes = np.array([lab.box for lab in labels], np.float32).reshape(-1, 7)
    names = ("none", *db.class_names)
    point_instance = np.zeros(len(points), np.int32)
    point_semantic = np.zeros(len(points), np.int32)
    for k, lab in enumerate(labels):
        inside = points_in_box(points, np.asarray(lab.box, np.float64)) & (point_instance == 0)
        point_instance[inside] = k + 1
        point_semantic[inside] = names.index(lab.class_name)
    return {
        "points": points.astype(np.float32),
        "boxes": boxes,
        "labels": np.array([lab.class_name for lab in labels], dtype=str),
        "point_instance": point_instance,
        "point_semantic": point_semantic,
        "semantic_names": np.array(names, dtype=str),
        "frame_index": np.array(frame_index),
        "coordinate_note": np.array(BOX_CONVENTION),
    }


def export_npz(db: SessionDB, folder: str | os.PathLike, frame_indices=None) -> list[Path]:
    """One ``frame_NNNNN.npz`` scene per frame in ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in _frames(db, frame_indices):
        path = folder / f"frame_{index:05d}.npz"
        np.savez_compressed(path, **scene_arrays(db, index))
        paths.append(path)
    return paths


def export_labels(db: SessionDB, fmt: str, out: str | os.PathLike, frame_indices=None) -> list[Path]:
    """Export in ``fmt`` (one of ``FORMATS``): a JSON file, or a folder of KITTI or npz files."""
    if fmt == "json":
        export_json(db, out, frame_indices)
        return [Path(out)]
    if fmt == "kitti":
        return export_kitti(db, out, frame_indices)
    if fmt == "npz":
        return export_npz(db, out, frame_indices)
    raise InputError(f"unknown label format {fmt!r}; choose from {', '.join(FORMATS)}")


def read_labels(
    path: str | os.PathLike, fmt: str | None = None, data_hash: str | None = None
) -> list[tuple[int, np.ndarray, str]]:
    """``(frame_index, box, class_name)`` of every box in an exported file or folder.

    Args:
        fmt: 'json', 'kitti' (a folder of ``NNNNNN.txt`` or one such file) or 'npz' (a folder of
            ``frame_NNNNN.npz`` or one file); guessed from the path when ``None``.
        data_hash: the session's data set hash; a JSON file exported from another data set is
            refused.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    if fmt is None:
        if path.suffix == ".json":
            fmt = "json"
        elif path.suffix == ".npz" or (path.is_dir() and any(path.glob("*.npz"))):
            fmt = "npz"
        else:
            fmt = "kitti"
    items: list[tuple[int, np.ndarray, str]] = []
    if fmt == "json":
        try:
            record = json.loads(path.read_text())
            if data_hash is not None and record.get("data_hash") not in (None, data_hash):
                raise InputError(
                    f"{path}: exported from another data set (hash {record['data_hash']}, the session's "
                    f"is {data_hash}); boxes would land on the wrong frames"
                )
            for frame in record["frames"]:
                for box, name in zip(frame["boxes"], frame["labels"], strict=True):
                    items.append((int(frame["frame_index"]), np.asarray(box, np.float64), str(name)))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: not a factorydet label file ({type(exc).__name__}: {exc})") from None
    elif fmt == "kitti":
        files = sorted(path.glob("*.txt")) if path.is_dir() else [path]
        for file in files:
            try:
                index = int(file.stem)
            except ValueError:
                raise InputError(
                    f"{file}: KITTI label files are named by frame index, e.g. 000003.txt"
                ) from None
            for n, line in enumerate(file.read_text().splitlines()):
                if line.strip():
                    name, box = parse_kitti_line(line, f"{file}:{n + 1}")
                    items.append((index, box, name))
    elif fmt == "npz":
        files = sorted(path.glob("*.npz")) if path.is_dir() else [path]
        for file in files:
            try:
                with np.load(file, allow_pickle=False) as data:
                    index = (
                        int(data["frame_index"])
                        if "frame_index" in data.files
                        else int(file.stem.split("_")[-1])
                    )
                    boxes, names = np.asarray(data["boxes"], np.float64), [str(n) for n in data["labels"]]
            except (OSError, ValueError, KeyError) as exc:
                raise InputError(f"{file}: not a scene file with boxes and labels ({exc})") from None
            if (len(boxes) and (boxes.ndim != 2 or boxes.shape[1] != 7)) or len(boxes) != len(names):
                raise InputError(f"{file}: boxes {boxes.shape} and labels ({len(names)}) do not pair up")
            items += [(index, box, name) for box, name in zip(boxes.reshape(-1, 7), names, strict=True)]
    else:
        raise InputError(f"unknown label format {fmt!r}; choose from {', '.join(FORMATS)}")
    return items


def import_labels(db: SessionDB, path: str | os.PathLike, author: str, fmt: str | None = None) -> dict:
    """Add the boxes of an exported file to the session as one undoable edit.

    Returns:
        ``{"imported": n, "duplicates": [...], "conflicts": [...], "edit": id}``; a duplicate
        repeats a label (same class, IoU >= 0.95) and is skipped, a conflict overlaps a label of
        another class (IoU >= 0.5) and is imported, both listed with the label they meet.
    """
    items = read_labels(path, fmt, db.meta().get("data_hash"))
    unknown = sorted({name for _, _, name in items} - set(db.class_names))
    if unknown:
        raise InputError(f"{path}: classes {unknown} are not the session's {list(db.class_names)}")
    duplicates, conflicts, keep = [], [], []
    names = db.class_names
    for frame_index, box, name in items:
        boxes, class_ids, label_ids = db.frame_boxes(frame_index)
        # Earlier boxes of the same file count as labels too, so a file's own repeats are caught.
        earlier = [(b, n) for f, b, n in keep if f == frame_index]
        all_boxes = np.concatenate([boxes, np.array([b for b, _ in earlier]).reshape(-1, 7)])
        all_names = [names[int(c)] for c in class_ids] + [n for _, n in earlier]
        all_ids = [int(i) for i in label_ids] + [None] * len(earlier)
        if len(all_boxes):
            iou = box_iou_3d(box[None], all_boxes)[0]
            same = np.array([n == name for n in all_names])

            found = None
            if same.any() and iou[same].max() >= DUPLICATE_IOU:
                found, kind = int(np.flatnonzero(same)[iou[same].argmax()]), duplicates
            elif (~same).any() and iou[~same].max() >= CONFLICT_IOU:
                found, kind = int(np.flatnonzero(~same)[iou[~same].argmax()]), conflicts
            if found is not None:
                kind.append(
                    {
                        "frame_index": frame_index,
                        "class": name,
                        "box": [round(float(v), 4) for v in box],
                        "label_id": all_ids[found],
                        "label_class": all_names[found],
                        "iou": round(float(iou[found]), 3),
                    }
                )
                if kind is duplicates:
                    continue
        keep.append((frame_index, box, name))
    added = db.add_labels(keep, author, origin="import")
    return {"imported": len(added), "duplicates": duplicates, "conflicts": conflicts, "edit": added.edit_id}
