"""Merging the sensors of a frame into one cloud in the vehicle frame (paper section 3.1, Eq. 1)."""

from __future__ import annotations

import numpy as np

from .types import Frame, MergedCloud, check_array


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
    rotations = extrinsics[frame.sensor_ids, :3, :3]  # (N, 3, 3)
    translations = extrinsics[frame.sensor_ids, :3, 3]
    points = np.einsum("nij,nj->ni", rotations, frame.points.astype(np.float64)) + translations
    return MergedCloud(
        points=points.astype(np.float32),
        sensor_ids=frame.sensor_ids,
        point_instance_ids=frame.point_instance_ids,
        T_vehicle_sensor=extrinsics,
    )
