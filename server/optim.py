"""Global optimisation primitives of the back-end, as pure functions over arrays.

- :func:`solve_pose_graph_sim3` (and ``_se3``): Sim(3) pose-graph optimisation over keyframe poses (gtsam
  ``BetweenFactorSimilarity3``), as ORB-SLAM's essential-graph optimisation after a loop or merge.
- :func:`global_bundle_adjustment`: full BA of keyframe poses and points: gtsam for stereo maps
  (:mod:`hivemap.server.ba_gtsam`), pycolmap (Ceres) for monocular ones.

Both are independent of the map model so they can run in a background worker on a snapshot.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, se3, se3_inverse
from hivemap.server import ba_build, ba_gtsam

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PoseGraphEdge:
    """A relative Sim(3) constraint ``cam_i_from_cam_j`` between keyframes ``i`` and ``j``.

    ``sigma_rot`` (rad), ``sigma_trans`` (m), ``sigma_logscale`` are the standard deviations of the
    measurement; ``robust`` applies a Huber loss (loop/merge edges, paper's peers do this).
    ``sigma_yaw`` (rad) with ``up_j`` (the unit up direction in keyframe ``j``'s camera frame, from its
    agent's IMU): the rotation about up gets this sigma and ``sigma_rot`` is left for roll/pitch. An
    agent's VIO measures yaw far better than tilt (``OptimiseOptions.pose_graph_sigma_yaw``).
    """

    i: int
    j: int
    i_from_j: Sim3
    sigma_rot: float = 0.01
    sigma_trans: float = 0.05
    sigma_logscale: float = 0.01
    robust: bool = False
    sigma_yaw: float | None = None
    up_j: tuple[float, float, float] | None = None
    # (6, 6) [rot, trans] covariance in gtsam's Between perturbation (``j`` side), instead of the sigmas
    covariance: F64 | None = field(default=None, compare=False)

    def rotation_covariance(self) -> F64:
        """3x3 covariance of the rotation error, in keyframe ``j``'s frame (gtsam's Between error: the
        tangent of ``measured^-1 (X_i^-1 X_j)``, a perturbation on the ``j`` side)."""
        cov = np.eye(3) * self.sigma_rot**2
        if self.sigma_yaw is None or self.up_j is None:
            return cov
        u = np.asarray(self.up_j, dtype=np.float64)
        norm = float(np.linalg.norm(u))
        if not np.isfinite(norm) or norm < 1e-9:
            return cov
        u = u / norm
        return cov + (self.sigma_yaw**2 - self.sigma_rot**2) * np.outer(u, u)

    def se3_covariance(self) -> F64:
        """(6, 6) [rot, trans] covariance in gtsam's Between perturbation: ``covariance`` where given, else
        :meth:`rotation_covariance` and ``sigma_trans`` per axis."""
        if self.covariance is not None:
            return np.asarray(self.covariance, dtype=np.float64)
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.rotation_covariance()
        cov[3:, 3:] = np.eye(3) * self.sigma_trans**2
        return cov


@dataclass(frozen=True)
class PoseGraphOptions:
    """``gnc``: the robust edges are judged by graduated non-convexity with a truncated-least-squares loss
    (gtsam ``GncOptimizer``, the other edges and the gauge being known inliers), so an edge the rest of the
    graph contradicts gets weight 0 and no pull at all; else they get a Huber loss, which still pulls.
    ``gnc_inlier_probability``: an edge whose whitened residual is within this quantile of the chi-square
    distribution of its dimension counts as an inlier."""

    max_iterations: int = 100
    huber_k: float = 1.345
    relative_error_tol: float = 1e-7
    gnc: bool = False
    gnc_inlier_probability: float = 0.99


@dataclass
class PoseGraphResult:
    """The solved poses and, per edge (in the order given), whether it was kept: robust edges that the
    GNC rejected are False, every other edge True. ``chi2``: each edge's whitened squared residual at the
    solution (what the GNC judged). ``cpu_ms``: the CPU time of the solve in the process that ran it (set
    by the back-end's caller; against the wall time it tells a slow solve from one that waited for a core)."""

    poses: list[Sim3]
    inlier: list[bool]
    chi2: list[float]
    cpu_ms: float = 0.0


def _check_graph(name: str, n: int, edges: list[PoseGraphEdge], fixed: set[int] | frozenset[int]) -> None:
    """Gauge and index checks shared by the pose graphs."""
    if not fixed:
        raise ValueError(f"{name} needs at least one fixed keyframe (gauge)")
    for k in fixed:
        if not 0 <= k < n:
            raise IndexError(f"fixed keyframe index {k} out of range 0..{n - 1}")
    for e in edges:
        if not (0 <= e.i < n and 0 <= e.j < n) or e.i == e.j:
            raise IndexError(f"pose-graph edge ({e.i}, {e.j}) invalid for {n} keyframes")


def _edge_noise(e: PoseGraphEdge, tail: list[float], options: PoseGraphOptions) -> Any:
    """The edge's noise model: its ``covariance`` (then the log-scale sigma for Sim(3)), or the rotation
    block from :meth:`PoseGraphEdge.rotation_covariance` and the independent sigmas ``tail``
    (translation, and log-scale for Sim(3)); Huber if robust."""
    import gtsam

    noise: Any
    if e.covariance is None and (e.sigma_yaw is None or e.up_j is None):
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([e.sigma_rot] * 3 + tail))
    else:
        cov = np.zeros((3 + len(tail), 3 + len(tail)))
        cov[:6, :6] = e.se3_covariance()
        cov[6:, 6:] = np.diag(np.square(tail[3:]))
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    if e.robust and not options.gnc:
        huber = gtsam.noiseModel.mEstimator.Huber.Create(options.huber_k)
        noise = gtsam.noiseModel.Robust.Create(huber, noise)
    return noise


def _loose_noise(dim: int) -> Any:
    """A prior that only keeps a part of the graph from floating (its gauge) when every robust edge to
    the rest is rejected: 1 rad, 100 m (and log-scale 1)."""
    import gtsam

    return gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0] * 3 + [100.0] * 3 + [1.0] * (dim - 6)))


