"""Applying the agents' data messages to the map stack: keyframes (held until their points arrived, paper
2.3.2), map points, pose updates; each returns the store write that goes into the message's commit.

A mixin of :class:`~hivemap.server.core.HiveServer`, which owns the state these methods use."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from itertools import compress, repeat
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps import MapStack
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.elements import first_observers, positions, set_positions
from hivemap.protocol import Keyframe, MapPoints, Message, PoseUpdates, Rendezvous
from hivemap.server.agents import AgentMap, AgentState, PendingKeyframe, Rejected
from hivemap.server.convert import fold_agent_id, keyframe_from_msg, points_from_msg
from hivemap.server.persist import GraphSnapshot, ServerStore
from hivemap.server.rendezvous import MAX_HELD, RendezvousObs

F64 = NDArray[np.float64]

if TYPE_CHECKING:
    from hivemap.server.settings import ServerSettings
    from hivemap.server.writer import StoreWriter

KfKey = tuple[str, int]
# sessions of one agent id over all its missions (each is one agent map); bounds what one id can hold
MAX_SESSIONS_PER_AGENT = 256
# front-end sessions within one mission
MAX_SESSIONS_PER_MISSION = 64


def _with_last_seq(
    data_op: Callable[[ServerStore], None] | None, agent_id: str, mission: str, seq: int
) -> Callable[[ServerStore], None]:
    """The message's data writes, then the mission's last seq: both land in the same commit."""

    def op(store: ServerStore) -> None:
        if data_op is not None:
            data_op(store)
        store.set_last_seq(agent_id, mission, seq)

    return op


class Ingest:
    """The message application of :class:`~hivemap.server.core.HiveServer` (all on the event loop)."""

    stack: MapStack
    settings: ServerSettings
    agents: dict[str, AgentState]
    rendezvous: dict[int, RendezvousObs]
    fresh_rendezvous: list[int]

    if TYPE_CHECKING:

        @property
        def writer(self) -> StoreWriter[ServerStore]: ...

        def _check_quota(self, agent: AgentState, kind: str, n: int, field: str) -> None: ...

    def _apply(
        self, agent: AgentState, mission: str, msg: Message
    ) -> tuple[Callable[[ServerStore], None] | None, list[tuple[int, KfKey]]]:
        if isinstance(msg, Keyframe):
            return self._apply_keyframe(agent, mission, msg)
        if isinstance(msg, MapPoints):
            return self._apply_points(agent, mission, msg)
        if isinstance(msg, PoseUpdates):
            return self._apply_pose_updates(agent, mission, msg), []
        if isinstance(msg, Rendezvous):
            return self._apply_rendezvous(agent, mission, msg), []
        raise Rejected("unexpected", f"'{type(msg).__name__}' is not a message an agent sends", "type")

    def _session_map(
        self, agent: AgentState, mission: str, session: int, create: bool, persist: bool = True
    ) -> AgentMap:
        """The agent map of the mission's front-end session ``session``; a new one gets the agent's next
        server session (so a second mission never lands in the first one's maps)."""
        am = agent.session_of(mission, session)
        if am is not None:
            return am
        if not create:
            raise Rejected(
                "unknown_id",
                f"unknown session {session} of mission {mission} for agent '{agent.agent_id}'",
                "body.session",
            )
        in_mission = [a.client_session for a in agent.maps.values() if a.mission == mission]
        if (
            session < 0
            or len(agent.maps) >= MAX_SESSIONS_PER_AGENT
            or len(in_mission) >= MAX_SESSIONS_PER_MISSION
            or session < max(in_mission, default=0)
        ):
            raise Rejected(
                "bad_field", f"session {session} not allowed for agent '{agent.agent_id}'", "body.session"
            )
        # an agent id's first mission keeps its own session numbers; a later one's go above all used
        first_mission = all(a.mission == mission for a in agent.maps.values())
        server_session = session if first_mission else max(agent.maps, default=-1) + 1
        am = self._new_agent_map(agent, server_session, mission, session)
        agent.session = max(agent.session, server_session)
        if not persist:
            return am
        rec, row = agent.record(), am.row()
        self.writer.submit(lambda store: (store.put_agent(rec), store.put_agent_map(row)))
        return am

    def _new_agent_map(self, agent: AgentState, session: int, mission: str, client_session: int) -> AgentMap:
        camera = PinholeCamera.from_dict(agent.camera)
        am = AgentMap(
            agent.agent_id, session, fold_agent_id(agent.agent_id, session), camera, mission, client_session
        )
        agent.maps[session] = am
        return am

    def _agent_map_by_folded(self, folded: str) -> AgentMap | None:
        for agent in self.agents.values():
            for am in agent.maps.values():
                if am.folded == folded:
                    return am
        return None

    def map_for(self, am: AgentMap) -> Any:
        """The stack map holding this agent map's data (created on first use)."""
        m = self.stack.map_of_agent(am.folded)
        if m is None:
            m = self.stack.new_map()
            m.agents.add(am.folded)
        return m

    @staticmethod
    def _missing_points(am: AgentMap, msg: Keyframe) -> set[int]:
        ids = np.unique(msg.point_ids[msg.point_ids >= 0])
        return {int(i) for i in ids.tolist() if int(i) not in am.arrived_points}

    def _apply_keyframe(
        self, agent: AgentState, mission: str, msg: Keyframe
    ) -> tuple[Callable[[ServerStore], None] | None, list[tuple[int, KfKey]]]:
        am = self._session_map(agent, mission, msg.session, create=True)
        if msg.kf_id in am.arrived_kfs or msg.kf_id in am.pending:
            agent.duplicates += 1
            return None, []
        self._check_quota(agent, "keyframes", 1, "body.kf_id")
        missing = self._missing_points(am, msg)
        if missing:
            if len(am.pending) >= self.settings.max_pending_keyframes:
                raise Rejected(
                    "overloaded",
                    f"{len(am.pending)} keyframes already wait for their map points; send the points first",
                    "body.point_ids",
                )
            am.pending[msg.kf_id] = PendingKeyframe(msg, missing)
            for pid in missing:
                am.waiting.setdefault(pid, set()).add(msg.kf_id)
            folded = am.folded
            return (lambda store: store.put_pending(folded, msg)), []
        m = self.map_for(am)
        kf = self._insert_keyframe(am, m, msg)
        map_id, graph = m.id, GraphSnapshot(m)

        def op(store: ServerStore) -> None:
            store.maps.put_keyframe(map_id, kf)
            store.sync_graph(graph)

        return op, [(map_id, kf.key)]

    def _insert_keyframe(self, am: AgentMap, m: Any, msg: Keyframe) -> Any:
        owner = self.agents.get(am.agent_id)
        baseline = None if owner is None else owner.stereo_baseline
        kf = keyframe_from_msg(am.folded, msg, am.camera, am.global_from_vio, baseline)
        m.add_keyframe(kf)
        am.arrived_kfs.add(msg.kf_id)
        if msg.intent_velocity is not None:
            am.intent = (int(msg.kf_id), np.array(msg.intent_velocity, dtype=np.float64))
        if msg.prev_session_from_world is not None and msg.prev_session_sigma is not None:
            guess = np.array(msg.prev_session_from_world, dtype=np.float64)
            am.session_guess = (int(msg.kf_id), guess, np.array(msg.prev_session_sigma, dtype=np.float64))
        return kf

    def _apply_points(
        self, agent: AgentState, mission: str, msg: MapPoints
    ) -> tuple[Callable[[ServerStore], None] | None, list[tuple[int, KfKey]]]:
        am = self._session_map(agent, mission, msg.session, create=True)
        ids = msg.ids.tolist()
        seen: set[int] = set()
        keep: list[int] = []
        for i, pid in enumerate(ids):
            if pid < 0:
                raise Rejected("bad_field", f"map point ids must be >= 0, got {pid}", "body.ids")
            if pid in am.arrived_points or pid in seen:
                continue
            seen.add(pid)
            keep.append(i)
        if not keep:
            agent.duplicates += 1
            return None, []
        self._check_quota(agent, "points", len(keep), "body.ids")
        m = self.map_for(am)
        points = points_from_msg(am.folded, msg, np.asarray(keep, dtype=np.int64), am.global_from_vio)
        for mp in points:
            m.add_point(mp)
        am.arrived_points.update(seen)
        # Keyframes that waited for these points (paper 2.3.2).
        ready: list[int] = []
        for pid in seen:
            for kf_id in am.waiting.pop(pid, ()):
                pk = am.pending.get(kf_id)
                if pk is None:
                    continue
                pk.missing.discard(pid)
                if not pk.missing:
                    ready.append(kf_id)
        released = []
        for kf_id in sorted(ready):
            pk = am.pending.pop(kf_id)
            released.append(self._insert_keyframe(am, m, pk.msg))
        map_id, folded = m.id, am.folded
        graph = GraphSnapshot(m) if released else None

        def op(store: ServerStore) -> None:
            store.maps.put_points(map_id, points)
            for kf in released:
                store.maps.put_keyframe(map_id, kf)
                store.delete_pending(folded, kf.id)
            if graph is not None:
                store.sync_graph(graph)

        return op, [(map_id, kf.key) for kf in released]

    def _apply_pose_updates(
        self, agent: AgentState, mission: str, msg: PoseUpdates
    ) -> Callable[[ServerStore], None] | None:
        am = self._session_map(agent, mission, msg.session, create=False)
        kf_ids = msg.kf_ids.tolist()
        point_ids = msg.point_ids.tolist()
        for i, k in enumerate(kf_ids):
            if k not in am.arrived_kfs and k not in am.pending:
                raise Rejected(
                    "unknown_id", f"keyframe {k} of '{am.folded}' never arrived", f"body.kf_ids[{i}]"
                )
        for i, p in enumerate(point_ids):
            if p not in am.arrived_points:
                raise Rejected(
                    "unknown_id", f"map point {p} of '{am.folded}' never arrived", f"body.point_ids[{i}]"
                )
        m = self.stack.map_of_agent(am.folded)
        g = am.global_from_vio
        changed_kfs = []
        changed_pending = []
        moves: list[tuple[Any, F64]] = []  # points_follow: (keyframe, world_new @ inv(world_old))
        for i, k in enumerate(kf_ids):
            T = np.array(msg.world_from_cam[i], dtype=np.float64)
            pk = am.pending.get(k)
            if pk is not None:
                pk.msg = replace(pk.msg, world_from_cam=T)
                changed_pending.append(pk.msg)
                continue
            kf = m.keyframes.get((am.folded, k)) if m is not None else None
            if kf is not None:  # None: removed by the back-end (culled); the update is moot
                old = kf.vio_from_cam
                if old is None:  # a keyframe of a store from before it was kept: the agent's transform alone
                    kf.world_from_cam = g.transform_pose(T)
                else:
                    # the agent's refinement, in the keyframe's frame (scaled like the agent's map), on
                    # top of the keyframe's current pose: g @ T would drop what the back-end did to this
                    # keyframe alone (its share of a loop closure or of the GNSS stage's bend)
                    delta = np.linalg.inv(old) @ T
                    delta[:3, 3] *= g.s
                    before = kf.world_from_cam
                    kf.world_from_cam = before @ delta
                    if msg.points_follow:
                        moves.append((kf, kf.world_from_cam @ np.linalg.inv(before)))
                kf.vio_from_cam = T
                changed_kfs.append(kf)
        changed_points = []
        if moves and m is not None:
            changed_points += _points_follow(m, moves, set(point_ids), am.folded)
        if point_ids and m is not None:
            changed_points += _place_listed(m, am, point_ids, np.asarray(msg.xyz, dtype=np.float64))
        map_id, folded = (m.id if m is not None else -1), am.folded

        def op(store: ServerStore) -> None:
            if changed_kfs or changed_points:
                store.maps.update_poses(map_id, changed_kfs, changed_points, vio=True)
            for pmsg in changed_pending:
                store.put_pending(folded, pmsg)

        return op

    def _apply_rendezvous(
        self, agent: AgentState, mission: str, msg: Rendezvous
    ) -> Callable[[ServerStore], None] | None:
        """Keep the observation (held: its reference keyframe or the observed agent may not have arrived
        yet, an unknown observed agent may still appear); the back-end resolves it
        (``fresh_rendezvous``)."""
        am = self._session_map(agent, mission, msg.session, create=False)
        if msg.observed_agent == agent.agent_id:
            raise Rejected("bad_field", "an agent cannot observe its own carrier", "body.observed_agent")
        held = sum(1 for r in self.rendezvous.values() if r.state == "held")
        if held >= MAX_HELD:
            why = f"{held} rendezvous observations already held"
            raise Rejected("overloaded", why, "body.observed_agent")
        rid = max(self.rendezvous, default=0) + 1
        obs = RendezvousObs.from_msg(rid, am.folded, msg)
        if msg.ref_kf_id not in am.arrived_kfs:
            obs.reason = f"reference keyframe {msg.ref_kf_id} of {am.folded} not arrived yet"
        elif msg.observed_agent not in self.agents:
            obs.reason = f"observed agent '{msg.observed_agent}' not known yet"
        self.rendezvous[rid] = obs
        self.fresh_rendezvous.append(rid)
        rec = obs.record()
        return lambda store: store.maps.put_rendezvous(rid, rec)


def _place_listed(m: Any, am: Any, point_ids: Any, sent: F64) -> list[Any]:
    """The points a pose update lists, at the agent's new positions ``sent`` (its VIO frame). A point
    follows its first observer, as the back-end's corrections move it: placed where the agent sees it from
    that keyframe, it keeps the keyframe's share of a loop closure, which the agent's transform alone
    would drop; a point whose first observer the server has no VIO pose of goes through the transform."""
    g = am.global_from_vio
    found = [
        (i, mp) for i, mp in enumerate(map(m.points.get, zip(repeat(am.folded), point_ids))) if mp is not None
    ]
    if not found:
        return []
    rows = np.fromiter((i for i, _ in found), dtype=np.int64, count=len(found))
    pts = [mp for _, mp in found]
    # the first observer's index among the observers with a VIO pose (-1: through the transform)
    observers: dict[KfKey | None, int] = {}
    poses: list[tuple[F64, F64]] = []

    def observer(obs: KfKey | None) -> int:
        at = observers.get(obs)
        if at is None:
            kf = m.keyframes.get(obs) if obs is not None and obs[0] == am.folded else None
            at = -1
            if kf is not None and kf.vio_from_cam is not None:
                at = len(poses)
                poses.append((kf.vio_from_cam, kf.world_from_cam))
            observers[obs] = at
        return at

    at = np.fromiter(map(observer, first_observers(pts)), dtype=np.int64, count=len(pts))
    X = sent[rows]
    xyz = np.empty((len(pts), 3))
    plain = at < 0
    if plain.any():
        xyz[plain] = g.apply(X[plain])
    if not plain.all():
        own = ~plain
        V = np.array([v for v, _ in poses], dtype=np.float64)[at[own]]
        W = np.array([w for _, w in poses], dtype=np.float64)[at[own]]
        # V^-1 applied, scaled like the map, then W
        in_cam = np.einsum("nji,nj->ni", V[:, :3, :3], X[own] - V[:, :3, 3]) * g.s
        xyz[own] = np.einsum("nij,nj->ni", W[:, :3, :3], in_cam) + W[:, :3, 3]
    set_positions(pts, xyz)
    return pts


def _points_follow(m: Any, moves: list[tuple[Any, F64]], listed: set[int], folded: str) -> list[Any]:
    """``PoseUpdates.points_follow``: each moved keyframe's points that it observed first (as the back-end's
    corrections move them) and the update does not list, moved rigidly with it (batched over the moves)."""
    # a keyframe listed twice moves its points by both steps, the later on top
    merged: dict[Any, tuple[Any, F64]] = {}
    for kf, d in moves:
        prev = merged.get(kf.key)
        merged[kf.key] = (kf, d if prev is None else d @ prev[1])
    moves = list(merged.values())
    keys: list[tuple[str, int]] = []
    owner: list[int] = []
    for j, (kf, _) in enumerate(moves):
        at = np.flatnonzero(kf.point_ids >= 0)
        ids = kf.point_ids[at].tolist()
        if kf.point_agents:  # keypoints that reference another agent's point
            agents = [kf.point_agents.get(i, kf.agent_id) for i in at.tolist()]
            keys += zip(agents, ids, strict=True)
        else:
            keys += zip(repeat(kf.agent_id), ids)
        owner += repeat(j, len(ids))
    mps = list(map(m.points.get, keys))
    anchor = [kf.key for kf, _ in moves]
    # the first observers of the points found, consumed in step with ``mps`` (None: no point)
    first_of = iter(first_observers([mp for mp in mps if mp is not None]))
    follow = [
        mp is not None and next(first_of) == anchor[j] and not (k[0] == folded and k[1] in listed)
        for mp, j, k in zip(mps, owner, keys, strict=True)
    ]
    pts = list(compress(mps, follow))
    if not pts:
        return []
    at_move = np.fromiter(compress(owner, follow), dtype=np.int64, count=len(pts))
    D = np.array([d for _, d in moves], dtype=np.float64)[at_move]
    X = positions(pts)
    set_positions(pts, np.einsum("nij,nj->ni", D[:, :3, :3], X) + D[:, :3, 3])
    return pts
