"""Sequential single-item (SSI) auction of goals to agents (seed 001, 4.2).

Every round each agent bids on every goal it may take the path cost it would add: the least increase of
its tour (start, then the goals it has won, visited in order; straight-line distances, as in the seed,
since the server has no planner) over every place the goal could be inserted. The lowest bid of the round
wins; that goal is inserted into the winner's tour where its bid said. Rounds go on until every goal is
won or no agent may take more (a per-agent cap). Ties go to the earlier agent, then the earlier goal,
then the insertion nearer the tour's end, so the result is deterministic.

An agent may enter the auction holding a goal (``first``): it stays the first stop of its tour and every
later goal is bid for after it. The seed auctions its points once and lets each drone finish its goals
before the next round; re-run from scratch every few seconds on a growing map, the auction hands an agent a
new first goal each time and it turns back and forth (:mod:`.commit` decides what an agent holds).

The uncertainty-aware variant subtracts a value from each bid (``value(agent, goal)``, in metres): with
:func:`d_optimal_gain` it is a proxy of the expected uncertainty reduction (seed 002 chooses targets by
D-optimality; its virtual-landmark EM over the map is not implemented here).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Value = Callable[[int, int], float]


@dataclass(frozen=True)
class Bid:
    round: int
    agent: int
    goal: int
    bid: float  # the winning bid (added path cost less the value, metres)
    added_cost: float  # metres
    position: int  # where in the agent's tour the goal went


@dataclass
class AuctionResult:
    tours: list[list[int]]  # per agent: goal indices in visiting order
    costs: list[float]  # per agent: path length of its tour (metres)
    won: list[Bid] = field(default_factory=list)  # one per round, in order
    unassigned: list[int] = field(default_factory=list)


def _insertion(start: F64, tour: list[int], goals: F64, g: int, lo: int = 0) -> tuple[float, int]:
    """(least added length, insertion index >= ``lo``) of goal ``g`` into the open path start -> tour."""
    p = goals[g]
    stops = [start, *(goals[i] for i in tour)]
    best = float(np.linalg.norm(p - stops[-1]))
    best_pos = len(tour)
    # inserting before tour[k], i.e. between stops[k] and stops[k + 1]
    for k in range(len(tour) - 1, lo - 1, -1):
        a, b = stops[k], stops[k + 1]
        added = float(np.linalg.norm(p - a) + np.linalg.norm(b - p) - np.linalg.norm(b - a))
        if added < best - 1e-12:
            best, best_pos = added, k
    return best, best_pos


def path_length(start: F64, tour: Sequence[int], goals: F64) -> float:
    pts = np.vstack([start[None, :], goals[list(tour)]]) if len(tour) else start[None, :]
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def ssi_auction(
    starts: F64,
    goals: F64,
    *,
    allowed: NDArray[np.bool_] | None = None,
    cap: int = 0,
    value: Value | None = None,
    first: Sequence[int | None] | None = None,
) -> AuctionResult:
    """Assign ``goals`` (G, D) to agents starting at ``starts`` (A, D).

    ``allowed`` (A, G): which agent may take which goal (reachability; default all); ``cap``: at most this
    many goals per agent (0: no cap); ``value(agent, goal)``: metres subtracted from that bid (the
    uncertainty-aware variant; default none); ``first[a]``: a goal agent ``a`` holds, the first stop of its
    tour, not auctioned (a held goal counts towards the cap)."""
    starts = np.asarray(starts, dtype=np.float64)
    goals = np.asarray(goals, dtype=np.float64)
    n_agents, n_goals = len(starts), len(goals)
    ok = np.ones((n_agents, n_goals), bool) if allowed is None else np.asarray(allowed, bool)
    held = list(first) if first is not None else [None] * n_agents
    if len(held) != n_agents:
        raise ValueError(f"first: {len(held)} entries for {n_agents} agents")
    tours: list[list[int]] = [[] if h is None else [h] for h in held]
    lo = [0 if h is None else 1 for h in held]
    taken = {h for h in held if h is not None}
    if len(taken) != n_agents - held.count(None):
        raise ValueError("first: two agents hold one goal")
    open_goals = [g for g in range(n_goals) if g not in taken]
    won: list[Bid] = []
    while open_goals:
        best: tuple[float, int, int, float, int] | None = None
        for a in range(n_agents):
            if cap and len(tours[a]) >= cap:
                continue
            for g in open_goals:
                if not ok[a, g]:
                    continue
                added, pos = _insertion(starts[a], tours[a], goals, g, lo[a])
                bid = added - (value(a, g) if value is not None else 0.0)
                if best is None or bid < best[0] - 1e-12:
                    best = (bid, a, g, added, pos)
        if best is None:
            break
        bid, a, g, added, pos = best
        tours[a].insert(pos, g)
        open_goals.remove(g)
        won.append(Bid(len(won), a, g, bid, added, pos))
    costs = [path_length(starts[a], tours[a], goals) for a in range(n_agents)]
    return AuctionResult(tours, costs, won, open_goals)


def d_optimal_gain(position_cov: F64, n_fixes: int, fix_sigma: float) -> float:
    """Expected uncertainty reduction (nats) of an agent's position when it observes ``n_fixes`` mapped
    points: ``0.5 * (log det P - log det P')`` with ``P' = (P^-1 + n / sigma^2 I)^-1``, each point taken as
    an independent isotropic position fix of ``fix_sigma``. A proxy of the D-optimality criterion: large
    for an uncertain agent going where the map is dense, zero for a goal without points."""
    P = np.asarray(position_cov, dtype=np.float64)
    if n_fixes <= 0:
        return 0.0
    info = np.linalg.inv(P) + (n_fixes / fix_sigma**2) * np.eye(len(P))
    _, logdet_p = np.linalg.slogdet(P)
    _, logdet_info = np.linalg.slogdet(info)
    # log det P' = -log det info
    return float(0.5 * (logdet_p + logdet_info))
