"""Two live UAVs on crossing roads keep their inflated radii apart (issue 26's acceptance): the real
controller and motion of ``hivemap.sim``, the server's ORCA, and a scripted server between them that sees
each agent's latest keyframe (every 0.5 s of its own clock) and advises every 0.12 s, as in the explore
runs. The agents' clocks may be apart (separate processes, each stepping its own simulated time); the
clearance is counted as ``eval/explore.pair_distances`` counts it: at equal simulated times, horizontal
distance less the two inflated radii while the vertical gap is within their two half heights."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hivemap.server.team.options import OrcaOptions
from hivemap.server.team.orca import AgentMotion, advisories, preferred_velocity
from hivemap.sim.live_control import Controller, RoadPaths, WorldAdvisory
from hivemap.sim.live_motion import LiveMotion

DT, REPLAN, KF_S, SERVER_S, SPEED = 0.05, 0.25, 0.5, 0.12, 2.0


def _closed_loop(
    roads: list[np.ndarray],
    start: dict[str, np.ndarray],
    goal: dict[str, np.ndarray],
    clock: dict[str, float],
    intents: bool,
    duration: float = 30.0,
) -> tuple[float, float]:
    """(smallest clearance [m], the two inflated radii [m]) of two live UAVs flying ``roads`` from
    ``start`` to ``goal`` at their heights; ``clock``: each agent's clock on the server's (wall) clock.
    ``intents``: each keyframe carries the controller's intent (``Controller.intent``), as live agents
    send it; else the server predicts each agent along its keyframes' velocity."""
    o = OrcaOptions()
    paths = RoadPaths(roads)
    ctl = {k: Controller("uav", SPEED, paths, cruise_height_m=float(p[2])) for k, p in start.items()}
    for k in start:  # the goal known from the start: the intent is along the path from the first frame
        ctl[k].advise(WorldAdvisory(-1.0, goal[k][None], np.zeros(3), np.zeros(3), 0.0))
    mot = {k: LiveMotion(k, "uav", p, math.atan2(*(goal[k] - p)[1::-1])) for k, p in start.items()}
    kfs: dict[str, list[tuple[float, np.ndarray, np.ndarray | None]]] = {k: [] for k in start}
    replanned = dict.fromkeys(start, -1e9)
    inbox: dict[str, AgentMotion | None] = dict.fromkeys(start)
    advised: dict[str, tuple[np.ndarray, np.ndarray, float] | None] = dict.fromkeys(start)
    truth: dict[str, dict[int, np.ndarray]] = {k: {} for k in start}
    next_server, radius, half = 0.0, 0.0, 0.0
    w = -max(clock.values())
    while w <= duration:
        for k in start:
            t = w + clock[k]
            if not 0.0 <= t <= duration:
                continue
            state, yaw = mot[k].state(t)
            truth[k][round(t / DT)] = state[0]
            if not kfs[k] or t - kfs[k][-1][0] >= KF_S - 1e-9:
                kfs[k].append((t, state[0].copy(), ctl[k].intent(state[0]) if intents else None))
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
                (tq, q, _), (tp, p, intent) = kfs[k][-2] if len(kfs[k]) > 1 else kfs[k][-1], kfs[k][-1]
                vel = (p - q) / (tp - tq) if tp > tq else np.zeros(3)
                desired = preferred_velocity(vel, p, goal[k], SPEED, o, intent)
                P = np.diag([o.default_position_sigma_m**2] * 2 + [0.0])
                V = np.diag([o.default_velocity_sigma_mps**2] * 2 + [0.0])
                inbox[k] = AgentMotion(k, p, vel, desired, o.radius_uav_m, SPEED, P, V, timestamp=tp,
                                       intent=intent, half_height=o.half_height_uav_m)  # fmt: skip
            motions = [m for m in inbox.values() if m is not None]
            for m, adv in zip(motions, advisories(motions, o), strict=True):
                advised[m.agent_id] = (adv.desired, adv.safe_velocity, adv.radius)
                radius, half = adv.radius, adv.half_height
        w = round(w + DT, 9)
    common = sorted(set(truth["a"]) & set(truth["b"]))
    A, B = np.array([truth["a"][i] for i in common]), np.array([truth["b"][i] for i in common])
    need = 2 * radius
    near = np.abs(A[:, 2] - B[:, 2]) < 2 * half
    assert near.any()
    return float((np.linalg.norm(A[:, :2] - B[:, :2], axis=1) - need)[near].min()), need


