"""RANSAC for a similarity from point correspondences, vectorised and the same on any machine.

The same estimator as Open3D's ``registration_ransac_based_on_correspondence`` with a
point-to-point estimation with scaling, an edge-length checker and a distance checker: draw
``ransac_n`` correspondences, fit the similarity in closed form (Umeyama), keep it if its
edges and its points agree, score it by the fraction of source points with a target point
within ``distance`` (then the RMSE of those), and stop once the best hypothesis's share of
agreeing correspondences says ``confidence`` has been reached.

Scoring is preemptive: every hypothesis of a batch that passes the checks is first scored on a
fixed, evenly spread subset of the source points (``preempt_points``), and only the
``preempt_keep`` best of the batch on every point. Most hypotheses that pass the checks are poor,
and a subset of a few hundred points ranks them as every point does, for a fraction of the
nearest-neighbour queries.

Why not Open3D's: Open3D 0.20 runs it on its thread pool, whose threads draw from one random
generator in the order they reach it (other hypotheses from run to run), so it had to run on
one thread (docs/decisions/registration-initialisation.md). Here the draws come
in batches from a seeded NumPy generator, every batch's checks and fits are array operations,
and the scoring's nearest-neighbour queries (SciPy, exact) split over the cores: the same
hypotheses on one core or many.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from regnf.core.errors import RegnfError


class RansacResult(NamedTuple):
    """The best hypothesis of one RANSAC run."""

    matrix: np.ndarray
    """(4, 4) float: the similarity mapping source points onto target points."""
    fitness: float
    """Fraction of source points with a target point within the distance."""
    inlier_rmse: float
    """RMSE of those points' distances."""
    iterations: int
    """Hypotheses drawn before the run stopped."""


