"""Two live UAVs on crossing roads keep their inflated radii apart (issue 26's acceptance): the real
controller and motion of ``hivemap.sim``, the server's ORCA, and a scripted server between them that sees
each agent's latest keyframe (every 0.5 s of its own clock) and advises every 0.12 s, as in the explore
runs. The agents' clocks may be apart (separate processes, each stepping its own simulated time); the
clearance is counted as ``eval/explore.pair_distances`` counts it: at equal simulated times, horizontal
distance less the two inflated radii while the vertical gap is within that sum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hivemap.server.team.options import OrcaOptions
from hivemap.server.team.orca import AgentMotion, advisories, inflated_radius
from hivemap.sim.live_control import Controller, RoadPaths, WorldAdvisory
from hivemap.sim.live_motion import LiveMotion

DT, REPLAN, KF_S, SERVER_S, SPEED = 0.05, 0.25, 0.5, 0.12, 2.0


def _crossing(ahead_b: float, gap_z: float, duration: float = 30.0) -> tuple[float, float]:
    """(smallest clearance [m], the two inflated radii [m]) of uav a flying east along y = 0 at 10 m and
    uav b north along x = 0 at ``10 - gap_z``, both at the crossing at the same simulated time; b's clock
    is ``ahead_b`` s ahead of a's on the server's (wall) clock."""
    o = OrcaOptions()
    paths = RoadPaths([np.array([[-60.0, 0.0], [60.0, 0.0]]), np.array([[0.0, -60.0], [0.0, 60.0]])])
    start = {"a": np.array([-23.5, 0.0, 10.0]), "b": np.array([0.0, -23.5, 10.0 - gap_z])}
    goal = {"a": np.array([45.0, 0.0, 10.0]), "b": np.array([0.0, 45.0, 10.0 - gap_z])}
    clock = {"a": 0.0, "b": ahead_b}
    ctl = {k: Controller("uav", SPEED, paths, cruise_height_m=float(p[2])) for k, p in start.items()}
    mot = {k: LiveMotion(k, "uav", p, math.atan2(-p[1], -p[0])) for k, p in start.items()}
    kfs: dict[str, list[tuple[float, np.ndarray]]] = {k: [] for k in start}
    replanned = dict.fromkeys(start, -1e9)
    inbox: dict[str, AgentMotion | None] = dict.fromkeys(start)
    advised: dict[str, tuple[np.ndarray, np.ndarray, float] | None] = dict.fromkeys(start)
    truth: dict[str, dict[int, np.ndarray]] = {k: {} for k in start}
    next_server, radius = 0.0, 0.0
    w = -max(clock.values())
    while w <= duration:
        for k in start:
            t = w + clock[k]
            if not 0.0 <= t <= duration:
                continue
            state, yaw = mot[k].state(t)
            truth[k][round(t / DT)] = state[0]
            if not kfs[k] or t - kfs[k][-1][0] >= KF_S - 1e-9:
                kfs[k].append((t, state[0].copy()))
            got = advised[k]
            if got is not None:  # taken between frames, stamped with the agent's own time
                ctl[k].advise(WorldAdvisory(t, goal[k][None], got[0], got[1], got[2]))
                advised[k] = None
            if t - replanned[k] >= REPLAN - 1e-9:
                v, heading = ctl[k].command(t, state[0], float(yaw[0]))
                mot[k].replan(t, v, heading)
                replanned[k] = t
        if w >= next_server - 1e-9:  # the server: latest keyframes, velocity from the last two
            next_server = w + SERVER_S
            for k in [k for k in start if kfs[k]]:
                (tq, q), (tp, p) = kfs[k][-2] if len(kfs[k]) > 1 else kfs[k][-1], kfs[k][-1]
                vel = (p - q) / (tp - tq) if tp > tq else np.zeros(3)
                to_goal = goal[k] - p
                desired = (
                    to_goal / np.linalg.norm(to_goal) * min(SPEED, np.linalg.norm(to_goal) / o.time_step_s)
                )
                P = np.diag([o.default_position_sigma_m**2] * 2 + [0.0])
                V = np.diag([o.default_velocity_sigma_mps**2] * 2 + [0.0])
                inbox[k] = AgentMotion(k, p, vel, desired, o.radius_uav_m, SPEED, P, V, timestamp=tp)
            motions = [m for m in inbox.values() if m is not None]
            for m, adv in zip(motions, advisories(motions, o), strict=True):
                advised[m.agent_id] = (adv.desired, adv.safe_velocity, adv.radius)
                radius = inflated_radius(m, o)
        w = round(w + DT, 9)
    common = sorted(set(truth["a"]) & set(truth["b"]))
    A, B = np.array([truth["a"][i] for i in common]), np.array([truth["b"][i] for i in common])
    need = 2 * radius
    near = np.abs(A[:, 2] - B[:, 2]) < need
    assert near.any()
    return float((np.linalg.norm(A[:, :2] - B[:, :2], axis=1) - need)[near].min()), need


@pytest.mark.parametrize(
    ("ahead_b", "gap_z"),
    [
        (0.0, 1.2),  # one clock; 1.2 m apart in height, within the two inflated radii (1.6 m)
        (1.0, 0.0),  # b's clock 1 s ahead: the server sees b 2 m further on than a meets it
        (-1.0, 0.0),  # and 1 s behind
    ],
)
def test_crossing_uavs_keep_their_inflated_radii_apart(ahead_b: float, gap_z: float) -> None:
    clearance, radii = _crossing(ahead_b, gap_z)
    # 0.5 + 2 (0.1 + 1 * 0.05) m each: the default sigmas
    assert radii == pytest.approx(1.6)
    assert clearance >= 0.0, clearance