def _solve_lm(graph: Any, initial: Any, options: PoseGraphOptions) -> Any:
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_error_tol)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


def _solve(
    graph: Any, initial: Any, n_fixed: int, edges: list[PoseGraphEdge], options: PoseGraphOptions
) -> tuple[Any, list[bool], list[float]]:
    """Solve the graph (the ``n_fixed`` gauge factors first, then one factor per edge): plain LM, or GNC
    over the robust edges when ``options.gnc``. Returns the values, each edge's inlier flag and chi2."""
    import gtsam

    robust = [k for k, e in enumerate(edges) if e.robust]
    weights = np.ones(len(edges))
    if options.gnc and robust:
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(options.max_iterations)
        lm.setRelativeErrorTol(options.relative_error_tol)
        params = gtsam.GncLMParams(lm)
        params.setLossType(gtsam.GncLossType.TLS)
        robust_set = set(robust)
        known = list(range(n_fixed)) + [n_fixed + k for k in range(len(edges)) if k not in robust_set]
        params.setKnownInliers(known)
        gnc = gtsam.GncLMOptimizer(graph, initial, params)
        gnc.setInlierCostThresholdsAtProbability(options.gnc_inlier_probability)
        result = gnc.optimize()
        weights = np.asarray(gnc.getWeights(), dtype=np.float64)[n_fixed:]
    else:
        result = _solve_lm(graph, initial, options)
    chi2 = [2.0 * float(graph.at(n_fixed + k).error(result)) for k in range(len(edges))]
    return result, [bool(w > 0.5) for w in weights], chi2