def fit_similarities(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares similarities ``dst ~ s R src + t`` (Umeyama), one per batch row.

    Parameters
    ----------
    src, dst : (b, n, 3) float
        Corresponding points, ``n`` >= 3 a row.

    Returns
    -------
    R : (b, 3, 3) float
        Proper rotations.
    t : (b, 3) float
    s : (b,) float
        Scales (0 where ``src`` has no spread).
    """
    mu_s, mu_d = src.mean(axis=1), dst.mean(axis=1)
    X, Y = src - mu_s[:, None], dst - mu_d[:, None]
    cov = np.einsum("bni,bnj->bij", Y, X) / src.shape[1]
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    D = np.ones((len(src), 3))
    D[:, 2] = d
    R = np.einsum("bij,bj,bjk->bik", U, D, Vt)
    var = (X**2).sum(axis=2).mean(axis=1)
    s = np.where(var > 0, (S * D).sum(axis=1) / np.where(var > 0, var, 1.0), 0.0)
    t = mu_d - s[:, None] * np.einsum("bij,bj->bi", R, mu_s)
    return R, t, s


def draws_needed(share: float, ransac_n: int, confidence: float) -> float:
    """Draws after which an all-agreeing sample has come with probability ``confidence``, when
    a ``share`` of the matches agree (Open3D's stopping rule); ``inf`` for a share of 0."""
    p = share**ransac_n
    if p >= 1.0:
        return 0.0
    if p <= 0.0:
        return math.inf
    # log1p: for a tiny share, 1 - share**n rounds to 1 and the plain log divides by zero.
    return math.log1p(-confidence) / math.log1p(-p)


SCORE_POINTS = 1 << 20
"""Source points moved and looked up at once while scoring (hypotheses x points): bounds the
memory where many hypotheses pass the checks (clean matches), about 100 MB."""


def _scores(source: np.ndarray, tree: cKDTree, R: np.ndarray, t: np.ndarray, s: np.ndarray,
            distance: float, workers: int) -> tuple[np.ndarray, np.ndarray]:
    """For each hypothesis (R (h, 3, 3), t (h, 3), s (h,)): how many of the ``source`` points
    (n, 3) land within ``distance`` of a target point (h,) int, and the RMSE of those (h,)
    (inf where none); the hypotheses a chunk at a time, each chunk in one query."""
    step = max(1, SCORE_POINTS // len(source))
    counts, rmses = [], []
    for k in range(0, len(R), step):
        moved = s[k:k + step, None, None] * np.einsum("bij,nj->bni", R[k:k + step], source) + t[k:k + step, None]
        d, _ = tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=distance, workers=workers)
        d = d.reshape(len(moved), len(source))
        inlier = np.isfinite(d)
        count = inlier.sum(axis=1)
        rmse = np.sqrt(np.where(inlier, d**2, 0.0).sum(axis=1) / np.maximum(count, 1))
        counts.append(count)
        rmses.append(np.where(count > 0, rmse, math.inf))
    return np.concatenate(counts), np.concatenate(rmses)


def ransac_similarity(
    source: np.ndarray,
    target: np.ndarray,
    correspondences: np.ndarray,
    distance: float,
    ransac_n: int = 4,
    edge_length_ratio: float = 0.9,
    max_iterations: int = 100_000,
    confidence: float = 0.999,
    seed: int = 0,
    batch: int = 5000,
    target_tree: cKDTree | None = None,
    workers: int = 1,
    preempt_points: int = 256,
    preempt_keep: int = 4,
) -> RansacResult | None:
    """The best similarity of one RANSAC run over ``correspondences``.

    Parameters
    ----------
    source : (n, 3) float
    target : (m, 3) float
    correspondences : (k, 2) int
        Rows ``(i, j)``: ``source[i]`` matches ``target[j]``.
    distance : float
        Inlier distance: of the distance checker, the scoring and the stopping rule.
    ransac_n : int
        Correspondences a hypothesis is fitted to (>= 3).
    edge_length_ratio : float
        A hypothesis is kept only if every edge between its source points and the matching
        edge between its target points are within this ratio of each other (so the clouds
        must be at about the same scale: the initialisation pre-scales the scene's).
    max_iterations : int
        Hypotheses drawn at most.
    confidence : float
        Stop once the chance of having drawn an all-inlier sample, at the best hypothesis's
        share of agreeing correspondences, reaches this.
    seed : int
        Seed of the draws.
    batch : int
        Hypotheses drawn and checked at once; the stopping rule is applied between batches,
        so the result depends on it (fixed, not on the machine).
    target_tree : cKDTree, optional
        Of ``target`` (built here if not given).
    workers : int
        Threads of the scoring's nearest-neighbour queries (exact: any count gives the same).
    preempt_points : int
        Source points (every k-th) a batch's hypotheses are first scored on; 0: no preemption,
        every hypothesis is scored on every point.
    preempt_keep : int
        Hypotheses of a batch, the best on the subset, then scored on every point (>= 1).

    Returns
    -------
    RansacResult or None
        None when no hypothesis passed the checks (or fewer than ``ransac_n`` matches).
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    corr = np.asarray(correspondences, dtype=np.int64).reshape(-1, 2)
    if ransac_n < 3 or len(corr) < ransac_n or not distance > 0:
        return None
    if preempt_points < 0 or preempt_keep < 1:
        raise RegnfError(f"need preempt_points >= 0 and preempt_keep >= 1, got {preempt_points}, {preempt_keep}")
    tree = target_tree if target_tree is not None else cKDTree(target)
    stride = len(source) // preempt_points if preempt_points else 0
    subset = source[::stride] if stride > 1 else None  # None: the subset would be every point
    rng = np.random.default_rng(seed)
    cs, ct = source[corr[:, 0]], target[corr[:, 1]]
    iu, ju = np.triu_indices(ransac_n, 1)
    best: tuple[float, float] = (0.0, math.inf)  # (fitness, rmse)
    best_matrix: np.ndarray | None = None
    limit, drawn = max_iterations, 0
    while drawn < limit:
        b = min(batch, limit - drawn)
        drawn += b
        pick = rng.integers(0, len(corr), size=(b, ransac_n))
        ps, pt = cs[pick], ct[pick]  # (b, ransac_n, 3)
        ds = np.linalg.norm(ps[:, iu] - ps[:, ju], axis=2)
        dt = np.linalg.norm(pt[:, iu] - pt[:, ju], axis=2)
        keep = ((ds >= dt * edge_length_ratio) & (dt >= ds * edge_length_ratio)).all(axis=1)
        if not keep.any():
            continue
        ps, pt = ps[keep], pt[keep]
        R, t, s = fit_similarities(ps, pt)
        mapped = s[:, None, None] * np.einsum("bij,bnj->bni", R, ps) + t[:, None]
        agree = (np.linalg.norm(mapped - pt, axis=2) <= distance).all(axis=1) & (s > 0)
        if not agree.any():
            continue
        R, t, s = R[agree], t[agree], s[agree]
        if subset is not None and len(R) > preempt_keep:
            c_sub, r_sub = _scores(subset, tree, R, t, s, distance, workers)
            # In draw order again, so that ties on every point still go to the earlier draw.
            top = np.sort(np.lexsort((r_sub, -c_sub))[:preempt_keep])
            R, t, s = R[top], t[top], s[top]
        count, rmse = _scores(source, tree, R, t, s, distance, workers)
        fitness = count / len(source)
        order = np.lexsort((rmse, -fitness))  # best first; ties keep the draw order
        i = int(order[0])
        if count[i] == 0 or (fitness[i], -rmse[i]) <= (best[0], -best[1]):
            continue
        best = (float(fitness[i]), float(rmse[i]))
        best_matrix = np.eye(4)
        best_matrix[:3, :3] = s[i] * R[i]
        best_matrix[:3, 3] = t[i]
        # Stop once an all-inlier draw is likely enough at this hypothesis's share of
        # agreeing correspondences (Open3D's rule).
        share = float((np.linalg.norm(s[i] * cs @ R[i].T + t[i] - ct, axis=1) < distance).mean())
        needed = draws_needed(share, ransac_n, confidence)
        if needed < limit:
            limit = max(drawn, math.ceil(needed))
    if best_matrix is None:
        return None
    return RansacResult(best_matrix, best[0], best[1], drawn)
