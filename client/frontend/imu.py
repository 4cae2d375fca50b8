"""The front-end's IMU: gyro preintegration between frames, the motion prediction it gives, and the
gravity alignment of the VIO frame."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.events import TrackingState
from hivemap.client.frontend.inertial import MotionFilter, gyro_bias_step
from hivemap.client.frontend.mapdata import Frame
from hivemap.client.frontend.optim import PosePrior
from hivemap.maps.geometry import se3, se3_inverse, so3_exp

if TYPE_CHECKING:
    from hivemap.client.frontend.tracker import Frontend

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


class _ImuState:
    """Gyro preintegration (gtsam) between frames + accelerometer buffer for gravity alignment."""

    def __init__(self, params: dict[str, float] | None) -> None:
        import gtsam

        p = params or {}
        self.gtsam = gtsam
        self.pp = gtsam.PreintegrationParams.MakeSharedU(9.81)
        self.pp.setGyroscopeCovariance(np.eye(3) * float(p.get("gyroscope_noise_density", 1.7e-4)) ** 2)
        self.pp.setAccelerometerCovariance(np.eye(3) * float(p.get("accelerometer_noise_density", 2e-3)) ** 2)
        self.pp.setIntegrationCovariance(np.eye(3) * 1e-8)
        self.bias = gtsam.imuBias.ConstantBias()
        self.last_t: float | None = None
        self.acc_log: list[tuple[float, F64]] = []

    def preintegrate(self, samples: F64) -> Any:
        """samples (K,7) [t_s, wx, wy, wz, ax, ay, az] -> gtsam PreintegratedImuMeasurements or None."""
        pim = self.gtsam.PreintegratedImuMeasurements(self.pp, self.bias)
        n = 0
        for row in samples:
            t = float(row[0])
            if self.last_t is not None and t > self.last_t:
                dt = t - self.last_t
                if dt < 0.5:
                    pim.integrateMeasurement(row[4:7], row[1:4], dt)
                    n += 1
            self.last_t = t
        return pim if n else None

    def bias_vector(self) -> F64:
        """[gyro, accel] (6,)."""
        return np.concatenate([self.bias.gyroscope(), self.bias.accelerometer()]).astype(np.float64)

    def set_bias(self, b: F64) -> None:
        self.bias = self.gtsam.imuBias.ConstantBias(np.asarray(b[3:], float), np.asarray(b[:3], float))

    def set_gyro_bias(self, gyro: F64) -> None:
        self.bias = self.gtsam.imuBias.ConstantBias(self.bias.accelerometer(), np.asarray(gyro, float))


@dataclass(frozen=True)
class Prediction:
    """The frame's predicted ``cam_from_world``; with a gravity-aligned IMU also the body velocity and
    the prior on the pose the frame-to-map refinement weighs (None: no prior)."""

    T_cw: F64
    v_w: F64 | None = None
    prior: PosePrior | None = None


def predict(fe: Frontend, pim: Any, dt: float) -> Prediction:
    """The frame's pose from the motion model, its rotation (and with gravity, its pose) from the IMU."""
    assert fe._last is not None
    o = fe.options
    motion = fe._motion.copy()
    if pim is None:
        return Prediction(se3_inverse(fe._last.T_wc @ motion))
    dR_body = pim.deltaRij().matrix()
    R_cb = fe.cam_from_body[:3, :3]
    motion[:3, :3] = R_cb @ dR_body @ R_cb.T
    filt = fe._filter
    if not (fe._gravity_aligned and fe.imu is not None and filt is not None):
        T_cw = se3_inverse(fe._last.T_wc @ motion)
        if not o.imu_prior:
            return Prediction(T_cw)
        # attitude only: the gyro without a velocity to integrate the accelerometer from
        info = np.zeros((6, 6))
        info[:3, :3] = np.eye(3) / (np.radians(o.vio_rot_sigma_deg) ** 2 * 4.0)
        return Prediction(T_cw, None, PosePrior(T_cw, info))
    import gtsam

    T_wb = fe._last.T_wc @ fe.cam_from_body
    T_wb[:3, 3] = filt.p
    nav = gtsam.NavState(gtsam.Pose3(T_wb), filt.v)
    pred = pim.predict(nav, fe.imu.bias)
    filt.predict(np.asarray(pred.position(), dtype=np.float64), np.asarray(pred.velocity()), dt, o)
    T_wb_pred = pred.pose().matrix()
    T_wb_pred[:3, 3] = filt.p
    T_cw = se3_inverse(T_wb_pred @ fe.body_from_cam)
    prior = PosePrior(T_cw, filt.prior_information()) if o.imu_prior else None
    return Prediction(T_cw, filt.v.copy(), prior)


