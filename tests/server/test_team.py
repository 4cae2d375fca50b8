"""Team services against hand-computed cases: SSI auction, ORCA advisories, frontiers, follow-the-leader,
and their options from TOML."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from hivemap.server.team.auction import d_optimal_gain, path_length, ssi_auction
from hivemap.server.team.follow import reference
from hivemap.server.team.frontiers import extract, voxel_downsample
from hivemap.server.team.options import ConfigError, FrontierOptions, OrcaOptions, TeamOptions, from_table
from hivemap.server.team.options import to_table as team_to_table
from hivemap.server.team.orca import AgentMotion, advisories, inflated_radius, preferred_velocity

# ---------------------------------------------------------------- auction


def test_auction_two_agents_on_a_line_exact_bids() -> None:
    starts = np.array([[0.0, 0.0], [10.0, 0.0]])
    goals = np.array([[1.0, 0.0], [2.0, 0.0], [9.0, 0.0], [11.0, 0.0]])
    r = ssi_auction(starts, goals)
    # round 0: A bids 1, 2, 9, 11; B bids 9, 8, 1, 1 -> A takes goal 0 at 1 (tie with B, A is earlier)
    # round 1: A adds goal 1 after goal 0 for 1 (B: 8); B's 1 for goals 2 and 3 ties, A is earlier
    # round 2: A would add 7 / 9, B 1 / 1 -> B takes goal 2 (the earlier goal)
    # round 3: B adds goal 3 for 2 (after goal 2: 9->11; before it: 10->11->9 adds 1 + 2 - 1); A: 9
    assert [(b.agent, b.goal) for b in r.won] == [(0, 0), (0, 1), (1, 2), (1, 3)]
    assert [b.bid for b in r.won] == pytest.approx([1.0, 1.0, 1.0, 2.0], abs=1e-12)
    assert r.tours == [[0, 1], [2, 3]]
    assert r.costs == pytest.approx([2.0, 3.0], abs=1e-12)
    assert r.unassigned == []


def test_auction_added_cost_differs_from_nearest_agent_greedy() -> None:
    # B is nearer goal 1 (5 vs 6) but A, having won goal 0, adds only 2 for it
    starts = np.array([[0.0, 0.0], [11.0, 0.0]])
    goals = np.array([[4.0, 0.0], [6.0, 0.0]])
    nearest = [int(np.argmin(np.linalg.norm(starts - g, axis=1))) for g in goals]
    assert nearest == [0, 1]
    r = ssi_auction(starts, goals)
    assert [(b.agent, b.goal, b.bid) for b in r.won] == [(0, 0, 4.0), (0, 1, 2.0)]
    assert r.tours == [[0, 1], []]
    greedy_total = 4.0 + 5.0
    assert sum(r.costs) == pytest.approx(6.0) and sum(r.costs) < greedy_total


def test_auction_insertion_goes_between_and_cap_and_reachability() -> None:
    # A wins (10, 0) first, then (5, 1) is cheaper inserted before it than appended
    starts = np.array([[0.0, 0.0]])
    goals = np.array([[10.0, 0.0], [5.0, 1.0]])
    r = ssi_auction(starts, goals, value=lambda a, g: 20.0 if g == 0 else 0.0)
    assert r.tours == [[1, 0]]
    added = 2 * math.hypot(5.0, 1.0) - 10.0
    assert r.won[1].added_cost == pytest.approx(added) and r.won[1].position == 0
    assert r.costs[0] == pytest.approx(path_length(starts[0], [1, 0], goals))
    # cap 1: the second goal goes to the other agent; a goal nobody may reach stays unassigned
    starts2 = np.array([[0.0, 0.0], [10.0, 0.0]])
    goals2 = np.array([[1.0, 0.0], [2.0, 0.0], [50.0, 0.0]])
    allowed = np.array([[True, True, False], [True, True, False]])
    r2 = ssi_auction(starts2, goals2, allowed=allowed, cap=1)
    assert r2.tours == [[0], [1]] and r2.unassigned == [2]
    assert r2.won[1].bid == pytest.approx(8.0)


def test_d_optimal_gain_by_hand() -> None:
    # P = s^2 I (2-D), n fixes of sigma: P' = (1/s^2 + n/sigma^2)^-1 I; gain = 0.5 * 2 * log(s^2 / p')
    s, sigma, n = 0.4, 0.5, 4
    p_after = 1.0 / (1.0 / s**2 + n / sigma**2)
    assert d_optimal_gain(s**2 * np.eye(2), n, sigma) == pytest.approx(math.log(s**2 / p_after))
    assert d_optimal_gain(np.eye(2), 0, sigma) == 0.0
    # the value hook can turn the assignment: the uncertain agent B takes goal 0 despite its longer path
    starts = np.array([[0.0, 0.0], [3.0, 0.0]])
    goals = np.array([[1.0, 0.0]])
    gains = {0: d_optimal_gain(0.01 * np.eye(2), 10, sigma), 1: d_optimal_gain(1.0 * np.eye(2), 10, sigma)}
    assert ssi_auction(starts, goals).tours == [[0], []]
    r = ssi_auction(starts, goals, value=lambda a, g: 1.0 * gains[a])
    assert r.tours == [[], [0]]
    assert r.won[0].bid == pytest.approx(2.0 - gains[1])


# ---------------------------------------------------------------- ORCA

OPT = OrcaOptions(time_horizon_s=5.0, time_step_s=0.1, k_sigma=2.0, velocity_horizon_s=1.0)


def _agent(name: str, p: tuple[float, float], v: tuple[float, float], **kw: object) -> AgentMotion:
    pos = np.array([p[0], p[1], 1.5])
    vel = np.array([v[0], v[1], 0.0])
    return AgentMotion(name, pos, vel, vel.copy(), radius=0.5, max_speed=2.0, **kw)  # type: ignore[arg-type]


def _min_distance(pa: np.ndarray, va: np.ndarray, pb: np.ndarray, vb: np.ndarray, horizon: float) -> float:
    """Closest approach of two agents moving at constant velocities over [0, horizon]."""
    dp, dv = pb - pa, vb - va
    t = 0.0 if dv @ dv == 0 else float(np.clip(-(dp @ dv) / (dv @ dv), 0.0, horizon))
    return float(np.linalg.norm(dp + t * dv))


@pytest.mark.parametrize("cov", [None, np.diag([0.04, 0.01, 0.0])])
def test_orca_head_on_safe_over_horizon(cov: np.ndarray | None) -> None:
    a = _agent("a", (0.0, 0.0), (1.0, 0.0), position_cov=cov)
    b = _agent("b", (8.0, 0.0), (-1.0, 0.0), position_cov=cov)
    # at their desired velocities they would meet within the horizon
    assert _min_distance(a.position[:2], a.velocity[:2], b.position[:2], b.velocity[:2], 5.0) == 0.0
    adv = advisories([a, b], OPT)
    r_sum = adv[0].radius + adv[1].radius
    va, vb = adv[0].safe_velocity[:2], adv[1].safe_velocity[:2]
    # RVO2 works in single precision: 1 mm
    assert _min_distance(a.position[:2], va, b.position[:2], vb, OPT.time_horizon_s) >= r_sum - 1e-3
    assert np.linalg.norm(va) <= 2.0 + 1e-6 and np.linalg.norm(vb) <= 2.0 + 1e-6
    assert adv[0].neighbours == ("b",) and adv[0].safe_velocity[2] == 0.0


def test_orca_closed_loop_never_closer_than_inflated_radii() -> None:
    cov = np.diag([0.01, 0.01, 0.0])
    goals = {"a": np.array([10.0, 0.2]), "b": np.array([0.0, 0.0])}
    pos = {"a": np.array([0.0, 0.0]), "b": np.array([10.0, 0.2])}
    vel = {k: np.zeros(2) for k in pos}
    dt, closest = OPT.time_step_s, math.inf
    r_sum = None
    for _ in range(200):  # 20 s: both reach their goals
        agents = []
        for k in ("a", "b"):
            to_goal = goals[k] - pos[k]
            desired = to_goal / max(np.linalg.norm(to_goal), 1e-9) * min(1.0, np.linalg.norm(to_goal) / dt)
            agents.append(AgentMotion(k, np.array([*pos[k], 0.0]), np.array([*vel[k], 0.0]),
                                      np.array([*desired, 0.0]), 0.5, 1.0, position_cov=cov))  # fmt: skip
        adv = advisories(agents, OPT)
        r_sum = adv[0].radius + adv[1].radius
        for k, ad in zip(("a", "b"), adv, strict=True):
            vel[k] = ad.safe_velocity[:2]
            pos[k] = pos[k] + dt * vel[k]
        closest = min(closest, float(np.linalg.norm(pos["a"] - pos["b"])))
    assert r_sum == pytest.approx(2 * (0.5 + 2.0 * 0.1))
    assert closest >= r_sum - 1e-3
    for k in pos:
        assert np.linalg.norm(pos[k] - goals[k]) < 0.05, (k, pos[k])


def test_orca_lone_agent_keeps_desired_velocity_exactly() -> None:
    a = _agent("a", (0.0, 0.0), (0.3, -1.1))
    far = _agent("far", (500.0, 0.0), (-1.0, 0.0))
    above = AgentMotion("above", np.array([0.5, 0.0, 30.0]), np.zeros(3), np.zeros(3), 0.5, 2.0)
    desired = np.array([0.3, -1.1, 0.25])
    a = AgentMotion("a", a.position, a.velocity, desired, 0.5, 2.0)
    adv = advisories([a, far, above], OPT)
    assert adv[0].neighbours == ()
    assert np.array_equal(adv[0].safe_velocity, desired)


def test_orca_guards_the_path_the_agents_fly_not_the_line_to_their_goals() -> None:
    """Two agents on roads that cross: a flies +x from (0, 0), b +y from (4, -4), both at 1 m/s, so they
    meet at (4, 0) after 4 s; their goals lie off the roads, a's straight up at (0, 10), b's to the right
    at (14, -4), and those straight lines never come within 5.6 m. With the lines to the goals as the
    preferred velocities ORCA finds them clear and leaves them as they are: the agents' controllers,
    which obey only a changed velocity, fly their roads into each other. With the velocities they fly
    as the preferred ones, ORCA changes them, and the advised velocities keep the pair apart by their
    inflated radii over the horizon."""
    a = _agent("a", (0.0, 0.0), (1.0, 0.0))
    b = _agent("b", (4.0, -4.0), (0.0, 1.0))
    goals = {"a": np.array([0.0, 10.0, 1.5]), "b": np.array([14.0, -4.0, 1.5])}
    assert _min_distance(a.position[:2], a.velocity[:2], b.position[:2], b.velocity[:2], 5.0) < 1e-9

    def with_desired(m: AgentMotion, d: np.ndarray) -> AgentMotion:
        return AgentMotion(m.agent_id, m.position, m.velocity, d, m.radius, m.max_speed)

    line = [with_desired(m, (goals[m.agent_id] - m.position) / np.linalg.norm(goals[m.agent_id] - m.position))
            for m in (a, b)]  # fmt: skip
    assert _min_distance(a.position[:2], line[0].desired[:2], b.position[:2], line[1].desired[:2], 5.0) > 5.6
    for adv, m in zip(advisories(line, OPT), line, strict=True):
        assert np.allclose(adv.safe_velocity, m.desired, atol=1e-6)  # the hazard: nothing changes

    flown = [with_desired(m, preferred_velocity(m.velocity, m.position, goals[m.agent_id], 2.0, OPT))
             for m in (a, b)]  # fmt: skip
    assert np.array_equal(flown[0].desired, a.velocity) and np.array_equal(flown[1].desired, b.velocity)
    adv = advisories(flown, OPT)
    changed = [np.linalg.norm(v.safe_velocity[:2] - m.desired[:2]) for v, m in zip(adv, flown, strict=True)]
    assert max(changed) > 0.1
    r_sum = adv[0].radius + adv[1].radius
    va, vb = adv[0].safe_velocity[:2], adv[1].safe_velocity[:2]
    assert _min_distance(a.position[:2], va, b.position[:2], vb, OPT.time_horizon_s) >= r_sum - 1e-3


def test_orca_prefers_an_agents_intent() -> None:
    """a flies +x from (0, 0) and b +x from (4, 3), both at 2 m/s: side by side, 3 m apart, clear. But b's
    path turns it south across a's (its intent: (0, -2) m/s), which would bring it within 0.71 m of a in
    1.75 s. Without intents ORCA keeps both as they fly; with them b's desired velocity is its intent,
    and ORCA answers it with a velocity that stays clear of a as a flies (the cones are built on current
    velocities), where a, whose intent is its course, keeps it."""
    a = _agent("a", (0.0, 0.0), (2.0, 0.0))
    b = _agent("b", (4.0, 3.0), (2.0, 0.0))
    intent = {"a": np.array([2.0, 0.0, 0.0]), "b": np.array([0.0, -2.0, 0.0])}
    assert _min_distance(a.position[:2], a.velocity[:2], b.position[:2], intent["b"][:2], 5.0) < 0.75
    for adv, m in zip(advisories([a, b], OPT), (a, b), strict=True):
        assert np.allclose(adv.safe_velocity, m.desired, atol=1e-6)  # current velocities: nothing to do

    def with_intent(m: AgentMotion) -> AgentMotion:
        i = intent[m.agent_id]
        return replace(m, desired=preferred_velocity(m.velocity, m.position, None, 2.0, OPT, i), intent=i)

    told = [with_intent(m) for m in (a, b)]
    assert np.array_equal(told[1].desired, intent["b"])
    adv = advisories(told, OPT)
    assert np.allclose(adv[0].safe_velocity, intent["a"], atol=1e-5)
    assert np.linalg.norm(adv[1].safe_velocity - intent["b"]) > 1.0
    r_sum = adv[0].radius + adv[1].radius + 2 * OPT.tracking_margin_m
    va, vb = adv[0].safe_velocity[:2], adv[1].safe_velocity[:2]
    assert _min_distance(a.position[:2], va, b.position[:2], vb, OPT.time_horizon_s) >= r_sum - 1e-3
    # an intent faster than the top speed is cut to it horizontally; its climb rate passes
    fast = preferred_velocity(np.zeros(3), a.position, None, 2.0, OPT, np.array([3.0, 4.0, 0.5]))
    assert np.allclose(fast, [1.2, 1.6, 0.5])


def test_preferred_velocity_of_a_standing_agent_is_the_line_to_its_goal() -> None:
    """Below ``moving_mps`` the agent is standing: the straight line to its goal at cruise speed,
    slowed to arrive within one advisory period (0.1 s here), zero without a goal; a moving agent's
    velocity above the top speed is cut to it."""
    p = np.array([1.0, 1.0, 2.0])
    still = np.array([0.05, 0.0, 0.0])
    v = preferred_velocity(still, p, np.array([4.0, 5.0, 2.0]), 2.0, OPT)
    assert np.allclose(v, [1.2, 1.6, 0.0])  # 5 m away: 2 m/s along (0.6, 0.8)
    v = preferred_velocity(still, p, np.array([1.06, 1.08, 2.0]), 2.0, OPT)
    assert np.allclose(v, [0.6, 0.8, 0.0])  # 0.1 m away: 1 m/s arrives in 0.1 s
    assert np.array_equal(preferred_velocity(still, p, None, 2.0, OPT), np.zeros(3))
    v = preferred_velocity(np.array([3.0, 4.0, 0.5]), p, None, 2.0, OPT)
    assert np.allclose(v, [1.2, 1.6, 0.5])


def test_inflated_radius_by_hand() -> None:
    base = _agent("a", (0.0, 0.0), (0.0, 0.0))
    assert inflated_radius(base, OPT) == 0.5
    # horizontal block [[0.05, 0.03], [0.03, 0.05]]: eigenvalues 0.08, 0.02 -> sigma 0.2828
    P = np.array([[0.05, 0.03, 0.0], [0.03, 0.05, 0.0], [0.0, 0.0, 9.0]])  # vertical variance ignored
    V = np.diag([0.0004, 0.0009, 4.0])  # sigma_v 0.03
    a = AgentMotion("a", base.position, base.velocity, base.desired, 0.5, 2.0, P, V)
    assert inflated_radius(a, OPT) == pytest.approx(0.5 + 2.0 * (math.sqrt(0.08) + 1.0 * 0.03))
    bigger = AgentMotion("a", base.position, base.velocity, base.desired, 0.5, 2.0, 4 * P, V)
    assert inflated_radius(bigger, OPT) == pytest.approx(0.5 + 2.0 * (2 * math.sqrt(0.08) + 0.03))


def test_radius_is_inflated_by_the_relative_not_the_absolute_uncertainty() -> None:
    """Two agents far from the map's anchor: each one's own position sigma is 2 m, but loops hold them
    together, so the covariance of their difference has a largest horizontal sigma of 0.2 m, split by
    their own sigmas (equal: 0.1 m each): each radius grows by k x 0.1 m, not k x 2 m. The vertical gate
    uses the relative vertical sigma likewise. A pair with an unknown relative covariance brings the own
    sigma back; a lost agent (own sigma 100 m, relative ~100 m) takes nearly all of its pair's share."""
    P = np.diag([4.0, 4.0, 1.0])  # own sigma 2 m (horizontal), 1 m (vertical)
    R = np.diag([0.04, 0.01, 0.0025])  # relative: 0.2 m horizontal, 0.05 m vertical

    def uav(name: str, x: float, z: float, rel: tuple[tuple[str, np.ndarray | None], ...],
            cov: np.ndarray = P) -> AgentMotion:  # fmt: skip
        v = np.array([1.0, 0.0, 0.0]) if name == "a" else np.array([-1.0, 0.0, 0.0])
        return AgentMotion(name, np.array([x, 0.3, z]), v, v, 0.5, 2.0, cov, None, relative=rel)

    a, b = uav("a", 0.0, 5.0, (("b", R),)), uav("b", 6.0, 5.0, (("a", R),))
    assert inflated_radius(a, OPT, [a, b]) == pytest.approx(0.5 + 2.0 * 0.1)
    assert inflated_radius(b, OPT, [a, b]) == pytest.approx(0.5 + 2.0 * 0.1)
    # head-on 6 m apart, 0.3 m off the line: neighbours at one height; 1.6 m higher they are not with the
    # relative vertical sigma (half heights 2 x 0.025 m, no own height here), but are with the absolute
    # ones (2 x 1 m each)
    assert advisories([a, b], OPT)[0].neighbours == ("b",)
    high = uav("b", 6.0, 6.6, (("a", R),))
    assert advisories([a, high], OPT)[0].neighbours == ()
    absolute = [replace(x, relative=()) for x in (a, high)]
    assert inflated_radius(absolute[0], OPT, absolute) == pytest.approx(0.5 + 2.0 * 2.0)
    assert advisories(absolute, OPT)[0].neighbours == ("b",)
    # a third agent of unknown relative covariance: the own sigma is the bound for that pair
    c = uav("a", 0.0, 5.0, (("b", R), ("c", None)))
    assert inflated_radius(c, OPT, [c, b]) == pytest.approx(0.5 + 2.0 * 2.0)
    # unequal own sigmas (2 m and 1 m): the 0.3 m relative sigma splits 0.2 / 0.1, any pair's sum holds it
    R3 = np.diag([0.09, 0.0, 0.0])
    d, e = uav("d", 0.0, 5.0, (("e", R3),)), uav("e", 6.0, 5.0, (("d", R3),), cov=P / 4.0)
    assert inflated_radius(d, OPT, [d, e]) == pytest.approx(0.5 + 2.0 * 0.2)
    assert inflated_radius(e, OPT, [d, e]) == pytest.approx(0.5 + 2.0 * 0.1)
    # a lost agent: own 100 m, 100.02 m from the other; the other's share stays within its own 2 m
    lost_cov = np.diag([1e4, 1e4, 1e4])
    Rl = np.diag([100.02**2, 0.0, 0.0])
    f, lost = uav("f", 0.0, 5.0, (("x", Rl),)), uav("x", 6.0, 5.0, (("f", Rl),), cov=lost_cov)
    share_f = inflated_radius(f, OPT, [f, lost]) - 0.5
    assert share_f == pytest.approx(2.0 * 100.02 * 2.0 / 102.0) and share_f <= 2.0 * 2.0
    assert inflated_radius(f, OPT, [f, lost]) + inflated_radius(lost, OPT, [f, lost]) == pytest.approx(
        1.0 + 2.0 * 100.02
    )


