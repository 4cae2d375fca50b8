"""A live simulated agent (``hivemap agent --sim SCENARIO:AGENT --live``, issue 26): frames, IMU and GNSS
rendered on the fly by :class:`hivemap.sim.live.LiveSim` are fed through :class:`hivemap.client.Agent`,
streamed to the server, and the server's team advisories steer the simulated agent.

Each advisory is in the frame of the agent's map; it is brought into the world frame through the agent's
own estimate (its latest tracked VIO pose, the correction's ``global_from_local`` of that session, identity
before the first), so the agent steers by where it thinks it is. Advisories are taken between frames, so
the run depends only on which advisory arrived before which frame.

The run ends after ``--duration`` simulated seconds, on SIGTERM/SIGINT, when the link fails, or when the
server, having given the agent goals, has had none for it for ``idle_stop_s`` (nothing left to explore).
Outputs: those of a replayed agent (``local.tum``, ``vio.tum``, ``run.json``, ...) plus the ground truth
``groundtruth.tum`` (body) and ``groundtruth_cam0.tum`` at every frame and ``live.json`` (why it stopped,
goals, path length, advisories).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.outputs import write_outputs
from hivemap.client.runner import RunnerOptions, RunSummary, write_tum_poses
from hivemap.sim.live import LiveOptions, LiveSim
from hivemap.sim.live_control import WorldAdvisory, world_from_map

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class LiveSummary:
    """What ``live.json`` holds."""

    agent_id: str
    scenario: str
    world_seed: int
    frames: int = 0
    sim_s: float = 0.0
    stopped_by: str = ""  # duration | explored | link | SIGTERM | SIGINT
    path_length_m: float = 0.0
    advisories: int = 0
    goals_received: int = 0  # advisories that carried goals
    goals_reached: int = 0
    obeyed: int = 0  # commands that took the advisory's safe velocity
    stopped_for_road: int = 0  # of those, a UGV's that stopped rather than leave the road
    replans: int = 0
    wall_s: float = 0.0
    advisory_log: list[dict[str, Any]] = field(default_factory=list)  # (sim t, goal world xy, safe velocity)


def _gnss_allows(mode: Any, t: float, last: list[float]) -> bool:
    """Whether the live GNSS ``mode`` (``hivemap.client.replay_io.GnssMode``) uses a fix taken at ``t``."""
    if mode.kind == "all":
        return True
    if mode.kind == "every" and t - last[0] >= mode.period_s - 1e-9:
        last[0] = t
        return True
    return False


class _Steering:
    """The agent's map-frame view: corrections' ``global_from_local`` per session, the latest world-from-map
    transform of a tracked frame, the newest advisory waiting for the next frame."""

    def __init__(self) -> None:
        self.global_from_sent: dict[int, F64] = {}
        self.world_from_map: F64 | None = None
        self._lock = threading.Lock()
        self._waiting: Any = None
        self.received = 0

    def on_advisory(self, msg: Any) -> None:  # the link's thread
        with self._lock:
            self._waiting = msg
            self.received += 1

    def take(self) -> Any:
        with self._lock:
            msg, self._waiting = self._waiting, None
            return msg


def run_live(
    sim_options: LiveOptions,
    out_dir: str | Path,
    server: str | None,
    agent_id: str | None,
    token: str,
    options: RunnerOptions | None = None,
    stopping: threading.Event | None = None,
    idle_stop_s: float = 15.0,
) -> tuple[RunSummary, LiveSummary]:
    """Run one live simulated agent (see the module docstring); ``server`` None: offline (no advisories,
    the agent holds its start). Raises ``StreamFailed`` as the streaming replay does."""
    from hivemap.client.agent import Agent, AgentOptions
    from hivemap.client.link import LinkFailed, LinkRefused
    from hivemap.client.logtags import tag_agent
    from hivemap.client.streaming import StreamFailed

    options = options or RunnerOptions(progress=False)
    if options.gnss.kind == "random":
        raise ValueError("a live agent cannot draw random fixes over a run it has not seen: use every:Ns")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sim = LiveSim(sim_options)
    aid = agent_id or sim.spec.agent_id
    tag_agent(aid)
    calib = sim.write_calibration(out / "calib")
    live = Agent.from_calibration([calib], agent_id=aid, kind=sim.spec.kind,
                                  options=AgentOptions(options))  # fmt: skip
    steer = _Steering()
    live.on_correction(lambda c: steer.global_from_sent.__setitem__(c.session, c.global_from_local))
    stopping = stopping or threading.Event()
    if server is not None:
        live.on_team_advisory(steer.on_advisory)
        live.connect(server, token, out)
    ls = LiveSummary(aid, sim.scenario.name, sim.scenario.seed)
    wall0 = time.perf_counter()
    n_frames, had_goals, idle_since, last_fix = 0, False, None, [-np.inf]
    try:
        while True:
            if stopping.is_set():
                ls.stopped_by = ls.stopped_by or "signal"
                break
            if server is not None and live.link_failed:
                ls.stopped_by = "link"
                break
            if n_frames and sim.t >= sim_options.duration_s:
                ls.stopped_by = "duration"
                break
            fr = sim.step()
            live.set_intent(fr.stamp, sim.intent_cam(fr.world_from_body))
            live.feed_imu_batch(fr.imu)
            for tf, enu, cov in fr.fixes:
                if _gnss_allows(options.gnss, tf, last_fix):
                    live.feed_gnss_cov(tf, enu, cov)
            res = live.feed_stereo(fr.stamp, fr.left, fr.right)
            n_frames += 1
            session = live.mission_session
            if res.tracked and res.world_from_body is not None and session is not None:
                G = steer.global_from_sent.get(session, np.eye(4))
                # the server's frame holds the agent's keyframes at their streamed poses
                C = live.core.latest_stream_from_vio()
                steer.world_from_map = world_from_map(fr.world_from_body, G @ C @ res.world_from_body)
            msg = steer.take()
            if msg is not None and steer.world_from_map is not None:
                adv = _to_world(msg, steer.world_from_map, fr.t)
                sim.advise(adv)
                ls.advisories += 1
                if len(adv.goals):
                    had_goals, idle_since = True, None
                    ls.goals_received += 1
                elif had_goals and idle_since is None:
                    idle_since = fr.t
                ls.advisory_log.append({
                    "t": round(fr.t, 3), "goals": np.round(adv.goals[:, :2], 2).tolist(),
                    "safe": np.round(adv.safe_velocity, 3).tolist(),
                    "desired": np.round(adv.desired_velocity, 3).tolist(), "radius": round(adv.radius_m, 3),
                    "half_height": round(adv.half_height_m, 3),
                })  # fmt: skip
            if idle_since is not None and fr.t - idle_since >= idle_stop_s:
                ls.stopped_by = "explored"
                break
            sim.steer()
        unsent = live.close(stop=stopping if not (server and live.link_failed) else _set())
    except BaseException:
        live.close(stop=_set())
        sim.close()
        raise
    sim.close()
    err = live.link_error
    if isinstance(err, LinkRefused | LinkFailed):
        raise StreamFailed(str(err), unsent, out / "outbox.sqlite") from err
    summary = RunSummary(agent_id=aid, gnss_mode=str(options.gnss))
    summary.unsent = unsent
    summary.stopped_by = ls.stopped_by
    summary.wall_s = time.perf_counter() - wall0
    write_outputs(live.core, out, summary, n_frames)
    gt_t, gt = np.asarray(sim.gt_t), np.asarray(sim.gt_poses).reshape(-1, 4, 4)
    write_tum_poses(out / "groundtruth.tum", gt_t, gt)
    write_tum_poses(out / "groundtruth_cam0.tum", gt_t, gt @ sim.T_BS[0])
    summary.outputs.update(groundtruth=str(out / "groundtruth.tum"), live=str(out / "live.json"))
    (out / "run.json").write_text(summary.to_json())
    c = sim.controller
    ls.frames, ls.sim_s, ls.path_length_m = n_frames, sim.t, sim.path_length()
    ls.goals_reached, ls.obeyed, ls.replans = c.goals_reached, c.obeyed, sim.motion.replans
    ls.stopped_for_road = c.stopped_for_road
    ls.wall_s = summary.wall_s
    (out / "live.json").write_text(json.dumps(asdict(ls), indent=1))
    log.info("live agent %s: %d frames (%.1f s simulated, %.1f m), %d advisories, stopped by %s",
             aid, n_frames, ls.sim_s, ls.path_length_m, ls.advisories, ls.stopped_by)  # fmt: skip
    return summary, ls


def _to_world(msg: Any, world_from_map_T: F64, t: float) -> WorldAdvisory:
    R = world_from_map_T[:3, :3]
    goals = np.asarray(msg.goals, dtype=np.float64).reshape(-1, 3)
    goals_w = goals @ R.T + world_from_map_T[:3, 3]
    return WorldAdvisory(
        t, goals_w, R @ np.asarray(msg.desired_velocity, dtype=np.float64),
        R @ np.asarray(msg.safe_velocity, dtype=np.float64), float(msg.radius_m), float(msg.half_height_m),
    )  # fmt: skip


def _set() -> threading.Event:
    ev = threading.Event()
    ev.set()
    return ev
