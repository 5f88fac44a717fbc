"""Procedural triangle meshes of the paper's seven classes and of background clutter.

Every builder returns a ``Mesh`` in the object's own frame: z up, standing on z = 0, roughly
centred on the z axis, with its long or characteristic axis along x (the ``dx`` edge of its box).
Sizes follow real objects and vary per instance.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import trimesh

from factorydet_core.geometry import make_transform, rotation_ypr


@dataclasses.dataclass(frozen=True)
class Mesh:
    """A triangle mesh as plain arrays."""

    vertices: np.ndarray
    """(V, 3) float64 vertex positions, metres."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices, counter-clockwise seen from outside."""

    @staticmethod
    def concatenate(meshes: list[Mesh]) -> Mesh:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            vertices=np.concatenate([m.vertices for m in meshes]),
            faces=np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]),
        )

    def transformed(self, transform: np.ndarray) -> Mesh:
        return Mesh(self.vertices @ transform[:3, :3].T + transform[:3, 3], self.faces)

    def posed(self, x: float, y: float, z: float, yaw: float) -> Mesh:
        return self.transformed(make_transform(rotation_ypr(yaw, 0.0, 0.0), np.array([x, y, z])))

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned min and max corners."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


def _from_trimesh(mesh: trimesh.Trimesh) -> Mesh:
    return Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))


_UNIT_BOX = _from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))
_UNIT_CYLINDERS: dict[int, Mesh] = {}


def cuboid(size: tuple[float, float, float], center: tuple[float, float, float]) -> Mesh:
    """Axis-aligned box of full edge lengths ``size`` centred at ``center``."""
    return Mesh(_UNIT_BOX.vertices * np.asarray(size) + np.asarray(center), _UNIT_BOX.faces)


def cylinder(
    radius: float,
    length: float,
    center: tuple[float, float, float],
    axis: str = "z",
    sections: int = 20,
) -> Mesh:
    """Closed cylinder along the x, y or z axis."""
    if sections not in _UNIT_CYLINDERS:
        _UNIT_CYLINDERS[sections] = _from_trimesh(
            trimesh.creation.cylinder(radius=1.0, height=1.0, sections=sections)
        )
    unit = _UNIT_CYLINDERS[sections]
    vertices = unit.vertices * np.array([radius, radius, length])
    if axis == "x":
        vertices = vertices[:, [2, 1, 0]] * np.array([1, 1, -1])
    elif axis == "y":
        vertices = vertices[:, [0, 2, 1]] * np.array([1, 1, -1])
    return Mesh(vertices + np.asarray(center), unit.faces)


def cone(radius: float, height: float, base_z: float, sections: int = 20) -> Mesh:
    return _from_trimesh(trimesh.creation.cone(radius=radius, height=height, sections=sections)).posed(
        0, 0, base_z, 0
    )


def sphere(radius: float, center: tuple[float, float, float]) -> Mesh:
    mesh = _from_trimesh(trimesh.creation.icosphere(subdivisions=1, radius=radius))
    return Mesh(mesh.vertices + np.asarray(center), mesh.faces)


# --- the seven classes -------------------------------------------------------------------------


def barrel(rng: np.random.Generator) -> Mesh:
    """A 200-litre drum, about 0.58 m across and 0.88 m tall, with two rolling hoops."""
    radius, height = rng.uniform(0.27, 0.30), rng.uniform(0.84, 0.92)
    parts = [cylinder(radius, height, (0, 0, height / 2), sections=24)]
    for z in (height / 3, 2 * height / 3):
        parts.append(cylinder(radius + 0.012, 0.03, (0, 0, z), sections=24))
    return Mesh.concatenate(parts)


