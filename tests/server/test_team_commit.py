"""Goal commitment: an agent keeps the goal it won while the map grows around it, and gives it up only when
it is reached, explored, or out of reach (hand-made frontiers, the service's assignment step)."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.server.team.auction import ssi_auction
from hivemap.server.team.frontiers import Frontier, FrontierResult
from hivemap.server.team.options import AuctionOptions, TeamOptions
from hivemap.server.team.service import TeamService, _AgentSnap


def _frontiers(*xy: tuple[float, float]) -> FrontierResult:
    fs = [
        Frontier(i, np.array([x, y, 0.0]), 10, ("ugv",), {"ugv": np.array([x, y, 0.0])})
        for i, (x, y) in enumerate(xy)
    ]
    return FrontierResult(fs, (0.0, 0.0, 0.0), 100, np.zeros((0, 3)))


def _ugv(x: float, y: float, t: float) -> _AgentSnap:
    return _AgentSnap("ugv", "ugv", 0, np.array([x, y, 0.0]), np.zeros(3), t)


def _first_goal(svc: TeamService, fr: FrontierResult, agent: _AgentSnap) -> list[float]:
    out = svc._assign(0, fr, [agent], [svc._covariance(agent.agent_id)])
    return out.agents[0].goal_positions[0][:2]


def test_auction_keeps_a_held_goal_first_and_bids_after_it() -> None:
    # agent 0 holds goal 2 at (10, 0); goal 0 at (1, 0) would be its cheapest first stop, but it goes after
    starts = np.array([[0.0, 0.0], [20.0, 0.0]])
    goals = np.array([[1.0, 0.0], [11.0, 0.0], [10.0, 0.0]])
    r = ssi_auction(starts, goals, first=[2, None])
    assert r.tours[0][0] == 2
    assert set(r.tours[0]) | set(r.tours[1]) == {0, 1, 2}
    assert 2 not in [b.goal for b in r.won]  # held, not auctioned
    # without the hold, agent 0 would start at goal 0
    assert ssi_auction(starts, goals).tours[0][0] == 0
    with pytest.raises(ValueError, match="two agents hold one goal"):
        ssi_auction(starts, goals, first=[2, 2])


def test_a_held_goal_survives_a_nearer_new_frontier_and_its_frontier_moving() -> None:
    svc = TeamService(server=None, options=TeamOptions())
    assert _first_goal(svc, _frontiers((10.0, 0.0), (-20.0, 0.0)), _ugv(0.0, 0.0, 0.0)) == [10.0, 0.0]
    # the map grew: a frontier appeared 3 m behind the agent, and the held one's cluster moved by 2.5 m
    fr = _frontiers((-3.0, 0.0), (11.5, 2.0), (-20.0, 0.0))
    assert _first_goal(svc, fr, _ugv(1.0, 0.0, 2.0)) == [10.0, 0.0]  # the position it was given
    # a fresh service (no hold) would turn back
    fresh = TeamService(server=None, options=TeamOptions())
    assert _first_goal(fresh, fr, _ugv(1.0, 0.0, 2.0)) == [-3.0, 0.0]


def test_a_held_goal_is_dropped_when_reached_explored_or_out_of_reach() -> None:
    o = AuctionOptions()
    svc = TeamService(server=None, options=TeamOptions())
    far = (-20.0, 0.0)
    assert _first_goal(svc, _frontiers((10.0, 0.0), far), _ugv(0.0, 0.0, 0.0)) == [10.0, 0.0]
    # reached: the frontier there lingers (the map has not caught up), but it is not given back
    fr = _frontiers((10.0, 0.0), (12.0, 6.0), far)
    assert _first_goal(svc, fr, _ugv(9.0, 0.0, 10.0)) == [12.0, 6.0]
    assert svc.commits.reasons == {"reached": 1}
    # explored: no frontier within held_match_m of (12, 6) any more
    fr = _frontiers((12.0 + o.held_match_m + 0.5, 6.0), far)
    assert _first_goal(svc, fr, _ugv(10.0, 1.0, 12.0)) == [12.0 + o.held_match_m + 0.5, 6.0]
    assert svc.commits.reasons == {"reached": 1, "explored": 1}
    # stopped short: the agent stands 8 m from its goal (as near as its roads go) for held_idle_s
    t0 = 12.0
    assert _first_goal(svc, fr, _ugv(10.0, 1.0, t0 + o.held_idle_s - 0.5)) == [16.5, 6.0]
    assert _first_goal(svc, fr, _ugv(10.0, 1.0, t0 + o.held_idle_s + 0.5)) == list(far)
    assert svc.commits.reasons["stopped short"] == 1
    # no progress: the agent keeps moving (a detour around a block) but gets no nearer for held_stall_s
    fr2 = _frontiers((0.0, 30.0), far)
    t1 = t0 + o.held_idle_s + 1.0
    svc.commits.held.clear()
    assert _first_goal(svc, fr2, _ugv(0.0, 10.0, t1)) == [0.0, 30.0]
    circle = [(0.0, 10.0), (12.0, 14.0), (16.0, 18.0), (12.0, 14.0)]  # each 20 m from the goal
    n = int(o.held_stall_s // 2) + 1
    for k in range(n):
        x, y = circle[k % 4]
        assert _first_goal(svc, fr2, _ugv(x, y, t1 + 2.0 * k)) == [0.0, 30.0]
    assert _first_goal(svc, fr2, _ugv(0.0, 10.0, t1 + 2.0 * n + 0.5)) == list(far)
    assert svc.commits.reasons["no progress"] == 1
    # once forgotten, a goal given up on the way may be won again; one the agent stood at may not
    later = t1 + 2.0 * n + 0.5 + o.dropped_memory_s + 1.0
    svc.commits.held.clear()
    assert _first_goal(svc, fr2, _ugv(0.0, 10.0, later)) == [0.0, 30.0]
    svc.commits.held.clear()
    assert _first_goal(svc, fr, _ugv(10.0, 1.0, later)) == list(far)


def test_a_visited_goal_is_offered_to_no_one_again() -> None:
    """A frontier that stays after an agent reached it faces nothing to map (the site's margin): another
    agent is not sent there either."""
    svc = TeamService(server=None, options=TeamOptions())
    fr = _frontiers((10.0, 0.0), (-20.0, 0.0))
    assert _first_goal(svc, fr, _ugv(0.0, 0.0, 0.0)) == [10.0, 0.0]
    assert _first_goal(svc, fr, _ugv(9.5, 0.0, 8.0)) == [-20.0, 0.0]  # reached; the frontier lingers
    other = _AgentSnap("ugv2", "ugv", 0, np.array([12.0, 0.0, 0.0]), np.zeros(3), 500.0)
    out = svc._assign(0, fr, [other], [svc._covariance("ugv2")])
    assert out.agents[0].goal_positions[0][:2] == [-20.0, 0.0]


def test_a_held_goal_in_another_map_is_forgotten() -> None:
    svc = TeamService(server=None, options=TeamOptions())
    assert _first_goal(svc, _frontiers((10.0, 0.0)), _ugv(0.0, 0.0, 0.0)) == [10.0, 0.0]
    moved = _AgentSnap("ugv", "ugv", 7, np.array([0.0, 0.0, 0.0]), np.zeros(3), 1.0)
    out = svc._assign(7, _frontiers((-4.0, 0.0), (10.0, 0.0)), [moved], [svc._covariance("ugv")])
    assert out.agents[0].goal_positions[0][:2] == [-4.0, 0.0]
    assert svc.commits.reasons == {"map changed": 1} and svc.commits.held["ugv"].map_id == 7
