"""UAV and UGV trajectories over the world's road network.

Frames: world z-up (x east, y north), ground at z = 0. Body frame = IMU frame, x forward, y left, z up.

Construction (``plan_trajectories(world, scenario)``):

1. The world's road centre polylines become a graph (nodes at crossings, T-junctions and ends).
2. Routes are walks in that graph (directed edges). The UGV drives a cycle of the graph around a block
   and passes its start again (loop closure). The UAVs fly over the roads (so never through a
   building), chosen by a seeded search so that each closes a loop, every UAV pair flies at least two
   road segments in the same direction at similar height, and at least two segments driven by the UGV
   are also flown by a UAV in the same direction at low height (``UAV_LOW_HEIGHT``), preferring
   segments that end facing a building facade (meeting points).
3. Geometry: corners get circular fillets, then Gaussian smoothing, then a C2 cubic spline in arc
   length. UAV height profile: take-off from the UGV's roof, cruise height with a gentle variation,
   low passes at meeting points, clearance over obstacles.
4. Timing: standstill (``scenario.hold_s``), smooth acceleration (quintic smoothstep speed ramp),
   cruise, deceleration, 1 s standstill. Position is a quintic (C4) B-spline in time through samples
   of the path every 0.2 s, clamped to zero velocity/acceleration at both ends; yaw is a quintic
   B-spline through the path heading (Gaussian-smoothed for UAVs).
5. Attitude: UGV = yaw only (flat ground). UAV = quadrotor differential flatness: body z along the
   thrust direction a - g, body x towards the yaw heading. Angular velocity is computed analytically
   from the spline derivatives (jerk, yaw rate), so the simulated IMU is exact.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from hivemap.sim.motion import G_WORLD, GRAVITY, UAV_GROUND_HEIGHT, Trajectory, _make_trajectory, _smoothstep5
from hivemap.sim.roads import (
    RoadGraph,
    _cycles_through,
    _fillet,
    _ray_hits_building,
    _resample,
    _with_air_edges,
    box_top,
    build_road_graph,
    inside_box_footprint,
)
from hivemap.sim.routes import CLIMB_M, Route, _edge_coverage, _has_self_loop, _random_walk, extend_to_length
from hivemap.sim.scenarios import (
    UAV_LOW_HEIGHT,
    UGV_BODY_HEIGHT,
    UGV_ROOF_HEIGHT,
    AgentSpec,
    Scenario,
)
from hivemap.sim.takeoff import CLIMB_S, spot, takeoff_plan

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# ---------------------------------------------------------------------------------------------
# Planning
# ---------------------------------------------------------------------------------------------


@dataclass
class TrajectoryPlan:
    """Trajectories of all agents plus what the planner intended (for tests and logs)."""

    trajectories: dict[str, Trajectory]
    graph: RoadGraph
    start_xy: F64
    start_heading: float
    routes: dict[str, Route]
    crossings: dict[tuple[str, str], list[tuple[int, bool]]]  # UAV pair -> shared directed edges
    meetings: list[tuple[str, tuple[int, bool]]]  # (uav id, directed edge shared with the UGV, flown low)
    loops: dict[str, list[tuple[int, bool]]]  # agent -> directed edges it travels twice


def _xy_path(route: Route, g: RoadGraph, road_width: float) -> tuple[F64, F64, list[tuple[float, float]]]:
    poly, spans = route.polyline(g)
    f = _fillet(poly, max_radius=6.0, max_cut=0.3 * road_width)
    xy, s = _resample(f, 0.25)
    xy_s = gaussian_filter1d(xy, sigma=4.0, axis=0, mode="nearest")
    xy_s[0] = xy[0]
    # Re-measure arc length after smoothing and map edge spans (defined on the raw polyline) onto it.
    s2 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy_s, axis=0), axis=1))])
    return xy_s, s2 * (s[-1] / max(s2[-1], 1e-9)) if s2[-1] > 0 else s2, spans


def _uav_heights(
    world: Any,
    xy: F64,
    s: F64,
    spec: AgentSpec,
    z_start: float,
    low_spans: list[tuple[float, float]],
    phase: float,
) -> F64:
    """UAV height along the path (xy arc length s): take-off ramp, cruise with variation, low passes."""
    h = spec.cruise_height_m + 0.5 * np.sin(2 * np.pi * s / 70.0 + phase)
    # low passes: blend towards UAV_LOW_HEIGHT with 14 m transitions
    w = np.zeros_like(s)
    trans = 14.0
    for a, b in low_spans:
        up = _smoothstep5((s - (a - trans)) / trans)
        down = 1.0 - _smoothstep5((s - b) / trans)
        w = np.maximum(w, np.minimum(up, down))
    h = (1 - w) * h + w * UAV_LOW_HEIGHT
    # take-off ramp from the start height over the first 14 m
    r = _smoothstep5(s / 14.0)
    h = z_start + (h - z_start) * r
    # clearance over obstacles/buildings under the path (1.5 m footprint margin, 2 m above the top)
    need = np.full_like(s, -np.inf)
    for b in [*getattr(world, "obstacles", []), *getattr(world, "buildings", [])]:
        m = inside_box_footprint(b, xy, margin=1.5)
        if m.any():
            need[m] = np.maximum(need[m], box_top(b) + 2.0)
    if np.isfinite(need).any():
        need[~np.isfinite(need)] = 0.0
        need = maximum_filter1d(need, size=49)  # +-6 m at 0.25 m spacing
        need = gaussian_filter1d(need, sigma=12.0, mode="nearest")
        start_zone = s < 3.0  # on the UGV roof
        need[start_zone] = np.minimum(need[start_zone], z_start)
        h = np.maximum(h, need)
        h = gaussian_filter1d(h, sigma=4.0, mode="nearest")
        h[0] = z_start
    return h


def _pick_start(
    g: RoadGraph, world_size: float, region: str, ugv_len: float | None
) -> tuple[tuple[int, bool], list[tuple[int, bool]] | None, float | None]:
    """Start directed edge (+ cycle for the UGV) near the centre of the region."""
    centre = {
        "all": np.zeros(2),
        "west": np.array([-world_size / 3, 0.0]),
        "east": np.array([world_size / 3, 0.0]),
    }[region]
    allowed = _region_edges(g, region, world_size)
    if ugv_len is not None:
        allowed &= g.road_edges
    cands = []
    for e in g.edges:
        if e.id not in allowed or e.length < 10.0:
            continue
        mid = e.pts[len(e.pts) // 2] if len(e.pts) > 2 else e.pts.mean(axis=0)
        cands.append((float(np.linalg.norm(mid - centre)), e.id))
    cands.sort()
    if not cands:
        raise ValueError("road graph has no edge >= 10 m to start from")
    if ugv_len is None:
        return (cands[0][1], True), None, None
    # Tier 1: a cycle the UGV closes within its nominal length; tier 2: up to 9 % longer.
    for tier in (1.0, 1.09):
        for _, eid in cands:
            for fwd in (True, False):
                de = (eid, fwd)
                d0 = _start_offset(g, de)
                max_len = tier * ugv_len + d0 - 5.0
                cyc = _cycles_through(g, de, max_len, 12, allowed)
                cyc = [c for c in cyc if sum(g.length(x) for x in c) >= 40.0]
                if cyc:
                    cyc.sort(key=lambda c: abs(sum(g.length(x) for x in c) - 0.8 * ugv_len))
                    lc = sum(g.length(x) for x in cyc[0])
                    return de, cyc[0], max(ugv_len, lc - d0 + 5.0)
    return (cands[0][1], True), None, ugv_len


def _start_offset(g: RoadGraph, de: tuple[int, bool]) -> float:
    L = g.length(de)
    return min(15.0, max(0.45 * L, L - 6.0))


def _region_edges(g: RoadGraph, region: str, world_size: float) -> set[int]:
    if region == "all":
        return {e.id for e in g.edges}
    sign = -1.0 if region == "west" else 1.0
    lim = 0.1 * world_size
    return {e.id for e in g.edges if sign * float(np.mean(e.pts[:, 0])) > lim}


def _passes(
    route: Route, g: RoadGraph, skip_first: float = CLIMB_M
) -> list[tuple[int, tuple[int, bool], F64]]:
    """(index in route.edges, directed edge, xy midpoint) of the covered passes after the climb."""
    out = []
    s_acc = -route.start_offset
    for i, de in enumerate(route.edges):
        L = g.length(de)
        lo, hi = max(s_acc, 0.0), min(s_acc + L, route.length)
        if hi - lo >= min(8.0, 0.8 * L) and lo >= skip_first:
            p = g.edges[de[0]].pts
            out.append((i, de, np.asarray(0.5 * (p[0] + p[-1]))))
        s_acc += L
    return out


def _choose_meetings(
    uav_routes: dict[str, Route],
    g: RoadGraph,
    ugv_cov: set[tuple[int, bool]],
    de_start: tuple[int, bool] | None,
    facade: dict[tuple[int, bool], bool],
) -> list[tuple[str, int]]:
    """Up to 3 low passes (uav, index into its route.edges) over edges the UGV drives in the same
    direction, >= 25 m apart, facade-facing first, spread over the UAVs, such that every UAV keeps a
    loop (an edge passed twice at cruise height) and every UAV pair keeps >= 2 shared edges at cruise.
    A low pass at index i also disturbs passes i-1 and i+1 (descent, climb)."""
    passes = {k: _passes(r, g) for k, r in uav_routes.items()}
    ids = list(uav_routes)
    low: dict[str, set[int]] = {k: set() for k in ids}

    def cruise_edges(k: str, lows: set[int]) -> list[tuple[int, bool]]:
        bad = {j for i in lows for j in (i - 1, i, i + 1)}
        return [de for i, de, _ in passes[k] if i not in bad and de != de_start]

    def feasible(k: str, lows: set[int]) -> bool:
        ce = cruise_edges(k, lows)
        if not any(ce.count(de) > 1 for de in ce):
            return False
        return all(len(set(ce) & set(cruise_edges(kk, low[kk]))) >= 2 for kk in ids if kk != k)

    chosen: list[tuple[str, int, F64]] = []
    while len(chosen) < 3:
        best: tuple[tuple[int, bool, int], str, int, F64] | None = None
        for k in ids:
            n_used = sum(1 for c in chosen if c[0] == k)
            for i, de, m in passes[k]:
                if de not in ugv_cov or de == de_start or i in low[k]:
                    continue
                if any(np.linalg.norm(m - c[2]) < 25.0 for c in chosen):
                    continue
                if not feasible(k, low[k] | {i}):
                    continue
                key = (n_used, not facade.get(de, False), i)
                if best is None or key < best[0]:
                    best = (key, k, i, m)
        if best is None:
            break
        _, k, i, m = best
        low[k].add(i)
        chosen.append((k, i, m))
    return [(k, i) for k, i, _ in chosen]


def _agent_path(
    world: Any, g: RoadGraph, r: Route, a: AgentSpec, road_width: float, with_ugv: bool, climb_m: float = 0.0
) -> tuple[F64, list[tuple[float, float]], F64]:
    """Dense smooth 3D path (M, 3) of one agent, the edge spans and the xy arc length. A UAV's path starts
    ``climb_m`` above the UGV's roof (the climb itself is timed in ``_make_trajectory``)."""
    xy, s, spans = _xy_path(r, g, road_width)
    if a.kind == "ugv":
        z = np.full(len(s), UGV_BODY_HEIGHT)
    else:
        z_start = UGV_ROOF_HEIGHT + 0.1 + climb_m if with_ugv else UAV_GROUND_HEIGHT
        low_spans = [spans[i] for i in r.low_edges]
        idx = spot(a)
        z = _uav_heights(world, xy, s, a, z_start, low_spans, phase=0.9 * idx)
        if with_ugv:
            # Take-off spots on the UGV roof: 0.35 m apart along the heading.
            off = (idx - 2) * 0.35
            d = xy[min(8, len(xy) - 1)] - xy[0]
            d /= np.linalg.norm(d)
            xy = xy + off * d[None, :] * np.exp(-s / 3.0)[:, None]
    return np.concatenate([xy, z[:, None]], axis=1), spans, s


