"""CLI command ``regnf register``: register a library field to an object in a scene field."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console

from neural_fields.checkpoint import load_field
from synthetic.atomic_io import write_json

if TYPE_CHECKING:
    from neural_fields.field import Field
    from registration.result import RegistrationResult

console = Console(stderr=True)


def load_box_metres(path: Path) -> np.ndarray:
    """(8, 3) box corners in scene metres from a JSON file.

    Accepted: ``{"corners": [[x, y, z] x 8]}`` or ``{"center": [..], "size": [..], "yaw": rad}``.
    """
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SystemExit(f"{path}: cannot read the box ({exc})") from exc
    if "corners" in data:
        corners = np.asarray(data["corners"], dtype=np.float64)
        if corners.shape != (8, 3) or not np.isfinite(corners).all():
            raise SystemExit(f"{path}: 'corners' must be 8 finite [x, y, z] points")
        return corners
    try:
        c = np.asarray(data["center"], dtype=np.float64)
        h = 0.5 * np.asarray(data["size"], dtype=np.float64)
        yaw = float(data.get("yaw", 0.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise SystemExit(f"{path}: expected 'corners' or 'center' + 'size' (+ 'yaw'), got {sorted(data)}") from exc
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    return c + (signs * h) @ R.T


def registration_payload(result: RegistrationResult, scene: Field, library: Field, scene_path: Path,
                         library_path: Path) -> dict:
    """What ``regnf register --out`` writes (and a stage records): the result, the fields, and the
    object -> scene transform in metres."""
    S = scene.to_world.detach().cpu().double().numpy()
    L = library.to_world.detach().cpu().double().numpy()
    object_to_scene = S @ result.transform.inverse().matrix() @ np.linalg.inv(L)
    return {
        **result.to_json(),
        "scene_field": str(scene_path),
        "library_field": str(library_path),
        "library_name": library.name,
        "library_label": library.label,
        "object_to_scene_metres": object_to_scene.tolist(),
    }


@dataclass
class Register:
    """Find the 7-DoF similarity of a library object inside a scene field (Reg-NF)."""

    scene: Path
    """Scene field checkpoint (.safetensors)."""
    library: Path
    """Library object field checkpoint (.safetensors)."""
    box: Path | None = None
    """JSON proposal box in scene metres: {"corners": 8x3} or {"center", "size", "yaw"}."""
    capture: Path | None = None
    """Instead of --box: a capture whose `instances` give the box (with --instance)."""
    instance: str | None = None
    """Instance id (or library name) in --capture to take the box from."""
    out: Path = Path("registration.json")
    """Where to write the result (JSON)."""
    stage: Path | None = None
    """Also write the result as an instance into this USD stage (made by `regnf stage new`)."""
    force: bool = False
    """Write into --stage even when the registration was not accepted (flagged as such)."""
    top_k: int | None = None
    """Hypotheses refined (default: the config's; 1 is the paper's method)."""
    device: str = "cpu"
    """Torch device."""

    def run(self) -> None:
        from registration.ground_truth import find_instance
        from registration.proposal import ProposalBox
        from registration.register import RegistrationConfig, register

        scene = load_field(self.scene, device=self.device)
        library = load_field(self.library, device=self.device)
        if self.box is not None:
            corners = load_box_metres(self.box)
        elif self.capture is not None and self.instance is not None:
            from synthetic.sdfstudio_format import load_capture

            instances = load_capture(self.capture).instances
            match = [i for i in instances if i.id == self.instance]
            inst = match[0] if match else find_instance(instances, self.instance)
            corners = np.asarray(inst.box_corners, dtype=np.float64)
        else:
            raise SystemExit("give a proposal box: --box BOX.json, or --capture DIR --instance ID")
        S = scene.to_world.detach().cpu().double().numpy()
        proposal = ProposalBox.from_corners(corners).transformed(np.linalg.inv(S))
        cfg = RegistrationConfig()
        if self.top_k is not None:
            import dataclasses

            cfg = dataclasses.replace(cfg, init=dataclasses.replace(cfg.init, top_k=self.top_k))
        result = register(scene, library, proposal, cfg)
        payload = registration_payload(result, scene, library, self.scene, self.library)
        write_json(self.out, payload)
        t = result.transform
        summary = (f"s = {t.s:.4f}, |t| = {np.linalg.norm(t.t):.4f}, confidence {result.confidence:.3f}, "
                   f"{result.timings.get('total', float('nan')):.1f} s -> {self.out}")
        written = None
        if self.stage is not None and (result.accepted or self.force):
            from scene_graph import add_instance_from_registration

            written = add_instance_from_registration(self.stage, payload, force=self.force)
        if result.accepted:
            console.print(f"[green]registered[/] {library.name!r}: {summary}")
            if written:
                console.print(f"instance {written!r} written to {self.stage}")
        else:
            if written:
                console.print(f"[yellow]forced[/]: instance {written!r} written to {self.stage} (flagged)")
            elif self.stage is not None:
                console.print(f"nothing written to {self.stage} (use --force to write it anyway)")
            console.print(
                f"[red]registration FAILED[/] for {library.name!r}: confidence {result.confidence:.3f} is "
                f"below the acceptance threshold {result.thresholds['acceptance_threshold']}; "
                f"the object in the box is probably not this library object. ({summary})"
            )
            raise SystemExit(3)
