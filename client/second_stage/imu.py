"""The second stage's IMU factors: preintegration parameters, and the factors and new variables of a
keyframe (an ``ImuFactor`` and a bias random walk to the previous one, or priors that start a segment)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.second_stage.factors import _bkey, _diag, _key, _vkey

if TYPE_CHECKING:
    from hivemap.client.second_stage.stage import SecondStage

F64 = NDArray[np.float64]


def imu_params(st: SecondStage) -> Any:
    """gtsam's preintegration parameters from ``options.imu``."""
    o = st.options.imu
    assert o is not None
    p = st._gtsam.PreintegrationParams.MakeSharedU(o.gravity)
    p.setGyroscopeCovariance(np.eye(3) * (o.gyroscope_noise_density * o.gyroscope_noise_scale) ** 2)
    p.setAccelerometerCovariance(np.eye(3) * o.accelerometer_noise_density**2)
    p.setIntegrationCovariance(np.eye(3) * o.integration_sigma**2)
    kf_from_imu = np.asarray(o.kf_from_imu, dtype=np.float64).reshape(4, 4)
    if not np.allclose(kf_from_imu, np.eye(4)):
        # gtsam's body_P_sensor: the sensor's (IMU's) pose in the state's (keyframe's) frame
        p.setBodyPSensor(st._gtsam.Pose3(kf_from_imu))
    return p


def velocity_bias(st: SecondStage, kf_id: int) -> tuple[F64, Any]:
    """The current estimate of a keyframe's velocity (local frame) and IMU bias."""
    return np.asarray(st._est.atVector(_vkey(kf_id)), dtype=np.float64), st._est.atConstantBias(_bkey(kf_id))


def imu_factors(st: SecondStage, kf_id: int, t: float, segment: int) -> tuple[list[Any], Any, F64 | None]:
    """The IMU factors and new values (velocity, bias) of a keyframe about to be added.

    Returns (factors, values, mean of the velocity prior or None). Within a segment, with samples
    since the previous keyframe and a gap under ``max_gap_s``: an ``ImuFactor`` and a bias random
    walk to the previous keyframe. Otherwise a loose velocity prior and a bias prior instead.
    """
    gtsam = st._gtsam
    o = st.options.imu
    assert o is not None
    prev = next((k for k in reversed(st._order) if st._kfs[k].segment == segment), None)
    t_prev = st._kfs[prev].timestamp if prev is not None else -math.inf
    buf = st._imu_buf
    samples = [r for r in buf if t_prev < r[0] <= t]
    st._imu_buf = [r for r in buf if r[0] > t]
    values = gtsam.Values()
    v_prev, b_prev = velocity_bias(st, prev) if prev is not None and prev in st._imu_kfs else (None, None)
    st._imu_kfs.add(kf_id)
    if prev is not None and v_prev is not None and samples and 0.0 < t - t_prev <= o.max_gap_s:
        pim = gtsam.PreintegratedImuMeasurements(st._imu_params, b_prev)
        last = t_prev
        for r in samples:
            if r[0] > last:
                pim.integrateMeasurement(r[4:7], r[1:4], float(r[0] - last))
                last = float(r[0])
        nav = gtsam.NavState(gtsam.Pose3(st._estimate[prev]), v_prev)
        v0 = np.asarray(pim.predict(nav, b_prev).velocity(), dtype=np.float64)
        dt = t - t_prev
        rw = np.array([o.accelerometer_random_walk] * 3 + [o.gyroscope_random_walk] * 3) * math.sqrt(dt)
        factors = [
            gtsam.ImuFactor(_key(prev), _vkey(prev), _key(kf_id), _vkey(kf_id), _bkey(prev), pim),
            gtsam.BetweenFactorConstantBias(
                _bkey(prev), _bkey(kf_id), gtsam.imuBias.ConstantBias(), _diag(rw)
            ),
        ]
        values.insert(_vkey(kf_id), v0)
        values.insert(_bkey(kf_id), b_prev)
        st.n_imu_factors += 1
        return factors, values, None
    v0 = np.zeros(3) if v_prev is None else v_prev
    b0 = gtsam.imuBias.ConstantBias() if b_prev is None else b_prev
    sig_b = np.array([o.bias_prior_sigma_accel] * 3 + [o.bias_prior_sigma_gyro] * 3)
    factors = [
        gtsam.PriorFactorVector(_vkey(kf_id), v0, _diag(np.full(3, o.velocity_prior_sigma))),
        gtsam.PriorFactorConstantBias(_bkey(kf_id), b0, _diag(sig_b)),
    ]
    values.insert(_vkey(kf_id), v0)
    values.insert(_bkey(kf_id), b0)
    return factors, values, v0
