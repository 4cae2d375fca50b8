"""Live motion (issue 26): replans keep position, velocity and acceleration continuous, reach the command,
and the IMU the trajectory gives dead-reckons back to it; the controller obeys a safe-velocity advisory."""

from __future__ import annotations

import math

import numpy as np

from hivemap.sim.live_control import Controller, RoadPaths, WorldAdvisory, world_from_map
from hivemap.sim.live_motion import LiveMotion, MotionLimits
from hivemap.sim.sensors import integrate_imu


def _zigzag(kind: str) -> LiveMotion:
    m = LiveMotion("a", kind, np.array([1.0, 2.0, 5.0]), 0.3, MotionLimits(horizon_s=1.0))
    cmds = [(1.0, [1.0, 0.0, 0.3], 0.0), (1.7, [0.0, 1.5, -0.2], 1.5), (2.2, [-1.0, 0.5, 0.0], 3.0),
            (2.25, [-1.0, 0.6, 0.0], 3.1), (4.0, [0.0, 0.0, 0.0], None)]  # fmt: skip
    for t, v, yaw in cmds:
        m.replan(t, np.array(v), yaw)
    return m


def test_replans_are_continuous_and_reach_the_command() -> None:
    m = _zigzag("uav")
    tr = m.trajectory
    for t in (1.0, 1.7, 2.2, 2.25, 4.0):
        eps = 1e-7
        for f in (tr.position, tr.velocity, tr.acceleration, tr.rotation):
            assert np.allclose(f(t - eps), f(t + eps), atol=1e-5), (f.__name__, t)
    # the last command (stop) is reached within its horizon and held
    assert np.allclose(tr.velocity(7.0)[0], 0.0, atol=1e-9)
    assert np.allclose(tr.position(7.0), tr.position(9.0), atol=1e-9)
    # before the first replan the agent is exactly at rest
    assert np.allclose(tr.position(0.5)[0], [1.0, 2.0, 5.0]) and np.allclose(tr.velocity(0.5), 0.0)
    # a velocity command with no later replan is reached exactly at the end of its horizon
    m2 = LiveMotion("b", "ugv", np.zeros(3), 0.0, MotionLimits(horizon_s=1.0, max_accel=10.0))
    m2.replan(0.0, np.array([1.0, 0.5, 0.0]), math.atan2(0.5, 1.0))
    assert np.allclose(m2.trajectory.velocity(1.0)[0], [1.0, 0.5, 0.0], atol=1e-9)
    assert np.allclose(m2.trajectory.acceleration(1.0)[0], 0.0, atol=1e-9)


def test_imu_of_a_replanned_uav_dead_reckons_to_its_trajectory() -> None:
    m = _zigzag("uav")
    tr = m.trajectory
    t = np.arange(0.0, 6.0 + 1e-9, 1 / 200.0)  # the scenarios' IMU rate
    R, p, _ = integrate_imu(t, tr.angular_velocity(t), tr.specific_force(t), tr.rotation(0.0)[0],
                            tr.position(0.0)[0], tr.velocity(0.0)[0])  # fmt: skip
    # m after 6 s of zigzag with five replans (the error is second order in the sample period: the
    # angular rate follows the jerk, continuous at replans)
    assert np.abs(p - tr.position(t)).max() < 2e-3
    # attitude of a quadrotor: body z along the thrust; a UGV keeps body z up
    assert not np.allclose(tr.rotation(1.5)[0][:, 2], [0, 0, 1], atol=1e-3)
    ugv = _zigzag("ugv").trajectory
    assert np.allclose(ugv.rotation(1.5)[0][:, 2], [0, 0, 1])


