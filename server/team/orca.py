"""ORCA collision advisories between the agents of one map (seed 001, section 3): each agent gets the
velocity nearest its desired one that stays collision-free for a time horizon, assuming the others do
their half, with its radius inflated by its position and velocity uncertainty (as Hennes et al. inflate
by localisation uncertainty; the seed adds the velocity's).

The linear programs are the reference RVO2 library's (van den Berg et al.) through the ``pyrvo``
bindings, which install from a wheel: no hand-written ORCA. ORCA is planar: it acts on the horizontal
velocity; agents are upright cylinders, whose half height is the agent's own inflated by its vertical
uncertainty, and two agents are neighbours only when their cylinders overlap in height (a UAV flying over
a UGV does not have to swerve), and the vertical velocity is passed through.

An agent that says where it is going (its keyframes' intent: the mean velocity along its own path over
the next seconds) wants that velocity: it is ORCA's preferred velocity for it, so a turn towards another
agent is answered before the agent flies it. The velocity cones are still built on the agents' current
velocities (RVO2's optimisation velocity), which is what they fly for the next second or two whatever
they intend: built on the intents, ORCA assumed turns the agents' dynamics take seconds to make.

What a pair has to stay clear of is the error of where one is *from the other*: the covariance of the
difference of their positions (their joint marginal), not each one's marginal in the map frame, which
grows with the distance from the map's anchor although loops hold the two together. ORCA takes one
radius per agent, so each pair's relative sigma is split between its two agents in proportion to their
own sigmas, and each agent's radius is inflated by the largest of its shares (an unknown pair: its own
sigma). Any pair's two radii then hold its relative sigma; since the relative sigma is at most the sum
of the two own sigmas, no share exceeds the agent's own sigma, so an agent the graph has lost (a new
session held only loosely) inflates its own radius, not its neighbours'.

Positions are of each agent's latest keyframe, and agents' keyframes are of different times (their
keyframe spacing; simulated agents' clocks also drift apart). Each agent's problem is therefore solved with
its neighbours' positions carried at their velocities to the time of its own position: the pair's geometry
at one instant, as the agents meet it. And the agents reach a new velocity over a second or more rather
than at once, so ORCA solves with each inflated radius plus ``tracking_margin_m`` (NH-ORCA's tracking
error bound, Alonso-Mora et al.).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyrvo
from numpy.typing import NDArray

from hivemap.server.team.options import OrcaOptions

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class AgentMotion:
    """One agent as ORCA sees it: map-frame position, current and desired velocity (3,), its own
    radius and top speed, and the covariances (3, 3) of its position and velocity (None: unknown);
    ``relative``: per other agent of its map, the covariance (3, 3) of this one's position minus that
    one's (None: unknown)."""

    agent_id: str
    position: F64
    velocity: F64
    desired: F64
    radius: float
    max_speed: float
    position_cov: F64 | None = None
    velocity_cov: F64 | None = None
    timestamp: float | None = None  # s, the team's clock: when the agent was at ``position``
    relative: tuple[tuple[str, F64 | None], ...] = ()
    intent: F64 | None = None  # (3,) what the agent says it will fly (None: it did not say)
    half_height: float = 0.0  # its own, about ``position``


@dataclass(frozen=True)
class Advisory:
    agent_id: str
    safe_velocity: F64  # (3,)
    desired: F64  # (3,)
    radius: float  # inflated
    neighbours: tuple[str, ...]
    half_height: float = 0.0  # inflated


