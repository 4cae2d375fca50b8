"""The road graph the trajectories follow, and the geometry helpers over roads and buildings."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

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
