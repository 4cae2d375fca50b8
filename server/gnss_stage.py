"""The server's global GNSS stage (paper 2.5.3; VINS-Fusion ``global_fusion`` style).

After global BA, a gtsam graph over a merged map's keyframe poses: the map's shape as its robust pose
graph knows it (:class:`ShapeEdge`: every agent's odometry between consecutive keyframes and every kept
loop, merge and rendezvous edge, each held at the map's current relative pose with that edge's own
uncertainty) plus a GNSS position factor per fix, weighted by the fix's covariance under a Huber loss. Its
output is ``enu_from_map`` (the rigid transform that moves the whole map into ENU) and the corrected
poses. Fixes more than ``outlier_sigma`` sigmas off after a first solve are rejected and the graph is
solved again. How stiffly the odometry holds the map's shape against the fixes is chosen by
cross-validation on the fixes (``GnssStageOptions.stiffness_scales``); the loops and merges are
measurements and keep their own covariances. (A chain of fixed per-metre sigmas dropped each agent's
loops, so a few noisy fixes bent a map whose loops had closed it.)

Roll/pitch: GNSS positions barely observe a keyframe's tilt, so on a gravity-aligned map an attitude
factor holds each keyframe's up direction: the one the agent's IMU measured (``up_in_body``, sent with
the keyframe) where there is one, else the map's own, which carries the front-end's visual tilt drift
and would put the far ends of a merged map off in height (``docs/decisions.md``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import se3, se3_inverse

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GnssStageOptions:
    min_fixes: int = 3
    min_spread_m: float = 5.0  # the fixes must span this much horizontally to fix yaw
    huber_k: float = 1.345
    # The map is gravity-aligned (IMU): estimate only yaw + translation into ENU and hold each
    # keyframe's roll/pitch with an attitude factor, as GNSS barely observes tilt.
    gravity_aligned: bool = True
    sigma_attitude: float = 0.005  # rad
    outlier_sigma: float = 10.0
    max_iterations: int = 50
    # How stiff the odometry is (its edges' sigmas times a scale) is chosen by cross-validation: the
    # fixes are split into ``cv_folds`` interleaved folds, each predicted by the stage solved without it,
    # and the scale with the closest predictions (mean squared Mahalanobis distance) wins. An agent's
    # odometry may drift more or less than the pose graph's model of it says (docs/decisions.md).
    stiffness_scales: tuple[float, ...] = (1.0, 0.3, 0.1, 0.03)
    cv_folds: int = 5
    cv_min_fixes: int = 10  # fewer used fixes: scale 1 (the first one), no cross-validation


@dataclass(frozen=True)
class GnssFix:
    """A fix attached to keyframe ``index``: ENU position (3,) and its 3x3 covariance."""

    index: int
    enu: F64
    cov: F64


@dataclass
class GnssStageResult:
    enu_from_map: F64  # 4x4 rigid transform from the map's (global) frame to ENU
    world_from_body: F64  # (N, 4, 4) corrected poses in ENU
    used: NDArray[np.bool_]  # per fix: fused (True) or rejected as outlier (False)
    residuals_m: F64  # per fix, after the final solve
    stiffness_scale: float = 1.0  # the relative sigmas' scale used (see GnssStageOptions.stiffness_scales)
    cv_scores: dict[float, float] | None = None  # scale -> mean held-out Mahalanobis^2 (None: no CV run)


@dataclass(frozen=True)
class ShapeEdge:
    """One relative-pose factor holding the map's shape between keyframes ``a`` and ``b`` at their
    current relative pose: ``cov`` (6, 6) in gtsam's Between perturbation ([rot, trans], ``b`` side);
    ``odometry``: an agent's own odometry, whose covariance the chain stiffness scales (a loop's or a
    merge's is a measurement's, and stays)."""

    a: int
    b: int
    cov: F64
    odometry: bool


class NotEnoughFixes(ValueError):
    """The fixes do not constrain the map's pose in ENU (too few or too close together)."""


