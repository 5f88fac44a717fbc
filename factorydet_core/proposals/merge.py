"""Merging the sensors of a frame into one cloud in the vehicle frame (paper section 3.1, Eq. 1)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from factorydet_core.geometry import apply_transforms
from factorydet_core.proposals.cloud import floor_mask
from factorydet_core.types import Frame, InputError, MergedCloud, check_array


def merge_frame(frame: Frame, T_vehicle_sensor: np.ndarray | None = None) -> MergedCloud:
    """Move every sensor's points into the vehicle frame.

    Args:
        frame: the scan, points in each sensor's own frame.
        T_vehicle_sensor: (S, 4, 4) extrinsics to use; the frame's nominal ones by default.

    Returns:
        The merged cloud, (N, 3) points in the vehicle frame, in the frame's point order.
    """
    extrinsics = (
        frame.T_vehicle_sensor if T_vehicle_sensor is None else np.asarray(T_vehicle_sensor, np.float64)
    )
    check_array(extrinsics, (frame.num_sensors, 4, 4), name="T_vehicle_sensor", finite=True)
    points = apply_transforms(extrinsics, frame.sensor_ids, frame.points)
    return MergedCloud(
        points=points.astype(np.float32),
        sensor_ids=frame.sensor_ids,
        point_instance_ids=frame.point_instance_ids,
        T_vehicle_sensor=extrinsics,
    )


@dataclasses.dataclass(frozen=True)
class ExtrinsicRefinement:
    """Result of refining each sensor's extrinsic by ICP against the other sensors."""

    T_vehicle_sensor: np.ndarray
    """(S, 4, 4) refined extrinsics (sensor frame -> vehicle frame)."""
    rmse_before: np.ndarray
    """(S,) inlier point-to-point RMSE of each sensor against the others with the input extrinsics, m."""
    rmse_after: np.ndarray
    """(S,) the same after refinement, m."""
    fitness: np.ndarray
    """(S,) share of each sensor's points that found a neighbour within the correspondence distance."""


