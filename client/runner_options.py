"""The options of an agent run (:class:`RunnerOptions`) and what its ``run.json`` holds
(:class:`RunSummary`); :mod:`hivemap.client.runner` re-exports both."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from hivemap.client.frontend.markers import MarkerOptions
from hivemap.client.replay_io import GnssMode


@dataclass(frozen=True)
class RunnerOptions:
    """Options of an offline run."""

    gnss: GnssMode = field(default_factory=lambda: GnssMode("denied"))
    seed: int = 0  # for random GNSS modes
    max_frames: int | None = None  # stop after this many frames (tests, quick looks)
    gnss_max_dt_s: float = 0.03  # a fix is attached to the frame closest in time within this
    # rad, m: prior of a server-corrected pose. The server's estimate holds this agent's own odometry and
    # the team's loops, so its shape is the better one; looser priors kept a third to a half of its gain.
    colocation_sigma: tuple[float, float] = (0.003, 0.02)
    colocation_gate_m: float = 1.0  # corrected poses farther than this from the agent's own are refused
    flush_timeout_s: float = 60.0  # streaming: wait this long for the server's acks at the end
    # streaming, after the last frame: the server's loop closures can come long after the last keyframe
    # (factory06: 8.5 s after uav1 finished; a server behind its team minutes later). So the agent waits
    # until the server's ``/health`` says its back-end is through with every keyframe that had reached it
    # when the wait began and runs no optimisation (or is idle), then ``corrections_grace_s`` more for
    # corrections on the wire; it stops early when the server made no progress (no keyframe done, no
    # correction) for ``corrections_stall_s``, and after ``corrections_max_wait_s`` in any case. A server
    # without those fields: until no correction came for ``corrections_quiet_s``.
    corrections_grace_s: float = 2.0
    corrections_quiet_s: float = 10.0
    corrections_stall_s: float = 60.0
    corrections_max_wait_s: float = 600.0
    health_max_failures: int = 5  # unanswered /health polls in a row before falling back to the quiet timer
    # co-location priors take the server's shape, placed by one free transform per agent (sigmas: tilt
    # 0.05 rad with IMU factors, else 0.01; yaw 0.01 rad; 0.1 m, or 0.01 m while the priors are ENU
    # poses), see SecondStageOptions
    colocation_offset: bool = True
    imu_factors: bool = True  # IMU factors in the second stage (loosely coupled VIO) when there is an IMU
    # streaming: keyframes at an IMU-only fusion of the odometry (hivemap.client.odometry) instead of the
    # visual tracking's poses, which in fog are 2-5x further off (docs/decisions.md)
    stream_imu_odometry: bool = True
    # streaming the IMU-aided odometry: a keyframe whose pose there moved this far (m, deg) since it was
    # sent is sent again (a pose update), so the server holds the smoothed odometry (None: never)
    stream_resend: tuple[float, float] | None = (0.03, 0.5)
    # at the end of a mission, every keyframe whose IMU-aided pose moved this far (m, deg) since it was sent
    # is sent again, so the server's last solve holds the agent's final odometry (None: never)
    stream_final_resend: tuple[float, float] | None = (0.001, 0.01)
    progress: bool = True
    # when frames reach the front-end (hivemap.client.pacing): asap (every frame, as fast as it takes
    # them), camera (at the recording's clock, every frame), live (the camera's clock, late frames dropped)
    pace: str = "asap"
    max_connect_attempts: int = 10  # streaming: see LinkOptions.max_connect_attempts
    # issue 25: detect the marker carriers of the dataset's ``markers.yaml`` in cam0 (``enabled=False``:
    # ``hivemap agent --no-markers``) and stream them as ``rendezvous`` messages
    markers: MarkerOptions = field(default_factory=MarkerOptions)


@dataclass
class RunSummary:
    """What ``run.json`` holds."""

    agent_id: str
    gnss_mode: str
    frames: int = 0
    tracked_frames: int = 0
    keyframes: int = 0
    tracking_losses: int = 0
    # every frame by the front-end's tracking quality (issue 28): few inliers, no visual pose taken
    # (IMU-only or lost), relocalised; visual poses the IMU gate refused; keyframes made at the IMU's
    # pose while lost; map sessions
    weak_frames: int = 0
    lost_frames: int = 0
    relocalized_frames: int = 0
    imu_rejections: int = 0
    lost_keyframes: int = 0
    sessions: int = 1
    segments: int = 0
    gnss_available: int = 0
    gnss_selected: int = 0
    gnss_used: int = 0
    gnss_rejected: int = 0
    frontend_ms_mean: float = 0.0
    frontend_ms_max: float = 0.0
    second_stage_ms_mean: float = 0.0
    second_stage_ms_max: float = 0.0
    wall_s: float = 0.0
    fps: float = 0.0
    pace: str = "asap"  # RunnerOptions.pace
    frames_dropped: int = 0  # pace live: frames skipped because a newer one was due
    late_max_s: float = 0.0  # pace camera/live: the furthest behind the recording's clock a frame was taken
    outputs: dict[str, str] = field(default_factory=dict)
    rejected_fixes: list[dict[str, float]] = field(default_factory=list)
    unsent: int = 0  # streaming: messages left in the outbox (not acknowledged by the server)
    stopped_by: str = ""  # streaming: the signal that ended the replay early ("SIGTERM", "SIGINT")
    # marker carriers seen (issue 25): rendezvous observations made (streaming: put into the outbox),
    # frames the detector ran on and its mean CPU time per such frame
    rendezvous_sent: int = 0
    marker_frames: int = 0
    marker_cpu_ms_mean: float = 0.0

    def to_json(self) -> str:
        from dataclasses import asdict

        return json.dumps(asdict(self), indent=2)
