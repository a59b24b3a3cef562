"""Signed-distance fields: the :class:`Field` interface, NeuS-style neural fields trained from
posed RGB-D captures (:func:`train_rgbd`) or distilled from meshes (:func:`distill_mesh`),
analytic fields for exact tests, checkpoints (:func:`save_field`, :func:`load_field`),
meshing (:func:`extract_mesh`), oriented boxes (:class:`OrientedBox`) and the one sphere tracer
(:func:`trace`) with its renderer (:func:`render` of a :class:`Camera` in metres).

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "Field": "field",
    "FieldInfo": "field",
    "Symmetry": "field",
    "NeuralSDF": "neural_sdf",
    "NeuralSDFConfig": "neural_sdf",
    "RGBDTrainConfig": "training",
    "train_rgbd": "training",
    "DistillConfig": "distill",
    "distill_mesh": "distill",
    "load_field": "checkpoint",
    "save_field": "checkpoint",
    "CheckpointError": "checkpoint",
    "extract_mesh": "meshing",
    "OrientedBox": "oriented_box",
    "Camera": "camera",
    "SphereTracerConfig": "sphere_tracer",
    "trace": "sphere_tracer",
    "render": "sphere_render",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .camera import Camera
    from .checkpoint import CheckpointError, load_field, save_field
    from .distill import DistillConfig, distill_mesh
    from .field import Field, FieldInfo, Symmetry
    from .meshing import extract_mesh
    from .neural_sdf import NeuralSDF, NeuralSDFConfig
    from .oriented_box import OrientedBox
    from .sphere_render import render
    from .sphere_tracer import SphereTracerConfig, trace
    from .training import RGBDTrainConfig, train_rgbd
