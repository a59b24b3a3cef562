"""CLI commands ``regnf render`` and ``regnf replace``: composites of a stage, rendered to a folder."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

from rich.console import Console
from tyro.conf import Positional, arg

from regnf.compositor.render_folder import MAX_PIXELS, RenderConfig
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.preflight import check_image_size, check_output_dir
from regnf.datasets.generate_config import SubstitutionConfig

if TYPE_CHECKING:
    from regnf.compositor import Camera, CompositeField

console = Console(stderr=True)


@dataclass
class _Views:
    """Options shared by both commands: the stage, the cameras, the renderer and the composite."""

    stage: Positional[Path]
    """The stage (.usda, .usdc, a replacement layer or a .usdz package)."""
    out: Path
    """Output folder: rgb_0000.png, ... (one per view), depth_*.png (16-bit mm), instance_*.png, contact_sheet.png,
    sequence.gif|mp4 (with --render.sequence), render.json (replace adds replacement.usda over the stage,
    exported there, and transforms.json)."""
    capture: Path | None = None
    """Render the cameras of this capture folder (meta_data.json), posed in metres."""
    orbit: int | None = None
    """Instead of --capture: this many cameras on a circle inside the scene's bounds."""
    usd_camera: Annotated[tuple[str, ...], arg(metavar="PRIM [PRIM ...]")] = ()
    """Instead of --capture or --orbit: these UsdGeom.Camera prims of the stage (or of --camera-stage)."""
    camera_stage: Path | None = None
    """Read the --usd-camera prims from this stage (Z up, any metersPerUnit) instead of the rendered one."""
    orbit_radius: float | None = None
    """Horizontal orbit radius in metres (default: 0.4 of the bounds' smaller horizontal side)."""
    orbit_elevation: float = 30.0
    """Orbit cameras look down at the target at this angle, degrees."""
    fov: float = 60.0
    """Horizontal field of view of orbit cameras, degrees."""
    width: int | None = None
    """Image width (orbit and USD cameras default 320; capture default: its own, K scaled when changed)."""
    height: int | None = None
    """Image height (orbit default 240; capture default: its own, or in proportion to --width; USD
    cameras: from the aperture's aspect ratio)."""
    frames: tuple[int, ...] = ()
    """Capture frames to render (indices; default all)."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """How the views are rendered and written (docs/design.md section 3.6): for example
    ``--render.renderer volume``, ``--render.renderer baked`` (the fields baked into grids once
    for these views, then traced: faster a view once the bake is paid, so for many views,
    docs/decisions/rendering-speed.md; its "evaluations" are grid look-ups), ``--render.volume.n-samples 64``, ``--render.sphere.grid-lipschitz 1.5``
    (fields that overestimate), ``--render.sequence gif``, ``--render.overwrite``."""
    composite: StageCompositeConfig = field(default_factory=StageCompositeConfig)
    """What is cut out and placed per instance: ``--composite.removal shell``, ``--composite.box-pad``,
    ``--composite.tint``, ... and ``--composite.mode`` (``scene``: the scene field alone;
    ``substitute``, the default: every instance replaced by its library field)."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (refused by default: a stage is
    a self-contained folder, and a path out of it may name anybody's file)."""
    device: str = "cpu"
    """Torch device."""

    def check_options(self) -> None:
        """Refuse, before loading anything, no or several camera sources and an MP4 without its package."""
        from regnf.compositor.sequence_io import SequenceBackendError, require_mp4

        sources = [self.capture is not None, self.orbit is not None, bool(self.usd_camera)]
        if sum(sources) != 1:
            raise SystemExit("give the cameras: --capture DIR, --orbit N or --usd-camera PRIM [PRIM ...] "
                             "(one of them)")
        if self.camera_stage is not None and not self.usd_camera:
            raise SystemExit("--camera-stage names the stage of the --usd-camera prims: give them too")
        if self.render.sequence == "mp4":
            try:
                require_mp4()
            except SequenceBackendError as exc:
                raise SystemExit(f"regnf: --render.sequence mp4: {exc}") from exc
        if self.orbit is not None and self.orbit < 1:
            raise SystemExit(f"--orbit must be at least 1 camera, got {self.orbit}")
        for option, value in (("--width", self.width), ("--height", self.height)):
            if value is not None and value < 1:
                raise SystemExit(f"{option} must be at least 1, got {value}")
        if self.capture is None:  # orbit and USD cameras: the size is known now
            check_image_size(self.width or 320, self.height or self.width or 240, MAX_PIXELS)
        elif self.width is not None and self.height is not None:
            check_image_size(self.width, self.height, MAX_PIXELS)
        check_output_dir(self.out)

    def cameras(self, field: CompositeField) -> list[Camera]:
        from regnf.compositor.cameras_io import (
            OrbitConfig,
            cameras_from_capture,
            field_bounds_metres,
            orbit_around_bounds,
        )
        from regnf.compositor.usd_cameras import cameras_from_usd

        self.check_options()
        try:
            if self.capture is not None:
                cams = cameras_from_capture(self.capture, self.width, self.height, self.frames or None)
            elif self.usd_camera:
                # The rendered stage is Z up in metres (read_stage checks it); another one must be Z up.
                cams = cameras_from_usd(self.camera_stage or self.stage, self.usd_camera, self.width or 320,
                                        self.height, up_axis="Z")
            else:
                cfg = OrbitConfig(n=self.orbit, width=self.width or 320, height=self.height or 240,
                                  fov_deg=self.fov, radius=self.orbit_radius, elevation_deg=self.orbit_elevation)
                cams = orbit_around_bounds(field_bounds_metres(field.scene), cfg)
        except ValueError as exc:  # CaptureError and StageError are ValueErrors naming the file
            raise SystemExit(f"regnf: cameras: {exc}") from exc
        for cam in cams:  # a capture's own size, or a USD camera's aspect ratio, is known only now
            check_image_size(cam.width, cam.height, MAX_PIXELS, "image size")
        return cams

    def composite_config(self, mode: str) -> StageCompositeConfig:
        """The composite settings with ``mode`` (``replace`` needs both modes)."""
        return dataclasses.replace(self.composite, mode=mode)


