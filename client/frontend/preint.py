"""IMU preintegration between consecutive keyframes and the visual-inertial terms of local BA.

The preintegrated rotation / velocity / position deltas with their first-order bias Jacobians and
covariance follow Forster et al. (TRO 2017) as ORB-SLAM3 implements them (``IMU::Preintegrated``);
the residuals and Jacobians are ORB-SLAM3's ``EdgeInertial`` (bias of the first keyframe) and its bias
random-walk edges, in this front-end's parametrisation: poses ``cam_from_world`` updated on the left
with ``[w, v]`` (:mod:`.optim`), velocities in the world, biases ``[gyro, accel]`` in the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import so3_exp, so3_log

F64 = NDArray[np.float64]

GRAVITY = np.array([0.0, 0.0, -9.81])  # the VIO frame is gravity-aligned (z up) before these are used
ANCHOR_INFO_SCALE = 1e-2  # ORB-SLAM3's down-weighting of the edge into the held keyframe
ANCHOR_HUBER_CHI2 = 16.92  # ORB-SLAM3's Huber threshold (9 DoF) of that edge
_EYE3 = np.eye(3)


def skew(x: F64) -> F64:
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def right_jacobian(phi: F64) -> F64:
    th = float(np.linalg.norm(phi))
    W = skew(phi)
    if th < 1e-5:
        return np.eye(3) - 0.5 * W
    return np.eye(3) - (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * (W @ W)  # type: ignore[no-any-return]


def right_jacobian_inv(phi: F64) -> F64:
    th = float(np.linalg.norm(phi))
    W = skew(phi)
    if th < 1e-5:
        return np.eye(3) + 0.5 * W
    return np.eye(3) + 0.5 * W + (1 / th**2 - (1 + np.cos(th)) / (2 * th * np.sin(th))) * (W @ W)  # type: ignore[no-any-return]


@dataclass
class Preintegrated:
    """Body-frame deltas from keyframe i to j at the linearisation bias ``bias`` ([gyro, accel])."""

    bias: F64
    gyro_sigma2: float  # continuous noise densities squared
    acc_sigma2: float
    dt: float = 0.0
    dR: F64 = field(default_factory=lambda: np.eye(3))
    dV: F64 = field(default_factory=lambda: np.zeros(3))
    dP: F64 = field(default_factory=lambda: np.zeros(3))
    JRg: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    JVg: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    JVa: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    JPg: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    JPa: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    cov: F64 = field(default_factory=lambda: np.zeros((9, 9)))  # [R, V, P]

    def integrate(self, gyro: F64, acc: F64, dt: float) -> None:
        a = acc - self.bias[3:]
        w = gyro - self.bias[:3]
        dR = self.dR
        aw = skew(a)
        # dR a and dR [a]x once: the scaled products below (by -1 and 0.5) are exact multiples of them
        dRa = dR @ a
        dRaw = dR @ aw
        dRaw_JRg = dRaw @ self.JRg
        dR_dt = dR * dt
        half_dR_dt2 = 0.5 * dR * dt * dt
        A = np.eye(9)
        B = np.zeros((9, 6))
        self.dP = self.dP + self.dV * dt + 0.5 * dRa * dt * dt
        self.dV = self.dV + dRa * dt
        A[3:6, 0:3] = -dRaw * dt
        A[6:9, 0:3] = -0.5 * dRaw * dt * dt
        A[6:9, 3:6] = _EYE3 * dt
        B[3:6, 3:6] = dR_dt
        B[6:9, 3:6] = half_dR_dt2
        self.JPa = self.JPa + self.JVa * dt - half_dR_dt2
        self.JPg = self.JPg + self.JVg * dt - 0.5 * dRaw_JRg * dt * dt
        self.JVa = self.JVa - dR_dt
        self.JVg = self.JVg - dRaw_JRg * dt
        dRi = so3_exp(w * dt)
        Jr = right_jacobian(w * dt)
        A[0:3, 0:3] = dRi.T
        Jr_dt = Jr * dt
        B[0:3, 0:3] = Jr_dt
        # discrete noise of one sample: density^2 / dt (a diagonal, so B N is B's columns scaled)
        n_diag = np.array([self.gyro_sigma2 / dt] * 3 + [self.acc_sigma2 / dt] * 3)
        self.cov = A @ self.cov @ A.T + (B * n_diag) @ B.T
        self.JRg = dRi.T @ self.JRg - Jr_dt
        U, _, Vt = np.linalg.svd(dR @ dRi)
        self.dR = U @ Vt
        self.dt += dt

    def corrected(self, bias: F64) -> tuple[F64, F64, F64]:
        """The deltas at another bias, to first order (the rotation on the manifold)."""
        dbg = bias[:3] - self.bias[:3]
        dba = bias[3:] - self.bias[3:]
        dR = self.dR @ so3_exp(self.JRg @ dbg)
        dV = self.dV + self.JVg @ dbg + self.JVa @ dba
        dP = self.dP + self.JPg @ dbg + self.JPa @ dba
        return dR, dV, dP


class KeyframeImu:
    """Collects a keyframe interval's IMU samples and preintegrates them when the next keyframe is made."""

    def __init__(self, params: dict[str, float]) -> None:
        self.gyro_sigma2 = float(params.get("gyroscope_noise_density", 1.7e-4)) ** 2
        self.acc_sigma2 = float(params.get("accelerometer_noise_density", 2e-3)) ** 2
        self.gyro_walk2 = float(params.get("gyroscope_random_walk", 2e-5)) ** 2
        self.acc_walk2 = float(params.get("accelerometer_random_walk", 3e-3)) ** 2
        self._samples: list[F64] = []
        self._last: F64 | None = None  # the last sample integrated (t, gyro, accel)

    def add(self, samples: F64) -> None:
        if len(samples):
            self._samples.append(np.asarray(samples, dtype=np.float64))

    def reset(self) -> None:
        self._samples = []

    def take(self, bias: F64) -> Preintegrated | None:
        """The preintegration of the samples since the last ``take`` (None without any)."""
        pre = Preintegrated(bias.copy(), self.gyro_sigma2, self.acc_sigma2)
        rows = np.concatenate(self._samples) if self._samples else np.zeros((0, 7))
        self._samples = []
        for row in rows:
            last = self._last
            if last is not None and 0.0 < row[0] - last[0] < 0.5:
                # the samples are instantaneous rates: their mean over the step (a held sample lags
                # the motion by half a step, which the tight preintegrated covariance would not forgive)
                mid = 0.5 * (last + row)
                pre.integrate(mid[1:4], mid[4:7], float(row[0] - last[0]))
            self._last = row
        return pre if pre.dt > 0 else None


