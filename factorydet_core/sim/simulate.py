"""Ray-cast the factory from the AGV's twelve LiDARs and write a partially annotated data set.

Data set layout (``DIR/``)::

    manifest.json            classes, sensors with nominal extrinsics, splits, seed, generator version
    frames/frame_00000.npz   what the data set publishes: points per sensor, odometry pose, annotations
    truth/truth.json         hidden truth: true extrinsics, every instance and its class
    truth/frame_00000.npz    hidden truth per frame: true pose, every point's instance, every visible box

Only benchmarks and tests read ``truth/``; the app and the detector never do.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d

from factorydet_core.geometry import invert_transform, make_transform, rotation_ypr, transform_boxes
from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.io.npz import save_npz
from factorydet_core.sim.factory import Factory, build_factory
from factorydet_core.sim.meshes import Mesh
from factorydet_core.sim.rig import (
    HORIZONTAL_FOV_DEG,
    MAX_RANGE_M,
    VERTICAL_FOV_DEG,
    LoopPath,
    SensorRig,
    default_rig,
)
from factorydet_core.types import CLASS_NAMES

GENERATOR = "factorydet-sim"
GENERATOR_VERSION = 1


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Settings of a simulated data set; every field is stored in the manifest."""

    num_frames: int = 10
    seed: int = 0
    unlabelled_fraction: float = 0.3
    """Fraction of the eligible objects of each class left unannotated in every frame."""
    min_annotated_points: int = 50
    """Instances with fewer visible points are never annotated. The paper uses 2048 on clouds
    accumulated over several frames; one 80k-point frame of this hall gives a tenth of that density
    (90th percentile of a visible barrel: about 50 points), so the default is scaled down."""
    points_per_frame: int = 80_000
    vertical_beams: int = 40
    step_m: float = 1.5
    """Distance the vehicle drives between frames."""
    vehicle_speed: float = 1.0
    """Metres per second; sets the time between frames, and so how far people and trucks move."""
    range_noise_m: float = 0.015
    calibration_rotation_deg: float = 1.0
    calibration_translation_m: float = 0.02
    odometry_translation_noise: float = 0.01
    """Standard deviation of the odometry drift, metres per metre driven."""
    odometry_yaw_noise_deg: float = 0.2
    """Standard deviation of the heading drift, degrees per metre driven."""
    train_fraction: float = 2 / 3

    def __post_init__(self) -> None:
        if self.num_frames < 1:
            raise ValueError("num_frames must be at least 1")
        if not 0.0 <= self.unlabelled_fraction <= 1.0:
            raise ValueError("unlabelled_fraction must lie in [0, 1]")
        if self.min_annotated_points < 0:
            raise ValueError("min_annotated_points must be >= 0")
        if self.vertical_beams < 2 or self.points_per_frame < 12 * self.vertical_beams:
            raise ValueError(
                f"points_per_frame must be at least 12 x vertical_beams = {12 * self.vertical_beams}"
            )
        if not 0.0 < self.train_fraction <= 1.0:
            raise ValueError("train_fraction must lie in (0, 1]")


@dataclasses.dataclass(frozen=True)
class SimulatedFrame:
    """One frame with its truth, in memory."""

    points: np.ndarray
    """(N, 3) float32 points in the frame of the sensor that measured them."""
    sensor_ids: np.ndarray
    """(N,) int16."""
    T_world_vehicle_odometry: np.ndarray
    T_world_vehicle_true: np.ndarray
    time_s: float
    point_instance_ids: np.ndarray
    """(N,) int32 true instance of every point (0 for floor, walls and racks)."""
    instance_ids: np.ndarray
    """(M,) int64 every instance with at least one visible point, structure excluded."""
    instance_class_ids: np.ndarray
    """(M,) int32 class of each, -1 for clutter."""
    instance_boxes: np.ndarray
    """(M, 7) whole-object boxes in the true vehicle frame."""
    instance_num_points: np.ndarray
    annotated_mask: np.ndarray
    """(M,) bool: the instance is annotated in this frame."""