def o3d_cloud(points: np.ndarray):
    """An open3d point cloud of (N, 3) ``points`` (open3d imported here, when first needed)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64))
    return cloud


def refine_extrinsics(
    frames: Frame | Sequence[Frame],
    T_vehicle_sensor: np.ndarray | None = None,
    *,
    max_correspondence_m: float = 0.3,
    downsample_m: float = 0.05,
    rounds: int = 3,
    max_iterations: int = 30,
    remove_common_motion: bool = True,
    level_to_floor: bool = True,
) -> ExtrinsicRefinement:
    """Refine every sensor's extrinsic by point-to-plane ICP of its points against all other sensors.

    The sensors of a rig overlap, so each sensor's points should lie on the surfaces the others see.
    Each round aligns every sensor in turn to the union of the others (with their current
    extrinsics). Extrinsics do not change between frames, so several frames of one trajectory can be
    stacked (in the vehicle frame of each) to add constraints; this is a calibration step run once
    per data set, not per frame.

    Args:
        frames: one frame or several frames of the same rig.
        T_vehicle_sensor: (S, 4, 4) starting extrinsics; the frames' nominal ones by default.
        max_correspondence_m: ICP correspondence distance; larger than the expected misalignment.
        downsample_m: voxel size of the down-sampling applied before ICP.
        rounds: passes over all sensors.
        max_iterations: ICP iterations per sensor and round.
        remove_common_motion: aligning sensors to each other cannot see a motion of the whole rig,
            and such a motion drifts in; remove the mean correction, which assumes the calibration
            errors of the starting extrinsics average out over the sensors.
        level_to_floor: then rotate the whole rig so that the floor plane seen within 10 m of the
            vehicle is level (normal +z, the vehicle frame's definition); this fixes the rig's roll
            and pitch absolutely, which the mean-correction assumption only fixes on average.

    Returns:
        The refined extrinsics and each sensor's residual before and after.
    """
    import open3d as o3d

    frames = [frames] if isinstance(frames, Frame) else list(frames)
    if not frames:
        raise InputError("refine_extrinsics: no frames given")
    extrinsics = np.array(frames[0].T_vehicle_sensor if T_vehicle_sensor is None else T_vehicle_sensor)
    num_sensors = len(extrinsics)
    check_array(extrinsics, (None, 4, 4), name="T_vehicle_sensor", finite=True)
    if num_sensors < 2:
        raise InputError("refine_extrinsics: needs at least two sensors that overlap")
    # Sensor-frame points per sensor, with the frame they came from; frames stay separate because
    # the odometry between them is not trusted here.
    per_sensor = [
        [f.points[f.sensor_ids == s].astype(np.float64) for f in frames] for s in range(num_sensors)
    ]

    def vehicle_points(sensor: int, frame_index: int, T: np.ndarray) -> np.ndarray:
        local = per_sensor[sensor][frame_index]
        return local @ T[sensor, :3, :3].T + T[sensor, :3, 3]

    def sensor_and_others(sensor: int, frame_index: int, T: np.ndarray):
        """Down-sampled open3d clouds of one sensor and of all the others, or None if either is empty."""
        source = vehicle_points(sensor, frame_index, T)
        others = [vehicle_points(o, frame_index, T) for o in range(num_sensors) if o != sensor]
        if not len(source) or not sum(len(o) for o in others):
            return None
        return (
            o3d_cloud(source).voxel_down_sample(downsample_m),
            o3d_cloud(np.concatenate(others)).voxel_down_sample(downsample_m),
        )

    def residual(sensor: int, T: np.ndarray) -> tuple[float, float]:
        sq_sum, num_inliers, num_total = 0.0, 0, 0
        for f in range(len(frames)):
            clouds = sensor_and_others(sensor, f, T)
            if clouds is None:
                continue
            source_cloud, target_cloud = clouds
            result = o3d.pipelines.registration.evaluate_registration(
                source_cloud, target_cloud, max_correspondence_m, np.eye(4)
            )
            num = len(source_cloud.points)
            inliers = int(round(result.fitness * num))
            sq_sum += result.inlier_rmse**2 * inliers
            num_inliers += inliers
            num_total += num
        rmse = np.sqrt(sq_sum / num_inliers) if num_inliers else np.nan
        return rmse, (num_inliers / num_total if num_total else 0.0)

    rmse_before = np.array([residual(s, extrinsics)[0] for s in range(num_sensors)])
    refined = extrinsics.copy()
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=max_iterations)
    for round_index in range(rounds):
        # Coarse to fine: the correspondence distance halves each round (not below 2 cells).
        distance = max(max_correspondence_m * 0.5**round_index, 2 * downsample_m)
        for sensor in range(num_sensors):
            corrections = []
            for f in range(len(frames)):
                clouds = sensor_and_others(sensor, f, refined)
                if clouds is None:
                    continue
                source_cloud, target_cloud = clouds
                if len(source_cloud.points) < 10 or len(target_cloud.points) < 10:
                    continue
                target_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
                result = o3d.pipelines.registration.registration_icp(
                    source_cloud,
                    target_cloud,
                    distance,
                    np.eye(4),
                    o3d.pipelines.registration.TransformationEstimationPointToPlane(),
                    criteria,
                )
                # open3d sums its normal equations in parallel, so the same input gives transforms that
                # differ in the last bits from run to run; ICP's stopping test, the voxel grid and cut
                # pursuit amplify that into different segments. Snapping to 1e-10 (far below any
                # calibration error) makes a calibration repeat exactly, except in the rare case
                # where the noise straddles a snapping step.
                corrections.append(np.round(result.transformation, 10))
            if corrections:
                # One ICP per frame (frames do not share correspondences), then the mean correction.
                refined[sensor] = mean_transform(np.array(corrections)) @ refined[sensor]
    if remove_common_motion:
        refined = _remove_common_correction(extrinsics, refined)
    if level_to_floor:
        refined = _level_to_floor(frames, refined)
    after = [residual(s, refined) for s in range(num_sensors)]
    return ExtrinsicRefinement(
        T_vehicle_sensor=refined,
        rmse_before=rmse_before,
        rmse_after=np.array([a[0] for a in after]),
        fitness=np.array([a[1] for a in after]),
    )


def mean_transform(transforms: np.ndarray) -> np.ndarray:
    """(4, 4) mean of (K, 4, 4) rigid transforms: chordal mean rotation, mean translation."""
    from scipy.spatial.transform import Rotation

    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix(transforms[:, :3, :3]).mean().as_matrix()
    mean[:3, 3] = transforms[:, :3, 3].mean(axis=0)
    return mean


def _level_to_floor(frames: list[Frame], T_vehicle_sensor: np.ndarray, radius_m: float = 10.0) -> np.ndarray:
    """Apply the rotation that makes the floor plane of the merged frames level (normal +z)."""

    normals = []
    for frame in frames:
        cloud = merge_frame(frame, T_vehicle_sensor)
        near = cloud.select(np.hypot(cloud.points[:, 0], cloud.points[:, 1]) <= radius_m)
        _, plane = floor_mask(near, distance_m=0.03)
        if np.all(np.isfinite(plane)):
            normals.append(plane[:3])
    if not normals:
        return T_vehicle_sensor  # no floor in view: nothing to level against
    normal = np.mean(normals, axis=0)
    normal /= np.linalg.norm(normal)
    # Smallest rotation taking the plane normal onto +z (Rodrigues), then the height shift.
    axis = np.cross(normal, [0.0, 0.0, 1.0])
    sin_angle, cos_angle = np.linalg.norm(axis), float(normal[2])
    rotation = np.eye(3)
    if sin_angle > 1e-12:
        k = axis / sin_angle
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + sin_angle * K + (1 - cos_angle) * K @ K
    level = np.eye(4)
    level[:3, :3] = rotation
    # Only the rotation: the floor plane's height is biased by a centimetre by whatever stands on
    # it (measured on the simulator), more than the rig's height error, so the height stays.
    return level[None] @ T_vehicle_sensor


def _remove_common_correction(start: np.ndarray, refined: np.ndarray) -> np.ndarray:
    """Remove the mean rigid correction of all sensors from ``refined``."""
    corrections = refined @ np.linalg.inv(start)  # (S, 4, 4) in the vehicle frame
    return np.linalg.inv(mean_transform(corrections))[None] @ refined


def accumulate(
    frames: Sequence[Frame],
    T_vehicle_sensor: np.ndarray | None = None,
    *,
    refine_with_icp: bool = False,
    max_correspondence_m: float = 0.5,
) -> MergedCloud:
    """Merge the last frame with the frames before it into one dense cloud in the last frame's
    vehicle frame (the paper's P = {P_(i-m) .. P_i} moved by N = {[R|T]}).

    Args:
        frames: frames in time order; the last one is the current frame.
        T_vehicle_sensor: (S, 4, 4) extrinsics for every frame; each frame's nominal ones by default.
        refine_with_icp: correct each earlier frame's odometry pose by point-to-plane ICP against the
            current frame (odometry drifts).
        max_correspondence_m: ICP correspondence distance.

    Returns:
        The accumulated cloud; ``frame_ages`` tells how many frames old each point is.
    """
    frames = list(frames)
    if not frames:
        raise InputError("accumulate: no frames given")
    current = frames[-1]
    current_cloud = merge_frame(current, T_vehicle_sensor)
    parts = [current_cloud]
    T_current_world = np.linalg.inv(current.T_world_vehicle)
    target = None
    for age, frame in enumerate(reversed(frames[:-1]), start=1):
        cloud = merge_frame(frame, T_vehicle_sensor)
        T_current_frame = T_current_world @ frame.T_world_vehicle
        if refine_with_icp and cloud.num_points and current_cloud.num_points:
            import open3d as o3d

            if target is None:
                target = o3d_cloud(current_cloud.points).voxel_down_sample(0.1)
                target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.5, max_nn=30))
            result = o3d.pipelines.registration.registration_icp(
                o3d_cloud(cloud.points).voxel_down_sample(0.1),
                target,
                max_correspondence_m,
                T_current_frame,
                o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            )
            T_current_frame = result.transformation
        moved = cloud.points.astype(np.float64) @ T_current_frame[:3, :3].T + T_current_frame[:3, 3]
        parts.append(
            MergedCloud(
                points=moved.astype(np.float32),
                sensor_ids=cloud.sensor_ids,
                point_instance_ids=cloud.point_instance_ids,
                T_vehicle_sensor=cloud.T_vehicle_sensor,
                frame_ages=np.full(cloud.num_points, age, np.int16),
            )
        )
    return MergedCloud(
        points=np.concatenate([p.points for p in parts]),
        sensor_ids=np.concatenate([p.sensor_ids for p in parts]),
        point_instance_ids=np.concatenate([p.point_instance_ids for p in parts]),
        T_vehicle_sensor=current_cloud.T_vehicle_sensor,
        frame_ages=np.concatenate([p.frame_ages for p in parts]),
    )
