"""Live input: drive a hivemap agent from a camera driver, a ROS node or any loop of your own.

::

    from hivemap.client import Agent

    agent = Agent.from_calibration(["mav0/"], agent_id="uav1")          # or Agent(rig, imu_noise=..., ...)
    agent.on_correction(lambda c: print("moved", c.keyframes, "keyframes into map", c.map_id))
    agent.connect("ws://server:8765/ws", token="secret", out_dir="agent-uav1")   # optional: stream
    for each IMU sample:   agent.feed_imu(t, gyro_xyz, accel_xyz)                # rad/s, m/s^2, body frame
    for each GNSS fix:     agent.feed_gnss(t, enu_xyz, sigma_h, sigma_v)        # metres, ENU
    for each stereo pair:  result = agent.feed_stereo(t, left, right)           # uint8 gray images
    agent.pose()           # latest world_from_body 4x4 in the local frame (None before tracking)
    agent.close()          # flush the front-end, wait for the server's acks and last corrections

Times are seconds on one clock for all sensors. IMU samples must arrive before the frame they lead up
to (each frame takes the samples after the previous frame up to its own time). A fix is used at the
first frame within ``RunnerOptions.gnss_max_dt_s`` of it (that frame becomes a keyframe); a fix that
arrives after its frame is dropped. ``world_from_body`` poses are of the IMU (body) frame, as in EuRoC.

Both dataset replays (``hivemap agent --offline`` and ``--server``) feed datasets through this class, so
what a live agent computes is what the replays are tested on. Corrections from the server are applied
between frames (on the thread that calls ``feed_stereo``; after the last frame on the one that calls
``close``), then the callbacks run. Corrections for sessions of an earlier process of the same mission
(a restart on the same outbox) are not this front-end's and are ignored.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.agent_stream import AgentStream
from hivemap.client.logtags import CorrectionSummary
from hivemap.client.rendezvous import RendezvousSource
from hivemap.client.replay_io import _Gnss
from hivemap.client.runner import OfflineAgent, RunnerOptions, _make_agent
from hivemap.maps.camera import PinholeCamera, StereoRig
from hivemap.maps.markers import LAYOUT_FILE, Carrier, load_layout
from hivemap.protocol import Rendezvous

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class AgentOptions:
    """Tuning of a live agent: the replay's options (GNSS association, co-location priors, IMU
    factors), the front-end's and the second stage's (None: their defaults)."""

    runner: RunnerOptions = field(default_factory=lambda: RunnerOptions(progress=False))
    frontend: object | None = None
    second_stage: object | None = None


@dataclass(frozen=True)
class FrameResult:
    """What one stereo frame gave: tracking state, whether it became a keyframe, its VIO pose."""

    t: float
    state: str  # "ok", "relocalized", "new_map", "lost", ...
    tracked: bool
    keyframe_id: int | None
    world_from_body: F64 | None  # VIO frame; ``Agent.pose()`` gives the local frame


@dataclass(frozen=True)
class CorrectionInfo:
    """A server correction after it was applied (see ``Agent.on_correction``)."""

    map_id: int
    frame: str  # "map" or "enu"
    session: int
    keyframes: int  # keyframes that became co-location factors
    global_from_local: F64  # (4, 4) Sim(3) matrix of the frame the keyframes were sent in


@dataclass(frozen=True)
class _Sensors:
    """What ``runner._make_agent`` reads of a dataset."""

    rig: StereoRig
    T_BS: dict[str, F64]
    imu_noise: dict[str, float] | None
    imu: F64


class Agent:
    """One agent fed live (see the module docstring)."""

    def __init__(
        self,
        rig: StereoRig,
        *,
        agent_id: str = "agent",
        kind: str = "uav",
        imu_noise: dict[str, float] | None = None,
        T_BS: dict[str, F64] | None = None,
        use_imu: bool = True,
        options: AgentOptions | None = None,
        carriers: Mapping[str, Carrier] | None = None,
    ) -> None:
        """``rig``: the stereo pair (``T_BS`` of cam0/cam1 inside); ``imu_noise``: EuRoC/Kalibr IMU noise
        names (defaults when empty); ``T_BS``: body_from_sensor for ``imu0`` and ``gnss0`` (lever arm);
        ``use_imu=False``: a camera-only agent (no IMU samples expected); ``carriers``: the team's marker
        carriers (``hivemap.maps.markers.load_layout``): the other agents' are masked out of tracking
        (``FrontendOptions.carrier_mask``) and, unless ``RunnerOptions.markers`` is off, streamed as
        rendezvous."""
        self.agent_id, self.kind = agent_id, kind
        self.options = options or AgentOptions()
        self.rig = rig
        self.use_imu = use_imu
        T = {"cam0": rig.body_from_left, "cam1": rig.body_from_right, **(T_BS or {})}
        self.T_BS = T
        noise = (imu_noise or {}) if use_imu else None
        sensors = _Sensors(rig, T, noise, np.zeros((1 if use_imu else 0, 7)))
        empty = _Gnss(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, bool))
        self.core: OfflineAgent = _make_agent(
            sensors, empty, self.options.runner, self.options.frontend, self.options.second_stage
        )
        self._imu: list[tuple[float, float, float, float, float, float, float]] = []
        self._prev_t = -np.inf
        self._fixes: list[tuple[float, F64, F64]] = []
        self._lock = threading.RLock()
        self._pending: list[Any] = []  # protocol Correction messages, applied between frames
        self._callbacks: list[Callable[[CorrectionInfo], None]] = []
        self._stream: AgentStream | None = None
        self._first_session = 0  # the mission's session this process's front-end session 0 is
        self._last_correction = time.monotonic()
        # per mission session its latest correction's (map id, frame "map"/"enu", global_from_local)
        self._frames: dict[int, tuple[int, str, F64]] = {}
        self._corrections_log = CorrectionSummary(log)  # DEBUG each, INFO every 10 s
        self.link_error: BaseException | None = None  # why the link ended (refused, unreachable), if it did
        self.link_stats: Any = None  # hivemap.client.link.LinkStats of the last connection
        self.frames = 0
        self.rendezvous: RendezvousSource | None = None
        mk = self.options.runner.markers
        if carriers and any(a != agent_id for a in carriers):
            # the carriers move: masked out of tracking whether or not their sightings are streamed
            self.core.frontend.use_carriers(carriers, agent_id, mk)
            if mk.enabled:
                self.rendezvous = RendezvousSource(rig.left, carriers, agent_id, mk)
        self._rendezvous_callbacks: list[Callable[[Rendezvous], None]] = []
        self._advisory_callbacks: list[Callable[[Any], None]] = []
        # (frame time, intended velocity in that frame's cam0): keyframes are emitted a few frames late
        self._intents: deque[tuple[float, F64]] = deque(maxlen=64)

    # -- construction ---------------------------------------------------------------------------------
    @classmethod
    def from_calibration(cls, paths: Sequence[str | Path], **kwargs: Any) -> Agent:
        """From a EuRoC ``mav0`` folder or Kalibr yaml files (as ``hivemap agent --calib``)."""
        from hivemap.client.bag_calib import load_calibration

        calib = load_calibration([Path(p) for p in paths])
        rig = calib.stereo_rig()
        if rig is None:
            raise ValueError("the built-in front-end needs a stereo calibration (cam0 and cam1)")
        kwargs.setdefault("agent_id", calib.agent_id or "agent")
        kwargs.setdefault("kind", calib.kind or "uav")
        return cls(rig, imu_noise=calib.imu_noise, T_BS=calib.T_BS, **kwargs)

    @classmethod
    def from_dataset(cls, ds: Any, **kwargs: Any) -> Agent:
        """With a dataset's calibration (``hivemap.client.dataset.AgentDataset``), e.g. to replay it."""
        if ds.rig is None:
            raise ValueError("the dataset has no stereo pair (cam1): the built-in front-end needs stereo")
        kwargs.setdefault("agent_id", ds.agent_id)
        kwargs.setdefault("kind", ds.kind)
        kwargs.setdefault("use_imu", len(ds.imu) > 0)
        layout = Path(ds.root) / LAYOUT_FILE
        if "carriers" not in kwargs and layout.is_file():
            kwargs["carriers"] = load_layout(layout)  # LayoutError: one line naming the file and field
        return cls(ds.rig, imu_noise=dict(ds.imu_noise), T_BS=dict(ds.T_BS), **kwargs)

    @property
    def camera(self) -> PinholeCamera:
        cam: PinholeCamera = self.rig.left
        return cam

    # -- input ----------------------------------------------------------------------------------------
    def feed_imu(self, t: float, gyro: Sequence[float] | F64, accel: Sequence[float] | F64) -> None:
        """One IMU sample: angular rate [rad/s] and specific force [m/s^2] in the IMU (body) frame."""
        g, a = np.asarray(gyro, dtype=np.float64).reshape(3), np.asarray(accel, dtype=np.float64).reshape(3)
        with self._lock:
            if self._imu and t <= self._imu[-1][0]:
                log.warning("IMU sample at %.6f s not after the previous one: dropped", t)
                return
            self._imu.append((float(t), *g.tolist(), *a.tolist()))  # type: ignore[arg-type]

    def feed_imu_batch(self, rows: F64) -> None:
        """IMU samples (N, 7): ``[t, w_x, w_y, w_z, a_x, a_y, a_z]``, increasing in time."""
        for r in np.asarray(rows, dtype=np.float64).reshape(-1, 7):
            self.feed_imu(float(r[0]), r[1:4], r[4:7])

    def feed_gnss(self, t: float, enu: Sequence[float] | F64, sigma_h: float, sigma_v: float) -> None:
        """One GNSS fix in ENU metres (around the mission's origin) with its horizontal/vertical sigma."""
        self.feed_gnss_cov(t, enu, np.diag([sigma_h**2, sigma_h**2, sigma_v**2]).astype(np.float64))

    def feed_gnss_cov(self, t: float, enu: Sequence[float] | F64, cov: F64) -> None:
        """One GNSS fix in ENU metres with its full 3x3 covariance [m^2]."""
        with self._lock:
            self._fixes.append(
                (
                    float(t),
                    np.asarray(enu, dtype=np.float64).reshape(3),
                    np.asarray(cov, np.float64).reshape(3, 3),
                )
            )

    def feed_stereo(self, t: float, left: U8, right: U8) -> FrameResult:
        """One rectification-free stereo pair (gray uint8, the calibration's distortion is modelled)."""
        with self._lock:
            applied = self._apply_pending()
            imu = self._take_imu(t)
            max_dt = self.options.runner.gnss_max_dt_s
            keep = []
            for tf, enu, cov in self._fixes:
                if abs(tf - t) <= max_dt:
                    self.core.attach_fix(t, tf, enu, cov)
                elif tf > t:
                    keep.append((tf, enu, cov))
                # else: its frame has passed
            self._fixes = keep
            res: Any = self.core.step(t, left, right, imu)
            self._prev_t = t
            self.frames += 1
            rv = self.rendezvous
            seen = [] if rv is None else rv.observe(t, left, res, self.core.frontend)
            for r in seen:
                if self._stream is not None:  # after the frame's keyframes: the reference is sent first
                    self._stream.send_rendezvous(r)
            tracked = res.state.tracked
            out = FrameResult(
                float(t), str(res.state.value), tracked,
                None if res.new_keyframe_id is None else int(res.new_keyframe_id),
                np.asarray(res.world_from_body, dtype=np.float64) if tracked else None,
            )  # fmt: skip
        for info in applied:
            for cb in list(self._callbacks):
                cb(info)
        for r in seen:
            for rcb in list(self._rendezvous_callbacks):
                rcb(r)
        return out

    def _take_imu(self, t: float) -> F64 | None:
        if not self.use_imu:
            return None
        n = 0
        while n < len(self._imu) and self._imu[n][0] <= t:
            n += 1
        rows = [r for r in self._imu[:n] if r[0] > self._prev_t]
        del self._imu[:n]
        return np.asarray(rows, dtype=np.float64).reshape(-1, 7)

    # -- output ---------------------------------------------------------------------------------------
    def pose(self, frame: str = "local") -> F64 | None:
        """The latest tracked frame's world_from_body, in the ``local`` frame (after GNSS and the server's
        co-location factors) or the front-end's ``vio`` frame; None before tracking starts."""
        with self._lock:
            c = self.core
            if not c.vio_t:
                return None
            T = np.asarray(c.vio_poses[-1], dtype=np.float64)
            if frame == "vio":
                return T
            if frame != "local":
                raise ValueError(f"frame must be 'local' or 'vio', not {frame!r}")
            seg = c._sess_segment.get(c.vio_session[-1])
            return T if seg is None else np.asarray(c.stage.local_from_frame(c.vio_t[-1], T, segment=seg))

    def on_correction(self, callback: Callable[[CorrectionInfo], None]) -> None:
        """Call ``callback(CorrectionInfo)`` after each server correction is applied."""
        self._callbacks.append(callback)

    def on_rendezvous(self, callback: Callable[[Rendezvous], None]) -> None:
        """Call ``callback(Rendezvous)`` for each marker carrier seen (the front-end's session numbering)."""
        self._rendezvous_callbacks.append(callback)

    def on_team_advisory(self, callback: Callable[[Any], None]) -> None:
        """Ask the server for team advisories (``hivemap.protocol.TeamAdvisory``: exploration goals and a
        safe velocity, in the frame of the agent's map) and call ``callback`` with each, on the link's thread.
        Call before ``connect``."""
        if self._stream is not None:
            raise RuntimeError("on_team_advisory() before connect(): the hello asks for advisories")
        self._advisory_callbacks.append(callback)

    def set_intent(self, t: float, velocity_cam: Sequence[float] | F64) -> None:
        """What the agent's planner will fly from the frame at time ``t`` (the mean velocity over the next
        seconds along its path, m/s, in that frame's cam0 frame). A keyframe of that frame carries it to the
        server (``hivemap.protocol.Keyframe.intent_velocity``), whose collision advisories then predict
        this agent along it. Call before feeding the frame."""
        v = np.asarray(velocity_cam, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"intended velocity must be finite, got {v.tolist()}")
        with self._lock:
            self._intents.append((float(t), v.copy()))

    def intent_at(self, t: float) -> F64 | None:
        """The intended velocity set for the frame at time ``t`` (within 1 ms), or None."""
        with self._lock:
            for ti, v in reversed(self._intents):
                if abs(ti - t) <= 1e-3:
                    return v
        return None

    def _advisory(self, msg: Any) -> None:
        for cb in list(self._advisory_callbacks):
            cb(msg)

    @property
    def mission_session(self) -> int | None:
        """The mission session of the latest tracked frame (the ``session`` of its corrections and
        advisories); None before tracking starts."""
        with self._lock:
            c = self.core
            return None if not c.vio_session else self._first_session + int(c.vio_session[-1])

    def submit_correction(self, msg: Any) -> None:
        """A server ``Correction`` (``hivemap.protocol``), applied before the next frame. ``connect`` does
        this itself; call it when you run your own link. Thread-safe."""
        with self._lock:
            self._pending.append(msg)
            self._last_correction = time.monotonic()

    def apply_corrections(self) -> list[CorrectionInfo]:
        """Apply the corrections received since the last frame now (``feed_stereo`` does this before each
        frame), then run the callbacks; returns what was applied."""
        with self._lock:
            applied = self._apply_pending()
        for info in applied:
            for cb in list(self._callbacks):
                cb(info)
        return applied

    def _apply_pending(self) -> list[CorrectionInfo]:
        todo, self._pending = self._pending, []
        first = self._first_session
        out = []
        for c in todo:
            if c.session < first:  # a session of the process that ran this mission before
                log.debug("correction for session %d of an earlier process: not this front-end's", c.session)
                continue
            G = np.asarray(c.global_from_local, dtype=np.float64)
            here = (int(c.map_id), str(c.global_frame))
            # the first earlier session of this front-end in the same map (the server sends every session
            # of a map its correction in turn, the first one first): the new one is tied to it
            same = [s for s in sorted(self._frames) if first <= s < c.session and self._frames[s][:2] == here]
            ref = same[0] if same else None
            via = None if ref is None else (ref - first, self._frames[ref][2])
            n = self.core.apply_correction(
                c.session - first, c.kf_ids, c.world_from_cam, G, enu=c.global_frame == "enu", via=via
            )
            self._frames[int(c.session)] = (*here, G)
            self._corrections_log.add(int(c.map_id), str(c.global_frame), n)
            out.append(CorrectionInfo(int(c.map_id), str(c.global_frame), int(c.session), n,
                                      np.asarray(c.global_from_local, dtype=np.float64)))  # fmt: skip
        return out

    def corrected_sessions(self) -> dict[int, str]:
        """Each mission session of this process that the server corrected, with the frame ("map" or
        "enu") of its latest correction."""
        with self._lock:
            return {s: frame for s, (_, frame, _) in self._frames.items()}

    def snapshot_frame(self, session: int) -> str:
        """The frame :meth:`apply_snapshot` wants ``session``'s poses in: "global" when its corrections
        are absolute ENU poses for this agent (it fused a GNSS fix), else "local" (the frame it sent
        them in)."""
        with self._lock:
            enu = session in self._frames and self._frames[session][1] == "enu"
            return "global" if enu and self.core.gnss_used > 0 else "local"

    def apply_snapshot(self, session: int, kf_ids: NDArray[np.int64], world_from_cam: F64) -> int:
        """The server's estimate of every keyframe of ``session``, in :meth:`snapshot_frame`, as one
        correction's co-location priors (they replace the session's earlier ones); the agent's frame
        transform is left as it is. Returns the keyframes fused."""
        with self._lock:
            if session not in self._frames or session < self._first_session:
                return 0
            frame = self._frames[session][1]
            return self.core.apply_correction(session - self._first_session, kf_ids, world_from_cam,
                                              np.eye(4), enu=frame == "enu")  # fmt: skip

    # -- streaming ------------------------------------------------------------------------------------
    def connect(
        self, server: str, token: str, out_dir: str | Path, max_connect_attempts: int | None = None
    ) -> None:
        """Stream keyframes and map points to ``server`` (``ws://HOST:PORT/ws``) from a background thread;
        ``out_dir`` holds the durable outbox: one outbox is one mission, an unfinished one is resumed
        (unsent messages survive a restart), a finished one is archived and a new mission begins. The
        link gives up after ``max_connect_attempts`` failed attempts in a row (default: the runner
        options'); then ``link_error`` says why. Call before the first frame."""
        from hivemap.client.link import check_server_url

        if (bad := check_server_url(server)) is not None:
            raise ValueError(f"server URL: {bad}")
        if self.frames:
            raise RuntimeError("connect() before the first frame: the server needs every keyframe")
        attempts = max_connect_attempts or self.options.runner.max_connect_attempts
        self._stream = AgentStream(self, server, token, Path(out_dir), attempts)
        self._first_session = self._stream.first_session
        self.link_error = None
        self.core.on_event = self._stream.on_event

    @property
    def link_failed(self) -> bool:
        """The link of ``connect`` ended by itself (refused, or gave up reconnecting: see ``link_error``)."""
        stream = self._stream
        if stream is not None and stream.task.done():
            self.link_error = stream.failure()
        return self.link_error is not None

    def close(self, timeout: float | None = None, *, stop: threading.Event | None = None) -> int:
        """Flush the front-end (its last keyframes); when connected, wait up to ``timeout`` s (default:
        ``RunnerOptions.flush_timeout_s``) for the server's acks, then for the corrections the server
        still owes (``RunnerOptions.corrections_*``; applied here, callbacks included), mark the mission
        complete when everything was acknowledged and stop the link. Returns the messages left unsent
        (kept in the outbox for the next start). ``stop`` set (a signal, a shutdown): end at once, with
        no flush and no waiting; what was produced stays in the outbox."""
        if stop is None or not stop.is_set():
            with self._lock:
                self.core.finish()
        if self._stream is None:
            self._corrections_log.flush()
            return 0
        stream, self._stream = self._stream, None
        unsent = stream.close(self.options.runner.flush_timeout_s if timeout is None else timeout, stop)
        self.link_error = stream.failure()
        self.link_stats = stream.link.stats
        self._corrections_log.flush()
        return unsent