def fuse_gnss(
    world_from_body: F64,
    shape: list[ShapeEdge],
    fixes: list[GnssFix],
    options: GnssStageOptions = GnssStageOptions(),
    up_in_body: F64 | None = None,
    stiffness_scale: float | None = None,
) -> GnssStageResult:
    """Move a map into ENU and bend it onto the GNSS fixes.

    world_from_body: (N, 4, 4) keyframe poses in the map frame (after BA).
    shape: the map's relative-pose factors (:class:`ShapeEdge`).
    up_in_body: (N, 3) the up direction measured in each keyframe's body frame (an agent's IMU), rows of
    NaN where there is none: the attitude factors hold those keyframes to it instead of to the map's own
    roll/pitch (which carries the visual tilt drift).
    fixes: GNSS fixes attached to keyframes. Raises :class:`NotEnoughFixes` when they cannot fix
    the map in ENU (fewer than ``min_fixes``, or spread less than ``min_spread_m``).
    stiffness_scale: the odometry sigmas' scale to use; None: chosen by cross-validation among
    ``options.stiffness_scales`` (a caller can keep the choice until more fixes arrive).
    """
    import gtsam

    poses = np.asarray(world_from_body, dtype=np.float64)
    n = len(poses)
    if len(fixes) < options.min_fixes:
        raise NotEnoughFixes(f"{len(fixes)} GNSS fixes, need at least {options.min_fixes}")
    idx = np.array([f.index for f in fixes])
    if idx.min() < 0 or idx.max() >= n:
        raise IndexError("a GNSS fix refers to a keyframe out of range")
    enu = np.array([f.enu for f in fixes], dtype=np.float64)
    spread = float(np.linalg.norm(enu[:, :2].max(axis=0) - enu[:, :2].min(axis=0)))
    if spread < options.min_spread_m:
        raise NotEnoughFixes(f"GNSS fixes span {spread:.1f} m, need {options.min_spread_m} m to fix yaw")
    # Initial alignment: rigid Umeyama (evo) between keyframe positions and fixes; in the
    # horizontal plane only (yaw + translation) when the map is gravity-aligned.
    R, t = _rigid_fit(poses[idx, :3, 3], enu, options.gravity_aligned)
    enu_from_map0 = se3(R, t)
    init = np.array([enu_from_map0 @ p for p in poses])
    used = np.ones(len(fixes), dtype=bool)

    # What every solve shares (the cross-validation solves 20 more times): the initial values, the loops,
    # the loose priors and attitude factors, and each odometry edge's relative pose and unscaled covariance.
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, gtsam.Pose3(init[k]))
    fixed = gtsam.NonlinearFactorGraph()
    for e in shape:
        if not e.odometry:
            rel = gtsam.Pose3(se3_inverse(poses[e.a]) @ poses[e.b])
            fixed.add(gtsam.BetweenFactorPose3(e.a, e.b, rel, gtsam.noiseModel.Gaussian.Covariance(e.cov)))
    # Keyframes of no edge and without fixes would be unconstrained: anchor all loosely.
    loose = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0] * 3 + [100.0] * 3))
    for k in range(n):
        fixed.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(init[k]), loose))
        if options.gravity_aligned:
            down_in_body = init[k, :3, :3].T @ np.array([0.0, 0.0, -1.0])
            if up_in_body is not None and np.all(np.isfinite(up_in_body[k])):
                down_in_body = -np.asarray(up_in_body[k], dtype=np.float64)
            fixed.add(
                gtsam.AttitudeFactorPose3(
                    k,
                    gtsam.Unit3(np.array([0.0, 0.0, -1.0])),
                    gtsam.noiseModel.Isotropic.Sigma(2, options.sigma_attitude),
                    gtsam.Unit3(down_in_body),
                )
            )
    # (a, b, relative pose, covariance at the stiffness scale 1)
    chain_edges = [
        (e.a, e.b, gtsam.Pose3(se3_inverse(poses[e.a]) @ poses[e.b]), np.asarray(e.cov, dtype=np.float64))
        for e in shape
        if e.odometry
    ]
    huber = gtsam.noiseModel.mEstimator.Huber.Create(options.huber_k)
    fix_models = [
        gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(f.cov)) for f in fixes
    ]

    def solve(mask: NDArray[np.bool_], scale: float = 1.0) -> F64:
        graph = gtsam.NonlinearFactorGraph()
        for a, b, rel, cov in chain_edges:
            noise = gtsam.noiseModel.Gaussian.Covariance(scale**2 * cov)
            graph.add(gtsam.BetweenFactorPose3(a, b, rel, noise))
        graph.push_back(fixed)
        for f, model, ok in zip(fixes, fix_models, mask, strict=True):
            if ok:
                graph.add(gtsam.GPSFactor(f.index, np.asarray(f.enu, dtype=np.float64), model))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(options.max_iterations)
        res = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return np.array([res.atPose3(k).matrix() for k in range(n)])

    scale = options.stiffness_scales[0] if stiffness_scale is None else stiffness_scale
    covs = [np.asarray(f.cov, dtype=np.float64) for f in fixes]
    out = solve(used, scale)
    for _ in range(3):
        maha = np.sqrt(_mahalanobis2(out[idx, :3, 3] - enu, covs))
        bad = used & (maha > options.outlier_sigma)
        if not bad.any():
            break
        log.warning(
            "GNSS stage: rejecting %d fix(es) over %.0f sigma: %s",
            bad.sum(),
            options.outlier_sigma,
            [fixes[i].index for i in np.flatnonzero(bad)],
        )
        used &= ~bad
        out = solve(used, scale)
    scores = None
    if stiffness_scale is None and len(options.stiffness_scales) > 1 and used.sum() >= options.cv_min_fixes:
        scores = _cross_validate(solve, used, idx, enu, covs, options)
        best = min(scores, key=lambda k: scores[k])
        if best != scale:
            scale = best
            out = solve(used, scale)
    residuals = np.linalg.norm(out[idx, :3, 3] - enu, axis=1)
    # The map-level transform: rigid alignment of the original poses onto the corrected ones; yaw and
    # translation only for a gravity-aligned map, so that a map moved by it stays gravity-aligned (with a
    # 6-DoF fit, the tilt each stage fitted to the fixes' vertical noise was held by the next stage's
    # attitude factors and compounded).
    R2, t2 = _rigid_fit(poses[:, :3, 3], out[:, :3, 3], options.gravity_aligned) if n >= 3 else (R, t)
    return GnssStageResult(se3(R2, t2), out, used, residuals, scale, scores)


