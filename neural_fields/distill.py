"""Distil a neural SDF from a watertight mesh (for users whose library is CAD models).

Targets are exact: signed distances from Open3D's ``RaycastingScene`` at points near the
surface and throughout the bounds, normals and colours of the mesh at surface samples.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import open3d as o3d
import torch
import torch.nn.functional as F
import trimesh
from tqdm import tqdm

from neural_fields.field import FieldInfo
from neural_fields.neural_sdf import (
    NeuralSDF,
    NeuralSDFConfig,
    tetrahedral_combine,
    tetrahedral_points,
)
from neural_fields.optim import finest_voxel, lr_factor, make_optimizer


@dataclass
class DistillConfig:
    """How to distil a field from a mesh."""

    steps: int = 400
    """Optimisation steps."""
    batch: int = 4096
    """Near-surface samples per step (plus half as many uniform ones)."""
    pool_surface: int = 150_000
    """Surface samples drawn once from the mesh."""
    pool_near_std: float = 0.02
    """Std of the offsets of near-surface samples, as a fraction of the bounds' size."""
    lr_grid: float = 2e-2
    """Learning rate of the feature grids."""
    lr_mlp: float = 2e-3
    """Learning rate of the MLPs."""
    w_eikonal: float = 0.1
    """Weight of the eikonal loss."""
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


def distill_mesh(
    mesh: trimesh.Trimesh,
    config: DistillConfig | None = None,
    info: FieldInfo | None = None,
    progress: bool = True,
) -> tuple[NeuralSDF, dict]:
    """Fit a :class:`NeuralSDF` to a watertight mesh given in metres.

    Returns the field (its ``to_world`` maps the normalised frame back to the mesh's
    metres) and a small log (seconds, losses).
    """
    cfg = config or DistillConfig()
    # Per-face colours are often stored on unmerged vertices; merging (which keeps the face
    # order, so colours still line up) is what makes the watertightness check meaningful.
    colors = face_colors(mesh)
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=False)
    if not mesh.is_watertight:
        raise ValueError("distillation needs a watertight mesh (signs come from ray parity)")
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    to_world = normalising_transform(mesh, cfg.margin)
    s = to_world[0, 0]
    verts = (mesh.vertices - to_world[:3, 3]) / s
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    unit = trimesh.Trimesh(verts, mesh.faces, process=False)
    pts, fid = trimesh.sample.sample_surface(unit, cfg.pool_surface, seed=cfg.seed)
    nrm = unit.face_normals[fid]
    col = colors[fid]
    lo = verts.min(0) - 0.08 * (verts.max(0) - verts.min(0)).max()
    hi = verts.max(0) + 0.08 * (verts.max(0) - verts.min(0)).max()
    lo, hi = np.maximum(lo, -1.0), np.minimum(hi, 1.0)
    size = float((hi - lo).max())
    near = pts + rng.normal(0.0, cfg.pool_near_std * size, pts.shape)
    uniform = lo + rng.random((cfg.pool_surface // 2, 3)) * (hi - lo)
    pool = np.concatenate([near, uniform]).astype(np.float32)
    sd = scene.compute_signed_distance(o3d.core.Tensor(pool)).numpy()

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
    n_near = near.shape[0]
    gen = torch.Generator().manual_seed(cfg.seed)
    opt = make_optimizer(model, cfg.lr_grid, cfg.lr_mlp)
    base = [g["lr"] for g in opt.param_groups]
    losses = []
    nb, nu, ns = cfg.batch, cfg.batch // 2, cfg.batch // 2
    for step in tqdm(range(cfg.steps), desc=f"distil {info.name or 'mesh'}", disable=not progress, leave=False):
        for g, lr in zip(opt.param_groups, base):
            g["lr"] = lr * lr_factor(step, cfg.steps)
        ii = torch.cat([
            torch.randint(n_near, (nb,), generator=gen),
            n_near + torch.randint(pool.shape[0] - n_near, (nu,), generator=gen),
        ]).to(device)
        si = torch.randint(S_pts.shape[0], (ns,), generator=gen).to(device)
        x, target = P[ii], SD[ii]
        xs = S_pts[si]
        fd = tetrahedral_points(torch.cat([xs, x[-nu:]]), h_fd)
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
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 50 == 0 or step == cfg.steps - 1:
            losses.append({
                "step": step, "loss": float(loss.detach()), "sdf": float(loss_sdf.detach()),
                "eikonal": float(loss_eik.detach()), "color": float(loss_color.detach()),
            })
    seconds = time.perf_counter() - t0
    model.info.provenance = {
        **model.info.provenance,
        "trained_from": "mesh",
        "train_config": json.loads(json.dumps(asdict(cfg), default=str)),
        "train_seconds": round(seconds, 3),
    }
    model.eval()
    return model, {"seconds": seconds, "steps": cfg.steps, "losses": losses}
