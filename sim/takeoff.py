"""How the agents leave their start (issue 25): the UAVs' staggered take-off from the UGV's roof and their
optional vertical climb, as times and heights that ``trajectories.plan_trajectories`` turns into motion."""

from __future__ import annotations

from dataclasses import dataclass

from hivemap.sim.scenarios import AgentSpec, Scenario


def spot(a: AgentSpec) -> int:
    """A UAV's take-off spot on the UGV's roof: (spot - 2) * 0.35 m along the heading
    (``trajectories._agent_path``)."""
    return int(a.agent_id[-1]) if a.agent_id[-1].isdigit() else 0


CLIMB_S = 3.5  # duration of a vertical climb off the UGV's roof (``Scenario.takeoff_climb_m``)
CLIMB_STAGGER_S = 1.0  # a UAV starts its climb this long after the one in front of it


@dataclass(frozen=True)
class Takeoff:
    """How an agent leaves its start: ``climb_m`` straight up over ``[climb_t, climb_t + CLIMB_S]``, then
    its route from ``leave_t`` (at rest before ``climb_t`` and between the climb and ``leave_t``)."""

    leave_t: float
    climb_m: float = 0.0
    climb_t: float = 0.0


def takeoff_plan(scenario: Scenario) -> dict[str, Takeoff]:
    """Every agent's :class:`Takeoff`. With a UGV the UAVs leave the roof (or, with a climb, their hover
    point) ``takeoff_interval_s`` apart after the UGV, the front one first, so no UAV's camera looks at the
    carrier of the UAV right in front of it and the UGV drives ahead of the UAVs in their first seconds.
    With ``takeoff_climb_m`` they first climb one after the other, the front one first and highest, so the
    carrier of the one in front is always above a camera (which looks 45 deg down), and the UGV leaves
    when they are all up."""
    has_ugv = any(a.kind == "ugv" for a in scenario.agents)
    t0 = scenario.hold_s
    if not has_ugv:
        return {a.agent_id: Takeoff(t0) for a in scenario.agents}
    uavs = sorted((a for a in scenario.agents if a.kind == "uav"), key=spot, reverse=True)  # front first
    dt = max(scenario.takeoff_interval_s, 0.0)
    climb = scenario.takeoff_climb_m
    t_ugv = t0 + (CLIMB_S + CLIMB_STAGGER_S * max(len(uavs) - 1, 0) if climb > 0 else 0.0)
    out = {a.agent_id: Takeoff(t_ugv) for a in scenario.agents if a.kind != "uav"}
    for r, a in enumerate(uavs):
        leave = t_ugv + (r + 1) * dt
        if climb > 0:
            out[a.agent_id] = Takeoff(leave, climb + 0.5 * (len(uavs) - 1 - r), t0 + CLIMB_STAGGER_S * r)
        else:
            out[a.agent_id] = Takeoff(leave)
    return out
