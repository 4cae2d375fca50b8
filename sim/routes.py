"""Routes: walks on the road graph, and what they cover (repeated edges, self-loops)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hivemap.sim.roads import RoadGraph, _turn_ok

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

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


def extend_to_length(route: Route, g: RoadGraph) -> None:
    """Append edges (no U-turns; the first allowed continuation, so no random draw changes the other
    agents' routes) while the route's edges hold less than ``start_offset + length``: the 3D length
    fit can ask a walk for more than it was drawn with. At a dead end it stops (``polyline`` says)."""
    total = sum(g.length(de) for de in route.edges)
    while total < route.start_offset + route.length:
        last = route.edges[-1]
        opts = [de for de in g.adj.get(g.end_node(last), []) if _turn_ok(g, last, de)]
        if not opts:
            return
        route.edges.append(opts[0])
        total += g.length(opts[0])


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
