"""Welding a loop's or merge's transform by stereo reprojection before it enters the pose graph.

A verified detection (query and candidate keyframe, its transform, its point pairs) is refined over both
covisible windows: the keyframe and its best covisible ones on either side, their poses held fixed within
each side, only the relative transform free. Each pair's candidate point is reprojected into the query
side's keyframes that observe its twin, and the query point into the candidate side's, as stereo
``(u, v, u_right)`` residuals where the keypoint has a stereo match (``(u, v)`` otherwise) under a Huber
loss, solved by gtsam's Levenberg-Marquardt, with the gross outliers dropped and the solve repeated.

The unknown is the query camera's pose in the candidate map's frame (gtsam ``Pose3``, tangent
``[rot, trans]`` in that camera), so its marginal covariance is directly the loop edge's uncertainty at
the query keyframe. With both keyframes' IMU up directions the fit was levelled (:mod:`.fit`); the weld
may correct its tilt within a prior of ``FitOptions.weld_tilt_sigma_deg`` (default 0.2 deg: the up
directions' own error was most of what loops were off by), 0 turns it only about the up axis (4 DoF);
negative, or without up directions: 6 DoF. A weld whose 99 % bound
exceeds ``weld_max_bound_m`` / ``weld_max_bound_deg`` is refused, and so is the detection (its RANSAC
transform was fitted to the same points, so it is no better determined); so is a weld that moved the fit
farther than the weld's bound and the fit's own (its bootstrap sigmas) allow together.

Built on the event loop (:func:`build`: arrays only), solved in the worker pool (:func:`solve`), applied
on the loop (:func:`welded`). Why the defaults are what they are: ``docs/decisions.md``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.server.backend.options import FitOptions
from hivemap.server.placerec import Detection

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
KfKey = tuple[str, int]

# 99 % points of the chi distribution with 3 degrees of freedom: the bound is this many sigmas along the
# covariance's largest axis (for the 1-dof yaw of a 4-DoF weld, conservative).
BOUND_SIGMAS = 3.368
CHI2_STEREO, CHI2_MONO = 7.815, 5.991  # 95 %, 3 and 2 dof: an observation beyond is dropped
HUBER = 2.45
OUTLIER_ROUNDS = 3
# tilt "held" in 4 DoF: a prior this tight (rad) on the rotation about the two axes across the up direction
HELD_TILT_RAD = 1e-6
# the variants ``FitOptions.weld_compare`` also solves (tilt sigma in degrees, as ``weld_tilt_sigma_deg``)
VARIANTS = {"4dof": 0.0, "tilt0.2": 0.2, "6dof": -1.0}


@dataclass(frozen=True)
class WeldJob:
    """One weld's arrays (picklable). Per observation ``i``: the fixed pose ``M[i]`` (3x4) of the observing
    camera from the frame ``y[i]`` is in: the candidate map (``inverse[i]``: a candidate point, seen by a
    query-side camera, reached through the unknown's inverse) or the query camera (a query point seen by a
    candidate-side camera); its measurement ``z[i]`` = undistorted (u, v, u_right; NaN: mono) px, sigma
    px, and the observing camera's ``fx, fy, cx, cy, baseline``."""

    query: KfKey
    candidate: KfKey
    P0: F64  # (4, 4) the query camera in the candidate map's frame, from the detection's transform
    Tq: F64  # (4, 4) the query keyframe's world_from_cam when built
    Tc: F64  # (4, 4) the candidate keyframe's
    up_q: F64 | None  # (3,) the IMU up direction in the query camera; None: 6 DoF
    M: F64  # (N, 3, 4)
    y: F64  # (N, 3)
    inverse: NDArray[np.bool_]  # (N,)
    z: F64  # (N, 3)
    sigma: F64  # (N,)
    intr: F64  # (N, 5)
    cluster: NDArray[np.int64]  # (N,) the point pair the observation belongs to
    pcov: F64  # (N, 3, 3) the point's covariance in ``y``'s frame (from its own side's stereo keyframes)
    tilt_sigma_deg: float
    max_bound_m: float
    max_bound_deg: float
    min_points: int
    variants: tuple[tuple[str, float], ...] = ()
    # the levelled fit's own sigmas (rad, m; its bootstrap spread): a weld that moves the fit farther than
    # both estimates' 99 % bounds together is refused (None: no levelled fit, no such check)
    fit_sigmas: tuple[float, float] | None = None


