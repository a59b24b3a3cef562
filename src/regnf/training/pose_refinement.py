"""Per-frame camera pose corrections, optimised jointly with a field.

Poses from SLAM or structure from motion are off by a centimetre or two and a fraction of a
degree; a field trained on them blurs every surface that frames disagree on. Each training
frame gets a small rigid correction, the SE(3) exponential of a 6-vector (a rotation vector in
radians and a translation in metres), that composes on the camera's own axes::

    corrected camtoworld = camtoworld @ exp(delta)

so the correction's translation moves the camera centre by ``R dt`` (its length is the
centre's displacement) and its rotation turns the camera about its own centre. A sample seen
by a frame moves with the frame: ``p' = t + R (dR R^T (p - t) + dt)`` for the frame's
``camtoworld = [R, t]`` and correction ``(dR, dt)``. The corrections start at zero, are
penalised by an L2 term, and are applied only from a given fraction of the training steps on
(:class:`PoseRefineConfig`), so that the field takes its shape before the poses move.

A motion of every camera together is invisible to the losses (the field can follow it), so
the corrections' common rigid motion is taken out (:meth:`PoseCorrections.applied`): the map
stays where the given poses put it on average, and what refinement fixes is how the frames sit
relative to each other. What it can and cannot do on SLAM-like pose error is measured in
docs/decisions/pose_refinement.md.

Units: the field, the poses and the samples live in the capture's normalised frame (metres =
``scale`` x normalised + offset); the corrections are kept in metres and radians so that the
learning rate and the penalty mean the same on a room as on an object.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch

from regnf.core.errors import RegnfError
from regnf.fields.similarity import cross_matrices

Maps = tuple[torch.Tensor, torch.Tensor]
"""Per-frame world-space maps ``(D (n, 3, 3), b (n, 3))``: ``p' = p + D p + b``."""

_TAYLOR_BELOW = 1e-4
"""Squared rotation angle (rad^2) under which the exponential uses its series (no 0/0)."""


@dataclass
class PoseRefineConfig:
    """Joint refinement of the training frames' poses (see :mod:`regnf.training.pose_refinement`)."""

    mode: Literal["auto", "on", "off"] = "auto"
    """Refine the poses: ``auto`` only where the capture's poses are estimates, ``on`` always, ``off`` never."""
    lr: float = 1e-3
    """Learning rate of the corrections, about Adam's step, m and rad (docs/decisions/pose_refinement.md)."""
    weight: float = 1.0
    """Weight of the L2 penalty on the mean squared correction, per m^2 (docs/decisions/pose_refinement.md)."""
    start: float = 0.25
    """The first training step that applies the corrections, as a fraction of the steps."""
    keep_mean_pose: bool = True
    """Take the corrections' common rigid motion out, keeping the mean pose (docs/decisions/pose_refinement.md)."""

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "on", "off"):
            raise RegnfError(f"pose refinement mode must be auto, on or off, got {self.mode!r}")
        for name in ("lr", "weight"):
            value = getattr(self, name)
            if not (value >= 0 and value < float("inf")):
                raise RegnfError(f"pose refinement {name} must be a finite number >= 0, got {value}")
        if not 0.0 <= self.start <= 1.0:
            raise RegnfError(f"pose refinement start is a fraction of the steps, in [0, 1]; got {self.start}")

    def enabled(self, poses_estimated: bool) -> bool:
        """Whether the poses are refined for a capture whose poses are (not) estimates."""
        return self.mode == "on" or (self.mode == "auto" and bool(poses_estimated))


class PoseReport(NamedTuple):
    """The size of the corrections applied (metric world)."""

    median_cm: float
    """Median displacement of a camera centre, centimetres."""
    worst_cm: float
    """Largest displacement of a camera centre, centimetres."""
    median_deg: float
    """Median rotation of a camera, degrees."""
    worst_deg: float
    """Largest rotation of a camera, degrees."""
    frames: int
    """Frames corrected."""

    def line(self) -> str:
        """One line for the console: ``median 0.8 cm / 0.12 deg, worst 2.1 cm / 0.60 deg over 27 frames``."""
        return (f"median {self.median_cm:.1f} cm / {self.median_deg:.2f} deg, worst {self.worst_cm:.1f} cm / "
                f"{self.worst_deg:.2f} deg over {self.frames} frames")


def pose_refine_line(config: PoseRefineConfig, poses_estimated: bool, recorded: dict | None) -> str:
    """The console line on the pose refinement of a training run.

    Parameters
    ----------
    config : PoseRefineConfig
        The run's settings.
    poses_estimated : bool
        Whether the capture's poses are estimates.
    recorded : dict or None
        The trained field's ``provenance["pose_refinement"]`` (the :class:`PoseReport`'s fields).
    """
    if not config.enabled(poses_estimated):
        why = "poses exact" if config.mode == "auto" else "--pose-refine off"
        return f"pose refinement: off ({why})"
    try:
        report = PoseReport(*(recorded[k] for k in PoseReport._fields))
        return f"pose refinement: {report.line()}"
    except (KeyError, TypeError, ValueError):
        # A field trained elsewhere need not record its corrections (or records them otherwise).
        return "pose refinement: no corrections recorded in the field"


