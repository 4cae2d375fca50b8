"""A live agent's true motion, planned leg by leg while it runs (issue 26, closed loop).

Each replan starts a polynomial of degree 7 per axis from the current position, velocity, acceleration and
jerk to the commanded velocity with zero acceleration and jerk ``horizon_s`` later, then continues at that
velocity; the heading does the same with a quintic towards the commanded yaw. Position and its first three
derivatives (and yaw, its rate and acceleration) are therefore continuous at every replan: a quadrotor's
angular rate follows the jerk, so the gyroscope never jumps, and a replan only changes the motion after its
own time, so samples already taken stay valid. The pieces form a :class:`scipy.interpolate.PPoly` that
:class:`~hivemap.sim.motion.Trajectory` evaluates like the planned trajectories: yaw-only attitude for a
UGV, quadrotor attitude (thrust along a - g) for a UAV, angular rate and specific force analytic, so the
simulated IMU is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import PPoly

from hivemap.sim.motion import Trajectory

F64 = NDArray[np.float64]
_FAR = 1e9  # the last piece (constant velocity) reaches this far in time


@dataclass(frozen=True)
class MotionLimits:
    """How fast the motion follows a command."""

    horizon_s: float = 1.5  # a velocity command is reached this long after the replan
    yaw_horizon_s: float = 1.5  # a yaw command likewise (longer for large turns, see max_yaw_rate)
    max_yaw_rate: float = 0.6  # rad/s: a turn of d rad takes at least 1.875 d / max_yaw_rate (quintic)
    max_accel: float = 1.5  # m/s^2: the horizon grows so that the mean acceleration stays below this


def hermite(start: F64, end: F64, T: float) -> F64:
    """(2k, D) coefficients, lowest power first, of the polynomial of degree 2k - 1 whose derivatives 0..k-1
    are ``start`` (k, D) at 0 and ``end`` (k, D) at ``T``."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    k = len(start)
    A = np.zeros((2 * k, 2 * k))
    for nu in range(k):
        A[nu, nu] = math.factorial(nu)
        for j in range(nu, 2 * k):
            A[k + nu, j] = math.factorial(j) / math.factorial(j - nu) * T ** (j - nu)
    return np.asarray(np.linalg.solve(A, np.concatenate([start, end])), dtype=np.float64)


def _eval(c: F64, tau: float, nu: int) -> F64:
    """Derivative ``nu`` of the polynomial with coefficients ``c`` (lowest power first) at ``tau``."""
    out = np.zeros(c.shape[1:])
    for k in range(nu, len(c)):
        out = out + c[k] * (math.factorial(k) / math.factorial(k - nu)) * tau ** (k - nu)
    return out


class LiveMotion:
    """The true motion of one live agent; call :meth:`replan` between samples, read :attr:`trajectory`."""

    def __init__(
        self, agent_id: str, kind: str, position: F64, yaw: float, limits: MotionLimits | None = None
    ) -> None:
        self.agent_id, self.kind = agent_id, kind
        self.limits = limits or MotionLimits()
        self._t: list[float] = [0.0]  # piece start times
        self._pos: list[F64] = [np.stack([np.asarray(position, np.float64)] + [np.zeros(3)] * 7)]
        self._yaw: list[F64] = [np.array([[yaw]] + [[0.0]] * 5)]
        self._traj: Trajectory | None = None
        self.replans = 0

    def _piece(self, t: float) -> int:
        return max(0, int(np.searchsorted(self._t, t, side="right")) - 1)

    def state(self, t: float) -> tuple[F64, F64]:
        """(position and its derivatives 1-3 (4, 3), yaw and its derivatives 1-2 (3,)) at ``t``."""
        i = self._piece(t)
        tau = t - self._t[i]
        p, y = self._pos[i], self._yaw[i]
        P = np.stack([_eval(p, tau, nu) for nu in range(4)])
        return P, np.array([_eval(y, tau, nu)[0] for nu in range(3)])

    def replan(self, t: float, velocity: F64, yaw: float | None = None) -> None:
        """From ``t`` on, go smoothly to ``velocity`` (world, m/s) and heading ``yaw`` (rad, any branch;
        None: keep the current one). Pieces after ``t`` are replaced."""
        lim = self.limits
        P, Y = self.state(t)
        p, v = P[0], P[1]
        v1 = np.asarray(velocity, dtype=np.float64).reshape(3)
        # 2.1875 = peak/mean ratio of the degree-7 speed-up: keep the peak acceleration below the limit
        T = max(lim.horizon_s, 2.1875 * float(np.linalg.norm(v1 - v)) / lim.max_accel)
        pos = hermite(P, np.stack([p + T * (v + v1) / 2, v1, np.zeros(3), np.zeros(3)]), T)
        psi = float(Y[0])
        target = psi if yaw is None else psi + math.remainder(float(yaw) - psi, 2 * math.pi)
        Ty = max(lim.yaw_horizon_s, 1.875 * abs(target - psi) / lim.max_yaw_rate)
        yw = hermite(Y.reshape(3, 1), np.array([[target], [0.0], [0.0]]), Ty)
        keep = int(np.searchsorted(self._t, t, side="left"))
        del self._t[keep:], self._pos[keep:], self._yaw[keep:]
        # the polynomials and their constant continuations end at different times: split at both
        ends = sorted({t, t + T, t + Ty})
        for s in ends:
            self._t.append(s)
            cp = pos if s < t + T else _line(pos, T, s - t)
            cy = yw if s < t + Ty else _line(yw, Ty, s - t)
            self._pos.append(_shift(cp, s - t) if s < t + T else cp)
            self._yaw.append(_shift(cy, s - t) if s < t + Ty else cy)
        self._traj = None
        self.replans += 1

    @property
    def trajectory(self) -> Trajectory:
        """The motion so far (and its constant-velocity continuation) as a :class:`Trajectory`."""
        if self._traj is None:
            x = np.array([*self._t, _FAR])
            # PPoly wants the highest power first: (order, pieces, dims)
            cp = np.stack(self._pos, axis=1)[::-1]
            cy = np.stack(self._yaw, axis=1)[::-1, :, 0]
            self._traj = Trajectory(
                self.agent_id, self.kind, PPoly(cp, x), PPoly(cy, x),  # type: ignore[arg-type]
                thrust_aligned=self.kind == "uav", duration=_FAR,
            )  # fmt: skip
        return self._traj


def _shift(c: F64, d: float) -> F64:
    """Coefficients (lowest power first) of the same polynomial in tau' = tau - d."""
    out = np.zeros_like(c)
    for nu in range(len(c)):
        out[nu] = _eval(c, d, nu) / math.factorial(nu)
    return out


def _line(c: F64, T: float, d: float) -> F64:
    """The constant-velocity continuation after T of polynomial ``c``, as coefficients in tau' = tau - d."""
    out = np.zeros_like(c)
    x, v = _eval(c, T, 0), _eval(c, T, 1)
    out[0] = x + v * (d - T)
    out[1] = v
    return out