@dataclass
class WeldResult:
    ok: bool
    reason: str  # why refused ("" if ok)
    P: F64  # (4, 4) welded query camera in the candidate map's frame (P0 if not solved)
    dof: str
    bound_m: float = math.inf
    bound_deg: float = math.inf
    n_obs: int = 0
    n_inliers: int = 0
    n_stereo: int = 0
    rms: float = 0.0  # whitened rms of the inliers
    moved_m: float = 0.0  # how far the weld moved the query camera from P0
    turned_deg: float = 0.0
    cpu_ms: float = 0.0
    variants: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self, Tc: F64) -> dict[str, Any]:
        """The record (``Tc``: the candidate's world_from_cam the job was built with)."""
        out = {k: getattr(self, k) for k in ("ok", "reason", "dof", "n_obs", "n_inliers", "n_stereo")}
        out.update({k: round(float(getattr(self, k)), 5) for k in
                    ("bound_m", "bound_deg", "rms", "moved_m", "turned_deg", "cpu_ms")})  # fmt: skip
        out["candidate_from_query"] = (se3_inverse(Tc) @ self.P).tolist()
        if self.variants:
            out["variants"] = self.variants
        return out


def _window(m: Any, key: KfKey, n: int) -> list[KfKey]:
    return [key, *(k for k in m.best_covisible(key, n - 1) if k in m.keyframes and k != key)]


def _point_cov(m: Any, p: Any, fixed: dict[KfKey, F64], y: F64) -> F64 | None:
    """Point ``p``'s covariance (3x3) in the frame of ``fixed``'s poses (``y``: its position there): the
    information of its stereo observations in its own side's window fused, each a depth sigma growing with
    the distance squared along the ray and a keypoint sigma across it (local BA did the same fusion). None
    without a stereo observation there (its depth is then not known well enough to weld on)."""
    info = np.zeros((3, 3))
    for k, idx in p.observations.items():
        M = fixed.get(k)
        kf = m.keyframes.get(k)
        if M is None or kf is None or kf.u_right is None or not kf.stereo_baseline:
            continue
        if not np.isfinite(kf.u_right[idx]):
            continue
        centre = -M[:3, :3].T @ M[:3, 3]
        ray = y - centre
        d = float(np.linalg.norm(ray))
        u = ray / max(d, 1e-9)
        sig_px = 1.2 ** float(kf.octaves[idx])
        f = kf.camera.fx
        s_depth = d * d * math.sqrt(2.0) * sig_px / (f * float(kf.stereo_baseline))
        s_lat = d * sig_px / f
        P = np.outer(u, u)
        info += P / s_depth**2 + (np.eye(3) - P) / s_lat**2
    if not info.any():
        return None
    cov: F64 = np.asarray(np.linalg.inv(info), dtype=np.float64)
    return cov


