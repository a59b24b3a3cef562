"""Settings of ``regnf generate`` (:class:`GenerateConfig`), checked when they are made."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from tyro.conf import Suppress

from regnf.compositor.cameras_io import OrbitConfig
from regnf.compositor.render_folder import RenderConfig, check_image_size
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.errors import RegnfError
from regnf.core.executors import ExecutorConfig

from .placement_jitter import check_ranges as check_jitter_ranges
from .variant_labels import parse_formats
from .variation import check_ranges

MAX_VARIANTS = 1_000_000
"""Most variants one run may ask for. Every run reads and checks the whole manifest (about
1 KB a row, and every listed file hashed) and keeps its rows in memory, and ``variants/``
holds one folder per variant: at a million that is a GB-sized manifest and a folder of a
million entries. Split a larger data set over several output folders (``first_seed``)."""
MAX_VIEWS = 10_000
"""Most views per variant: a variant's views travel from its worker to the driver in one
message, held in memory on both sides."""

@dataclass(frozen=True)
class SubstitutionConfig(StageCompositeConfig):
    """The composite settings of a command that always substitutes every instance (``regnf
    generate``, ``regnf replace``): ``mode`` is not an option there."""

    mode: Suppress[Literal["scene", "substitute"]] = "substitute"
    """Always ``substitute`` on the command line."""


@dataclass(frozen=True)
class GenerateConfig:
    """What :func:`generate` makes and how it runs."""

    format: str = "nerfstudio"
    """Data set formats to write, comma separated: ``nerfstudio``, ``coco``, ``bop``."""
    variants: int = 10
    """Number of variants (seeds first_seed, first_seed + 1, ...), 1 to :data:`MAX_VARIANTS`."""
    first_seed: int = 0
    """Seed of the first variant."""
    cameras: OrbitConfig = field(default_factory=lambda: OrbitConfig(n=8, width=256, height=192))
    """Orbit cameras: n views a variant (<= :data:`MAX_VIEWS`), width x height pixels (<= :data:`regnf.compositor.render_folder.MAX_PIXELS`)."""
    camera_source: Literal["orbit", "capture"] = "orbit"
    """Where the views' cameras come from: ``orbit`` (``cameras``) or ``capture`` (frames of ``capture``)."""
    capture: Path | None = None
    """Capture folder (any capture format) whose frames are the cameras when ``camera_source`` is capture."""
    exposure_stops: float = 0.0
    """Largest exposure change of a variant's camera, stops (0 to 4; 0: none)."""
    white_balance: float = 0.0
    """Largest white-balance gain change of a variant's camera per channel, a fraction (0 to below 1)."""
    jitter_yaw_deg: float = 0.0
    """Largest turn of each instance about the up axis through its base, degrees (0 to 180; 0: no turn)."""
    jitter_shift: float = 0.0
    """Largest move of each instance along its support plane, metres (0 to 0.5; 0: no move)."""
    jitter_cameras: bool = True
    """Turn each variant's orbit by a seeded random azimuth (capture cameras: seeded random frames)."""
    composite: SubstitutionConfig = field(default_factory=SubstitutionConfig)
    """Removal settings of the substituted instances (the mode is always substitute)."""
    render: RenderConfig = field(default_factory=lambda: RenderConfig(progress=False, views_per_trace=16))
    """Renderer settings: up to 16 views a trace (docs/decisions/rendering-speed.md); one progress bar a run."""
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    """Where the variants run."""
    retry_failed: bool = True
    """Make variants that failed in an earlier run again (finished ones are always kept)."""
    device: str = "cpu"
    """Torch device of the workers."""
    reuse: bool = False
    """Write into an output folder that holds other files (kept as they are); without it, it is refused."""
    allow_size_change: bool = False
    """Allow swaps that change an instance's size by more than :data:`~regnf.compositor.size_change.SIZE_CHANGE_LIMIT` times."""

    def __post_init__(self) -> None:
        # Checked here, before any work: a huge request fails at once, not minutes in.
        parse_formats(self.format)
        if isinstance(self.variants, bool) or not 1 <= self.variants <= MAX_VARIANTS:
            raise RegnfError(f"variants must be between 1 and {MAX_VARIANTS:,}, got {self.variants} "
                             "(split a larger data set over several output folders with first_seed)")
        if self.first_seed < 0:
            raise RegnfError(f"first_seed must be >= 0, got {self.first_seed}")
        if self.cameras.n > MAX_VIEWS:
            raise RegnfError(f"views per variant must be at most {MAX_VIEWS:,}, got {self.cameras.n}")
        check_image_size(self.cameras.width, self.cameras.height, "cameras: a view")
        if self.camera_source not in ("orbit", "capture"):
            raise RegnfError(f"camera_source must be orbit or capture, got {self.camera_source!r}")
        if self.camera_source == "capture" and self.capture is None:
            raise RegnfError("camera_source capture needs the capture folder (--camera-source capture --capture DIR)")
        if self.camera_source == "orbit" and self.capture is not None:
            raise RegnfError(f"capture {self.capture} is read with camera_source capture only; give "
                             "--camera-source capture too, or leave --capture out for orbit cameras")
        check_ranges(self.exposure_stops, self.white_balance)
        check_jitter_ranges(self.jitter_yaw_deg, self.jitter_shift)
        if (self.exposure_stops or self.white_balance) and self.render.sequence != "none":
            raise RegnfError("a varied exposure or white balance and render.sequence cannot go together "
                             "(the sequence would show the views before the variation)")

    @property
    def formats(self) -> tuple[str, ...]:
        """The data set formats of :attr:`format`."""
        return parse_formats(self.format)

    @property
    def seeds(self) -> range:
        """The seeds of the variants (a range: nothing is built per seed)."""
        return range(self.first_seed, self.first_seed + self.variants)

    def output_settings(self) -> dict[str, Any]:
        """Every setting that changes what a variant's files hold (not how or where it runs)."""
        render = dataclasses.replace(self.render, progress=False, overwrite=False)
        if render.renderer == "baked":  # the tracer's settings as the baked renderer uses them
            from regnf.compositor.baked_composite import baked_tracing

            render = dataclasses.replace(render, sphere=baked_tracing(render.sphere))
        return {
            "formats": list(self.formats),
            "appearance": {"exposure_stops": self.exposure_stops, "white_balance": self.white_balance},
            "cameras": dataclasses.asdict(self.cameras),
            "jitter_cameras": self.jitter_cameras,
            # Only with a placement jitter: data sets without one keep the settings (and the
            # resumption) of those made before it.
            **({"placement": {"jitter_yaw_deg": self.jitter_yaw_deg, "jitter_shift": self.jitter_shift}}
               if self.jitter_yaw_deg or self.jitter_shift else {}),
            # Only for capture cameras (the capture itself is keyed by prepare_output): orbit data
            # sets keep the settings (and the resumption) of those made before them.
            **({"camera_source": self.camera_source} if self.camera_source != "orbit" else {}),
            "composite": dataclasses.asdict(dataclasses.replace(self.composite, mode="substitute")),
            # The grids' settings change the files of the baked renderer only; left out of the
            # others, they keep the settings (and the resumption) of data sets made before them.
            "render": {k: v for k, v in dataclasses.asdict(render).items()
                       if k != "bake" or render.renderer == "baked"},
            "threads_per_task": self.executor.threads_per_task,
            "device": self.device,
        }
