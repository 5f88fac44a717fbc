"""What the app shows about one patch or proposal the user clicked (numbers only, no drawing)."""

from __future__ import annotations

import numpy as np

from factorydet_core.boxes import box_iou_3d, fit_box
from factorydet_core.detection.detector import ProposalResult
from factorydet_core.geometry import points_in_box
from factorydet_core.session.review_rank import MIN_ANSWERS, MIN_EACH, REFIT_EVERY
from factorydet_core.session.store import HIDE_LABELLED_IOU, on_labelled_object
from factorydet_core.session.world import COUNT_VOXEL_M, BestView
from factorydet_core.types import BOX_KINDS, CLASS_NAMES, LEVELS, Detections, Frame, InputError, Proposals


def nearest_point_on_ray(
    points: np.ndarray, origin: np.ndarray, direction: np.ndarray, max_distance: float
) -> int | None:
    """Index of the point closest to the camera among those within ``max_distance`` of a click ray.

    Args:
        points: (N, 3) points.
        origin: (3,) ray origin (the camera).
        direction: (3,) ray direction (need not be unit length).
        max_distance: largest perpendicular distance from the ray, metres.

    Returns:
        The index, or ``None`` when no point is near the ray in front of the camera.
    """
    direction = np.asarray(direction, np.float64)
    norm = np.linalg.norm(direction)
    if norm == 0 or not len(points):
        return None
    direction = direction / norm
    offsets = np.asarray(points, np.float64) - np.asarray(origin, np.float64)
    along = offsets @ direction
    perpendicular_sq = np.einsum("ij,ij->i", offsets, offsets) - along**2
    candidates = np.flatnonzero((along > 0) & (perpendicular_sq <= max_distance**2))
    if not len(candidates):
        return None
    return int(candidates[np.argmin(along[candidates])])


def _best_label(frame: Frame, box: np.ndarray) -> dict:
    """The annotated instance whose box overlaps ``box`` most, with the IoU (None without overlap)."""
    if not len(frame.labels):
        return {"label": None, "label_iou": 0.0}
    iou = box_iou_3d(box[None], frame.labels.boxes)[0]
    best = int(np.argmax(iou))
    if iou[best] <= 0:
        return {"label": None, "label_iou": 0.0}
    return {
        "label": f"{frame.class_names[frame.labels.class_ids[best]]} #{int(frame.labels.instance_ids[best])}",
        "label_iou": round(float(iou[best]), 3),
    }


def describe_patch(result: ProposalResult, frame: Frame, patch_id: int) -> dict:
    """Numbers of one cut-pursuit patch: points, voxels, fitted box and the best-overlapping label."""
    segmentation = result.segmentation
    if not 0 <= patch_id < segmentation.num_patches:
        raise InputError(f"patch {patch_id} out of range [0, {segmentation.num_patches})")
    mask = segmentation.patch_ids == patch_id
    box = fit_box(result.cloud.points[mask])
    return {
        "kind": "patch",
        "id": int(patch_id),
        "segment": int(segmentation.patch_segment_ids[patch_id]),
        "num_points": int(mask.sum()),
        "num_voxels": int(len(np.unique(result.grid.point_voxel_ids[mask]))),
        "box": box,
        **_best_label(frame, box),
    }


def segment_patch_ids(result: ProposalResult, patch_id: int) -> np.ndarray:
    """(K,) the patches of the segment that ``patch_id`` belongs to (what a click selects)."""
    segmentation = result.segmentation
    if not 0 <= patch_id < segmentation.num_patches:
        raise InputError(f"patch {patch_id} out of range [0, {segmentation.num_patches})")
    return np.flatnonzero(segmentation.patch_segment_ids == segmentation.patch_segment_ids[patch_id])