def build(
    maps: Any,
    det: Detection,
    up_q: F64 | None,
    o: FitOptions,
    fit_sigmas: tuple[float, float] | None = None,
) -> WeldJob | None:
    """The weld of ``det`` (its ``target_from_source``, SE(3)); ``up_q``: the query camera's up direction
    if the transform was levelled by it (4 DoF), else None; ``fit_sigmas``: the levelled fit's (rad, m), if
    any. None when a keyframe is gone."""
    mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
    if mq is None or mc is None or det.query_key not in mq.keyframes or det.candidate_key not in mc.keyframes:
        return None
    Tq = np.asarray(mq.keyframes[det.query_key].world_from_cam, dtype=np.float64)
    Tc = np.asarray(mc.keyframes[det.candidate_key].world_from_cam, dtype=np.float64)
    sim = det.target_from_source
    P0 = Sim3(sim.R, sim.t, 1.0).matrix() @ Tq
    q_from_world = se3_inverse(Tq)
    # fixed poses: a query-side camera from the query camera, a candidate-side camera from the candidate map
    fixed_q = {k: (se3_inverse(np.asarray(mq.keyframes[k].world_from_cam)) @ Tq)[:3]
               for k in _window(mq, det.query_key, o.weld_window)}  # fmt: skip
    fixed_c = {k: se3_inverse(np.asarray(mc.keyframes[k].world_from_cam))[:3]
               for k in _window(mc, det.candidate_key, o.weld_window)}  # fmt: skip
    obs: dict[KfKey, list[tuple[int, F64, F64, bool, int, F64]]] = {}  # kf -> (kp, M, y, inverse, pair, cov)
    seen: set[tuple[Any, Any]] = set()
    for kq, kc in zip(det.query_points, det.candidate_points, strict=True):
        rq, rc = mq.resolve_point(kq), mc.resolve_point(kc)
        pq, pc = mq.points.get(rq), mc.points.get(rc)
        if pq is None or pc is None or (rq, rc) in seen or (mq is mc and rq == rc):
            continue
        yq = q_from_world[:3, :3] @ pq.xyz + q_from_world[:3, 3]
        cov_c = _point_cov(mc, pc, fixed_c, pc.xyz)
        cov_q = _point_cov(mq, pq, fixed_q, yq)
        if cov_c is None or cov_q is None:
            continue
        seen.add((rq, rc))
        for k, idx in pq.observations.items():
            if k in fixed_q:
                obs.setdefault(k, []).append((idx, fixed_q[k], pc.xyz, True, len(seen), cov_c))
        for k, idx in pc.observations.items():
            if k in fixed_c:
                obs.setdefault(k, []).append((idx, fixed_c[k], yq, False, len(seen), cov_q))
    rows_M, rows_y, rows_inv, rows_z, rows_s, rows_k, rows_p, rows_c = [], [], [], [], [], [], [], []
    for k, items in obs.items():
        kf = (mq if k in fixed_q else mc).keyframes[k]
        idx = np.array([it[0] for it in items], dtype=np.int64)
        cam = kf.camera
        uv = cam.undistort_pixels(np.asarray(kf.keypoints, dtype=np.float64)[idx])
        ur = (np.asarray(kf.u_right, dtype=np.float64)[idx] if kf.u_right is not None and kf.stereo_baseline
              else np.full(len(idx), np.nan))  # fmt: skip
        rows_z.append(np.column_stack([uv, ur]))
        rows_s.append(1.2 ** np.asarray(kf.octaves, dtype=np.float64)[idx])
        b = float(kf.stereo_baseline) if kf.stereo_baseline else math.nan
        rows_k.append(np.tile([cam.fx, cam.fy, cam.cx, cam.cy, b], (len(idx), 1)))
        rows_M += [it[1] for it in items]
        rows_y += [it[2] for it in items]
        rows_inv += [it[3] for it in items]
        rows_p += [it[4] for it in items]
        rows_c += [it[5] for it in items]
    n = len(rows_M)
    variants = tuple(VARIANTS.items()) if o.weld_compare else ()
    return WeldJob(
        det.query_key, det.candidate_key, P0, Tq, Tc, None if up_q is None else np.asarray(up_q, float),
        np.array(rows_M).reshape(n, 3, 4), np.array(rows_y).reshape(n, 3), np.array(rows_inv, dtype=bool),
        np.concatenate(rows_z) if n else np.zeros((0, 3)), np.concatenate(rows_s) if n else np.zeros(0),
        np.concatenate(rows_k) if n else np.zeros((0, 5)), np.array(rows_p, dtype=np.int64),
        np.array(rows_c).reshape(n, 3, 3), o.weld_tilt_sigma_deg, o.weld_max_bound_m,
        o.weld_max_bound_deg, o.weld_min_points, variants, fit_sigmas,
    )  # fmt: skip


