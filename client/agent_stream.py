"""The server link of a connected :class:`~hivemap.client.agent.Agent`: its own event loop in a thread,
the front-end's events turned into protocol messages into the mission's outbox, and a clean close."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import dataclasses
import logging
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hivemap.protocol import Rendezvous

if TYPE_CHECKING:
    from hivemap.client.agent import Agent

log = logging.getLogger(__name__)


class AgentStream:
    """The link of a connected :class:`Agent`: its own event loop in a thread, fed thread-safely."""

    def __init__(self, agent: Agent, server: str, token: str, out: Path, max_attempts: int) -> None:
        from hivemap.client.link import AgentLink, LinkOptions
        from hivemap.client.outbox import open_mission_outbox

        out.mkdir(parents=True, exist_ok=True)
        self.agent = agent
        self.server = server
        self.box = open_mission_outbox(out, agent.agent_id)
        self.first_session = self.box.start_session()
        if self.first_session:
            log.info("agent %s resumes mission %s in session %d", agent.agent_id, self.box.mission,
                     self.first_session)  # fmt: skip
        self._sessions = {self.first_session}
        from hivemap.client.odometry import StreamedPoses

        if agent.core.options.stream_imu_odometry:
            agent.core.odometry.start()
        self._streamed = StreamedPoses(agent.core.stream_from_vio)
        T = agent.T_BS
        lever = None
        if "gnss0" in T and "cam0" in T:
            lever = (np.linalg.inv(np.asarray(T["cam0"])) @ np.asarray(T["gnss0"]))[:3, 3].copy()
        self.loop = asyncio.new_event_loop()
        self.link = AgentLink(
            server, agent.agent_id, agent.kind, agent.camera.to_dict(), token, self.box,
            on_correction=agent.submit_correction, cam_from_antenna=lever, session=self.first_session,
            options=LinkOptions(max_connect_attempts=max_attempts), stereo_baseline=agent.rig.baseline,
            on_team_advisory=agent._advisory if agent._advisory_callbacks else None,
        )  # fmt: skip
        # the link's log lines carry the agent tag of the context that connected (hivemap.client.logtags)
        ctx = contextvars.copy_context()
        self._thread = threading.Thread(
            target=ctx.run, args=(self._run,), name=f"hivemap-link-{agent.agent_id}", daemon=True
        )
        self._thread.start()
        self.task: Future[Any] = asyncio.run_coroutine_threadsafe(self.link.run(), self.loop)

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()
        # the link's helper tasks (waits on its events) end with the loop
        pending = [t for t in asyncio.all_tasks(self.loop) if not t.done()]
        for t in pending:
            t.cancel()
        self.loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        self.loop.close()

    def _submit(self, msg: Any) -> None:
        # the outbox is written on the link's loop, like everything else the link does
        self.loop.call_soon_threadsafe(self.link.submit_nowait, msg)

    def on_event(self, ev: object) -> None:
        """Front-end events -> protocol messages (as ``hivemap.client.streaming`` sends them)."""
        from hivemap.client.frontend.tracker import KeyframeEvent, PoseUpdateEvent
        from hivemap.protocol import Keyframe, MapPoints, PoseUpdates

        core = self.agent.core
        session = self.first_session + int(getattr(ev, "session", 0))
        if session not in self._sessions:
            self._sessions.add(session)
            self.box.reserve_sessions(session)
        if isinstance(ev, KeyframeEvent):
            # at the agent's IMU-aided odometry, not its visual tracking (hivemap.client.odometry)
            world_from_cam, xyz, guess = self._streamed.keyframe(ev)
            if len(ev.new_point_ids):
                self._submit(MapPoints(ev.new_point_ids, xyz, ev.new_point_descriptors, session))
            fix = core.kf_fix.get((ev.session, ev.kf_id))
            g = core.gnss
            self._submit(
                Keyframe(
                    ev.kf_id, ev.timestamp, world_from_cam, ev.keypoints, ev.octaves, ev.descriptors,
                    ev.point_ids, None if fix is None else g.enu[fix], None if fix is None else g.cov[fix],
                    session, core.up_in_cam(ev.session, ev.kf_id), guess,
                    None if ev.prev_session_sigma is None else np.asarray(ev.prev_session_sigma, np.float64),
                    ev.u_right,
                    None if ev.odom_sigma is None else np.asarray(ev.odom_sigma, np.float64),
                    None if ev.track_sigma is None else np.asarray(ev.track_sigma, np.float64),
                    self.agent.intent_at(ev.timestamp),
                )
            )  # fmt: skip
            self._resend()
        elif isinstance(ev, PoseUpdateEvent):
            world_from_cam, xyz = self._streamed.update(ev)
            self._submit(PoseUpdates(ev.kf_ids, world_from_cam, ev.point_ids, xyz, session))

    def _resend(self, final: bool = False) -> None:
        """The keyframes the odometry's smoothing moved since they were sent, as pose updates
        (:meth:`StreamedPoses.refresh`); ``final``: at the end of the mission, by the finer threshold."""
        from hivemap.protocol import PoseUpdates
        from hivemap.protocol.limits import Limits

        o = self.agent.core.options
        threshold = o.stream_final_resend if final else o.stream_resend
        if threshold is None or not o.stream_imu_odometry:
            return
        none, no_xyz, n = np.zeros(0, np.int64), np.zeros((0, 3)), Limits().max_poses_per_msg
        for s, kf_ids, world_from_cam in self._streamed.refresh(*threshold):
            for i in range(0, len(kf_ids), n):
                self._submit(PoseUpdates(kf_ids[i : i + n], world_from_cam[i : i + n], none, no_xyz,
                                         self.first_session + s, points_follow=True))  # fmt: skip

    def send_rendezvous(self, r: Rendezvous) -> None:
        """A rendezvous of the front-end's session ``r.session``, into the outbox like every message."""
        self._submit(dataclasses.replace(r, session=self.first_session + int(r.session)))

    def failure(self) -> BaseException | None:
        """Why the link's task ended, if it ended by itself (None while it runs or after a clean close)."""
        if not self.task.done() or self.task.cancelled():
            return None
        return self.task.exception()

    def close(self, timeout: float, stop: threading.Event | None) -> int:
        from hivemap.client.health import adopt_final_estimate, wait_for_server

        def stopping() -> bool:
            return stop is not None and stop.is_set()

        if not stopping() and not self.task.done():
            self._resend(final=True)  # queued before the flush: the server acknowledges it too
            flush = asyncio.run_coroutine_threadsafe(asyncio.wait_for(self.link.flush(), timeout), self.loop)
            if not _wait(flush, stop, self.task):
                log.warning("server did not acknowledge everything within %.0f s", timeout)
        agent = self.agent
        linked, through = not stopping() and not self.task.done(), False
        if linked:
            through = wait_for_server(self.server, agent.options.runner, lambda: agent._last_correction,
                                      agent.apply_corrections, stop)  # fmt: skip

        async def end(finish_mission: bool) -> None:
            # all acknowledged: the next start on this outbox is a new mission (before close shuts it)
            if finish_mission and not self.task.done() and self.box.finish():
                log.info("agent %s: mission %s complete", self.agent.agent_id, self.box.mission)
            await self.link.close()

        asyncio.run_coroutine_threadsafe(end(not stopping()), self.loop).result()
        if linked and not stopping():
            if through:
                # the bye asked the server for the mission's last solve, on the odometry just resent: wait
                # for it too (no correction reaches a closed link)
                wait_for_server(self.server, agent.options.runner, lambda: 0.0, lambda: None, stop)
            if not stopping():
                adopt_final_estimate(self.server, agent)
        if (exc := self.failure()) is not None:  # refused or unreachable: what is left stays in the outbox
            log.debug("link ended: %s", exc)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10.0)
        return int(self.link.unsent)


def _wait(fut: Future[Any], stop: threading.Event | None, link: Future[Any]) -> bool:
    """Wait for ``fut`` until it is done (True if it succeeded), ``stop`` is set or the link ended (then
    ``fut`` is cancelled)."""
    while not fut.done():
        if (stop is not None and stop.is_set()) or link.done():
            fut.cancel()
            return False
        concurrent.futures.wait([fut], timeout=0.1)
    return not fut.cancelled() and fut.exception() is None
