"""Procedural ONR-like data: library objects, rooms, trajectories, RGB-D captures.

Main entry points: :func:`make_library_object`, :func:`make_room`, :func:`capture_object` and
:func:`capture_room` (captures are read and written by :mod:`regnf.captures`).

Exports are resolved lazily, so that importing a light module (``regnf.synthetic.library``) does not
import pyrender / OpenGL; the renderer is loaded only when something needs it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS: dict[str, str] = {
    "ObjectCaptureConfig": "capture",
    "RoomCaptureConfig": "capture",
    "capture_object": "capture",
    "capture_room": "capture",
    "LIBRARY_NAMES": "library",
    "LibraryObject": "library",
    "library_object_names": "library",
    "make_library_object": "library",
    "PoseNoiseConfig": "pose_noise",
    "perturb_poses": "pose_noise",
    "RGBDRenderer": "render",
    "ROOM_NAMES": "rooms",
    "Room": "rooms",
    "make_room": "rooms",
    "NOISE_LEVELS": "sensor_noise",
    "SensorNoiseConfig": "sensor_noise",
    "apply_sensor_noise": "sensor_noise",
    "ShadingConfig": "shading",
    "shade_face_colors": "shading",
    "shaded_copy": "shading",
}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


if TYPE_CHECKING:  # static analysers see the real names
    from regnf.synthetic.capture import (
        ObjectCaptureConfig,
        RoomCaptureConfig,
        capture_object,
        capture_room,
    )
    from regnf.synthetic.library import (
        LIBRARY_NAMES,
        LibraryObject,
        library_object_names,
        make_library_object,
    )
    from regnf.synthetic.pose_noise import PoseNoiseConfig, perturb_poses
    from regnf.synthetic.render import RGBDRenderer
    from regnf.synthetic.rooms import ROOM_NAMES, Room, make_room
    from regnf.synthetic.sensor_noise import NOISE_LEVELS, SensorNoiseConfig, apply_sensor_noise
    from regnf.synthetic.shading import ShadingConfig, shade_face_colors, shaded_copy
