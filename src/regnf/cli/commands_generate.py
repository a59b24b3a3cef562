"""CLI command ``regnf generate``: many random instance replacements of a stage, as a data set."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from tyro.conf import Positional

from regnf.datasets.generation import GenerateConfig

console = Console(stderr=True)


@dataclass(frozen=True, kw_only=True)
class Generate(GenerateConfig):
    """Generate a synthetic data set: random instance replacements of a stage, rendered (resumable)."""

    stage: Positional[Path]
    """The stage with registered instances (.usda, .usdc or .usdz)."""
    out: Path
    """Output folder: manifest.jsonl, generation.json, stage/ (base + one layer per variant),
    variants/NNNNNN/ (views, depth, instance masks, transforms.json). It must be new, empty or
    an earlier generate's (see --reuse); rerunning resumes. One run at a time: a second run into
    the same folder stops at once (exit status 5)."""

    def __post_init__(self) -> None:
        # The values are checked when the settings are taken (:meth:`config`, first thing in
        # :meth:`run`): a value out of range is then one line and status 1, not a usage error.
        pass

    def config(self) -> GenerateConfig:
        """The settings alone (every option but the stage and the output folder)."""
        return GenerateConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(GenerateConfig)})

    def run(self) -> None:
        from regnf.core.preflight import check_output_dir
        from regnf.datasets.generation import generate, tile_sheet, variants_per_minute

        cfg = self.config()
        check_output_dir(self.out, "--out")
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
        for note in report.notes:
            console.print(f"note: {note}")
        for problem in report.problems:
            console.print(f"[yellow]redone[/]: {problem}")
        for seed, error in sorted(report.failed.items()):
            console.print(f"[red]variant {seed} failed[/]: {error}")
        rate = variants_per_minute(report)
        console.print(f"[green]generated[/] {len(report.made)} variants, kept {len(report.skipped)} finished, "
                      f"{len(report.failed)} failed, in {report.seconds:.1f} s"
                      + (f" ({rate:.2f} variants per minute)" if report.made else "")
                      + (f", of which {report.bake_seconds:.1f} s baking the grids" if report.bake_seconds else "")
                      + f" -> {report.manifest}")
        try:
            console.print(f"contact sheet: {tile_sheet(self.out)}")
        except ValueError:
            pass
        if report.failed:
            raise SystemExit(4)
