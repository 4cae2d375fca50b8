"""Stereo(-inertial) ORB visual odometry front-end of the agent (issue 4, items 1-2).

Usage::

    from hivemap.client.frontend import Frontend, FrontendOptions
    fe = Frontend(rig, FrontendOptions(), imu_params={})          # imu_params=None: stereo only
    res = fe.process(t, left_gray, right_gray, imu_samples, gnss_epoch=False)   # -> FrameResult
    for ev in fe.poll_events(): ...   # KeyframeEvent / PoseUpdateEvent / NewSessionEvent
    fe.flush()                        # end of run: emit the keyframes still held back

Pipeline per frame: ORB (grid-thinned, adaptive FAST threshold; optionally, nearly empty cells
detected again at a threshold above the image's noise) on the left image; stereo depth by
pyramidal LK into the right image, checked on rectified rows and forward-backward; prediction by the
constant-velocity model with the gyro rotation (gtsam preintegration, gyro bias estimated against the
visual rotation); once the VIO frame is gravity-aligned, the full IMU prediction from a motion filter
(position, velocity, world acceleration correction) whose covariance makes it a prior; guided
matching of the local map by projection, P3P RANSAC, motion-only Gauss-Newton with Huber and stereo
residuals plus the IMU prior, then track-local-map and a second refinement.  Tracking quality: OK,
WEAK (fewer than ``good_min_inliers``), or LOST when no visual pose is taken -- too few inliers, or a
pose beyond the IMU gate (chi2 of the prior, ``imu_gate_chi2``, widened for well-supported poses;
the attitude alone, ``imu_gate_rot_chi2``, never widened); a lost frame's pose is the IMU's.
Keyframes: tracked ratio vs reference keyframe, close-point starvation, 0.5 s, GNSS epochs, after a
relocalisation.  Local mapping: stereo points (all close ones, >= 100), multi-view triangulation with
3 neighbours, local BA over the 10 best covisible keyframes (+10 fixed; each sharing >= 15 points)
with numpy/scipy Schur LM (see ``optim``), observation and point culling.  With ``vi_ba`` (off by default, see
docs/decisions.md) local BA is visual-inertial: the last 10 keyframes in time with velocity and bias
states and preintegrated IMU terms between them (``preint``), the biases fed back to the tracker.
Lost: a frame lost for want of matches (not refused by the gate) with enough close stereo points
becomes a keyframe at the IMU's pose, so tracking resumes on its points (ORB-SLAM3's keyframes while
recently lost); the IMU prediction, then relocalisation (BF descriptors of the last 20 keyframes' points and
of the bag-of-words candidates + P3P RANSAC), both through the IMU gate; after ``imu_hold_s`` of
IMU-only propagation (``max_lost_frames`` without an IMU) a new session, started at the propagated
pose: its first keyframe carries that guess of its frame in the old session
(``KeyframeEvent.prev_session_from_world``).

Frames: poses are in the agent's VIO frame, z up (gravity) when an IMU is given.  Body = IMU frame
(``rig.body_from_left`` = EuRoC ``T_BS`` of cam0).
"""

from hivemap.client.frontend.options import FrontendOptions
from hivemap.client.frontend.tracker import (
    Event,
    FrameResult,
    Frontend,
    FrontendStats,
    KeyframeEvent,
    NewSessionEvent,
    PoseUpdateEvent,
    TrackingState,
)

__all__ = [
    "Event",
    "FrameResult",
    "Frontend",
    "FrontendOptions",
    "FrontendStats",
    "KeyframeEvent",
    "NewSessionEvent",
    "PoseUpdateEvent",
    "TrackingState",
]