def solve_pose_graph_sim3(
    world_from_cam: F64,
    edges: list[PoseGraphEdge],
    fixed: set[int] | frozenset[int],
    options: PoseGraphOptions = PoseGraphOptions(),
    loose: Sequence[int] = (),
) -> PoseGraphResult:
    """Optimise keyframe poses under relative Sim(3) constraints.

    world_from_cam: (N, 4, 4) initial SE(3) poses. ``fixed``: indices held constant (at least one).
    ``loose``: indices held by a very loose prior at their initial pose (parts of the graph joined to the
    rest only by robust edges, which may all be rejected).
    Returns N ``Sim3`` ``world_from_cam`` (scale may differ from 1 where drift was in scale) and the
    edges' verdicts. Points anchored to keyframe ``i`` follow with
    ``new[i] @ Sim3.from_se3(old_i).inverse()``.
    """
    import gtsam

    poses = np.asarray(world_from_cam, dtype=np.float64)
    n = len(poses)
    if n == 0:
        return PoseGraphResult([], [True] * len(edges), [0.0] * len(edges))
    _check_graph("solve_pose_graph_sim3", n, edges, fixed)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k in range(n):
        initial.insert(k, Sim3.from_se3(poses[k]).to_gtsam())
    for k in sorted(fixed):
        graph.add(gtsam.NonlinearEqualitySimilarity3(k, Sim3.from_se3(poses[k]).to_gtsam()))
    for k in loose:
        graph.add(gtsam.PriorFactorSimilarity3(k, Sim3.from_se3(poses[k]).to_gtsam(), _loose_noise(7)))
    for e in edges:
        noise = _edge_noise(e, [e.sigma_trans] * 3 + [e.sigma_logscale], options)
        graph.add(gtsam.BetweenFactorSimilarity3(e.i, e.j, e.i_from_j.to_gtsam(), noise))
    result, inlier, chi2 = _solve(graph, initial, len(fixed) + len(loose), edges, options)
    out = [Sim3.from_gtsam(result.atSimilarity3(k)) for k in range(n)]
    log.debug(
        "pose graph: %d keyframes, %d edges, error %.3g -> %.3g",
        n,
        len(edges),
        graph.error(initial),
        graph.error(result),
    )
    return PoseGraphResult(out, inlier, chi2)


def solve_pose_graph_se3(
    world_from_cam: F64,
    edges: list[PoseGraphEdge],
    fixed: set[int] | frozenset[int],
    options: PoseGraphOptions = PoseGraphOptions(),
    loose: Sequence[int] = (),
) -> PoseGraphResult:
    """:func:`solve_pose_graph_sim3` for metric maps: SE(3) poses and edges (gtsam Pose3; the edges'
    scale and ``sigma_logscale`` are ignored). Poses come back as Sim3 with scale 1."""
    n = len(world_from_cam)
    if n == 0:
        return PoseGraphResult([], [True] * len(edges), [0.0] * len(edges))
    graph, initial = se3_graph(world_from_cam, edges, fixed, options, loose)
    result, inlier, chi2 = _solve(graph, initial, len(fixed) + len(loose), edges, options)
    return PoseGraphResult([Sim3.from_se3(result.atPose3(k).matrix()) for k in range(n)], inlier, chi2)


def se3_graph(
    world_from_cam: F64,
    edges: list[PoseGraphEdge],
    fixed: set[int] | frozenset[int],
    options: PoseGraphOptions = PoseGraphOptions(),
    loose: Sequence[int] = (),
) -> tuple[Any, Any]:
    """The SE(3) pose graph of :func:`solve_pose_graph_se3` and its initial values (gtsam
    ``NonlinearFactorGraph``, ``Values`` keyed 0..N-1): the ``fixed`` equalities first, then the ``loose``
    priors, then one factor per edge (what :mod:`hivemap.server.marginals` linearises too)."""
    import gtsam

    poses = np.asarray(world_from_cam, dtype=np.float64)
    n = len(poses)
    _check_graph("solve_pose_graph_se3", n, edges, fixed)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k in range(n):
        initial.insert(k, gtsam.Pose3(poses[k]))
    for k in sorted(fixed):
        graph.add(gtsam.NonlinearEqualityPose3(k, gtsam.Pose3(poses[k])))
    for k in loose:
        graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(poses[k]), _loose_noise(6)))
    for e in edges:
        noise = _edge_noise(e, [e.sigma_trans] * 3, options)
        rel = se3(e.i_from_j.R, e.i_from_j.t)
        graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(rel), noise))
    return graph, initial


