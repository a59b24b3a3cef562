"""CLI command ``regnf discover``: find, identify and register library objects with no boxes."""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from regnf.captures.up_axis import UpChoice
from regnf.core.preflight import (
    PreflightError,
    check_input_file,
    check_output_dir,
    check_output_file,
)
from regnf.fields.field import Field
from regnf.io.checkpoint import load_field
from regnf.registration.discovery import DiscoveryConfig

console = Console(stderr=True)

DISCOVER_KIND = "discover"
"""The output-folder kind of ``regnf discover`` (:mod:`regnf.core.output_dir`)."""
ENTRIES = ("discovery.json", "registration", "top_view.png")
"""What ``regnf discover`` writes in its output folder."""


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_stage_scene(stage: Path, scene: Path, allow_outside: bool) -> None:
    """An existing stage must hold the scene field being searched (its checkpoint's bytes):
    instances registered in one field are wrong in another."""
    from regnf.scene_graph import check_writable, read_stage

    check_writable(stage, allow_outside=allow_outside)
    held = read_stage(stage, allow_outside=allow_outside).scene.checkpoint
    if file_sha256(held) != file_sha256(scene):
        raise PreflightError(f"--stage {stage}: its scene field ({held.name}) is not the field of --scene {scene}; "
                             "discover into a new stage, or a stage made from this scene field")