def preferred_velocity(
    velocity: F64, position: F64, goal: F64 | None, speed: float, o: OrcaOptions, intent: F64 | None = None
) -> F64:
    """The velocity ORCA keeps an agent nearest to (3,): what it will fly without an advisory. Its
    ``intent`` when it sent one (cut to ``speed``). Else a moving agent (faster than ``o.moving_mps``)
    keeps its current velocity: agents follow roads and their own controllers, so the straight line to the
    goal may be clear while the path they fly is not. A standing one: the straight line to ``goal`` at
    ``speed``, slowing to arrive within one advisory period (zero without a goal)."""
    v = np.asarray(velocity if intent is None else intent, dtype=np.float64)
    horizontal = float(np.linalg.norm(v[:2]))
    if intent is not None or horizontal > o.moving_mps:
        out = v.copy()
        if horizontal > 0:
            out[:2] *= min(1.0, speed / horizontal)
        return out
    if goal is None:
        return np.zeros(3)
    to_goal = np.asarray(goal, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    dist = float(np.linalg.norm(to_goal))
    return to_goal / dist * min(speed, dist / o.time_step_s) if dist > 0 else np.zeros(3)


def _sigma_max(cov: F64 | None, axes: slice) -> float:
    if cov is None:
        return 0.0
    c = np.asarray(cov, dtype=np.float64)[axes, axes]
    return float(np.sqrt(max(0.0, float(np.linalg.eigvalsh(c).max()))))


def position_sigma(agent: AgentMotion, axes: slice, others: Sequence[AgentMotion] = ()) -> float:
    """The position sigma the agent's radius is inflated by along ``axes`` (module docstring): the largest
    of its shares of the relative sigmas to the other agents of its map (``others``, those of its
    ``relative`` entries; a pair with an absent other agent is split evenly), its own sigma for a pair of
    unknown relative covariance, and its own sigma with no other agents."""
    own = _sigma_max(agent.position_cov, axes)
    if not agent.relative:
        return own
    theirs = {b.agent_id: _sigma_max(b.position_cov, axes) for b in others}
    shares = []
    for other, c in agent.relative:
        if c is None:
            shares.append(own)
            continue
        rel = _sigma_max(c, axes)
        total = own + theirs.get(other, own)
        shares.append(rel * (own / total) if total > 0.0 else 0.5 * rel)
    return max(shares)


def inflated_radius(agent: AgentMotion, options: OrcaOptions, others: Sequence[AgentMotion] = ()) -> float:
    """``radius + k (sigma_p + t_v sigma_v)``: ``sigma_p`` the horizontal :func:`position_sigma` among
    ``others``, ``sigma_v`` the square root of the largest eigenvalue of the velocity covariance's
    horizontal 2x2 block (``k`` = ``options.k_sigma``; ``t_v`` = ``options.velocity_horizon_s``, how
    long a velocity error acts before the next estimate corrects it; the velocity is differenced within
    one agent's chain, so its covariance is already free of the anchor's drift)."""
    xy = slice(0, 2)
    sp = position_sigma(agent, xy, others)
    sv = _sigma_max(agent.velocity_cov, xy)
    return agent.radius + options.k_sigma * (sp + options.velocity_horizon_s * sv)


def half_height(agent: AgentMotion, options: OrcaOptions, others: Sequence[AgentMotion] = ()) -> float:
    """Half the height of the agent's cylinder: its own ``half_height`` plus ``k_sigma`` times its vertical
    :func:`position_sigma` (two agents are neighbours when their heights differ by less than the sum of
    their half heights, as the explore evaluation counts them)."""
    return agent.half_height + options.k_sigma * position_sigma(agent, slice(2, 3), others)


def _position_at(agent: AgentMotion, t: float | None, options: OrcaOptions) -> F64:
    """The agent's position carried at its velocity to time ``t`` (no further than
    ``options.max_predict_s``); as it is without both times."""
    p = np.asarray(agent.position, dtype=np.float64)
    if t is None or agent.timestamp is None:
        return p
    dt = float(np.clip(t - agent.timestamp, -options.max_predict_s, options.max_predict_s))
    return p + dt * np.asarray(agent.velocity, dtype=np.float64)


def _clamp(v: F64, speed: float) -> F64:
    n = float(np.linalg.norm(v))
    return v if n <= speed or n == 0.0 else v * (speed / n)


def advisories(agents: Sequence[AgentMotion], options: OrcaOptions) -> list[Advisory]:
    """One advisory per agent (same order). An agent without neighbours keeps its desired velocity
    (clamped to its top speed) exactly."""
    o = options
    radii = [inflated_radius(a, o, agents) for a in agents]
    vmargin = [half_height(a, o, agents) for a in agents]
    out: list[Advisory] = []
    for i, a in enumerate(agents):
        desired = np.asarray(a.desired, dtype=np.float64)
        wanted = _clamp(desired[:2], a.max_speed)
        # everyone where they are at agent i's time (its own position unchanged)
        at = [_position_at(b, a.timestamp, o) for b in agents]
        nbrs = []
        for j in range(len(agents)):
            if j == i:
                continue
            d = at[j] - at[i]
            if abs(d[2]) > vmargin[i] + vmargin[j]:
                continue
            if float(np.linalg.norm(d[:2])) <= o.neighbor_dist_m + radii[i] + radii[j]:
                nbrs.append(j)
        if not nbrs:
            out.append(
                Advisory(a.agent_id, np.array([*wanted, desired[2]]), desired, radii[i], (), vmargin[i])
            )
            continue
        v = _solve(i, nbrs, agents, at, [r + o.tracking_margin_m for r in radii], wanted, o)
        out.append(
            Advisory(a.agent_id, np.array([v[0], v[1], desired[2]]), desired, radii[i],
                     tuple(agents[j].agent_id for j in nbrs), vmargin[i])
        )  # fmt: skip
    return out


def _solve(
    i: int,
    nbrs: list[int],
    agents: Sequence[AgentMotion],
    at: list[F64],
    radii: list[float],
    wanted: F64,
    o: OrcaOptions,
) -> F64:
    """Agent ``i``'s ORCA velocity among ``nbrs``: one RVO2 step in a simulator holding just them, in
    coordinates centred on agent ``i`` (RVO2 computes in single precision)."""
    sim = pyrvo.RVOSimulator()
    sim.set_time_step(o.time_step_s)
    centre = at[i][:2]
    # the neighbour range must cover every neighbour chosen above, whatever RVO2's own k-d tree does
    reach = float(max(np.linalg.norm(at[j][:2] - centre) for j in nbrs))
    reach += 2.0 * max(radii) + 1.0
    handles = []
    for j in [i, *nbrs]:
        b = agents[j]
        p = at[j][:2] - centre
        v = np.asarray(b.velocity, dtype=np.float64)[:2]
        handles.append(
            sim.add_agent((float(p[0]), float(p[1])), reach, len(nbrs), o.time_horizon_s, o.time_horizon_s,
                          radii[j], max(b.max_speed, float(np.linalg.norm(v))), (float(v[0]), float(v[1])))
        )  # fmt: skip
        # the neighbours' preferred velocities do not change agent i's result (only their current ones)
        sim.set_agent_pref_velocity(handles[-1], (float(v[0]), float(v[1])))
    sim.set_agent_pref_velocity(handles[0], (float(wanted[0]), float(wanted[1])))
    sim.set_agent_max_speed(handles[0], agents[i].max_speed)
    sim.do_step()
    v = sim.get_agent_velocity(handles[0])
    return np.array([v.x, v.y], dtype=np.float64)
