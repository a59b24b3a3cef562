"""Initial registration: FPFH + RANSAC + ICP with scale (docs/design.md section 1.3).

Input: surface samples of the scene (inside the proposal) and of the library object, each in
its own FIELD frame. Output: up to ``top_k`` hypotheses ``T: scene field -> library field``,
distinct in rotation, best first.

Procedure:

1. Centre both clouds and pre-estimate the scale ratio (RMS radius or a radius percentile,
   on voxel-thinned clouds so that sampling density does not bias it); express both clouds in
   a normalised frame where the library is unit-size (largest AABB side 1) and the scene is
   pre-scaled to match. Feature radii then mean the same in both clouds (the authors'
   RANSAC assumed scale 1 between fields of different scales).
2. Voxel-downsample (*paper*: 0.025 of a unit-size object), FPFH (normal radius 2 voxels,
   feature radius 5 voxels, 100 neighbours). The fields' own (outward, consistent) normals
   are used by default instead of re-estimated (sign-ambiguous) ones.
3. RANSAC on nearest-neighbour feature matches (:mod:`regnf.registration.ransac`, the
   estimator of Open3D's ``registration_ransac_based_on_correspondence``, vectorised):
   point-to-point estimation WITH scaling, ``ransac_n`` 4, edge-length and distance checkers,
   and explicit criteria (100 000 iterations, confidence 0.999; the authors' (4 000 000, 500)
   is read by Open3D as confidence 1, so all 4 million iterations always ran). Run 0 uses all
   matches; each later run drops the matches that
   an earlier hypothesis explains, so that it finds the next-best mode (a symmetric object's
   other poses), with its own seed.
4. With an upright prior (:mod:`regnf.registration.upright`), evenly spaced yaw starts over one
   period of the object's symmetry join RANSAC's results: they need no features, so an object
   seen from one side, whose features match poorly, still gets a start near its true pose.
5. ICP refinement of every start, point-to-point with scaling or point-to-plane: first on
   clouds thinned to ``icp_coarse_voxels``, then, for the ``candidates`` distinct coarse
   results only, on the full (normalised) clouds; rank by fitness then inlier RMSE; keep
   hypotheses distinct in turn (modulo the object's symmetry), scale or place; undo the
   normalisation.
   :func:`regnf.registration.pipeline.initialise` then screens them by SDF evidence
   (:mod:`regnf.registration.screening`).

Determinism: every RANSAC run draws from its own seeded NumPy generator, and the
initialisation runs with torch and Open3D on one thread a call
(:func:`regnf.core.threads.one_thread`): the same hypotheses on any machine.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from regnf.core.errors import RegnfError
from regnf.core.threads import map_one_thread_each, one_thread
from regnf.registration.init_config import InitConfig

from .metrics import ObjectSymmetry, same_pose
from .ransac import ransac_similarity
from .sampling import SurfaceSamples
from .transform import SimilarityTransform
from .upright import UprightPrior, yaw_starts

reg = o3d.pipelines.registration


class Hypothesis(NamedTuple):
    """One initial registration."""

    transform: SimilarityTransform
    """Scene field frame -> library field frame."""
    fitness: float
    """Fraction of scene samples with a library sample within the ICP distance."""
    inlier_rmse: float
    """RMSE of those inlier distances, in LIBRARY field units."""


class _Prepared(NamedTuple):
    """Both clouds in the normalised frame, with features."""

    src: o3d.geometry.PointCloud  # full scene cloud (normalised)
    tgt: o3d.geometry.PointCloud  # full library cloud (normalised)
    src_down: o3d.geometry.PointCloud
    tgt_down: o3d.geometry.PointCloud
    src_fpfh: o3d.pipelines.registration.Feature
    tgt_fpfh: o3d.pipelines.registration.Feature
    scene_to_norm: SimilarityTransform
    library_to_norm: SimilarityTransform
    scale0: float  # pre-estimated scale, scene -> library


def _check_samples(s: SurfaceSamples, what: str) -> None:
    P, N = np.asarray(s.points), np.asarray(s.normals)
    if P.ndim != 2 or P.shape[1] != 3 or N.shape != P.shape:
        raise RegnfError(f"{what} samples: points and normals must both be (n, 3)")
    if len(P) < 10:
        raise RegnfError(f"{what} samples: {len(P)} points are too few to register (need >= 10)")
    if not (np.isfinite(P).all() and np.isfinite(N).all()):
        raise RegnfError(f"{what} samples contain non-finite values")


def _cloud(points: np.ndarray, normals: np.ndarray | None) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pc


def _thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel (the first), so statistics follow area, not ray density."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def _centre_and_radius(points: np.ndarray, config: InitConfig) -> tuple[np.ndarray, float]:
    """Centroid (3,) and radius (RMS or percentile) of a density-thinned cloud."""
    c = points.mean(axis=0)
    rms = float(np.sqrt(((points - c) ** 2).sum(axis=1).mean()))
    thin = _thin(points, 0.02 * rms) if rms > 0 else points
    c = thin.mean(axis=0)
    d = np.linalg.norm(thin - c, axis=1)
    if config.scale_estimate == "rms":
        r = float(np.sqrt((d**2).mean()))
    else:
        r = float(np.percentile(d, config.scale_percentile))
    if not r > 0:
        raise RegnfError("a sample cloud has zero spread (all points coincide)")
    return c, r


def _prepare(scene: SurfaceSamples, library: SurfaceSamples, config: InitConfig,
             workers: int = 1) -> _Prepared:
    """Both clouds in the normalised frame, thinned to the voxel, with normals and FPFH
    features; the two clouds side by side on ``workers`` threads (Open3D's calls let go of the
    interpreter lock, and each runs on its calling thread under ``one_thread``)."""
    _check_samples(scene, "scene")
    _check_samples(library, "library")
    Ps, Pl = np.asarray(scene.points, np.float64), np.asarray(library.points, np.float64)
    c_s, r_s = _centre_and_radius(Ps, config)
    c_l, r_l = _centre_and_radius(Pl, config)
    size = float((Pl.max(axis=0) - Pl.min(axis=0)).max())  # library frame is canonical-aligned
    scale0 = r_l / r_s
    # Normalised frame: library unit-size, scene pre-scaled to the library's scale.
    lib_n = SimilarityTransform(np.eye(3), -c_l / size, 1.0 / size)
    scn_n = SimilarityTransform(np.eye(3), -c_s * scale0 / size, scale0 / size)
    v = config.voxel_size
    use_n = config.use_field_normals
    src = _cloud(scn_n.apply(Ps), np.asarray(scene.normals) if use_n else None)
    tgt = _cloud(lib_n.apply(Pl), np.asarray(library.normals) if use_n else None)

    def features(pc: o3d.geometry.PointCloud) -> tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature]:
        down = pc.voxel_down_sample(v)
        if use_n:
            down.normalize_normals()  # voxel averaging shortens them
        else:
            down.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(
                    radius=config.normal_radius_voxels * v, max_nn=config.normal_max_nn
                )
            )
        if len(down.points) < config.ransac_n:
            raise RegnfError(
                f"only {len(down.points)} points left after the {v} voxel downsampling; "
                "the sample clouds are too small to register"
            )
        return down, reg.compute_fpfh_feature(
            down,
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=config.feature_radius_voxels * v, max_nn=config.feature_max_nn
            ),
        )

    (src_down, src_feat), (tgt_down, tgt_feat) = map_one_thread_each(features, [src, tgt], workers)
    if not use_n:
        tgt.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=config.normal_radius_voxels * v, max_nn=config.normal_max_nn
            )
        )
    return _Prepared(src, tgt, src_down, tgt_down, src_feat, tgt_feat, scn_n, lib_n, scale0)


def _feature_matches(prep: _Prepared, mutual: bool, workers: int = 1) -> np.ndarray:
    """(m, 2) int32: each scene point's nearest library point in FPFH space.

    The queries are split over ``workers`` threads (SciPy's): each point's nearest neighbour is
    exact, so the matches are the same on any count (in 33 dimensions the k-d tree is slow;
    docs/decisions/registration-initialisation.md)."""

    Fs, Fl = np.asarray(prep.src_fpfh.data).T, np.asarray(prep.tgt_fpfh.data).T
    j = cKDTree(Fl).query(Fs, k=1, workers=workers)[1]
    i = np.arange(len(Fs))
    if mutual:
        back = cKDTree(Fs).query(Fl, k=1, workers=workers)[1]
        keep = back[j] == i
        i, j = i[keep], j[keep]
    return np.stack([i, j], axis=1).astype(np.int32)


def _to_field(prep: _Prepared, M_norm: np.ndarray) -> SimilarityTransform:
    """Normalised-frame 4x4 -> scene field -> library field transform."""
    T_norm = SimilarityTransform.from_matrix(M_norm)
    return prep.library_to_norm.inverse().compose(T_norm).compose(prep.scene_to_norm)


def _to_norm(prep: _Prepared, T: SimilarityTransform) -> np.ndarray:
    """Scene field -> library field transform -> normalised-frame 4x4 (inverse of _to_field)."""
    return prep.library_to_norm.compose(T).compose(prep.scene_to_norm.inverse()).matrix()


def _evaluate(prep: _Prepared, M_norm: np.ndarray, config: InitConfig) -> tuple[float, float]:
    res = reg.evaluate_registration(
        prep.src, prep.tgt, config.icp_distance_voxels * config.voxel_size, M_norm
    )
    size = 1.0 / prep.library_to_norm.s
    return float(res.fitness), float(res.inlier_rmse) * size


def _icp(src: o3d.geometry.PointCloud, tgt: o3d.geometry.PointCloud, M0: np.ndarray,
         distance: float, relative_change: float, config: InitConfig) -> np.ndarray:
    """ICP of ``src`` onto ``tgt`` from the normalised-frame 4x4 ``M0``; the 4x4 result."""
    if config.icp_method == "point_to_point":
        est = reg.TransformationEstimationPointToPoint(with_scaling=True)
    else:
        est = reg.TransformationEstimationPointToPlane()
    res = reg.registration_icp(
        src, tgt, distance, M0, est,
        reg.ICPConvergenceCriteria(
            relative_fitness=relative_change,
            relative_rmse=relative_change,
            max_iteration=config.icp_max_iteration,
        ),
    )
    return np.asarray(res.transformation)


def _similarity_or_none(M: np.ndarray) -> np.ndarray | None:
    """``M`` re-projected onto a proper similarity, or None if it is degenerate."""
    A = M[:3, :3]
    if not np.isfinite(M).all() or np.linalg.det(A) <= 0:
        return None
    U, S, Vt = np.linalg.svd(A)
    out = M.copy()
    out[:3, :3] = (U @ Vt) * S.mean()
    return out


def _ransac_runs(prep: _Prepared, config: InitConfig, workers: int = 1) -> list[np.ndarray]:
    """Normalised-frame 4x4 results of the sequential RANSAC runs (before ICP)."""
    dist = config.ransac_distance_voxels * config.voxel_size
    corr = _feature_matches(prep, config.mutual_filter, workers)
    Ps = np.asarray(prep.src_down.points)
    Pl = np.asarray(prep.tgt_down.points)
    tree = cKDTree(Pl)
    out = []
    for r in range(config.ransac_runs):
        if len(corr) < max(config.min_matches, config.ransac_n):
            break
        res = ransac_similarity(
            Ps, Pl, corr, dist, config.ransac_n, config.edge_length_ratio,
            config.ransac_max_iteration if r == 0 else config.ransac_followup_iteration,
            config.ransac_confidence, seed=config.seed + r, target_tree=tree, workers=workers,
        )
        if res is None:
            break  # RANSAC found nothing valid in the remaining matches
        M = res.matrix
        out.append(M)
        # Drop the matches this hypothesis explains, so that the next run finds another mode.
        mapped = Ps[corr[:, 0]] @ M[:3, :3].T + M[:3, 3]
        corr = corr[np.linalg.norm(mapped - Pl[corr[:, 1]], axis=1) > dist]
    return out


def _yaw_period(symmetry: ObjectSymmetry | None, upright: UprightPrior) -> float:
    """The turn about the up axis after which the object looks the same again, radians: 2 pi
    without a symmetry about that axis, 2 pi / k for a k-fold one, 0 for a continuous one."""
    if symmetry is None or symmetry.order == 1:
        return 2.0 * np.pi
    a = np.asarray(symmetry.axis, dtype=np.float64)
    u = np.asarray(upright.library_up, dtype=np.float64)
    if abs(a @ u) < 0.999 * np.linalg.norm(a) * np.linalg.norm(u):
        return 2.0 * np.pi  # a symmetry about another axis says nothing about the yaw
    return 0.0 if symmetry.order == 0 else 2.0 * np.pi / symmetry.order


def _select(cands: list[Hypothesis], config: InitConfig,
            symmetry: ObjectSymmetry | None = None, limit: int | None = None,
            centre: np.ndarray | None = None, size: float = 1.0) -> list[Hypothesis]:
    """Best first (fitness, then RMSE), pairwise distinct poses.

    Two hypotheses are one pose when their rotations are less than ``min_rotation_deg`` apart
    modulo the object's symmetry (two poses a symmetry maps onto each other are one, else a
    symmetric object refines the same pose several times), their scales differ by less
    than ``min_scale_change`` and they put the library's ``centre`` (3,) (library frame, on its
    symmetry axis) less than ``min_shift`` of the library's ``size`` apart in the scene.
    Rotation alone is not enough: ICP with scaling can shrink or grow a start onto part of
    an object seen from one side, and that result, with the best fitness, then hides every
    start of the same turn at the right size (docs/decisions/registration-initialisation.md).
    """
    cands = sorted(cands, key=lambda h: (-h.fitness, h.inlier_rmse))
    kept: list[Hypothesis] = []
    min_angle = np.radians(config.min_rotation_deg)
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)

    def same(h: Hypothesis, k: Hypothesis) -> bool:
        shift = h.transform.inverse().apply(c[None])[0] - k.transform.inverse().apply(c[None])[0]
        return same_pose(h.transform.R, k.transform.R, h.transform.s, k.transform.s,
                         float(np.linalg.norm(shift)) * h.transform.s, symmetry, min_angle,
                         config.min_scale_change, config.min_shift * size)

    for h in cands:
        if len(kept) == (limit or config.top_k):
            break
        if not any(same(h, k) for k in kept):
            kept.append(h)
    return kept


# One thread: Open3D's parallel ICP gives other last bits on other thread counts
# (see regnf.core.threads.one_thread), and a registration must not depend on the machine.
@one_thread()
def initial_hypotheses(
    scene: SurfaceSamples, library: SurfaceSamples, config: InitConfig = InitConfig(),
    symmetry: ObjectSymmetry | None = None, upright: UprightPrior | None = None,
    limit: int | None = None, workers: int = 1,
) -> list[Hypothesis]:
    """Up to ``top_k`` initial transforms scene field -> library field, best first.

    Parameters
    ----------
    scene : SurfaceSamples
        Samples of the scene field inside the proposal (scene field frame).
    library : SurfaceSamples
        Samples of the library field (library field frame).
    config : InitConfig
    symmetry : ObjectSymmetry, optional
        The library object's symmetry: hypotheses it maps onto each other count as one.
    upright : UprightPrior, optional
        The object stands as its library model does: ``config.upright_yaws`` yaw starts join
        RANSAC's (:func:`regnf.registration.upright.yaw_starts`).
    limit : int, optional
        Hypotheses returned at most (default ``config.top_k``).
    workers : int
        Threads for the two clouds' features, the FPFH matching and the ICP starts, side by
        side, and RANSAC's scoring queries (the same hypotheses on any count: each Open3D call
        runs on one thread, RANSAC's draws come from one seeded generator).

    Returns
    -------
    list of Hypothesis
        Non-empty, sorted by fitness (then inlier RMSE), pairwise distinct in rotation.

    Raises
    ------
    ValueError
        For malformed or too small sample sets, or when no run produced a usable transform.
    """
    prep = _prepare(scene, library, config, workers)
    yaws: list[np.ndarray] = []
    if upright is not None and config.upright_yaws > 0:
        starts = yaw_starts(scene.points, library.points, upright, config.upright_yaws,
                            _yaw_period(symmetry, upright))
        yaws = [_to_norm(prep, T) for T in starts]
    lib = np.asarray(library.points, dtype=np.float64)
    lo, hi = lib.min(axis=0), lib.max(axis=0)
    centre, size = 0.5 * (lo + hi), float((hi - lo).max())
    v = config.voxel_size
    fine_distance = config.icp_distance_voxels * v

    def fine(M0: np.ndarray) -> np.ndarray:
        return _icp(prep.src, prep.tgt, M0, fine_distance, config.icp_relative_change, config)

    first = fine
    if config.icp_coarse_voxels > 0:
        cv = config.icp_coarse_voxels * v
        src, tgt = prep.src.voxel_down_sample(cv), prep.tgt.voxel_down_sample(cv)

        def first(M0: np.ndarray) -> np.ndarray:
            return _icp(src, tgt, M0, cv, config.icp_coarse_relative_change, config)

    # The yaw starts need no RANSAC: with two workers their first ICP begins on another thread
    # while RANSAC runs on this one, and this one joins in on the starts left when RANSAC's
    # own are done (Open3D lets go of the interpreter lock; each call on its own thread, so
    # the same bits as one after the other).
    from_yaws = _SharedStarts([functools.partial(_refine_start, prep, M0, config, first) for M0 in yaws])
    with ThreadPoolExecutor(1, thread_name_prefix="yaw-starts") as pool:  # no thread until a submit
        helper = pool.submit(from_yaws.work) if workers > 1 and yaws else None
        # With the helper busy, this thread's queries keep to one core (two would compete).
        here = 1 if helper is not None else workers
        runs = _ransac_runs(prep, config, here)
        if not runs and config.mutual_filter:
            runs = _ransac_runs(prep, dataclasses.replace(config, mutual_filter=False), here)
        firsts = _refined(prep, runs, config, first, here)
        from_yaws.work()
        if helper is not None:
            helper.result()
    firsts += from_yaws.results()
    cands = firsts
    if first is not fine:
        # The distinct coarse results, refined again on every sample (from close by: few steps).
        runs = [_to_norm(prep, h.transform)
                for h in _select(firsts, config, symmetry, config.candidates, centre, size)]
        cands = _refined(prep, runs, config, fine, workers)
    if not cands:
        raise NoHypothesisError(
            "initial registration failed: RANSAC found no transform consistent with the FPFH "
            "matches (too few or too different surface samples?)"
        )
    return _select(cands, config, symmetry, limit, centre, size)


def _refined(prep: _Prepared, starts: list[np.ndarray], config: InitConfig,
             icp: Callable[[np.ndarray], np.ndarray], workers: int = 1) -> list[Hypothesis]:
    """``icp`` from each normalised-frame start (4, 4), scored on every sample; degenerate
    results and those whose scale strays from the pre-estimate by more than
    ``max_scale_ratio`` are dropped. The starts are independent: side by side on ``workers``
    threads, each ICP on its own thread (the same bits as one after another: no random draws,
    and Open3D on one thread under ``one_thread``)."""

    one = functools.partial(_refine_start, prep, config=config, icp=icp)
    return [h for h in map_one_thread_each(one, starts, workers) if h is not None]


def _refine_start(prep: _Prepared, M0: np.ndarray, config: InitConfig,
                  icp: Callable[[np.ndarray], np.ndarray]) -> Hypothesis | None:
    """``icp`` from the normalised-frame start ``M0`` (4, 4), scored on every sample; None for a
    degenerate result or one whose scale strays from the pre-estimate (see :func:`_refined`)."""
    M = _similarity_or_none(icp(M0))
    if M is None:
        M = _similarity_or_none(M0)
    if M is None:
        return None
    T = _to_field(prep, M)
    # ICP with scaling can collapse the scene onto part of the library: reject that.
    ratio = T.s / prep.scale0
    if not 1.0 / config.max_scale_ratio <= ratio <= config.max_scale_ratio:
        return None
    fit, rmse = _evaluate(prep, M, config)
    return Hypothesis(T, fit, rmse)


class _SharedStarts:
    """Jobs (each an ICP from one start) taken one at a time by every thread that calls
    :meth:`work`, so that a thread that joins late takes over the jobs not yet begun; the
    results in job order, the same whichever thread ran each."""

    def __init__(self, jobs: list[Callable[[], Hypothesis | None]]) -> None:
        self._jobs = jobs
        self._out: list[Hypothesis | None] = [None] * len(jobs)
        self._next = 0
        self._lock = threading.Lock()

    def work(self) -> None:
        """Run jobs until none is left to begin."""
        while True:
            with self._lock:
                i, self._next = self._next, self._next + 1
            if i >= len(self._jobs):
                return
            self._out[i] = self._jobs[i]()

    def results(self) -> list[Hypothesis]:
        """The jobs' hypotheses in job order, the failed ones left out (after every work())."""
        return [h for h in self._out if h is not None]