def describe_proposal(result: ProposalResult, frame: Frame, index: int) -> dict:
    """Numbers of one proposal: points, voxels, box, its patches and the best-overlapping label."""
    proposals = result.proposals
    if not 0 <= index < len(proposals):
        raise InputError(f"proposal {index} out of range [0, {len(proposals)})")
    box = proposals.boxes[index]
    return {
        "kind": "proposal",
        "id": int(index),
        "num_points": int(proposals.num_points[index]),
        "num_voxels": int(proposals.num_voxels[index]),
        "num_patches": len(proposals.patch_sets[index]),
        "level": LEVELS[int(proposals.level[index])],
        "box_kind": BOX_KINDS[int(proposals.box_kind[index])],
        "box": box,
        **_best_label(frame, box),
    }


def description_markdown(info: dict) -> str:
    """The description as a short Markdown table for the app's side panel."""
    box = info["box"]
    rows = [
        ("points", f"{info['num_points']:,}"),
        ("voxels", f"{info['num_voxels']:,}"),
        ("box size (m)", f"{box[3]:.2f} x {box[4]:.2f} x {box[5]:.2f}"),
        ("box centre (m)", f"{box[0]:.2f}, {box[1]:.2f}, {box[2]:.2f}"),
        ("yaw (deg)", f"{np.degrees(box[6]):.0f}"),
    ]
    if info["kind"] == "patch":
        rows.insert(0, ("segment", str(info["segment"])))
    else:
        rows.insert(
            0, ("made of", f"{info['num_patches']} patches ({info['level']}, {info['box_kind']} box)")
        )
    label = "none" if info["label"] is None else f"{info['label']} (IoU {info['label_iou']:.2f})"
    rows.append(("best annotation", label))
    table = "\n".join(f"| {k} | {v} |" for k, v in rows)
    return f"**{info['kind'].capitalize()} {info['id']}**\n\n| | |\n|---|---|\n{table}"


def ray_box_distances(origin: np.ndarray, direction: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance along a click ray to where it enters each oriented box (inf where it misses).

    Args:
        origin: (3,) ray origin.
        direction: (3,) ray direction.
        boxes: (M, 7) boxes.

    Returns:
        (M,) float64 distances; 0 when the origin is inside a box.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    direction = np.asarray(direction, np.float64)
    direction = direction / max(np.linalg.norm(direction), 1e-12)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = np.asarray(origin, np.float64) - boxes[:, :3]
    # Ray in each box's own frame (rotate by -yaw about z).
    local_origin = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
    local_dir = np.stack(
        [
            c * direction[0] + s * direction[1],
            -s * direction[0] + c * direction[1],
            np.full_like(c, direction[2]),
        ],
        1,
    )
    half = boxes[:, 3:6] / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - local_origin) / local_dir
        t2 = (half - local_origin) / local_dir
    # Axis-parallel rays: inside the slab means (-inf, inf), outside means empty.
    parallel = local_dir == 0
    inside = np.abs(local_origin) <= half
    t_lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = t_lo.max(axis=1), t_hi.min(axis=1)
    hit = (enter <= leave) & (leave >= 0)
    return np.where(hit, np.maximum(enter, 0.0), np.inf)


