"""Composite neural fields and render them: scene minus removals plus placed library objects.

See METHOD.md section 9. Everything here works on any :class:`regnf.neural_fields.field.Field`;
:func:`composite_from_stage` builds the composite of a USD stage (section 8), and
:func:`render_views` / :func:`replace_and_render` render it to folders of images (and,
optionally, a GIF or MP4 sequence). Cameras come from a capture, an orbit, or the
``UsdGeom.Camera`` prims of a stage (:func:`cameras_from_usd`, :func:`camera_to_usd`).
"""

from .camera import Camera, CameraRays, camera_rays, look_at, orbit_cameras
from .cameras_io import OrbitConfig, cameras_from_capture, field_bounds_metres, orbit_around_bounds
from .composite_field import (
    BACKGROUND_ID,
    SCENE_ID,
    CompositeConfig,
    CompositeField,
    CompositeSample,
    sample_field,
)
from .contact_sheets import contact_sheet
from .distance_grid import DistanceGrid
from .from_stage import StageComposite, composite_from_stage
from .image_io import (
    read_depth_png,
    read_instance_png,
    read_rgb_png,
    rgb_to_uint8,
    write_depth_png,
    write_instance_png,
    write_rgb_png,
)
from .nerfstudio import opencv_to_opengl, transforms_json
from .oriented_box import OrientedBox
from .placement import PlacedObject
from .regions import OrientedBoxRegion, RemovalRegion, ShellRegion
from .render_folder import RenderConfig, RenderReport, ViewFiles, render_views
from .render_result import Render
from .replace import ReplaceConfig, ReplacementResult, pick_replacements, replace_and_render
from .sequence_io import SequenceBackendError, write_gif, write_mp4
from .sphere_tracer import SphereTracerConfig, TraceHits, render, trace
from .stage_config import StageCompositeConfig
from .substitution import SubstitutedInstance, build_composite, library_to_scene
from .usd_cameras import camera_to_usd, cameras_from_usd, write_cameras_usd
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
    "OrbitConfig",
    "OrientedBox",
    "OrientedBoxRegion",
    "PlacedObject",
    "RemovalRegion",
    "Render",
    "RenderConfig",
    "RenderReport",
    "ReplaceConfig",
    "ReplacementResult",
    "SequenceBackendError",
    "ShellRegion",
    "SphereTracerConfig",
    "StageComposite",
    "StageCompositeConfig",
    "SubstitutedInstance",
    "TraceHits",
    "ViewFiles",
    "VolumeHits",
    "VolumeRendererConfig",
    "build_composite",
    "camera_rays",
    "camera_to_usd",
    "cameras_from_capture",
    "cameras_from_usd",
    "composite_from_stage",
    "contact_sheet",
    "field_bounds_metres",
    "integrate",
    "library_to_scene",
    "look_at",
    "opencv_to_opengl",
    "orbit_around_bounds",
    "orbit_cameras",
    "pick_replacements",
    "read_depth_png",
    "read_instance_png",
    "read_rgb_png",
    "render",
    "render_views",
    "render_volume",
    "replace_and_render",
    "rgb_to_uint8",
    "sample_field",
    "trace",
    "transforms_json",
    "write_cameras_usd",
    "write_depth_png",
    "write_gif",
    "write_instance_png",
    "write_mp4",
    "write_rgb_png",
]