def _cross_validate(
    solve: Callable[[NDArray[np.bool_], float], F64],
    used: NDArray[np.bool_],
    idx: NDArray[np.int64],
    enu: F64,
    covs: list[F64],
    options: GnssStageOptions,
) -> dict[float, float]:
    """Per scale of ``options.stiffness_scales``: the mean squared Mahalanobis distance of each used fix to
    the stage's prediction of its keyframe's antenna when solved without the fix's fold (folds interleaved
    in the fixes' order, so that every fold spans every agent's path)."""
    rows = np.flatnonzero(used)
    fold = np.full(len(used), -1)
    fold[rows] = np.arange(len(rows)) % options.cv_folds
    scores: dict[float, float] = {}
    for scale in options.stiffness_scales:
        d2: list[F64] = []
        for f in range(options.cv_folds):
            held = fold == f
            if not held.any():
                continue
            pred = solve(used & ~held, scale)
            rows_f = np.flatnonzero(held)
            d2.append(_mahalanobis2(pred[idx[rows_f], :3, 3] - enu[rows_f], [covs[i] for i in rows_f]))
        scores[float(scale)] = float(np.mean(np.concatenate(d2)))
    log.info("GNSS stage stiffness by cross-validation: %s", {k: round(v, 2) for k, v in scores.items()})
    return scores


def _mahalanobis2(res: F64, covs: list[F64]) -> F64:
    """Squared Mahalanobis distance of each residual row (N, 3) under its covariance."""
    return np.array([float(r @ np.linalg.solve(c, r)) for r, c in zip(res, covs, strict=True)])


def _rigid_fit(src: F64, dst: F64, yaw_only: bool) -> tuple[F64, F64]:
    """``R, t`` with ``dst ~ R src + t`` (evo's Umeyama); yaw + translation only if ``yaw_only``."""
    from evo.core.geometry import umeyama_alignment

    if not yaw_only:
        R, t, _ = umeyama_alignment(src.T, dst.T, with_scale=False)
        return np.asarray(R), np.asarray(t).reshape(3)
    R2d, t2d, _ = umeyama_alignment(src[:, :2].T, dst[:, :2].T, with_scale=False)
    R = np.eye(3)
    R[:2, :2] = R2d
    return R, np.array([t2d[0], t2d[1], float(np.mean(dst[:, 2] - src[:, 2]))])
