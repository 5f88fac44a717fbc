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
conflict for a person to resolve. Every box and frame index is checked first (``store.check_box``):
a file with an absurd one is refused whole, with a one-line error naming it. Exports are written
whole or not at all (``io.atomic``), into folders made if missing; a target that cannot be written
is a one-line ``InputError`` naming it.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from factorydet_core.boxes import box_iou_3d
from factorydet_core.geometry import point_box_ids, wrap_angle
from factorydet_core.io.atomic import atomic_path, write_text_atomic
from factorydet_core.io.npz import load_npz
from factorydet_core.proposals.merge import merge_frame
from factorydet_core.session.store import Label, SessionDB, check_box, check_frame_index
from factorydet_core.settings_check import exception_line
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


@contextlib.contextmanager
def _writing(target: Path) -> Iterator[None]:
    """An export's writes to ``target``: a failure (a missing or read-only folder, a folder where
    a file goes) is an ``InputError`` naming ``target``, not the temporary file written first."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"cannot write {target}: {exc.strerror or exception_line(exc, 200)}") from None


def _export_folder(folder: str | os.PathLike) -> Path:
    """The folder a KITTI or npz export writes into, made with its parents if missing."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"cannot write {folder}: a file, not a folder (this format writes a folder)")
    with _writing(folder):
        folder.mkdir(parents=True, exist_ok=True)
    return folder


def _truth(labelled: dict[int, list[Label]]) -> dict[int, list[Label]]:
    """The labels an export writes: a person's (the model's pre-labels nobody confirmed yet are
    not truth, and are left out)."""
    return {index: [lab for lab in labels if lab.reviewed] for index, labels in labelled.items()}


