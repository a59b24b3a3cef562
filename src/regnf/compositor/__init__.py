"""Composite neural fields and render them: scene minus removals plus placed library objects.

See docs/design.md section 1.9. Everything here works on any
:class:`regnf.fields.field.Field`; :func:`composite_from_stage` builds the composite of a USD
stage (section 1.8), and :func:`render_views` / :func:`replace_and_render` render it to folders of
images (and, optionally, a GIF or MP4 sequence). Cameras come from a capture, an orbit, or the
``UsdGeom.Camera`` prims of a stage (:func:`cameras_from_usd`, :func:`camera_to_usd`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "Camera": "regnf.render.camera",
    "look_at": "regnf.core.cameras",
    "orbit_cameras": "regnf.render.camera",
    "CompositeField": "composite_field",
    "CompositeConfig": "composite_field",
    "build_composite": "substitution",
    "composite_from_stage": "from_stage",
    "StageCompositeConfig": "stage_config",
    "render": "regnf.render.sphere_render",
    "SphereTracerConfig": "regnf.render.sphere_tracer",
    "render_volume": "regnf.render.volume_renderer",
    "VolumeRendererConfig": "regnf.render.volume_renderer",
    "render_views": "render_folder",
    "RenderConfig": "render_folder",
    "replace_and_render": "replace",
    "ReplaceConfig": "replace",
    "Render": "regnf.core.render_result",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from regnf.core.cameras import look_at
    from regnf.core.render_result import Render
    from regnf.render.camera import Camera, orbit_cameras
    from regnf.render.sphere_render import render
    from regnf.render.sphere_tracer import SphereTracerConfig
    from regnf.render.volume_renderer import VolumeRendererConfig, render_volume

    from .composite_field import CompositeConfig, CompositeField
    from .from_stage import composite_from_stage
    from .render_folder import RenderConfig, render_views
    from .replace import ReplaceConfig, replace_and_render
    from .stage_config import StageCompositeConfig
    from .substitution import build_composite
