"""Rendering fields: cameras in metres (:class:`Camera`), the one sphere tracer (:func:`trace`) and its renderer (:func:`render`), the volume renderer, baked fields, and image and surface metrics.

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "Camera": "camera",
    "SphereTracerConfig": "sphere_tracer",
    "trace": "sphere_tracer",
    "render": "sphere_render",
    "render_volume": "volume_renderer",
    "VolumeRendererConfig": "volume_renderer",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .camera import Camera
    from .sphere_render import render
    from .sphere_tracer import SphereTracerConfig, trace
    from .volume_renderer import VolumeRendererConfig, render_volume
