"""The team services on a running server: frontiers per map and the team's assignments (auction goals and
ORCA advisories), for ``GET /maps/{id}/frontiers`` and ``GET /team/assignments``.

What they need is copied from the maps on the event loop (the only thread that changes them); the work runs
in a thread, at most once per ``min_interval_s`` per map (frontiers) or for the team (assignments): a
request within that interval gets the last result, and concurrent requests share one computation.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.elements import positions
from hivemap.protocol import TeamAdvisory
from hivemap.server import schemas
from hivemap.server.backend.options import UncertaintyOptions
from hivemap.server.backend.uncertainty import velocity_reference
from hivemap.server.team.auction import d_optimal_gain, ssi_auction
from hivemap.server.team.commit import Commitments
from hivemap.server.team.frontiers import FrontierResult, even_subsample, extract
from hivemap.server.team.options import TeamOptions
from hivemap.server.team.orca import AgentMotion, advisories, preferred_velocity
from hivemap.server.team.sight import SightLines

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
# agent id -> (position covariance (3, 3) or None, velocity covariance (3, 3) or None) in its map's frame;
# None: unknown (the options' default sigmas are used). The server's are :func:`graph_covariances`.
Covariances = Callable[[str], tuple[F64 | None, F64 | None] | None]
# (agent id a, agent id b) -> the (3, 3) covariance of a's position minus b's in their map's frame, None:
# unknown. The server's are :func:`graph_relative_covariances`.
RelativeCovariances = Callable[[str, str], F64 | None]


class TeamOff(RuntimeError):
    """The team services are switched off (``[team] enabled = false``)."""


@dataclass
class _Cached:
    at: float = -1e18  # monotonic time of the last computation
    wall: float = 0.0
    value: Any = None
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


@dataclass(frozen=True)
class _AgentSnap:
    agent_id: str
    kind: str
    map_id: int
    position: F64
    velocity: F64
    timestamp: float | None = None  # of the keyframe ``position`` is from (None: unknown)
    intent: F64 | None = None  # what the agent says it will fly, map frame (None: it did not say)


class TeamService:
    def __init__(
        self,
        server: Any,
        options: TeamOptions,
        covariances: Covariances | None = None,
        relative: RelativeCovariances | None = None,
    ) -> None:
        self.server = server
        self.options = options
        self.covariances = covariances
        self.relative = relative
        self._frontiers: dict[int, _Cached] = {}
        self._team = _Cached()
        self.commits = Commitments()  # the goal each agent holds between auctions
        self.sight = SightLines(options.frontiers.view_rays)
        self._push: asyncio.Task[None] | None = None
        self.pushed = 0  # advisories sent

    # ---------------------------------------------------------------- pushed advisories

    def start_push(self) -> None:
        """Push ``team_advisory`` messages to the agents that asked for them, until none is connected."""
        if self.options.enabled and (self._push is None or self._push.done()):
            self._push = asyncio.get_running_loop().create_task(self._push_loop(), name="hivemap-team-push")

    async def stop(self, _server: Any = None) -> None:
        """Cancel the push task (a server shutdown hook)."""
        if self._push is not None and not self._push.done():
            self._push.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._push

    def _wanting(self) -> list[Any]:
        return [a for a in self.server.agents.values() if a.team_advisories and a.connection is not None]

    async def _push_loop(self) -> None:
        while True:
            # first wait: the hello that started this is answered before the agent's connection is set
            await asyncio.sleep(self.options.push_interval_s)
            if not self._wanting():
                return
            try:
                team = await self.assignments()
            except Exception:
                logger.exception("team assignments failed; advisories not pushed")
                continue
            wanting = {a.agent_id: a for a in self._wanting()}
            for m in team.maps:
                for a in m.agents:
                    agent = wanting.get(a.agent_id)
                    am = agent.maps.get(agent.session) if agent is not None else None
                    if agent is None or am is None or agent.connection is None:
                        continue
                    msg = TeamAdvisory(
                        map_id=m.map_id, computed_at=team.computed_at,
                        goals=np.array(a.goal_positions, dtype=np.float64).reshape(-1, 3),
                        desired_velocity=np.array(a.advisory.desired_velocity, dtype=np.float64),
                        safe_velocity=np.array(a.advisory.safe_velocity, dtype=np.float64),
                        radius_m=a.advisory.inflated_radius_m, session=am.client_session,
                        half_height_m=a.advisory.half_height_m,
                    )  # fmt: skip
                    if agent.connection.send(msg):  # not queued for later: a stale advisory is no use
                        self.pushed += 1

    # ---------------------------------------------------------------- frontiers

    def _map_snapshot(self, map_id: int) -> tuple[F64, list[F64], F64]:
        m = self.server.stack.maps[map_id]
        # the even subsample extract() takes of a larger map, taken here: on the event loop, every point's
        # position of a large map costs a fraction of a second
        points = list(m.points.values())
        xyz = positions(points[even_subsample(len(points), self.options.frontiers.max_points)])
        paths: dict[str, list[tuple[float, F64]]] = {}
        for kf in m.keyframes.values():
            T = np.asarray(kf.world_from_cam, dtype=np.float64)
            paths.setdefault(kf.agent_id, []).append((float(kf.timestamp), T[:3, 3].copy()))
        rays = self.sight.rays(m)
        self.sight.prune(self.server.stack.maps)
        return xyz, [np.array([p for _, p in sorted(v, key=lambda e: e[0])]) for v in paths.values()], rays

    async def frontiers(self, map_id: int) -> tuple[float, FrontierResult]:
        """(unix time computed, frontiers) of the map; KeyError for an unknown map."""
        if not self.options.enabled:
            raise TeamOff("the team services are off")
        if map_id not in self.server.stack.maps:
            raise KeyError(map_id)
        c = self._frontiers.setdefault(map_id, _Cached())
        async with c.lock:
            if time.monotonic() - c.at >= self.options.min_interval_s or c.value is None:
                xyz, paths, rays = self._map_snapshot(map_id)
                c.value = await asyncio.to_thread(extract, xyz, self.options.frontiers, paths, rays)
                c.at, c.wall = time.monotonic(), time.time()
            return c.wall, c.value

    # ---------------------------------------------------------------- assignments

    @property
    def _velocity_baseline_s(self) -> float:
        """The back-end's rule for an agent's velocity, so that the velocity and its covariance are of the
        same two keyframes."""
        bk = getattr(self.server, "backend", None)
        return float((bk.options.uncertainty if bk is not None else UncertaintyOptions()).velocity_baseline_s)

    def _agents(self) -> list[_AgentSnap]:
        out = []
        for agent in sorted(self.server.agents.values(), key=lambda a: a.agent_id):
            am = agent.maps.get(agent.session)
            if agent.connection is None or am is None:
                continue
            m = self.server.stack.map_of_agent(am.folded)
            kfs = sorted(
                (kf for kf in m.keyframes.values() if kf.agent_id == am.folded) if m is not None else (),
                key=lambda kf: (kf.timestamp, kf.id),
            )
            if not kfs:
                continue
            p = np.asarray(kfs[-1].world_from_cam, dtype=np.float64)[:3, 3].copy()
            v = np.zeros(3)
            ref = velocity_reference([kf.timestamp for kf in kfs], self._velocity_baseline_s)
            if ref is not None and kfs[-1].timestamp > kfs[ref].timestamp:
                q = np.asarray(kfs[ref].world_from_cam, dtype=np.float64)[:3, 3]
                v = (p - q) / (kfs[-1].timestamp - kfs[ref].timestamp)
            map_id: int = m.id  # type: ignore[union-attr]
            intent = None
            if am.intent is not None and am.intent[0] == kfs[-1].id:
                # a map keyframe's pose is rigid (Sim3.transform_pose): its rotation takes the camera frame in
                intent = np.asarray(kfs[-1].world_from_cam, dtype=np.float64)[:3, :3] @ am.intent[1]
            out.append(_AgentSnap(agent.agent_id, agent.kind, map_id, p, v, float(kfs[-1].timestamp), intent))
        return out

    async def assignments(self) -> schemas.TeamAssignments:
        if not self.options.enabled:
            raise TeamOff("the team services are off")
        c = self._team
        async with c.lock:
            if time.monotonic() - c.at >= self.options.min_interval_s or c.value is None:
                agents = self._agents()
                maps = []
                for map_id in sorted({a.map_id for a in agents}):
                    _, fr = await self.frontiers(map_id)
                    team = [a for a in agents if a.map_id == map_id]
                    covs = [self._covariance(a.agent_id) for a in team]
                    rel = self._relative(team)
                    maps.append(await asyncio.to_thread(self._assign, map_id, fr, team, covs, rel))
                c.value = schemas.TeamAssignments(computed_at=time.time(), maps=maps)
                c.at = time.monotonic()
            value: schemas.TeamAssignments = c.value
            return value

    def _covariance(self, agent_id: str) -> tuple[F64, F64, str]:
        o = self.options.orca
        got = self.covariances(agent_id) if self.covariances is not None else None
        P = got[0] if got is not None else None
        V = got[1] if got is not None else None
        source = "graph" if P is not None else "default"
        if P is None:
            P = np.diag([o.default_position_sigma_m**2] * 2 + [0.0])
        if V is None:
            V = np.diag([o.default_velocity_sigma_mps**2] * 2 + [0.0])
        return np.asarray(P, dtype=np.float64), np.asarray(V, dtype=np.float64), source

    def _relative(self, team: list[_AgentSnap]) -> list[tuple[tuple[str, F64 | None], ...]]:
        """Per agent of one map's team, each other agent's id and the covariance of their positions'
        difference (None: unknown)."""

        def get(a: str, b: str) -> F64 | None:
            return self.relative(a, b) if self.relative is not None else None

        return [tuple((b.agent_id, get(a.agent_id, b.agent_id)) for b in team if b is not a) for a in team]

    @staticmethod
    def _t(a: _AgentSnap) -> float:
        return a.timestamp if a.timestamp is not None else time.monotonic()

    def _held_goals(
        self, map_id: int, fr: FrontierResult, team: list[_AgentSnap], goals: F64, allowed: NDArray[np.bool_]
    ) -> list[int | None]:
        """Per agent, the frontier that stands for the goal it holds (None: it takes a new one), the held
        position written into ``goals``; the goals it gave up lately and those the team visited are struck
        from ``allowed``."""
        ao = self.options.auction
        first: list[int | None] = []
        for i, a in enumerate(team):
            t = self._t(a)
            cands = [
                (j, f.goal_for(a.kind))
                for j, f in enumerate(fr.frontiers)
                if allowed[i, j] and j not in first
            ]
            j = self.commits.match(a.agent_id, map_id, a.position, t, cands, ao)
            if j is not None:
                goals[j] = self.commits.held[a.agent_id].position[:2]
            gone = self.commits.struck(a.agent_id, map_id, t, ao)
            if len(gone) and len(goals):
                near = (np.linalg.norm(goals[:, None, :] - gone[None], axis=2) < ao.held_match_m).any(axis=1)
                if j is not None:
                    near[j] = False
                allowed[i] &= ~near
            first.append(j)
        return first

    def _assign(
        self,
        map_id: int,
        fr: FrontierResult,
        team: list[_AgentSnap],
        covs: list[tuple[F64, F64, str]],
        relative: list[tuple[tuple[str, F64 | None], ...]] | None = None,
    ) -> schemas.MapAssignments:
        """The auction of the map's frontiers among ``team`` and the ORCA advisories (in a thread)."""
        o = self.options
        goals = np.array([f.goal[:2] for f in fr.frontiers]).reshape(-1, 2)
        starts = np.array([a.position[:2] for a in team]).reshape(-1, 2)
        allowed = np.array([[a.kind in f.reachable for f in fr.frontiers] for a in team], bool)
        allowed = allowed.reshape(len(team), len(goals))
        first = self._held_goals(map_id, fr, team, goals, allowed)
        value: Callable[[int, int], float] | None = None
        if o.auction.uncertainty_weight_m > 0 and len(goals):
            pts = fr.frontier_points[:, :2]
            near = [int((np.linalg.norm(pts - g, axis=1) <= o.auction.gain_radius_m).sum()) for g in goals]
            gain = [
                [d_optimal_gain(P[:2, :2], min(n, o.auction.max_fixes), o.auction.fix_sigma_m) for n in near]
                for P, _, _ in covs
            ]

            def uncertainty_value(a: int, g: int) -> float:
                return o.auction.uncertainty_weight_m * gain[a][g]

            value = uncertainty_value

        res = ssi_auction(
            starts, goals, allowed=allowed, cap=o.auction.max_goals_per_agent, value=value, first=first
        )  # fmt: skip
        for a, tour, held in zip(team, res.tours, first, strict=True):
            if tour and held is None:
                f0 = fr.frontiers[tour[0]]
                self.commits.hold(a.agent_id, map_id, f0.goal_for(a.kind), a.position, self._t(a))
        goal_at = [
            [
                self.commits.held[a.agent_id].position if g == held else fr.frontiers[g].goal_for(a.kind)
                for g in tour
            ]
            for a, tour, held in zip(team, res.tours, first, strict=True)
        ]
        motions = []
        rel = relative if relative is not None else [()] * len(team)
        for a, at, (P, V, _), r in zip(team, goal_at, covs, rel, strict=True):
            ugv = a.kind == "ugv"
            speed = o.orca.max_speed_ugv if ugv else o.orca.max_speed_uav
            desired = preferred_velocity(
                a.velocity, a.position, at[0] if at else None, speed, o.orca, a.intent
            )
            radius = o.orca.radius_ugv_m if ugv else o.orca.radius_uav_m
            half = o.orca.half_height_ugv_m if ugv else o.orca.half_height_uav_m
            motions.append(
                AgentMotion(a.agent_id, a.position, a.velocity, desired, radius, speed, P, V, a.timestamp, r,
                            a.intent, half)
            )  # fmt: skip
        advs = advisories(motions, o.orca)
        ids = [f.id for f in fr.frontiers]
        out_agents = []
        for a, m, adv, tour, at, cost, (_, _, source) in zip(
            team, motions, advs, res.tours, goal_at, res.costs, covs, strict=True
        ):
            out_agents.append(
                schemas.AgentAssignment(
                    agent_id=a.agent_id, kind=a.kind, position=a.position.tolist(),
                    velocity=a.velocity.tolist(), goals=[fr.frontiers[g].id for g in tour],
                    goal_positions=[g.tolist() for g in at],
                    path_cost_m=cost,
                    advisory=schemas.Advisory(
                        desired_velocity=adv.desired.tolist(), safe_velocity=adv.safe_velocity.tolist(),
                        radius_m=m.radius, inflated_radius_m=adv.radius, half_height_m=adv.half_height,
                        intent=None if m.intent is None else np.asarray(m.intent).tolist(),
                        neighbours=list(adv.neighbours), covariance=source,
                        relative_position_cov={b: None if c is None else np.asarray(c).tolist()
                                               for b, c in m.relative},
                    ),
                )
            )  # fmt: skip
        rounds = [
            schemas.AuctionRound(round=b.round, agent_id=team[b.agent].agent_id, frontier_id=ids[b.goal],
                                 bid_m=b.bid, added_cost_m=b.added_cost)
            for b in res.won
        ]  # fmt: skip
        return schemas.MapAssignments(
            map_id=map_id, frontiers=len(fr.frontiers), agents=out_agents, rounds=rounds,
            unassigned=[ids[g] for g in res.unassigned],
        )  # fmt: skip


