"""The refinement's two optimisers on a :class:`~regnf.registration.refine_batch.HypothesisBatch`:
the paper's Adam, and Levenberg-Marquardt (:mod:`regnf.registration.refinement`)."""

from __future__ import annotations

import math

import numpy as np
import torch

from regnf.registration.irls import damped_step
from regnf.registration.linearisation import Linearisation
from regnf.registration.metrics import ObjectSymmetry, same_pose
from regnf.registration.refine_batch import HypothesisBatch, check_finite


def _adam(batch: HypothesisBatch) -> torch.optim.Adam:
    """Adam over the batch's pose, offset and kernel parameters, at the configured rates.

    Made only when Adam refines: torch's optimisers import its compiler (torch._dynamo) on
    first use, a cost to the first registration in a process otherwise
    (docs/decisions/implementation-speed.md).
    """
    cfg = batch.cfg
    groups = [
        {"params": [batch.w], "lr": cfg.lr_rotation},
        {"params": [batch.tau], "lr": cfg.lr_translation},
        {"params": list(batch.kernel.parameters()), "lr": cfg.lr_kernel},
    ]
    if not cfg.fix_scale:
        groups.append({"params": [batch.log_s], "lr": cfg.lr_scale})
    if cfg.level_set_offset:
        groups.append({"params": [batch.delta], "lr": cfg.lr_offset})
    return torch.optim.Adam(groups)


def run_adam(batch: HypothesisBatch, histories: list[list[dict]], steps: list[int]) -> None:
    """The paper's refinement: Adam on the pose, the offset and the kernel together."""
    cfg = batch.cfg
    opt = _adam(batch)
    previous = batch.pose_snapshot()
    for it in range(cfg.max_iterations):
        if not batch.active:
            break
        if it > 0 and cfg.resample_every > 0 and it % cfg.resample_every == 0:
            batch.resample()
        loss, stats = batch.evaluate()
        check_finite(loss.detach(), f"the refinement loss (iteration {it})")
        opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        _record(batch, histories, it, loss.detach(), stats)
        # Early stop on the transform just evaluated: it is the one returned, no step after.
        done = [k for i, k in enumerate(batch.active) if float(stats[i, 0]) < cfg.early_stop_residual * batch.L]
        if cfg.convergence_window > 0 and it % cfg.convergence_window == 0:
            done += [k for k in batch.converged(previous) if k not in done] if it > 0 else []
            previous = batch.pose_snapshot()
        if cfg.prune_after > 0 and it == cfg.prune_after:
            done += [k for k in _trailing(batch, stats) if k not in done]
        for k in done:
            batch.snapshot(k)
        opt.step()
        for k in batch.active:
            if k not in done:
                steps[k] += 1
        if done:
            batch.deactivate(done)


def _trailing(batch: HypothesisBatch, stats: torch.Tensor, best: float = float("-inf")) -> list[int]:
    """Active hypotheses whose inlier fraction trails the best by more than ``prune_margin``
    (the best of the active ones and ``best``, that of the stopped ones)."""
    frac = (stats[:, 2] / stats[:, 3].clamp(min=1)).tolist()
    if len(batch.active) + (best > float("-inf")) < 2:
        return []
    best = max(frac + [best])
    return [k for i, k in enumerate(batch.active) if frac[i] < best - batch.cfg.prune_margin]


def _merged(batch: HypothesisBatch, fraction: list[float], symmetry: ObjectSymmetry | None) -> list[int]:
    """Active hypotheses within the ``lm_merge_*`` tolerances of one with a higher inlier
    ``fraction`` (K,) (the latest of each hypothesis, running or stopped; ties: the earlier
    one stays)."""
    cfg = batch.cfg
    if cfg.lm_merge_rotation_deg <= 0 or batch.K < 2:
        return []
    R, c, s = (v.detach().cpu().numpy() for v in batch.pose_snapshot())
    limit = math.radians(cfg.lm_merge_rotation_deg)
    return [k for k in batch.active
            if any(same_pose(R[k], R[j], float(s[k]), float(s[j]), float(np.linalg.norm(c[k] - c[j])),
                             symmetry, limit, cfg.lm_merge_scale, cfg.lm_merge_shift * batch.L)
                   for j in range(batch.K) if j != k and (fraction[j], -j) > (fraction[k], -k))]


