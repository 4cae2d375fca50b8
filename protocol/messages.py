"""Protocol v7 messages: one frozen dataclass per message type (DESIGN.md "Protocol v1").

Arrays are numpy arrays with fixed dtypes; shapes are given per field. Poses are 4x4 float64
``world_from_cam`` in the sender's frame (the agent's VIO frame for agent -> server messages, the
global frame in corrections). Arrays produced by :func:`hivemap.protocol.decode` are read-only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Hello:
    """Agent -> server, first message. ``camera``: ``PinholeCamera.to_dict()``.

    ``mission`` names one run of the agent's outbox (a UUID created with the outbox); ``resume_from`` and
    every seq after the hello count within that mission. ``session`` is the agent's front-end map within
    the mission: it increments when the agent resets its map (the server keeps the old session's map and
    starts a new one). A known agent id with a mission the server has not seen starts new sessions of that
    agent and never touches the data of its earlier missions."""

    TYPE: ClassVar[str] = "hello"
    agent_id: str
    kind: str  # "uav" | "ugv"
    camera: dict[str, object]
    token: str
    resume_from: int = 0
    session: int = 0
    # GNSS antenna position in the cam0 frame, f64 (3,) (None: no GNSS receiver, or at the camera). The
    # server's GNSS stage needs it: a fix is the antenna's position, a keyframe pose the camera's.
    cam_from_antenna: NDArray[np.float64] | None = None
    mission: str = ""
    # The stereo baseline (m) of a stereo agent's rig (None: monocular): the virtual rectified right
    # camera of its keyframes' ``u_right`` sits this far along cam0's x axis (protocol v2).
    stereo_baseline: float | None = None
    # The agent reads ``team_advisory`` messages (protocol v4); agents that do not say so never get one.
    team_advisories: bool = False


@dataclass(frozen=True)
class Welcome:
    """Server -> agent: ``last_seq`` is the highest seq the server durably stored for the hello's mission.
    ``mission_known`` is False when the server has no record of that mission (a new outbox, or a server
    that lost its data): the agent then sends its whole outbox again, from seq 1."""

    TYPE: ClassVar[str] = "welcome"
    last_seq: int
    server_version: str
    mission_known: bool = True


@dataclass(frozen=True)
class Keyframe:
    """Agent -> server. keypoints f32 (N,2), octaves u8 (N,), descriptors u8 (N,32), point_ids i64 (N,)
    (-1 = no map point), world_from_cam f64 (4,4); optional GNSS fix in ENU f64 (3,) + covariance (3,3);
    optional ``up_cam`` f64 (3,): the unit up direction (against gravity) in the camera frame, from the
    agent's IMU (its second stage), which the server's GNSS stage holds the keyframe's roll/pitch to.
    Optional on the first keyframe of a session after a tracking loss (``session`` >= 1):
    ``prev_session_from_world`` f64 (4,4), the agent's guess of this session's frame in the previous
    session's, from the IMU propagation that bridged the loss, and ``prev_session_sigma`` f64 (2,) its
    1-sigma uncertainty [position m, attitude deg], so the server can merge the session back.
    Optional ``u_right`` f32 (N,) (protocol v2): per keypoint, its stereo match's u in the virtual
    rectified right camera (cam0's undistorted pinhole intrinsics, ``Hello.stereo_baseline`` along x),
    NaN where the keypoint has no stereo match; what lets the server's global BA hold metric scale.
    Optional ``odom_sigma`` f64 (2,) [position m, attitude deg]: the 1-sigma error of this keyframe's pose
    relative to the previous keyframe of its session that weak or lost tracking between them added; absent
    when both tracked well, so the server's pose graph can let a loop correct a jump there.
    Optional ``track_sigma`` f64 (2,) [position m, attitude deg] (protocol v5): the per-axis 1-sigma of this
    keyframe's pose relative to the previous keyframe of its session as its tracking measured it (its
    observations' information), so the server's pose graph weighs each agent's odometry by how well it
    tracked."""

    TYPE: ClassVar[str] = "keyframe"
    kf_id: int
    timestamp: float
    world_from_cam: NDArray[np.float64]
    keypoints: NDArray[np.float32]
    octaves: NDArray[np.uint8]
    descriptors: NDArray[np.uint8]
    point_ids: NDArray[np.int64]
    gnss_enu: NDArray[np.float64] | None = None
    gnss_cov: NDArray[np.float64] | None = None
    session: int = 0
    up_cam: NDArray[np.float64] | None = None
    prev_session_from_world: NDArray[np.float64] | None = None
    prev_session_sigma: NDArray[np.float64] | None = None
    u_right: NDArray[np.float32] | None = None
    odom_sigma: NDArray[np.float64] | None = None
    track_sigma: NDArray[np.float64] | None = None
    intent_velocity: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class MapPoints:
    """Agent -> server. ids i64 (M,), xyz f64 (M,3), representative descriptors u8 (M,32)."""

    TYPE: ClassVar[str] = "map_points"
    ids: NDArray[np.int64]
    xyz: NDArray[np.float64]
    descriptors: NDArray[np.uint8]
    session: int = 0


@dataclass(frozen=True)
class PoseUpdates:
    """Agent -> server: the dynamic part only. kf_ids i64 (K,), world_from_cam f64 (K,4,4),
    point_ids i64 (P,), xyz f64 (P,3). ``points_follow`` (protocol v6): the points each keyframe was
    the first to observe, where not listed, move rigidly with it (an agent resending keyframes its
    odometry's smoothing moved, without their points)."""

    TYPE: ClassVar[str] = "pose_updates"
    kf_ids: NDArray[np.int64]
    world_from_cam: NDArray[np.float64]
    point_ids: NDArray[np.int64]
    xyz: NDArray[np.float64]
    session: int = 0
    points_follow: bool = False


@dataclass(frozen=True)
class Rendezvous:
    """Agent -> server (protocol v3): the sender (the observer) saw a marker carrier of another agent.

    ``timestamp``: the observer's image time (s, the team's shared clock). ``observed_agent``: the agent id
    that carries the markers (resolved by the observer from the marker ids and the team's carrier layout);
    ``marker_ids`` i64 (M,) the markers that went into the pose. ``ref_kf_id``: a keyframe of the
    observer's ``session`` (already sent or about to be), and ``ref_from_cam`` f64 (4,4): the observer's
    cam0 at ``timestamp`` in that keyframe's cam0 frame (its own tracking). ``cam_from_observed`` f64
    (4,4): the observed agent's cam0 in the observer's cam0 at ``timestamp``, from one PnP over all
    visible corners of the carrier. ``covariance`` f64 (6,6): of ``cam_from_observed`` in gtsam's Pose3
    tangent convention, [rx, ry, rz (rad), tx, ty, tz (m)], perturbation on the right (in the observed
    cam0 frame). ``reproj_rms_px``: the PnP's RMS reprojection error."""

    TYPE: ClassVar[str] = "rendezvous"
    timestamp: float
    observed_agent: str
    marker_ids: NDArray[np.int64]
    ref_kf_id: int
    ref_from_cam: NDArray[np.float64]
    cam_from_observed: NDArray[np.float64]
    covariance: NDArray[np.float64]
    reproj_rms_px: float
    session: int = 0


@dataclass(frozen=True)
class Ack:
    """Server -> agent: the message ``seq`` is durably stored."""

    TYPE: ClassVar[str] = "ack"
    seq: int


@dataclass(frozen=True)
class Correction:
    """Server -> agent. ``global_from_local`` f64 (4,4) Sim(3) matrix ``[[sR, t], [0, 1]]``; corrected
    poses of the agent's changed keyframes in the global frame: kf_ids i64 (K,), world_from_cam (K,4,4).

    Optional (protocol v4), together: ``pose_covariance`` f64 (6,6), the marginal covariance of keyframe
    ``covariance_kf_id`` (the agent's latest in the server's map) from the server's pose graph, in the
    global frame: of ``[dtheta (rad), dp (m)]`` with ``R = Exp(dtheta) R_hat`` and ``p = p_hat + dp`` (the
    camera centre), both in the global frame (its lower-right 3x3 block is the position covariance).
    Symmetric positive semi-definite; relative to the map's gauge (its reference keyframe is exact)."""

    TYPE: ClassVar[str] = "correction"
    map_id: int
    global_from_local: NDArray[np.float64]
    kf_ids: NDArray[np.int64]
    world_from_cam: NDArray[np.float64]
    session: int = 0
    # "map": the global frame is the merged map's own frame; "enu": the server's GNSS stage has put the
    # map into the ENU frame the agents' GNSS fixes are in, so the poses are absolute ENU poses.
    global_frame: str = "map"
    pose_covariance: NDArray[np.float64] | None = None
    covariance_kf_id: int | None = None


@dataclass(frozen=True)
class TeamAdvisory:
    """Server -> agent (protocol v4, only to agents whose hello set ``team_advisories``): the agent's
    exploration goals and collision advisory in the frame of its map ``map_id`` (the global frame of its
    corrections). ``goals`` f64 (G,3): its won frontier goals in visiting order (G may be 0);
    ``desired_velocity`` f64 (3,): the velocity the server expects it to fly (its current one while it
    moves, else towards the first goal); ``safe_velocity`` f64 (3,): the ORCA velocity nearest it that
    stays clear of the map's other agents; ``radius_m``: the agent's radius as inflated by
    its uncertainty; ``half_height_m`` (protocol v7; 0 from an older server: unknown): the half height of
    the agent's cylinder, its own half height inflated by its vertical uncertainty (another agent is a
    neighbour only when their heights differ by less than their two half heights). Advisory only and not
    stored: a newer one replaces it; ``computed_at`` is the server's unix time."""

    TYPE: ClassVar[str] = "team_advisory"
    map_id: int
    computed_at: float
    goals: NDArray[np.float64]
    desired_velocity: NDArray[np.float64]
    safe_velocity: NDArray[np.float64]
    radius_m: float
    session: int = 0
    half_height_m: float = 0.0


@dataclass(frozen=True)
class Error:
    """Either direction: what was wrong (``field`` names the culprit) with message ``seq``."""

    TYPE: ClassVar[str] = "error"
    code: str
    message: str
    field: str | None = None
    seq: int | None = None


@dataclass(frozen=True)
class Bye:
    TYPE: ClassVar[str] = "bye"
    reason: str = ""


Message = (
    Hello
    | Welcome
    | Keyframe
    | MapPoints
    | PoseUpdates
    | Rendezvous
    | Ack
    | Correction
    | TeamAdvisory
    | Error
    | Bye
)
MESSAGE_TYPES: dict[str, type] = {
    cls.TYPE: cls
    for cls in (Hello, Welcome, Keyframe, MapPoints, PoseUpdates, Rendezvous, Ack, Correction, TeamAdvisory)
    + (Error, Bye)
}
