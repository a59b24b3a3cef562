"""CLI commands ``regnf stage new | add-instance | show | export``: the USD scene graph."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from rich.console import Console
from tyro.conf import Positional

from regnf.compositor.tool_export import ToolExportConfig
from regnf.core.preflight import check_mesh_resolution, check_output_file, read_json_input

console = Console(stderr=True)


def _fail(exc: Exception) -> SystemExit:
    return SystemExit(f"regnf stage: {exc}")


@dataclass
class StageNew:
    """Create a USD stage from a scene field and library fields (no instances yet)."""

    stage: Positional[Path]
    """Stage to write (.usda or .usdc); assets go beside it (library/, slots/, fields/)."""
    scene: Path
    """Scene field checkpoint (.safetensors)."""
    library: tuple[Path, ...] = ()
    """Library object checkpoints (.safetensors); names and classes come from their headers."""
    proxy_resolution: int = 48
    """Marching-cubes cells along the longest axis for the proxy meshes."""
    overwrite: bool = False
    """Replace an existing stage."""
    device: str = "cpu"
    """Torch device used to mesh the proxies."""

    def run(self) -> None:
        from regnf.scene_graph import ProxyConfig, StageError, new_stage

        if self.stage.suffix not in (".usda", ".usdc"):
            raise SystemExit(f"regnf stage new: {self.stage} must end in .usda or .usdc")
        check_output_file(self.stage, "the stage")
        if self.proxy_resolution < 4:
            raise SystemExit(f"--proxy-resolution must be at least 4, got {self.proxy_resolution}")
        check_mesh_resolution(self.proxy_resolution, "--proxy-resolution")
        try:
            scene = new_stage(self.stage, self.scene, self.library,
                              ProxyConfig(resolution=self.proxy_resolution, device=self.device),
                              overwrite=self.overwrite)
        except StageError as exc:
            raise _fail(exc) from exc
        console.print(f"[green]stage[/] {self.stage}: scene + {len(scene.library)} library objects "
                      f"in {len(scene.classes())} classes")


@dataclass
class StageAddInstance:
    """Add a registered instance to a stage from a `regnf register` result (JSON)."""

    stage: Positional[Path]
    """The stage (.usda or .usdc)."""
    result: Path
    """Registration result JSON written by `regnf register --out`."""
    id: str | None = None
    """Instance id (prim name); default <library name>_<k>."""
    force: bool = False
    """Write a registration that was not accepted (confidence below the threshold)."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (refused by default: a stage is
    a self-contained folder, and a path out of it may name anybody's file)."""

    def run(self) -> None:
        from regnf.scene_graph import StageError, add_instance_from_registration

        data = read_json_input(self.result, "--result", "registration result")
        if not isinstance(data, dict):
            raise SystemExit(f"{self.result}: a registration result is a JSON object (from `regnf register --out`)")
        try:
            iid = add_instance_from_registration(self.stage, data, force=self.force, instance_id=self.id,
                                                 allow_outside=self.allow_outside)
        except StageError as exc:
            raise SystemExit(f"regnf stage add-instance ({self.result}): {exc}") from exc
        console.print(f"[green]added[/] instance {iid!r} ({data.get('library_name')}) to {self.stage}")


@dataclass
class StageShow:
    """Summarise a stage: scene, library classes, instances with transforms and confidence."""

    stage: Positional[Path]
    """The stage (.usda, .usdc, a replacement layer or a .usdz package)."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (refused by default: a stage is
    a self-contained folder, and a path out of it may name anybody's file)."""

    def run(self) -> None:
        from regnf.scene_graph import StageError, read_stage, summarize

        try:
            scene = read_stage(self.stage, allow_outside=self.allow_outside)
        except StageError as exc:
            raise _fail(exc) from exc
        print(summarize(scene))


@dataclass(frozen=True, kw_only=True)
class StageExport(ToolExportConfig):
    """Export a stage as .usda, .usdc or a self-contained .usdz (checkpoints and proxies inside)."""

    stage: Positional[Path]
    """The stage to export."""
    usdz: Path | None = None
    """Write a self-contained .usdz package here."""
    usdc: Path | None = None
    """Write the stage with a binary (.usdc) root layer here, assets beside it."""
    usda: Path | None = None
    """Write the stage with a text (.usda) root layer here, assets beside it."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder and copy them in (refused by default: a stage is
    a self-contained folder, and a path out of it may name anybody's file)."""

    def __post_init__(self) -> None:
        # The settings are checked in :meth:`run` (one line and status 1, not a usage error).
        pass

    def run(self) -> None:
        from regnf.compositor.tool_export import export_for_tools
        from regnf.scene_graph import StageError

        targets = [p for p in (self.usdz, self.usdc, self.usda) if p is not None]
        if not targets:
            raise SystemExit("regnf stage export: give --usdz, --usdc and/or --usda")
        try:
            config = ToolExportConfig(**{f.name: getattr(self, f.name) for f in fields(ToolExportConfig)})
        except ValueError as exc:
            raise SystemExit(f"regnf stage export: {exc}") from exc
        for out, suffix in ((self.usdz, ".usdz"), (self.usdc, ".usdc"), (self.usda, ".usda")):
            if out is not None:
                check_output_file(out, suffix.replace(".", "--"), suffix=suffix)
        try:
            for out in export_for_tools(self.stage, targets, config, self.allow_outside, say=console.print):
                console.print(f"[green]exported[/] {self.stage} -> {out}")
        except (StageError, ValueError) as exc:
            raise _fail(exc) from exc