def frontier_list(
    map_id: int, computed_at: float, fr: FrontierResult, voxel_m: float
) -> schemas.FrontierList:
    return schemas.FrontierList(
        map_id=map_id, computed_at=computed_at, voxel_m=voxel_m, ground=list(fr.ground),
        known_cells=fr.known_cells, frontier_points=len(fr.frontier_points),
        frontiers=[
            schemas.FrontierInfo(id=f.id, goal=f.goal.tolist(), points=f.points, reachable=list(f.reachable),
                                 goals={k: g.tolist() for k, g in f.goals.items()})
            for f in fr.frontiers
        ],
    )  # fmt: skip


def _session_map(server: Any, agent_id: str) -> Any:
    """The agent's current session's :class:`~hivemap.server.agents.AgentMap` (None: unknown agent or no
    session yet)."""
    agent = server.agents.get(agent_id)
    return agent.maps.get(agent.session) if agent is not None else None


def graph_covariances(server: Any) -> Covariances:
    """The :data:`Covariances` hook from the server's pose graph: an agent's position covariance is the
    (3, 3) camera-centre block of the back-end's marginal of its current session's latest keyframe, the
    one ``/agents/{id}`` and the corrections carry (:func:`~hivemap.server.views_uncertainty.
    latest_pose_covariance`), already in its map's frame (:mod:`hivemap.server.marginals`); none while
    the back-end has none for the map the agent is in now (off, fewer than two keyframes, singular).

    The velocity covariance is that of the position difference of the same keyframe and the agent's
    previous one over their time apart, from the two poses' joint marginal (the drift both share from the
    gauge cancels in the difference); unknown (the options' ``default_velocity_sigma_mps``) while the
    session has one keyframe."""
    from hivemap.server.marginals import position_covariance
    from hivemap.server.views_uncertainty import latest_pose_covariance

    def of_agent(agent_id: str) -> tuple[F64 | None, F64 | None] | None:
        am = _session_map(server, agent_id)
        if am is None:
            return None
        m = server.stack.map_of_agent(am.folded)
        cov = latest_pose_covariance(server, am.folded)
        if cov is None or m is None or cov.map_id != m.id:
            return None
        return position_covariance(cov.covariance), cov.velocity

    return of_agent