def try_gravity_alignment(fe: Frontend) -> None:
    """Once enough frames have IMU samples, rotate the VIO frame so that its z axis is up."""
    buf = fe._align_buffer
    if len(buf) < 3 or buf[-1][0] - buf[0][0] < fe.options.gravity_init_s:
        return
    # specific force in the world: R_wb a = acc_w + g_up  ->  g_up = mean(R_wb a) - (v1 - v0) / T
    ts = np.array([b[0] for b in buf])
    ps = np.array([b[1][:3, 3] for b in buf])
    f_w = np.array([b[1][:3, :3] @ b[2] for b in buf])
    k = max(1, len(buf) // 5)
    v0 = (ps[k] - ps[0]) / (ts[k] - ts[0])
    v1 = (ps[-1] - ps[-1 - k]) / (ts[-1] - ts[-1 - k])
    g_up = f_w.mean(0) - (v1 - v0) / ((ts[-1] + ts[-1 - k]) / 2 - (ts[k] + ts[0]) / 2)
    if not 8.0 < np.linalg.norm(g_up) < 11.6:
        fe._align_failures += 1
        if fe._align_failures < 5:
            log.warning("gravity estimate %.2f m/s^2 implausible; retrying", np.linalg.norm(g_up))
            fe._align_buffer = buf[len(buf) // 2 :]
            return
        g_up = f_w.mean(0)  # give up on the motion correction: assume a small mean acceleration
        log.warning("gravity from the mean specific force only (%.2f m/s^2)", np.linalg.norm(g_up))
    a = g_up / np.linalg.norm(g_up)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(a, z)
    s = np.linalg.norm(axis)
    ang = np.arctan2(s, float(a @ z))
    R = so3_exp(axis / s * ang) if s > 1e-9 else np.eye(3)
    A = se3(R, np.zeros(3))
    apply_world_transform(fe, A)
    fe._gravity_aligned = True
    p_body = (fe._last.T_wc @ fe.cam_from_body)[:3, 3] if fe._last is not None else np.zeros(3)
    fe._filter = MotionFilter.start(p_body, fe._velocity_w, fe.options)
    fe._align_buffer = []
    log.info("VIO frame gravity-aligned (%.2f deg correction)", np.degrees(ang))


def apply_world_transform(fe: Frontend, A: F64) -> None:
    """Move the whole local map (keyframes, points, last frame, velocity) by ``A``."""
    Ainv = se3_inverse(A)
    for kf in fe._kfs.values():
        kf.T_cw = kf.T_cw @ Ainv
        kf.frame.T_cw = kf.T_cw
    n = fe._pts.n
    fe._pts.xyz[:n] = fe._pts.xyz[:n] @ A[:3, :3].T + A[:3, 3]
    if fe._last is not None and not any(kf.frame is fe._last for kf in fe._kfs.values()):
        fe._last.T_cw = fe._last.T_cw @ Ainv
    fe._velocity_w = A[:3, :3] @ fe._velocity_w
    for kf in fe._kfs.values():
        if kf.v_w is not None:
            kf.v_w = A[:3, :3] @ kf.v_w
    if fe._filter is not None:
        fe._filter.rotate(A[:3, :3])
        fe._filter.p = fe._filter.p + A[:3, 3]


def visual_update(fe: Frontend, frame: Frame, pim: Any, state: TrackingState) -> None:
    """A visual pose was taken: it corrects the motion filter and (tracked well after a tracked
    frame) the gyro bias."""
    if fe.imu is None:
        return
    T_wb = frame.T_wc @ fe.cam_from_body
    if fe._filter is not None:
        fe._filter.update(T_wb[:3, 3], fe.options)
    if fe._vi_ba_ran:
        return  # the visual-inertial local BA estimates the biases
    if pim is not None and state == TrackingState.OK and fe._last_tracked and fe._last is not None:
        R_prev = (fe._last.T_wc @ fe.cam_from_body)[:3, :3]
        bg = np.asarray(fe.imu.bias.gyroscope(), dtype=np.float64)
        dR = pim.deltaRij().matrix()
        fe.imu.set_gyro_bias(gyro_bias_step(R_prev, T_wb[:3, :3], dR, frame.t - fe._last.t, bg, fe.options))


def gate_refuses(fe: Frontend, pred: Prediction, frame: Frame, n_tracked: int) -> bool:
    """Whether the IMU gate refuses the visual pose ``frame.T_cw``. A weak visual solution that disagrees
    with the IMU beyond both uncertainties is not taken; a well supported one only when the disagreement
    is gross (the IMU integrates the map's tilt into its position). The attitude is gated on its own and
    never widened: over one frame the gyro holds it far better than any visual solution the map's tilt
    could excuse, and a taken attitude jump makes the IMU integrate gravity wrongly from then on."""
    if pred.prior is None:
        return False
    o = fe.options
    gate = o.imu_gate_chi2 * (1.0 if n_tracked < o.good_min_inliers else o.imu_gate_strong_scale)
    full, attitude = pred.prior.chi2_and_attitude(frame.T_cw, fe._vis_info)
    return full > gate or attitude > o.imu_gate_rot_chi2
