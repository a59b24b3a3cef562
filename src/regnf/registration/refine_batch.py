"""The refinement's batched problem: K hypotheses' parameters, samples and cached SDFs,
their loss and its linearisation (:mod:`regnf.registration.refinement` states the objective)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.core.threads import map_one_thread_each
from regnf.fields.field import Field
from regnf.fields.similarity import cross_matrices
from regnf.registration.irls import (
    barron_curvature,
    barron_weight,
    fit_kernel,
    segment_gram,
    segment_mean,
    segment_normal_equations,
    segment_sum,
)
from regnf.registration.linearisation import Linearisation
from regnf.registration.metrics import ObjectSymmetry, symmetric_angle
from regnf.registration.point_sets import NearestPoints, bounding_radius, unit_directions, voxel_new
from regnf.registration.refine_config import RefineConfig, reference_length
from regnf.registration.robust_loss import AdaptiveRobustLoss, general_rho, log_partition
from regnf.registration.transform import SimilarityTransform

T = TypeVar("T")
U = TypeVar("U")


def check_finite(values: torch.Tensor, what: str) -> None:
    """Refuse non-finite SDF ``values`` (any shape) that ``what`` returned, in one line."""
    bad = ~torch.isfinite(values)
    if bool(bad.any()):
        raise RegnfError(f"{what} returned non-finite SDF values at {int(bad.sum())} of "
                         f"{values.numel()} samples")


def _split_rows(columns: list[torch.Tensor | None], tensors: list[torch.Tensor]) -> list[tuple]:
    """Per tensor of ``tensors`` (stacked in that order), its rows of each column (None: None)."""
    sizes = [t.shape[0] for t in tensors]
    return list(zip(*(c.split(sizes) if c is not None else [None] * len(sizes) for c in columns)))


class HypothesisBatch:
    """K hypotheses' parameters, samples and cached SDFs, refined together."""

    def __init__(
        self,
        scene: Field,
        library: Field,
        A: torch.Tensor,
        B: torch.Tensor | None,
        inits: Sequence[SimilarityTransform],
        cfg: RefineConfig,
        workers: int = 1,
    ) -> None:
        self.scene, self.library, self.cfg = scene, library, cfg
        self.workers = workers
        # Where the scene's training views observed space (None: everywhere, e.g. analytic or
        # mesh-distilled scenes). Samples in unobserved space are no evidence either way.
        self.visibility = getattr(scene, "visibility", None) if cfg.use_visibility else None
        # The lookahead in scene units (grid voxels: their longest edge).
        self.lookahead = (cfg.visibility_lookahead * float(self.visibility.voxel_size.max())
                          if self.visibility is not None else 0.0)
        self.normal_B: torch.Tensor | None = None
        self.K = K = len(inits)
        dev, dt = A.device, A.dtype
        self.dtype = dt
        self.L = reference_length(library)
        self.rho = cfg.jitter_fraction * bounding_radius(A)  # scene units
        f64 = {"device": dev, "dtype": torch.float64}
        self.R0 = torch.stack([torch.as_tensor(np.asarray(T.R), **f64) for T in inits])
        self.t0 = torch.stack([torch.as_tensor(np.asarray(T.t).reshape(3), **f64) for T in inits])
        self.s0 = torch.tensor([float(T.s) for T in inits], **f64)
        # Centre of rotation and scaling: the centroid of T0(A) in the library frame.
        a_mean = A.double().mean(dim=0)
        self.a_mean = a_mean
        self.centre = self.s0[:, None] * (self.R0 @ a_mean) + self.t0
        self.w = torch.zeros(K, 3, requires_grad=True, **f64)
        self.log_s = torch.zeros(K, requires_grad=not cfg.fix_scale, **f64)
        self.tau = torch.zeros(K, 3, requires_grad=True, **f64)
        self.delta = torch.zeros(K, requires_grad=cfg.level_set_offset, **f64)
        self.kernel = AdaptiveRobustLoss(
            K, alpha_lo=cfg.alpha_lo, alpha_hi=cfg.alpha_hi, scale_init=cfg.kernel_scale_init
        ).to(dev)
        # One generator per hypothesis, all with the same seed: a hypothesis draws the same
        # jitter whether it is refined alone or in a batch.
        self.gens = [torch.Generator().manual_seed(int(cfg.seed)) for _ in range(K)]
        self.bidirectional = cfg.bidirectional
        # One tensor shared by every hypothesis until its resampling replaces it: what does not
        # move with the pose is computed once per distinct tensor (see _fixed_values).
        self.A = [A.detach()] * K
        self.B = [B.detach()] * K if self.bidirectional else []
        self.fixed_A: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}
        self.fixed_B: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, NearestPoints | None]] = {}
        self.active = list(range(K))
        self.stopped: dict[int, dict[str, torch.Tensor]] = {}
        self._rebuild()

    # -- pose -------------------------------------------------------------------------------
    def pose(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K, 3, 3) R, (K, 3) t, (K,) s in float64, differentiable in the parameters."""
        E = torch.linalg.matrix_exp(cross_matrices(self.w))
        e = torch.exp(self.log_s)
        R = E @ self.R0
        s = e * self.s0
        t = e[:, None] * (E @ (self.t0 - self.centre)[..., None])[..., 0] + self.centre + self.L * self.tau
        return R, t, s

    def offset(self) -> torch.Tensor:
        """(K,) level-set offset delta, *L*, bounded by ``max_offset``."""
        m = self.cfg.max_offset
        return m * torch.tanh(self.delta / m) if m > 0 else self.delta

    # -- samples ----------------------------------------------------------------------------
    def _rebuild(self) -> None:
        """Stack the active hypotheses' samples and the SDFs that do not move with the pose."""
        act = self.active
        dev = self.A[0].device
        self._fixed_values()
        self.gA = torch.cat([torch.full((self.A[k].shape[0],), i, dtype=torch.long, device=dev)
                             for i, k in enumerate(act)])
        self.xA = torch.cat([self.A[k] for k in act])
        self.nA = torch.tensor([float(self.A[k].shape[0]) for k in act], device=dev)
        self.sA = torch.cat([self.fixed_A[k][1] for k in act])  # S_scene(A): fixed in the scene frame
        self.wA = None if self.visibility is None else torch.cat([self.fixed_A[k][2] for k in act])
        if self.bidirectional:
            self.gB = torch.cat([torch.full((self.B[k].shape[0],), i, dtype=torch.long, device=dev)
                                 for i, k in enumerate(act)])
            self.yB = torch.cat([self.B[k] for k in act])
            self.nB = torch.tensor([float(self.B[k].shape[0]) for k in act], device=dev)
            self.sB = torch.cat([self.fixed_B[k][1] for k in act])  # S_lib(B): fixed in the library frame
            # Outward library normals at B, for the visibility lookup in front of them.
            self.normal_B = torch.cat([self.fixed_B[k][2] for k in act]) if self.lookahead > 0 else None
            self.nearest = [self.fixed_B[k][3] for k in act] if self.cfg.regulariser_weight > 0 else []

    def _both(self, scene_side: Callable[[], T], library_side: Callable[[], U]) -> tuple[T, U]:
        """``(scene_side(), library_side())``: the two directions' field queries are independent,
        so with ``workers`` > 1 they run side by side, each on one CPU thread
        (:func:`~regnf.core.threads.map_one_thread_each`): the bits of one after the other.

        Not under autograd (Adam's loss): the backward pass orders its nodes by a creation
        counter that torch keeps per thread, so a graph built on two threads sums the pose's
        gradient contributions in an order that depends on the scheduling
        (docs/decisions/registration-refinement.md)."""
        if self.workers < 2 or torch.is_grad_enabled():
            return scene_side(), library_side()
        a, b = map_one_thread_each(lambda call: call(), [scene_side, library_side], 2)
        return a, b

    def _fixed_values(self) -> None:
        """Evaluate, for the active hypotheses whose samples changed, what does not move with the
        pose: S_scene and the visibility at A; S_lib, the library normals and the nearest-sample
        lookup at B. Once per distinct sample tensor, in one field query per side: the field
        queries are the refinement's main cost (docs/decisions/implementation-speed.md)."""
        if not self.bidirectional:
            self._cache_per_tensor(self.A, self.fixed_A, self._fixed_at_A)
            return
        self._both(lambda: self._cache_per_tensor(self.A, self.fixed_A, self._fixed_at_A),
                   lambda: self._cache_per_tensor(self.B, self.fixed_B, self._fixed_at_B))

    def _cache_per_tensor(self, sets: list[torch.Tensor], cache: dict,
                          evaluate: Callable[[list[torch.Tensor]], list[tuple]]) -> None:
        """``cache[k] = (sets[k], *values)`` for each active hypothesis whose sample tensor the
        cache does not hold yet; ``evaluate`` gets each such tensor once and returns its values."""
        todo = {id(sets[k]): sets[k] for k in self.active if cache.get(k, (None,))[0] is not sets[k]}
        if not todo:
            return
        values = dict(zip(todo, evaluate(list(todo.values()))))
        for k in self.active:
            if id(sets[k]) in values:
                cache[k] = (sets[k], *values[id(sets[k])])

    def _fixed_at_A(self, tensors: list[torch.Tensor]) -> list[tuple]:
        """Per scene sample tensor: S_scene and the visibility (None without) at its points."""
        x = torch.cat(tensors)
        with torch.no_grad():
            sdf = self.scene.sdf(x)
            w = self._observed(x)
        check_finite(sdf, "the scene field (at A)")
        return _split_rows([sdf, w], tensors)

    def _fixed_at_B(self, tensors: list[torch.Tensor]) -> list[tuple]:
        """Per library sample tensor: S_lib, the outward normals (None without a lookahead) and
        the nearest-sample lookup (None without the regulariser)."""
        y = torch.cat(tensors)
        with torch.no_grad():
            sdf = self.library.sdf(y)
            normal = self.library.normal(y) if self.lookahead > 0 else None
        check_finite(sdf, "the library field (at B)")
        return [(*row, NearestPoints(t) if self.cfg.regulariser_weight > 0 else None)
                for row, t in zip(_split_rows([sdf, normal], tensors), tensors)]

    def resample(self) -> None:
        """Jitter every sample by rho; keep new ones on both surfaces, spaced apart, up to the cap."""
        cfg, L = self.cfg, self.L
        with torch.no_grad():
            R, t, s = (v.to(self.dtype) for v in self.pose())
            act = self.active
            idx = torch.tensor(act, device=R.device)
            R, t, s = R[idx], t[idx], s[idx]
            # Scene side: jitter A in the scene frame.
            cA = self.xA + self.rho * self._directions(self.A, self.xA)
            ssc = self.scene.sdf(cA)
            yc = s[self.gA, None] * torch.einsum("nij,nj->ni", R[self.gA], cA) + t[self.gA]
            slib = self.library.sdf(yc)
            res = (slib - s[self.gA] * ssc).abs()
            okA = ((s[self.gA] * ssc).abs() <= cfg.surface_tolerance * L) \
                & (slib.abs() <= cfg.surface_tolerance * L) & (res <= cfg.residual_tolerance * L)
            for i, k in enumerate(act):
                sel = okA & (self.gA == i)
                self.A[k] = self._grow(self.A[k], cA[sel], cfg.min_spacing * L / float(s[i]), k)
            if self.bidirectional:
                # Library side: jitter B in the library frame by the same physical distance.
                jit = (self.rho * s)[self.gB, None]
                cB = self.yB + jit * self._directions(self.B, self.yB)
                slib = self.library.sdf(cB)
                xc = torch.einsum("nji,nj->ni", R[self.gB], cB - t[self.gB]) / s[self.gB, None]
                ssc = s[self.gB] * self.scene.sdf(xc)
                okB = (slib.abs() <= cfg.surface_tolerance * L) & (ssc.abs() <= cfg.surface_tolerance * L) \
                    & ((ssc - slib).abs() <= cfg.residual_tolerance * L)
                for i, k in enumerate(act):
                    sel = okB & (self.gB == i)
                    self.B[k] = self._grow(self.B[k], cB[sel], cfg.min_spacing * L, k)
        self._rebuild()

    def _observed(self, x: torch.Tensor, normals: torch.Tensor | None = None) -> torch.Tensor | None:
        """(n,) observation weights in [0, 1] of surface samples ``x`` (n, 3, scene frame), read
        ``visibility_lookahead`` voxels out along their unit outward ``normals`` (n, 3, scene
        frame) where given; None: all observed."""
        if self.visibility is None:
            return None
        x = x.detach()
        if normals is not None:
            x = x + self.lookahead * normals.to(x.dtype)
        return self.visibility.observed(x).to(x.dtype)

    def _normals_B(self, R: torch.Tensor) -> torch.Tensor | None:
        """(n, 3) the library normals at B in the scene frame, by their hypotheses' rotations
        ``R`` (k, 3, 3, active ones); None without a lookahead."""
        if self.normal_B is None:
            return None
        return torch.einsum("nji,nj->ni", R[self.gB].to(self.normal_B.dtype), self.normal_B)

    def _directions(self, sets: list[torch.Tensor], like: torch.Tensor) -> torch.Tensor:
        """(n, 3) random unit jitter directions for the stacked active sets, per-hypothesis streams."""
        return torch.cat([unit_directions(sets[k].shape[0], self.gens[k], like) for k in self.active])

    def _grow(self, existing: torch.Tensor, cand: torch.Tensor, voxel: float, k: int) -> torch.Tensor:
        """``existing`` plus the candidates in voxels it leaves free, capped at max_samples."""
        room = self.cfg.max_samples - existing.shape[0]
        if room <= 0 or cand.shape[0] == 0:
            return existing
        cand = cand[voxel_new(existing, cand, voxel)]
        if cand.shape[0] > room:
            pick = torch.randperm(cand.shape[0], generator=self.gens[k])[:room].to(cand.device)
            cand = cand[pick]
        return torch.cat([existing, cand])

    # -- the objective ----------------------------------------------------------------------
    def evaluate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Loss per active hypothesis (k,) and a (k, 7) stats table (no grad): mean rA, mean rB,
        inlier count, residual count, regulariser, and the inlier count and residual count of A
        alone; residuals in library units, counts weighted by the visibility."""
        cfg, L = self.cfg, self.L
        R, t, s = self.pose()
        idx = torch.tensor(self.active, device=R.device)
        R, t, s = R[idx].to(self.dtype), t[idx].to(self.dtype), s[idx].to(self.dtype)
        gA = self.gA
        yA = s[gA, None] * torch.einsum("nij,nj->ni", R[gA], self.xA) + t[gA]
        d = (self.offset()[idx] * L).to(self.dtype)
        if self.bidirectional:
            gB = self.gB
            xB = torch.einsum("nji,nj->ni", R[gB], self.yB - t[gB]) / s[gB, None]
            scene_at_xB, lib_at_yA = self._both(lambda: self.scene.sdf(xB), lambda: self.library.sdf(yA))
        else:
            lib_at_yA = self.library.sdf(yA)
        rA = (lib_at_yA - s[gA] * self.sA - d[gA]).abs()
        k = len(self.active)
        if self.wA is None:
            loss = segment_mean(self.kernel(rA / L, idx[gA]), gA, self.nA)
            meanA = segment_mean(rA.detach(), gA, self.nA)
            inl = segment_mean((rA.detach() <= cfg.inlier_threshold * L).to(rA.dtype), gA, self.nA) * self.nA
            count = self.nA.clone()
        else:  # every sum weighted by how well the scene's views observed the sample's place
            wA = self.wA.to(rA.dtype)
            count = segment_sum(wA, gA, k)
            loss = segment_mean(wA * self.kernel(rA / L, idx[gA]), gA, count)
            meanA = segment_mean(wA * rA.detach(), gA, count)
            inl = segment_sum(wA * (rA.detach() <= cfg.inlier_threshold * L).to(rA.dtype), gA, k)
        meanB = torch.full_like(meanA, float("nan"))
        reg = torch.zeros_like(meanA)
        inl_A, count_A = inl.detach().clone(), count.detach().clone()
        if self.bidirectional:
            rB = (s[gB] * scene_at_xB + d[gB] - self.sB).abs()
            # In front of where the library sample lands in the scene, at this pose.
            wB = self._observed(xB, self._normals_B(R))
            if wB is None:
                loss = loss + segment_mean(self.kernel(rB / L, idx[gB]), gB, self.nB)
                meanB = segment_mean(rB.detach(), gB, self.nB)
                inl = inl + segment_mean((rB.detach() <= cfg.inlier_threshold * L).to(rB.dtype), gB,
                                          self.nB) * self.nB
                count = count + self.nB
            else:
                cB = segment_sum(wB, gB, k)
                loss = loss + segment_mean(wB * self.kernel(rB / L, idx[gB]), gB, cB)
                meanB = segment_mean(wB * rB.detach(), gB, cB)
                inl = inl + segment_sum(wB * (rB.detach() <= cfg.inlier_threshold * L).to(rB.dtype), gB, k)
                count = count + cB
            if cfg.regulariser_weight > 0:
                reg = torch.stack([self._regulariser(yA[gA == i], k) for i, k in enumerate(self.active)])
                loss = loss + cfg.regulariser_weight * reg
        stats = torch.stack([meanA, meanB, inl, count, reg.detach(), inl_A, count_A], dim=1)
        return loss, stats.detach()

    def _regulariser(self, yA: torch.Tensor, k: int) -> torch.Tensor:
        """Trimmed mean of squared distances (in L^2) from mapped scene samples to library samples."""
        B = self.B[k]
        nn = self.nearest[self.active.index(k)].query(yA).to(B.device)
        d2 = ((yA - B[nn]) ** 2).sum(dim=1) / self.L**2
        keep = max(1, math.floor(self.cfg.trim_fraction * d2.shape[0]))
        return torch.topk(d2, keep, largest=False, sorted=False).values.mean()

    # -- Levenberg-Marquardt -----------------------------------------------------------------
    def linearise(self) -> Linearisation:
        """Residuals, Jacobians and stats of the active hypotheses at their pose (no autograd
        through the pose: the fields' spatial gradients and the chain rule written out).

        The local update of a pose is ``y -> e^dl exp([dw]x) (y - c) + c + L dtau`` about the
        centre ``c``, and the offset delta (*L*) moves by ``d delta``; with ``v = T(x) - c``
        and ``g`` the library SDF gradient at ``T(x)``, the scene-side residual's derivatives
        are ``(v x g, g.v - s S_scene(x), L g, -L)``; for a library sample ``y``, with
        ``u = y - c`` and ``h = R grad S_scene(T^-1 y)``, ``(h x u, s S_scene - h.u, -L h, L)``.
        All divided by ``L`` (residuals in reference lengths)."""
        cfg, L = self.cfg, self.L
        act = self.active
        k = len(act)
        idx = torch.tensor(act, device=self.xA.device)
        with torch.no_grad():
            R, t, s = (v[idx] for v in self.pose())
            d = self.offset()[idx] * L
            c = self.centre[idx]
        thr = cfg.inlier_threshold * L
        gA = self.gA
        yA = s[gA, None] * torch.einsum("nij,nj->ni", R[gA], self.xA.double()) + t[gA]
        if self.bidirectional:
            gB = self.gB
            yB = self.yB.double()
            xB = torch.einsum("nji,nj->ni", R[gB], yB - t[gB]) / s[gB, None]
            at_xB, at_yA = self._both(lambda: self.scene.sdf_and_gradient(xB.to(self.dtype)),
                                      lambda: self.library.sdf_and_gradient(yA.to(self.dtype)))
        else:
            at_yA = self.library.sdf_and_gradient(yA.to(self.dtype))
        slib, glib = (v.double() for v in at_yA)
        check_finite(slib, "the library field (at the mapped scene samples)")
        ssA = s[gA] * self.sA.double()
        eA = slib - ssA - d[gA]
        v = yA - c[gA]
        JA = torch.cat([torch.linalg.cross(v, glib), ((glib * v).sum(1) - ssA)[:, None], L * glib,
                        torch.full_like(eA, -L)[:, None]], dim=1)
        wA = self.wA.double() if self.wA is not None else torch.ones_like(eA)
        cntA = segment_sum(wA, gA, k)
        rows = [(eA, JA, wA / cntA.clamp(min=1)[gA], gA)]
        stats = torch.zeros(k, 7, dtype=torch.float64, device=eA.device)
        stats[:, 0] = segment_sum(wA * eA.abs(), gA, k) / cntA.clamp(min=1)
        stats[:, 1] = float("nan")
        stats[:, 2] = stats[:, 5] = segment_sum(wA * (eA.abs() <= thr).double(), gA, k)
        stats[:, 3] = stats[:, 6] = cntA
        q = Jq = aq = gq = None
        if self.bidirectional:
            ssc, gsc = (v.double() for v in at_xB)
            check_finite(ssc, "the scene field (at the mapped library samples)")
            eB = s[gB] * ssc + d[gB] - self.sB.double()
            u = yB - c[gB]
            h = torch.einsum("nij,nj->ni", R[gB], gsc)
            JB = torch.cat([torch.linalg.cross(h, u), (s[gB] * ssc - (h * u).sum(1))[:, None], -L * h,
                            torch.full_like(eB, L)[:, None]], dim=1)
            wB = self._observed(xB, self._normals_B(R))
            wB = wB.double() if wB is not None else torch.ones_like(eB)
            cntB = segment_sum(wB, gB, k)
            rows.append((eB, JB, wB / cntB.clamp(min=1)[gB], gB))
            stats[:, 1] = segment_sum(wB * eB.abs(), gB, k) / cntB.clamp(min=1)
            stats[:, 2] += segment_sum(wB * (eB.abs() <= thr).double(), gB, k)
            stats[:, 3] += cntB
            if cfg.regulariser_weight > 0:
                q, Jq, aq, gq = self._linear_regulariser(yA, v, stats)
        if q is None:
            z = eA.new_zeros(0)
            q, Jq, aq, gq = z.view(0, 3), z.view(0, 3, 8), z, gA.new_zeros(0)
        x, J, a, group = (torch.cat(parts) for parts in zip(*rows))
        return Linearisation(x / L, J / L, a, group, q, Jq, aq, gq, stats)

    def _linear_regulariser(self, yA: torch.Tensor, v: torch.Tensor, stats: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The kept nearest-neighbour vectors of the regulariser, their Jacobians, weights and
        hypotheses; writes each hypothesis's trimmed mean into ``stats[:, 4]``."""
        L, parts = self.L, []
        for i, k in enumerate(self.active):
            sel = self.gA == i
            y = yA[sel]
            nn = self.nearest[i].query(y).to(y.device)
            diff = (y - self.B[k][nn].double()) / L
            d2 = (diff**2).sum(1)
            keep = max(1, math.floor(self.cfg.trim_fraction * d2.shape[0]))
            kept = torch.topk(d2, keep, largest=False, sorted=False).indices.sort().values
            stats[i, 4] = d2[kept].mean()
            vk = v[sel][kept]
            eye = torch.eye(3, dtype=vk.dtype, device=vk.device).expand(vk.shape[0], 3, 3)
            Jq = torch.cat([-cross_matrices(vk), vk[:, :, None], L * eye, vk.new_zeros(vk.shape[0], 3, 1)], dim=2) / L
            w = torch.full((keep,), self.cfg.regulariser_weight / keep, dtype=vk.dtype, device=vk.device)
            parts.append((diff[kept], Jq, w, torch.full((keep,), i, dtype=torch.long, device=vk.device)))
        return tuple(torch.cat(p) for p in zip(*parts))  # type: ignore[return-value]

    def objective(self, lin: Linearisation, alpha: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """(k,) the loss of :meth:`evaluate` from a linearisation, under the kernels (k,) given."""
        a, c = alpha[lin.group], scale[lin.group]
        nll = general_rho(lin.x, a, c) + torch.log(c) + log_partition(a)
        k = lin.stats.shape[0]
        return segment_sum(lin.a * nll, lin.group, k) + segment_sum(lin.aq * (lin.q**2).sum(1), lin.gq, k)

    def normal_equations(self, lin: Linearisation, alpha: torch.Tensor, scale: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(k, 8, 8) H with the loss's own curvature ``max(rho'', 0)``, (k, 8, 8) H of the
        reweighting (``rho'/x``, a majoriser: never a smaller curvature) and the (k, 8) gradient
        g (:mod:`regnf.registration.irls`)."""
        k = lin.stats.shape[0]
        a, c = alpha[lin.group], scale[lin.group]
        W = barron_weight(lin.x, a, c)
        H_irls, g = segment_normal_equations(lin.J, lin.x, lin.a * W, lin.group, k)
        H_newton = segment_gram(lin.J, lin.a * barron_curvature(lin.x, a, c), lin.group, k)
        if lin.q.shape[0]:
            Jq = lin.Jq.reshape(-1, 8)
            Hq, gq = segment_normal_equations(Jq, lin.q.reshape(-1), 2.0 * lin.aq.repeat_interleave(3),
                                              lin.gq.repeat_interleave(3), k)
            H_newton, H_irls, g = H_newton + Hq, H_irls + Hq, g + gq
        return H_newton, H_irls, g

    def fit_kernels(self, lin: Linearisation) -> tuple[torch.Tensor, torch.Tensor]:
        """(k,) alpha and c minimising the residuals' NLL; also set in ``self.kernel`` (reported)."""
        cfg = self.cfg
        alpha, scale = fit_kernel(lin.x, lin.a, lin.group, lin.stats.shape[0], cfg.alpha_lo, cfg.alpha_hi)
        self.kernel.assign(torch.tensor(self.active, device=alpha.device), alpha, scale)
        return alpha, scale

    def pose_state(self) -> tuple[torch.Tensor, ...]:
        """Clones of every pose parameter (for undoing a rejected step)."""
        return tuple(p.detach().clone() for p in (self.R0, self.t0, self.s0, self.w, self.log_s, self.tau,
                                                  self.delta))

    def restore_pose(self, state: tuple[torch.Tensor, ...], which: torch.Tensor) -> None:
        """Put the hypotheses ``which`` (K,) bool back to ``state``."""
        with torch.no_grad():
            for p, saved in zip((self.R0, self.t0, self.s0, self.w, self.log_s, self.tau, self.delta), state):
                p[which] = saved[which]

    def apply_step(self, step: torch.Tensor) -> None:
        """Move the active hypotheses by their local updates ``step`` (k, 8), re-basing each
        pose on the result: ``R0, t0, s0`` become the new pose and ``w, log_s, tau`` zero."""
        idx = torch.tensor(self.active, device=step.device)
        with torch.no_grad():
            R, t, s = (v[idx] for v in self.pose())
            c = self.centre[idx]
            E = torch.linalg.matrix_exp(cross_matrices(step[:, :3]))
            e = torch.exp(step[:, 3])
            self.R0[idx] = E @ R
            self.s0[idx] = e * s
            self.t0[idx] = e[:, None] * (E @ (t - c)[..., None])[..., 0] + c + self.L * step[:, 4:7]
            for p in (self.w, self.log_s, self.tau):
                p[idx] = 0.0
            # The offset moves directly, kept inside its bound (the latent is its tanh preimage).
            m = self.cfg.max_offset
            if m > 0:
                bounded = ((self.offset()[idx] + step[:, 7]) / m).clamp(-1 + 1e-9, 1 - 1e-9)
                self.delta[idx] = m * torch.atanh(bounded)
            else:
                self.delta[idx] = self.delta[idx] + step[:, 7]

    def offset_at_bound(self) -> torch.Tensor:
        """(k,) sign (+1, -1) of the active hypotheses' offsets that sit at their bound, else 0."""
        m = self.cfg.max_offset
        delta = self.offset()[torch.tensor(self.active, device=self.delta.device)].detach()
        if m <= 0:
            return torch.zeros_like(delta)
        return torch.sign(delta) * (delta.abs() >= m * (1 - 1e-6)).to(delta.dtype)

    # -- convergence ------------------------------------------------------------------------
    def pose_snapshot(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K, 3, 3) R, (K, 3) mapped centroid of A, (K,) s, detached."""
        with torch.no_grad():
            R, t, s = self.pose()
            c = s[:, None] * (R @ self.a_mean) + t
        return R, c, s

    def motion(self, previous: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
               symmetry: ObjectSymmetry | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K,) rotation (rad), motion of the mapped centroid of A (*L*) and relative scale change
        of every hypothesis since ``previous`` (a :meth:`pose_snapshot`).

        For an object with a continuous ``symmetry`` a turn about its axis is no motion: the
        rotation is measured modulo those turns and the centroid by its height along the axis
        and its distance from it (the axis through the library bounds' centre): a round object
        can turn about its axis at a constant loss for every iteration
        (docs/decisions/registration-refinement.md)."""
        R0, c0, s0 = previous
        R1, c1, s1 = self.pose_snapshot()
        cos = ((R0.transpose(1, 2) @ R1).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
        angle = torch.arccos(cos.clamp(-1.0, 1.0))
        moved = (c1 - c0).norm(dim=1) / self.L
        if symmetry is not None and symmetry.order == 0:
            a = torch.as_tensor(np.asarray(symmetry.axis), dtype=c0.dtype, device=c0.device)
            a = a / a.norm()
            p = self.library.bounds.to(c0).mean(dim=0)
            h0, h1 = (c0 - p) @ a, (c1 - p) @ a
            r0 = (c0 - p - h0[:, None] * a).norm(dim=1)
            r1 = (c1 - p - h1[:, None] * a).norm(dim=1)
            moved = torch.hypot(h1 - h0, r1 - r0) / self.L
            Q = (R1 @ R0.transpose(1, 2)).cpu().numpy()
            axis = np.asarray(symmetry.axis, dtype=np.float64)
            angle = torch.tensor([symmetric_angle(q, axis, 0) for q in Q], dtype=angle.dtype,
                                 device=angle.device)
        return angle, moved, (s1 / s0 - 1).abs()

    def converged(self, previous: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> list[int]:
        """Active hypotheses whose pose moved less than the tolerances since ``previous``."""
        cfg = self.cfg
        angle, moved, ds = self.motion(previous)
        ok = (angle < math.radians(cfg.convergence_rotation_deg)) & (moved < cfg.convergence_translation) \
            & (ds < cfg.convergence_scale)
        return [k for k in self.active if bool(ok[k])]

    # -- bookkeeping ------------------------------------------------------------------------
    def _leaves(self) -> list[torch.Tensor]:
        return [self.w, self.log_s, self.tau, self.delta, self.kernel.latent_alpha, self.kernel.latent_scale]

    def snapshot(self, k: int) -> None:
        """Hypothesis k is done: remember its parameters (Adam's momentum would move them)."""
        self.stopped[k] = {str(i): p.detach()[k].clone() for i, p in enumerate(self._leaves())}

    def deactivate(self, done: list[int]) -> None:
        """Stop querying the fields for the hypotheses in ``done``."""
        self.active = [a for a in self.active if a not in done]
        if self.active:
            self._rebuild()

    def restore_all(self) -> None:
        """Put every stopped hypothesis back at the parameters it stopped with; all active again."""
        with torch.no_grad():
            for k, saved in self.stopped.items():
                for i, p in enumerate(self._leaves()):
                    p[k] = saved[str(i)]
        self.stopped = {}
        self.active = list(range(self.K))
        self._rebuild()

    def transforms(self) -> list[SimilarityTransform]:
        with torch.no_grad():
            R, t, s = self.pose()
        R, t, s = R.cpu().numpy(), t.cpu().numpy(), s.cpu().numpy()
        return [SimilarityTransform(R[k].copy(), t[k].copy(), float(s[k])) for k in range(self.K)]


# -- public API ------------------------------------------------------------------------------