@dataclass
class Discover:
    """Find, identify and register library objects in a scene field, with no boxes given."""

    scene: Path
    """Scene field checkpoint (.safetensors)."""
    library: tuple[Path, ...]
    """Library object checkpoints (.safetensors): the objects discovery may find (each may stand
    in several places)."""
    out: Path
    """Output folder: discovery.json (every candidate, the library objects tried in it with their
    confidences, what it became; the candidates skipped with why; the warnings; the files
    written), registration/candidate_<k>.json (each identified one, as `regnf register --out`
    writes it) and top_view.png (the room from above, the boxes found). A rerun removes only the
    files its previous run listed in discovery.json."""
    stage: Path | None = None
    """Write every identified instance into this stage, with how it was found as its
    provenance; made from --scene and --library if it does not exist."""
    up: UpChoice = "auto"
    """Up axis of the scene in metres: the candidates stand on it and the registration's upright
    prior uses it (``--discovery.candidates.up`` and ``--discovery.registration.scene-sampling.up``
    at once); auto: the up the scene field's training recorded (``regnf train --up``), else +z,
    unless those options are given."""
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    """Candidates, the short registration's shortlist and the registration itself."""
    device: str = "cpu"
    """Torch device of the fields."""
    reuse: bool = False
    """Write into an output folder that holds other files (nothing of theirs is removed)."""
    allow_outside: bool = False
    """Open asset paths of an existing stage that lie outside its folder (refused by default: a
    stage is a self-contained folder, and a path out of it may name anybody's file)."""

    def scene_up_config(self, scene: Field) -> DiscoveryConfig:
        """``--discovery`` with ``--up`` applied to the candidates and the registration (printed)."""
        from regnf.cli.field_up import scene_up, set_apart, with_scene_up

        cfg = self.discovery
        if self.up == "auto" and set_apart(cfg.candidates.up, cfg.registration.scene_sampling.up):
            console.print("up: as given by --discovery.candidates.up and --discovery.registration.scene-sampling.up",
                          soft_wrap=True)
            return cfg
        up = scene_up(scene, self.up)
        console.print(escape(up.line), soft_wrap=True)
        candidates = dataclasses.replace(cfg.candidates, up=tuple(float(v) for v in up.metres))
        return dataclasses.replace(cfg, candidates=candidates, registration=with_scene_up(cfg.registration, scene, up.metres))

    def run(self) -> None:
        from regnf.core.atomic_io import write_json
        from regnf.core.output_dir import inspect_output_dir, owned_output_dir
        from regnf.registration.discovery import FieldFiles, discover
        from regnf.registration.discovery_records import (
            discovery_json,
            instance_payloads,
            recorded_files,
            registration_file,
            remove_stale,
        )
        from regnf.registration.discovery_view import draw_top_view
        from regnf.registration.field_roles import check_roles, checkpoint_label
        from regnf.scene_graph import add_instance_from_registration, new_stage

        # Everything that can be checked is checked before the minute of work.
        if not self.library:
            raise PreflightError("--library: give at least one library object checkpoint")
        check_output_dir(self.out, "--out")
        check_input_file(self.scene, "--scene", "scene field checkpoint")
        for path in self.library:
            check_input_file(path, "--library", "library field checkpoint")
        # From the headers alone: a room taken for an object is refused before it is loaded.
        check_roles((self.scene, checkpoint_label(self.scene)), [(p, checkpoint_label(p)) for p in self.library])
        if self.stage is not None:
            if self.stage.suffix not in (".usda", ".usdc"):
                raise PreflightError(f"--stage {self.stage}: must end in .usda or .usdc")
            if self.stage.exists():
                check_stage_scene(self.stage, self.scene, self.allow_outside)
            else:
                check_output_file(self.stage, "--stage")
        inspect_output_dir(self.out, DISCOVER_KIND, self.reuse).require_free(ENTRIES)
        scene = load_field(self.scene, device=self.device)
        config = self.scene_up_config(scene)
        library, paths = {}, {}
        for path in self.library:
            f = load_field(path, device=self.device)
            if f.name in library:
                raise PreflightError(f"--library {path}: holds {f.name!r}, as {paths[f.name]} does; "
                                     "library names must be unique")
            library[f.name], paths[f.name] = f, path
        with owned_output_dir(self.out, DISCOVER_KIND, self.reuse, "the discovery folder") as claimed:
            # What the previous run made here, by its own record: only that may be removed.
            previous = recorded_files(claimed.path / "discovery.json") if claimed.owns("discovery.json") else set()
            folder = claimed.reserve(ENTRIES)
            result = discover(scene, library, config, progress=True,
                              files=FieldFiles(self.scene, dict(paths)))
            payloads = instance_payloads(result, scene, library, self.scene, paths)
            files = [registration_file(index) for index, _ in payloads]
            for rel, (_, payload) in zip(files, payloads):
                write_json(folder.path / rel, payload)
            written: dict[int, str] = {}
            if self.stage is not None and payloads:
                if not self.stage.exists():
                    new_stage(self.stage, self.scene, list(paths.values()))
                for index, payload in payloads:
                    written[index] = add_instance_from_registration(self.stage, payload,
                                                                    allow_outside=self.allow_outside)
            write_json(folder.path / "discovery.json", discovery_json(result, payloads, written, files, {
                "scene_field": str(self.scene),
                "library_fields": {name: str(p) for name, p in paths.items()},
                "stage": None if self.stage is None else str(self.stage),
            }))
            remove_stale(folder.path, previous, set(files))
            draw_top_view(result, folder.path / "top_view.png", title=f"regnf discover: {self.scene.name}")
        warned = {index: payload["warnings"] for index, payload in payloads}
        for i, d in enumerate(result.discoveries):
            size = " x ".join(f"{2 * h:.2f}" for h in d.candidate.box.half_extents)
            for t in d.tried:
                if t.error is not None:
                    console.print(f"  candidate {i}: [yellow]{t.library_name} not registered[/] ({escape(t.error)})")
            if d.skipped is not None:
                console.print(f"  candidate {i} ({size} m): [yellow]skipped[/]: {escape(d.skipped)}")
            elif d.ambiguous:
                console.print(f"  candidate {i} ({size} m): [red]unmatched[/], ambiguous: {' or '.join(d.ambiguous)} "
                              "(they differ only where no view of the scene looked)")
            elif d.chosen is None:
                registered = [t for t in d.tried if t.result is not None]
                best = max(registered, key=lambda t: t.result.confidence) if registered else None
                shown = "no object registered" if best is None else (
                    f"best: {best.library_name}, confidence {best.result.confidence:.2f}")
                console.print(f"  candidate {i} ({size} m): [red]unmatched[/] ({shown})")
            else:
                where = f" -> {written[i]}" if i in written else ""
                console.print(f"  candidate {i} ({size} m): [green]{d.chosen.library_name}[/], confidence "
                              f"{d.chosen.result.confidence:.2f}{where}")
                for warning in warned.get(i, []):
                    console.print(f"  [yellow]candidate {i} ({d.chosen.library_name})[/]: {escape(warning)}")
        skipped = f", {len(result.skipped)} skipped" if result.skipped else ""
        console.print(f"[green]discovered[/] {len(result.instances)} instances in {len(result.discoveries)} "
                      f"candidates{skipped}, {result.seconds['total']:.0f} s -> {self.out}")