def _skew(v: F64) -> F64:
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)  # fmt: skip


class _Batch:
    """Every observation's whitened residual (N, 3) and Jacobian (N, 3, 6) at one pose, computed once per
    pose for all factors (gtsam calls each factor on its own). Each observation is whitened by its keypoint
    sigma and its (fixed) point's covariance carried into the observing camera at the start pose; a mono
    observation's third row is zero."""

    def __init__(self, job: WeldJob) -> None:
        self.job = job
        self.stereo = np.isfinite(job.z[:, 2])
        self._key = b""
        self.e, self.J = np.zeros((0, 3)), np.zeros((0, 3, 6))
        _, D, A = self._project(job.P0)
        n = len(job.y)
        DA = np.einsum("nij,njk->nik", D, A)
        C = np.einsum("nij,njk,nlk->nil", DA, job.pcov, DA) + job.sigma[:, None, None] ** 2 * np.eye(3)
        C[~self.stereo, 2, :] = C[~self.stereo, :, 2] = 0.0
        C[~self.stereo, 2, 2] = 1.0
        self.W = np.linalg.inv(np.linalg.cholesky(C)) if n else np.zeros((0, 3, 3))
        self.W[~self.stereo, 2, :] = 0.0

    def at(self, P: F64) -> tuple[F64, F64]:
        key = P.tobytes()
        if key != self._key:
            r, D, A = self._project(P)
            self.e = np.einsum("nij,nj->ni", self.W, r)
            self.J = np.einsum("nij,njk,nkl->nil", self.W, D, self._dpose(P, A))
            self._key = key
        return self.e, self.J

    def _f(self, P: F64) -> tuple[F64, F64]:
        """The point in the observing camera's fixed frame, f (N, 3), and df/dy (N, 3, 3)."""
        j, R, t = self.job, P[:3, :3], P[:3, 3]
        f, dy = np.empty((len(j.y), 3)), np.empty((len(j.y), 3, 3))
        inv = j.inverse
        f[inv], dy[inv] = (j.y[inv] - t) @ R, R.T  # a candidate point into the query camera: R^T (y - t)
        f[~inv], dy[~inv] = j.y[~inv] @ R.T + t, R  # a query point into the candidate map: R y + t
        return f, dy

    def _project(self, P: F64) -> tuple[F64, F64, F64]:
        """Residuals predicted - measured (N, 3; px), d(u, v, uR)/d(point in camera) (N, 3, 3) and
        d(point in camera)/dy (N, 3, 3)."""
        j = self.job
        f, dy = self._f(P)
        MR = j.M[:, :, :3]
        p = np.einsum("nij,nj->ni", MR, f) + j.M[:, :, 3]
        fx, fy, cx, cy, b = j.intr.T
        b = np.nan_to_num(b)
        z = np.where(np.abs(p[:, 2]) > 1e-6, p[:, 2], 1e-6)
        u = fx * p[:, 0] / z + cx
        pred = np.column_stack([u, fy * p[:, 1] / z + cy, u - fx * b / z])
        D = np.zeros((len(p), 3, 3))
        D[:, 0, 0] = D[:, 2, 0] = fx / z
        D[:, 0, 2] = -fx * p[:, 0] / z**2
        D[:, 1, 1] = fy / z
        D[:, 1, 2] = -fy * p[:, 1] / z**2
        D[:, 2, 2] = -fx * (p[:, 0] - b) / z**2
        return np.nan_to_num(pred - j.z), D, np.einsum("nij,njk->nik", MR, dy)

    def _dpose(self, P: F64, A: F64) -> F64:
        """d(point in camera)/dxi (N, 3, 6) for the right perturbation P Exp(xi), xi = [rot, trans]."""
        j = self.job
        f, _ = self._f(P)
        inv = j.inverse
        H = np.empty((len(f), 3, 6))
        H[inv, :, :3], H[inv, :, 3:] = _skew(f[inv]), -np.eye(3)  # d R^T (y - t) = [f^, -I] xi
        R = P[:3, :3]
        H[~inv, :, :3], H[~inv, :, 3:] = -R @ _skew(j.y[~inv]), R  # d (R y + t) = R [-y^, I] xi
        return np.einsum("nij,njk->nik", j.M[:, :, :3], H)


