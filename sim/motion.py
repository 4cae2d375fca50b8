"""A planned agent's motion in time: :class:`Trajectory` (position, attitude and their derivatives from
splines, quadrotor differential flatness for UAVs) and its speed profile."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, CubicSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d

from hivemap.sim.routes import Route
from hivemap.sim.scenarios import (
    AgentSpec,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
GRAVITY = 9.81
G_WORLD = np.array([0.0, 0.0, -GRAVITY])  # gravity vector in the world frame (z up)
UAV_GROUND_HEIGHT = 0.25  # UAV body height when standing on the ground (disjoint scenario)


def _smoothstep5(x: F64) -> F64:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _smoothstep5_integral(x: F64) -> F64:
    """Integral of smoothstep5 from 0 to x (x in [0, 1]); equals 0.5 at 1."""
    x = np.clip(x, 0.0, 1.0)
    return x**6 - 3 * x**5 + 2.5 * x**4


def _hat(w: F64) -> F64:
    """(N, 3) -> (N, 3, 3) skew matrices."""
    z = np.zeros(w.shape[0])
    return np.stack(
        [
            np.stack([z, -w[:, 2], w[:, 1]], 1),
            np.stack([w[:, 2], z, -w[:, 0]], 1),
            np.stack([-w[:, 1], w[:, 0], z], 1),
        ],
        axis=1,
    )


def _normalize_with_rate(v: F64, vdot: F64) -> tuple[F64, F64]:
    """n = v / |v| and its time derivative (I - n n^T) vdot / |v|, row-wise."""
    nrm = np.linalg.norm(v, axis=1, keepdims=True)
    n = v / nrm
    ndot = (vdot - n * np.sum(n * vdot, axis=1, keepdims=True)) / nrm
    return n, ndot


@dataclass
class Trajectory:
    """True motion of one agent, t in seconds from the scenario start (t = 0 .. duration).

    ``position`` / ``velocity`` / ``acceleration`` are world-frame (z up); ``rotation`` is
    world_from_body (body x forward, y left, z up); ``angular_velocity`` is in the body frame. All
    accept a scalar or an array of times and return (N, ...) arrays (N = 1 for a scalar).
    """

    agent_id: str
    kind: str
    pos: BSpline  # t -> (3,)
    yaw: BSpline  # t -> heading (rad, unwrapped), body x axis azimuth from east
    thrust_aligned: bool  # UAV: body z along a - g
    duration: float
    route: Route | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    move_span: tuple[float, float] = (0.0, float("inf"))  # exactly at rest outside this interval

    def _ev(self, spline: BSpline, t: float | F64, nu: int = 0) -> F64:
        tt = self._t(t)
        a, b = self.move_span
        out = np.asarray(spline(np.clip(tt, a, b), nu))
        if nu > 0:
            out[(tt < a) | (tt > b)] = 0.0
        return out

    def _t(self, t: float | F64) -> F64:
        return np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), 0.0, self.duration)

    def position(self, t: float | F64) -> F64:
        return self._ev(self.pos, t)

    def velocity(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 1)

    def acceleration(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 2)

    def jerk(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 3)

    def _attitude(self, t: float | F64) -> tuple[F64, F64]:
        """(R (N,3,3) world_from_body, omega_body (N,3)) computed analytically."""
        tt = self._t(t)
        n = len(tt)
        psi = self._ev(self.yaw, tt)
        psid = self._ev(self.yaw, tt, 1)
        if self.thrust_aligned:
            zt = self.acceleration(tt) - G_WORLD[None, :]
            ztd = self.jerk(tt)
        else:
            zt = np.tile([0.0, 0.0, 1.0], (n, 1))
            ztd = np.zeros((n, 3))
        zb, zbd = _normalize_with_rate(zt, ztd)
        xc = np.stack([np.cos(psi), np.sin(psi), np.zeros(n)], axis=1)
        xcd = psid[:, None] * np.stack([-np.sin(psi), np.cos(psi), np.zeros(n)], axis=1)
        yt = np.cross(zb, xc)
        ytd = np.cross(zbd, xc) + np.cross(zb, xcd)
        yb, ybd = _normalize_with_rate(yt, ytd)
        xb = np.cross(yb, zb)
        xbd = np.cross(ybd, zb) + np.cross(yb, zbd)
        R = np.stack([xb, yb, zb], axis=2)
        Rd = np.stack([xbd, ybd, zbd], axis=2)
        W = np.einsum("nji,njk->nik", R, Rd)  # R^T Rdot = hat(omega_body)
        omega = 0.5 * np.stack(
            [W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1
        )
        return R, omega

    def rotation(self, t: float | F64) -> F64:
        return self._attitude(t)[0]

    def angular_velocity(self, t: float | F64) -> F64:
        """Body-frame angular rate (N, 3), rad/s (what a gyroscope measures, noise-free)."""
        return self._attitude(t)[1]

    def specific_force(self, t: float | F64) -> F64:
        """Body-frame specific force R^T (a - g) (N, 3), m/s^2 (what an accelerometer measures)."""
        R = self.rotation(t)
        return np.einsum("nji,nj->ni", R, self.acceleration(t) - G_WORLD[None, :])

    def world_from_body(self, t: float | F64) -> F64:
        """(N, 4, 4) poses; for a scalar t use ``[0]``."""
        tt = self._t(t)
        T = np.tile(np.eye(4), (len(tt), 1, 1))
        T[:, :3, :3] = self.rotation(tt)
        T[:, :3, 3] = self.position(tt)
        return T

    def path_length(self, t_end: float | None = None, dt: float = 0.01) -> float:
        """Travelled distance (3D) from 0 to t_end (default: the whole trajectory)."""
        te = self.duration if t_end is None else min(t_end, self.duration)
        tt = np.arange(0.0, te + dt / 2, dt)
        sp = np.linalg.norm(self.velocity(tt), axis=1)
        return float(np.trapezoid(sp, tt))


def _speed_profile(length: float, v: float, hold: float, t_acc: float, hold_end: float = 1.0):
    """Arc length s(t) for: rest ``hold`` s, smooth ramp to v in t_acc, cruise, ramp down, rest."""
    t_acc = min(t_acc, length / v)
    t_cruise = length / v - t_acc
    T = hold + 2 * t_acc + t_cruise + hold_end

    def s_of_t(t: F64) -> F64:
        t = np.asarray(t, dtype=np.float64)
        s = np.zeros_like(t)
        x1 = (t - hold) / t_acc
        s += np.where(t > hold, v * t_acc * _smoothstep5_integral(x1), 0.0)
        t2 = hold + t_acc
        s += np.where(t > t2, v * np.clip(t - t2, 0, t_cruise), 0.0)
        t3 = t2 + t_cruise
        x3 = (t - t3) / t_acc
        s += np.where(t > t3, v * (np.clip(x3, 0, 1) - _smoothstep5_integral(x3)) * t_acc, 0.0)
        return np.minimum(s, length)

    return s_of_t, T


def _make_trajectory(
    spec: AgentSpec,
    pts3: F64,
    hold: float,
    route: Route | None,
    meta: dict[str, Any],
    knot_dt: float = 0.2,
    climb: tuple[float, float, float] | None = None,
) -> Trajectory:
    """Time-parameterise a dense smooth 3D path (M, 3) into a Trajectory. ``climb = (t0, duration, dz)``:
    before ``hold`` the agent rises straight up by ``dz`` to the path's start over ``[t0, t0 + duration]``
    (zero velocity and acceleration at both ends, so the turn onto the path is smooth)."""
    seg = np.linalg.norm(np.diff(pts3, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts3 = pts3[keep]
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts3, axis=0), axis=1))])
    path = CubicSpline(u, pts3, axis=0)
    L = float(u[-1])
    t_acc = 4.0
    s_of_t, T = _speed_profile(L, spec.speed_mps, hold, t_acc)
    t_a, t_b = hold, T - 1.0  # moving interval (rest before and after)
    n = int(np.ceil((t_b - t_a) / knot_dt))
    tk = np.linspace(t_a, t_b, n + 1)
    if climb is not None:
        t0 = climb[0]
        tk = np.concatenate([np.linspace(t0, t_a, int(np.ceil((t_a - t0) / knot_dt)) + 1)[:-1], tk])
        t_a = t0
    sk = s_of_t(tk)
    Xk = path(sk)
    if climb is not None:
        Xk[:, 2] -= climb[2] * (1.0 - _smoothstep5(np.clip((tk - climb[0]) / climb[1], 0.0, 1.0)))
    z3 = np.zeros(3)
    pos = make_interp_spline(tk, Xk, k=5, bc_type=([(1, z3), (2, z3)], [(1, z3), (2, z3)]))
    tan = path(sk, 1)
    psi = np.unwrap(np.arctan2(tan[:, 1], tan[:, 0]))
    if spec.kind == "uav":
        psi = gaussian_filter1d(psi, sigma=0.4 / knot_dt, mode="nearest")
    z1 = np.zeros(1)
    yaw = make_interp_spline(tk, psi, k=5, bc_type=([(1, z1), (2, z1)], [(1, z1), (2, z1)]))
    uav = spec.kind == "uav"
    return Trajectory(spec.agent_id, spec.kind, pos, yaw, uav, float(T), route, meta, (t_a, t_b))