def export_json(db: SessionDB, path: str | os.PathLike, frame_indices=None) -> dict:
    """Write every frame's labels to one JSON file (whole or not at all), making its folder if
    missing, as the other commands' outputs do; returns what was written.

    Raises:
        InputError: ``path`` is a folder, or cannot be written (naming it).
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"cannot write {path}: a folder; give a .json file, or --format kitti or npz")
    frames = []
    labelled = db.frame_labels(_frames(db, frame_indices))
    num_unreviewed = sum(not lab.reviewed for labels in labelled.values() for lab in labels)
    for index, labels in _truth(labelled).items():
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
        "unreviewed_pre_labels_left_out": num_unreviewed,
        "frames": frames,
    }
    with _writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps(record, indent=1) + "\n")
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
    if not np.isfinite([h, w, length, x_cam, y_cam, z_cam, rotation_y]).all():
        # float() reads "nan" and "inf"; caught here, before the angle arithmetic warns on them
        raise InputError(f"{where}: non-finite KITTI fields in {line!r}")
    yaw = float(wrap_angle(-rotation_y - np.pi / 2))
    return parts[0], np.array([z_cam, -x_cam, -y_cam + h / 2, length, w, h, yaw])


def export_kitti(db: SessionDB, folder: str | os.PathLike, frame_indices=None) -> list[Path]:
    """One ``NNNNNN.txt`` per frame (its index) in ``folder`` (made if missing), each written whole
    or not at all; a folder that cannot be written is an ``InputError`` naming it."""
    folder = _export_folder(folder)
    paths = []
    for index, labels in _truth(db.frame_labels(_frames(db, frame_indices))).items():
        path = folder / f"{index:06d}.txt"
        with _writing(path):
            write_text_atomic(path, "".join(kitti_line(lab.box, lab.class_name) + "\n" for lab in labels))
        paths.append(path)
    return paths


def scene_arrays(db: SessionDB, frame_index: int, labels: list[Label] | None = None) -> dict[str, np.ndarray]:
    """A frame in the neutral ``.npz`` scene format: merged points in the vehicle frame, the
    session's boxes and classes (``labels``, default: the frame's now), and per-point instance
    (index into the boxes, plus 1; 0 none) and class (into ``semantic_names``, 0 none) labels
    from the boxes."""
    frame = db.dataset.frame(frame_index)
    points = merge_frame(frame).points
    labels = [lab for lab in (db.labels(frame_index) if labels is None else labels) if lab.reviewed]
    boxes = np.array([lab.box for lab in labels], np.float32).reshape(-1, 7)
    names = ("none", *db.class_names)
    box_ids = point_box_ids(points, boxes.astype(np.float64))  # a point in two boxes: the first
    point_instance = (box_ids + 1).astype(np.int32)
    label_semantic = np.array([names.index(lab.class_name) for lab in labels] + [0], np.int32)
    point_semantic = label_semantic[box_ids]  # -1 (none) picks the trailing 0
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
    """One ``frame_NNNNN.npz`` scene per frame in ``folder`` (made if missing), each written whole
    or not at all; a folder that cannot be written is an ``InputError`` naming it."""
    folder = _export_folder(folder)
    paths = []
    for index, labels in db.frame_labels(_frames(db, frame_indices)).items():
        path = folder / f"frame_{index:05d}.npz"
        arrays = scene_arrays(db, index, labels)
        with _writing(path), atomic_path(path) as partial:
            np.savez_compressed(partial, **arrays)
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


def export_bytes(db: SessionDB, fmt: str, frame_indices=None) -> tuple[str, bytes]:
    """``export_labels`` into memory, for a download: ``(file name, content)``; the folder formats
    (KITTI, npz) come as one ZIP archive of their files."""
    import io
    import tempfile
    import zipfile

    if fmt not in FORMATS:
        raise InputError(f"unknown label format {fmt!r}; choose from {', '.join(FORMATS)}")
    stem = f"{db.session.name}_labels"
    with tempfile.TemporaryDirectory(prefix="factorydet-export-") as folder:
        target = Path(folder) / (f"{stem}.json" if fmt == "json" else f"{stem}_{fmt}")
        paths = export_labels(db, fmt, target, frame_indices)
        if fmt == "json":
            return target.name, target.read_bytes()
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            for path in sorted(paths):
                archive.write(path, f"{target.name}/{path.relative_to(target).as_posix()}")
        return f"{target.name}.zip", buffer.getvalue()


def _json_labels(path: Path, data_hash: str | None) -> list[tuple[int, np.ndarray, str]]:
    """The boxes of a ``factorydet-labels`` JSON file, each checked."""
    try:
        record = json.loads(path.read_bytes().decode("utf-8"))
    except ValueError as exc:  # not UTF-8, not JSON, an integer of more digits than Python converts
        raise InputError(f"{path}: not a factorydet label file ({exception_line(exc, 200)})") from None
    except RecursionError:
        raise InputError(f"{path}: not a factorydet label file (nested too deeply)") from None
    if not isinstance(record, dict) or not isinstance(record.get("frames"), list):
        raise InputError(f'{path}: not a factorydet label file (no "frames" list at the top level)')
    if data_hash is not None and record.get("data_hash") not in (None, data_hash):
        raise InputError(
            f"{path}: exported from another data set (hash {str(record['data_hash'])[:40]}, the session's "
            f"is {data_hash}); boxes would land on the wrong frames"
        )
    items = []
    for k, frame in enumerate(record["frames"]):
        where = f"{path}: frames[{k}]"
        if not isinstance(frame, dict) or not {"frame_index", "boxes", "labels"} <= set(frame):
            raise InputError(f'{where}: a frame has "frame_index", "boxes" and "labels"')
        index = check_frame_index(frame["frame_index"], f"{where}.frame_index")
        boxes, names = frame["boxes"], frame["labels"]
        if not isinstance(boxes, list) or not isinstance(names, list) or len(boxes) != len(names):
            raise InputError(f'{where}: "boxes" and "labels" are lists of the same length')
        for j, (box, name) in enumerate(zip(boxes, names)):
            if not isinstance(box, list) or not isinstance(name, str):
                raise InputError(f"{where}: box {j} is not a list of 7 numbers with a class name")
            items.append((index, np.array(check_box(box, f"{where} box {j}")), name))
    return items


def _kitti_labels(path: Path) -> list[tuple[int, np.ndarray, str]]:
    """The boxes of a KITTI label file or a folder of them, each checked."""
    files = sorted(f for f in path.glob("*.txt") if not f.name.startswith(".")) if path.is_dir() else [path]
    items = []
    for file in files:
        if not file.stem.isdigit():
            raise InputError(f"{file}: KITTI label files are named by frame index, e.g. 000003.txt")
        index = check_frame_index(int(file.stem), str(file))
        try:
            text = file.read_bytes().decode("utf-8")
        except UnicodeDecodeError as exc:
            raise InputError(f"{file}: not a KITTI label text file (not UTF-8: {exc.reason})") from None
        for n, line in enumerate(text.splitlines()):
            if line.strip():
                where = f"{file}:{n + 1}"
                name, box = parse_kitti_line(line, where)
                items.append((index, np.array(check_box(box, where)), name))
    return items


def _npz_labels(path: Path) -> list[tuple[int, np.ndarray, str]]:
    """The boxes of a neutral ``.npz`` scene or a folder of them, each checked. Only the three
    arrays needed are read, through ``io.npz.load_npz``, which checks each header first (a header
    claiming 10**10 boxes is refused, not allocated)."""
    files = sorted(f for f in path.glob("*.npz") if not f.name.startswith(".")) if path.is_dir() else [path]
    items = []
    for file in files:
        _, data = load_npz(file, ("frame_index", "boxes", "labels"))
        if "boxes" not in data or "labels" not in data:
            raise InputError(f"{file}: not a scene file with boxes and labels")
        if "frame_index" in data:
            stored = data["frame_index"]
            if stored.shape != ():
                raise InputError(f"{file}: frame_index is one number, got shape {stored.shape}")
            index = check_frame_index(stored.item(), f"{file}: frame_index")
        elif file.stem.split("_")[-1].isdigit():
            index = check_frame_index(int(file.stem.split("_")[-1]), str(file))
        else:
            raise InputError(f"{file}: no frame_index, and not named frame_NNNNN.npz")
        if data["boxes"].dtype.kind not in "iuf":  # complex: numpy would drop the imaginary part
            raise InputError(f"{file}: boxes are {data['boxes'].dtype} values, not real numbers")
        try:
            boxes = np.asarray(data["boxes"], np.float64)
            names = [str(n) for n in np.asarray(data["labels"]).reshape(-1)]
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"{file}: not a scene file with boxes and labels ({exception_line(exc, 200)})"
            ) from None
        if (len(boxes) and (boxes.ndim != 2 or boxes.shape[1] != 7)) or len(boxes) != len(names):
            raise InputError(f"{file}: boxes {boxes.shape} and labels ({len(names)}) do not pair up")
        items += [
            (index, np.array(check_box(box, f"{file} box {j}")), name)
            for j, (box, name) in enumerate(zip(boxes.reshape(-1, 7), names, strict=True))
        ]
    return items


def read_labels(
    path: str | os.PathLike, fmt: str | None = None, data_hash: str | None = None
) -> list[tuple[int, np.ndarray, str]]:
    """``(frame_index, box, class_name)`` of every box in an exported file or folder.

    Every box is checked (``store.check_box``: 7 finite numbers, sizes and centre within bounds,
    yaw wrapped) and every frame index is a true integer (``1.7`` or ``true`` is refused, not
    truncated to frame 1); the first bad one is an ``InputError`` naming the file and item.

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
    if fmt not in FORMATS:
        raise InputError(f"unknown label format {fmt!r}; choose from {', '.join(FORMATS)}")
    try:
        if fmt == "json":
            return _json_labels(path, data_hash)
        if fmt == "kitti":
            return _kitti_labels(path)
        return _npz_labels(path)
    except OSError as exc:  # a folder where a file was expected, a file that cannot be read
        raise InputError(f"{path}: cannot read the labels ({exception_line(exc, 200)})") from None