def _graph(batch: _Batch, keep: NDArray[np.bool_], up_q: F64 | None, P0: F64,
           tilt_sigma_deg: float) -> gtsam.NonlinearFactorGraph:  # fmt: skip
    graph = gtsam.NonlinearFactorGraph()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER)
    for i in np.flatnonzero(keep).tolist():
        d = 3 if batch.stereo[i] else 2

        def err(this: Any, v: Any, H: Any, i: int = i, d: int = d) -> F64:
            e, J = batch.at(v.atPose3(this.keys()[0]).matrix())
            if H is not None:
                H[0] = J[i, :d]
            return e[i, :d]

        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Unit.Create(d)),
                                     [0], err))  # fmt: skip
    if up_q is not None and tilt_sigma_deg >= 0:
        # the rotation about the two axes across the query camera's up direction stays the levelled fit's
        u = up_q / np.linalg.norm(up_q)
        a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        B = np.stack([a, np.cross(u, a)])
        R0 = gtsam.Rot3(P0[:3, :3])
        JB = np.hstack([B, np.zeros((2, 3))])

        def tilt(this: Any, v: Any, H: Any) -> F64:
            w = gtsam.Rot3.Logmap(R0.between(v.atPose3(this.keys()[0]).rotation()))
            if H is not None:
                H[0] = JB
            out: F64 = B @ w
            return out

        sigma = math.radians(tilt_sigma_deg) if tilt_sigma_deg > 0 else HELD_TILT_RAD
        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(2, sigma), [0], tilt))
    return graph


def _clustered(batch: _Batch, P: F64, keep: NDArray[np.bool_], bread: F64, dof: int) -> F64:
    """The weld's covariance clustered by point pair (sandwich ``bread meat bread``, ``bread`` the
    Marginals' inverse Hessian), or ``bread`` if larger: all observations of one point share its error."""
    e, J = batch.at(P)
    norm = np.linalg.norm(e, axis=1)
    w = np.where(norm <= HUBER, 1.0, HUBER / np.maximum(norm, 1e-12))  # Huber weights at the solution
    g = np.einsum("nij,ni->nj", J, e) * w[:, None]
    ids, inv = np.unique(batch.job.cluster[keep], return_inverse=True)
    G = np.zeros((len(ids), 6))
    np.add.at(G, inv, g[keep])
    c = len(ids)
    cov: F64 = bread @ (G.T @ G * c / max(c - dof, 1)) @ bread
    return cov if np.trace(cov) > np.trace(bread) else bread


