"""The agent's second stage (paper 003, section 2.2, eqs. 1-3): GNSS + co-location fusion.

A gtsam iSAM2 pose graph over keyframe poses ``local_from_kf`` (one ``Pose3`` per keyframe; ``kf`` is
whatever frame the caller's keyframe poses use, normally the left camera as in the protocol):

- relative-pose factors from the front-end (eq. 1): ``BetweenFactorPose3`` with the front-end's 6x6
  covariance in gtsam's tangent order ``[rot, trans]`` (body-frame perturbation, ``T * Exp(xi)``);
- GNSS position factors (eq. 2): ``GPSFactor`` (or ``GPSFactorArm`` with a lever arm
  ``kf_from_antenna``) on an ENU position with the fix's 3x3 covariance.  A fix whose Mahalanobis
  distance to the predicted antenna position (predicted covariance + fix covariance) exceeds
  ``gnss_gate_sigma`` is rejected and logged (a chi-square gate on 3 dof);
- co-location factors (eq. 3) from server corrections: a prior on the keyframe's local-frame pose
  with a given covariance; a newer correction of the same keyframe replaces the older factor;
- a loose prior on the first pose of every segment (iSAM2 is indeterminate with GNSS factors only).
  With a gravity-aligned VIO frame the prior is tight on roll/pitch and loose on yaw and position;
- optionally (``SecondStageOptions.imu``) IMU factors between consecutive keyframes of a segment
  (gtsam ``ImuFactor`` on the IMU samples fed with :meth:`add_imu`, a velocity and a bias per
  keyframe, bias random walk between keyframes): loosely coupled VIO. The front-end uses the IMU
  for gravity alignment and rotation prediction only, so its roll/pitch drifts with the visual
  rotation error; the IMU factors observe gravity through the velocity change between keyframes and
  hold the tilt (docs/decisions.md).

The **local frame** equals the VIO frame until GNSS or co-location factors move it.  When GNSS
arrives, the estimate is re-initialised once (translation after the first fix, yaw + translation
once the fixes span ``align_min_spread_m``): iSAM2 linearises around its current estimate, and a
90 degree yaw jump is far outside what incremental relinearisation handles well.

After each update ``local_from_vio`` is re-estimated (yaw + translation when gravity-aligned, else
SE(3), least-squares on keyframe positions; Umeyama without scale from evo), and the pose of any
frame in the local frame is available by interpolating the per-keyframe correction
``local_from_kf @ inv(vio_from_kf)`` between the neighbouring keyframes (:meth:`local_from_frame`).

Segments: when the front-end starts a new map (tracking lost, new VIO frame), call
:meth:`add_keyframe` with ``new_segment=True``; the segment gets its own loose prior and its own
``local_from_vio``.  GNSS or co-location factors tie segments together in the local frame.
"""

from hivemap.client.second_stage.factors import interpolate_se3, rigid_alignment, yaw_translation_alignment
from hivemap.client.second_stage.options import ImuOptions, SecondStageOptions
from hivemap.client.second_stage.stage import GnssDecision, SecondStage

__all__ = [
    "GnssDecision",
    "ImuOptions",
    "SecondStage",
    "SecondStageOptions",
    "interpolate_se3",
    "rigid_alignment",
    "yaw_translation_alignment",
]