def run_lm(batch: HypothesisBatch, histories: list[list[dict]], steps: list[int],
            symmetry: ObjectSymmetry | None = None) -> None:
    """Levenberg-Marquardt on the iteratively reweighted problem (:mod:`regnf.registration.irls`).

    Each iteration fits every active hypothesis's kernel (alpha, c) to its residuals, solves the
    damped normal equations for a local update, and keeps the update where it lowers that
    hypothesis's loss (same kernel) by a fair share of what the model predicted, else undoes it
    and raises the damping. A hypothesis stops when a step would move it less than
    ``lm_step_tolerance``, when no damping finds a lower loss, on the paper's residual stop, or
    when pruned.
    """
    cfg, K = batch.cfg, batch.K
    dev = batch.xA.device
    free = torch.tensor([True] * 3 + [not cfg.fix_scale] + [True] * 3 + [cfg.level_set_offset], device=dev)
    mu = torch.full((K,), cfg.lm_damping, dtype=torch.float64, device=dev)
    nu = torch.full((K,), 2.0, dtype=torch.float64, device=dev)
    cautious = torch.zeros((K,), dtype=torch.bool, device=dev)  # use the majoriser
    fraction = torch.full((K,), -1.0, dtype=torch.float64, device=dev)  # latest inlier fraction
    lin: Linearisation | None = None
    for it in range(cfg.lm_max_iterations):
        if not batch.active:
            break
        if it > 0 and cfg.lm_resample_every > 0 and it % cfg.lm_resample_every == 0 \
                and it // cfg.lm_resample_every <= cfg.lm_resamples:
            batch.resample()
            lin = None
        if lin is None:
            lin = batch.linearise()
        alpha, scale = batch.fit_kernels(lin)
        loss = batch.objective(lin, alpha, scale)
        check_finite(loss, f"the refinement loss (iteration {it})")
        _record(batch, histories, it, loss, lin.stats)
        act = torch.tensor(batch.active, device=dev)
        done = [k for i, k in enumerate(batch.active)
                if float(lin.stats[i, 0]) < cfg.early_stop_residual * batch.L]
        fraction[act] = lin.stats[:, 2] / lin.stats[:, 3].clamp(min=1)
        if cfg.lm_prune_after > 0 and it == cfg.lm_prune_after:
            stopped = [float(fraction[k]) for k in range(K) if k not in batch.active and fraction[k] >= 0]
            done += [k for k in _trailing(batch, lin.stats, max(stopped, default=float("-inf")))
                     if k not in done]
        if cfg.lm_prune_after > 0 and it >= cfg.lm_prune_after:
            done += [k for k in _merged(batch, fraction.tolist(), symmetry) if k not in done]
        H_newton, H_irls, g = batch.normal_equations(lin, alpha, scale)
        H = torch.where(cautious[act][:, None, None], H_irls, H_newton)
        state, before = batch.pose_state(), batch.pose_snapshot()
        offset_before = batch.offset()[act].detach().clone()
        step = damped_step(H, g, mu[act], free)
        # An offset at its bound that the step would push further out stays there (active set).
        held = batch.offset_at_bound() * step[:, 7] > 0
        if bool(held.any()):
            pinned = free.expand(len(batch.active), -1).clone()
            pinned[held, 7] = False
            step = torch.where(held[:, None], damped_step(H, g, mu[act], pinned), step)
        batch.apply_step(step)
        trial = batch.linearise()
        # Gain ratio: the loss's decrease over the decrease the quadratic model predicted.
        predicted = -((g * step).sum(1) + 0.5 * torch.einsum("ki,kij,kj->k", step, H, step))
        gain = (loss - batch.objective(trial, alpha, scale)) / predicted.clamp(min=1e-300)
        accepted = (gain > 1e-3) & (predicted > 0)
        # The step's size, accepted or not: a step this small that does not help is a minimum.
        angle, moved, ds = batch.motion(before, symmetry)
        tol = cfg.lm_step_tolerance
        # The offset is part of the step: a step that only moves the offset is not small.
        small = (angle < tol) & (moved < tol) & (ds < tol)
        small[act] &= (batch.offset()[act].detach() - offset_before).abs() < tol
        rejected = torch.zeros(K, dtype=torch.bool, device=dev)
        rejected[act] = ~accepted
        batch.restore_pose(state, rejected)
        # Nielsen's damping update: shrink by up to 3 after a good step, grow ever faster
        # after successive bad ones; the first bad Newton step only switches to the majoriser.
        retry = ~accepted & ~cautious[act]
        grow = ~accepted & cautious[act]
        shrink = torch.clamp(1 - (2 * gain - 1) ** 3, min=1 / 3)
        mu[act] = torch.where(accepted, (mu[act] * shrink).clamp(min=1e-12),
                              torch.where(grow, mu[act] * nu[act], mu[act]))
        nu[act] = torch.where(accepted, torch.full_like(nu[act], 2.0), torch.where(grow, nu[act] * 2, nu[act]))
        cautious[act] = retry
        lin = lin.merge(trial, accepted)
        for k in batch.active:
            steps[k] += 1
            if k not in done and (bool(small[k]) or float(mu[k]) > 1e8):
                done.append(k)
        if done:
            keep = torch.tensor([k not in done for k in batch.active], device=dev)
            batch.deactivate(done)
            lin = lin.select(keep) if batch.active else None


def _record(batch: HypothesisBatch, histories: list[list[dict]], it: int, loss: torch.Tensor,
            stats: torch.Tensor) -> None:
    idx = torch.tensor(batch.active, device=loss.device)
    with torch.no_grad():
        s = (torch.exp(batch.log_s) * batch.s0)[idx]
        table = torch.stack([loss.double(), stats[:, 0].double(), stats[:, 1].double(),
                             batch.kernel.alpha[idx].double(), batch.kernel.scale[idx].double(), s,
                             stats[:, 4].double(), batch.offset()[idx].double()], dim=1).cpu().numpy()
    for i, k in enumerate(batch.active):
        row = table[i]
        histories[k].append({
            "iteration": it, "loss": float(row[0]), "mean_residual_A": float(row[1]),
            "mean_residual_B": float(row[2]), "alpha": float(row[3]), "c": float(row[4]),
            "s": float(row[5]), "regulariser": float(row[6]), "offset": float(row[7]),
            "n_A": int(batch.A[k].shape[0]), "n_B": int(batch.B[k].shape[0]) if batch.B else 0,
        })
