"""CLI command ``regnf generate``: many random instance replacements of a stage, as a data set."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rich.console import Console
from tyro.conf import Positional

console = Console(stderr=True)


@dataclass
class Generate:
    """Generate a synthetic data set: random instance replacements of a stage, rendered (resumable)."""

    stage: Positional[Path]
    """The stage with registered instances (.usda, .usdc or .usdz)."""
    out: Path
    """Output folder: manifest.jsonl, generation.json, stage/ (base + one layer per variant),
    variants/NNNNNN/ (views, depth, instance masks, transforms.json). It must be new, empty or
    an earlier generate's (see --reuse); rerunning resumes. One run at a time: a second run into
    the same folder stops at once (exit status 5)."""
    reuse: bool = False
    """Write into an --out folder that holds other files (they are kept: nothing is removed, and
    only the data set's own names are written)."""
    variants: int = 10
    """Number of variants (one seed each), at most 1,000,000 (a larger data set: several folders,
    --first-seed)."""
    views: int = 8
    """Views per variant, on an orbit inside the scene's bounds."""
    first_seed: int = 0
    """Seed of the first variant."""
    executor: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: a Ray cluster (pip install 'regnf[distributed]')."""
    address: str | None = None
    """Ray cluster to join ('auto', 'ray://head:10001'); default: a local Ray instance."""
    workers: int = 0
    """Variants at once (local pool size, or CPUs of a local Ray instance); 0: CPU count / threads."""
    threads_per_task: int = 1
    """Torch threads per variant (pinned: the same on every machine, so outputs agree)."""
    width: int = 256
    """Image width (width * height at most 4096 * 4096)."""
    height: int = 192
    """Image height."""
    fov: float = 60.0
    """Horizontal field of view, degrees."""
    orbit_radius: float | None = None
    """Horizontal orbit radius in metres (default: 0.4 of the bounds' smaller horizontal side)."""
    orbit_elevation: float = 30.0
    """Cameras look down at the target at this angle, degrees."""
    jitter_cameras: bool = True
    """Turn each variant's orbit by a random azimuth from its seed."""
    removal: Literal["box", "shell"] = "box"
    """What is cut out of the scene per instance: its oriented box or a shell around its surface."""
    box_pad: float = 0.05
    """Relative growth of the removal box."""
    retry_failed: bool = True
    """Make variants that failed in an earlier run again."""
    device: str = "cpu"
    """Torch device of the workers."""

    def config(self):  # -> GenerateConfig (imported lazily: `regnf --help` stays fast)
        """The :class:`regnf.generate.GenerateConfig` these options describe."""
        from regnf.compositor.cameras_io import OrbitConfig
        from regnf.compositor.stage_config import StageCompositeConfig
        from regnf.core.executors import ExecutorConfig
        from regnf.generate import GenerateConfig

        try:
            return GenerateConfig(
                variants=self.variants,
                first_seed=self.first_seed,
                cameras=OrbitConfig(n=self.views, width=self.width, height=self.height, fov_deg=self.fov,
                                    radius=self.orbit_radius, elevation_deg=self.orbit_elevation),
                jitter_cameras=self.jitter_cameras,
                composite=StageCompositeConfig(mode="substitute", removal=self.removal, box_pad=self.box_pad),
                executor=ExecutorConfig(kind=self.executor, workers=self.workers,
                                        threads_per_task=self.threads_per_task, address=self.address),
                retry_failed=self.retry_failed,
                device=self.device,
                reuse=self.reuse,
            )
        except ValueError as exc:
            raise SystemExit(f"regnf generate: {exc}") from exc

    def run(self) -> None:
        from regnf.generate import generate, tile_sheet, variants_per_minute

        cfg = self.config()
        try:
            report = generate(self.stage, self.out, cfg)
        except ValueError as exc:  # StageError, a refused folder, settings mismatches: each names the file
            raise SystemExit(f"regnf generate: {exc}") from exc
        except ImportError as exc:  # the ray executor without Ray
            raise SystemExit(f"regnf generate: {exc}") from exc
        except KeyboardInterrupt:
            console.print(f"[yellow]interrupted[/]: finished variants are kept in {self.out}; "
                          "run the same command again to resume")
            raise SystemExit(130) from None
        for problem in report.problems:
            console.print(f"[yellow]redone[/]: {problem}")
        for seed, error in sorted(report.failed.items()):
            console.print(f"[red]variant {seed} failed[/]: {error}")
        rate = variants_per_minute(report)
        console.print(f"[green]generated[/] {len(report.made)} variants, kept {len(report.skipped)} finished, "
                      f"{len(report.failed)} failed, in {report.seconds:.1f} s"
                      + (f" ({rate:.2f} variants per minute)" if report.made else "")
                      + f" -> {report.manifest}")
        try:
            console.print(f"contact sheet: {tile_sheet(self.out)}")
        except ValueError:
            pass
        if report.failed:
            raise SystemExit(4)
