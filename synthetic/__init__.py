"""Procedural ONR-like data: library objects, rooms, trajectories, RGB-D captures.

Main entry points: :func:`make_library_object`, :func:`make_room`, :func:`capture_object`,
:func:`capture_room` and :func:`load_capture` (which also reads real sdfstudio / ONR folders).

Exports are resolved lazily, so that importing a light module (``regnf.synthetic.library``) does not
import pyrender / OpenGL; the renderer is loaded only when something needs it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    "ObjectCaptureConfig": "regnf.synthetic.capture",
    "RoomCaptureConfig": "regnf.synthetic.capture",
    "capture_object": "regnf.synthetic.capture",
    "capture_room": "regnf.synthetic.capture",
    "Instance": "regnf.synthetic.instance",
    "LIBRARY_NAMES": "regnf.synthetic.library",
    "LibraryObject": "regnf.synthetic.library",
    "library_object_names": "regnf.synthetic.library",
    "make_library_object": "regnf.synthetic.library",
    "RGBDRenderer": "regnf.synthetic.render",
    "RenderOutput": "regnf.synthetic.render",
    "ROOM_NAMES": "regnf.synthetic.rooms",
    "Room": "regnf.synthetic.rooms",
    "make_room": "regnf.synthetic.rooms",
    "Capture": "regnf.synthetic.sdfstudio_format",
    "CaptureError": "regnf.synthetic.sdfstudio_format",
    "CaptureFrame": "regnf.synthetic.sdfstudio_format",
    "load_capture": "regnf.synthetic.sdfstudio_format",
    "write_capture": "regnf.synthetic.sdfstudio_format",
    "ShadingConfig": "regnf.synthetic.shading",
    "shade_face_colors": "regnf.synthetic.shading",
    "shaded_copy": "regnf.synthetic.shading",
    "look_at": "regnf.synthetic.trajectories",
}

__all__ = [
    "LIBRARY_NAMES",
    "ROOM_NAMES",
    "Capture",
    "CaptureError",
    "CaptureFrame",
    "Instance",
    "LibraryObject",
    "ObjectCaptureConfig",
    "RGBDRenderer",
    "RenderOutput",
    "Room",
    "RoomCaptureConfig",
    "ShadingConfig",
    "capture_object",
    "capture_room",
    "library_object_names",
    "load_capture",
    "look_at",
    "make_library_object",
    "make_room",
    "shade_face_colors",
    "shaded_copy",
    "write_capture",
]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'synthetic' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # static analysers see the real names
    from regnf.synthetic.capture import (
        ObjectCaptureConfig,
        RoomCaptureConfig,
        capture_object,
        capture_room,
    )
    from regnf.synthetic.instance import Instance
    from regnf.synthetic.library import (
        LIBRARY_NAMES,
        LibraryObject,
        library_object_names,
        make_library_object,
    )
    from regnf.synthetic.render import RenderOutput, RGBDRenderer
    from regnf.synthetic.rooms import ROOM_NAMES, Room, make_room
    from regnf.synthetic.sdfstudio_format import (
        Capture,
        CaptureError,
        CaptureFrame,
        load_capture,
        write_capture,
    )
    from regnf.synthetic.shading import ShadingConfig, shade_face_colors, shaded_copy
    from regnf.synthetic.trajectories import look_at
