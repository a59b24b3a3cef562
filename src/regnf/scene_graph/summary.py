"""A readable summary of a stage: the scene, the library by class, every instance."""

from __future__ import annotations

import numpy as np

from .model import ComposedScene
from .xform import ops_from_matrix


def discovery_line(record: dict) -> str:
    """``found by discovery (tried c 0.81, dc 0.42, ...)`` from an instance's discovery record."""
    tried = record.get("tried") or []
    shown = ", ".join(
        f"{t.get('library')} {t['confidence']:.2f}" for t in tried
        if isinstance(t, dict) and isinstance(t.get("confidence"), (int, float))
    )
    return "found by discovery" + (f" (tried {shown})" if shown else "")


def _yaw_deg(M: np.ndarray) -> float:
    """Heading of the object's +X axis in the scene's XY plane, degrees."""
    x = M[:3, 0]
    return float(np.degrees(np.arctan2(x[1], x[0])))


def summarize(scene: ComposedScene) -> str:
    """Several lines of text: scene field, classes and their objects, instances with
    translation (m), heading (deg), scale, confidence and method."""
    s = scene.scene
    lines = [
        (f"scene field: {s.name or '(unnamed)'} [{s.label}] {s.checkpoint.name}, "
         f"proxy {len(s.proxy.points)} vertices"),
        "library:",
    ]
    for label, names in scene.classes().items():
        lines.append(f"  {label}: {', '.join(names)}")
    lines.append(f"instances: {len(scene.instances)}")
    for iid, inst in scene.instances.items():
        ops = ops_from_matrix(inst.object_to_scene)
        label = scene.library[inst.library_name].label
        reg = inst.registration
        how = "placed by hand" if reg is None else (
            f"{reg.method}, confidence {reg.confidence:.3f}"
            + ("" if reg.accepted else " (NOT accepted, forced)")
            + ("" if reg.library_name == inst.library_name else f", registered as {reg.library_name}")
            + ("" if reg.discovery is None else ", " + discovery_line(reg.discovery))
            + "".join(f"; warning: {w}" for w in reg.warnings)
        )
        t = ", ".join(f"{v:.3f}" for v in ops.translate)
        lines.append(
            f"  {iid}: {inst.library_name} [{label}] at ({t}) m, heading {_yaw_deg(inst.object_to_scene):.1f} deg, "
            f"scale {ops.scale:.4f}; {how}"
        )
    return "\n".join(lines)
