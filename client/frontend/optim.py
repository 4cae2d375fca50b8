"""Motion-only pose refinement and local bundle adjustment (numpy, Schur complement, Huber).

Why not gtsam or pycolmap here: measured on this machine, one gtsam 4.3 linear elimination of a
10-keyframe / 2000-point stereo window (``GenericStereoFactor3D``) takes 0.3 s, 0.5-3 s per LM run,
which would cap the front-end far below 20 fps; pycolmap's bundle adjustment has no stereo
(``uR``) residual, which is what fixes the metric scale.  The window problem is small and its
structure regular, so a vectorised Levenberg-Marquardt with the point Schur complement
(scipy.sparse) solves it in a few milliseconds per iteration.

Model: undistorted left pixels with ``fx, fy, cx, cy`` and a virtual rectified right camera at
baseline ``b`` along x: ``u = fx x/z + cx, v = fy y/z + cy, uR = fx (x - b)/z + cx``.  Poses are
``cam_from_world`` 4x4, updated on the left: ``T <- [[Exp(w), v], [0, 1]] @ T`` with tangent
``[w, v]`` (rotation first, gtsam's order).  Mono observations have ``uR = NaN``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from hivemap.client.frontend.preint import InertialWindow
from hivemap.maps.geometry import so3_exp, so3_log

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

CHI2_MONO = 5.991
CHI2_STEREO = 7.815


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float


def _skew_batch(x: F64) -> F64:
    S = np.zeros((len(x), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -x[:, 2], x[:, 1]
    S[:, 1, 0], S[:, 1, 2] = x[:, 2], -x[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -x[:, 1], x[:, 0]
    return S


def _pose_jacobian(Jp: F64, pc: F64) -> F64:
    """d[u,v,uR]/d[w, v] (N,3,6) of a left update, from d[u,v,uR]/d(pc) (N,3,3)."""
    Jx = np.empty((len(pc), 3, 6))
    Jx[:, :, :3] = -(Jp @ _skew_batch(pc))
    Jx[:, :, 3:] = Jp
    return Jx


def project(k: Intrinsics, pc: F64) -> F64:
    """Camera-frame points (N,3) -> (N,3) [u, v, uR] undistorted pixels."""
    z = pc[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    out = np.empty((len(pc), 3))
    out[:, 0] = k.fx * pc[:, 0] / zs + k.cx
    out[:, 1] = k.fy * pc[:, 1] / zs + k.cy
    out[:, 2] = out[:, 0] - k.fx * k.baseline / zs
    return out


def _linearize(k: Intrinsics, pc: F64) -> F64:
    """d[u,v,uR]/d(pc) (N,3,3)."""
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    iz = 1.0 / np.where(np.abs(z) > 1e-9, z, 1e-9)
    iz2 = iz * iz
    J = np.zeros((len(pc), 3, 3))
    J[:, 0, 0] = k.fx * iz
    J[:, 0, 2] = -k.fx * x * iz2
    J[:, 1, 1] = k.fy * iz
    J[:, 1, 2] = -k.fy * y * iz2
    J[:, 2, 0] = k.fx * iz
    J[:, 2, 2] = -k.fx * (x - k.baseline) * iz2
    return J


def _residuals(k: Intrinsics, pc: F64, meas: F64) -> tuple[F64, F64]:
    """Residuals (N,3) (NaN uR rows zeroed) and row mask (N,3)."""
    e = project(k, pc)
    e -= meas
    mask = np.ones_like(e)
    mono = np.isnan(meas[:, 2])
    mask[mono, 2] = 0.0
    e[mono, 2] = 0.0
    e[pc[:, 2] <= 1e-3] = 0.0  # behind camera: no information (rejected as outlier by chi2 below)
    return e, mask


def chi2_of(k: Intrinsics, pc: F64, meas: F64, inv_sigma2: F64) -> F64:
    e, _ = _residuals(k, pc, meas)
    chi2 = (e * e).sum(1) * inv_sigma2
    chi2[pc[:, 2] <= 1e-3] = np.inf
    return chi2


def chi2_thresholds(meas: F64) -> F64:
    """Per observation: the 95% chi2 gate, 2 DoF (mono) or 3 DoF (with a right-image coordinate)."""
    return np.where(np.isnan(meas[:, 2]), CHI2_MONO, CHI2_STEREO)


def _huber_weights(chi2: F64, th: F64) -> F64:
    w = np.ones_like(chi2)
    big = chi2 > th
    w[big] = np.sqrt(th[big] / chi2[big])
    return w


def _robust_cost(chi2: F64, th: F64) -> float:
    c = np.where(chi2 <= th, chi2, 2.0 * np.sqrt(th * chi2) - th)
    return float(c.sum())


def left_update(T: F64, d: F64) -> F64:
    U = np.eye(4)
    U[:3, :3] = so3_exp(d[:3])
    U[:3, 3] = d[3:]
    return U @ T


def pose_hessian(k: Intrinsics, T_cw: F64, X: F64, meas: F64, inv_sigma2: F64) -> F64:
    """Gauss-Newton information (6,6) of a pose from its (inlier) observations, tangent [w, v]."""
    pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    _, mask = _residuals(k, pc, meas)
    Jx = _pose_jacobian(_linearize(k, pc), pc)
    W = mask * inv_sigma2[:, None]
    A = Jx.reshape(-1, 6)
    return (A * W.reshape(-1, 1)).T @ A  # type: ignore[no-any-return]


@dataclass(frozen=True)
class PosePrior:
    """A Gaussian prior on ``cam_from_world`` (the IMU prediction): mean and 6x6 information of the
    left tangent ``[w, v]`` (``T = [[Exp(w), v], [0, 1]] @ mean``)."""

    T_cw: F64
    info: F64

    def residual(self, T: F64) -> tuple[F64, F64]:
        """(r, dr/dd) of ``T`` against the mean, for a left update ``d`` of ``T``."""
        E = T @ np.linalg.inv(self.T_cw)
        r = np.concatenate([so3_log(E[:3, :3]), E[:3, 3]])
        J = np.eye(6)
        t = E[:3, 3]
        J[3:, :3] = -np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        return r, J

    def chi2(self, T: F64, other_info: F64 | None = None, rotation_only: bool = False) -> float:
        """Mahalanobis distance^2 of ``T`` from the mean; with ``other_info`` (the information of
        ``T``'s own estimate) under the sum of both covariances. Only the components the prior
        constrains count; ``rotation_only``: of the attitude alone, under its marginal covariance."""
        if other_info is None and not rotation_only:
            r, _ = self.residual(T)
            return float(r @ self.info @ r)
        full, rot = self.chi2_and_attitude(T, other_info)
        return rot if rotation_only else full

    def chi2_and_attitude(self, T: F64, other_info: F64 | None = None) -> tuple[float, float]:
        """(:meth:`chi2` of the constrained components, of the attitude alone) from one residual and one
        marginal covariance, as the IMU gate needs both on every frame."""
        r, _ = self.residual(T)
        use, cov = self._marginal_cov(other_info)
        ru = r[use]
        full = float(ru @ np.linalg.solve(cov, ru))
        att = np.flatnonzero(use) < 3
        if not att.any():
            return full, 0.0
        ra = ru[att]
        return full, float(ra @ np.linalg.solve(cov[np.ix_(att, att)], ra))

    def _marginal_cov(self, other_info: F64 | None) -> tuple[NDArray[np.bool_], F64]:
        """(components the prior constrains, their covariance, plus ``other_info``'s if given)."""
        use = np.diag(self.info) > 0
        cov = np.asarray(np.linalg.inv(self.info[np.ix_(use, use)]), dtype=np.float64)
        if other_info is not None:
            cov = cov + np.linalg.inv(other_info + 1e-9 * np.eye(6))[np.ix_(use, use)]
        return use, cov


def optimize_pose(
    k: Intrinsics,
    T_cw: F64,
    X: F64,
    meas: F64,
    inv_sigma2: F64,
    rounds: int = 4,
    iterations: int = 6,
    prior: PosePrior | None = None,
) -> tuple[F64, NDArray[np.bool_]]:
    """Motion-only refinement (ORB-SLAM style: re-classify outliers after each round).

    X (N,3) world points, meas (N,3) [u, v, uR|NaN], inv_sigma2 (N,).  ``prior``: the IMU's pose
    prediction, a term of the same least squares (as ORB-SLAM3's inertial edge in pose
    optimisation).  Returns (T_cw, inliers).
    """
    T = T_cw.copy()
    th = chi2_thresholds(meas)
    inl = np.ones(len(X), bool)
    for rnd in range(rounds):
        idx = np.flatnonzero(inl)  # the inliers change between rounds only
        if len(idx) < 6:
            return T, inl
        X_in, meas_in, s2_in, th_in = X[idx], meas[idx], inv_sigma2[idx], th[idx]
        for _ in range(iterations):
            pc = X_in @ T[:3, :3].T + T[:3, 3]
            e, mask = _residuals(k, pc, meas_in)
            chi2 = (e * e).sum(1) * s2_in
            w = s2_in * (_huber_weights(chi2, th_in) if rnd < rounds - 1 else 1.0)
            Jx = _pose_jacobian(_linearize(k, pc), pc)
            W = mask * w[:, None]
            A = Jx.reshape(-1, 6)
            AW = A * W.reshape(-1, 1)
            H = AW.T @ A
            g = AW.T @ e.reshape(-1)
            if prior is not None:
                r, Jr = prior.residual(T)
                JI = Jr.T @ prior.info
                H = H + JI @ Jr
                g = g + JI @ r
            try:
                d = np.asarray(np.linalg.solve(H + 1e-9 * np.eye(6), -g), dtype=np.float64)
            except np.linalg.LinAlgError:
                return T, inl
            T = left_update(T, d)
            if np.linalg.norm(d) < 1e-7:
                break
        pc = X @ T[:3, :3].T + T[:3, 3]
        chi2 = chi2_of(k, pc, meas, inv_sigma2)
        inl = chi2 < th
    return T, inl


@dataclass
class BAProblem:
    """Observations of a local BA.

    poses: (C,4,4) cam_from_world; fixed: (C,) bool; points: (P,3); cam_idx, pt_idx: (O,);
    meas: (O,3) [u, v, uR|NaN] undistorted pixels; inv_sigma2: (O,).
    """

    poses: F64
    fixed: NDArray[np.bool_]
    points: F64
    cam_idx: I64
    pt_idx: I64
    meas: F64
    inv_sigma2: F64


def _ba_cost(k: Intrinsics, poses: F64, points: F64, prob: BAProblem, active: NDArray[np.bool_]) -> float:
    R = poses[prob.cam_idx, :3, :3]
    t = poses[prob.cam_idx, :3, 3]
    pc = np.einsum("nij,nj->ni", R, points[prob.pt_idx]) + t
    chi2 = chi2_of(k, pc, prob.meas, prob.inv_sigma2)
    chi2 = np.where(np.isfinite(chi2), chi2, 1e6)
    return _robust_cost(chi2[active], chi2_thresholds(prob.meas)[active])


def bundle_adjust(
    k: Intrinsics,
    prob: BAProblem,
    iterations: int = 10,
    active: NDArray[np.bool_] | None = None,
    inertial: InertialWindow | None = None,
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Levenberg-Marquardt over free poses and all points with a Huber loss.

    ``inertial``: preintegrated IMU terms between consecutive cameras; each free camera's block is
    then [pose, velocity, gyro bias, accel bias] (15), the points are still eliminated, and the
    solution's velocities and biases are left in ``inertial.v``/``inertial.b``.
    Returns (poses, points, inlier mask over observations by chi2 at the solution).
    """
    C, P, n_obs = len(prob.poses), len(prob.points), len(prob.cam_idx)
    poses = prob.poses.copy()
    points = prob.points.copy()
    act = np.ones(n_obs, bool) if active is None else active.copy()
    th_all = chi2_thresholds(prob.meas)
    free_index = -np.ones(C, np.int64)
    free = np.flatnonzero(~prob.fixed)
    free_index[free] = np.arange(len(free))
    nf = len(free)
    lam = 1e-4
    cost = _ba_cost(k, poses, points, prob, act)
    vel, bias = (inertial.v.copy(), inertial.b.copy()) if inertial is not None else (None, None)
    if inertial is not None:
        cost += inertial.cost(poses, vel, bias)
    rel = 1.0
    # the active observations and their aggregation into points and free cameras, the same every iteration
    ci, pi, meas = prob.cam_idx[act], prob.pt_idx[act], prob.meas[act]
    inv_s2, th = prob.inv_sigma2[act], th_all[act]
    n = len(ci)
    # per-point / per-camera sums as sparse aggregation products (much faster than np.add.at)
    agg_p = sp.csr_matrix((np.ones(n), (pi, np.arange(n))), shape=(P, n))
    fi = free_index[ci]
    hasc = np.flatnonzero(fi >= 0)
    fh = fi[hasc]
    blk_p = pi[hasc]
    agg_c = sp.csr_matrix((np.ones(len(hasc)), (fh, np.arange(len(hasc)))), shape=(nf, len(hasc)))
    for _ in range(iterations):
        R = poses[ci, :3, :3]
        pc = np.einsum("nij,nj->ni", R, points[pi]) + poses[ci, :3, 3]
        e, mask = _residuals(k, pc, meas)
        chi2 = (e * e).sum(1) * inv_s2
        w = inv_s2 * _huber_weights(chi2, th)
        w[pc[:, 2] <= 1e-3] = 0.0
        W = mask * w[:, None]
        Jpc = _linearize(k, pc)
        Jx = _pose_jacobian(Jpc, pc)  # (n,3,6)
        Jp = np.matmul(Jpc, R)  # (n,3,3)
        JxW_T = (Jx * W[:, :, None]).transpose(0, 2, 1)  # (n,6,3)
        JpW_T = (Jp * W[:, :, None]).transpose(0, 2, 1)  # (n,3,3)
        Hpp = (agg_p @ np.matmul(JpW_T, Jp).reshape(n, 9)).reshape(P, 3, 3)
        gp = agg_p @ np.matmul(JpW_T, e[:, :, None])[:, :, 0]
        Hcc = (agg_c @ np.matmul(JxW_T[hasc], Jx[hasc]).reshape(-1, 36)).reshape(nf, 6, 6)
        gc = agg_c @ np.matmul(JxW_T[hasc], e[hasc][:, :, None])[:, :, 0]
        # camera-point blocks (one observation per (keyframe, point)) written straight into the dense
        # (6 nf x 3 P) layout the Schur complement multiplies
        Hcp_blk = np.matmul(JxW_T[hasc], Jp[hasc])  # (m, 6, 3)
        Hcp = np.zeros((6 * nf, 3 * P))
        Hcp.reshape(nf, 6, P, 3)[fh, :, blk_p, :] = Hcp_blk
        diag_c = np.einsum("nii->ni", Hcc)
        diag_p = np.einsum("nii->ni", Hpp)
        if inertial is not None:
            assert vel is not None and bias is not None
            Hi, gi = inertial.normal_equations(poses, vel, bias, free_index)
            diag_i = np.diag(Hi).copy()
            pose_rows = (np.arange(nf)[:, None] * 15 + np.arange(6)[None, :]).ravel()
        dx: F64 | None = None
        for _try in range(4):
            Hpp_d = Hpp.copy()
            Hpp_d[:, np.arange(3), np.arange(3)] += lam * diag_p + 1e-9
            Hpp_inv = np.linalg.inv(Hpp_d)
            if nf > 0:
                Hcc_full = np.zeros((6 * nf, 6 * nf))
                for j in range(nf):
                    blk = Hcc[j] + np.diag(lam * diag_c[j] + 1e-9)
                    Hcc_full[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = blk
                # Hcp Hpp^-1 on the observed blocks only (the rest is zero), by the same einsum arithmetic
                Y = np.zeros((6 * nf, 3 * P))
                Y.reshape(nf, 6, P, 3)[fh, :, blk_p, :] = np.einsum("kci,kij->kcj", Hcp_blk, Hpp_inv[blk_p])
                S = Hcc_full - Y @ Hcp.T
                rhs = -gc.ravel() + Y @ gp.ravel()
                if inertial is not None:
                    # the reduced visual system embedded in the pose rows of the inertial blocks
                    S15 = Hi + np.diag(lam * diag_i + 1e-9)
                    S15[np.ix_(pose_rows, pose_rows)] += S
                    rhs15 = -gi
                    rhs15[pose_rows] += rhs
                    S, rhs = S15, rhs15
                try:
                    dx = np.linalg.solve(S, rhs)
                except np.linalg.LinAlgError:
                    dx = np.linalg.lstsq(S, rhs, rcond=None)[0]
                dc = dx[pose_rows] if inertial is not None else dx
                dp = -(gp.ravel() + Hcp.T @ dc)
            else:
                dc = np.zeros(0)
                dp = -gp.ravel()
            dp = np.einsum("nij,nj->ni", Hpp_inv, dp.reshape(P, 3))
            new_poses = poses.copy()
            for j, c in enumerate(free):
                new_poses[c] = left_update(poses[c], dc[6 * j : 6 * j + 6])
            new_points = points + dp
            new_cost = _ba_cost(k, new_poses, new_points, prob, act)
            if inertial is not None and vel is not None and bias is not None:
                new_vel, new_bias = vel.copy(), bias.copy()
                if nf > 0:
                    assert dx is not None
                    blk = dx.reshape(nf, 15)
                    new_vel[free] += blk[:, 6:9]
                    new_bias[free] += blk[:, 9:15]
                new_cost += inertial.cost(new_poses, new_vel, new_bias)
            if new_cost < cost:
                poses, points = new_poses, new_points
                if inertial is not None:
                    vel, bias = new_vel, new_bias
                rel = (cost - new_cost) / max(cost, 1e-12)
                cost = new_cost
                lam = max(lam / 10.0, 1e-7)
                break
            lam *= 10.0
        else:
            break
        if rel < 1e-6:
            break
    if inertial is not None and vel is not None and bias is not None:
        inertial.v, inertial.b = vel, bias
    R = poses[prob.cam_idx, :3, :3]
    pc = np.einsum("nij,nj->ni", R, points[prob.pt_idx]) + poses[prob.cam_idx, :3, 3]
    chi2 = chi2_of(k, pc, prob.meas, prob.inv_sigma2)
    return poses, points, chi2 < th_all
