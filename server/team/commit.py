"""Goal commitment: which goal each agent holds from one auction to the next.

The seed (001, 4.2) auctions a set of frontier points once and lets every drone visit the points it won
before the next round. The server re-runs frontiers and auction every few seconds on a map that grows as
the agents move, so a plain re-auction hands an agent a different first goal each time, and it turns back
and forth covering nothing. An agent therefore keeps its first goal until it is reached, is no longer a
frontier (explored, by it or by another agent), the agent stands still short of it (its controller went as
near as the roads go, or gave up), or it stops getting nearer to it (a detour that does not end); only
then does it take a new one. A goal given up is not offered to the same agent again for a while. A goal
reached, or stood at, is not offered to anyone again: its agent has looked from there, and a frontier that
is still there afterwards faces space with nothing to map (the site's empty margin, where the map never
grows and the frontier would draw agents back for ever).

Times are the agent's mission time (its latest keyframe's timestamp), so the rules hold whatever pace the
agents run at.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from hivemap.server.team.options import AuctionOptions

F64 = NDArray[np.float64]


# the agent went there, or as near as it could: what it could see from there it has seen
VISITED = ("reached", "stopped short")


@dataclass(frozen=True)
class Held:
    """A goal an agent holds, in its map's frame."""

    map_id: int
    position: F64  # (3,) as it was assigned: the agent's kind's goal of the frontier
    best_dist: float  # the least horizontal distance the agent has come to it
    best_at: float  # mission time of that
    anchor: F64  # (3,) where the agent was when it last moved by held_progress_m
    moved_at: float  # mission time of that


@dataclass
class Commitments:
    """The goals the team holds, the ones each agent gave up lately, and the places visited."""

    held: dict[str, Held] = field(default_factory=dict)
    # agent id -> [(mission time dropped, map id, position)]
    dropped: dict[str, list[tuple[float, int, F64]]] = field(default_factory=dict)
    visited: list[tuple[int, F64]] = field(default_factory=list)  # (map id, goal position) reached
    reasons: dict[str, int] = field(default_factory=dict)  # why goals were dropped, counted

    def _drop(self, agent_id: str, h: Held, t: float, why: str) -> None:
        self.held.pop(agent_id, None)
        if why in VISITED:  # struck for everyone for good: no need to remember it for the agent too
            self.visited.append((h.map_id, h.position))
        else:
            self.dropped.setdefault(agent_id, []).append((t, h.map_id, h.position))
        self.reasons[why] = self.reasons.get(why, 0) + 1

    def struck(self, agent_id: str, map_id: int, t: float, options: AuctionOptions) -> F64:
        """(K, 2) where in its map the agent may not be sent: the goals it gave up within the memory
        (older ones are forgotten) and every goal the team visited."""
        keep = [e for e in self.dropped.get(agent_id, []) if t - e[0] <= options.dropped_memory_s]
        self.dropped[agent_id] = keep
        pts = [p[:2] for _, m, p in keep if m == map_id] + [p[:2] for m, p in self.visited if m == map_id]
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def match(
        self,
        agent_id: str,
        map_id: int,
        position: F64,
        t: float,
        candidates: Sequence[tuple[int, F64]],
        options: AuctionOptions,
    ) -> int | None:
        """The frontier (an index of ``candidates``' first entries) that stands for the agent's held goal,
        or None when it holds none or has just dropped it (reached, stopped short, no progress, explored,
        another map).

        ``candidates``: (frontier index, the agent's kind's goal (3,)) of the frontiers it may take."""
        h = self.held.get(agent_id)
        if h is None:
            return None
        if h.map_id != map_id:  # merged into another map: the position is in a frame that is gone
            self.held.pop(agent_id)
            self.reasons["map changed"] = self.reasons.get("map changed", 0) + 1
            return None
        dist = float(np.linalg.norm(h.position[:2] - position[:2]))
        if dist < options.held_reached_m:
            self._drop(agent_id, h, t, "reached")
            return None
        if np.linalg.norm(position - h.anchor) > options.held_progress_m:
            h = replace(h, anchor=np.asarray(position, dtype=np.float64).copy(), moved_at=t)
        elif t - h.moved_at > options.held_idle_s:
            self._drop(agent_id, h, t, "stopped short")
            return None
        if dist < h.best_dist - options.held_progress_m:
            h = replace(h, best_dist=dist, best_at=t)
        elif t - h.best_at > options.held_stall_s:
            self._drop(agent_id, h, t, "no progress")
            return None
        self.held[agent_id] = h
        if not candidates:
            self._drop(agent_id, h, t, "explored")
            return None
        d = [float(np.linalg.norm(g[:2] - h.position[:2])) for _, g in candidates]
        k = int(np.argmin(d))
        if d[k] > options.held_match_m:
            self._drop(agent_id, h, t, "explored")
            return None
        return candidates[k][0]

    def hold(self, agent_id: str, map_id: int, goal: F64, position: F64, t: float) -> None:
        """The agent takes ``goal`` (3,) as its new held goal."""
        dist = float(np.linalg.norm(goal[:2] - position[:2]))
        here = np.asarray(position, dtype=np.float64).copy()
        self.held[agent_id] = Held(map_id, np.asarray(goal, dtype=np.float64).copy(), dist, t, here, t)
