"""The simple controller of a live simulated agent (issue 26, closed loop): towards its goals along the
site's roads, in its altitude band, obeying the server's collision advisory.

Goals and advisories arrive in the frame of the agent's map; :func:`world_from_map` turns them into the
world frame through the agent's own estimate (what a real robot does: it steers by where it thinks it is).
Paths follow a graph of the road centre lines, which keeps a UGV on drivable ground and a UAV over roads
(and the air lines across blocks), clear of the buildings; a UAV keeps its cruise height, higher over
obstacles. A fresh advisory whose safe velocity differs from the server's desired one (ORCA changed it)
overrides the horizontal command for ``advisory_ttl_s``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ControlOptions:
    """Tuning of :class:`Controller`."""

    lookahead_m: float = 3.0  # pure pursuit: the carrot is this far along the path
    # a UGV keeps this far from an obstacle's footprint: it passes one in its road aside and stops before
    # one across the road (RoadPaths)
    obstacle_margin_m: float = 2.0
    node_spacing_m: float = 1.0  # the road graph's nodes are this far apart along each centre line
    join_m: float = 1.5  # nodes of different lines closer than this are joined (crossings)
    goal_reached_m: float = 2.0  # a goal this close (horizontally) counts as reached: on to the next
    # 1/s: the speed falls to this times the remaining distance near the last goal (through the others the
    # agent keeps its speed: the next one is the way on)
    arrive_gain: float = 0.5
    advisory_ttl_s: float = 2.0  # sim seconds an advisory is obeyed after it arrived
    # goals reached in the last reached_memory_s are dropped from new advisories (the server reassigns a
    # frontier until it is seen, and one off the road stays unseen from the road's end)
    reached_memory_s: float = 30.0
    orca_eps_mps: float = 0.05  # safe and desired velocity differ by more: ORCA changed it, obey it
    replan_goal_m: float = 2.0  # the path is replanned when the goal moved more than this
    climb_mps: float = 1.0  # UAV vertical speed limit
    z_gain: float = 0.8  # 1/s: vertical speed per metre of height error
    clearance_m: float = 2.0  # UAV height above the tops of obstacles under it
    min_turn_speed: float = 0.2  # below this speed the heading is kept
    # a UGV obeying a safe velocity that would take it within road_margin_m of the road's edge in
    # road_check_s stops instead: ORCA knows nothing of the roads, and standing still is what a car can do
    road_check_s: float = 1.0
    road_margin_m: float = 1.0
    # the intent each keyframe carries: the mean velocity along the path over this long (Controller.intent)
    intent_horizon_s: float = 2.0


@dataclass(frozen=True)
class WorldAdvisory:
    """A team advisory in the world frame, with the sim time it arrived."""

    t: float
    goals: F64  # (G, 3)
    desired_velocity: F64  # (3,)
    safe_velocity: F64  # (3,)
    radius_m: float
    half_height_m: float = 0.0


def world_from_map(world_from_body: F64, map_from_body: F64) -> F64:
    """The world-from-map transform an agent acts on: its true pose composed with its estimate's inverse
    (both 4x4 body poses); ``map_from_body`` may be a Sim(3) matrix (its scale is divided out)."""
    M = np.asarray(map_from_body, dtype=np.float64).copy()
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    M[:3, :3] /= s
    return np.asarray(world_from_body, dtype=np.float64) @ np.linalg.inv(M)


class RoadPaths:
    """Shortest paths over road centre lines sampled every ``spacing`` metres (2D). With ``blocked`` boxes
    (a UGV's: the site's obstacles), a node within ``margin`` of a box's footprint moves sideways, up to
    ``lateral`` metres, to the nearest place of the road that keeps ``margin`` (a pillar in the road is
    passed), and is dropped where there is none (a fence across the road ends it there). The world's fences
    cross the roads' ends, and a UGV on the centre line drove through them: its camera saw a wall come to
    zero range, and its tracking failed."""

    def __init__(
        self,
        lines: Sequence[F64],
        spacing: float = 1.0,
        join: float = 1.5,
        blocked: Sequence[object] = (),
        margin: float = 1.0,
        lateral: float = 0.0,
    ) -> None:
        pts, normals, rows, cols = [], [], [], []
        n = 0
        for line in lines:
            line = np.asarray(line, dtype=np.float64)[:, :2]
            seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
            s = np.concatenate([[0.0], np.cumsum(seg)])
            if s[-1] <= 0:
                continue
            k = max(1, int(math.ceil(s[-1] / spacing)))
            u = np.linspace(0.0, s[-1], k + 1)
            p = np.stack([np.interp(u, s, line[:, 0]), np.interp(u, s, line[:, 1])], axis=1)
            d = np.gradient(p, axis=0)
            normals.append(np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True))
            pts.append(p)
            rows += list(range(n, n + k))
            cols += list(range(n + 1, n + k + 1))
            n += k + 1
        if not pts:
            raise ValueError("no road lines to plan on")
        nodes = np.concatenate(pts)
        r = np.asarray(rows, dtype=np.int64)
        c = np.asarray(cols, dtype=np.int64)
        if blocked:
            nodes, free = _clear_of(nodes, np.concatenate(normals), blocked, margin, lateral, spacing)
        pairs = cKDTree(nodes).query_pairs(join, output_type="ndarray")
        r, c = np.concatenate([r, pairs[:, 0]]), np.concatenate([c, pairs[:, 1]])
        if blocked:
            r, c, nodes = _kept_edges(nodes, free, r, c, blocked, margin / 2)
        self.nodes = nodes
        self.tree = cKDTree(self.nodes)
        w = np.linalg.norm(self.nodes[r] - self.nodes[c], axis=1) + 1e-6
        self.graph = coo_matrix((w, (r, c)), shape=(len(self.nodes), len(self.nodes))).tocsr()

    def nearest(self, xy: F64) -> int:
        return int(self.tree.query(np.asarray(xy, dtype=np.float64)[:2])[1])

    def path(self, start_xy: F64, goal_xy: F64) -> F64:
        """(K, 2) from the node nearest ``start_xy`` to the node nearest ``goal_xy``, or, when that one is
        not connected to the start (behind a fence), to the connected node nearest the goal."""
        a, b = self.nearest(start_xy), self.nearest(goal_xy)
        dist, pred = dijkstra(self.graph, directed=False, indices=a, return_predecessors=True)
        if b != a and pred[b] < 0:
            ok = np.flatnonzero(np.isfinite(dist))
            b = int(ok[np.argmin(np.linalg.norm(self.nodes[ok] - np.asarray(goal_xy)[:2], axis=1))])
        out = [b]
        while out[-1] != a:
            out.append(int(pred[out[-1]]))
        return self.nodes[out[::-1]]


def _near_any(boxes: Sequence[object], xy: F64, margin: float) -> NDArray[np.bool_]:
    from hivemap.sim.roads import inside_box_footprint

    hit = np.zeros(len(xy), bool)
    for b in boxes:
        hit |= inside_box_footprint(b, xy, margin)
    return hit


def _clear_of(
    nodes: F64, normals: F64, boxes: Sequence[object], margin: float, lateral: float, step: float
) -> tuple[F64, NDArray[np.bool_]]:
    """(nodes moved sideways out of the boxes' margins where the road allows it, which nodes are clear)."""
    out = nodes.copy()
    bad = np.flatnonzero(_near_any(boxes, nodes, margin))
    offsets = np.arange(0.5 * step, lateral + 1e-9, 0.5 * step)
    for o in offsets:  # the smallest shift that clears, either side
        if not len(bad):
            break
        for sign in (1.0, -1.0):
            cand = nodes[bad] + sign * o * normals[bad]
            ok = ~_near_any(boxes, cand, margin)
            out[bad[ok]] = cand[ok]
            bad = bad[~ok]
    free = np.ones(len(nodes), bool)
    free[bad] = False
    return out, free


def _kept_edges(
    nodes: F64, free: NDArray[np.bool_], r: NDArray[np.int64], c: NDArray[np.int64], boxes: Sequence[object],
    margin: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], F64]:  # fmt: skip
    """The edges between clear nodes none of whose points is within ``margin`` of a box (its ends may lie
    either side of a thin one), renumbered over the clear nodes."""
    steps = np.linspace(0.0, 1.0, 11)
    samples = nodes[r][:, None, :] + steps[None, :, None] * (nodes[c] - nodes[r])[:, None, :]
    hit = _near_any(boxes, samples.reshape(-1, 2), margin).reshape(len(r), -1).any(axis=1)
    keep = ~hit & free[r] & free[c]
    index = np.cumsum(free) - 1
    return index[r[keep]], index[c[keep]], nodes[free]


