"""Procedural factory hall: structure, racks, stored objects, clutter and moving agents.

The layout (world frame, origin at the hall centre, z up, metres)::

    y = +16  wall ---------------------------------------------------------------
    y = 12.3..13.5   rack row A (3-4 levels: bobbins, pallets, boxes)
    y =  8.8..11.8   floor storage: barrel groups, pallet loads, box stacks, machines, tables
    y =  6.8.. 7.8   walking lane (people)      y = 6.2 cones
    y =  5           AGV loop (top edge)
    y = -1.2.. 1.2   double rack island C (x in [-10.8, 10.8]); |x| 11.5..13.5 loop ends
    y = -5           AGV loop (bottom edge)
    y = -6.9..-8.1   truck lane (pallet trucks and forklifts driving)   y = -6.2 cones
    y = -8.8..-11.8  floor storage: box stacks, parked trucks, pallet loads, bins, tables
    y = -12.3..-13.5 rack row B
    y = -16  wall ---------------------------------------------------------------
    |x| 16.5..23.5   east/west work areas: machines, tables, standing people, pallets, cones

Objects touch each other and the racks on purpose: separating them is the hard part of the paper.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from factorydet_core.sim import meshes
from factorydet_core.sim.meshes import Mesh
from factorydet_core.types import CLASS_NAMES

HALL_HALF_X, HALL_HALF_Y, HALL_HEIGHT = 24.0, 16.0, 8.0
LEVEL_SPACING = 1.6
BAY_WIDTH = 2.7
RACK_DEPTH = 1.2
PLATE = 0.03


@dataclasses.dataclass(frozen=True)
class Motion:
    """Back-and-forth walk between two floor points at constant speed."""

    start: np.ndarray
    """(2,) xy of one end, metres."""
    end: np.ndarray
    """(2,) xy of the other end."""
    speed: float
    """Metres per second."""
    phase: float
    """Distance already walked at time 0, metres."""

    def pose_at(self, time_s: float) -> tuple[float, float, float]:
        """(x, y, yaw) at ``time_s``; the agent faces where it is going."""
        delta = self.end - self.start
        length = float(np.linalg.norm(delta))
        walked = (self.speed * time_s + self.phase) % (2 * length)
        forward = walked < length
        along = walked if forward else 2 * length - walked
        xy = self.start + delta * (along / length)
        heading = np.arctan2(delta[1], delta[0]) + (0.0 if forward else np.pi)
        return float(xy[0]), float(xy[1]), float((heading + np.pi) % (2 * np.pi) - np.pi)


@dataclasses.dataclass(frozen=True)
class PlacedObject:
    """One object instance of the factory."""

    instance_id: int
    kind: str
    """Class name (one of ``CLASS_NAMES``) or a clutter kind (machine, table, bin, cabinet)."""
    mesh: Mesh
    """Mesh in the object's own frame."""
    pose: tuple[float, float, float, float]
    """(x, y, z, yaw) of the object frame in the world, for static objects and at time 0."""
    motion: Motion | None = None

    @property
    def class_id(self) -> int:
        """Index into ``CLASS_NAMES``, or -1 for clutter."""
        return CLASS_NAMES.index(self.kind) if self.kind in CLASS_NAMES else -1

    def pose_at(self, time_s: float) -> tuple[float, float, float, float]:
        if self.motion is None:
            return self.pose
        x, y, yaw = self.motion.pose_at(time_s)
        return (x, y, self.pose[2], yaw)

    def box_at(self, time_s: float) -> np.ndarray:
        """(7,) box of the whole object in the world frame at ``time_s``."""
        x, y, z, yaw = self.pose_at(time_s)
        low, high = self.mesh.bounds
        center_local = (low + high) / 2
        c, s = np.cos(yaw), np.sin(yaw)
        center = np.array(
            [
                x + c * center_local[0] - s * center_local[1],
                y + s * center_local[0] + c * center_local[1],
                z + center_local[2],
            ]
        )
        return np.concatenate([center, high - low, [yaw]])