def _split(num_frames: int, train_fraction: float) -> dict[str, list[int]]:
    """Contiguous blocks, so that test frames are not interleaved with near-identical train frames."""
    num_train = min(num_frames, max(1, int(round(num_frames * train_fraction))))
    return {"train": list(range(num_train)), "test": list(range(num_train, num_frames))}


def _random_rotation(rng: np.random.Generator, angle_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(angle_deg) * rng.uniform(0.6, 1.4)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


class FactorySimulator:
    """A factory, a rig with calibration errors, and a trajectory; renders frames on demand.

    Args:
        config: data set settings.
    """

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        seed = config.seed
        self.factory: Factory = build_factory(np.random.default_rng([seed, 0]))
        self.rig: SensorRig = default_rig(config.points_per_frame, config.vertical_beams)
        self.path = LoopPath()
        rng = np.random.default_rng([seed, 1])
        self.T_vehicle_sensor_true = np.stack(
            [
                T
                @ make_transform(
                    _random_rotation(rng, config.calibration_rotation_deg),
                    rng.normal(size=3) / np.sqrt(3) * config.calibration_translation_m,
                )
                for T in self.rig.T_vehicle_sensor
            ]
        )
        self.unannotated_ids = self._choose_unannotated(np.random.default_rng([seed, 2]))
        self._odometry = self._odometry_poses(np.random.default_rng([seed, 3]))
        self._static_scene, self._static_face_ids = self._scene(
            [(o.instance_id, o.mesh.posed(*o.pose)) for o in self.factory.static_objects],
            self.factory.structure,
        )
        self._objects_by_id = {o.instance_id: o for o in self.factory.objects}

    def _choose_unannotated(self, rng: np.random.Generator) -> frozenset[int]:
        """The same objects stay unannotated in every frame: a per-class share of the instances."""
        chosen: list[int] = []
        for class_id in range(len(CLASS_NAMES)):
            ids = [o.instance_id for o in self.factory.objects if o.class_id == class_id]
            count = int(round(self.config.unlabelled_fraction * len(ids)))
            chosen += rng.permutation(ids)[:count].tolist()
        return frozenset(int(i) for i in chosen)

    def true_pose(self, frame_index: int) -> np.ndarray:
        x, y, heading = self.path.pose_at(frame_index * self.config.step_m)
        return make_transform(rotation_ypr(heading, 0, 0), np.array([x, y, 0.0]))

    def _odometry_poses(self, rng: np.random.Generator) -> list[np.ndarray]:
        """Odometry = truth composed with a drift that grows as a random walk with distance."""
        poses, drift = [], np.zeros(3)
        step = self.config.step_m
        for i in range(self.config.num_frames):
            if i:
                drift += rng.normal(size=3) * np.array(
                    [self.config.odometry_translation_noise * step] * 2
                    + [np.radians(self.config.odometry_yaw_noise_deg) * step]
                )
            T_drift = make_transform(rotation_ypr(drift[2], 0, 0), np.array([drift[0], drift[1], 0.0]))
            poses.append(self.true_pose(i) @ T_drift)
        return poses

    @staticmethod
    def _scene(
        posed: list[tuple[int, Mesh]], structure: Mesh | None = None
    ) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray]:
        parts = ([(0, structure)] if structure is not None else []) + posed
        mesh = Mesh.concatenate([m for _, m in parts])
        face_ids = np.concatenate([np.full(len(m.faces), i, np.int32) for i, m in parts])
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
        )
        return scene, face_ids

    def render(self, frame_index: int) -> SimulatedFrame:
        """Ray-cast frame ``frame_index`` (deterministic for a given seed and index)."""
        cfg = self.config
        time_s = frame_index * cfg.step_m / cfg.vehicle_speed
        rng = np.random.default_rng([cfg.seed, 4, frame_index])
        T_world_vehicle = self.true_pose(frame_index)
        moving = self.factory.moving_objects
        dynamic_scene, dynamic_face_ids = self._scene(
            [(o.instance_id, o.mesh.posed(*o.pose_at(time_s))) for o in moving]
        )

        directions = self.rig.ray_directions
        num_rays = len(directions)
        T_world_sensor = T_world_vehicle[None] @ self.T_vehicle_sensor_true
        world_dirs = np.einsum("sij,rj->sri", T_world_sensor[:, :3, :3], directions)
        origins = np.broadcast_to(T_world_sensor[:, None, :3, 3], world_dirs.shape)
        rays = o3d.core.Tensor(np.concatenate([origins, world_dirs], -1).reshape(-1, 6).astype(np.float32))
        hit_static = self._static_scene.cast_rays(rays, nthreads=0)
        hit_dynamic = dynamic_scene.cast_rays(rays, nthreads=0)
        t_static, t_dynamic = hit_static["t_hit"].numpy(), hit_dynamic["t_hit"].numpy()
        dynamic_first = t_dynamic < t_static
        t_hit = np.where(dynamic_first, t_dynamic, t_static)
        valid = np.isfinite(t_hit) & (t_hit <= MAX_RANGE_M)
        primitive_static = hit_static["primitive_ids"].numpy().astype(np.int64)
        primitive_dynamic = hit_dynamic["primitive_ids"].numpy().astype(np.int64)

        ray_index = np.nonzero(valid)[0]
        ranges = t_hit[ray_index].astype(np.float64) + rng.normal(0.0, cfg.range_noise_m, len(ray_index))
        points = (directions[ray_index % num_rays] * ranges[:, None]).astype(np.float32)
        sensor_ids = (ray_index // num_rays).astype(np.int16)
        from_dynamic = dynamic_first[ray_index]
        point_instance_ids = np.where(
            from_dynamic,
            dynamic_face_ids[np.where(from_dynamic, primitive_dynamic[ray_index], 0)]
            if len(dynamic_face_ids)
            else 0,
            self._static_face_ids[np.where(from_dynamic, 0, primitive_static[ray_index])],
        ).astype(np.int32)

        instance_ids, counts = np.unique(point_instance_ids[point_instance_ids > 0], return_counts=True)
        T_vehicle_world = invert_transform(T_world_vehicle)
        world_boxes = np.array([self._objects_by_id[int(i)].box_at(time_s) for i in instance_ids]).reshape(
            -1, 7
        )
        class_ids = np.array([self._objects_by_id[int(i)].class_id for i in instance_ids], dtype=np.int32)
        annotated = (
            (class_ids >= 0)
            & (counts >= cfg.min_annotated_points)
            & np.array([int(i) not in self.unannotated_ids for i in instance_ids], dtype=bool)
        )
        return SimulatedFrame(
            points=points,
            sensor_ids=sensor_ids,
            T_world_vehicle_odometry=self._odometry[frame_index]
            if frame_index < len(self._odometry)
            else T_world_vehicle,
            T_world_vehicle_true=T_world_vehicle,
            time_s=time_s,
            point_instance_ids=point_instance_ids,
            instance_ids=instance_ids.astype(np.int64),
            instance_class_ids=class_ids,
            instance_boxes=transform_boxes(T_vehicle_world, world_boxes),
            instance_num_points=counts.astype(np.int64),
            annotated_mask=annotated,
        )

    def manifest(self) -> dict:
        rig = self.rig
        return {
            "generator": GENERATOR,
            "generator_version": GENERATOR_VERSION,
            "seed": self.config.seed,
            "config": dataclasses.asdict(self.config),
            "classes": list(CLASS_NAMES),
            "box_convention": (
                "(cx, cy, cz, dx, dy, dz, yaw) in the vehicle frame; z up, metres, yaw CCW about +z"
            ),
            "sensors": [
                {
                    "id": i,
                    "name": f"lidar_{i:02d}",
                    "T_vehicle_sensor": np.round(T, 12).tolist(),
                    "horizontal_fov_deg": HORIZONTAL_FOV_DEG,
                    "vertical_fov_deg": VERTICAL_FOV_DEG,
                    "max_range_m": MAX_RANGE_M,
                    "horizontal_beams": rig.horizontal_beams,
                    "vertical_beams": rig.vertical_beams,
                }
                for i, T in enumerate(rig.T_vehicle_sensor)
            ],
            "frames": [f"frames/frame_{i:05d}.npz" for i in range(self.config.num_frames)],
            "splits": _split(self.config.num_frames, self.config.train_fraction),
        }

    def truth(self) -> dict:
        return {
            "T_vehicle_sensor_true": np.round(self.T_vehicle_sensor_true, 12).tolist(),
            "instances": [
                {
                    "id": o.instance_id,
                    "kind": o.kind,
                    "class_id": o.class_id,
                    "moving": o.motion is not None,
                    "unannotated": o.instance_id in self.unannotated_ids,
                }
                for o in self.factory.objects
            ],
        }


def _write_json(path: Path, obj: dict) -> None:
    write_text_atomic(path, json.dumps(obj, indent=1, sort_keys=True) + "\n")


def write_frame(out: Path, simulator: FactorySimulator, frame_index: int) -> Path:
    """Render frame ``frame_index`` and write its truth, then the frame itself (a frame file
    present means its truth is too: a batch that resumes skips it whole). Returns the frame file."""
    frame = simulator.render(frame_index)
    annotated_ids = frame.instance_ids[frame.annotated_mask]
    save_npz(
        out / "truth" / f"frame_{frame_index:05d}.npz",
        {
            "T_world_vehicle": frame.T_world_vehicle_true,
            "point_instance_ids": frame.point_instance_ids,
            "instance_ids": frame.instance_ids,
            "instance_class_ids": frame.instance_class_ids,
            "instance_boxes": frame.instance_boxes,
            "instance_num_points": frame.instance_num_points,
            "annotated_mask": frame.annotated_mask,
        },
    )
    path = out / "frames" / f"frame_{frame_index:05d}.npz"
    save_npz(
        path,
        {
            "points": frame.points,
            "sensor_ids": frame.sensor_ids,
            "T_world_vehicle": frame.T_world_vehicle_odometry,
            "time_s": np.float64(frame.time_s),
            "point_instance_ids": np.where(
                np.isin(frame.point_instance_ids, annotated_ids), frame.point_instance_ids, 0
            ).astype(np.int32),
            "label_boxes": frame.instance_boxes[frame.annotated_mask],
            "label_class_ids": frame.instance_class_ids[frame.annotated_mask],
            "label_instance_ids": annotated_ids,
            "label_num_points": frame.instance_num_points[frame.annotated_mask],
        },
    )
    return path


def finish_dataset(out: Path, simulator: FactorySimulator) -> Path:
    """Write the truth's object list and, last, the manifest: a folder with a manifest is a
    complete data set."""
    _write_json(out / "truth" / "truth.json", simulator.truth())
    _write_json(out / "manifest.json", simulator.manifest())
    return out


def simulate_dataset(
    out_dir: str | os.PathLike,
    config: SimConfig,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Write a simulated data set to ``out_dir``; the same config gives the same bytes.

    Args:
        out_dir: folder to create (it may exist; its frames are overwritten).
        config: settings, stored in the manifest.
        progress: called as ``progress(frames_done, num_frames)``.

    Returns:
        The data set folder.
    """
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    simulator = FactorySimulator(config)
    for i in range(config.num_frames):
        write_frame(out, simulator, i)
        if progress is not None:
            progress(i + 1, config.num_frames)
    return finish_dataset(out, simulator)