@dataclass
class InertialEdge:
    """Preintegration ``pre`` between problem cameras ``i`` (earlier) and ``j``.

    ``anchor``: ``i`` is held (the keyframe before the window). As in ORB-SLAM3's local inertial BA,
    that edge's information is scaled down and Huber-weighted: the held velocity and biases carry the
    previous window's error, which a full-weight edge would pass on into this window (and so on along
    the trajectory) instead of letting the vision correct it."""

    i: int
    j: int
    pre: Preintegrated
    anchor: bool = False


@dataclass
class InertialWindow:
    """The inertial part of a local BA: per problem camera its velocity (world) and bias, the edges
    between consecutive keyframes and the body-from-camera extrinsic. ``v``/``b`` hold the solution
    after :func:`.optim.bundle_adjust`."""

    v: F64  # (C,3)
    b: F64  # (C,6) [gyro, accel]
    edges: list[InertialEdge]
    cam_from_body: F64
    gyro_walk2: float
    acc_walk2: float
    bias_prior_info: F64  # (6,) information of each free camera's bias about its start value
    b0: F64 = field(default_factory=lambda: np.zeros((0, 6)))

    def __post_init__(self) -> None:
        if len(self.b0) == 0:
            self.b0 = self.b.copy()

    def _body(self, T_cw: F64) -> tuple[F64, F64, F64]:
        """(R_wb, p_wb, R_wc) of a ``cam_from_world``."""
        R_wc = T_cw[:3, :3].T
        p_wc = -R_wc @ T_cw[:3, 3]
        R_cb, p_cb = self.cam_from_body[:3, :3], self.cam_from_body[:3, 3]
        return R_wc @ R_cb, R_wc @ p_cb + p_wc, R_wc

    def _edge(self, poses: F64, v: F64, b: F64, e: InertialEdge) -> tuple[F64, F64, F64]:
        """Residual (15,) [R, V, P, bg walk, ba walk] and whitening (15,15) of one edge; the state
        Jacobian is built by :meth:`_jacobian` from the pieces kept here."""
        Ri, pi, _ = self._body(poses[e.i])
        Rj, pj, _ = self._body(poses[e.j])
        dR, dV, dP = e.pre.corrected(b[e.i])
        dt = e.pre.dt
        eR = so3_log(dR.T @ Ri.T @ Rj)
        eV = Ri.T @ (v[e.j] - v[e.i] - GRAVITY * dt) - dV
        eP = Ri.T @ (pj - pi - v[e.i] * dt - 0.5 * GRAVITY * dt * dt) - dP
        eb = b[e.j] - b[e.i]
        return np.concatenate([eR, eV, eP, eb]), Ri, Rj

    def _info(self, e: InertialEdge) -> F64:
        info = np.zeros((15, 15))
        cov = e.pre.cov + 1e-12 * np.eye(9)
        info[:9, :9] = np.linalg.inv(cov) * (ANCHOR_INFO_SCALE if e.anchor else 1.0)
        dt = max(e.pre.dt, 1e-3)
        info[9:12, 9:12] = np.eye(3) / (self.gyro_walk2 * dt)
        info[12:15, 12:15] = np.eye(3) / (self.acc_walk2 * dt)
        return info

    def cost(self, poses: F64, v: F64, b: F64) -> float:
        c = 0.0
        for e in self.edges:
            r, _, _ = self._edge(poses, v, b, e)
            info = self._info(e)
            chi2 = float(r[:9] @ info[:9, :9] @ r[:9])
            if e.anchor and chi2 > ANCHOR_HUBER_CHI2:
                chi2 = 2.0 * np.sqrt(ANCHOR_HUBER_CHI2 * chi2) - ANCHOR_HUBER_CHI2
            c += chi2 + float(r[9:] @ info[9:, 9:] @ r[9:])
        db = b - self.b0
        c += float((db * db * self.bias_prior_info).sum())
        return c

    def _pose_to_body(self, T_cw: F64) -> F64:
        """(6,6) d[phi_body, dp_world] / d[w, v] of the left update of ``cam_from_world``."""
        _, _, R_wc = self._body(T_cw)
        R_cb, p_cb = self.cam_from_body[:3, :3], self.cam_from_body[:3, 3]
        M = np.zeros((6, 6))
        M[:3, :3] = -R_cb.T
        M[3:, :3] = R_wc @ skew(p_cb)
        M[3:, 3:] = -R_wc
        return M

    def normal_equations(self, poses: F64, v: F64, b: F64, free_index: NDArray[np.int64]) -> tuple[F64, F64]:
        """H (15 nf, 15 nf), g (15 nf) over the free cameras' [pose(6), v(3), bg(3), ba(3)] blocks."""
        nf = int(free_index.max()) + 1 if len(free_index) else 0
        H = np.zeros((15 * nf, 15 * nf))
        g = np.zeros(15 * nf)
        for e in self.edges:
            r, Ri, Rj = self._edge(poses, v, b, e)
            dt = e.pre.dt
            eR = r[:3]
            Jri = right_jacobian_inv(eR)
            dbg = b[e.i][:3] - e.pre.bias[:3]
            # Jacobians in [phi_i, dp_i, v_i, bg_i, ba_i | phi_j, dp_j, v_j, bg_j, ba_j]
            J = np.zeros((15, 30))
            J[0:3, 0:3] = -Jri @ Rj.T @ Ri
            J[0:3, 15:18] = Jri
            J[0:3, 9:12] = -Jri @ so3_exp(eR).T @ right_jacobian(e.pre.JRg @ dbg) @ e.pre.JRg
            J[3:6, 0:3] = skew(Ri.T @ (v[e.j] - v[e.i] - GRAVITY * dt))
            J[3:6, 6:9] = -Ri.T
            J[3:6, 21:24] = Ri.T
            J[3:6, 9:12] = -e.pre.JVg
            J[3:6, 12:15] = -e.pre.JVa
            _, pi, _ = self._body(poses[e.i])
            _, pj, _ = self._body(poses[e.j])
            J[6:9, 0:3] = skew(Ri.T @ (pj - pi - v[e.i] * dt - 0.5 * GRAVITY * dt * dt))
            J[6:9, 3:6] = -Ri.T
            J[6:9, 18:21] = Ri.T
            J[6:9, 6:9] = -Ri.T * dt
            J[6:9, 9:12] = -e.pre.JPg
            J[6:9, 12:15] = -e.pre.JPa
            J[9:15, 9:15] = -np.eye(6)
            J[9:15, 24:30] = np.eye(6)
            info = self._info(e)
            if e.anchor:
                chi2 = float(r[:9] @ info[:9, :9] @ r[:9])
                if chi2 > ANCHOR_HUBER_CHI2:
                    info[:9, :9] *= np.sqrt(ANCHOR_HUBER_CHI2 / chi2)  # IRLS weight of the Huber loss
            for side, cam in ((0, e.i), (15, e.j)):
                J[:, side : side + 6] = J[:, side : side + 6] @ self._pose_to_body(poses[cam])
            blocks = [(free_index[e.i], 0), (free_index[e.j], 15)]
            JI = J.T @ info
            Hl = JI @ J
            gl = JI @ r
            for fa, sa in blocks:
                if fa < 0:
                    continue
                g[15 * fa : 15 * fa + 15] += gl[sa : sa + 15]
                for fb, sb in blocks:
                    if fb >= 0:
                        H[15 * fa : 15 * fa + 15, 15 * fb : 15 * fb + 15] += Hl[sa : sa + 15, sb : sb + 15]
        for c in np.flatnonzero(free_index >= 0):
            f = free_index[c]
            sl = slice(15 * f + 9, 15 * f + 15)
            H[sl, sl] += np.diag(self.bias_prior_info)
            g[sl] += self.bias_prior_info * (b[c] - self.b0[c])
        return H, g
