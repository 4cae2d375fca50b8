"""How the agents leave their start (issue 25): the UAVs' staggered take-off from the UGV's roof and their
optional vertical climb, as times and heights that ``trajectories.plan_trajectories`` turns into motion."""

from __future__ import annotations

from dataclasses import dataclass

from hivemap.sim.scenarios import AgentSpec, Scenario


def spot(a: AgentSpec) -> int:
    """A UAV's take-off spot on the UGV's roof: (spot - 2) * 0.35 m along the heading
    (``trajectories._agent_path``)."""
    return int(a.agent_id[-1]) if a.agent_id[-1].isdigit() else 0


def takeoff_delays(scenario: Scenario) -> dict[str, float]:
    """Per UAV, how long after the UGV it leaves the roof, or with a climb its hover point
    (``Scenario.takeoff_interval_s``): the front one first, so no UAV's camera looks at the carrier of the
    UAV right in front of it, and the UGV drives ahead of the UAVs in their first seconds (they see its
    markers)."""
    dt = scenario.takeoff_interval_s
    uavs = sorted((a for a in scenario.agents if a.kind == "uav"), key=spot, reverse=True)
    return {a.agent_id: (k + 1) * dt for k, a in enumerate(uavs)} if dt > 0 else {}


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
    """Every agent's :class:`Takeoff`. With a UGV and ``takeoff_climb_m``, the UAVs climb one after the
    other, the front one first and highest, so the carrier of the one in front is always above a camera
    (which looks 45 deg down); the UGV leaves when they are all up and each UAV then follows
    ``takeoff_delays`` after it."""
    has_ugv = any(a.kind == "ugv" for a in scenario.agents)
    delays = takeoff_delays(scenario) if has_ugv else {}
    t0 = scenario.hold_s
    climb = scenario.takeoff_climb_m if has_ugv else 0.0
    if climb <= 0:
        return {a.agent_id: Takeoff(t0 + delays.get(a.agent_id, 0.0)) for a in scenario.agents}
    uavs = sorted((a for a in scenario.agents if a.kind == "uav"), key=spot, reverse=True)
    t_up = t0 + CLIMB_S + CLIMB_STAGGER_S * max(len(uavs) - 1, 0)
    out = {
        a.agent_id: Takeoff(
            t_up + delays.get(a.agent_id, 0.0), climb + 0.5 * (len(uavs) - 1 - r), t0 + CLIMB_STAGGER_S * r
        )
        for r, a in enumerate(uavs)
    }
    out.update({a.agent_id: Takeoff(t_up) for a in scenario.agents if a.kind == "ugv"})
    return out
