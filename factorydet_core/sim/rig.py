"""The AGV: its twelve-LiDAR rig and the closed loop it drives."""

from __future__ import annotations

import dataclasses

import numpy as np

from factorydet_core.geometry import make_transform, rotation_ypr

NUM_SENSORS = 12
HORIZONTAL_FOV_DEG = 120.0
VERTICAL_FOV_DEG = 45.0
MAX_RANGE_M = 100.0


@dataclasses.dataclass(frozen=True)
class SensorRig:
    """Nominal sensor mounting and the beam pattern every sensor shares."""

    T_vehicle_sensor: np.ndarray
    """(S, 4, 4) nominal extrinsics: sensor frame (x forward, y left, z up) -> vehicle frame."""
    ray_directions: np.ndarray
    """(R, 3) unit beam directions in the sensor frame, identical for every sensor."""
    horizontal_beams: int
    vertical_beams: int

    @property
    def num_sensors(self) -> int:
        return len(self.T_vehicle_sensor)


def beam_directions(horizontal_beams: int, vertical_beams: int) -> np.ndarray:
    """(H * V, 3) unit directions covering the 120 x 45 degree field of view on a regular grid."""
    half_h, half_v = np.radians(HORIZONTAL_FOV_DEG) / 2, np.radians(VERTICAL_FOV_DEG) / 2
    azimuth = np.linspace(-half_h, half_h, horizontal_beams)
    elevation = np.linspace(-half_v, half_v, vertical_beams)
    az, el = np.meshgrid(azimuth, elevation, indexing="xy")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)


def default_rig(points_per_frame: int = 80_000, vertical_beams: int = 40) -> SensorRig:
    """Twelve sensors around a 1.6 x 1.0 m vehicle, looking every 30 degrees, at three heights.

    Low sensors look slightly up, high ones down, so that together they cover the floor near the
    vehicle, the objects around it and the upper shelves. Indoors almost every beam returns, so the
    horizontal beam count is set from the requested number of points per frame; 40 x 167 beams give
    about 0.7 x 1.2 degrees between beams.
    """
    if points_per_frame < NUM_SENSORS * vertical_beams:
        raise ValueError(f"points_per_frame must be at least {NUM_SENSORS * vertical_beams}")
    horizontal_beams = int(np.ceil(points_per_frame / (NUM_SENSORS * vertical_beams)))
    transforms = []
    for i in range(NUM_SENSORS):
        yaw = np.radians(30.0 * i)
        height, pitch = [(0.45, np.radians(8.0)), (1.1, np.radians(-4.0)), (1.75, np.radians(-16.0))][i % 3]
        roll = np.radians([0.0, 1.5, -1.5, 0.0][i % 4])
        position = np.array([0.8 * np.cos(yaw), 0.5 * np.sin(yaw), height])
        transforms.append(make_transform(rotation_ypr(yaw, -pitch, roll), position))
    return SensorRig(
        np.stack(transforms),
        beam_directions(horizontal_beams, vertical_beams),
        horizontal_beams,
        vertical_beams,
    )


@dataclasses.dataclass(frozen=True)
class LoopPath:
    """A rounded rectangle around the central rack island, driven counter-clockwise."""

    half_x: float = 15.0
    half_y: float = 5.0
    corner_radius: float = 3.0

    @property
    def length(self) -> float:
        straight = 4 * (self.half_x - self.corner_radius) + 4 * (self.half_y - self.corner_radius)
        return straight + 2 * np.pi * self.corner_radius

    def pose_at(self, distance: float) -> tuple[float, float, float]:
        """(x, y, heading) after driving ``distance`` metres from (0, -half_y) heading +x."""
        a, b, r = self.half_x - self.corner_radius, self.half_y - self.corner_radius, self.corner_radius
        s = distance % self.length
        arc = np.pi * r / 2
        # (length, start point, start heading, corner centre or None) for each piece, in order.
        pieces = [
            (a, (0.0, -self.half_y), 0.0, None),
            (arc, None, 0.0, (a, -b)),
            (2 * b, (self.half_x, -b), np.pi / 2, None),
            (arc, None, np.pi / 2, (a, b)),
            (2 * a, (a, self.half_y), np.pi, None),
            (arc, None, np.pi, (-a, b)),
            (2 * b, (-self.half_x, b), -np.pi / 2, None),
            (arc, None, -np.pi / 2, (-a, -b)),
            (a, (-a, -self.half_y), 0.0, None),
        ]
        for piece in pieces:
            if s <= piece[0]:
                break
            s -= piece[0]
        _, start, heading, centre = piece
        if centre is None:
            return start[0] + s * np.cos(heading), start[1] + s * np.sin(heading), heading
        angle = heading - np.pi / 2 + s / r  # position angle on the corner circle
        new_heading = heading + s / r
        return (
            centre[0] + r * np.cos(angle),
            centre[1] + r * np.sin(angle),
            float((new_heading + np.pi) % (2 * np.pi) - np.pi),
        )