def _solve_one(job: WeldJob, tilt_sigma_deg: float) -> WeldResult:
    four = job.up_q is not None and tilt_sigma_deg >= 0
    dof = "4dof" if four and tilt_sigma_deg == 0 else (f"tilt{tilt_sigma_deg:g}" if four else "6dof")
    n = len(job.y)
    res = WeldResult(False, "", job.P0, dof, n_obs=n)
    if len(np.unique(job.cluster)) < job.min_points:
        res.reason = f"{len(np.unique(job.cluster))} point pairs observed (at least {job.min_points})"
        return res
    batch = _Batch(job)
    thr = np.where(batch.stereo, CHI2_STEREO, CHI2_MONO)
    keep = np.ones(n, dtype=bool)
    P = gtsam.Pose3(job.P0)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(30)
    params.setRelativeErrorTol(1e-7)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for _ in range(OUTLIER_ROUNDS):
        graph = _graph(batch, keep, job.up_q, job.P0, tilt_sigma_deg)
        values = gtsam.Values()
        values.insert(0, P)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        P = values.atPose3(0)
        new = np.sum(batch.at(P.matrix())[0] ** 2, axis=1) <= thr
        n_points = len(np.unique(job.cluster[new]))
        if n_points < job.min_points:
            res.n_inliers = int(new.sum())
            res.reason = f"{n_points} point pairs fit the weld (at least {job.min_points})"
            return res
        if (new == keep).all():
            break
        keep = new
    chi2 = np.sum(batch.at(P.matrix())[0] ** 2, axis=1)
    res.P, res.n_inliers, res.n_stereo = P.matrix(), int(keep.sum()), int((keep & batch.stereo).sum())
    res.rms = float(math.sqrt(chi2[keep].sum() / max(int(np.where(batch.stereo, 3, 2)[keep].sum()), 1)))
    delta = se3_inverse(job.P0) @ res.P
    res.moved_m, res.turned_deg = float(np.linalg.norm(delta[:3, 3])), rotation_angle_deg(delta[:3, :3])
    try:
        bread = gtsam.Marginals(graph, values).marginalCovariance(0)
    except RuntimeError as exc:  # indeterminate: the points do not fix the transform
        res.reason = f"no covariance ({exc})"
        return res
    cov = _clustered(batch, P.matrix(), keep, bread, 4 if four else 6)
    res.bound_deg = math.degrees(BOUND_SIGMAS * math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    res.bound_m = BOUND_SIGMAS * math.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))
    if res.bound_m > job.max_bound_m or res.bound_deg > job.max_bound_deg:
        res.reason = (f"99 % bound {res.bound_m:.2f} m / {res.bound_deg:.2f} deg (limits "
                      f"{job.max_bound_m} m / {job.max_bound_deg} deg)")  # fmt: skip
        return res
    # the fit and the weld estimate one transform from the same points: where they disagree beyond their
    # bounds together, the points hold it only along a valley (distant points, one depth) and either may
    # sit at the wrong end of it
    if job.fit_sigmas is not None:
        lim_m = math.hypot(res.bound_m, BOUND_SIGMAS * job.fit_sigmas[1])
        lim_deg = math.hypot(res.bound_deg, BOUND_SIGMAS * math.degrees(job.fit_sigmas[0]))
        if res.moved_m > lim_m or res.turned_deg > lim_deg:
            res.reason = (f"moved the fit {res.moved_m:.2f} m / {res.turned_deg:.2f} deg, beyond both 99 % "
                          f"bounds together ({lim_m:.2f} m / {lim_deg:.2f} deg)")  # fmt: skip
            return res
    res.ok = True
    return res


def solve(job: WeldJob) -> WeldResult:
    """The weld (runs in a worker process); with ``job.variants`` the others are solved too and recorded."""
    t0 = time.process_time()
    res = _solve_one(job, job.tilt_sigma_deg)
    for name, sigma in job.variants:
        v = _solve_one(job, sigma)
        res.variants[name] = {"ok": v.ok, "dof": v.dof, "bound_m": v.bound_m, "bound_deg": v.bound_deg,
                              "candidate_from_query": (se3_inverse(job.Tc) @ v.P).tolist()}  # fmt: skip
    res.cpu_ms = 1e3 * (time.process_time() - t0)
    return res