def graph_relative_covariances(server: Any) -> RelativeCovariances:
    """The :data:`RelativeCovariances` hook from the server's pose graph: the covariance of the difference
    of two agents' current sessions' latest keyframes' camera centres (:func:`~hivemap.server.
    views_uncertainty.latest_relative_covariance`), when one map holds both; none before the back-end
    has solved for that pair."""
    from hivemap.server.views_uncertainty import latest_relative_covariance

    def between(a: str, b: str) -> F64 | None:
        ma, mb = _session_map(server, a), _session_map(server, b)
        if ma is None or mb is None:
            return None
        rel = latest_relative_covariance(server, ma.folded, mb.folded)
        m = server.stack.map_of_agent(ma.folded)
        if rel is None or m is None or rel.map_id != m.id:
            return None
        return rel.covariance

    return between


def team_service(server: Any) -> TeamService:
    """The server's team service, made on first use from its settings' ``team`` options, its advisories'
    radii inflated by the back-end's pose covariances (:func:`graph_covariances`,
    :func:`graph_relative_covariances`)."""
    svc: TeamService | None = getattr(server, "team", None)
    if svc is None:
        svc = server.team = TeamService(
            server, server.settings.team, graph_covariances(server), graph_relative_covariances(server)
        )
        server.shutdown_hooks.append(svc.stop)
    return svc
