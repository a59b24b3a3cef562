"""Composite neural fields and render them: scene minus removals plus placed library objects.

See METHOD.md section 9. Everything here works on any :class:`neural_fields.field.Field`.
"""

from .camera import Camera, CameraRays, camera_rays, look_at, orbit_cameras
from .composite_field import (
    BACKGROUND_ID,
    SCENE_ID,
    CompositeConfig,
    CompositeField,
    CompositeSample,
    sample_field,
)
from .distance_grid import DistanceGrid
from .image_io import (
    read_depth_png,
    read_instance_png,
    read_rgb_png,
    write_depth_png,
    write_instance_png,
    write_rgb_png,
)
from .oriented_box import OrientedBox
from .placement import PlacedObject
from .regions import OrientedBoxRegion, RemovalRegion, ShellRegion
from .render_result import Render
from .sphere_tracer import SphereTracerConfig, TraceHits, render, trace
from .volume_renderer import VolumeHits, VolumeRendererConfig, integrate, render_volume

__all__ = [
    "BACKGROUND_ID",
    "SCENE_ID",
    "Camera",
    "CameraRays",
    "CompositeConfig",
    "CompositeField",
    "CompositeSample",
    "DistanceGrid",
    "OrientedBox",
    "OrientedBoxRegion",
    "PlacedObject",
    "RemovalRegion",
    "Render",
    "ShellRegion",
    "SphereTracerConfig",
    "TraceHits",
    "VolumeHits",
    "VolumeRendererConfig",
    "camera_rays",
    "integrate",
    "look_at",
    "orbit_cameras",
    "read_depth_png",
    "read_instance_png",
    "read_rgb_png",
    "render",
    "render_volume",
    "sample_field",
    "trace",
    "write_depth_png",
    "write_instance_png",
    "write_rgb_png",
]
