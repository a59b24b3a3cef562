"""Export a stage for other tools: the edit meshed in, physics on, library meshes fine enough.

What ``regnf stage export`` and ``regnf demo`` write: the stage as it is
(:func:`regnf.scene_graph.export_stage`), plus

- ``/World/Scene/Edited``: the scene field less every instance's removal region, meshed
  (:func:`regnf.compositor.scene_mesh.edited_scene_mesh`), so that Blender, Isaac Sim and
  usdview show the substituted objects and none of the originals;
- ``UsdPhysics`` rigid bodies of a density, convex-hull colliders on the library meshes, the
  edited scene a static collider;
- library meshes re-meshed from their fields at a cell of a few millimetres (thin parts such
  as slats are lost at the stage's 48 cells); a library object's source mesh, when it has
  one, stays what viewers render.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from regnf.compositor.scene_mesh import SceneMeshConfig
from regnf.core.errors import RegnfError
from regnf.scene_graph import ComposedScene, ProxyMesh


@dataclass(frozen=True)
class ToolExportConfig:
    """What an export for other tools adds to the stage."""

    density: float = 500.0
    """Density of the library objects for the physics, kg / m^3."""
    physics: bool = True
    """Write the physics above (off: the stage's own setting is kept)."""
    edit: bool = True
    """Mesh the scene less its instances' removal regions into the export (when the stage has instances)."""
    scene_mesh: SceneMeshConfig = field(default_factory=SceneMeshConfig)
    """How the edited scene is meshed."""
    library_cell: float = 0.005
    """Marching-cubes cell of the library objects' exported meshes, metres; 0 keeps the stage's proxies."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.library_cell) and self.library_cell >= 0):
            raise RegnfError(f"--library-cell must be >= 0 metres, got {self.library_cell}")
        if self.physics and not (math.isfinite(self.density) and self.density > 0):
            raise RegnfError(f"--density must be > 0 kg/m^3, got {self.density}")


def library_meshes(stage: Path, scene: ComposedScene, cell: float,
                   say: Callable[[str], None] = lambda _: None) -> dict[str, ProxyMesh]:
    """Every library object of ``scene`` meshed from its field at ``cell`` metres (object metres)."""
    from regnf.meshes.meshing import extract_mesh
    from regnf.scene_graph.fields import load_record_field, proxy_from_trimesh

    out = {}
    for name, rec in sorted(scene.library.items()):  # a loop over library objects
        field_ = load_record_field(stage, f"library object {name!r}", rec, "cpu")
        extent = float((rec.bounds[1] - rec.bounds[0]).max()) * field_.world_scale
        cells = max(2, math.ceil(extent / cell))
        out[name] = proxy_from_trimesh(extract_mesh(field_, resolution=cells, in_world=True))
        say(f"library object {name}: {len(out[name].faces):,} triangles at {cells} cells")
    return out


def edited_scene(stage: Path, config: SceneMeshConfig, say: Callable[[str], None] = lambda _: None) -> ProxyMesh:
    """The scene less its instances' removal regions, meshed (see the module)."""
    from regnf.compositor.scene_mesh import edited_scene_mesh
    from regnf.scene_graph.fields import proxy_from_trimesh

    say(f"meshing the scene less its instances' removal regions at {config.cell * 100:g} cm cells")
    result = edited_scene_mesh(stage, config)
    say(f"edited scene: {len(result.mesh.faces):,} triangles, {result.removals} removal regions cut out; "
        f"distance to the field's surface p99 {result.distance_p99 * 1000:.1f} mm, "
        f"max {result.distance_max * 1000:.1f} mm")
    return proxy_from_trimesh(result.mesh)


def export_for_tools(stage: str | os.PathLike, targets: Sequence[str | os.PathLike],
                     config: ToolExportConfig = ToolExportConfig(), allow_outside: bool = False,
                     say: Callable[[str], None] = lambda _: None) -> list[Path]:
    """Export ``stage`` to each of ``targets`` (.usda, .usdc, .usdz) with what ``config`` adds.

    Raises
    ------
    regnf.scene_graph.StageError
        The stage cannot be read or written (the message names the file).
    ValueError
        Settings out of range, or a room too large for the scene mesh's cell.
    """
    from regnf.scene_graph import export_stage, read_stage

    stage = Path(stage)
    scene = read_stage(stage, allow_outside=allow_outside)
    edited = edited_scene(stage, config.scene_mesh, say) if config.edit and scene.instances else None
    meshes = library_meshes(stage, scene, config.library_cell, say) if config.library_cell > 0 else None
    written = []
    for out in targets:  # a loop over output files
        written.append(export_stage(stage, out, allow_outside=allow_outside, edited_scene=edited,
                                    density=config.density if config.physics else None, library_meshes=meshes))
    return written
