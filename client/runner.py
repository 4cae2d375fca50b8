"""Offline agent runner: dataset -> front-end -> second stage -> TUM trajectories + run log.

``run_offline(agent_dir, out_dir, options)`` replays one EuRoC-layout agent dataset through the
front-end (``hivemap.client.frontend``) and the second stage (``hivemap.client.second_stage``) with the
GNSS fixes a *GNSS mode* allows (paper Table 8):

- ``denied``: no fix is used;
- ``every:20s``: one valid fix every 20 s (the first valid fix, then the first valid fix at least
  20 s after the previously used one);
- ``random:4``: 4 valid fixes drawn at random (seeded) over the whole run;
- ``all``: every valid fix.

Outputs in ``out_dir``: ``vio.tum`` (every tracked frame, body pose in the VIO frame), ``local.tum``
(every tracked frame in the local frame, final smoothed estimate: the per-keyframe correction
interpolated between neighbouring keyframes), ``keyframes_local.tum``, ``run.json`` (summary: keyframe
count, tracking losses, GNSS used/rejected, timing) and ``frames.csv`` (per-frame timing and state).
TUM lines are ``t tx ty tz qx qy qz qw`` (seconds; quaternion x, y, z, w as TUM requires) of
``world_from_body`` (body = IMU frame, like the EuRoC ground truth).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.outputs import write_outputs
from hivemap.client.runner_options import RunnerOptions, RunSummary  # noqa: F401  (re-exported)

if TYPE_CHECKING:
    from hivemap.client.dataset import DatasetSource

# The GNSS modes, the dataset adapter and the TUM writer live in replay_io; imported here for this
# module's use and so that ``hivemap.client.runner.<name>`` keeps working.
from hivemap.client.replay_io import (  # noqa: F401
    GnssMode,
    _frame_times,
    _Gnss,
    _gnss_table,
    _imu,
    _imu_params,
    _load_pair,
    _seconds,
    parse_gnss_mode,
    select_gnss,
    write_tum_poses,
)

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------- run
# Relative-pose covariance used when the front-end gives none for a keyframe (e.g. its previous
# keyframe was culled): 1 deg and 5 cm + 2% of the distance, deliberately loose.
def _fallback_rel_cov(rel: F64) -> F64:
    d = float(np.linalg.norm(rel[:3, 3]))
    return np.diag([math.radians(1.0) ** 2] * 3 + [(0.05 + 0.02 * d) ** 2] * 3)


class OfflineAgent:
    """Front-end + second stage for one agent; feed frames with :meth:`step` (also used by streaming)."""

    def __init__(
        self,
        rig: object,
        imu_params: dict[str, float] | None,
        gnss: _Gnss,
        options: RunnerOptions,
        frontend_options: object | None = None,
        second_stage_options: object | None = None,
    ) -> None:
        from hivemap.client.frontend.tracker import Frontend
        from hivemap.client.odometry import StreamOdometry
        from hivemap.client.second_stage import SecondStage, SecondStageOptions

        self.options = options
        self.frontend = Frontend(rig, frontend_options, imu_params=imu_params)  # type: ignore[arg-type]
        self.stage = SecondStage(
            second_stage_options or SecondStageOptions(gravity_aligned=imu_params is not None)
        )  # type: ignore[arg-type]
        self.odometry = StreamOdometry(self.stage.options)  # what the keyframes are streamed at
        self.gnss = gnss
        self.selected = np.zeros(0, bool)
        self._fix_by_time: dict[float, int] = {}
        self._sess_segment: dict[int, int] = {}
        self._node_of: dict[tuple[int, int], int] = {}  # (session, kf_id) -> second-stage node id
        self._next_node = 0
        self.frame_log: list[dict[str, float | int | str]] = []
        self.vio_t: list[float] = []
        self.vio_poses: list[F64] = []
        self.vio_session: list[int] = []
        # per tracked frame: (session, reference keyframe id, ref_kf_from_frame) for the final estimate
        self.vio_ref: list[tuple[int, int, F64] | None] = []
        self._ref_kf: dict[int, int] = {}  # session -> last keyframe id created
        self.gnss_used = 0
        self.gnss_rejected = 0
        self.losses = 0
        self._was_lost = False
        self.stage_ms: list[float] = []
        self.fe_ms: list[float] = []
        self.on_event: Callable[[object], None] | None = None  # every front-end event, after fusion
        self.kf_fix: dict[tuple[int, int], int] = {}  # (session, kf_id) -> index of its accepted fix
        self.corrections_applied = 0
        self.corrections_refused = 0

    def select(self, frame_times: F64) -> None:
        """Choose the fixes of the GNSS mode and attach each to the closest frame time."""
        self.selected = select_gnss(self.gnss.t, self.gnss.valid, self.options.gnss, self.options.seed)
        if not len(frame_times):
            return
        for i in np.flatnonzero(self.selected):
            j = int(np.argmin(np.abs(frame_times - self.gnss.t[i])))
            if abs(frame_times[j] - self.gnss.t[i]) <= self.options.gnss_max_dt_s:
                self._fix_by_time[float(frame_times[j])] = int(i)

    def attach_fix(self, frame_t: float, t: float, enu: F64, cov: F64) -> int:
        """Live input: a fix (ENU, 3x3 covariance) taken at ``t``, used at the frame at ``frame_t`` (not yet
        stepped); returns its index in ``gnss``. Replays choose theirs up front with :meth:`select`."""
        g = self.gnss
        self.gnss = _Gnss(
            np.append(g.t, t), np.vstack([g.enu, np.reshape(enu, (1, 3))]),
            np.concatenate([g.cov, np.reshape(cov, (1, 3, 3))]), np.append(g.valid, True),
        )  # fmt: skip
        self.selected = np.append(self.selected, True)
        self._fix_by_time[float(frame_t)] = len(g.t)
        return len(g.t)

    def step(self, t: float, left: NDArray[np.uint8], right: NDArray[np.uint8], imu: F64 | None) -> object:
        import time

        from hivemap.client.frontend.tracker import TrackingState

        gnss_epoch = float(t) in self._fix_by_time
        t0 = time.perf_counter()
        res = self.frontend.process(t, left, right, imu, gnss_epoch=gnss_epoch)
        t1 = time.perf_counter()
        self.stage.add_imu(imu)
        self.odometry.add_imu(imu)
        self._consume(self.frontend.poll_events())
        t2 = time.perf_counter()
        self.fe_ms.append(1e3 * (t1 - t0))
        self.stage_ms.append(1e3 * (t2 - t1))
        lost = res.state == TrackingState.LOST
        if lost and not self._was_lost:
            self.losses += 1
        self._was_lost = lost
        if res.state.tracked:
            T_wb = np.asarray(res.world_from_body, dtype=np.float64)
            self.vio_t.append(float(t))
            self.vio_poses.append(T_wb)
            self.vio_session.append(int(res.session))
            if res.new_keyframe_id is not None:
                # The frame is the keyframe (its reported pose can predate a gravity re-alignment).
                self._ref_kf[int(res.session)] = int(res.new_keyframe_id)
                self.vio_ref.append((int(res.session), int(res.new_keyframe_id), np.eye(4)))
            else:
                self.vio_ref.append(self._reference(int(res.session), T_wb))
        self.frame_log.append(
            {
                "t": float(t),
                "state": str(res.state.value),
                "session": int(res.session),
                "n_tracked": int(res.n_tracked),
                "keyframe": -1 if res.new_keyframe_id is None else int(res.new_keyframe_id),
                "gnss_epoch": int(gnss_epoch),
                "frontend_ms": round(1e3 * (t1 - t0), 3),
                "second_stage_ms": round(1e3 * (t2 - t1), 3),
            }
        )
        return res

    def _reference(self, session: int, T_wb: F64) -> tuple[int, int, F64] | None:
        """The frame's pose relative to its reference keyframe, both as the front-end has them now.

        The front-end may re-express its VIO frame (gravity alignment) and move keyframes (local
        BA); a frame stored relative to its reference keyframe follows both (as ORB-SLAM saves
        trajectories).
        """
        k = self._ref_kf.get(session)
        if k is None:
            return None
        kf = self.frontend.keyframes.get(k)
        if kf is None or session != self.frontend.session:
            return None
        T_wkf = kf.T_wc @ np.linalg.inv(self.frontend.body_from_cam)
        return session, int(k), np.linalg.inv(T_wkf) @ T_wb

    def vio_trajectory(self) -> tuple[F64, F64]:
        """Every tracked frame's body pose in the (final) VIO frame of its session.

        Frames are re-expressed through their reference keyframe's final VIO pose when that keyframe
        reached the second stage; otherwise the pose the front-end reported at the time is used.
        """
        out = []
        for T, ref in zip(self.vio_poses, self.vio_ref, strict=True):
            node = self._node_of.get((ref[0], ref[1])) if ref is not None else None
            if ref is not None and node is not None:
                out.append(self.stage.vio_pose(node) @ ref[2])
            else:
                out.append(T)
        return np.asarray(self.vio_t), np.asarray(out).reshape(-1, 4, 4)

    def finish(self) -> None:
        self.frontend.flush()
        self._consume(self.frontend.poll_events())

    def _consume(self, events: list[object]) -> None:
        from hivemap.client.frontend.tracker import KeyframeEvent, PoseUpdateEvent

        cam_from_body = np.linalg.inv(self.frontend.body_from_cam)
        for ev in events:
            if isinstance(ev, KeyframeEvent):
                self._add_keyframe(ev)
            elif isinstance(ev, PoseUpdateEvent):
                upd = {}
                for kid, T_wc in zip(ev.kf_ids, ev.world_from_cam, strict=True):
                    node = self._node_of.get((ev.session, int(kid)))
                    if node is not None:
                        upd[node] = T_wc @ cam_from_body
                self.stage.update_vio_poses(upd)
                self.odometry.update_vio_poses(upd)
            if self.on_event is not None:
                self.on_event(ev)

    def _add_keyframe(self, ev: object) -> None:
        from hivemap.client.frontend.tracker import KeyframeEvent

        assert isinstance(ev, KeyframeEvent)
        node = self._next_node
        self._next_node += 1
        self._node_of[(ev.session, ev.kf_id)] = node
        prev = self._node_of.get((ev.session, ev.prev_kf_id)) if ev.prev_kf_id is not None else None
        new_segment = ev.session not in self._sess_segment
        T_wb = np.asarray(ev.world_from_body, dtype=np.float64)
        kw: dict[str, object]
        if new_segment:
            kw = {"new_segment": True}
        elif prev is not None and ev.rel_body is not None and ev.rel_cov is not None:
            kw = {"rel_cov": ev.rel_cov, "prev_id": prev, "prev_from_kf": ev.rel_body}
        else:
            # No relative pose from the front-end: chain to the session's last keyframe.
            last = max(n for (s, _), n in self._node_of.items() if s == ev.session and n != node)
            rel = np.linalg.inv(self.stage.vio_pose(last)) @ T_wb
            kw = {"rel_cov": _fallback_rel_cov(rel), "prev_id": last}
        self.stage.add_keyframe(node, ev.timestamp, T_wb, **kw)  # type: ignore[arg-type]
        self.odometry.add_keyframe(node, ev.timestamp, T_wb, **kw)
        if new_segment:
            self._sess_segment[ev.session] = self.stage.segment_count - 1
        fix = self._fix_by_time.get(float(ev.timestamp))
        if fix is not None:
            d = self.stage.add_gnss(node, self.gnss.enu[fix], self.gnss.cov[fix])
            if d.accepted:
                self.gnss_used += 1
                self.kf_fix[(ev.session, ev.kf_id)] = fix
            else:
                self.gnss_rejected += 1

    def stream_from_vio(self, session: int, kf_id: int | None) -> F64:
        """:meth:`StreamOdometry.stream_from_vio` of a front-end keyframe (identity if unknown)."""
        node = None if kf_id is None else self._node_of.get((int(session), int(kf_id)))
        return self.odometry.stream_from_vio(node)

    def latest_stream_from_vio(self) -> F64:
        """:meth:`stream_from_vio` of the newest keyframe of the latest tracked frame's session: what
        takes a current VIO pose into the frame the agent streams in."""
        if not self.vio_session:
            return np.eye(4)
        session = int(self.vio_session[-1])
        return self.stream_from_vio(session, self._ref_kf.get(session))

    def apply_correction(
        self,
        session: int,
        kf_ids: NDArray[np.int64],
        global_from_kf_cam: F64,
        global_from_sent: F64,
        enu: bool = False,
        via: tuple[int, F64] | None = None,
    ) -> int:
        """Co-location factors from a server correction (poses of the agent's keyframes in the global
        frame + ``global_from_local`` of the frame the keyframes were sent in: the odometry's frame,
        :meth:`StreamOdometry.local_from_stream`).

        ``via``: (an earlier session of this front-end in the same server map, that session's latest
        ``global_from_local``). The poses are then brought into the local frame through that session's
        frame, not their own: the server's map says where this session lies from that one, which the
        agent itself only guessed when it lost tracking (the new segment's frame came from IMU
        propagation), so the segments are tied together in the local frame. The gate then judges the
        poses' shape within the segment (after one fitted shift and yaw), not that shift.

        Each corrected pose is brought back into the sent frame, then into the local frame with
        the segment's current ``local_from_stream``, and added as a prior with ``options.colocation_sigma``.
        With ``enu`` (the server's map is in the ENU frame of the GNSS fixes) and a local frame that is
        ENU too (this agent fused a fix), the corrected poses are absolute local poses: the team's
        GNSS fixes then place this agent in ENU, not only its own. Returns the number of keyframes used.
        """
        from hivemap.maps.geometry import Sim3

        if len(kf_ids) == 0:
            return 0  # a new frame only (e.g. after a merge): the current priors stay valid
        absolute = enu and self.gnss_used > 0
        via_seg = None if via is None or absolute else self._segment_of_session(via[0])
        frame_of = via[1] if via is not None and via_seg is not None else global_from_sent
        sent_from_global = Sim3.from_matrix(np.asarray(frame_of, dtype=np.float64)).inverse()
        cam_from_body = np.linalg.inv(self.frontend.body_from_cam)
        rot, trans = self.options.colocation_sigma
        cov = np.diag([rot**2] * 3 + [trans**2] * 3)
        candidates: dict[int, F64] = {}
        local_from_sent: dict[int, F64] = {}
        for kid, T_gc in zip(
            np.asarray(kf_ids), np.asarray(global_from_kf_cam).reshape(-1, 4, 4), strict=True
        ):
            node = self._node_of.get((int(session), int(kid)))
            if node is None:
                continue
            if absolute:
                prior = T_gc @ cam_from_body
            else:
                # the keyframe was sent at its streamed pose (:mod:`hivemap.client.odometry`), in its own
                # segment's frame or, tied, in the earlier session's
                seg = via_seg if via_seg is not None else self.stage.keyframe_segment(node)
                if seg not in local_from_sent:
                    local_from_sent[seg] = self.odometry.local_from_stream(self.stage, seg)
                prior = local_from_sent[seg] @ sent_from_global.transform_pose(T_gc @ cam_from_body)
            candidates[node] = prior
        priors: dict[int, tuple[F64, F64]] = {}
        for node, gap in self._gaps(candidates, tied=via_seg is not None).items():
            if gap > self.options.colocation_gate_m:
                # a server pose this far from ours is a server-side failure, not a correction
                self.corrections_refused += 1
                continue
            priors[node] = (candidates[node], cov)
        # each correction is a whole snapshot of the server's estimate for one session: it replaces that
        # session's previous priors (and only those)
        scope = {n for (s, _), n in self._node_of.items() if s == int(session)}
        self.stage.set_colocations(priors, enu=enu and self.gnss_used > 0, scope=scope)
        n = len(priors)
        self.corrections_applied += n
        return n

    def _segment_of_session(self, session: int) -> int | None:
        """The second-stage segment of front-end session ``session`` (None before its first keyframe)."""
        return self._sess_segment.get(int(session))

    def _gaps(self, priors: dict[int, F64], tied: bool) -> dict[int, float]:
        """Per keyframe node, how far its prior lies from the stage's estimate; ``tied``: after the one
        shift and yaw (rigid without gravity) that best takes the estimates onto the priors."""
        from hivemap.client.second_stage.factors import frame_fit

        nodes = list(priors)
        if not nodes:
            return {}
        dst = np.array([priors[n][:3, 3] for n in nodes])
        src = np.array([self.stage.keyframe_pose(n)[:3, 3] for n in nodes])
        if tied:
            shift = np.eye(4)
            shift[:3, 3] = (dst - src).mean(axis=0)
            F = frame_fit(src, dst, self.stage.options.gravity_aligned, shift)
            src = src @ F[:3, :3].T + F[:3, 3]
        return dict(zip(nodes, np.linalg.norm(dst - src, axis=1).tolist(), strict=True))

    def up_in_cam(self, session: int, kf_id: int) -> F64 | None:
        """The keyframe's up direction (unit, against gravity) in its camera frame, from the second stage
        when it fuses the IMU (its local frame's z is then up); None without IMU factors."""
        node = self._node_of.get((int(session), int(kf_id)))
        if node is None or self.stage.options.imu is None:
            return None
        R_local_cam = self.stage.keyframe_pose(node)[:3, :3] @ self.frontend.body_from_cam[:3, :3]
        up = R_local_cam.T @ np.array([0.0, 0.0, 1.0])
        return up / np.linalg.norm(up)

    def local_trajectory(self) -> tuple[F64, F64]:
        """Every tracked frame's pose in the local frame (final estimate, interpolated corrections)."""
        out = []
        _, vio = self.vio_trajectory()
        for t, T, s in zip(self.vio_t, vio, self.vio_session, strict=True):
            seg = self._sess_segment.get(s)
            if seg is None:  # a session whose keyframes never reached the second stage
                out.append(T)
            else:
                out.append(self.stage.local_from_frame(t, T, segment=seg))
        return np.asarray(self.vio_t), np.asarray(out).reshape(-1, 4, 4)


def _make_agent(
    ds: Any,
    gnss: _Gnss,
    options: RunnerOptions,
    frontend_options: object | None,
    second_stage_options: object | None,
) -> OfflineAgent:
    from hivemap.client.second_stage import ImuOptions, SecondStageOptions

    if getattr(ds, "rig", None) is None:
        raise ValueError("the dataset has no stereo pair (cam1): the built-in front-end needs stereo")
    imu_params = _imu_params(ds)
    if second_stage_options is None:
        # second-stage nodes are body poses: the antenna lever arm is T_BS(gnss0)'s translation
        T_BS = getattr(ds, "T_BS", {}) or {}
        lever = np.asarray(T_BS.get("gnss0", np.eye(4)), dtype=np.float64)[:3, 3]
        imu = None
        if imu_params is not None and options.imu_factors:
            # the second stage's nodes are body poses, so the IMU's pose in them is T_BS(imu0)
            imu = ImuOptions.from_noise(imu_params, np.asarray(T_BS.get("imu0", np.eye(4)), dtype=np.float64))
        offset = offset_enu = None
        if options.colocation_offset:
            tilt = 0.05 if imu is not None else 0.01
            offset, offset_enu = (tilt, 0.01, 0.1), (tilt, 0.01, 0.01)
        second_stage_options = SecondStageOptions(
            gravity_aligned=imu_params is not None,
            kf_from_antenna=(float(lever[0]), float(lever[1]), float(lever[2])),
            imu=imu,
            colocation_offset_sigma=offset,
            colocation_offset_sigma_enu=offset_enu,
        )
    return OfflineAgent(ds.rig, imu_params, gnss, options, frontend_options, second_stage_options)


def run_offline(
    agent_dir: DatasetSource,
    out_dir: str | Path,
    options: RunnerOptions | None = None,
    frontend_options: object | None = None,
    second_stage_options: object | None = None,
) -> RunSummary:
    """Replay one agent dataset without a server; writes the outputs listed in the module docstring."""
    import time

    from hivemap.client.logtags import tag_agent

    options = options or RunnerOptions()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from hivemap.client.replay import Replay

    replay = Replay.open(agent_dir, options, frontend_options, second_stage_options)
    tag_agent(replay.live.agent_id)  # log lines say which agent speaks
    wall0 = time.perf_counter()
    n_frames = replay.feed()
    replay.live.close()
    summary = replay.summary()
    summary.wall_s = time.perf_counter() - wall0
    write_outputs(replay.live.core, out, summary, n_frames)
    log.info(
        "agent %s: %d frames, %d keyframes, %d tracking losses, GNSS %d used / %d rejected, %.1f fps",
        summary.agent_id, summary.frames, summary.keyframes, summary.tracking_losses, summary.gnss_used,
        summary.gnss_rejected, summary.fps,
    )  # fmt: skip
    return summary


def __getattr__(name: str) -> Any:
    """The streaming entry points moved to ``hivemap.client.streaming`` and ``hivemap.client.health``;
    imported lazily (they import this one) so ``from hivemap.client.runner import run_streaming``
    keeps working."""
    if name == "run_streaming":
        from hivemap.client import streaming

        return streaming.run_streaming
    if name in ("health_url", "wait_for_server"):
        from hivemap.client import health

        return getattr(health, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
