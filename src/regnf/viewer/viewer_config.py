"""Settings of ``regnf view`` and what its panel offers (:mod:`regnf.viewer.stage_viewer`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from regnf.compositor.render_folder import MAX_PIXELS
from regnf.core.errors import RegnfError
from regnf.render.sphere_tracer import SphereTracerConfig
from regnf.viewer.messages import MAX_ASPECT
from regnf.viewer.trust import check_host

VIEWS = ("proxies", "scene field", "substitution", "replacement")
"""What the viewport shows: the stage's proxy meshes, or a field render of one composite."""
CHANNELS = ("rgb", "depth", "instance id")
"""Which image of a field render is shown."""

_MODE_OF_VIEW = {"scene field": "scene", "substitution": "substitute", "replacement": "substitute"}
SCENE_SAMPLES_RGB = (40, 110, 255)
"""Colour of a selected registration's scene samples (the benchmark's pictures use blue too)."""
LIBRARY_SAMPLES_RGB = (255, 140, 0)
"""Colour of its library samples (orange)."""
OPENING_GRACE_S = 3.0
"""Seconds after a browser connects during which its camera reports count only once they show
the opening view (see ``StageViewer._on_connect``)."""


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of :func:`serve`."""

    port: int = 8080
    """TCP port of the viewer's web page (0: any free one); a port in use is refused."""
    host: str = "127.0.0.1"
    """Interface to listen on; the default serves this machine only (others need allow_remote_edits)."""
    allow_remote_edits: bool = False
    """Accept a non-loopback ``host``: whoever has the printed URL can then edit the stage."""
    device: str = "cpu"
    """Where the fields are loaded and rendered (``cpu`` or ``cuda``)."""
    coarse_pixels: int = 64 * 48
    """Pixels of the image rendered as soon as the camera moves (docs/decisions/rendering-speed.md)."""
    refined_pixels: int = 320 * 240
    """Pixels of the image rendered once the camera rests (docs/decisions/rendering-speed.md)."""
    rest_seconds: float = 0.4
    """The camera counts as resting when it has not moved for this long."""
    opening_rest_seconds: float = 3.0
    """Seconds a new page's first view waits before it is refined (docs/decisions/rendering-speed.md)."""
    opening_fov: float = 63.0
    """Vertical field of view of the camera a browser opens with, degrees (docs/decisions/viewer.md)."""
    opening_aspect: float = 2.4
    """Width over height of the opening view's image rendered in advance (docs/decisions/viewer.md)."""
    sphere: SphereTracerConfig = field(default_factory=lambda: SphereTracerConfig(footprint_fraction=0.05))
    """The sphere tracer's settings (as ``regnf render``'s: stop at 5 % of a pixel's footprint)."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (as in ``regnf stage show``)."""
    stage_poll_seconds: float = 1.0
    """Seconds between two checks of the stage's files for changes made by another program."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise RegnfError(f"port must be in [0, 65535], got {self.port}")
        check_host(self.host, self.allow_remote_edits)
        if self.coarse_pixels < 1 or self.refined_pixels < self.coarse_pixels:
            raise RegnfError("need 1 <= coarse_pixels <= refined_pixels, got "
                             f"{self.coarse_pixels} and {self.refined_pixels}")
        if self.refined_pixels > MAX_PIXELS:
            raise RegnfError(f"refined_pixels must be at most {MAX_PIXELS:,}, got {self.refined_pixels:,}")
        if not (math.isfinite(self.stage_poll_seconds) and self.stage_poll_seconds > 0):
            raise RegnfError(f"stage_poll_seconds must be finite and > 0, got {self.stage_poll_seconds}")
        for name in ("rest_seconds", "opening_rest_seconds"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise RegnfError(f"{name} must be finite and >= 0, got {getattr(self, name)}")
        if not 3.0 < self.opening_fov < 170.0:
            raise RegnfError(f"opening_fov must be in (3, 170) degrees, got {self.opening_fov}")
        if not (math.isfinite(self.opening_aspect) and 1.0 <= self.opening_aspect <= MAX_ASPECT):
            raise RegnfError(f"opening_aspect must be in [1, {MAX_ASPECT:g}], got {self.opening_aspect}")
