"""Size limits applied on decode (and by the server's WebSocket layer)."""

from __future__ import annotations

from dataclasses import dataclass

# 2: keyframes carry ``u_right`` and ``odom_sigma``, hellos ``stereo_baseline``. A v1 frame still reads
# (all keypoints mono, every keyframe tracked well).
# 3: the ``rendezvous`` message (an agent saw another agent's marker carrier). v1 and v2 frames still read.
# 4: corrections carry ``pose_covariance`` and ``covariance_kf_id``; the ``team_advisory`` message
# (server -> agent) and the hello's ``team_advisories`` (the agent reads them; no agent that does not say so
# gets one). v1-v3 frames still read, and a frame to a peer that said hello in an older version is written in
# that version, without the newer fields (``encode(..., version=)``, ``downgrade``); a message type newer
# than the peer's version is not sent to it at all, so older agents keep working.
# 5: keyframes carry ``track_sigma``.
# 6: pose updates carry ``points_follow`` (the keyframes' points not listed move with them).
# 7: keyframes carry ``intent_velocity``, team advisories ``half_height_m``.
PROTOCOL_VERSION = 7
SUPPORTED_VERSIONS = (1, 2, 3, 4, 5, 6, 7)


@dataclass(frozen=True)
class Limits:
    """Upper bounds on what one frame may carry; a decoder never allocates beyond them."""

    max_frame_bytes: int = 4 * 1024 * 1024
    max_keypoints: int = 4000
    max_points_per_msg: int = 20000
    max_poses_per_msg: int = 5000
    max_agent_id_len: int = 64
    max_token_len: int = 256
    max_string_len: int = 1024
    max_seq: int = 2**62
    max_baseline_m: float = 100.0
    max_markers: int = 256
    max_goals: int = 256  # goals of one team advisory
    max_speed_mps: float = 100.0  # an intended velocity's norm