def welded(maps: Any, det: Detection, job: WeldJob, res: WeldResult) -> Detection | None:
    """``det`` with the weld's transform, for the maps as they are now: the welded relative pose of the two
    keyframes is kept, so an optimisation applied while the weld was solved does not skew it. None if a
    keyframe is gone."""
    mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
    if mq is None or mc is None or det.query_key not in mq.keyframes or det.candidate_key not in mc.keyframes:
        return None
    rel = se3_inverse(job.Tc) @ res.P  # cam_candidate_from_cam_query
    Tc = np.asarray(mc.keyframes[det.candidate_key].world_from_cam, dtype=np.float64)
    Tq = np.asarray(mq.keyframes[det.query_key].world_from_cam, dtype=np.float64)
    S = Tc @ rel @ se3_inverse(Tq)
    return replace(det, target_from_source=Sim3(S[:3, :3], S[:3, 3], 1.0))


def _stereo(kf: Any) -> bool:
    return kf.u_right is not None and bool(kf.stereo_baseline) and bool(np.isfinite(kf.u_right).any())


async def weld_detection(
    verifier: Any,
    maps: Any,
    det: Detection,
    up_q: F64 | None,
    o: FitOptions,
    fit_sigmas: tuple[float, float] | None = None,
) -> tuple[Detection | None, dict[str, Any]]:
    """``det`` welded in the worker pool (``verifier``, :meth:`~.executor.Verifier.call`), or None if the
    weld is refused or a keyframe went meanwhile (``det`` itself if either keyframe has no stereo
    observations); and the weld's record (with the unwelded relative pose,
    so that a run can compare the two)."""
    mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
    q = mq.keyframes.get(det.query_key) if mq is not None else None
    c = mc.keyframes.get(det.candidate_key) if mc is not None else None
    if q is not None and c is not None and not (_stereo(q) and _stereo(c)):
        # nothing to weld by (a monocular keyframe, an older agent): the fit stands as it is
        return det, {"ok": False, "skipped": True, "reason": "no stereo observations"}
    job = build(maps, det, up_q, o, fit_sigmas)
    if job is None:
        return None, {"ok": False, "reason": "a keyframe is gone"}
    try:
        res: WeldResult = await verifier.call(solve, job)
    except Exception:
        logger.exception("weld %s -> %s failed", det.query_key, det.candidate_key)
        return None, {"ok": False, "reason": "the solve failed (see log)"}
    rec = res.to_dict(job.Tc)
    rec["unwelded_candidate_from_query"] = (se3_inverse(job.Tc) @ job.P0).tolist()
    if q is not None and c is not None:  # (a refused one's event carries these for the eval)
        rec.update(query=list(det.query_key), candidate=list(det.candidate_key),
                   query_t=float(q.timestamp), candidate_t=float(c.timestamp))  # fmt: skip
    if not res.ok:
        return None, rec
    out = welded(maps, det, job, res)
    if out is None:
        rec.update(ok=False, reason="a keyframe is gone")
    return out, rec


async def run(
    backend: Any, det: Detection, up_q: F64 | None, fit_sigmas: tuple[float, float] | None
) -> tuple[Detection | None, dict[str, Any] | None]:
    """The back-end's weld of ``det`` (itself when ``FitOptions.weld`` is off or the maps are not metric;
    None, with a refusal event, when refused) and the weld's record; ``fit_sigmas``: the levelled fit's
    (rad, m; None: no levelled fit, whose spread would say how far the weld may move it).
    A weld too unsure to bound the edge refuses its loop or merge: the fit was made from the same points,
    so it is no better determined. So does a weld that disagrees with the fit beyond both their bounds."""
    o = backend.options
    if not o.fit.weld or not o.fix_scale:
        return det, None
    out, rec = await weld_detection(backend.verifier, backend.server.stack.maps, det, up_q, o.fit, fit_sigmas)
    if out is None:
        kind = "loop" if det.is_loop else "merge"
        backend.server.events.add(
            kind, f"{kind} {det.query_key} -> {det.candidate_key} refused: weld {rec['reason']}",
            map_id=det.query_map, data={"refused": True, "weld": rec, **det.to_dict()},
        )  # fmt: skip
    return out, rec
