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
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, CubicSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from hivemap.sim.scenarios import (
    UAV_LOW_HEIGHT,
    UGV_BODY_HEIGHT,
    UGV_ROOF_HEIGHT,
    AgentSpec,
    Scenario,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
GRAVITY = 9.81
G_WORLD = np.array([0.0, 0.0, -GRAVITY])  # gravity vector in the world frame (z up)
UAV_GROUND_HEIGHT = 0.25  # UAV body height when standing on the ground (disjoint scenario)

# ---------------------------------------------------------------------------------------------
# Road graph
# ---------------------------------------------------------------------------------------------


@dataclass
class RoadEdge:
    id: int
    u: int
    v: int
    pts: F64  # (K, 2) geometry from node u to node v
    length: float


@dataclass
class RoadGraph:
    """Road network: nodes (N, 2) and edges with geometry. A directed edge is ``(edge_id, forward)``."""

    nodes: F64
    edges: list[RoadEdge]
    adj: dict[int, list[tuple[int, bool]]] = field(default_factory=dict)  # node -> outgoing directed edges
    air: set[int] = field(default_factory=set)  # edges off the roads (UAV only: across blocks, over roofs)

    @property
    def road_edges(self) -> set[int]:
        return {e.id for e in self.edges} - self.air

    def start_node(self, de: tuple[int, bool]) -> int:
        e = self.edges[de[0]]
        return e.u if de[1] else e.v

    def end_node(self, de: tuple[int, bool]) -> int:
        e = self.edges[de[0]]
        return e.v if de[1] else e.u

    def geometry(self, de: tuple[int, bool]) -> F64:
        e = self.edges[de[0]]
        return e.pts if de[1] else e.pts[::-1]

    def length(self, de: tuple[int, bool]) -> float:
        return self.edges[de[0]].length

    def degree(self, n: int) -> int:
        return len(self.adj.get(n, []))


def _seg_intersection(p: F64, p2: F64, q: F64, q2: F64) -> tuple[float, float] | None:
    r = p2 - p
    s = q2 - q
    den = r[0] * s[1] - r[1] * s[0]
    if abs(den) < 1e-12:
        return None
    qp = q - p
    t = (qp[0] * s[1] - qp[1] * s[0]) / den
    u = (qp[0] * r[1] - qp[1] * r[0]) / den
    eps = 1e-9
    if -eps <= t <= 1 + eps and -eps <= u <= 1 + eps:
        return float(np.clip(t, 0, 1)), float(np.clip(u, 0, 1))
    return None


def build_road_graph(roads: list[Any], snap_tol: float = 4.0, merge_tol: float = 1.0) -> RoadGraph:
    """Graph of road centre polylines (list of (K, 2) arrays).

    Polylines are split where they cross; a polyline end within ``snap_tol`` of another road is snapped
    onto it (T-junction). Split points closer than ``merge_tol`` become one node.
    """
    polys = [np.asarray(r, dtype=np.float64)[:, :2].copy() for r in roads if len(r) >= 2]
    # Snap free ends onto other roads (T-junctions).
    for i, P in enumerate(polys):
        for end in (0, -1):
            e = P[end]
            best: tuple[float, F64] | None = None
            for j, Q in enumerate(polys):
                if j == i:
                    continue
                for k in range(len(Q) - 1):
                    a, b = Q[k], Q[k + 1]
                    ab = b - a
                    t = float(np.clip(np.dot(e - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1))
                    c = a + t * ab
                    d = float(np.linalg.norm(e - c))
                    if d < snap_tol and (best is None or d < best[0]):
                        best = (d, c)
            if best is not None and best[0] > 1e-6:
                P[end] = best[1]
    # Split parameters per polyline: (segment index, t, point).
    splits: list[list[tuple[int, float, F64]]] = [[(0, 0.0, P[0]), (len(P) - 2, 1.0, P[-1])] for P in polys]
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            P, Q = polys[i], polys[j]
            for a in range(len(P) - 1):
                for b in range(len(Q) - 1):
                    r = _seg_intersection(P[a], P[a + 1], Q[b], Q[b + 1])
                    if r is None:
                        continue
                    x = P[a] + r[0] * (P[a + 1] - P[a])
                    splits[i].append((a, r[0], x))
                    splits[j].append((b, r[1], x))
    node_pts: list[F64] = []

    def node_of(x: F64) -> int:
        for n, y in enumerate(node_pts):
            if np.linalg.norm(x - y) < merge_tol:
                return n
        node_pts.append(np.asarray(x, dtype=np.float64))
        return len(node_pts) - 1

    edges: list[RoadEdge] = []
    for i, P in enumerate(polys):
        sp = sorted(splits[i], key=lambda s: (s[0], s[1]))
        for (a0, _t0, x0), (a1, _t1, x1) in zip(sp[:-1], sp[1:], strict=True):
            pts = [x0] + [P[k] for k in range(a0 + 1, a1 + 1)] + [x1]
            geo = np.asarray(pts)
            keep = np.concatenate([[True], np.linalg.norm(np.diff(geo, axis=0), axis=1) > 1e-6])
            geo = geo[keep]
            length = float(np.sum(np.linalg.norm(np.diff(geo, axis=0), axis=1)))
            if length < merge_tol:
                continue
            u, v = node_of(x0), node_of(x1)
            if u == v:
                continue
            geo[0], geo[-1] = node_pts[u], node_pts[v]
            edges.append(RoadEdge(len(edges), u, v, geo, length))
    g = RoadGraph(np.asarray(node_pts).reshape(-1, 2), edges)
    for e in edges:
        g.adj.setdefault(e.u, []).append((e.id, True))
        g.adj.setdefault(e.v, []).append((e.id, False))
    return g


def _air_polylines(g: RoadGraph) -> list[F64]:
    """Straight lines across every 4-sided block, joining the midpoints of opposite sides ('+' shape)."""
    seen: set[frozenset[int]] = set()
    out: list[F64] = []
    for e in g.edges:
        for de in ((e.id, True), (e.id, False)):
            for cyc in _cycles_through(g, de, 200.0, 4):
                key = frozenset(x[0] for x in cyc)
                if len(cyc) != 4 or key in seen:
                    continue
                seen.add(key)
                mids = []
                for x in cyc:
                    geo = g.geometry(x)
                    seg = np.linalg.norm(np.diff(geo, axis=0), axis=1)
                    sc = np.concatenate([[0.0], np.cumsum(seg)])
                    h = sc[-1] / 2
                    mids.append(np.array([np.interp(h, sc, geo[:, 0]), np.interp(h, sc, geo[:, 1])]))
                out.append(np.stack([mids[0], mids[2]]))
                out.append(np.stack([mids[1], mids[3]]))
    return out


def _with_air_edges(g: RoadGraph, roads: list[F64], snap: float, road_width: float) -> RoadGraph:
    """Road graph plus the UAV-only air lines across blocks (marked in ``RoadGraph.air``)."""
    air = _air_polylines(g)
    if not air:
        return g
    g2 = build_road_graph(roads + air, snap_tol=snap)
    segs = [
        (np.asarray(r, dtype=np.float64)[k], np.asarray(r, dtype=np.float64)[k + 1])
        for r in roads
        for k in range(len(r) - 1)
    ]
    for e in g2.edges:
        seg = np.linalg.norm(np.diff(e.pts, axis=0), axis=1)
        sc = np.concatenate([[0.0], np.cumsum(seg)])
        mid = np.array([np.interp(sc[-1] / 2, sc, e.pts[:, 0]), np.interp(sc[-1] / 2, sc, e.pts[:, 1])])
        dmin = min(_point_seg_dist(mid, a, b) for a, b in segs)
        if dmin > road_width / 2:
            g2.air.add(e.id)
    return g2


def _point_seg_dist(p: F64, a: F64, b: F64) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def _turn_ok(g: RoadGraph, a: tuple[int, bool], b: tuple[int, bool], min_angle_deg: float = 60.0) -> bool:
    """Whether going from directed edge a into b is not (nearly) a U-turn."""
    if a[0] == b[0]:
        return False
    ga, gb = g.geometry(a), g.geometry(b)
    da = ga[-1] - ga[-2]
    db = gb[1] - gb[0]
    c = float(np.dot(da, db) / (np.linalg.norm(da) * np.linalg.norm(db) + 1e-12))
    return c > np.cos(np.deg2rad(180.0 - min_angle_deg))


def _cycles_through(
    g: RoadGraph, de0: tuple[int, bool], max_len: float, max_edges: int = 10, allowed: set[int] | None = None
) -> list[list]:
    """Simple directed cycles starting with ``de0`` (no U-turns), length <= max_len."""
    out: list[list] = []
    start = g.start_node(de0)

    def dfs(path: list[tuple[int, bool]], visited: set[int], length: float) -> None:
        last = path[-1]
        n = g.end_node(last)
        if n == start:
            if _turn_ok(g, last, path[0]):
                out.append(list(path))
            return
        if len(path) >= max_edges:
            return
        for de in g.adj.get(n, []):
            m = g.end_node(de)
            if (m in visited and m != start) or not _turn_ok(g, last, de):
                continue
            if allowed is not None and de[0] not in allowed:
                continue
            nl = length + g.length(de)
            if nl > max_len:
                continue
            dfs([*path, de], visited | {m}, nl)

    dfs([de0], {start, g.end_node(de0)}, g.length(de0))
    return out


# ---------------------------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------------------------


def _box_local(box: Any, xy: F64) -> F64:
    c = np.asarray(box.center, dtype=np.float64)
    yaw = float(getattr(box, "yaw", 0.0))
    d = xy - c[:2]
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.stack([cy * d[..., 0] + sy * d[..., 1], -sy * d[..., 0] + cy * d[..., 1]], axis=-1)


def inside_box_footprint(box: Any, xy: F64, margin: float = 0.0) -> NDArray[np.bool_]:
    """Mask of points (N, 2) inside the box's footprint grown by ``margin``."""
    loc = _box_local(box, np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    half = np.asarray(box.size, dtype=np.float64)[:2] / 2 + margin
    return np.all(np.abs(loc) <= half, axis=1)


def box_top(box: Any) -> float:
    return float(np.asarray(box.center)[2] + np.asarray(box.size)[2] / 2)


def _ray_hits_building(world: Any, origin: F64, direction: F64, max_dist: float) -> float | None:
    """Distance along a horizontal ray to the first building footprint (sampled every 0.5 m)."""
    d = direction / (np.linalg.norm(direction) + 1e-12)
    s = np.arange(0.5, max_dist, 0.5)
    pts = origin[None, :] + s[:, None] * d[None, :]
    best = None
    for b in getattr(world, "buildings", []):
        m = inside_box_footprint(b, pts)
        if m.any():
            dist = float(s[np.argmax(m)])
            best = dist if best is None else min(best, dist)
    return best


def _fillet(poly: F64, max_radius: float, max_cut: float, step: float = 0.25) -> F64:
    """Replace the corners of a polyline with circular arcs (tangent lengths capped by the segments)."""
    pts = [poly[0]]
    n = len(poly)
    for i in range(1, n - 1):
        A, B, C = poly[i - 1], poly[i], poly[i + 1]
        d1 = A - B
        d2 = C - B
        l1, l2 = np.linalg.norm(d1), np.linalg.norm(d2)
        if l1 < 1e-9 or l2 < 1e-9:
            continue
        d1, d2 = d1 / l1, d2 / l2
        phi = float(np.arccos(np.clip(np.dot(d1, d2), -1, 1)))  # interior angle
        if phi > np.deg2rad(179.0):
            pts.append(B)
            continue
        r = max_radius
        cut_factor = 1 / np.sin(phi / 2) - 1
        if cut_factor > 1e-9:
            r = min(r, max_cut / cut_factor)
        tan_len = r / np.tan(phi / 2)
        cap = 0.45 * min(l1, l2)
        if tan_len > cap:
            tan_len = cap
            r = tan_len * np.tan(phi / 2)
        T1, T2 = B + d1 * tan_len, B + d2 * tan_len
        bis = d1 + d2
        bis /= np.linalg.norm(bis)
        centre = B + bis * r / np.sin(phi / 2)
        a1 = np.arctan2(*(T1 - centre)[::-1])
        a2 = np.arctan2(*(T2 - centre)[::-1])
        da = (a2 - a1 + np.pi) % (2 * np.pi) - np.pi
        k = max(2, int(np.ceil(abs(da) * r / step)))
        ang = a1 + da * np.linspace(0, 1, k)
        pts.extend(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    pts.append(poly[-1])
    return np.asarray(pts)


def _resample(poly: F64, step: float) -> tuple[F64, F64]:
    """Uniform resampling of a polyline by arc length -> (points (M, D), arc length (M,))."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly = poly[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    m = max(2, int(np.ceil(s[-1] / step)) + 1)
    si = np.linspace(0, s[-1], m)
    out = np.stack([np.interp(si, s, poly[:, d]) for d in range(poly.shape[1])], axis=1)
    return out, si


def _smoothstep5(x: F64) -> F64:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _smoothstep5_integral(x: F64) -> F64:
    """Integral of smoothstep5 from 0 to x (x in [0, 1]); equals 0.5 at 1."""
    x = np.clip(x, 0.0, 1.0)
    return x**6 - 3 * x**5 + 2.5 * x**4


# ---------------------------------------------------------------------------------------------
# Routes
# ---------------------------------------------------------------------------------------------


@dataclass
class Route:
    """A walk on the road graph: directed edges, start offset on the first, total length (m)."""

    edges: list[tuple[int, bool]]
    start_offset: float
    length: float
    low_edges: list[int] = field(default_factory=list)  # indices into ``edges`` flown low (meetings)

    def polyline(self, g: RoadGraph) -> tuple[F64, list[tuple[float, float]]]:
        """XY polyline of the route and the [s0, s1] arc-length span of each edge occurrence."""
        pts: list[F64] = []
        spans: list[tuple[float, float]] = []
        s_acc = -self.start_offset
        for de in self.edges:
            geo = g.geometry(de)
            pts.append(geo if not pts else geo[1:])
            L = g.length(de)
            spans.append((s_acc, s_acc + L))
            s_acc += L
        poly = np.concatenate(pts, axis=0)
        # Trim to [start_offset, start_offset + length].
        seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        a, b = self.start_offset, self.start_offset + self.length
        if b > s[-1] + 1e-6:
            raise ValueError(f"route too short: {s[-1]:.1f} m < {b:.1f} m")
        inner = (s > a) & (s < b)
        start = np.array([np.interp(a, s, poly[:, 0]), np.interp(a, s, poly[:, 1])])
        end = np.array([np.interp(b, s, poly[:, 0]), np.interp(b, s, poly[:, 1])])
        return np.concatenate([start[None], poly[inner], end[None]]), spans


CLIMB_M = 20.0  # a UAV's first metres are its take-off climb: no crossing/meeting/loop counts there


def _edge_coverage(
    route: Route, g: RoadGraph, min_cover: float = 8.0, skip_first: float = 0.0
) -> list[tuple[int, bool]]:
    """Directed edges of the route travelled for at least ``min_cover`` metres (in order), ignoring
    passes that start within the first ``skip_first`` metres."""
    out = []
    s_acc = -route.start_offset
    for de in route.edges:
        L = g.length(de)
        lo, hi = max(s_acc, 0.0), min(s_acc + L, route.length)
        if hi - lo >= min(min_cover, 0.8 * L) and lo >= skip_first:
            out.append(de)
        s_acc += L
    return out


def _random_walk(
    g: RoadGraph, de0: tuple[int, bool], start_offset: float, length: float, rng: np.random.Generator,
    allowed: set[int] | None = None, follow: dict[tuple[int, bool], tuple[int, bool]] | None = None,
    p_follow: float = 0.0,
) -> Route | None:  # fmt: skip
    """Random non-U-turn walk; on an edge of ``follow`` (e.g. the UGV's route) it takes the same next
    edge with probability ``p_follow``."""
    edges = [de0]
    total = g.length(de0) - start_offset
    while total < 1.1 * length + 3.0:
        last = edges[-1]
        opts = [de for de in g.adj.get(g.end_node(last), []) if _turn_ok(g, last, de)]
        if allowed is not None:
            opts = [de for de in opts if de[0] in allowed]
        if not opts:
            return None
        nxt = follow.get(last) if follow else None
        if nxt is not None and nxt in opts and rng.random() < p_follow:
            de = nxt
        else:
            de = opts[int(rng.integers(len(opts)))]
        edges.append(de)
        total += g.length(de)
    return Route(edges, start_offset, length)


def _repeated_edges(route: Route, g: RoadGraph, climb: float = CLIMB_M) -> set[tuple[int, bool]]:
    """Directed edges travelled twice (>= 8 m each time), not counting passes that start within the
    first ``climb`` metres (the take-off climb)."""
    seen: list[tuple[int, bool]] = []
    s_acc = -route.start_offset
    for de in route.edges:
        L = g.length(de)
        lo, hi = max(s_acc, 0.0), min(s_acc + L, route.length)
        if hi - lo >= min(8.0, 0.8 * L) and lo >= climb:
            seen.append(de)
        s_acc += L
    return {de for de in seen if seen.count(de) > 1}


def _has_self_loop(route: Route, g: RoadGraph) -> bool:
    return bool(_repeated_edges(route, g))


# ---------------------------------------------------------------------------------------------
# Trajectory
# ---------------------------------------------------------------------------------------------


def _hat(w: F64) -> F64:
    """(N, 3) -> (N, 3, 3) skew matrices."""
    z = np.zeros(w.shape[0])
    return np.stack(
        [
            np.stack([z, -w[:, 2], w[:, 1]], 1),
            np.stack([w[:, 2], z, -w[:, 0]], 1),
            np.stack([-w[:, 1], w[:, 0], z], 1),
        ],
        axis=1,
    )


def _normalize_with_rate(v: F64, vdot: F64) -> tuple[F64, F64]:
    """n = v / |v| and its time derivative (I - n n^T) vdot / |v|, row-wise."""
    nrm = np.linalg.norm(v, axis=1, keepdims=True)
    n = v / nrm
    ndot = (vdot - n * np.sum(n * vdot, axis=1, keepdims=True)) / nrm
    return n, ndot


@dataclass
class Trajectory:
    """True motion of one agent, t in seconds from the scenario start (t = 0 .. duration).

    ``position`` / ``velocity`` / ``acceleration`` are world-frame (z up); ``rotation`` is
    world_from_body (body x forward, y left, z up); ``angular_velocity`` is in the body frame. All
    accept a scalar or an array of times and return (N, ...) arrays (N = 1 for a scalar).
    """

    agent_id: str
    kind: str
    pos: BSpline  # t -> (3,)
    yaw: BSpline  # t -> heading (rad, unwrapped), body x axis azimuth from east
    thrust_aligned: bool  # UAV: body z along a - g
    duration: float
    route: Route | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    move_span: tuple[float, float] = (0.0, float("inf"))  # exactly at rest outside this interval

    def _ev(self, spline: BSpline, t: float | F64, nu: int = 0) -> F64:
        tt = self._t(t)
        a, b = self.move_span
        out = np.asarray(spline(np.clip(tt, a, b), nu))
        if nu > 0:
            out[(tt < a) | (tt > b)] = 0.0
        return out

    def _t(self, t: float | F64) -> F64:
        return np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), 0.0, self.duration)

    def position(self, t: float | F64) -> F64:
        return self._ev(self.pos, t)

    def velocity(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 1)

    def acceleration(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 2)

    def jerk(self, t: float | F64) -> F64:
        return self._ev(self.pos, t, 3)

    def _attitude(self, t: float | F64) -> tuple[F64, F64]:
        """(R (N,3,3) world_from_body, omega_body (N,3)) computed analytically."""
        tt = self._t(t)
        n = len(tt)
        psi = self._ev(self.yaw, tt)
        psid = self._ev(self.yaw, tt, 1)
        if self.thrust_aligned:
            zt = self.acceleration(tt) - G_WORLD[None, :]
            ztd = self.jerk(tt)
        else:
            zt = np.tile([0.0, 0.0, 1.0], (n, 1))
            ztd = np.zeros((n, 3))
        zb, zbd = _normalize_with_rate(zt, ztd)
        xc = np.stack([np.cos(psi), np.sin(psi), np.zeros(n)], axis=1)
        xcd = psid[:, None] * np.stack([-np.sin(psi), np.cos(psi), np.zeros(n)], axis=1)
        yt = np.cross(zb, xc)
        ytd = np.cross(zbd, xc) + np.cross(zb, xcd)
        yb, ybd = _normalize_with_rate(yt, ytd)
        xb = np.cross(yb, zb)
        xbd = np.cross(ybd, zb) + np.cross(yb, zbd)
        R = np.stack([xb, yb, zb], axis=2)
        Rd = np.stack([xbd, ybd, zbd], axis=2)
        W = np.einsum("nji,njk->nik", R, Rd)  # R^T Rdot = hat(omega_body)
        omega = 0.5 * np.stack(
            [W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1
        )
        return R, omega

    def rotation(self, t: float | F64) -> F64:
        return self._attitude(t)[0]

    def angular_velocity(self, t: float | F64) -> F64:
        """Body-frame angular rate (N, 3), rad/s (what a gyroscope measures, noise-free)."""
        return self._attitude(t)[1]

    def specific_force(self, t: float | F64) -> F64:
        """Body-frame specific force R^T (a - g) (N, 3), m/s^2 (what an accelerometer measures)."""
        R = self.rotation(t)
        return np.einsum("nji,nj->ni", R, self.acceleration(t) - G_WORLD[None, :])

    def world_from_body(self, t: float | F64) -> F64:
        """(N, 4, 4) poses; for a scalar t use ``[0]``."""
        tt = self._t(t)
        T = np.tile(np.eye(4), (len(tt), 1, 1))
        T[:, :3, :3] = self.rotation(tt)
        T[:, :3, 3] = self.position(tt)
        return T

    def path_length(self, t_end: float | None = None, dt: float = 0.01) -> float:
        """Travelled distance (3D) from 0 to t_end (default: the whole trajectory)."""
        te = self.duration if t_end is None else min(t_end, self.duration)
        tt = np.arange(0.0, te + dt / 2, dt)
        sp = np.linalg.norm(self.velocity(tt), axis=1)
        return float(np.trapezoid(sp, tt))


def _speed_profile(length: float, v: float, hold: float, t_acc: float, hold_end: float = 1.0):
    """Arc length s(t) for: rest ``hold`` s, smooth ramp to v in t_acc, cruise, ramp down, rest."""
    t_acc = min(t_acc, length / v)
    t_cruise = length / v - t_acc
    T = hold + 2 * t_acc + t_cruise + hold_end

    def s_of_t(t: F64) -> F64:
        t = np.asarray(t, dtype=np.float64)
        s = np.zeros_like(t)
        x1 = (t - hold) / t_acc
        s += np.where(t > hold, v * t_acc * _smoothstep5_integral(x1), 0.0)
        t2 = hold + t_acc
        s += np.where(t > t2, v * np.clip(t - t2, 0, t_cruise), 0.0)
        t3 = t2 + t_cruise
        x3 = (t - t3) / t_acc
        s += np.where(t > t3, v * (np.clip(x3, 0, 1) - _smoothstep5_integral(x3)) * t_acc, 0.0)
        return np.minimum(s, length)

    return s_of_t, T


def _make_trajectory(
    spec: AgentSpec,
    pts3: F64,
    hold: float,
    route: Route | None,
    meta: dict[str, Any],
    knot_dt: float = 0.2,
) -> Trajectory:
    """Time-parameterise a dense smooth 3D path (M, 3) into a Trajectory."""
    seg = np.linalg.norm(np.diff(pts3, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts3 = pts3[keep]
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts3, axis=0), axis=1))])
    path = CubicSpline(u, pts3, axis=0)
    L = float(u[-1])
    t_acc = 4.0
    s_of_t, T = _speed_profile(L, spec.speed_mps, hold, t_acc)
    t_a, t_b = hold, T - 1.0  # moving interval (rest before and after)
    n = int(np.ceil((t_b - t_a) / knot_dt))
    tk = np.linspace(t_a, t_b, n + 1)
    sk = s_of_t(tk)
    Xk = path(sk)
    z3 = np.zeros(3)
    pos = make_interp_spline(tk, Xk, k=5, bc_type=([(1, z3), (2, z3)], [(1, z3), (2, z3)]))
    tan = path(sk, 1)
    psi = np.unwrap(np.arctan2(tan[:, 1], tan[:, 0]))
    if spec.kind == "uav":
        psi = gaussian_filter1d(psi, sigma=0.4 / knot_dt, mode="nearest")
    z1 = np.zeros(1)
    yaw = make_interp_spline(tk, psi, k=5, bc_type=([(1, z1), (2, z1)], [(1, z1), (2, z1)]))
    uav = spec.kind == "uav"
    return Trajectory(spec.agent_id, spec.kind, pos, yaw, uav, float(T), route, meta, (t_a, t_b))


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
    world: Any, g: RoadGraph, r: Route, a: AgentSpec, road_width: float, with_ugv: bool
) -> tuple[F64, list[tuple[float, float]], F64]:
    """Dense smooth 3D path (M, 3) of one agent, the edge spans and the xy arc length."""
    xy, s, spans = _xy_path(r, g, road_width)
    if a.kind == "ugv":
        z = np.full(len(s), UGV_BODY_HEIGHT)
    else:
        z_start = UGV_ROOF_HEIGHT + 0.1 if with_ugv else UAV_GROUND_HEIGHT
        low_spans = [spans[i] for i in r.low_edges]
        idx = int(a.agent_id[-1]) if a.agent_id[-1].isdigit() else 0
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
    start_xy = None
    start_heading = 0.0
    for a in scenario.agents:
        r = routes[a.agent_id]
        target = targets.get(a.agent_id, a.path_length_m)
        for _ in range(3):  # adjust the route length so that the smoothed 3D path has the target length
            pts3, spans, s = _agent_path(world, g, r, a, road_width, bool(ugv))
            l3 = float(np.sum(np.linalg.norm(np.diff(pts3, axis=0), axis=1)))
            if abs(l3 - target) < 0.05:
                break
            r.length += target - l3
        if a.kind == "ugv":
            start_xy = pts3[0, :2].copy()
            d = pts3[min(8, len(pts3) - 1), :2] - pts3[0, :2]
            start_heading = float(np.arctan2(d[1], d[0]))
        meta = {"spans": spans, "xy_len": float(s[-1])}
        trajs[a.agent_id] = _make_trajectory(a, pts3, scenario.hold_s, r, meta)
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
