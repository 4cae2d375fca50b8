"""What the front-end reports: tracking states, per-frame results, keyframe / pose-update / new-session
events and statistics."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class TrackingState(StrEnum):
    INITIALIZING = "initializing"
    OK = "ok"
    WEAK = "weak"  # few inliers, the pose held by the IMU prior
    RELOCALIZED = "relocalized"
    LOST = "lost"  # no visual pose taken: the IMU (or the motion model) alone propagates it
    NEW_MAP = "new_map"

    @property
    def tracked(self) -> bool:
        """The frame's pose is a visual one (good, weak, relocalised or a new map's first)."""
        return self in (
            TrackingState.OK,
            TrackingState.WEAK,
            TrackingState.RELOCALIZED,
            TrackingState.NEW_MAP,
        )


@dataclass(frozen=True)
class FrameResult:
    """Result of one ``Frontend.process`` call.  Poses are in the VIO frame of ``session``."""

    t: float
    state: TrackingState
    world_from_cam: F64
    world_from_body: F64
    n_tracked: int
    session: int
    new_keyframe_id: int | None = None


@dataclass(frozen=True)
class KeyframeEvent:
    """A new keyframe ready for the link / second stage (emitted once, after ``emit_delay_keyframes``).

    ``rel_body`` = prev_body_from_body (4x4) with ``rel_cov`` (6x6, gtsam order [rot, trans], right
    perturbation of ``rel_body``), both None for the first keyframe of a session.
    New points: those its keypoints reference that were not emitted before.
    ``prev_session_from_world`` / ``prev_session_sigma`` [m, deg]: on the first keyframe of a session
    the IMU bridged from the previous one, the guess of this session's frame in that one's.
    ``odom_sigma`` [m, deg]: the error of this keyframe's pose relative to the previous one that weak or
    lost tracking between them added (None: both tracked well).
    ``track_sigma`` [m, deg]: the per-axis sigma of this keyframe's pose relative to the previous one from
    its observations' information (``rel_cov`` in the camera frame); None with ``rel_cov``.
    """

    session: int
    kf_id: int
    timestamp: float
    world_from_cam: F64
    world_from_body: F64
    keypoints: NDArray[np.float32]
    octaves: NDArray[np.uint8]
    descriptors: NDArray[np.uint8]
    point_ids: I64
    prev_kf_id: int | None
    rel_body: F64 | None
    rel_cov: F64 | None
    gnss_epoch: bool
    new_point_ids: I64
    new_point_xyz: F64
    new_point_descriptors: NDArray[np.uint8]
    prev_session_from_world: F64 | None = None
    prev_session_sigma: tuple[float, float] | None = None
    # per keypoint its stereo match's u in the virtual rectified right camera (undistorted), NaN if none
    u_right: NDArray[np.float32] | None = None
    odom_sigma: tuple[float, float] | None = None
    track_sigma: tuple[float, float] | None = None


@dataclass(frozen=True)
class PoseUpdateEvent:
    """Poses/points (already emitted) changed by local BA or gravity alignment."""

    session: int
    kf_ids: I64
    world_from_cam: F64  # (K,4,4)
    point_ids: I64
    xyz: F64


@dataclass(frozen=True)
class NewSessionEvent:
    """Tracking was lost and relocalisation failed: a new map (session) starts.

    ``old_from_new``: the guess of the new session's VIO frame in the old one's (4x4), with its
    uncertainty (``sigma_m`` position, ``sigma_deg`` attitude) from the IMU-only propagation that
    bridged the loss; None when nothing bridged it (no IMU, or not yet gravity-aligned).
    """

    old_session: int
    session: int
    t: float
    old_from_new: F64 | None = None
    sigma_m: float = float("inf")
    sigma_deg: float = float("inf")


Event = KeyframeEvent | PoseUpdateEvent | NewSessionEvent


@dataclass
class FrontendStats:
    frames: int = 0
    keyframes: int = 0
    weak_frames: int = 0
    lost_frames: int = 0
    relocalizations: int = 0
    imu_rejections: int = 0  # visual poses not taken because the IMU prediction disagreed
    lost_keyframes: int = 0  # keyframes made at the IMU's pose while lost
    sessions: int = 1
    timing: dict[str, float] = field(default_factory=dict)