class NoHypothesisError(RegnfError):
    """RANSAC found no transform at all: the two clouds do not look alike."""


def centroid_hypothesis(
    scene: SurfaceSamples, library: SurfaceSamples, config: InitConfig = InitConfig()
) -> Hypothesis:
    """The weakest possible start: centroids aligned, radii matched, no rotation.

    Used when RANSAC finds nothing, so that the refinement still runs and its confidence
    (not an exception) reports the failed registration.
    """
    c_s, r_s = _centre_and_radius(np.asarray(scene.points, np.float64), config)
    c_l, r_l = _centre_and_radius(np.asarray(library.points, np.float64), config)
    s = r_l / r_s
    T = SimilarityTransform(np.eye(3), c_l - s * c_s, float(s))
    return Hypothesis(T, 0.0, float("inf"))


def fgr_baseline(
    scene: SurfaceSamples, library: SurfaceSamples, config: InitConfig = InitConfig()
) -> Hypothesis:
    """Open3D's Fast Global Registration on the same normalised clouds and features.

    FGR estimates a RIGID transform only: the scale of the result is the pre-estimate
    (ratio of the clouds' radii, see ``InitConfig.scale_estimate``), not FGR's. No ICP.

    Returns
    -------
    Hypothesis
        Scene field -> library field, with fitness and inlier RMSE as in
        :func:`initial_hypotheses`.
    """
    prep = _prepare(scene, library, config)
    option = reg.FastGlobalRegistrationOption(
        maximum_correspondence_distance=config.fgr_distance_voxels * config.voxel_size
    )
    o3d.utility.random.seed(config.seed)
    res = reg.registration_fgr_based_on_feature_matching(
        prep.src_down, prep.tgt_down, prep.src_fpfh, prep.tgt_fpfh, option
    )
    M = _similarity_or_none(np.asarray(res.transformation))
    if M is None:
        raise RegnfError("FGR returned a degenerate transform")
    fit, rmse = _evaluate(prep, M, config)
    return Hypothesis(_to_field(prep, M), fit, rmse)
