"""CLI command ``regnf register``: register a library field to an object in a scene field."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.markup import escape
from scipy.spatial.transform import Rotation

from regnf.captures.up_axis import UpChoice
from regnf.core.atomic_io import write_json
from regnf.core.errors import RegnfError
from regnf.core.preflight import check_output_file, read_json_input
from regnf.io.checkpoint import load_field
from regnf.registration.pipeline import RegistrationConfig
from regnf.registration.result import registration_payload

console = Console(stderr=True)


def load_box_metres(path: Path) -> np.ndarray:
    """(8, 3) box corners in scene metres from a JSON file, checked to form a real box.

    Accepted: ``{"corners": [[x, y, z] x 8]}`` or ``{"center": [..], "size": [..], "yaw": rad}``.
    A box of zero or negative size, a mirrored one or corners that form no box are refused
    with a message naming the file (``SystemExit``, before anything is loaded); a file that is
    not a regular file, too large or not JSON, by :func:`regnf.core.preflight.read_json_input`.
    """
    from regnf.fields.oriented_box import OrientedBox

    data = read_json_input(path, "--box", "box")
    if not isinstance(data, dict):
        raise SystemExit(f"{path}: a box is a JSON object with 'corners' or 'center' + 'size' (+ 'yaw')")
    try:
        if "corners" in data:
            corners = np.asarray(data["corners"], dtype=np.float64)
            if corners.shape != (8, 3) or not np.isfinite(corners).all():
                raise RegnfError("'corners' must be 8 finite [x, y, z] points")
        else:
            c = np.asarray(data["center"], dtype=np.float64)
            size = np.asarray(data["size"], dtype=np.float64)
            yaw = float(data.get("yaw", 0.0))
            if c.shape != (3,) or size.shape != (3,) or not (np.isfinite(c).all() and np.isfinite(size).all()
                                                              and np.isfinite(yaw)):
                raise RegnfError("'center' and 'size' must be 3 finite numbers each, 'yaw' a finite angle")
            if not (size > 0).all():
                raise RegnfError(f"'size' must be positive on every axis, got {size.tolist()}")
            signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
            R = Rotation.from_euler("z", yaw).as_matrix()
            corners = c + (signs * 0.5 * size) @ R.T
        OrientedBox.from_corners(corners)  # refuses degenerate, mirrored or non-box corners
    except KeyError as exc:
        raise SystemExit(f"{path}: expected 'corners' or 'center' + 'size' (+ 'yaw'), got {sorted(data)}") from exc
    except (TypeError, ValueError) as exc:
        raise SystemExit(f"{path}: not a usable box: {exc}") from exc
    return corners


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
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (refused by default: a stage is
    a self-contained folder, and a path out of it may name anybody's file)."""
    up: UpChoice = "auto"
    """Up axis of the scene in metres, for the upright prior (``--registration.scene-sampling.up``
    in the field frame); auto: the up the scene field's training recorded (``regnf train --up``),
    else +z, unless that option is given."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """Every setting of the registration, with its unit (docs/design.md section 3): for example
    ``--registration.init.top-k 1`` (the paper's single hypothesis), ``--registration.no-upright``
    (objects in any orientation: features alone), ``--registration.refine.optimizer adam`` (the
    paper's Adam instead of Levenberg-Marquardt)."""
    device: str = "cpu"
    """Torch device the fields are loaded on."""

    def proposal_corners(self) -> np.ndarray:
        """(8, 3) corners of the proposal box in scene metres, from --box or --capture/--instance."""
        from regnf.captures.formats import read_capture
        from regnf.synthetic.ground_truth import find_instance

        if self.box is not None:
            return load_box_metres(self.box)
        if self.capture is None or self.instance is None:
            raise SystemExit("give a proposal box: --box BOX.json, or --capture DIR --instance ID")
        capture, _ = read_capture(self.capture)
        match = [i for i in capture.instances if i.id == self.instance]
        try:
            inst = match[0] if match else find_instance(capture.instances, self.instance)
        except ValueError as exc:
            raise SystemExit(f"{capture.root}: {exc}") from exc
        if inst.box_corners is None:
            raise SystemExit(f"{capture.root}: instance {self.instance!r} has no box_corners")
        return np.asarray(inst.box_corners, dtype=np.float64)

    def run(self) -> None:
        from regnf.cli.field_up import scene_up, set_apart, with_scene_up
        from regnf.fields.oriented_box import OrientedBox
        from regnf.registration.field_roles import check_roles
        from regnf.registration.pipeline import register

        # Everything that can be checked is checked before the registration's seconds of work.
        check_output_file(self.out, "--out")
        if self.stage is not None:
            from regnf.scene_graph import check_writable

            check_writable(self.stage, allow_outside=self.allow_outside)
        corners = self.proposal_corners()
        scene = load_field(self.scene, device=self.device)
        library = load_field(self.library, device=self.device)
        check_roles((self.scene, scene.label), [(self.library, library.label)])
        S = scene.to_world.detach().cpu().double().numpy()
        proposal = OrientedBox.from_corners(corners).transformed(np.linalg.inv(S))
        config = self.registration
        if self.up == "auto" and set_apart(config.scene_sampling.up):
            console.print("up: as given by --registration.scene-sampling.up (field frame)")
        else:
            up = scene_up(scene, self.up)
            console.print(escape(up.line), soft_wrap=True)
            config = with_scene_up(config, scene, up.metres)
        result = register(scene, library, proposal, config)
        payload = registration_payload(result, scene, library, self.scene, self.library)
        write_json(self.out, payload)
        t = result.transform
        inside = result.losses.get("containment", float("nan"))
        summary = (f"s = {t.s:.4f}, |t| = {np.linalg.norm(t.t):.4f}, confidence {result.confidence:.3f} "
                   f"(SDF agreement {result.losses.get('inlier_fraction', float('nan')):.3f} x "
                   f"{inside:.3f} of the object inside the box), "
                   f"{result.timings.get('total', float('nan')):.1f} s -> {self.out}")
        written = None
        if self.stage is not None and (result.accepted or self.force):
            from regnf.scene_graph import add_instance_from_registration

            written = add_instance_from_registration(self.stage, payload, force=self.force,
                                                    allow_outside=self.allow_outside)
        for warning in payload["warnings"]:  # a scale that suggests other units
            console.print(f"[yellow]{written or library.name}[/]: {escape(warning)}")
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