def _crossing(ahead_b: float, gap_z: float) -> tuple[float, float]:
    """uav a flies east along y = 0 at 10 m and uav b north along x = 0 at ``10 - gap_z``, both at the
    crossing at the same simulated time; b's clock is ``ahead_b`` s ahead of a's."""
    roads = [np.array([[-60.0, 0.0], [60.0, 0.0]]), np.array([[0.0, -60.0], [0.0, 60.0]])]
    start = {"a": np.array([-23.5, 0.0, 10.0]), "b": np.array([0.0, -23.5, 10.0 - gap_z])}
    goal = {"a": np.array([45.0, 0.0, 10.0]), "b": np.array([0.0, 45.0, 10.0 - gap_z])}
    return _closed_loop(roads, start, goal, {"a": 0.0, "b": ahead_b}, intents=False)


@pytest.mark.parametrize(
    ("ahead_b", "gap_z"),
    [
        (0.0, 0.4),  # one clock; 0.4 m apart in height, within the two half heights (0.6 m)
        (1.0, 0.0),  # b's clock 1 s ahead: the server sees b 2 m further on than a meets it
        (-1.0, 0.0),  # and 1 s behind
    ],
)
def test_crossing_uavs_keep_their_inflated_radii_apart(ahead_b: float, gap_z: float) -> None:
    clearance, radii = _crossing(ahead_b, gap_z)
    # 0.5 + 2 (0.1 + 1 * 0.05) m each: the default sigmas
    assert radii == pytest.approx(1.6)
    assert clearance >= 0.0, clearance


def _turning(intents: bool, gap: float = 4.0, behind_b: float = 0.0, ahead_b: float = 0.0) -> float:
    """The near miss of the live runs: a and b fly north on parallel roads ``gap`` m apart (b
    ``behind_b`` m behind a), then turn towards each other onto the road along y = 0, a east and b west,
    so that they meet head on at once. Their current velocities show it only as they turn. Returns the
    smallest clearance [m]."""
    x = gap / 2
    roads = [np.array([[-x, -40.0], [-x, 0.0]]), np.array([[x, -40.0], [x, 0.0]]),
             np.array([[-40.0, 0.0], [40.0, 0.0]])]  # fmt: skip
    start = {"a": np.array([-x, -14.0, 10.0]), "b": np.array([x, -14.0 - behind_b, 10.0])}
    goal = {"a": np.array([30.0, 0.0, 10.0]), "b": np.array([-30.0, 0.0, 10.0])}
    clock = {"a": 0.0, "b": ahead_b}
    return _closed_loop(roads, start, goal, clock, intents=intents, duration=25.0)[0]


TURNS = [(4.0, 0.0, 0.0), (3.0, 1.0, 0.5), (5.0, -2.0, 0.5), (8.0, 0.0, 0.0), (3.8, -0.25, -0.5)]


@pytest.mark.parametrize(("gap", "behind_b", "ahead_b"), TURNS)
def test_turning_uavs_keep_their_radii_apart_when_the_server_knows_their_intents(
    gap: float, behind_b: float, ahead_b: float
) -> None:
    assert _turning(True, gap, behind_b, ahead_b) >= 0.0


def test_without_intents_the_turn_is_seen_late() -> None:
    """The same turns predicted along the keyframes' velocities: ORCA answers only once both turn, and
    the closest pair comes to its radii (within 0.3 m of them); with the intents it keeps at least 0.5 m
    more."""
    without = min(_turning(False, *c) for c in TURNS)
    told = min(_turning(True, *c) for c in TURNS)
    assert without < 0.3 and told > without + 0.5, (without, told)