_VOLUME_CLASSES_APART = int(np.ceil(np.log2(1 / min(CONFLICT_IOU, DUPLICATE_IOU)))) + 1
"""How many volume classes (factors of 2) apart two boxes overlapping at ``CONFLICT_IOU`` can be:
their volumes differ by at most 1 / ``CONFLICT_IOU``, plus one class for where the classes' edges
fall (and floating point at a ratio of exactly 2)."""


def _size_classes(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per box (N, 7), its volume class and its ground-radius class: ``floor(log2)`` of each."""
    log_volume = np.log2(boxes[:, 3]) + np.log2(boxes[:, 4]) + np.log2(boxes[:, 5])
    radius = np.hypot(boxes[:, 3], boxes[:, 4]) / 2
    return np.floor(log_volume).astype(np.int64), np.floor(np.log2(radius)).astype(np.int64)


def _near(boxes: np.ndarray, first: int) -> list[list[int]]:
    """For each of ``boxes[first:]``, the indices of every box of ``boxes`` (N, 7) it may overlap
    at IoU ``CONFLICT_IOU`` or more, itself included: a superset, the exact IoU decides.

    IoU >= t needs the smaller volume to be at least t times the larger (the intersection is at
    most the smaller, the union at least the larger): with volume classes a factor 2 wide, a
    box's matches lie within ``_VOLUME_CLASSES_APART`` of its class. And the ground circles must
    meet. So the boxes are grouped by volume class and radius class, each group gets its own
    k-d tree, and a box asks only the groups of a volume it can match, each within its own radius
    plus that group's largest: one 100 m box widens the search of its own group alone, not that of
    every other box.
    """
    volume_class, radius_class = _size_classes(boxes)
    radius = np.hypot(boxes[:, 3], boxes[:, 4]) / 2
    near: list[list[int]] = [[] for _ in range(len(boxes) - first)]
    groups: dict[tuple[int, int], list[int]] = {}
    for index, key in enumerate(zip(volume_class.tolist(), radius_class.tolist())):
        groups.setdefault(key, []).append(index)
    asking = np.arange(first, len(boxes))
    for (group_volume, _), members in groups.items():
        ask = asking[np.abs(volume_class[first:] - group_volume) <= _VOLUME_CLASSES_APART]
        if not len(ask):
            continue
        members_array = np.array(members, np.int64)
        tree = cKDTree(boxes[members_array, :2])
        found = tree.query_ball_point(boxes[ask, :2], radius[ask] + radius[members_array].max())
        for index, hits in zip(ask.tolist(), found):
            near[index - first].extend(members_array[hits].tolist())
    return near


def _screen(
    items: list[tuple[int, np.ndarray, str]], current: dict[int, list[Label]]
) -> tuple[list[int], list[dict], list[dict]]:
    """Which of ``items`` to add given the frames' ``current`` labels: ``(positions to add,
    duplicates, conflicts)``, both lists in the order of ``items``.

    An item repeats a label, or an earlier item of the same file, of its class (IoU >=
    ``DUPLICATE_IOU``: left out) or overlaps one of another class (IoU >= ``CONFLICT_IOU``: added
    and reported). Only pairs whose ground circles meet and whose volumes are alike can match, so
    k-d trees over the box centres, one per size class (``_size_classes``), find the few
    candidates of each item: linear in the file, not quadratic, even with a few huge boxes.
    """
    by_frame: dict[int, list[int]] = {}
    for k, (frame_index, _, _) in enumerate(items):
        by_frame.setdefault(frame_index, []).append(k)
    keep, reports = [], []
    for frame_index, positions in by_frame.items():
        labels = current.get(frame_index, [])
        num_labels = len(labels)
        # The frame's labels first, then its items in the file's order; index j into all of them.
        boxes = np.concatenate(
            [
                np.array([lab.box for lab in labels], np.float64).reshape(-1, 7),
                np.array([items[k][1] for k in positions], np.float64).reshape(-1, 7),
            ]
        )
        names = [lab.class_name for lab in labels] + [items[k][2] for k in positions]
        label_ids = [lab.id for lab in labels] + [None] * len(positions)
        near = _near(boxes, num_labels)
        kept = np.ones(len(boxes), bool)  # the labels, and the items not left out as repeats
        for n, k in enumerate(positions):
            j = num_labels + n
            # Earlier boxes only (labels, earlier items), in that order: ties go to the first.
            candidates = np.array(sorted(c for c in near[n] if c < j and kept[c]), np.int64)
            found = None
            if len(candidates):
                iou = box_iou_3d(boxes[j][None], boxes[candidates])[0]
                same = np.array([names[c] == names[j] for c in candidates])
                if same.any() and iou[same].max() >= DUPLICATE_IOU:
                    found, kind = int(np.flatnonzero(same)[iou[same].argmax()]), "duplicate"
                elif (~same).any() and iou[~same].max() >= CONFLICT_IOU:
                    found, kind = int(np.flatnonzero(~same)[iou[~same].argmax()]), "conflict"
            if found is not None:
                other = int(candidates[found])
                reports.append(
                    (
                        k,
                        kind,
                        {
                            "frame_index": frame_index,
                            "class": names[j],
                            "box": [round(float(v), 4) for v in boxes[j]],
                            "label_id": label_ids[other],
                            "label_class": names[other],
                            "iou": round(float(iou[found]), 3),
                        },
                    )
                )
                if kind == "duplicate":
                    kept[j] = False
                    continue
            keep.append(k)
    reports.sort(key=lambda r: r[0])
    duplicates = [r[2] for r in reports if r[1] == "duplicate"]
    conflicts = [r[2] for r in reports if r[1] == "conflict"]
    return sorted(keep), duplicates, conflicts


def import_labels(db: SessionDB, path: str | os.PathLike, author: str, fmt: str | None = None) -> dict:
    """Add the boxes of an exported file to the session as one undoable edit.

    The check for repeats and the write are one transaction (``SessionDB.add_labels``'s
    ``screen``): two imports of one file at the same time add its boxes once, and the other
    reports them as duplicates.

    Returns:
        ``{"imported": n, "duplicates": [...], "conflicts": [...], "edit": id}``; a duplicate
        repeats a label (same class, IoU >= 0.95) and is skipped, a conflict overlaps a label of
        another class (IoU >= 0.5) and is imported, both listed with the label they meet.
    """
    items = read_labels(path, fmt, db.meta().get("data_hash"))
    unknown = sorted({name for _, _, name in items} - set(db.class_names))
    if unknown:
        raise InputError(f"{path}: classes {unknown} are not the session's {list(db.class_names)}")
    outside = sorted({index for index, _, _ in items if index >= db.dataset.num_frames})
    if outside:
        raise InputError(
            f"{path}: frame {outside[0]} out of range: the data set has {db.dataset.num_frames} frame(s)"
        )
    found: dict[str, list[dict]] = {"duplicates": [], "conflicts": []}

    def screen(current: dict[int, list[Label]]) -> list[int]:
        # Called once, inside the write transaction; its reports describe what was written.
        keep, found["duplicates"], found["conflicts"] = _screen(items, current)
        return keep

    added = db.add_labels(items, author, origin="import", screen=screen)
    return {"imported": len(added), **found, "edit": added.edit_id}
