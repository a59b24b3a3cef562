"""Bidirectional SDF refinement of a scene -> library similarity (docs/design.md section 1.5).

Given surface samples ``A`` of the object in the scene field (scene field frame) and ``B`` of
the library object (library field frame), and an initial similarity ``T0``, the refinement
minimises

    mean_{x in A} k(|S_lib(T x) - s S_scene(x)|) + mean_{y in B} k(|s S_scene(T^-1 y) - S_lib(y)|)
        + w L_reg

over ``T(x) = s R x + t`` and the kernel's (alpha, c), where ``k`` is Barron's adaptive robust
NLL (:mod:`regnf.registration.robust_loss`, one (alpha, c) pair shared by both terms) and ``L_reg`` the
trimmed mean of the squared distances from every mapped SCENE sample ``T x`` to its nearest
LIBRARY sample (pulling the library to the scene would punish library surface the scene never
saw). Both residuals are library distances: an SDF scales with its geometry, so the scene's is
multiplied by ``s``.

Units. The paper's thresholds are absolute numbers for fields normalised to [-1, 1]^3. Here
every length in the loss and every threshold is measured in the library's *reference length*
``L = max(bounds extent) / 2`` of the library field (1 for a field normalised to [-1, 1]^3, so
the paper's numbers carry over unchanged, and a library field kept in metres behaves the same).
The kernel sees residuals divided by ``L`` (so its scale init 1 means what it means in the
paper), the translation is learnt in units of ``L`` (so its learning rate does too), and scene-
side tolerances are the library ones mapped through the current scale (``s |S_scene| <= tol L``).

Parameterisation: ``R = exp([w]x) R0``, ``s = exp(l) s0`` (w, l start at 0), and a free
translation. The rotation and the scale are applied about ``c``, the centroid of ``T0(A)``
(``T(x) = e^l exp([w]x) (T0(x) - c) + c + L tau``, i.e. ``t = e^l exp([w]x)(t0 - c) + c + L tau``
with tau free, starting at 0): the same 7 degrees of freedom as ``(w, l, t)``, but a rotation
step no longer swings the object about the library origin, which would couple rotation and
translation (library objects have their origin at the base, not the centre).

Regulariser weight: the default 0.1 keeps the paper's term at no measurable cost in accuracy;
the SDF terms decide the basin, and a larger weight lets the nearest-neighbour distances, which
do not vanish at the truth, bias the optimum (docs/decisions/registration-refinement.md).

Two optimisers (``RefineConfig.optimizer``):

- ``lm`` (default, not in the paper): Levenberg-Marquardt. The objective is a robust
  least-squares problem in 8 parameters (pose, scale, offset), so each iteration writes out the
  residuals' Jacobians from the fields' spatial gradients (:meth:`~regnf.registration.refine_batch.HypothesisBatch.linearise`), fits each
  hypothesis's kernel (alpha, c) to its residuals by minimising their NLL (what Adam does by
  gradient steps), and solves a damped 8 x 8 system whose curvature is the loss's own (clamped
  at 0 where a term is not convex; :mod:`regnf.registration.irls`). 5-15 iterations instead of 80-200
  Adam steps, to the same or a tighter optimum (``docs/benchmarks.md``).
- ``adam``: the paper's, as published: Adam on all parameters and the kernel together.

Several hypotheses are refined in one batch (:func:`refine_many`): their samples are stacked so
that each iteration costs two field queries in all. Adam is elementwise, so one Adam over the
stacked per-hypothesis parameters is exactly K independent optimisations; Levenberg-Marquardt
solves, accepts and fits a kernel per hypothesis, which is the same.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.core.threads import one_thread, worker_count
from regnf.fields.field import Field
from regnf.registration.metrics import ObjectSymmetry
from regnf.registration.refine_batch import HypothesisBatch
from regnf.registration.refine_config import (
    RefineConfig,
    RefineResult,
    reference_length,
    without_steps,
)
from regnf.registration.refine_loops import run_adam, run_lm
from regnf.registration.transform import SimilarityTransform

__all__ = ["RefineConfig", "RefineResult", "reference_length", "refine", "refine_many", "without_steps"]


@contextlib.contextmanager
def _frozen(*modules: torch.nn.Module) -> Iterator[None]:
    """No gradients to the fields' own parameters (autograd w.r.t. query points still flows)."""
    params = {id(p): p for m in modules for p in m.parameters()}
    saved = {k: p.requires_grad for k, p in params.items()}
    try:
        for p in params.values():
            p.requires_grad_(False)
        yield
    finally:
        for k, p in params.items():
            p.requires_grad_(saved[k])


def _check_points(x: torch.Tensor | None, what: str, device: torch.device) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != 3:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise RegnfError(f"{what} must be a (n, 3) tensor, got {shape}")
    if x.shape[0] == 0:
        raise RegnfError(f"{what} is empty: refinement needs surface samples")
    if not x.is_floating_point():
        raise RegnfError(f"{what} must be a float tensor, got {x.dtype}")
    if x.device != device:
        raise RegnfError(f"{what} is on {x.device} but the fields are on {device}; move them to one device")
    if not bool(torch.isfinite(x).all()):
        raise RegnfError(f"{what} contains non-finite coordinates")
    return x


