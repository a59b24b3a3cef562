"""Distil a neural SDF from a mesh as users have it (CAD models, scans, triangle soups).

The mesh need not be watertight. It is first turned to +Z up (:attr:`DistillConfig.up`) and
repaired (:func:`regnf.meshes.mesh_repair.repair_mesh`: close vertices merged, degenerate
and duplicate faces dropped, winding made consistent and outward per connected piece). The
targets are then:

- signed distances at points near the surface and throughout the bounds: the distance to
  the solid's surface (Open3D ``compute_distance``, the mesh without the faces that lie
  inside another part), negative where the generalised winding number is above 0.5
  (:mod:`regnf.meshes.winding`), which needs neither closed nor consistently sampled
  surfaces: a hole is spanned by the winding number's 0.5 level, overlapping parts add up;
- normals and colours of the repaired mesh at points sampled on that surface.

A mesh that cannot be signed (no triangles, no area, a flat sheet, a winding number above 0.5
nowhere or everywhere) raises :class:`~regnf.meshes.mesh_repair.MeshError` naming the file.

Preparing the targets (:func:`distillation_targets`: repair, winding numbers, distances)
takes seconds for a large mesh (docs/decisions/field-training.md).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

from regnf.core.errors import RegnfError
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import (
    NeuralSDF,
    NeuralSDFConfig,
    tetrahedral_combine,
    tetrahedral_points,
)
from regnf.meshes.mesh_repair import UP_AXES, RepairReport, repair_mesh, up_rotation
from regnf.meshes.mesh_sign import MeshSignConfig, SignedMesh, check_signable
from regnf.training.optim import OptimiserConfig, finest_voxel, optimise

DISTILL_VERSION = 3
"""Version of what a distilled field is for a given mesh and config (part of cache keys).
2: repaired meshes, winding-number signs, distances to the solid's surface (1: ray parity on
watertight meshes only). 3: the learning rates decay to ``lr_final`` = 0.01 of their start,
not 0.1."""


@dataclass
class DistillConfig(OptimiserConfig):
    """How to distil a field from a mesh (the optimiser's settings: :class:`OptimiserConfig`)."""

    batch: int = 4096
    """Near-surface samples per step (plus half as many uniform ones)."""
    pool_surface: int = 150_000
    """Surface samples drawn once from the mesh."""
    pool_near_std: float = 0.02
    """Std of the offsets of near-surface samples, as a fraction of the bounds' size."""
    w_eikonal: float = 0.1
    """Weight of the eikonal loss."""
    eikonal_uniform: bool = True
    """Eikonal loss at the uniform samples too, not only the surface ones (docs/decisions/field-training.md)."""
    w_normal: float = 0.05
    """Weight of the normal loss at surface samples."""
    w_color: float = 1.0
    """Weight of the colour loss."""
    margin: float = 1.15
    """Normalisation: the field frame's unit is the half of the mesh's largest extent times this."""
    seed: int = 0
    """Seed of the sampling and the initialisation."""
    device: str = "cpu"
    """Torch device to train on."""
    architecture: NeuralSDFConfig = field(default_factory=NeuralSDFConfig)
    """Architecture of the field."""
    up: str = "z"
    """Up axis of the mesh as given (z, y, x, -z, -y, -x), turned to +Z first and not moved otherwise."""
    sign: MeshSignConfig = field(default_factory=MeshSignConfig)
    """How signs are decided (winding numbers) and internal faces found."""
    scale: float = 1.0
    """Metres per unit of the mesh as given (0.001 for a file in millimetres), applied to the vertices first."""

    def __post_init__(self) -> None:
        super().__post_init__()
        name = type(self).__name__
        for key in ("w_eikonal", "w_normal", "w_color", "pool_near_std"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) >= 0):
                raise RegnfError(f"{name}.{key} must be a finite number >= 0, got {getattr(self, key)}")
        for key in ("batch", "pool_surface"):
            value = getattr(self, key)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise RegnfError(f"{name}.{key} must be a whole number >= 1, got {value}")
        for key in ("margin", "scale"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) > 0):
                raise RegnfError(f"{name}.{key} must be finite and > 0, got {getattr(self, key)}")


def normalising_transform(mesh: trimesh.Trimesh, margin: float) -> np.ndarray:
    """(4, 4) field frame -> metres: the mesh's box centre, half its largest extent * margin."""
    lo, hi = mesh.bounds
    s = float((hi - lo).max()) * 0.5 * margin
    m = np.eye(4)
    m[:3, :3] *= s
    m[:3, 3] = (lo + hi) * 0.5
    return m