def se3_exp(xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The SE(3) exponential of twists ``xi = (w, u)``: rotation vector ``w``, translation part ``u``.

    Rodrigues' formula ``R = I + a W + b W^2`` and ``t = (I + b W + c W^2) u`` with ``W = [w]_x``,
    ``a = sin(q)/q``, ``b = (1 - cos(q))/q^2``, ``c = (q - sin(q))/q^3``, ``q = |w|``; below
    :data:`_TAYLOR_BELOW` (q^2) the coefficients come from their series, so the value and the
    gradient are finite at 0. Computed in float64.

    Parameters
    ----------
    xi : (n, 6) tensor

    Returns
    -------
    R : (n, 3, 3) float64
    t : (n, 3) float64
    """
    xi = xi.to(torch.float64)
    w, u = xi[:, :3], xi[:, 3:]
    q2 = (w * w).sum(-1)
    small = q2 < _TAYLOR_BELOW
    # The direct branch never sees a small angle: no 0/0 in its value or its gradient.
    q = torch.sqrt(torch.where(small, torch.ones_like(q2), q2))
    a = torch.where(small, 1 - q2 / 6 + q2 * q2 / 120, torch.sin(q) / q)
    b = torch.where(small, 0.5 - q2 / 24 + q2 * q2 / 720, (1 - torch.cos(q)) / (q * q))
    c = torch.where(small, 1 / 6 - q2 / 120 + q2 * q2 / 5040, (q - torch.sin(q)) / (q * q * q))
    W = cross_matrices(w)
    W2 = W @ W
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    R = eye + a[:, None, None] * W + b[:, None, None] * W2
    V = eye + b[:, None, None] * W + c[:, None, None] * W2
    return R, (V @ u[:, :, None]).squeeze(-1)


def per_frame(x: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
    """``x[frame]``, rows of the per-frame values ``x`` (n, ...) for frames ``frame`` (m,), as a one-hot product.

    Indexing's backward adds the samples' gradients into each frame's row in an order that
    changes from run to run on the CPU (at a training batch's size); the product's backward is a
    matrix product, which sums in a fixed order, so training with pose refinement repeats bit
    for bit.
    """
    onehot = torch.nn.functional.one_hot(frame.long(), x.shape[0]).to(x.dtype)
    return (onehot @ x.reshape(x.shape[0], -1)).reshape(frame.shape[0], *x.shape[1:])


class PoseCorrections(torch.nn.Module):
    """Learnable rigid corrections of ``n`` frames' camera-to-world poses.

    Parameters
    ----------
    camtoworld : (n, 4, 4) tensor
        The frames' poses as given (OpenCV camera axes, normalised frame).
    scale : float
        Metres per normalised unit (the field's ``world_scale``).
    config : PoseRefineConfig, optional
        Learning rate and penalty.

    Attributes
    ----------
    delta : (n, 6) parameter
        Rotation vector (radians) and translation (metres) of each frame, zero at first.
    """

    def __init__(self, camtoworld: torch.Tensor, scale: float,
                 config: PoseRefineConfig | None = None) -> None:
        super().__init__()
        c2w = torch.as_tensor(camtoworld, dtype=torch.float64)
        if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
            raise RegnfError(f"camtoworld must be (n, 4, 4), got {tuple(c2w.shape)}")
        if not (scale > 0 and scale < float("inf")):
            raise RegnfError(f"scale must be finite and > 0, got {scale}")
        self.config = config or PoseRefineConfig()
        self.scale = float(scale)
        self.register_buffer("rotation", c2w[:, :3, :3].clone(), persistent=False)
        self.register_buffer("centre", c2w[:, :3, 3].clone(), persistent=False)
        self.delta = torch.nn.Parameter(torch.zeros(c2w.shape[0], 6, dtype=torch.float32,
                                                    device=c2w.device))

    def applied(self) -> torch.Tensor:
        """(n, 6) float64: the corrections applied, ``delta`` less its common rigid motion.

        With ``keep_mean_pose`` the motion that would move every camera together (a turn
        ``W``, the mean of the corrections' world rotation vectors, about the mean camera centre,
        and the mean shift of the centres) is taken out, to first order: what is left has world
        rotation vectors and centre shifts of mean zero. The field could follow such a motion
        unseen, so nothing in the losses holds it, and it would move the map off the frame the
        given poses put it in.
        """
        delta = self.delta.to(torch.float64)
        if not self.config.keep_mean_pose or delta.shape[0] < 2:
            return delta
        R = self.rotation.to(delta.device)
        turn = (R @ delta[:, :3, None]).squeeze(-1)
        shift = (R @ delta[:, 3:, None]).squeeze(-1)
        centre = self.centre.to(delta.device)
        arm = (centre - centre.mean(0)) * self.scale
        mean_turn = turn.mean(0)
        turn = turn - mean_turn
        shift = shift - shift.mean(0) - torch.linalg.cross(mean_turn.expand_as(arm), arm)
        Rt = R.transpose(1, 2)
        return torch.cat([(Rt @ turn[:, :, None]).squeeze(-1), (Rt @ shift[:, :, None]).squeeze(-1)], -1)

    def corrections(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each frame's correction ``(dR (n, 3, 3), dt (n, 3))``, ``dt`` in normalised units (float64)."""
        dR, dt = se3_exp(self.applied())
        return dR, dt / self.scale

    def world_maps(self) -> Maps:
        """Each frame's correction as a world-space rigid map ``p' = p + D p + b``.

        Returns
        -------
        D : (n, 3, 3) float64
            ``R (dR - I) R^T`` (exactly 0 for a zero correction).
        b : (n, 3) float64
            ``R dt - D t``.
        """
        dR, dt = self.corrections()
        R, t = self.rotation.to(dR.device), self.centre.to(dR.device)
        eye = torch.eye(3, dtype=dR.dtype, device=dR.device)
        D = R @ (dR - eye) @ R.transpose(1, 2)
        b = (R @ dt[:, :, None]).squeeze(-1) - (D @ t[:, :, None]).squeeze(-1)
        return D, b

    def points(self, p: torch.Tensor, frame: torch.Tensor, maps: Maps | None = None) -> torch.Tensor:
        """(m, 3) world points ``p`` seen by frames ``frame`` (m,), moved with their frames' corrections.

        ``maps``: :meth:`world_maps`, when several calls share one step's corrections.
        """
        D, b = maps if maps is not None else self.world_maps()
        D, b = per_frame(D.to(p.dtype), frame), per_frame(b.to(p.dtype), frame)
        return p + (D @ p[:, :, None]).squeeze(-1) + b

    def points_back(self, p: torch.Tensor, frame: torch.Tensor, maps: Maps | None = None) -> torch.Tensor:
        """The inverse of :meth:`points`: where world points ``p`` (m, 3) lie for frames ``frame`` (m,) as given."""
        D, b = maps if maps is not None else self.world_maps()
        D, b = per_frame(D.to(p.dtype), frame), per_frame(b.to(p.dtype), frame)
        # I + D is a rotation: its inverse is its transpose.
        q = p - b
        return q + (D.transpose(1, 2) @ q[:, :, None]).squeeze(-1)

    def directions(self, d: torch.Tensor, frame: torch.Tensor, maps: Maps | None = None) -> torch.Tensor:
        """(m, 3) world directions (or normals) of frames ``frame`` (m,), turned with their frames."""
        D = per_frame((maps if maps is not None else self.world_maps())[0].to(d.dtype), frame)
        return d + (D @ d[:, :, None]).squeeze(-1)

    def rays(self, origins: torch.Tensor, dirs: torch.Tensor, frame: torch.Tensor,
             maps: Maps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrected rays of frames ``frame`` (m,): origins (m, 3) and directions (m, 3)."""
        maps = maps if maps is not None else self.world_maps()
        return self.points(origins, frame, maps), self.directions(dirs, frame, maps)

    def camtoworld(self) -> torch.Tensor:
        """(n, 4, 4) float64: the corrected poses ``camtoworld @ exp(delta)`` (normalised frame)."""
        dR, dt = self.corrections()
        R, t = self.rotation.to(dR.device), self.centre.to(dR.device)
        out = torch.zeros(R.shape[0], 4, 4, dtype=dR.dtype, device=dR.device)
        out[:, :3, :3] = R @ dR
        out[:, :3, 3] = t + (R @ dt[:, :, None]).squeeze(-1)
        out[:, 3, 3] = 1.0
        return out

    def regulariser(self) -> torch.Tensor:
        """The penalty: ``weight`` x the frames' mean squared correction (metres and radians)."""
        applied = self.applied()
        return self.config.weight * (applied * applied).sum(-1).mean().to(self.delta.dtype)

    def param_group(self) -> dict:
        """The optimiser parameter group of the corrections (no weight decay: the penalty is explicit)."""
        return {"params": [self.delta], "lr": self.config.lr, "weight_decay": 0.0}

    @torch.no_grad()
    def report(self) -> PoseReport:
        """Median and largest camera displacement (cm, metric) and rotation (degrees) applied."""
        applied = self.applied()
        _, dt = se3_exp(applied)
        cm = dt.norm(dim=-1) * 100.0
        # The rotation vector's length is the angle (folded into [0, pi]).
        angle = torch.remainder(applied[:, :3].norm(dim=-1), 2 * torch.pi)
        deg = torch.rad2deg(torch.minimum(angle, 2 * torch.pi - angle))
        return PoseReport(float(cm.quantile(0.5)), float(cm.max()), float(deg.quantile(0.5)), float(deg.max()),
                          int(self.delta.shape[0]))