def relative_sim3(world_from_i: F64, world_from_j: F64) -> Sim3:
    """``i_from_j`` between two SE(3) poses, as a Sim3 with scale 1."""
    return Sim3.from_se3(se3_inverse(world_from_i) @ world_from_j)


@dataclass(frozen=True)
class BundleAdjustmentOptions:
    max_iterations: int = 50
    huber_px: float = 2.0
    num_threads: int = 1
    # Observations farther than this from their projection before BA are outliers (wrong matches,
    # badly fused points) and are left out; points left with < 2 observations are not optimised.
    max_initial_error_px: float = 8.0
    min_depth_m: float = 0.05
    # After BA a point whose worst observation is off by more than this keeps its old position.
    max_final_error_px: float = 4.0
    # Metric maps (stereo / VIO): every keyframe's input position becomes a prior with this standard
    # deviation (m), which holds the map's metric scale (monocular residuals alone let it drift).
    # None: no prior (Sim(3) maps, whose scale is free anyway).
    position_prior_m: float | None = None
    # Ceres: stop when the cost changes by less than this fraction per iteration.
    function_tolerance: float = 1e-6
    # Use the stereo observations (``u_right``) where the keyframes carry them.
    stereo: bool = True
    # A problem with stereo observations is solved by gtsam (:mod:`hivemap.server.ba_gtsam`: one stereo
    # factor per observation, sigma per pyramid level, the agents' odometry as between factors), else by
    # pycolmap ("pycolmap": also the stereo ones, as rigs, without weights or odometry).
    stereo_solver: str = "gtsam"
    octave_weights: bool = True  # gtsam: sigma scale_factor ** octave px per observation
    scale_factor: float = 1.2  # the agents' ORB pyramid scale
    # gtsam: LM stops iterating once this much CPU is spent (a 2000-keyframe map within a minute)
    cpu_budget_s: float = 40.0


@dataclass
class BundleAdjustmentResult:
    """``accepted`` False: BA failed or made things worse; poses and points are the inputs unchanged.

    RMSEs are over the inlier observations (``obs_inlier``); ``point_ok`` marks the points BA moved.
    """

    world_from_cam: F64
    points: F64
    initial_rmse_px: float
    final_rmse_px: float
    iterations: int = 0
    extras: dict[str, float] = field(default_factory=dict)
    accepted: bool = True
    obs_inlier: NDArray[np.bool_] | None = None
    point_ok: NDArray[np.bool_] | None = None


def reprojection_errors(
    cameras: list[PinholeCamera],
    camera_index: NDArray[np.int64],
    world_from_cam: F64,
    points: F64,
    obs_kf: NDArray[np.int64],
    obs_pt: NDArray[np.int64],
    obs_uv: F64,
) -> tuple[F64, F64]:
    """Per observation: pixel error (inf when the point is behind the camera) and depth (m)."""
    err = np.full(len(obs_kf), np.inf)
    depth = np.zeros(len(obs_kf))
    for k in np.unique(obs_kf):
        sel = np.flatnonzero(obs_kf == k)
        T = world_from_cam[k]
        pc = (points[obs_pt[sel]] - T[:3, 3]) @ T[:3, :3]
        uv, valid = cameras[int(camera_index[k])].project(pc)
        e = np.linalg.norm(uv - obs_uv[sel], axis=1)
        err[sel] = np.where(valid, e, np.inf)
        depth[sel] = pc[:, 2]
    return err, depth


def _similarity_scale(src: F64, dst: F64) -> float:
    """Scale of the least-squares similarity taking points ``src`` onto ``dst`` (Umeyama); 1 if degenerate."""
    a, b = src - src.mean(0), dst - dst.mean(0)
    var = float((a**2).sum(1).mean())
    if var < 1e-12:
        return 1.0
    u, d, vt = np.linalg.svd(b.T @ a / len(a))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    return float((d * sign).sum() / var)