def plan_trajectories(
    world: Any, scenario: Scenario, n_candidates: int = 400, n_trials: int = 4000
) -> TrajectoryPlan:
    """Plan every agent's trajectory for ``scenario`` on ``world`` (deterministic for the scenario seed)."""
    rng = np.random.default_rng(scenario.seed + 1000)
    snap = max(2.0, float(world.road_width))
    g = build_road_graph(list(world.roads), snap_tol=snap)
    if any(a.kind == "uav" for a in scenario.agents):
        g = _with_air_edges(g, list(world.roads), snap, float(world.road_width))
    road_width = float(world.road_width)
    routes: dict[str, Route] = {}
    loops: dict[str, list] = {}
    trajs: dict[str, Trajectory] = {}
    ugv = [a for a in scenario.agents if a.kind == "ugv"]
    uavs = [a for a in scenario.agents if a.kind == "uav"]
    crossings: dict[tuple[str, str], list] = {}
    meetings: list[tuple[str, tuple[int, bool]]] = []
    targets: dict[str, float] = {}

    if ugv:
        # Shared start: everyone starts at the UGV (UAVs on its roof).
        de0, cycle, ugv_len = _pick_start(g, scenario.world_size_m, "all", ugv[0].path_length_m)
        if ugv_len is not None and ugv_len > ugv[0].path_length_m + 0.01:
            log.warning("UGV path lengthened to %.1f m to close its loop", ugv_len)
            targets[ugv[0].agent_id] = ugv_len
        d0 = _start_offset(g, de0)
        if cycle is None:
            log.warning("no road cycle shorter than the UGV path: the UGV will not close a loop")
            r = None
            for _ in range(200):
                r = _random_walk(g, de0, d0, ugv[0].path_length_m, rng)
                if r is not None:
                    break
            if r is None:
                raise ValueError("cannot find a UGV route on the road graph")
            ugv_route = r
        else:
            ugv_route = Route(cycle * 3, d0, targets.get(ugv[0].agent_id, ugv[0].path_length_m))
        routes[ugv[0].agent_id] = ugv_route
        starts = {a.agent_id: (de0, d0) for a in scenario.agents}
    else:
        starts = {}
        for a in scenario.agents:
            de, _, _ = _pick_start(g, scenario.world_size_m, a.region, None)
            starts[a.agent_id] = (de, _start_offset(g, de))

    # --- UAV routes: seeded search over random walks for loops, pair crossings and meetings.
    ugv_cov = set(_edge_coverage(routes[ugv[0].agent_id], g)) if ugv else set()
    follow: dict[tuple[int, bool], tuple[int, bool]] = {}
    if ugv:
        ue = routes[ugv[0].agent_id].edges
        follow = {x: y for x, y in zip(ue[:-1], ue[1:], strict=True)}
    de_start = starts[uavs[0].agent_id][0] if uavs else None
    facade: dict[tuple[int, bool], bool] = {}
    for de in ugv_cov:
        geo = g.geometry(de)
        d = geo[-1] - geo[-2]
        facade[de] = _ray_hits_building(world, geo[-1], d, 30.0) is not None
    cands: dict[str, list[Route]] = {}
    for a in uavs:
        de, d0 = starts[a.agent_id]
        allowed = _region_edges(g, a.region, scenario.world_size_m)
        lst: list[Route] = []
        for _ in range(n_candidates):
            r = _random_walk(
                g, de, d0, a.path_length_m, rng, allowed, follow, float(rng.choice([0.0, 0.5, 0.8]))
            )
            if r is not None and _has_self_loop(r, g):
                lst.append(r)
        if not lst:
            for _ in range(n_candidates):
                r = _random_walk(g, de, d0, a.path_length_m, rng, allowed)
                if r is not None:
                    lst.append(r)
            level = logging.WARNING if a.path_length_m > 100.0 else logging.INFO
            log.log(level, "%s: no looping route found on the road graph", a.agent_id)
        if not lst:
            raise ValueError(f"cannot find a route for {a.agent_id}")
        uniq: dict[tuple, Route] = {}
        for r in lst:
            uniq.setdefault(tuple(_edge_coverage(r, g)), r)
        cands[a.agent_id] = list(uniq.values())
        log.debug("%s: %d distinct candidate routes", a.agent_id, len(uniq))

    best: tuple[float, dict[str, Route]] | None = None
    shared_mode = bool(ugv)
    ids = [a.agent_id for a in uavs]
    covs_all = {
        k: [set(_edge_coverage(r, g, skip_first=CLIMB_M)) - {de_start} for r in cands[k]] for k in ids
    }
    lists_all = {k: [_edge_coverage(r, g) for r in cands[k]] for k in ids}
    orders = {k: [int(i) for i in rng.permutation(len(cands[k]))] for k in ids}

    def evaluate(sel: dict[str, int]) -> float:
        pick = {k: cands[k][i] for k, i in sel.items()}
        covs = {k: covs_all[k][i] for k, i in sel.items()}
        union = set().union(*covs.values()) if covs else set()
        score = 3.0 * len({de[0] for de in union})
        if not shared_mode:
            return score
        for x in range(len(ids)):
            for y in range(x + 1, len(ids)):
                kx, ky = ids[x], ids[y]
                n_shared = len(covs[kx] & covs[ky])
                score += min(n_shared, 3) - 2.0 * max(0, n_shared - 4)
                # flying the same edges at the same time is formation flight, not a crossing
                ca, cb = lists_all[kx][sel[kx]], lists_all[ky][sel[ky]]
                prefix = next(
                    (n for n, (u, v) in enumerate(zip(ca, cb, strict=False)) if u != v), min(len(ca), len(cb))
                )
                score -= 30.0 * max(0, prefix - 2)
        meet = _choose_meetings(pick, g, ugv_cov, de_start, facade)
        if len(meet) < 2:
            score -= 1000.0
        return score + 4.0 * len(meet) + 3.0 * sum(facade.get(pick[k].edges[i], False) for k, i in meet)

    n_eval = 0

    def search(depth: int, sel: dict[str, int]) -> None:
        nonlocal best, n_eval
        if n_eval >= n_trials:
            return
        if depth == len(ids):
            n_eval += 1
            sc = evaluate(sel)
            if best is None or sc > best[0]:
                best = (sc, {k: cands[k][i] for k, i in sel.items()})
            return
        k = ids[depth]
        for i in orders[k]:
            ok = True
            if shared_mode:
                for kk, j in sel.items():
                    sh = covs_all[k][i] & covs_all[kk][j]
                    if len(sh) < 2 or covs_all[k][i] == covs_all[kk][j]:
                        ok = False
                        break
            if ok:
                search(depth + 1, {**sel, k: i})

    search(0, {})
    if best is None and ids:  # no pairwise-feasible combination: take any
        best = (-2000.0, {k: cands[k][0] for k in ids})
    if best is not None and best[0] < 0:
        log.warning("UAV routes do not meet every crossing/meeting constraint (score %.1f)", best[0])
    uav_routes = best[1] if best is not None else {}

    # Meetings: up to 3 UGV segments flown low by a UAV (facade-facing first), keeping >= 2 crossings
    # per UAV pair.
    if ugv and uav_routes:
        low = _choose_meetings(uav_routes, g, ugv_cov, de_start, facade)
        for k, r in uav_routes.items():
            r.low_edges = sorted(i for kk, i in low if kk == k)
        meetings = [(k, uav_routes[k].edges[i]) for k, i in low]
        ids = list(uav_routes)

        def cruise(k: str) -> set[tuple[int, bool]]:
            bad = {j for i in uav_routes[k].low_edges for j in (i - 1, i, i + 1)}
            return {de for i, de, _ in _passes(uav_routes[k], g) if i not in bad and de != de_start}

        for i in range(len(ids)):
            for j in range(i + 1, len(ids)):
                crossings[(ids[i], ids[j])] = sorted(cruise(ids[i]) & cruise(ids[j]))
    routes.update(uav_routes)

    for k, r in routes.items():
        cov = _edge_coverage(r, g)
        loops[k] = sorted({de for de in cov if cov.count(de) > 1})

    # --- Geometry and timing.
    takeoffs = takeoff_plan(scenario)
    start_xy = None
    start_heading = 0.0
    for a in scenario.agents:
        r = routes[a.agent_id]
        # the vertical climb is part of the agent's path length, so its route is no longer than without it
        target = targets.get(a.agent_id, a.path_length_m) - takeoffs[a.agent_id].climb_m
        for _ in range(3):  # adjust the route length so that the smoothed 3D path has the target length
            pts3, spans, s = _agent_path(world, g, r, a, road_width, bool(ugv), takeoffs[a.agent_id].climb_m)
            l3 = float(np.sum(np.linalg.norm(np.diff(pts3, axis=0), axis=1)))
            if abs(l3 - target) < 0.05:
                break
            r.length += target - l3
            extend_to_length(r, g)
        if a.kind == "ugv":
            start_xy = pts3[0, :2].copy()
            d = pts3[min(8, len(pts3) - 1), :2] - pts3[0, :2]
            start_heading = float(np.arctan2(d[1], d[0]))
        meta = {"spans": spans, "xy_len": float(s[-1])}
        to = takeoffs[a.agent_id]
        climb = (to.climb_t, CLIMB_S, to.climb_m) if to.climb_m > 0 else None
        trajs[a.agent_id] = _make_trajectory(a, pts3, to.leave_t, r, meta, climb=climb)
    return TrajectoryPlan(
        trajs,
        g,
        np.zeros(2) if start_xy is None else start_xy,
        start_heading,
        routes,
        crossings,
        meetings,
        loops,
    )


__all__ = [
    "GRAVITY",
    "G_WORLD",
    "RoadGraph",
    "Route",
    "Trajectory",
    "TrajectoryPlan",
    "box_top",
    "build_road_graph",
    "inside_box_footprint",
    "plan_trajectories",
]