def _pursuit(path: F64, xy: F64, lookahead: float) -> tuple[F64, float]:
    """(carrot (2,), remaining arc length from the point of ``path`` nearest ``xy`` to its end)."""
    if len(path) == 1:
        return path[0], float(np.linalg.norm(path[0] - xy))
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    i = int(np.argmin(np.linalg.norm(path - xy, axis=1)))
    target = min(s[i] + lookahead, s[-1])
    carrot = np.array([np.interp(target, s, path[:, 0]), np.interp(target, s, path[:, 1])])
    return carrot, float(s[-1] - s[i] + np.linalg.norm(path[i] - xy))


class Controller:
    """Velocity and heading commands of one live agent (see the module docstring)."""

    def __init__(
        self,
        kind: str,
        speed_mps: float,
        paths: RoadPaths,
        cruise_height_m: float = 0.0,
        obstacles: Sequence[object] = (),
        options: ControlOptions | None = None,
        road_half_width_m: float | None = None,
    ) -> None:
        self.kind, self.speed = kind, float(speed_mps)
        self.paths = paths
        self.cruise = float(cruise_height_m)
        self.obstacles = list(obstacles)
        self.road_half_width = road_half_width_m  # set: drivable ground only (a UGV)
        self.options = options or ControlOptions()
        self.goal_index = 0
        self.goals_reached = 0
        self._path: F64 | None = None
        self._path_goal: F64 | None = None
        self._advisory: WorldAdvisory | None = None
        self._reached: list[tuple[float, F64]] = []  # (sim time, goal xy)
        self.obeyed = 0  # commands that took the advisory's safe velocity
        self.stopped_for_road = 0  # of those, commands that stopped rather than leave the road

    def advise(self, adv: WorldAdvisory) -> None:
        """A new advisory (world frame): its goals replace the current ones, less those reached lately; the
        goal being pursued stays first while the advisory still has it (within ``replan_goal_m``): the
        auction's order changes as the agents move, and turning back and forth covers nothing."""
        o = self.options
        self._reached = [(t, xy) for t, xy in self._reached if adv.t - t <= o.reached_memory_s]
        goals = np.asarray(adv.goals, dtype=np.float64).reshape(-1, 3)
        if self._reached and len(goals):
            done = np.array([xy for _, xy in self._reached])
            d = np.linalg.norm(goals[:, None, :2] - done[None, :, :], axis=2).min(axis=1)
            goals = goals[d >= o.goal_reached_m]
        current = self.goal
        if current is not None and len(goals):
            d = np.linalg.norm(goals[:, :2] - current[:2], axis=1)
            k = int(np.argmin(d))
            if d[k] <= o.replan_goal_m:
                goals = np.concatenate([goals[k : k + 1], np.delete(goals, k, axis=0)])
        self.goal_index = 0
        self._advisory = dataclasses.replace(adv, goals=goals)

    @property
    def goal(self) -> F64 | None:
        adv = self._advisory
        if adv is None or self.goal_index >= len(adv.goals):
            return None
        return np.asarray(adv.goals[self.goal_index], dtype=np.float64)

    def _height_target(self, xy: F64) -> float:
        from hivemap.sim.roads import box_top, inside_box_footprint

        z = self.cruise
        for b in self.obstacles:
            if inside_box_footprint(b, xy.reshape(-1, 2), margin=1.5).any():
                z = max(z, box_top(b) + self.options.clearance_m)
        return z

    def _climb(self, p: F64) -> tuple[float, bool]:
        """(vertical speed towards the height target at ``p``, whether the agent is still climbing to it:
        then it does not move on, so the path stays over the roads). Zero and False for a UGV."""
        if self.kind != "uav":
            return 0.0, False
        o = self.options
        dz = self._height_target(p[:2]) - p[2]
        return float(np.clip(o.z_gain * dz, -o.climb_mps, o.climb_mps)), dz > 1.0

    def _planned(self, goal: F64) -> bool:
        """Whether the stored path leads to ``goal`` (within ``replan_goal_m``)."""
        pg = self._path_goal
        near = pg is not None and np.linalg.norm(pg - goal[:2]) <= self.options.replan_goal_m
        return self._path is not None and bool(near)

    def _is_reached(self, goal: F64, p: F64) -> bool:
        """The goal is near, or as near as the roads go: its path ends here."""
        o = self.options
        if np.linalg.norm(goal[:2] - p[:2]) < o.goal_reached_m:
            return True
        path = self._path
        return bool(
            self._planned(goal)
            and path is not None
            and np.linalg.norm(path[-1] - p[:2]) < o.goal_reached_m / 2
        )

    def intent(self, position: F64) -> F64:
        """What the agent will fly without advisories (3,) world m/s: the mean velocity over the next
        ``intent_horizon_s`` along its path to the current goal at its speed (the chord, so a turn ahead
        shows), its climb rate vertically; zero horizontally without a goal or while a UAV climbs to its
        height. The server's ORCA predicts the agent along it (NH-ORCA's reference path, in one velocity)."""
        o = self.options
        p = np.asarray(position, dtype=np.float64)
        v = np.zeros(3)
        v[2], climbing = self._climb(p)
        goal = self.goal
        if goal is None or climbing:
            return v
        # the path command() follows; planned here (not stored) when command() has not planned it yet
        path = self._path if self._planned(goal) else self.paths.path(p[:2], goal[:2])
        assert path is not None
        ahead, _ = _pursuit(path, p[:2], self.speed * o.intent_horizon_s)
        d = ahead - p[:2]
        n = float(np.linalg.norm(d))
        if n > 1e-6:
            v[:2] = d / n * min(self.speed, n / o.intent_horizon_s)
        return v

    def command(self, t: float, position: F64, yaw: float, airborne: bool = True) -> tuple[F64, float | None]:
        """(velocity (3,) world m/s, heading rad or None to keep it) at sim time ``t``; a UAV climbs to
        its height before it moves (``airborne`` False: it may not move yet, e.g. held on the ground)."""
        o = self.options
        p = np.asarray(position, dtype=np.float64)
        v = np.zeros(3)
        goal = self.goal
        while goal is not None and self._is_reached(goal, p):
            self._reached.append((t, goal[:2].copy()))
            self.goal_index += 1
            self.goals_reached += 1
            goal = self.goal
        if not airborne:
            return v, None
        if goal is not None:
            if not self._planned(goal):
                self._path = self.paths.path(p[:2], goal[:2])
                self._path_goal = goal[:2].copy()
            assert self._path is not None
            carrot, remaining = _pursuit(self._path, p[:2], o.lookahead_m)
            d = carrot - p[:2]
            n = float(np.linalg.norm(d))
            if n > 1e-6:
                adv = self._advisory
                last = adv is None or self.goal_index >= len(adv.goals) - 1
                v[:2] = d / n * (min(self.speed, o.arrive_gain * remaining) if last else self.speed)
        adv = self._advisory
        fresh = adv is not None and t - adv.t <= o.advisory_ttl_s
        if fresh and adv is not None:
            changed = np.linalg.norm(adv.safe_velocity[:2] - adv.desired_velocity[:2]) > o.orca_eps_mps
            if changed:  # ORCA moved the server's desired velocity: obey the safe one
                safe = np.asarray(adv.safe_velocity[:2], dtype=np.float64)
                ns = float(np.linalg.norm(safe))
                v[:2] = safe if ns <= self.speed else safe / ns * self.speed
                self.obeyed += 1
                hw = self.road_half_width
                if hw is not None:
                    ahead = p[:2] + v[:2] * o.road_check_s
                    off = float(self.paths.tree.query(ahead)[0]) > hw - o.road_margin_m
                    if off:
                        v[:2] = 0.0
                        self.stopped_for_road += 1
        heading: float | None = None
        sp = float(np.linalg.norm(v[:2]))
        if sp > o.min_turn_speed:
            heading = math.atan2(v[1], v[0])
            if self.kind == "ugv":
                # a car does not slide sideways: slow down while the heading is far off, turn first
                err = math.remainder(heading - yaw, 2 * math.pi)
                v[:2] *= max(0.0, math.cos(err))
        v[2], climbing = self._climb(p)
        if climbing:  # take-off and climbs: height first, so the path stays over the roads
            v[:2] *= 0.0
            heading = None
        return v, heading