@dataclasses.dataclass(frozen=True)
class Factory:
    """A generated hall: static structure plus object instances."""

    structure: Mesh
    """Floor, walls, roof, pillars and racks: instance id 0."""
    objects: tuple[PlacedObject, ...]

    @property
    def static_objects(self) -> tuple[PlacedObject, ...]:
        return tuple(o for o in self.objects if o.motion is None)

    @property
    def moving_objects(self) -> tuple[PlacedObject, ...]:
        return tuple(o for o in self.objects if o.motion is not None)


class _Builder:
    """Accumulates structure and objects; keeps floor footprints to avoid overlaps."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.structure: list[Mesh] = []
        self.objects: list[PlacedObject] = []
        self.footprints: list[tuple[float, float, float, float]] = []  # xmin, ymin, xmax, ymax

    def add(
        self, kind: str, mesh: Mesh, x: float, y: float, z: float, yaw: float, motion: Motion | None = None
    ) -> PlacedObject:
        placed = PlacedObject(len(self.objects) + 1, kind, mesh, (x, y, z, yaw), motion)
        self.objects.append(placed)
        return placed

    def free(self, xmin: float, ymin: float, xmax: float, ymax: float, pad: float = 0.25) -> bool:
        return all(
            xmax + pad <= a or xmin - pad >= c or ymax + pad <= b or ymin - pad >= d
            for a, b, c, d in self.footprints
        )

    def place_group(
        self, zone: tuple[float, float, float, float], half: tuple[float, float], tries: int = 60
    ) -> tuple[float, float] | None:
        """Find a free spot in ``zone`` (xmin, ymin, xmax, ymax) for a group of half extents ``half``."""
        if 2 * half[0] > zone[2] - zone[0] or 2 * half[1] > zone[3] - zone[1]:
            return None
        for _ in range(tries):
            x = self.rng.uniform(zone[0] + half[0], zone[2] - half[0])
            y = self.rng.uniform(zone[1] + half[1], zone[3] - half[1])
            if self.free(x - half[0], y - half[1], x + half[0], y + half[1]):
                self.footprints.append((x - half[0], y - half[1], x + half[0], y + half[1]))
                return x, y
        return None


def _rotated_half(mesh: Mesh, yaw: float) -> tuple[float, float]:
    low, high = mesh.bounds
    half = (high - low)[:2] / 2
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    return (c * half[0] + s * half[1], s * half[0] + c * half[1])


def _hall(builder: _Builder) -> None:
    t = 0.2
    hx, hy, h = HALL_HALF_X, HALL_HALF_Y, HALL_HEIGHT
    builder.structure += [
        meshes.cuboid((2 * hx, 2 * hy, t), (0, 0, -t / 2)),
        meshes.cuboid((2 * hx, 2 * hy, t), (0, 0, h + t / 2)),
        meshes.cuboid((2 * hx, t, h), (0, hy + t / 2, h / 2)),
        meshes.cuboid((2 * hx, t, h), (0, -hy - t / 2, h / 2)),
        meshes.cuboid((t, 2 * hy, h), (hx + t / 2, 0, h / 2)),
        meshes.cuboid((t, 2 * hy, h), (-hx - t / 2, 0, h / 2)),
    ]
    for x in np.arange(-hx + 4.0, hx - 3.9, 8.0):
        for y in (-hy + 0.3, hy - 0.3):
            builder.structure.append(meshes.cuboid((0.5, 0.5, h), (x, y, h / 2)))
    for x, y in ((-19.5, 8.0), (19.5, -8.0)):
        builder.structure.append(meshes.cuboid((0.5, 0.5, h), (x, y, h / 2)))
        builder.footprints.append((x - 0.25, y - 0.25, x + 0.25, y + 0.25))


def _rack_row(
    builder: _Builder, x_min: float, num_bays: int, y_back: float, facing: float, num_levels: int
) -> None:
    """One single-depth rack row; ``facing`` is +1 when its open side looks to +y."""
    rng = builder.rng
    y_front = y_back + facing * RACK_DEPTH
    y_mid = (y_back + y_front) / 2
    top = (num_levels - 1) * LEVEL_SPACING + 0.4
    x_max = x_min + num_bays * BAY_WIDTH
    for x in np.linspace(x_min, x_max, num_bays + 1):
        for y in (y_back, y_front):
            builder.structure.append(meshes.cuboid((0.09, 0.07, top), (x, y - facing * 0.035, top / 2)))
    for level in range(1, num_levels):
        z = level * LEVEL_SPACING
        builder.structure.append(
            meshes.cuboid((x_max - x_min, RACK_DEPTH, PLATE), ((x_min + x_max) / 2, y_mid, z - PLATE / 2))
        )
        for y in (y_back, y_front):
            builder.structure.append(
                meshes.cuboid(
                    (x_max - x_min, 0.05, 0.12), ((x_min + x_max) / 2, y - facing * 0.025, z - PLATE - 0.06)
                )
            )
    builder.footprints.append(
        (x_min - 0.1, min(y_back, y_front) - 0.1, x_max + 0.1, max(y_back, y_front) + 0.1)
    )
    for bay in range(num_bays):
        bay_x0 = x_min + bay * BAY_WIDTH + 0.06
        for level in range(num_levels):
            _fill_bay(
                builder, bay_x0, BAY_WIDTH - 0.12, y_mid, level * LEVEL_SPACING, LEVEL_SPACING - 0.25, rng
            )


def _fill_bay(
    builder: _Builder,
    x0: float,
    width: float,
    y_mid: float,
    z: float,
    clearance: float,
    rng: np.random.Generator,
) -> None:
    content = rng.choice(["bobbins", "pallets", "boxes", "empty"], p=[0.25, 0.3, 0.3, 0.15])
    if content == "bobbins":
        # Bobbins in a row, flange against flange; large ones in one row, small ones front and back.
        template = meshes.bobbin(rng)
        rows = [y_mid] if template.bounds[1, 1] > 0.26 else [y_mid - 0.3, y_mid + 0.3]
        for y in rows:
            x = x0
            while True:
                mesh = meshes.bobbin(rng) if rng.uniform() < 0.3 else template
                length = mesh.bounds[1, 0] - mesh.bounds[0, 0]
                if x + length > x0 + width:
                    break
                builder.add("bobbin", mesh, x + length / 2, y, z, 0.0)
                x += length + rng.choice([0.0, 0.0, 0.01])
    elif content == "pallets":
        x = x0 + 0.05
        while x + 0.8 <= x0 + width:
            pallet = meshes.pallet(rng)
            half_y = (pallet.bounds[1, 1] - pallet.bounds[0, 1]) / 2  # pallet's short side along the beam
            builder.add("pallet", pallet, x + half_y, y_mid, z, np.pi / 2)
            if rng.uniform() < 0.75:
                _stack_boxes(
                    builder, x + half_y, y_mid, z + 0.144, (2 * half_y - 0.05, 1.15), clearance - 0.15, rng
                )
            x += 2 * half_y + rng.uniform(0.05, 0.1)
    elif content == "boxes":
        x = x0
        while True:
            size = (rng.uniform(0.4, 0.8), rng.uniform(0.4, 0.6))
            if x + size[0] > x0 + width:
                break
            _stack_boxes(builder, x + size[0] / 2, y_mid, z, size, clearance, rng, max_height=3)
            x += size[0] + rng.choice([0.0, 0.02])


def _stack_boxes(
    builder: _Builder,
    x: float,
    y: float,
    z: float,
    footprint: tuple[float, float],
    clearance: float,
    rng: np.random.Generator,
    max_height: int = 2,
) -> None:
    """A column of boxes of one footprint, each resting on the one below."""
    top = z
    for _ in range(rng.integers(1, max_height + 1)):
        height = rng.uniform(0.25, 0.55)
        if top + height - z > clearance:
            break
        mesh = meshes.box(rng, (footprint[0], footprint[1], height))
        builder.add("box", mesh, x, y, top, 0.0 if footprint[0] >= footprint[1] else np.pi / 2)
        top += height


def _floor_zone(builder: _Builder, zone: tuple[float, float, float, float], recipe: dict[str, int]) -> None:
    rng = builder.rng
    for kind, count in recipe.items():
        for _ in range(count):
            _floor_group(builder, zone, kind, rng)


def _floor_group(
    builder: _Builder, zone: tuple[float, float, float, float], kind: str, rng: np.random.Generator
) -> None:
    if kind == "barrels":
        nx, ny = int(rng.integers(1, 4)), int(rng.integers(1, 3))
        spacing = 0.6
        spot = builder.place_group(zone, (nx * spacing / 2, ny * spacing / 2))
        if spot is None:
            return
        for i in range(nx):
            for j in range(ny):
                builder.add(
                    "barrel",
                    meshes.barrel(rng),
                    spot[0] + (i - (nx - 1) / 2) * spacing,
                    spot[1] + (j - (ny - 1) / 2) * spacing,
                    0.0,
                    rng.uniform(-np.pi, np.pi),
                )
    elif kind == "boxstack":
        nx = int(rng.integers(1, 3))
        size = (rng.uniform(0.5, 0.8), rng.uniform(0.4, 0.6))
        spot = builder.place_group(zone, (nx * size[0] / 2, size[1] / 2))
        if spot is None:
            return
        for i in range(nx):
            _stack_boxes(
                builder, spot[0] + (i - (nx - 1) / 2) * size[0], spot[1], 0.0, size, 2.2, rng, max_height=3
            )
    elif kind == "palletload":
        pallet = meshes.pallet(rng)
        yaw = rng.choice([0.0, np.pi / 2])
        spot = builder.place_group(zone, _rotated_half(pallet, yaw))
        if spot is None:
            return
        if rng.uniform() < 0.35:  # a stack of empty pallets, each its own instance
            for level in range(int(rng.integers(2, 6))):
                builder.add("pallet", pallet, spot[0], spot[1], level * 0.144, yaw)
        else:
            builder.add("pallet", pallet, spot[0], spot[1], 0.0, yaw)
            fp = (1.15, pallet.bounds[1, 1] * 2 - 0.05)
            if yaw:
                fp = (fp[1], fp[0])
            _stack_boxes(builder, spot[0], spot[1], 0.144, fp, 1.6, rng, max_height=3)
    elif kind == "cone":
        mesh = meshes.traffic_cone(rng)
        spot = builder.place_group(zone, (0.2, 0.2))
        if spot is not None:
            builder.add("cone", mesh, spot[0], spot[1], 0.0, rng.uniform(-np.pi, np.pi))
    elif kind in ("person", "truck"):
        mesh = meshes.person(rng) if kind == "person" else meshes.truck(rng)
        # Parked trucks stand roughly along the aisle; people face anywhere.
        yaw = (
            rng.uniform(-np.pi, np.pi)
            if kind == "person"
            else rng.choice([0.0, np.pi]) + rng.uniform(-0.3, 0.3)
        )
        spot = builder.place_group(zone, _rotated_half(mesh, yaw))
        if spot is not None:
            builder.add(kind, mesh, spot[0], spot[1], 0.0, yaw)
    else:
        mesh = meshes.CLUTTER_BUILDERS[kind](rng)
        yaw = rng.choice([0.0, np.pi / 2, rng.uniform(-np.pi, np.pi)])
        spot = builder.place_group(zone, _rotated_half(mesh, yaw))
        if spot is None:
            return
        builder.add(kind, mesh, spot[0], spot[1], 0.0, yaw)
        if kind == "table" and rng.uniform() < 0.5:  # a box on the table, touching it
            top = mesh.bounds[1, 2]
            builder.add(
                "box", meshes.box(rng, (0.4, 0.3, rng.uniform(0.2, 0.35))), spot[0], spot[1], top, yaw
            )


def _movers(builder: _Builder) -> None:
    rng = builder.rng
    # People walk the lane north of the loop and the east/west areas, one per stretch, so they never collide.
    for x0, x1 in ((-15.0, -6.0), (-4.0, 5.0), (7.0, 15.0)):
        mesh = meshes.person(rng, walking=True)
        motion = Motion(
            np.array([x0, 7.3 + rng.uniform(-0.2, 0.2)]),
            np.array([x1, 7.3]),
            rng.uniform(0.9, 1.4),
            rng.uniform(0, 10),
        )
        builder.add("person", mesh, x0, 7.3, 0.0, 0.0, motion)
    for x in (-20.0, 20.0):
        mesh = meshes.person(rng, walking=True)
        motion = Motion(
            np.array([x, -3.5]),
            np.array([x + rng.uniform(-1.5, 1.5), 3.5]),
            rng.uniform(0.8, 1.2),
            rng.uniform(0, 10),
        )
        builder.add("person", mesh, x, -3.5, 0.0, 0.0, motion)
    # Trucks drive the lane south of the loop, one per half.
    for x0, x1 in ((-15.0, -2.0), (2.0, 15.0)):
        mesh = meshes.truck(rng)
        motion = Motion(np.array([x0, -7.5]), np.array([x1, -7.5]), rng.uniform(1.0, 1.8), rng.uniform(0, 20))
        builder.add("truck", mesh, x0, -7.5, 0.0, 0.0, motion)


def build_factory(rng: np.random.Generator) -> Factory:
    """Generate a factory hall; the same generator state gives the same hall."""
    builder = _Builder(rng)
    _hall(builder)
    row_levels = [int(rng.integers(3, 5)) for _ in range(3)]
    _rack_row(builder, -20.25, 15, 13.5, -1.0, row_levels[0])
    _rack_row(builder, -20.25, 15, -13.5, 1.0, row_levels[1])
    _rack_row(builder, -10.8, 8, 0.0, 1.0, row_levels[2])
    _rack_row(builder, -10.8, 8, 0.0, -1.0, row_levels[2])
    # Aisle cones along the loop, and a lane boundary the walkers and trucks keep off.
    for y in (6.2, -6.2):
        for x in np.arange(-13.0, 13.5, 3.25) + rng.uniform(-0.5, 0.5):
            builder.add("cone", meshes.traffic_cone(rng), float(x), y, 0.0, rng.uniform(-np.pi, np.pi))
    builder.footprints += [(-16.5, 6.0, 16.5, 8.2), (-16.5, -8.6, 16.5, -6.0), (-16.5, -5.6, 16.5, 5.6)]
    builder.footprints += [(18.2, -3.8, 21.8, 3.8), (-21.8, -3.8, -18.2, 3.8)]  # east/west walkers' paths
    _floor_zone(
        builder,
        (-16.0, 8.8, 16.0, 11.8),
        {
            "barrels": 7,
            "palletload": 4,
            "boxstack": 3,
            "person": 2,
            "machine": 2,
            "table": 2,
            "bin": 2,
            "cone": 1,
        },
    )
    _floor_zone(
        builder,
        (-16.0, -11.8, 16.0, -8.8),
        {
            "boxstack": 5,
            "truck": 2,
            "palletload": 4,
            "barrels": 4,
            "person": 1,
            "bin": 3,
            "table": 1,
            "cabinet": 1,
        },
    )
    for sign in (-1.0, 1.0):
        zone = (16.5, -11.8, 23.5, 11.8) if sign > 0 else (-23.5, -11.8, -16.5, 11.8)
        _floor_zone(
            builder,
            zone,
            {
                "machine": 2,
                "table": 2,
                "person": 2,
                "palletload": 2,
                "barrels": 2,
                "boxstack": 2,
                "truck": 1,
                "cone": 2,
                "cabinet": 1,
                "bin": 1,
            },
        )
    _movers(builder)
    return Factory(structure=Mesh.concatenate(builder.structure), objects=tuple(builder.objects))