def test_controller_obeys_a_safe_velocity_advisory() -> None:
    # one straight east-west road; the goal lies 20 m east: the pursuit command is 2 m/s east
    paths = RoadPaths([np.array([[-50.0, 0.0], [50.0, 0.0]])])
    c = Controller("ugv", 2.0, paths)
    p = np.array([0.0, 0.0, 0.9])
    goal = np.array([[20.0, 0.0, 0.0]])
    c.advise(WorldAdvisory(0.0, goal, np.array([2.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0]), 0.8))
    v, heading = c.command(0.5, p, 0.0)
    assert np.allclose(v, [2.0, 0.0, 0.0]) and heading == 0.0 and c.obeyed == 0
    # ORCA turned the desired (2, 0) into (1, -1) to pass a neighbour: the command is that, exactly,
    # heading -45 deg; a UGV facing east (0 deg) drives at cos(45 deg) of it while it turns
    c.advise(WorldAdvisory(1.0, goal, np.array([2.0, 0.0, 0.0]), np.array([1.0, -1.0, 0.0]), 0.8))
    v, heading = c.command(1.25, p, -math.pi / 4)
    assert np.allclose(v, [1.0, -1.0, 0.0]) and heading is not None
    assert math.isclose(heading, -math.pi / 4) and c.obeyed == 1
    v, _ = c.command(1.5, p, 0.0)
    assert np.allclose(v, np.array([1.0, -1.0, 0.0]) * math.cos(math.pi / 4))
    # a safe velocity above the agent's speed is scaled down to it, same direction
    c.advise(WorldAdvisory(2.0, goal, np.array([2.0, 0.0, 0.0]), np.array([0.0, -4.0, 0.0]), 0.8))
    v, _ = c.command(2.0, p, -math.pi / 2)
    assert np.allclose(v, [0.0, -2.0, 0.0])
    # advisories expire after advisory_ttl_s: back to the pursuit of the goal
    v, _ = c.command(2.0 + c.options.advisory_ttl_s + 0.1, p, 0.0)
    assert np.allclose(v, [2.0, 0.0, 0.0])
    # a UGV 1 m left of a road's centre line (7 m wide) stops rather than follow a safe velocity that takes it
    # within 1 m of the edge in 1 s (to y = 1 + 1.96 > 2.5); one that keeps it on the road it follows
    ugv = Controller("ugv", 2.0, paths, road_half_width_m=3.5)
    q = np.array([0.0, 1.0, 0.9])
    ugv.advise(WorldAdvisory(0.0, goal, np.array([2.0, 0.0, 0.0]), np.array([0.5, 2.5, 0.0]), 0.8))
    v, _ = ugv.command(0.0, q, math.atan2(2.5, 0.5))
    assert np.allclose(v, 0.0) and ugv.stopped_for_road == 1
    ugv.advise(WorldAdvisory(0.0, goal, np.array([2.0, 0.0, 0.0]), np.array([1.0, 0.5, 0.0]), 0.8))
    v, _ = ugv.command(0.0, q, math.atan2(0.5, 1.0))
    assert np.allclose(v, [1.0, 0.5, 0.0]) and ugv.stopped_for_road == 1
    # near a goal the agent slows (0.5/s times the remaining 3 m) unless another goal follows
    near = np.array([[3.0, 0.0, 0.0]])
    c.advise(WorldAdvisory(9.0, near, np.zeros(3), np.zeros(3), 0.8))
    assert np.allclose(c.command(9.0, p, 0.0)[0], [1.5, 0.0, 0.0])
    c.advise(WorldAdvisory(9.0, np.vstack([near, goal]), np.zeros(3), np.zeros(3), 0.8))
    assert np.allclose(c.command(9.0, p, 0.0)[0], [2.0, 0.0, 0.0])
    # commitment: while pursuing a goal, a new advisory that still has it (reordered) keeps it first
    a_, b_ = np.array([10.0, 0.0, 0.0]), np.array([-10.0, 0.0, 0.0])
    c.advise(WorldAdvisory(20.0, np.stack([a_, b_]), np.zeros(3), np.zeros(3), 0.8))
    c.command(20.0, p, 0.0)
    c.advise(WorldAdvisory(21.0, np.stack([b_, a_ + 0.5]), np.zeros(3), np.zeros(3), 0.8))
    assert c.goal is not None and np.allclose(c.goal, a_ + 0.5)
    # a goal reached is dropped from the advisories of the next reached_memory_s, then allowed again
    c.command(22.0, np.array([10.0, 0.0, 0.9]), 0.0)
    assert c.goal is not None and np.allclose(c.goal, b_)
    c.advise(WorldAdvisory(23.0, np.stack([a_, b_]), np.zeros(3), np.zeros(3), 0.8))
    assert c.goal is not None and np.allclose(c.goal, b_)
    t_late = 23.0 + c.options.reached_memory_s
    c.advise(WorldAdvisory(t_late, np.stack([a_, b_]), np.zeros(3), np.zeros(3), 0.8))
    c.command(t_late, np.array([-10.0, 0.0, 0.9]), 0.0)  # b reached: a again, the memory of it is gone
    assert c.goal is not None and np.allclose(c.goal, a_)
    # and the motion follows the obeyed command: after the horizon its velocity is the safe one
    m = LiveMotion("u", "ugv", p, -math.pi / 4, MotionLimits(horizon_s=1.0, max_accel=10.0))
    m.replan(0.0, np.array([1.0, -1.0, 0.0]), -math.pi / 4)
    assert np.allclose(m.trajectory.velocity(1.0)[0], [1.0, -1.0, 0.0], atol=1e-9)


def test_world_from_map_uses_the_estimate() -> None:
    # truth at (10, 0) facing north; the estimate (map frame) says (0, 0) facing east: a goal 5 m ahead
    # in the map, (5, 0), is 5 m ahead in the world, (10, 5)
    W = np.eye(4)
    W[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    W[:3, 3] = [10, 0, 0]
    M = np.eye(4)
    M[:3, :3] *= 2.0
    T = world_from_map(W, M)  # a Sim(3) estimate: the scale is divided out
    assert np.allclose(T @ [5, 0, 0, 1], [10, 5, 0, 1])
