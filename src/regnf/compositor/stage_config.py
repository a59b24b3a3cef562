"""How a stage becomes a composite: which mode, which removal, how much margin."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from regnf.core.errors import RegnfError

MODES = ("scene", "substitute")
"""``scene``: the scene field alone; ``substitute``: every instance swapped for its library field."""
REMOVALS = ("box", "shell")
"""Shapes of the region cut out of the scene for each substituted instance."""


@dataclass(frozen=True)
class StageCompositeConfig:
    """Settings of :func:`regnf.compositor.from_stage.composite_from_stage`: lengths in scene
    METRES, except ``cull_pad`` (scene FIELD units) and the relative ``box_pad``."""

    mode: Literal["scene", "substitute"] = "substitute"
    """``scene``: the scene field alone; ``substitute``: each instance cut out, its library field placed."""
    removal: Literal["box", "shell"] = "box"
    """Removal region per instance: ``box`` (its oriented box) or ``shell`` (round its registered surface)."""
    box_pad: float = 0.05
    """Relative growth of the removal box (0.05: half extents times 1.05)."""
    shell_dilation: float = 0.05
    """Dilation of the shell removal around the original library surface, metres."""
    floor_margin: float = 0.01
    """Height above the object's base (its canonical z = 0) below which nothing is removed, metres."""
    use_proposal: bool = True
    """With ``box`` removal, also remove the registration's proposal box (when recorded)."""
    tint: bool = False
    """Multiply each placed object's colour by a per-instance tint (tells them apart)."""
    cull_pad: float = 0.02
    """Culling margin of placed fields in scene FIELD units (see CompositeConfig)."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise RegnfError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.removal not in REMOVALS:
            raise RegnfError(f"removal must be one of {REMOVALS}, got {self.removal!r}")
        for name in ("box_pad", "shell_dilation", "floor_margin"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise RegnfError(f"{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.cull_pad) and self.cull_pad > 0):
            raise RegnfError(f"cull_pad must be finite and > 0, got {self.cull_pad}")


DEFAULT_STAGE_COMPOSITE = StageCompositeConfig()
"""The default settings: substitute every instance, box removal grown by 5 %."""
