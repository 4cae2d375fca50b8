"""Options of the agent's second stage (GNSS + co-location + optional IMU fusion)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
_IDENTITY16 = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class ImuOptions:
    """IMU factors of the second stage: noise as in a EuRoC/Kalibr ``imu0/sensor.yaml``."""

    gyroscope_noise_density: float = 1.7e-4  # rad/s/sqrt(Hz)
    accelerometer_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    gyroscope_random_walk: float = 2.0e-5  # rad/s^2/sqrt(Hz)
    accelerometer_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    gyroscope_noise_scale: float = 1.0
    """The IMU factor's gyro noise is the density times this. Above 1 the front-end's relative rotation
    outweighs the gyro (whose turn-on bias must otherwise be estimated); 1 was best for every agent in a
    replay (docs/decisions.md)."""
    gravity: float = 9.81
    kf_from_imu: tuple[float, ...] = _IDENTITY16
    """The IMU's pose in the keyframe frame, row-major 4x4 (``body_P_sensor`` of gtsam)."""
    integration_sigma: float = 1e-4
    velocity_prior_sigma: float = 5.0
    """m/s, on the first velocity of a segment (or after a gap without IMU samples)."""
    bias_prior_sigma_accel: float = 0.1
    bias_prior_sigma_gyro: float = 0.01
    max_gap_s: float = 2.0
    """No IMU factor between keyframes further apart than this (or without samples in between)."""

    @classmethod
    def from_noise(cls, noise: dict[str, float], kf_from_imu: F64 | None = None) -> ImuOptions:
        """From ``imu0/sensor.yaml`` keys (missing keys keep the defaults)."""
        names = (
            "gyroscope_noise_density",
            "accelerometer_noise_density",
            "gyroscope_random_walk",
            "accelerometer_random_walk",
        )
        kw: dict[str, Any] = {k: float(noise[k]) for k in names if k in noise and float(noise[k]) > 0}
        if kf_from_imu is not None:
            kw["kf_from_imu"] = tuple(float(x) for x in np.asarray(kf_from_imu, dtype=np.float64).reshape(16))
        return cls(**kw)


@dataclass(frozen=True)
class SecondStageOptions:
    """Tuning of the second stage. Distances in metres, angles in radians."""

    gravity_aligned: bool = True
    """The VIO frame's z axis is up (IMU): roll/pitch are observable, only yaw + translation drift."""
    first_prior_sigma_pos: float = 100.0
    """Loose prior on the first pose's position (per segment)."""
    first_prior_sigma_yaw: float = math.pi
    """Loose prior on the first pose's yaw."""
    first_prior_sigma_tilt: float = 0.05
    """Prior on the first pose's roll/pitch when gravity-aligned (else the yaw sigma is used)."""
    kf_from_antenna: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """GNSS antenna position in the keyframe frame (lever arm); zeros -> plain ``GPSFactor``."""
    gnss_gate_sigma: float = 10.0
    """Reject a fix whose Mahalanobis distance to the prediction exceeds this (chi-square gate)."""
    gnss_max_consecutive_rejections: int = 5
    """After this many rejections in a row the next fix is accepted anyway (recovers from an
    over-confident prediction); 0 disables the safety valve."""
    align_min_spread_m: float = 5.0
    """Horizontal spread of accepted fixes needed before the yaw re-initialisation."""
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    extra_iterations: int = 1
    """Extra ``update()`` calls after each new factor batch (lets iSAM2 relinearise)."""
    imu: ImuOptions | None = None
    """IMU factors between keyframes (feed samples with :meth:`SecondStage.add_imu`); None: off."""
    between_huber: float = 3.0
    """Huber threshold (in sigmas) on the front-end's relative-pose factors, so a tracking step far
    outside its covariance (a keyframe the tracking placed centimetres off, a step 1-5 deg off in fog)
    yields to the IMU instead of driving its velocity and biases off; 0: Gaussian (docs/decisions.md)."""
    colocation_offset_sigma: tuple[float, float, float] | None = None
    """(tilt rad, yaw rad, translation m): co-location priors take the server's shape, placed by one
    free transform ``O`` per agent (``local_from_kf ~ O @ prior``) with a prior of these sigmas at
    identity, instead of pinning every keyframe absolutely. A server map's common tilt or ENU offset
    (the visual tilt drift it keeps) then yields to the agent's own IMU and GNSS. None: plain priors."""
    colocation_offset_sigma_enu: tuple[float, float, float] | None = None
    """O's prior while the co-location priors are absolute ENU poses (a server map the GNSS stage put
    into ENU with every agent's fixes): a tighter translation lets the team's pooled fixes place this
    agent instead of its own few (each agent's local trajectory otherwise sits off by the mean error of
    its own fixes). None: ``colocation_offset_sigma`` in both frames. Its online effect is not resolved
    (docs/decisions.md)."""
    colocation_enu_holds_own_fixes: bool = True
    """While the co-location priors are ENU poses, this agent's own fixes on the keyframes they cover (up
    to the latest one) leave the graph: the server's GNSS stage already fused them with the team's, and
    counting them twice pulls the agent back toward its own few fixes' mean error (docs/decisions.md).
    They come back if the priors stop being ENU."""
