"""The front-end's inertial state between frames: a position/velocity filter driven by the IMU and
corrected by the visual poses, the gyro bias estimate, and the uncertainty of the IMU's pose
prediction, which weighs it in the frame-to-map refinement and gates the visual solution."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.options import FrontendOptions
from hivemap.maps.geometry import so3_log

F64 = NDArray[np.float64]


@dataclass
class MotionFilter:
    """Kalman filter of the body's position ``p``, velocity ``v`` and a world-frame acceleration
    correction ``c``, the same 3x3 covariance for each axis (the axes decouple).

    The IMU propagates ``p``/``v``; each accepted visual pose measures ``p``. ``c`` absorbs the
    accelerometer bias and the residual tilt of the VIO frame against gravity (``g x tilt``), which the
    prediction would otherwise integrate twice over an IMU-only stretch. A finite-difference velocity
    instead would carry each frame's visual noise (a few mm over 50 ms) into the propagation.
    """

    p: F64
    v: F64
    c: F64
    P: F64  # (3,3) covariance of [p, v, c] per axis
    rot_var: float  # variance (rad^2) of the attitude since the last accepted visual pose
    # position and attitude variances just after the last accepted visual pose (or the start)
    visual_var: tuple[float, float] = (0.0, 0.0)

    @staticmethod
    def start(p: F64, v: F64, o: FrontendOptions) -> MotionFilter:
        P = np.diag([o.vio_meas_sigma_m**2, o.vio_init_vel_sigma_mps**2, o.vio_init_acc_sigma_mps2**2])
        rot_var = float(np.radians(o.vio_rot_sigma_deg) ** 2)
        return MotionFilter(p.copy(), v.copy(), np.zeros(3), P, rot_var, (float(P[0, 0]), rot_var))

    def predict(self, p_nav: F64, v_nav: F64, dt: float, o: FrontendOptions) -> None:
        """``p_nav``/``v_nav``: the IMU's prediction from the filter's ``p``/``v`` over ``dt``."""
        self.p = p_nav + 0.5 * self.c * dt * dt
        self.v = v_nav + self.c * dt
        F = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        qa = o.vio_acc_noise**2
        Q = qa * np.array([[dt**3 / 3, dt**2 / 2, 0.0], [dt**2 / 2, dt, 0.0], [0.0, 0.0, 0.0]])
        Q[2, 2] = o.vio_acc_correction_walk**2 * dt
        self.P = F @ self.P @ F.T + Q
        self.rot_var += np.radians(o.vio_gyro_drift_dps) ** 2 * dt

    def update(self, p_meas: F64, o: FrontendOptions) -> None:
        """An accepted visual body position."""
        s = self.P[0, 0] + o.vio_meas_sigma_m**2
        K = self.P[:, 0] / s
        r = p_meas - self.p
        self.p = self.p + K[0] * r
        self.v = self.v + K[1] * r
        self.c = self.c + K[2] * r
        self.P = self.P - np.outer(K, self.P[0])
        self.rot_var = float(np.radians(o.vio_rot_sigma_deg) ** 2)
        self.visual_var = (float(self.P[0, 0]), self.rot_var)

    def prior_information(self) -> F64:
        """Information (6,6) of the predicted ``cam_from_world`` in the left tangent ``[w, v]``.

        To first order the camera centre moves by ``-R^T v`` alone, so an isotropic position
        variance is the same isotropic variance of ``v``; ``w`` is the attitude error (camera frame).
        """
        info = np.zeros((6, 6))
        info[:3, :3] = np.eye(3) / self.rot_var
        info[3:, 3:] = np.eye(3) / self.P[0, 0]
        return info

    def sigmas(self) -> tuple[float, float]:
        """1-sigma position (m) and attitude (deg) of the propagated pose."""
        return float(np.sqrt(self.P[0, 0])), float(np.degrees(np.sqrt(self.rot_var)))

    def growth_sigmas(self) -> tuple[float, float]:
        """1-sigma position (m) and attitude (deg) the IMU alone added since the last accepted visual
        pose: what an IMU-only stretch can put between two keyframes. The variances that pose left
        (``vio_meas_sigma_m``, ``vio_rot_sigma_deg``) are its error against the map, which the keyframe
        before the stretch shares, so they are not part of it."""
        dp = max(0.0, float(self.P[0, 0]) - self.visual_var[0])
        dr = max(0.0, self.rot_var - self.visual_var[1])
        return float(np.sqrt(dp)), float(np.degrees(np.sqrt(dr)))

    def rotate(self, R: F64) -> None:
        """The world frame was rotated by ``R`` (gravity alignment)."""
        self.p, self.v, self.c = R @ self.p, R @ self.v, R @ self.c


def gyro_bias_step(
    R_wb_prev: F64, R_wb_cur: F64, dR_imu: F64, dt: float, bias: F64, o: FrontendOptions
) -> F64:
    """One step of the gyro bias estimate from two visually tracked frames.

    ``dR_imu``: the gyro's rotation between them, integrated with ``bias`` removed. Its difference
    from the visual rotation, per second, is the bias left over; an exponential average over
    ``gyro_bias_time_s`` keeps the visual noise of single frames out.
    """
    if dt <= 0:
        return bias
    dR_vis = R_wb_prev.T @ R_wb_cur
    e = so3_log(dR_vis.T @ dR_imu) / dt
    if np.linalg.norm(e) > np.radians(o.gyro_bias_max_step_dps):
        return bias  # a bad visual rotation, not a bias
    k = min(1.0, dt / o.gyro_bias_time_s)
    return bias + k * e  # type: ignore[no-any-return]
