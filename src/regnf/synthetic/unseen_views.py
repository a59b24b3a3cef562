"""Views of a synthetic room's object from the side its capture never saw, and the truth there.

Object completion is judged from these: the low-coverage rooms' captures look at their objects
from the -y side only, so cameras on the +y side see what only a substituted library field can
show. :func:`reference_renderer` draws the room's ground-truth meshes from any camera.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from regnf.core.cameras import look_at
from regnf.fields.field import Field
from regnf.render.camera import Camera
from regnf.render.evaluation import world_to_field
from regnf.synthetic.render import RGBDRenderer
from regnf.synthetic.rooms import Room
from regnf.synthetic.shading import shaded_copy

WIDTH, HEIGHT = 256, 192
"""Image size of the unseen views."""
FOCAL_OVER_WIDTH = 0.9
"""Focal length of the unseen views, in image widths."""
DISTANCE = 1.6
"""Distance of the cameras from the object's centre, metres (horizontal)."""
EYE_HEIGHT = 1.3
"""Height of the cameras, metres."""


def reference_renderer(room: Room, width: int = WIDTH, height: int = HEIGHT) -> RGBDRenderer:
    """pyrender of the room's ground-truth meshes, instance ids in the order of ``room.instances``."""
    meshes = room.instance_meshes()
    return RGBDRenderer([shaded_copy(room.mesh), *[shaded_copy(m) for m in meshes]], width, height,
                        instance_ids=[-1, *range(len(meshes))])


def unseen_cameras(room: Room, centre: np.ndarray, views: int, distance: float = DISTANCE,
                   height: float = EYE_HEIGHT, free: Field | None = None) -> list[Camera]:
    """``views`` cameras on the object's +y side (azimuth 30-150 degrees), looking at its centre.

    Parameters
    ----------
    room : Room
        The room; cameras stay 0.3 m inside its walls.
    centre : (3,) float
        The object's centre, metres.
    views : int
        How many cameras, evenly spread over the azimuths.
    distance, height : float
        The cameras' horizontal distance from ``centre`` and their height, metres.
    free : Field, optional
        A camera whose centre this field puts inside matter (a low-coverage field fills space it
        never saw with floaters) moves closer to the object, then to nearby azimuths, until its
        centre is at least 5 cm outside; views that find no such spot are dropped.
    """
    half = np.asarray(room.config.size[:2], dtype=np.float64) / 2
    f = FOCAL_OVER_WIDTH * WIDTH
    K = np.array([[f, 0.0, WIDTH / 2], [0.0, f, HEIGHT / 2], [0.0, 0.0, 1.0]])
    cams = []
    for az0 in np.radians(np.linspace(30.0, 150.0, views)):
        for daz, scale in ((0, 1.0), (0, 0.8), (0, 1.2), (5, 1.0), (-5, 1.0), (10, 0.8), (-10, 0.8)):
            az = az0 + math.radians(daz)
            eye = centre + scale * distance * np.array([math.cos(az), math.sin(az), 0.0])
            eye[:2] = np.clip(eye[:2], -half + 0.3, half - 0.3)
            eye[2] = height
            if free is None or _free_at(free, eye) > 0.05:
                cams.append(Camera(K, WIDTH, HEIGHT, look_at(eye, centre)))
                break
    return cams


def _free_at(field: Field, point: np.ndarray) -> float:
    """SDF of ``field`` (metres) at a point in metres."""
    with torch.no_grad():
        d = field.sdf(world_to_field(field, np.asarray(point, np.float64)[None]))
    return float(d[0]) * field.world_scale
