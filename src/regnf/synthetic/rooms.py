"""The three rooms of the ONR-like data set: furniture at random yaw and position in a room.

Room frame: metres, floor at z = 0, +Z up, interior centred on the origin. Library objects are
metric, so every instance has scale 1.0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from regnf.captures.instance import Instance, box_corners, yaw_pose
from regnf.synthetic.clutter import make_table_clutter
from regnf.synthetic.library import instance_mesh, make_library_object
from regnf.synthetic.placement import place_circles
from regnf.synthetic.primitives import box

ROOM_NAMES: tuple[str, ...] = ("ac-room", "atbl-room", "mix-room")
"""Names of the rooms."""

ROOM_CONTENTS: dict[str, tuple[str, ...]] = {
    "ac-room": ("c", "dc", "fc", "fc-nop", "mc"),
    "atbl-room": ("et", "t", "wt"),
    "mix-room": ("dc", "fc", "t"),
}
"""Library objects placed in each room."""

FLOOR_COLOR = (0.58, 0.60, 0.64)
WALL_COLOR = (0.88, 0.86, 0.80)
ACCENT_WALL_COLOR = (0.62, 0.74, 0.84)


@dataclass(frozen=True)
class RoomConfig:
    """Geometry of the room shell and the placement rules."""

    size: tuple[float, float] = (6.0, 5.0)
    """Interior size along x and y, metres."""
    wall_height: float = 2.6
    """Wall height, metres."""
    wall_thickness: float = 0.1
    """Wall and floor slab thickness, metres."""
    object_gap: float = 0.3
    """Minimum distance between two objects' footprints, metres."""
    wall_margin: float = 0.4
    """Minimum distance between an object's footprint and a wall, metres."""


@dataclass
class Room:
    """A generated room: its shell (floor, walls, clutter) and its furniture instances."""

    name: str
    """Room name, one of :data:`ROOM_NAMES`."""
    seed: int
    """Seed the layout was drawn with."""
    mesh: trimesh.Trimesh
    """Floor, walls and clutter in room metres, per-face colours (no furniture)."""
    instances: list[Instance] = field(default_factory=list)
    """Placed furniture."""
    clutter: list[trimesh.Trimesh] = field(default_factory=list)
    """Clutter items resting on furniture, room metres (also part of ``mesh``)."""
    config: RoomConfig = field(default_factory=RoomConfig)
    """Room geometry used."""

    def instance_meshes(self) -> list[trimesh.Trimesh]:
        """Each instance's mesh in room metres, in ``instances`` order."""
        return [instance_mesh(inst) for inst in self.instances]

    def full_mesh(self) -> trimesh.Trimesh:
        """The whole room (shell, clutter and furniture) as one coloured mesh in metres.

        A concatenation of closed pieces, not a boolean union: furniture touches the floor.
        """
        return trimesh.util.concatenate([self.mesh, *self.instance_meshes()])


def _shell(config: RoomConfig) -> list[trimesh.Trimesh]:
    """Floor slab (top at z = 0) and four walls outside the interior rectangle."""
    hx, hy = config.size[0] / 2, config.size[1] / 2
    t, h = config.wall_thickness, config.wall_height
    parts = [
        box((2 * hx + 2 * t, 2 * hy + 2 * t, t), (0.0, 0.0, -t / 2), FLOOR_COLOR, "floor"),
        box((t, 2 * hy + 2 * t, h), (hx + t / 2, 0.0, h / 2), ACCENT_WALL_COLOR, "wall +x"),
        box((t, 2 * hy + 2 * t, h), (-hx - t / 2, 0.0, h / 2), WALL_COLOR, "wall -x"),
        box((2 * hx, t, h), (0.0, hy + t / 2, h / 2), WALL_COLOR, "wall +y"),
        box((2 * hx, t, h), (0.0, -hy - t / 2, h / 2), WALL_COLOR, "wall -y"),
    ]
    meshes = []
    for p in parts:
        p.mesh.visual.face_colors = np.r_[np.round(np.asarray(p.color) * 255), 255].astype(np.uint8)
        meshes.append(p.mesh)
    return meshes


def make_room(name: str, seed: int = 0, config: RoomConfig = RoomConfig()) -> Room:
    """Build room ``name`` with a random layout drawn from ``seed`` (deterministic).

    Objects get a yaw uniform in [0, 2 pi) and a position such that footprints are at least
    ``config.object_gap`` apart and ``config.wall_margin`` from the walls; all rest on the floor.
    """
    if name not in ROOM_CONTENTS:
        raise KeyError(f"unknown room {name!r}; expected one of {ROOM_NAMES}")
    rng = np.random.default_rng(seed)
    objects = [make_library_object(lib) for lib in ROOM_CONTENTS[name]]
    radii = np.array([np.linalg.norm(o.mesh.vertices[:, :2], axis=1).max() for o in objects])
    yaws = rng.uniform(0.0, 2 * np.pi, size=len(objects))
    centres = place_circles(
        radii,
        (config.size[0] / 2, config.size[1] / 2),
        config.object_gap,
        config.wall_margin,
        rng,
        context=f"room {name!r}",
    )
    instances = []
    counts: dict[str, int] = {}
    pieces = _shell(config)
    clutter: list[trimesh.Trimesh] = []
    for obj, yaw, c in zip(objects, yaws, centres):
        pose = yaw_pose(float(yaw), np.array([c[0], c[1], 0.0]))
        k = counts.get(obj.name, 0)
        counts[obj.name] = k + 1
        instances.append(
            Instance(
                id=f"{obj.name}_{k}",
                library=obj.name,
                label=obj.label,
                object_to_world=pose,
                scale=1.0,
                yaw=float(yaw),
                box_corners=box_corners(obj.mesh.bounds, pose),
            )
        )
        if name == "mix-room" and obj.name == "t":
            hi = obj.mesh.bounds[1]
            for item in make_table_clutter((hi[0], hi[1]), hi[2], rng):
                item.apply_transform(pose)
                clutter.append(item)
    return Room(name, seed, trimesh.util.concatenate(pieces + clutter), instances, clutter, config)