def global_bundle_adjustment(
    cameras: list[PinholeCamera],
    camera_index: NDArray[np.int64],
    world_from_cam: F64,
    points: F64,
    obs_kf: NDArray[np.int64],
    obs_pt: NDArray[np.int64],
    obs_uv: F64,
    fixed_kfs: set[int] | frozenset[int],
    options: BundleAdjustmentOptions = BundleAdjustmentOptions(),
    obs_ur: F64 | None = None,
    baselines: Sequence[float | None] | None = None,
    obs_octave: NDArray[np.integer] | None = None,
    odometry: Sequence[ba_gtsam.OdometryEdge] = (),
) -> BundleAdjustmentResult:
    """Jointly refine keyframe poses and points (pycolmap / Ceres, or gtsam for stereo problems),
    intrinsics held constant.

    cameras: the distinct camera models; camera_index (N,) picks one per keyframe.
    world_from_cam (N, 4, 4); points (M, 3); observations as parallel arrays obs_kf (K,), obs_pt (K,),
    obs_uv (K, 2) in distorted pixels. ``fixed_kfs``: keyframes held constant; at least two of them,
    or one plus the two-camera gauge, so the problem has no free similarity (DESIGN.md: holding one
    pose fixes only 6 DoF), unless there are stereo observations.
    ``obs_ur`` (K,): each observation's ``u_right`` in its keyframe's virtual rectified right camera
    (NaN: mono) and ``baselines``: per camera its stereo baseline (m) or None; with them the BA is a
    stereo BA whose scale is held by the baseline: gtsam (:mod:`hivemap.server.ba_gtsam`, with
    ``obs_octave`` (K,) the keypoints' pyramid levels and ``odometry`` between factors) unless
    ``options.stereo_solver`` is "pycolmap" (a rig BA, :mod:`hivemap.server.ba_build`).
    """

    poses = np.asarray(world_from_cam, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    n, m = len(poses), len(pts)
    if len(obs_kf) != len(obs_pt) or len(obs_kf) != len(obs_uv):
        raise ValueError("obs_kf, obs_pt and obs_uv must have the same length")
    if len(obs_kf) and (obs_kf.max() >= n or obs_pt.max() >= m or obs_kf.min() < 0 or obs_pt.min() < 0):
        raise IndexError("observation refers to a keyframe or point out of range")
    err0, depth0 = reprojection_errors(cameras, camera_index, poses, pts, obs_kf, obs_pt, obs_uv)
    inlier = (err0 <= options.max_initial_error_px) & (depth0 >= options.min_depth_m)
    keep = np.flatnonzero(inlier)
    obs_kf_all = obs_kf
    obs_kf, obs_pt, obs_uv = obs_kf[keep], obs_pt[keep], obs_uv[keep]
    if obs_ur is None or baselines is None or not options.stereo:
        obs_ur_kept = np.full(len(obs_kf), np.nan)
        cam_baselines: Sequence[float | None] = [None] * len(cameras)
    else:
        cam_baselines = baselines
        obs_ur_kept = np.asarray(obs_ur, dtype=np.float64)[keep].copy()
        err_r = ba_build.right_errors(
            cameras, cam_baselines, camera_index, poses, pts, obs_kf, obs_pt, obs_ur_kept
        )
        # a wrong stereo match is dropped alone; its left observation may still be right
        obs_ur_kept[~(err_r <= options.max_initial_error_px)] = np.nan
    if np.isfinite(obs_ur_kept).any() and options.stereo_solver == "gtsam":
        octs = None if obs_octave is None else np.asarray(obs_octave)[keep]
        g = ba_gtsam.solve(
            cameras, cam_baselines, camera_index, poses, pts, obs_kf, obs_pt, obs_uv, obs_ur_kept, octs,
            fixed_kfs, odometry, max_iterations=options.max_iterations,
            relative_error_tol=options.function_tolerance, scale_factor=options.scale_factor,
            octave_weights=options.octave_weights, cpu_budget_s=options.cpu_budget_s,
        )  # fmt: skip
        return _checked(
            cameras, camera_index, poses, pts, (obs_kf, obs_pt, obs_uv), keep, len(obs_kf_all), err0,
            (g.world_from_cam, g.points, g.in_problem, g.iterations), {"n_stereo": float(g.n_stereo)},
            options, use_priors=False,
        )  # fmt: skip
    out_poses, out_pts, in_problem, iters, n_stereo, use_priors = ba_build.solve_pycolmap(
        cameras, cam_baselines, camera_index, poses, pts, obs_kf, obs_pt, obs_uv, obs_ur_kept, fixed_kfs,
        options,
    )  # fmt: skip
    return _checked(
        cameras, camera_index, poses, pts, (obs_kf, obs_pt, obs_uv), keep, len(obs_kf_all), err0,
        (out_poses, out_pts, in_problem, iters), {"n_stereo": float(n_stereo)}, options, use_priors,
    )  # fmt: skip


def _checked(
    cameras: list[PinholeCamera],
    camera_index: NDArray[np.int64],
    poses: F64,
    pts: F64,
    obs: tuple[NDArray[np.int64], NDArray[np.int64], F64],
    keep: NDArray[np.int64],
    n_obs_all: int,
    err0: F64,
    solved: tuple[F64, F64, NDArray[np.bool_], int],
    extras: dict[str, float],
    options: BundleAdjustmentOptions,
    use_priors: bool,
) -> BundleAdjustmentResult:
    """The result of a solve, checked: points that ended far from their observations keep their old
    position; a result that is worse than its input, or kept under half the observations, is refused."""
    obs_kf, obs_pt, obs_uv = obs
    out_poses, out_pts, in_problem, iters = solved
    m = len(pts)
    out_pts = out_pts.copy()
    err1, depth1 = reprojection_errors(cameras, camera_index, out_poses, out_pts, obs_kf, obs_pt, obs_uv)
    bad = np.zeros(m, dtype=bool)
    np.logical_or.at(bad, obs_pt, ~(err1 <= options.max_final_error_px) | (depth1 < options.min_depth_m))
    point_ok = in_problem & ~bad
    out_pts[~point_ok] = pts[~point_ok]
    good_obs = point_ok[obs_pt]
    initial = float(np.sqrt(np.mean(err0[keep][good_obs] ** 2))) if good_obs.any() else float("nan")
    final = float(np.sqrt(np.mean(err1[good_obs] ** 2))) if good_obs.any() else float("nan")
    obs_inlier = np.zeros(n_obs_all, dtype=bool)
    obs_inlier[keep[good_obs]] = True
    ok = bool(np.isfinite(final) and np.isfinite(out_poses).all() and final <= max(initial, 0.0) + 0.5)
    ok = ok and good_obs.sum() >= 0.5 * n_obs_all  # most of the problem survived
    if ok and use_priors:
        # pycolmap drops the priors with only a log line when it cannot align them: then nothing held the
        # metric scale; refuse a result whose overall scale moved by more than 1%
        s = _similarity_scale(out_poses[:, :3, 3], poses[:, :3, 3])
        if not abs(s - 1.0) < 0.01:
            log.warning("global BA rejected: metric scale moved %.2f%% despite the priors", (s - 1) * 100)
            ok = False
    if not ok:
        log.warning(
            "global BA rejected: rmse %.3g -> %.3g px, %d of %d observations kept", initial, final,
            int(good_obs.sum()), n_obs_all,
        )  # fmt: skip
        return BundleAdjustmentResult(
            poses.copy(), pts.copy(), initial, final, iters, {}, False, obs_inlier, point_ok
        )
    return BundleAdjustmentResult(
        out_poses, out_pts, initial, final, iters, extras, True, obs_inlier, point_ok
    )