def face_colors(mesh: trimesh.Trimesh) -> np.ndarray:
    """(f, 3) float face colours in [0, 1] (grey where the mesh has none)."""
    visual = mesh.visual
    if visual is not None and getattr(visual, "kind", None) in ("face", "vertex"):
        return np.asarray(visual.face_colors[:, :3], dtype=np.float32) / 255.0
    return np.full((len(mesh.faces), 3), 0.7, dtype=np.float32)


@dataclass
class DistillTargets:
    """What a field is distilled against, in the field frame (see :func:`distillation_targets`)."""

    to_world: np.ndarray
    """(4, 4) field frame -> metres (+Z up)."""
    bounds: np.ndarray
    """(2, 3) float: the box samples are drawn in (and the field's bounds)."""
    points: np.ndarray
    """(n, 3) float32: sample points, the first ``n_near`` near the surface, then uniform."""
    sdf: np.ndarray
    """(n,) float32: signed distance at ``points`` (negative inside)."""
    n_near: int
    """How many of ``points`` are near-surface samples."""
    surface_points: np.ndarray
    """(s, 3) float64: points on the surface."""
    surface_normals: np.ndarray
    """(s, 3) float64: outward unit normals there."""
    surface_colors: np.ndarray
    """(s, 3) float32 colours in [0, 1] there."""
    report: RepairReport
    """What the repair found and changed."""
    internal_faces: int
    """Faces (or pieces of faces) dropped as inside another part."""
    seconds: float
    """Time taken to prepare all this."""


def mesh_source(info: FieldInfo | None) -> str:
    """The name a mesh goes by in error messages: its file if known, else the field's name."""
    if info is not None:
        return str(info.provenance.get("mesh") or info.name or "mesh")
    return "mesh"