# ---------------------------------------------------------------- frontiers

FOPT = FrontierOptions(voxel_m=0.5, close_cells=1, cluster_m=2.5, min_cluster_points=3,
                       ugv_max_height_m=0.5, uav_min_alt_m=1.0, uav_max_alt_m=8.0)  # fmt: skip


def _half_explored(hole: bool = False) -> np.ndarray:
    """A 20 x 10 m site whose west half x in [0, 10] is mapped: floor points for y < 4.9, a deck at 3 m
    (its floor unseen) for y > 5.1; east of x = 10 nothing is known."""
    rng = np.random.default_rng(3)
    xs = np.arange(0.0, 10.0 + 1e-9, 0.2)
    floor = np.array([(x, y, 0.0) for x in xs for y in np.arange(0.0, 4.9, 0.2)])
    if hole:  # a textureless patch of floor
        inside = (floor[:, 0] > 3.9) & (floor[:, 0] < 6.1) & (floor[:, 1] > 1.4) & (floor[:, 1] < 3.6)
        floor = floor[~inside]
    deck = np.array([(x, y, 3.0) for x in xs for y in np.arange(5.2, 10.0 + 1e-9, 0.2)])
    pts = np.vstack([floor, deck])
    return pts + rng.normal(0.0, 0.01, pts.shape)


