"""CLI commands ``regnf stage new | add-instance | show | export``: the USD scene graph."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from regnf.compositor.scene_mesh import SceneMeshConfig
from regnf.core.preflight import check_mesh_resolution, check_output_file, read_json_input

console = Console(stderr=True)


def _fail(exc: Exception) -> SystemExit:
    return SystemExit(f"regnf stage: {exc}")


@dataclass
class StageNew:
    """Create a USD stage from a scene field and library fields (no instances yet)."""

    out: Path
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

        if self.out.suffix not in (".usda", ".usdc"):
            raise SystemExit(f"regnf stage new: {self.out} must end in .usda or .usdc")
        check_output_file(self.out, "--out")
        if self.proxy_resolution < 4:
            raise SystemExit(f"--proxy-resolution must be at least 4, got {self.proxy_resolution}")
        check_mesh_resolution(self.proxy_resolution, "--proxy-resolution")
        try:
            scene = new_stage(self.out, self.scene, self.library,
                              ProxyConfig(resolution=self.proxy_resolution, device=self.device),
                              overwrite=self.overwrite)
        except StageError as exc:
            raise _fail(exc) from exc
        console.print(f"[green]stage[/] {self.out}: scene + {len(scene.library)} library objects "
                      f"in {len(scene.classes())} classes")


@dataclass
class StageAddInstance:
    """Add a registered instance to a stage from a `regnf register` result (JSON)."""

    stage: Path
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

    stage: Path
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


@dataclass
class StageExport:
    """Export a stage as .usda, .usdc or a self-contained .usdz (checkpoints and proxies inside)."""

    stage: Path
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
    density: float = 500.0
    """Density of the library objects, kg / m^3: every instance becomes a rigid body and every
    library mesh a convex-hull collider of this density (UsdPhysics), the edited scene a static
    collider."""
    physics: bool = True
    """Write the physics above (off: the stage's own setting is kept)."""
    edit: bool = True
    """Mesh the scene less its instances' removal regions into the export (the mesh other tools
    show; the whole scene stays as the proxy), when the stage has instances."""
    scene_mesh: SceneMeshConfig = field(default_factory=SceneMeshConfig)
    """How the edited scene is meshed."""
    library_cell: float = 0.005
    """Marching-cubes cell of the library objects' meshes in the export, metres (thin parts
    such as chair slats need a few mm); 0 keeps the stage's proxies."""

    def run(self) -> None:
        from regnf.scene_graph import StageError, export_stage, read_stage

        targets = [p for p in (self.usdz, self.usdc, self.usda) if p is not None]
        if not targets:
            raise SystemExit("regnf stage export: give --usdz, --usdc and/or --usda")
        if not (math.isfinite(self.library_cell) and self.library_cell >= 0):
            raise SystemExit(f"regnf stage export: --library-cell must be >= 0 metres, got {self.library_cell}")
        if self.physics and not (math.isfinite(self.density) and self.density > 0):
            raise SystemExit(f"regnf stage export: --density must be > 0 kg/m^3, got {self.density}")
        for out, suffix in ((self.usdz, ".usdz"), (self.usdc, ".usdc"), (self.usda, ".usda")):
            if out is not None:
                check_output_file(out, suffix.replace(".", "--"), suffix=suffix)
        try:
            edited = None
            scene = read_stage(self.stage, allow_outside=self.allow_outside)
            if self.edit and scene.instances:
                edited = self._edited_scene()
            meshes = self._library_meshes(scene) if self.library_cell > 0 else None
            for out in targets:
                export_stage(self.stage, out, allow_outside=self.allow_outside, edited_scene=edited,
                             density=self.density if self.physics else None, library_meshes=meshes)
                console.print(f"[green]exported[/] {self.stage} -> {out}")
        except (StageError, ValueError) as exc:
            raise _fail(exc) from exc

    def _library_meshes(self, scene):
        """Every library object meshed at ``library_cell`` (canonical object metres)."""
        import math as m

        from regnf.neural_fields.meshing import extract_mesh
        from regnf.scene_graph.fields import load_record_field, proxy_from_trimesh

        out = {}
        for name, rec in sorted(scene.library.items()):  # a loop over library objects
            field = load_record_field(self.stage, f"library object {name!r}", rec, "cpu")
            extent = float((rec.bounds[1] - rec.bounds[0]).max()) * field.world_scale
            cells = max(2, m.ceil(extent / self.library_cell))
            out[name] = proxy_from_trimesh(extract_mesh(field, resolution=cells, in_world=True))
            console.print(f"library object {name}: {len(out[name].faces):,} triangles at {cells} cells")
        return out

    def _edited_scene(self):
        from regnf.compositor.scene_mesh import edited_scene_mesh
        from regnf.scene_graph.fields import proxy_from_trimesh

        console.print(f"meshing the scene less its instances' removal regions at {self.scene_mesh.cell * 100:g} cm cells")
        result = edited_scene_mesh(self.stage, self.scene_mesh)
        console.print(f"edited scene: {len(result.mesh.faces):,} triangles, {result.removals} removal regions cut out; "
                      f"distance to the field's surface p99 {result.distance_p99 * 1000:.1f} mm, "
                      f"max {result.distance_max * 1000:.1f} mm")
        return proxy_from_trimesh(result.mesh)