def describe_detection(
    detections: Detections, index: int, proposals: Proposals, frame: Frame, probability_exponent: float = 1.0
) -> dict:
    """Numbers of one detection: class probabilities, the proposal and patches it came from, the
    detections it suppressed, and the best-overlapping annotation."""
    if not 0 <= index < len(detections):
        raise InputError(f"detection {index} out of range [0, {len(detections)})")
    box = detections.boxes[index]
    proposal = int(detections.proposal_ids[index])
    names = (*detections.class_names, "background")
    order = np.argsort(-detections.probabilities[index])
    suppressed = np.flatnonzero(detections.suppressed_by == index)
    info = {
        "title": f"Detection: {names[int(detections.class_ids[index])]} {detections.scores[index]:.2f}",
        "class probabilities": ", ".join(
            f"{names[c]} {detections.probabilities[index, c]:.2f}" for c in order[:4]
        ),
        "proposal": f"#{proposal} ({LEVELS[int(proposals.level[proposal])]}, "
        f"{BOX_KINDS[int(proposals.box_kind[proposal])]} box, {int(proposals.num_points[proposal])} points)",
        "patches": ", ".join(str(p) for p in proposals.patch_sets[proposal][:12])
        + (" …" if len(proposals.patch_sets[proposal]) > 12 else ""),
        "box (cx, cy, cz, dx, dy, dz, yaw)": ", ".join(f"{v:.2f}" for v in box),
        "suppressed": (
            ", ".join(
                f"{detections.class_names[int(detections.class_ids[k])]} {detections.scores[k]:.2f}"
                for k in suppressed[:8]
            )
            if len(suppressed)
            else "none"
        ),
    }
    probability = float(detections.probabilities[index, int(detections.class_ids[index])])
    if probability > 0 and abs(float(detections.scores[index]) - probability) > 1e-6:
        # A model with box quality scores probability ** probability_exponent x predicted IoU
        # (detection.score_groups; the model's exponent).
        predicted = float(detections.scores[index]) / probability**probability_exponent
        info["predicted box IoU"] = f"{predicted:.2f}"
    if detections.suppressed_by[index] >= 0:
        info["suppressed by"] = f"detection scoring {detections.scores[detections.suppressed_by[index]]:.2f}"
    best = _best_label(frame, box)
    info["annotation"] = "none" if best["label"] is None else f"{best['label']} (IoU {best['label_iou']})"
    return info


def detection_markdown(info: dict) -> str:
    """``describe_detection``'s numbers as a Markdown table."""
    rows = "\n".join(f"| {key} | {value} |" for key, value in info.items() if key != "title")
    return f"**{info['title']}**\n\n| | |\n|---|---|\n{rows}"


def _neighbours(box, labels, radius: float = 3.0, exclude_id: int | None = None) -> list[str]:
    """Labels whose centre is within ``radius`` metres of ``box``'s, nearest first."""
    centre = np.asarray(box, np.float64)[:3]
    near = []
    for lab in labels:
        if lab.id == exclude_id:
            continue
        distance = float(np.linalg.norm(np.asarray(lab.box[:3]) - centre))
        if distance <= radius:
            near.append((distance, f"{lab.class_name} #{lab.id} at {distance:.1f} m"))
    return [text for _, text in sorted(near)]


def _box_text(box) -> str:
    b = np.asarray(box, np.float64)
    return (
        f"centre ({b[0]:.2f}, {b[1]:.2f}, {b[2]:.2f}) m, size {b[3]:.2f} × {b[4]:.2f} × {b[5]:.2f} m, "
        f"yaw {np.degrees(b[6]):.0f}°"
    )


def describe_label(label, frame_labels) -> str:
    """Markdown about a stored label (``store.Label``) and its neighbours among ``frame_labels``."""
    near = _neighbours(label.box, frame_labels, exclude_id=label.id)
    waiting = ""
    if not getattr(label, "reviewed", True):
        score = "" if label.score is None else f", score {label.score:.2f}"
        waiting = (
            f"**Pre-label** from the model{score}, not confirmed yet: **Confirm [Enter]** if it is right,"
            " fix its class or box (that confirms it too), or delete it.  \n"
        )
    return (
        waiting + f"**Label #{label.id}: {label.class_name}** (frame {label.frame_index + 1})  \n"
        f"{_box_text(label.box)}  \n"
        f"origin *{label.origin}*, made by {label.created_by}, last changed by {label.modified_by} "
        f"at {label.modified[:19].replace('T', ' ')} (version {label.version})  \n"
        f"Nearby: {', '.join(near[:5]) if near else 'no other label within 3 m'}"
    )