def _to_perimeter(xy: np.ndarray) -> np.ndarray:
    x, y = xy[:, 0], xy[:, 1]
    return np.minimum.reduce([np.abs(x), np.abs(10 - x), np.abs(y), np.abs(10 - y)])


def test_voxel_downsample_centroids() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.2, 0.0, 0.0]])
    out = voxel_downsample(pts, 1.0)
    assert sorted(map(tuple, out.round(9))) == [(0.2, 0.2, 0.2), (1.2, 0.0, 0.0)]


def test_frontiers_of_half_explored_rectangle() -> None:
    res = extract(_half_explored(), FOPT)
    a, b, c = res.ground
    assert abs(a) < 1e-3 and abs(b) < 1e-3 and abs(c) < 0.02
    assert len(res.frontiers) >= 8
    goals = np.array([f.goal[:2] for f in res.frontiers])
    # every frontier point and goal lies on the known boundary, within one voxel
    assert (_to_perimeter(res.frontier_points[:, :2]) <= FOPT.voxel_m).all()
    assert (_to_perimeter(goals) <= FOPT.voxel_m).all()
    # the boundary with the unknown east half is covered, on both the floor and the deck
    east = [f for f in res.frontiers if f.goal[0] > 10 - FOPT.voxel_m]
    assert {int(f.goal[1] // 2.5) for f in east} == {0, 1, 2, 3}
    for f in res.frontiers:
        if f.goal[1] < 4.9:
            assert f.reachable == ("ugv",), f
            assert f.goals["ugv"][2] == pytest.approx(0.0, abs=0.02)
        elif f.goal[1] > 5.1:
            assert f.reachable == ("uav",), f
            assert f.goals["uav"][2] == pytest.approx(3.0, abs=0.02)


def test_frontiers_hole_is_closed_by_a_path_through_it() -> None:
    pts = _half_explored(hole=True)
    res = extract(pts, FOPT)
    inner = _to_perimeter(res.frontier_points[:, :2]) > FOPT.voxel_m
    assert inner.sum() > 10  # the hole's rim is a frontier
    rows = [np.array([[3.5, y, 1.0], [6.5, y, 1.0]]) for y in np.arange(1.5, 3.6, 0.5)]
    lawnmower = np.vstack([r if i % 2 == 0 else r[::-1] for i, r in enumerate(rows)])
    res2 = extract(pts, FOPT, paths=[lawnmower])
    assert (_to_perimeter(res2.frontier_points[:, :2]) <= FOPT.voxel_m).all()
    assert res2.known_cells > res.known_cells


def test_lines_of_sight_close_a_sparse_maps_holes_but_not_its_outer_boundary() -> None:
    """A textureless patch of floor inside the mapped half: its rim is a frontier from the points alone.
    A camera on the floor's west edge that saw points across the patch (lines of sight over it) marks the
    patch seen: no frontier inside the mapped half; the east boundary's frontiers stay. A line of sight
    longer than ``view_range_m`` counts only up to it."""
    pts = _half_explored(hole=True)
    floor = pts[(pts[:, 2] < 1.0) & (pts[:, 0] > 6.5) & (pts[:, 1] > 0.5) & (pts[:, 1] < 4.0)]
    cams = np.array([[0.5, y, 1.0] for y in np.arange(1.0, 4.01, 0.25)])
    rays = np.array([[c, p] for c in cams for p in floor[:: max(1, len(floor) // 40)]])
    res = extract(pts, FOPT, rays=rays)
    assert (_to_perimeter(res.frontier_points[:, :2]) <= FOPT.voxel_m).all()
    east = [f for f in res.frontiers if f.goal[0] > 10 - FOPT.voxel_m]
    assert {0, 1, 2, 3} <= {int(f.goal[1] // 2.5) for f in east}
    # cut at 3 m from the camera, the lines of sight stop short of the patch (x 3.9 .. 6.1): its rim stays
    short = extract(pts, replace(FOPT, view_range_m=3.0), rays=rays)
    inner = _to_perimeter(short.frontier_points[:, :2]) > FOPT.voxel_m
    assert inner.sum() > 10
    assert (
        extract(pts, replace(FOPT, view_range_m=0.0), rays=rays).known_cells == extract(pts, FOPT).known_cells
    )


def test_sight_lines_run_from_a_keyframe_to_the_points_it_observes_in_the_map_frame_now() -> None:
    from hivemap.maps import Keyframe as MapKeyframe
    from hivemap.maps import Map, MapPoint
    from hivemap.maps.geometry import se3, so3_exp
    from hivemap.server.loadgen import CAMERA
    from hivemap.server.team.sight import SightLines

    m = Map(0)
    T = se3(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    n = 40
    ids = np.full(n, -1, np.int64)
    ids[::2] = np.arange(20)  # every other keypoint observes a point
    kf = MapKeyframe("a", 0, 0.0, T, CAMERA, np.zeros((n, 2), np.float32), np.zeros(n, np.uint8),
                     np.zeros((n, 32), np.uint8), ids)  # fmt: skip
    rng = np.random.default_rng(1)
    xyz = rng.normal(0, 5, (20, 3))
    for i in range(20):
        m.add_point(MapPoint("a", i, xyz[i], np.zeros(32, np.uint8)))
    m.add_keyframe(kf)
    sight = SightLines(8)
    r = sight.rays(m)
    assert r.shape == (8, 2, 3)
    np.testing.assert_allclose(r[:, 0], np.tile(T[:3, 3], (8, 1)))
    assert all(np.linalg.norm(xyz - e, axis=1).min() < 1e-9 for e in r[:, 1])
    # the map moves the keyframe and its points together: the lines move with them, not re-read
    G = se3(so3_exp(np.array([0.0, 0.0, 0.5])), np.array([3.0, 0.0, 0.0]))
    kf.world_from_cam = G @ T
    r2 = sight.rays(m)
    np.testing.assert_allclose(r2[:, 1], r[:, 1] @ G[:3, :3].T + G[:3, 3], atol=1e-9)
    sight.prune({})
    assert sight.rays(Map(1)).shape == (0, 2, 3)


# ---------------------------------------------------------------- follow-the-leader


def test_follow_straight_path() -> None:
    path = np.column_stack([np.linspace(0.0, 10.0, 11), np.zeros(11), np.full(11, 1.5)])
    ref = reference(path, 3.0, spacing=0.5)
    np.testing.assert_allclose(ref.point, [7.0, 0.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(ref.tangent, [1.0, 0.0, 0.0], atol=1e-12)
    assert ref.behind_m == pytest.approx(3.0)
    np.testing.assert_allclose(ref.path[-1], ref.point) and np.testing.assert_allclose(ref.path[0], path[0])
    assert np.diff(ref.path[:, 0]).max() <= 0.5 + 1e-12
    short = reference(path[:3], 3.0)  # the leader has gone 2 m: the follower waits at its start
    np.testing.assert_allclose(short.point, path[0]) and np.testing.assert_allclose(short.behind_m, 2.0)


def test_follow_circular_path() -> None:
    R, theta, d = 5.0, math.pi, 2.0
    t = np.linspace(0.0, theta, 4001)
    path = np.column_stack([R * np.cos(t), R * np.sin(t), np.zeros_like(t)])
    ref = reference(path, d)
    phi = theta - d / R  # arc length d behind on the circle
    np.testing.assert_allclose(ref.point, [R * math.cos(phi), R * math.sin(phi), 0.0], atol=1e-4)
    np.testing.assert_allclose(ref.tangent, [-math.sin(phi), math.cos(phi), 0.0], atol=1e-3)
    assert abs(np.linalg.norm(ref.point[:2]) - R) < 1e-4


# ---------------------------------------------------------------- options


def test_team_options_from_toml() -> None:
    table = tomllib.loads(
        "min_interval_s = 1.0\n[frontiers]\nvoxel_m = 0.25\n[orca]\nk_sigma = 3\n[auction]\n"
        "max_goals_per_agent = 2\n"
    )
    o = from_table(table)
    assert o.min_interval_s == 1.0 and o.frontiers.voxel_m == 0.25 and o.orca.k_sigma == 3.0
    assert o.auction.max_goals_per_agent == 2 and o.frontiers.cluster_m == FrontierOptions().cluster_m
    assert from_table(team_to_table(o)) == o
    assert from_table(False) == TeamOptions(enabled=False)
    with pytest.raises(ConfigError, match="team.orca.nope"):
        from_table({"orca": {"nope": 1}})
    with pytest.raises(ConfigError, match="team.frontiers.voxel_m"):
        from_table({"frontiers": {"voxel_m": "big"}})


def test_orca_gate_is_the_inflated_cylinder_and_neighbours_are_carried_to_ones_time() -> None:
    P, V = np.diag([0.01, 0.01, 0.0]), np.diag([0.0025, 0.0025, 0.0])  # inflated: 0.5 + 2 (0.1 + 0.05)

    def uav(name: str, p: tuple[float, ...], v: tuple[float, ...], t: float | None,
            cov: np.ndarray = P) -> AgentMotion:  # fmt: skip
        return AgentMotion(name, np.array(p), np.array(v), np.array(v), 0.5, 2.0, cov, V, timestamp=t,
                           half_height=0.3)  # fmt: skip

    # a east along y = 0 at 10 m, b north along x = 6 at 9.6 m: both at (6, 0) in 3 s. The gap of 0.4 m
    # is within the two half heights (0.3 m each, no vertical sigma): near, as the explore evaluation
    # counts a pair
    a, b = (
        uav("a", (0.0, 0.0, 10.0), (2.0, 0.0, 0.0), 100.0),
        uav("b", (6.0, -6.0, 9.6), (0.0, 2.0, 0.0), 100.0),
    )
    now = advisories([a, b], OPT)
    assert inflated_radius(a, OPT) == pytest.approx(0.8)
    assert now[0].half_height == pytest.approx(0.3)
    assert now[0].neighbours == ("b",) and now[1].neighbours == ("a",)
    assert not np.allclose(now[0].safe_velocity, a.desired)
    # 0.7 m apart in height: not near, each keeps its desired velocity; with a vertical sigma of 0.1 m
    # each (half heights 0.3 + 2 x 0.1 m) they are
    high = uav("b", (6.0, -6.0, 9.3), (0.0, 2.0, 0.0), 100.0)
    assert advisories([a, high], OPT)[0].neighbours == ()
    Pz = np.diag([0.01, 0.01, 0.01])
    unsure = advisories([uav("a", (0.0, 0.0, 10.0), (2.0, 0.0, 0.0), 100.0, Pz),
                         uav("b", (6.0, -6.0, 9.3), (0.0, 2.0, 0.0), 100.0, Pz)], OPT)  # fmt: skip
    assert unsure[0].half_height == pytest.approx(0.5) and unsure[0].neighbours == ("b",)
    # a UGV 3 m below, 2 m uncertain horizontally and 0.1 m vertically: a wide but low cylinder
    ugv = AgentMotion("g", np.array([6.0, -6.0, 7.0]), np.array([0.0, 2.0, 0.0]), np.array([0.0, 2.0, 0.0]),
                      0.8, 1.0, np.diag([4.0, 4.0, 0.01]), V, timestamp=100.0, half_height=1.0)  # fmt: skip
    low = advisories([a, ugv], OPT)
    assert low[1].radius > 4.0 and low[1].half_height == pytest.approx(1.2) and low[0].neighbours == ()
    # b's latest keyframe 1 s older than a's (2 m back): a's advisory is the one for b where it is at a's
    # time; b's own is for a carried 1 s back to b's time
    old = uav("b", (6.0, -8.0, 9.6), (0.0, 2.0, 0.0), 99.0)
    lagged = advisories([a, old], OPT)
    assert np.allclose(lagged[0].safe_velocity, now[0].safe_velocity, atol=1e-5)
    back = advisories([uav("a", (-2.0, 0.0, 10.0), (2.0, 0.0, 0.0), 99.0), old], OPT)
    assert np.allclose(lagged[1].safe_velocity, back[1].safe_velocity, atol=1e-5)
    # without both times: as given (the lag makes b look 2 m further from the crossing)
    untimed = uav("a", (0.0, 0.0, 10.0), (2.0, 0.0, 0.0), None)
    assert not np.allclose(advisories([untimed, old], OPT)[0].safe_velocity, now[0].safe_velocity, atol=1e-3)