@dataclass
class RenderStage(_Views):
    """Render a stage's scene field alone, or with every instance substituted by its library field."""

    def run(self) -> None:
        from regnf.compositor.from_stage import composite_from_stage
        from regnf.compositor.render_folder import render_views
        from regnf.scene_graph import StageError

        self.check_options()
        t0 = time.perf_counter()
        try:
            comp = composite_from_stage(self.stage, self.composite, self.device,
                                        allow_outside=self.allow_outside)
            cams = self.cameras(comp.field)
            meta = {"stage": str(self.stage.absolute()), "mode": self.composite.mode,
                    "instance_ids": comp.instance_ids, "load_seconds": time.perf_counter() - t0}
            report = render_views(comp.field, cams, self.out, self.render, meta)
        except (StageError, ValueError) as exc:
            raise SystemExit(f"regnf render: {exc}") from exc
        console.print(f"[green]rendered[/] {len(report.views)} views of {self.stage} ({self.composite.mode}) -> {self.out} "
                      f"in {sum(report.seconds):.1f} s, {report.evals_per_pixel_mean:.1f} evaluations per pixel")


@dataclass
class ReplaceInstances(_Views):
    """Swap every instance for a random library object of its class, render it, write transforms.json."""

    composite: SubstitutionConfig = field(default_factory=SubstitutionConfig)
    """What is cut out and placed per instance: ``--composite.removal shell``, ``--composite.box-pad``,
    ``--composite.tint``, ... (every instance is substituted)."""
    seed: int = 0
    """Seed of the random choices (the same seed gives the same outputs)."""
    allow_size_change: bool = False
    """Swap in an object whose size differs from the instance's by more than 3x (bounding-box
    diagonals at the instance's scale; refused by default: one library is likely in other units)."""

    def run(self) -> None:
        from regnf.compositor.from_stage import composite_from_stage
        from regnf.compositor.replace import ReplaceConfig, replace_and_render
        from regnf.scene_graph import StageError

        self.check_options()
        try:
            # The cameras need the scene's bounds: the scene field alone is enough for that.
            scene_only = composite_from_stage(self.stage, self.composite_config("scene"), self.device,
                                              allow_outside=self.allow_outside)
            cams = self.cameras(scene_only.field)
            cfg = ReplaceConfig(self.composite_config("substitute"), self.render, self.device,
                                allow_size_change=self.allow_size_change)
            result = replace_and_render(self.stage, self.seed, self.out, cams, cfg, allow_outside=self.allow_outside)
        except (StageError, ValueError) as exc:
            raise SystemExit(f"regnf replace: {exc}") from exc
        for iid, name in result.selections.items():
            console.print(f"  {iid} -> {name}")
        console.print(f"[green]replaced[/] {len(result.selections)} instances (seed {self.seed}): {result.layer}, "
                      f"{len(result.render.views)} views, {result.transforms}")