def review_item_markdown(
    item: dict,
    frame_labels,
    rank: int,
    total: int,
    num_points: int | None = None,
    min_points: int | None = None,
    hold: float | None = None,
    best_view: BestView | None = None,
    pseudo: float | None = None,
) -> str:
    """Markdown about one review-queue item (a mined negative, ``SessionDB.review_queue``), with
    whether its run held it out of the background (``hold``: the run's ``hold_confident``) or
    queued it for review alone (``in_background`` 0: ``LoopSettings.review_extra``), with
    the number of points in its box when known and the data set's annotation policy (objects of
    at least ``min_points`` points are labelled), where the frames see its object best
    (``best_view``: a ``world.BestView``, or ``None`` when its own frame does), and whether its
    run took it for a label of its predicted class (``pseudo``: the run's
    ``pseudo_label_confident``; not on a labelled object)."""
    lines = [
        f"**Item {rank} of {total}** (#{item['id']}, frame {item['frame_index'] + 1}, "
        f"mined in run {item['run_id']} round {item['round']})",
        f"predicted **{item['predicted_class']}**, score **{item['score']:.3f}**; best IoU with a "
        f"label when mined {item['best_annotated_iou']:.2f}"
        + (f", now {item['label_iou']:.2f}" if item.get("label_iou") is not None else ""),
        _box_text(item["box"]),
    ]
    if num_points is not None:
        lines.append(
            f"{num_points} points in its box"
            + (f" (the data set labels objects of at least {min_points} points)" if min_points else "")
        )
    if best_view is not None:
        lines.append(
            f"Seen best in frame {best_view.frame_index + 1}: {best_view.num_points} points in its box"
            f" there against {best_view.num_points_here} here ({100 * COUNT_VOXEL_M:g} cm thinned):"
            " **Look where it is seen best [I]** before calling it too sparse to label"
        )
    lines += [
        f"patches {', '.join(map(str, item['patch_set'][:12]))}"
        + (" …" if len(item["patch_set"]) > 12 else ""),
    ]
    probabilities = item.get("probabilities")
    if probabilities:
        names = (*CLASS_NAMES, "background") if len(probabilities) == len(CLASS_NAMES) + 1 else None
        if names is not None:
            top = sorted(zip(names, probabilities), key=lambda t: -t[1])[:3]
            lines.append("probabilities: " + ", ".join(f"{n} {p:.2f}" for n, p in top))
    if item.get("place_useful") is not None:
        lines.append(
            f"Learned order: a **{100 * item['place_useful']:.0f}%** chance that a verdict here gives a label"
            f" (fitted on {item.get('learned_from', 0)} answered places)"
        )
    elif item.get("learned_from") is not None:
        lines.append(
            f"Learned order: the queue order until {MIN_ANSWERS} places are answered, at least {MIN_EACH}"
            f" giving a label and {MIN_EACH} not (it looks again every {REFIT_EVERY} verdicts)"
        )
    near = _neighbours(item["box"], frame_labels)
    lines.append(f"Nearby labels: {', '.join(near[:5]) if near else 'none within 3 m'}")
    if item.get("verdict"):
        verdict = item["verdict"] + (f" ({item['verdict_class']})" if item.get("verdict_class") else "")
        lines.append(f"Verdict: **{verdict}** by {item['reviewer']}")
    elif not item.get("in_background", 1):
        lines.append(
            "**For review alone**: after the run's mined negatives in its queue (review extra), so"
            " training leaves it out until a verdict says what it is"
        )
    elif (
        pseudo is not None
        and item["score"] >= pseudo
        and not on_labelled_object(item.get("label_iou"), HIDE_LABELLED_IOU)
    ):
        lines.append(
            f"**Pseudo-label**: scored {pseudo:g} or more off every label, so training takes it for a"
            f" *{item['predicted_class']}* until a verdict says what it is"
        )
    elif hold is not None and item["score"] >= hold:
        lines.append(
            f"**Held**: scored {hold:g} or more, so training keeps it out of the background (a likely"
            " unlabelled object) until a verdict says what it is"
        )
    return "  \n".join(lines)


def num_points_in_box(result: ProposalResult, box) -> int:
    """How many of the proposed cloud's points lie inside ``box`` (7,)."""

    return int(points_in_box(result.cloud.points, np.asarray(box, np.float64)).sum())


def patches_in_box(result: ProposalResult, box) -> np.ndarray:
    """(K,) the patches with at least one point inside ``box`` (7,)."""

    inside = points_in_box(result.cloud.points, np.asarray(box, np.float64))
    ids = np.unique(result.segmentation.patch_ids[inside])
    return ids[ids >= 0]