def bobbin(rng: np.random.Generator) -> Mesh:
    """A cable or yarn spool lying on its side: two flanges on a core, axis along x."""
    flange_radius = rng.uniform(0.16, 0.32)
    width = rng.uniform(0.22, 0.45)
    core_radius = flange_radius * rng.uniform(0.45, 0.7)
    flange = rng.uniform(0.025, 0.04)
    z = flange_radius
    return Mesh.concatenate(
        [
            cylinder(core_radius, width - 2 * flange, (0, 0, z), axis="x"),
            cylinder(flange_radius, flange, (-(width - flange) / 2, 0, z), axis="x"),
            cylinder(flange_radius, flange, ((width - flange) / 2, 0, z), axis="x"),
        ]
    )


def box(rng: np.random.Generator, size: tuple[float, float, float] | None = None) -> Mesh:
    """A cardboard or plastic box."""
    if size is None:
        size = (rng.uniform(0.35, 0.8), rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.6))
    size = (max(size[0], size[1]), min(size[0], size[1]), size[2])
    return cuboid(size, (0, 0, size[2] / 2))


def traffic_cone(rng: np.random.Generator) -> Mesh:
    """A traffic cone on its square foot."""
    height = rng.uniform(0.5, 0.75)
    foot = rng.uniform(0.34, 0.4)
    return Mesh.concatenate(
        [cuboid((foot, foot, 0.03), (0, 0, 0.015)), cone(height * 0.24, height - 0.03, 0.03, sections=16)]
    )


def pallet(rng: np.random.Generator) -> Mesh:
    """A wooden EUR (1.2 x 0.8 m) or industrial (1.2 x 1.0 m) pallet: deck boards on nine blocks."""
    length, width = 1.2, (0.8 if rng.uniform() < 0.7 else 1.0)
    board, block, bottom = 0.022, 0.078, 0.022
    parts = []
    for y in np.linspace(-width / 2 + 0.0725, width / 2 - 0.0725, 5):
        parts.append(cuboid((length, 0.12, board), (0, y, bottom + block + board / 2)))
    for y in (-width / 2 + 0.0725, 0.0, width / 2 - 0.0725):
        parts.append(cuboid((length, 0.145, bottom), (0, y, bottom / 2)))
        for x in (-length / 2 + 0.05, 0.0, length / 2 - 0.05):
            parts.append(cuboid((0.1, 0.145, block), (x, y, bottom + block / 2)))
    return Mesh.concatenate(parts)


def person(rng: np.random.Generator, walking: bool = False) -> Mesh:
    """A standing or walking person facing +x, 1.55 to 1.95 m tall."""
    height = rng.uniform(1.55, 1.95)
    leg = 0.47 * height
    torso = 0.3 * height
    head_r = 0.06 * height
    shoulder = rng.uniform(0.38, 0.46)
    stride = 0.18 if walking else 0.0
    parts = [
        cylinder(0.065, leg, (stride, 0.1, leg / 2)),
        cylinder(0.065, leg, (-stride, -0.1, leg / 2)),
        cuboid((0.24, shoulder, torso), (0, 0, leg + torso / 2)),
        sphere(head_r, (0, 0, leg + torso + head_r + 0.04)),
        cylinder(0.045, 0.62 * torso * 1.9, (-stride, shoulder / 2 + 0.05, leg + torso * 0.45)),
        cylinder(0.045, 0.62 * torso * 1.9, (stride, -shoulder / 2 - 0.05, leg + torso * 0.45)),
    ]
    return Mesh.concatenate(parts)