def _check_transform(T: SimilarityTransform, k: int) -> None:
    R = np.asarray(T.R, dtype=np.float64)
    t = np.asarray(T.t, dtype=np.float64).reshape(-1)
    s = float(T.s)
    if R.shape != (3, 3) or t.shape != (3,):
        raise RegnfError(f"initial transform {k}: R must be 3x3 and t have 3 entries")
    if not (np.isfinite(R).all() and np.isfinite(t).all() and math.isfinite(s) and s > 0):
        raise RegnfError(f"initial transform {k} has non-finite entries or a scale <= 0 (s = {s})")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise RegnfError(f"initial transform {k}: R is not a rotation")


def refine_many(
    scene_field: Field,
    library_field: Field,
    A: torch.Tensor,
    B: torch.Tensor | None,
    inits: Sequence[SimilarityTransform],
    config: RefineConfig | None = None,
    device: torch.device | str | None = None,
    symmetry: ObjectSymmetry | None = None,
    workers: int | None = None,
) -> list[RefineResult]:
    """Refine K initial hypotheses at once (one batched pair of field queries per iteration).

    Parameters
    ----------
    scene_field, library_field : Field
        On one device; their parameters receive no gradient.
    A : (n, 3) float
        Surface samples of the object in the scene field frame.
    B : (m, 3) float or None
        Surface samples of the library object in the library field frame (ignored, and may be
        None, when ``config.bidirectional`` is False).
    inits : list of SimilarityTransform
        Initial scene -> library similarities, at least one.
    config : RefineConfig, optional
    device : torch device, optional
        Where to compute; it must be the fields' device (nothing is moved implicitly).
    symmetry : ObjectSymmetry, optional
        The library object's symmetry: Levenberg-Marquardt stops a hypothesis that reaches a
        better one's pose modulo it (``RefineConfig.lm_merge_rotation_deg``).
    workers : int, optional
        CPU threads for the pair of field queries, the scene's and the library's side by side
        (each on one thread, so the results are the same bits on any count); default: one per
        core torch may use here (:func:`~regnf.core.threads.worker_count`).

    Returns
    -------
    list of RefineResult
        One per hypothesis, in the order of ``inits``.
    """
    cfg = config or RefineConfig()
    dev = library_field.device
    if scene_field.device != dev:
        raise RegnfError(f"the scene field is on {scene_field.device} and the library field on {dev}; "
                         "move both to one device")
    if device is not None and torch.device(device) != dev:
        raise RegnfError(f"device {device} requested but the fields are on {dev}")
    _check_points(A, "A (scene samples)", dev)
    if cfg.bidirectional:
        _check_points(B, "B (library samples)", dev)
        if B.dtype != A.dtype:
            raise RegnfError(f"A is {A.dtype} but B is {B.dtype}")
    inits = list(inits)
    if not inits:
        raise RegnfError("refine_many needs at least one initial transform")
    for k, T in enumerate(inits):
        _check_transform(T, k)

    workers = worker_count(workers)  # before one_thread() sets torch's count to 1
    start = time.perf_counter()
    with _frozen(scene_field, library_field), one_thread():
        batch = HypothesisBatch(scene_field, library_field, A, B if cfg.bidirectional else None, inits, cfg, workers)
        K = len(inits)
        histories: list[list[dict]] = [[] for _ in range(K)]
        steps = [0] * K
        if cfg.optimizer == "lm":
            run_lm(batch, histories, steps, symmetry)
        else:
            run_adam(batch, histories, steps)
        # One more evaluation at the returned parameters, so the reported numbers describe them.
        batch.restore_all()
        with torch.no_grad():
            loss, stats = batch.evaluate()
        transforms = batch.transforms()
        offsets = batch.offset().detach().cpu().tolist()
    seconds = time.perf_counter() - start
    loss, stats = loss.cpu().numpy(), stats.cpu().numpy()
    return [
        RefineResult(
            transform=transforms[k],
            loss=float(loss[k]),
            mean_residual_A=float(stats[k, 0]),
            mean_residual_B=float(stats[k, 1]),
            inlier_fraction=float(stats[k, 2] / max(stats[k, 3], 1.0)),
            iterations=steps[k],
            history=histories[k],
            seconds=seconds,
            inlier_fraction_scene=float(stats[k, 5] / max(stats[k, 6], 1.0)),
            inlier_fraction_library=float((stats[k, 2] - stats[k, 5]) / max(stats[k, 3] - stats[k, 6], 1.0))
            if cfg.bidirectional else float("nan"),
            offset=float(offsets[k]),
        )
        for k in range(K)
    ]


def refine(
    scene_field: Field,
    library_field: Field,
    A: torch.Tensor,
    B: torch.Tensor | None,
    T0: SimilarityTransform,
    config: RefineConfig | None = None,
    device: torch.device | str | None = None,
) -> RefineResult:
    """Refine one scene -> library similarity by bidirectional SDF alignment.

    Parameters
    ----------
    scene_field, library_field : Field
        On one device.
    A : (n, 3) float
        Scene surface samples, scene field frame.
    B : (m, 3) float or None
        Library surface samples, library field frame (None allowed when not bidirectional).
    T0 : SimilarityTransform
        Initial scene -> library similarity.
    config : RefineConfig, optional
    device : torch device, optional
        Must be the fields' device.

    Returns
    -------
    RefineResult
    """
    return refine_many(scene_field, library_field, A, B, [T0], config, device)[0]