def distillation_targets(
    mesh: trimesh.Trimesh, config: DistillConfig | None = None, source: str = "mesh"
) -> DistillTargets:
    """Turn, repair and sign ``mesh``; sample the targets of distillation.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        In units of ``config.scale`` metres, up axis ``config.up``; any triangles (open,
        flipped, several parts...).
    config : DistillConfig, optional
    source : str
        The mesh's file, for error messages.

    Raises
    ------
    MeshError
        The mesh cannot be signed (see the module).
    ValueError
        ``config.up`` is not an axis, or ``config.scale`` is not a positive number.
    """
    cfg = config or DistillConfig()
    if cfg.up not in UP_AXES:
        raise RegnfError(f"up axis must be one of {', '.join(UP_AXES)}, got {cfg.up!r}")
    if not (np.isfinite(cfg.scale) and cfg.scale > 0):
        raise RegnfError(f"scale must be a positive number of metres per unit, got {cfg.scale}")
    t0 = time.perf_counter()
    colors = face_colors(mesh)
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * cfg.scale
    if cfg.up != "z":
        vertices = vertices @ up_rotation(cfg.up).T
    repaired = repair_mesh(vertices, np.asarray(mesh.faces), source=source)
    rng = np.random.default_rng(cfg.seed)
    to_world = normalising_transform(trimesh.Trimesh(repaired.vertices, repaired.faces, process=False), cfg.margin)
    s = to_world[0, 0]
    verts = (repaired.vertices - to_world[:3, 3]) / s
    signed = SignedMesh(verts, repaired.faces, repaired.piece, cfg.sign, source)
    surf = signed.surface
    unit = trimesh.Trimesh(surf.vertices, surf.faces, process=False)
    pts, fid = trimesh.sample.sample_surface(unit, cfg.pool_surface, seed=cfg.seed)
    nrm = unit.face_normals[fid]
    col = colors[repaired.face_index[surf.parent[fid]]]
    lo = verts.min(0) - 0.08 * (verts.max(0) - verts.min(0)).max()
    hi = verts.max(0) + 0.08 * (verts.max(0) - verts.min(0)).max()
    lo, hi = np.maximum(lo, -1.0), np.minimum(hi, 1.0)
    size = float((hi - lo).max())
    near = pts + rng.normal(0.0, cfg.pool_near_std * size, pts.shape)
    uniform = lo + rng.random((cfg.pool_surface // 2, 3)) * (hi - lo)
    pool = np.concatenate([near, uniform]).astype(np.float32)
    sd, w = signed.signed_distance(pool)
    # Uniform samples fill the mesh's box: an inside and an outside must both show there.
    check_signable(w[len(near):], source)
    return DistillTargets(
        to_world=to_world, bounds=np.stack([lo, hi]), points=pool, sdf=sd, n_near=len(near),
        surface_points=pts, surface_normals=nrm, surface_colors=col, report=repaired.report,
        internal_faces=surf.internal_faces, seconds=time.perf_counter() - t0,
    )


def distill_mesh(
    mesh: trimesh.Trimesh,
    config: DistillConfig | None = None,
    info: FieldInfo | None = None,
    progress: bool = True,
    source: str | None = None,
    targets: DistillTargets | None = None,
) -> tuple[NeuralSDF, dict]:
    """Fit a :class:`NeuralSDF` to a mesh given in metres (any triangles; see the module).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Units of ``config.scale`` metres, up axis ``config.up``.
    config : DistillConfig, optional
    info : FieldInfo, optional
        Label, name, symmetry, provenance of the field (``provenance["mesh"]``, if set, names
        the mesh in error messages).
    progress : bool
        Show a progress bar.
    source : str, optional
        Name of the mesh in error messages (default: from ``info``).
    targets : DistillTargets, optional
        ``distillation_targets(mesh, config)`` if already prepared (a caller that checks the
        mesh before it takes a lock); prepared here otherwise.

    Returns
    -------
    field : NeuralSDF
        Its ``to_world`` maps the normalised frame to the mesh's metres (turned to +Z up).
    log : dict
        ``seconds`` (all), ``prepare_seconds`` (targets), ``steps``, ``losses``, ``repair``.

    Raises
    ------
    MeshError
        The mesh cannot be signed, before any training.
    """
    cfg = config or DistillConfig()
    t0 = time.perf_counter()
    prepared_before = 0.0 if targets is None else targets.seconds
    if targets is None:
        targets = distillation_targets(mesh, cfg, source or mesh_source(info))
    torch.manual_seed(cfg.seed)
    to_world = targets.to_world
    lo, hi = targets.bounds
    pool, sd = targets.points, targets.sdf
    pts, nrm, col = targets.surface_points, targets.surface_normals, targets.surface_colors
    n_near = targets.n_near
    device = torch.device(cfg.device)
    info = info or FieldInfo()
    model = NeuralSDF(
        cfg.architecture,
        bounds=torch.tensor(np.stack([lo, hi]), dtype=torch.float32),
        to_world=torch.tensor(to_world),
        info=info,
    ).to(device)
    ell = finest_voxel(model)
    h_fd = 0.5 * ell
    P = torch.from_numpy(pool).to(device)
    SD = torch.from_numpy(sd).float().to(device)
    S_pts = torch.from_numpy(pts.astype(np.float32)).to(device)
    S_nrm = torch.from_numpy(nrm.astype(np.float32)).to(device)
    S_col = torch.from_numpy(col.astype(np.float32)).to(device)
    gen = torch.Generator().manual_seed(cfg.seed)
    nb, nu, ns = cfg.batch, cfg.batch // 2, cfg.batch // 2

    def loss_at(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        ii = torch.cat([
            torch.randint(n_near, (nb,), generator=gen),
            n_near + torch.randint(pool.shape[0] - n_near, (nu,), generator=gen),
        ]).to(device)
        si = torch.randint(S_pts.shape[0], (ns,), generator=gen).to(device)
        x, target = P[ii], SD[ii]
        xs = S_pts[si]
        fd = tetrahedral_points(torch.cat([xs, x[-nu:]]) if cfg.eikonal_uniform else xs, h_fd)
        f_all, feat_all = model.sdf_and_features(torch.cat([x, xs, fd]))
        f_x = f_all[: x.shape[0]]
        f_s = f_all[x.shape[0] : x.shape[0] + ns]
        feat_s = feat_all[x.shape[0] : x.shape[0] + ns]
        grads, _ = tetrahedral_combine(f_all[x.shape[0] + ns :], h_fd)
        g_s = grads[:ns]
        loss_sdf = (f_x - target).abs().mean() / ell + f_s.abs().mean() / ell
        loss_eik = ((grads.norm(dim=-1) - 1.0) ** 2).mean()
        loss_normal = (1.0 - F.cosine_similarity(g_s, S_nrm[si], dim=-1)).mean()
        rgb = model.color_from(feat_s, F.normalize(g_s.detach(), dim=-1), None)
        loss_color = (rgb - S_col[si]).abs().mean()
        loss = loss_sdf + cfg.w_eikonal * loss_eik + cfg.w_normal * loss_normal + cfg.w_color * loss_color
        return loss, {"sdf": loss_sdf, "eikonal": loss_eik, "color": loss_color}

    losses = optimise(model, cfg, loss_at, desc=f"distil {info.name or 'mesh'}", progress=progress)
    seconds = time.perf_counter() - t0 + prepared_before
    model.info.provenance = {
        **model.info.provenance,
        "trained_from": "mesh",
        "distill_version": DISTILL_VERSION,
        "mesh_repair": {**targets.report.as_dict(), "internal_faces": targets.internal_faces},
        "train_config": json.loads(json.dumps(asdict(cfg), default=str)),
        "train_seconds": round(seconds, 3),
    }
    model.eval()
    return model, {
        "seconds": seconds, "prepare_seconds": targets.seconds, "steps": cfg.steps,
        "losses": losses, "repair": targets.report.as_dict(),
    }