def truck(rng: np.random.Generator) -> Mesh:
    """A forklift (mast and forks) or a hand pallet truck; forks point along +x."""
    if rng.uniform() < 0.5:
        body_l, body_w, body_h = rng.uniform(1.9, 2.4), rng.uniform(1.05, 1.2), rng.uniform(1.1, 1.3)
        mast_h = rng.uniform(2.0, 2.4)
        parts = [
            cuboid((body_l, body_w, body_h), (0, 0, 0.15 + body_h / 2)),
            cuboid((0.4, body_w * 0.8, 0.5), (-body_l / 2 + 0.2, 0, 0.15 + body_h + 0.25)),  # counterweight
            cuboid((0.08, 0.08, mast_h), (body_l / 2 + 0.05, body_w / 2 - 0.15, mast_h / 2)),
            cuboid((0.08, 0.08, mast_h), (body_l / 2 + 0.05, -body_w / 2 + 0.15, mast_h / 2)),
            cuboid((0.05, 0.05, 0.95), (-0.1, body_w / 2 - 0.05, 0.15 + body_h + 0.47)),  # cabin guard posts
            cuboid((0.05, 0.05, 0.95), (-0.1, -body_w / 2 + 0.05, 0.15 + body_h + 0.47)),
            cuboid((0.9, body_w, 0.05), (0.25, 0, 0.15 + body_h + 0.95)),
            cuboid((1.1, 0.12, 0.05), (body_l / 2 + 0.65, 0.25, 0.08)),
            cuboid((1.1, 0.12, 0.05), (body_l / 2 + 0.65, -0.25, 0.08)),
        ]
        for x in (-body_l / 2 + 0.35, body_l / 2 - 0.35):
            for y in (-body_w / 2, body_w / 2):
                parts.append(cylinder(0.25, 0.2, (x, y, 0.25), axis="y", sections=16))
        return Mesh.concatenate(parts)
    fork_l = rng.uniform(1.1, 1.2)
    parts = [
        cuboid((fork_l, 0.16, 0.08), (fork_l / 2, 0.2, 0.04)),
        cuboid((fork_l, 0.16, 0.08), (fork_l / 2, -0.2, 0.04)),
        cuboid((0.35, 0.56, 0.35), (-0.175, 0, 0.2)),
        cylinder(0.02, 1.0, (-0.45, 0, 0.8)).transformed(
            make_transform(rotation_ypr(0, -0.35, 0), np.array([0.0, 0.0, 0.0]))
        ),
        cuboid((0.06, 0.3, 0.04), (-0.78, 0, 1.28)),
    ]
    return Mesh.concatenate(parts)


# --- background clutter (no class) ----------------------------------------------------------------


def machine(rng: np.random.Generator) -> Mesh:
    length, width, height = rng.uniform(1.6, 3.0), rng.uniform(1.0, 1.8), rng.uniform(1.3, 2.2)
    return Mesh.concatenate(
        [
            cuboid((length, width, height), (0, 0, height / 2)),
            cylinder(width * 0.3, 0.6, (length * 0.2, 0, height + 0.3)),
            cuboid((0.3, 0.6, 0.5), (length / 2 + 0.15, 0, 1.0)),  # control panel
        ]
    )


def table(rng: np.random.Generator) -> Mesh:
    length, width, height = rng.uniform(1.2, 2.0), rng.uniform(0.6, 0.9), rng.uniform(0.72, 0.9)
    parts = [cuboid((length, width, 0.04), (0, 0, height - 0.02))]
    for x in (-length / 2 + 0.05, length / 2 - 0.05):
        for y in (-width / 2 + 0.05, width / 2 - 0.05):
            parts.append(cuboid((0.05, 0.05, height - 0.04), (x, y, (height - 0.04) / 2)))
    return Mesh.concatenate(parts)


def bin_(rng: np.random.Generator) -> Mesh:
    size = (rng.uniform(0.5, 0.8), rng.uniform(0.4, 0.6), rng.uniform(0.6, 1.1))
    return cuboid(size, (0, 0, size[2] / 2))


def cabinet(rng: np.random.Generator) -> Mesh:
    size = (rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.6), rng.uniform(1.8, 2.1))
    return cuboid(size, (0, 0, size[2] / 2))


CLASS_BUILDERS: dict[str, Callable[[np.random.Generator], Mesh]] = {
    "barrel": barrel,
    "bobbin": bobbin,
    "box": box,
    "cone": traffic_cone,
    "pallet": pallet,
    "person": person,
    "truck": truck,
}
CLUTTER_BUILDERS: dict[str, Callable[[np.random.Generator], Mesh]] = {
    "machine": machine,
    "table": table,
    "bin": bin_,
    "cabinet": cabinet,
}
