"""The ingest core: agents, their maps in the map stack, pending keyframes, persistence and acks.

All map mutations happen on the event loop thread (the back-end must do the same: compute in a worker, then
apply on the loop). Store writes run in the single writer thread (:mod:`hivemap.server.writer`); a message is
acknowledged only after the SQLite commit that holds its data and the agent's last seq.

Hooks for the collaboration back-end:

* ``server.keyframe_observers``: async callables ``(map_id, kf_key) -> None`` awaited after a keyframe is
  inserted into a map (keep them quick: enqueue work, don't compute).
* ``await server.send_correction(agent_id, correction)``: deliver a ``Correction`` (queued while offline).
* ``server.set_agent_transform(folded_id, global_from_vio)``: the Sim(3) applied to the agent's incoming data
  after its map was merged (incoming poses are in the agent's VIO frame; stored poses are in the map's frame).
* ``await server.persist(fn)``: run ``fn(store)`` in the writer thread (``store.maps`` is the MapStore) and
  wait for its commit, e.g. to record a merge.
* ``await server.persist_exclusive(fn)``: the same with ingest paused, for writes that read whole maps.
* ``await server.apply_merge(target_id, source_id, target_from_source, fused_pairs)``: merge two maps of the
  stack, re-frame the moved agents, persist it all in one commit, publish a ``merge`` event.
* ``server.events.add(kind, message, ...)``: publish merges, loops, corrections on ``/events``.
* ``server.startup_hooks`` / ``server.shutdown_hooks``: async ``(server) -> None`` run after the reload /
  before the store closes (start and stop the back-end's workers there).
* ``server.mission_end_observers``: async ``(agent_id) -> None`` run when an agent says bye (its mission's
  data is all in: the back-end's mission-end global BA).
* ``server.loop``: the event loop; from a worker thread use ``asyncio.run_coroutine_threadsafe(.., loop)``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hivemap import __version__
from hivemap.maps import MapStack
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3
from hivemap.protocol import (
    Correction,
    Hello,
    Message,
    Welcome,
)
from hivemap.protocol import Error as ErrorMsg
from hivemap.server.agents import AgentMap as AgentMap
from hivemap.server.agents import AgentState as AgentState
from hivemap.server.agents import Connection as Connection
from hivemap.server.agents import MissionState as MissionState
from hivemap.server.agents import PendingKeyframe as PendingKeyframe
from hivemap.server.agents import Rejected as Rejected
from hivemap.server.counters import Counters
from hivemap.server.events import EventLog
from hivemap.server.ingest import Ingest, _with_last_seq
from hivemap.server.mapedits import MapEdits
from hivemap.server.metrics import Histogram
from hivemap.server.persist import ServerStore
from hivemap.server.quotas import Quotas
from hivemap.server.rendezvous import RendezvousObs
from hivemap.server.settings import ServerSettings
from hivemap.server.writer import StoreWriter

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
KeyframeObserver = Callable[[int, KfKey], Awaitable[None]]


class HiveServer(Ingest, MapEdits, Counters):
    """The server state shared by the WebSocket handlers, the REST routes and the back-end."""

    def __init__(self, settings: ServerSettings) -> None:
        self.settings = settings
        self.events = EventLog(settings.event_buffer)
        self.stack = MapStack()
        self.agents: dict[str, AgentState] = {}
        self.keyframe_observers: list[KeyframeObserver] = []
        self.rendezvous: dict[int, RendezvousObs] = {}  # every rendezvous observation by id
        self.fresh_rendezvous: list[int] = []  # applied, not yet handed to the observers
        #: async callables ``(rendezvous id) -> None`` awaited after a rendezvous observation is applied
        self.rendezvous_observers: list[Callable[[int], Awaitable[None]]] = []
        self.ack_latency = Histogram((0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 5.0))
        self.started_at = time.time()
        self.rejected_frames = 0
        self._writer: StoreWriter[ServerStore] | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._ingest_open = asyncio.Event()
        self._ingest_open.set()
        #: async callables ``(server) -> None`` run after the stack is loaded / before the store closes
        self.startup_hooks: list[Callable[[HiveServer], Awaitable[None]]] = []
        self.shutdown_hooks: list[Callable[[HiveServer], Awaitable[None]]] = []
        self.mission_end_observers: list[Callable[[str], Awaitable[None]]] = []
        self._uncommitted: asyncio.Semaphore | None = None
        self.quotas = Quotas(settings.quotas)
        # the highest seq that passed the step check, per agent (rejected messages included, so an agent
        # whose messages are refused for another reason is not then refused for its seq step)
        self._seen_seq: dict[tuple[str, str], int] = {}
        #: True from ``open_store`` until the stored maps are loaded (``/health`` says ``loading``)
        self.loading = False
        self.loaded = asyncio.Event()
        self._counters_task: asyncio.Task[None] | None = None
        self._counters_written: dict[str, Any] = {}

    # -- lifecycle ----------------------------------------------------------------------------------
    @property
    def db_path(self) -> Path:
        return Path(self.settings.data_dir) / "hivemap.sqlite"

    @property
    def writer(self) -> StoreWriter[ServerStore]:
        if self._writer is None:
            raise RuntimeError("server not started")
        return self._writer

    async def start(self) -> None:
        """Open the store and load it (``open_store`` then ``load``)."""
        await self.open_store()
        await self.load()

    async def open_store(self) -> None:
        """Start the writer thread on the store; the maps are not loaded yet (see ``load``)."""
        self.loading = True
        Path(self.settings.data_dir).mkdir(parents=True, exist_ok=True)
        loop = asyncio.get_running_loop()
        self.loop = loop  # for other threads: asyncio.run_coroutine_threadsafe(coro, server.loop)
        self._uncommitted = asyncio.Semaphore(self.settings.max_uncommitted)
        path, sync = self.db_path, self.settings.sqlite_synchronous
        self._writer = StoreWriter(
            lambda: ServerStore(path, synchronous=sync), loop, self.settings.commit_interval_ms / 1000.0
        )
        await self._writer.start()

    async def load(self) -> None:
        """Load the stored maps and agents, then run the startup hooks. The HTTP server may already serve
        meanwhile: ``/health`` says ``loading`` and hellos are told to come back (see ``ws``)."""
        t0 = time.perf_counter()
        path = self.db_path
        logger.info("loading the store %s", path)
        loaded = await self.writer.call(lambda store: store.load_all())
        self._restore(loaded)
        self._restore_counters(await self.writer.call(lambda store: store.load_counters()))
        n_kfs = sum(len(m.keyframes) for m in self.stack.maps.values())
        n_pts = sum(len(m.points) for m in self.stack.maps.values())
        logger.info(
            "store loaded in %.1f s: %d maps, %d keyframes, %d map points, %d agents",
            time.perf_counter() - t0, len(self.stack.maps), n_kfs, n_pts, len(self.agents),
        )  # fmt: skip
        # Long-lived objects (modules, FastAPI/pydantic internals, the reloaded maps) leave the collector's
        # view: a full collection over them otherwise stalls the loop for tens of ms (measured: 60 ms).
        gc.collect()
        gc.freeze()
        self.events.add(
            "info",
            f"server started: {len(self.stack.maps)} maps, {len(self.agents)} agents reloaded from {path}",
        )
        for hook in self.startup_hooks:
            await hook(self)
        self._counters_task = asyncio.create_task(self._write_counters_periodically())
        self.loading = False
        self.loaded.set()

    async def stop(self) -> None:
        if self._counters_task is not None:
            self._counters_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._counters_task
        for hook in self.shutdown_hooks:
            try:
                await hook(self)
            except Exception:
                logger.exception("shutdown hook failed")
        for agent in list(self.agents.values()):
            if agent.connection is not None:
                await agent.connection.close(1001, "server shutting down")
        if self._writer is not None:
            if self.loaded.is_set():  # (a store that never finished loading has no counters to keep)
                self._submit_counters()
            await self._writer.stop()
            self._writer = None
            logger.info("store closed: %s", self.db_path)

    def _restore(self, loaded: Any) -> None:
        self.stack = loaded.stack
        for rec in loaded.agents:
            agent = AgentState(
                agent_id=rec["agent_id"], kind=rec["kind"], camera=rec["camera"], session=rec["session"]
            )
            agent.mission = rec.get("mission", "")
            self.agents[agent.agent_id] = agent
        for agent_id, mission, last_seq in loaded.missions:
            owner = self.agents.get(agent_id)
            if owner is not None:
                owner.missions[mission] = MissionState(mission, last_seq=last_seq, applied_seq=last_seq)
        for folded, rec in loaded.agent_maps.items():
            owner = self.agents.get(rec["agent_id"])
            if owner is None:
                continue
            am = self._new_agent_map(owner, rec["session"], rec["mission"], rec["client_session"])
            am.global_from_vio = Sim3.from_matrix(np.asarray(rec["global_from_vio"], dtype=np.float64))
            m = self.stack.map_of_agent(folded)
            if m is not None:
                for kf in m.keyframes.values():
                    if kf.agent_id != folded:
                        continue
                    am.arrived_kfs.add(kf.id)
                    am.arrived_points.update(k[1] for _, k in kf.referenced_points() if k[0] == folded)
                am.arrived_points.update(p.id for p in m.points.values() if p.agent_id == folded)
                # points fused into another agent's point arrived too
                am.arrived_points.update(k[1] for k in m.point_redirects if k[0] == folded)
        for folded, kf_id, msg in loaded.pending:
            pam = self._agent_map_by_folded(folded)
            if pam is None:
                continue
            missing = self._missing_points(pam, msg)
            pam.pending[kf_id] = PendingKeyframe(msg, missing)
            for pid in missing:
                pam.waiting.setdefault(pid, set()).add(kf_id)
        self.rendezvous = {rid: RendezvousObs.from_record(rec) for rid, rec in loaded.rendezvous.items()}
        logger.info("restored %d agents, %d maps", len(self.agents), len(self.stack.maps))

    # -- agents -------------------------------------------------------------------------------------
    def authenticate(self, hello: Hello) -> str | None:
        """None if the hello's token is the one configured for its agent id, else the reason for refusal."""
        import hmac

        expected = self.settings.tokens.get(hello.agent_id)
        if expected is None:
            return f"unknown agent '{hello.agent_id}': no token configured for it"
        if not hello.token:
            return f"missing token for agent '{hello.agent_id}'"
        if not hmac.compare_digest(expected.encode(), hello.token.encode()):
            return f"wrong token for agent '{hello.agent_id}'"
        return None

    async def attach(self, conn: Connection, hello: Hello) -> Welcome:
        """Register ``conn`` as the agent's connection (replacing an older one); send the welcome, then the
        corrections the agent missed while offline."""
        try:
            camera = PinholeCamera.from_dict(hello.camera)
        except (KeyError, TypeError, ValueError) as exc:
            raise Rejected("bad_field", f"invalid camera: {exc}", "body.camera") from exc
        if hello.kind not in ("uav", "ugv"):
            raise Rejected("bad_field", f"kind must be 'uav' or 'ugv', got {hello.kind!r}", "body.kind")
        agent = self.agents.get(hello.agent_id)
        if agent is None:
            agent = AgentState(agent_id=hello.agent_id)
            self.agents[agent.agent_id] = agent
        old = agent.connection
        if old is not None and old is not conn:
            old.replaced = True
            agent.connection = None
            self.events.add(
                "disconnect", f"{agent.agent_id}: replaced by a new connection", agent_id=agent.agent_id
            )
            await old.close(1000, "replaced by a new connection of the same agent")
        ms = agent.missions.get(hello.mission)
        known = ms is not None
        if ms is None:
            ms = MissionState(hello.mission)
            agent.missions[hello.mission] = ms
            if agent.maps:
                self.events.add(
                    "mission",
                    f"{agent.agent_id}: new mission {hello.mission} (earlier missions' maps kept apart)",
                    agent_id=agent.agent_id,
                    data={"mission": hello.mission, "resume_from": hello.resume_from},
                )
        elif agent.session_of(hello.mission, hello.session) is None:
            self.events.add(
                "session",
                f"{agent.agent_id} started session {hello.session} of mission {hello.mission} (map reset)",
                agent_id=agent.agent_id,
            )
        if not known and hello.resume_from > 0:
            logger.warning(
                "%s resumes mission %s from seq %d, which this server has no record of: it re-sends it all",
                agent.agent_id,
                hello.mission,
                hello.resume_from,
            )
        agent.kind = hello.kind
        agent.camera = camera.to_dict()
        agent.mission = hello.mission
        if hello.cam_from_antenna is not None:
            agent.cam_from_antenna = np.array(hello.cam_from_antenna, dtype=np.float64)
        agent.stereo_baseline = hello.stereo_baseline
        agent.team_advisories = hello.team_advisories
        if hello.team_advisories:  # the team service pushes goals and advisories while such agents are on
            from hivemap.server.team.service import team_service

            team_service(self).start_push()
        am_now = self._session_map(agent, hello.mission, hello.session, create=True, persist=False)
        self.map_for(am_now)  # the agent's map exists (maybe empty) from its hello on
        am_now.camera = camera
        rec, rows, mission = agent.record(), [am.row() for am in agent.maps.values()], hello.mission

        def op(store: ServerStore) -> None:
            store.put_agent(rec)
            store.put_mission(agent.agent_id, mission)
            for row in rows:
                store.put_agent_map(row)

        await self.writer.call(op)  # also flushes everything the old connection had applied
        agent.connection = conn
        conn.mission = hello.mission
        agent.connected_since = agent.last_seen = time.time()
        self.events.add(
            "connect",
            f"{agent.agent_id} connected (mission {hello.mission}, last seq {ms.last_seq})",
            agent_id=agent.agent_id,
        )
        welcome = Welcome(last_seq=ms.last_seq, server_version=__version__, mission_known=known)
        conn.send(welcome)
        for corr in list(ms.undelivered):
            conn.send(corr)
        ms.undelivered.clear()
        return welcome

    def detach(self, conn: Connection) -> None:
        if conn.agent_id is None:
            return
        agent = self.agents.get(conn.agent_id)
        if agent is not None and agent.connection is conn:
            agent.connection = None
            agent.last_seen = time.time()
            self.events.add("disconnect", f"{agent.agent_id} disconnected", agent_id=agent.agent_id)
            self._submit_counters()

    # -- ingest -------------------------------------------------------------------------------------
    async def handle(self, conn: Connection, seq: int, msg: Message, received_at: float) -> None:
        """Apply one data message from an authenticated connection; ack it after its commit."""
        assert conn.agent_id is not None and conn.mission is not None and self._uncommitted is not None
        agent = self.agents[conn.agent_id]
        ms = agent.missions[conn.mission]
        await self._uncommitted.acquire()  # back-pressure: the reader stops reading while commits lag
        released = False

        def release() -> None:
            nonlocal released
            if not released:
                released = True
                assert self._uncommitted is not None
                self._uncommitted.release()

        try:
            if not self._ingest_open.is_set():  # the back-end is writing a whole map (merge, global BA)
                await self._ingest_open.wait()
            # From here to the submit there is no await: the message is applied atomically on the loop.
            if conn.replaced:
                release()
                return
            agent.last_seen = time.time()
            agent.received[type(msg).__name__] += 1
            if seq <= 0:
                raise Rejected("bad_field", f"seq must be >= 1 for data messages, got {seq}", "seq")
            self._check_seq_step(agent, ms, seq)
            store_op: Callable[[ServerStore], None] | None = None
            inserted: list[tuple[int, KfKey]] = []
            if seq <= ms.applied_seq:
                agent.duplicates += 1  # already applied (maybe not yet committed): ack after the next commit
            else:
                data_op, inserted = self._apply(agent, ms.mission, msg)
                ms.applied_seq = seq
                store_op = _with_last_seq(data_op, agent.agent_id, ms.mission, seq)
        except Rejected:
            release()
            raise
        except Exception as exc:
            # A bug met by one message must not take the connection down: the agent would resend the same
            # message forever and the back-pressure slot would never come back, so every later message of
            # every agent would wait. The message is refused for good (not a transient code, so the agent
            # drops it rather than resend it) and the rest go on.
            release()
            logger.exception("%s seq %d: applying %s failed", agent.agent_id, seq, type(msg).__name__)
            raise Rejected(
                "apply_failed", f"the server could not apply this {type(msg).__name__}: {exc!r}"
            ) from exc

        def done(exc: BaseException | None) -> None:
            release()
            if exc is not None:
                conn.send(ErrorMsg(code="storage", message=f"could not store message: {exc}", seq=seq))
                return
            ms.last_seq = max(ms.last_seq, seq)
            self.ack_latency.observe(time.monotonic() - received_at)
            if not conn.replaced:
                from hivemap.protocol import Ack

                conn.send(Ack(seq=seq))

        self.writer.submit(store_op, done)
        for map_id, key in inserted:
            for observer in list(self.keyframe_observers):
                try:
                    await observer(map_id, key)
                except Exception:
                    logger.exception("keyframe observer failed")
        fresh, self.fresh_rendezvous = self.fresh_rendezvous, []
        for rid in fresh:
            for rv_observer in list(self.rendezvous_observers):
                try:
                    await rv_observer(rid)
                except Exception:
                    logger.exception("rendezvous observer failed")

    def _check_seq_step(self, agent: AgentState, ms: MissionState, seq: int) -> None:
        """A seq may grow by at most ``max_seq_step``: one frame with seq 2**62 would otherwise make the
        agent's stored last seq unreachable and lock its id out of ever being stored again."""
        key = (agent.agent_id, ms.mission)
        ref = max(ms.applied_seq, self._seen_seq.get(key, 0))
        step = self.settings.max_seq_step
        if seq > ref + step:
            raise Rejected(
                "bad_field", f"seq {seq} jumps more than max_seq_step = {step} past seq {ref}", "seq"
            )
        if seq > ref:
            self._seen_seq[key] = seq

    def _check_quota(self, agent: AgentState, kind: str, n: int, field: str) -> None:
        """Refuse a message that would take the agent over one of its ``[quotas]`` (nothing applied)."""
        if kind == "points":
            stored = sum(len(am.arrived_points) for am in agent.maps.values())
        else:
            stored = sum(len(am.arrived_kfs) + len(am.pending) for am in agent.maps.values())
        over = self.quotas.check(agent.agent_id, kind, n, stored)
        if over is None:
            return
        if self.quotas.should_report(agent.agent_id, over.limit):
            logger.warning("quota: %s", over.message)
            self.events.add("quota", over.message, agent_id=agent.agent_id, data={"limit": over.limit})
        raise Rejected(over.code, over.message, field)

    # -- hooks for the back-end ---------------------------------------------------------------------
    async def agent_said_bye(self, agent_id: str) -> None:
        for observer in self.mission_end_observers:
            await observer(agent_id)

    async def send_correction(self, agent_id: str, correction: Correction) -> bool:
        """Send a correction to an agent now, or when it next connects. ``correction.session`` is the
        server session of the agent map it corrects; it reaches only that map's mission, under the
        session number the agent gave it. True if sent now."""
        agent = self.agents.get(agent_id)
        if agent is None:
            raise KeyError(agent_id)
        am = agent.maps.get(correction.session)
        if am is None:
            raise KeyError(f"{agent_id} session {correction.session}")
        self.events.add(
            "correction",
            f"correction for {am.folded}: {len(correction.kf_ids)} keyframes of map {correction.map_id}",
            agent_id=agent_id,
            map_id=correction.map_id,
        )
        out = replace(correction, session=am.client_session)
        conn = agent.connection
        if conn is not None and conn.mission == am.mission and conn.send(out):
            return True
        ms = agent.missions.get(am.mission)
        if ms is not None:
            ms.undelivered.append(out)
        return False

    def set_agent_transform(self, folded: str, global_from_vio: Sim3) -> None:
        """Set the Sim(3) from an agent map's VIO frame to the frame of the stack map that now holds it."""
        am = self._agent_map_by_folded(folded)
        if am is None:
            raise KeyError(folded)
        am.global_from_vio = global_from_vio
        row = am.row()
        self.writer.submit(lambda store: store.put_agent_map(row))

    async def persist(self, fn: Callable[[ServerStore], Any]) -> Any:
        """Run ``fn(store)`` in the writer thread; returns its result after the commit. ``fn`` must not read
        maps the loop may be changing (pass copies), else use :meth:`persist_exclusive`."""
        return await self.writer.call(fn)

    async def persist_exclusive(self, fn: Callable[[ServerStore], Any]) -> Any:
        """Like :meth:`persist`, with ingest paused until the commit. Agents' messages wait meanwhile
        (nothing is lost); back-end tasks do not, so a whole map goes in as ``map_rows(m)`` taken
        before the call."""
        self._ingest_open.clear()
        try:
            return await self.writer.call(fn)
        finally:
            self._ingest_open.set()

    # -- inspection helpers -------------------------------------------------------------------------
    def agent_maps(self, agent_id: str) -> Iterable[AgentMap]:
        agent = self.agents.get(agent_id)
        return agent.maps.values() if agent is not None else ()

    def pending_count(self, agent: AgentState) -> int:
        return sum(len(am.pending) for am in agent.maps.values())
