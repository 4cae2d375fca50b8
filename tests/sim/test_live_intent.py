"""The live controller's intent (what a live agent's keyframes tell the server it will fly): the mean
velocity over the next ``intent_horizon_s`` along its road path, by hand on an L-shaped road."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.sim.live_control import Controller, ControlOptions, RoadPaths, WorldAdvisory

ROADS = [np.array([[-30.0, 0.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [0.0, 30.0]])]


def _uav(goal: tuple[float, float] | None, height: float = 10.0) -> Controller:
    c = Controller("uav", 2.0, RoadPaths(ROADS), cruise_height_m=height, options=ControlOptions())
    if goal is not None:
        c.advise(WorldAdvisory(0.0, np.array([[goal[0], goal[1], height]]), np.zeros(3), np.zeros(3), 0.0))
    return c


def test_intent_is_the_chord_along_the_path() -> None:
    c = _uav((0.0, 20.0))
    # far from the corner: along the road at full speed (2 m/s over 2 s: 4 m on)
    np.testing.assert_allclose(c.intent(np.array([-20.0, 0.0, 10.0])), [2.0, 0.0, 0.0], atol=1e-6)
    # 1 m before the corner: the road graph joins the crossing's nodes, so the path cuts the corner to
    # (0, 1), and its 4 m end at (0, 5 - sqrt 2); the chord there, flown at the mean speed its length over
    # 2 s gives
    v = c.intent(np.array([-1.0, 0.0, 10.0]))
    chord = np.array([1.0, 5.0 - np.sqrt(2.0)]) / 2.0
    np.testing.assert_allclose(v[:2], chord, atol=0.03)
    assert v[2] == 0.0 and np.linalg.norm(v[:2]) < 2.0
    # 3 m below its height a UAV climbs (at most 1 m/s) and does not move on yet
    np.testing.assert_allclose(c.intent(np.array([-20.0, 0.0, 7.0])), [0.0, 0.0, 1.0])
    # without a goal: nothing horizontally; nothing changed in the controller's own state
    assert np.array_equal(_uav(None).intent(np.array([-20.0, 0.0, 10.0])), np.zeros(3))
    assert c.goal_index == 0 and c.goals_reached == 0


@pytest.mark.parametrize("x", [-10.0, -2.5, -0.5])
def test_intent_never_exceeds_the_speed(x: float) -> None:
    v = _uav((0.0, 20.0)).intent(np.array([x, 0.0, 10.0]))
    assert np.linalg.norm(v[:2]) <= 2.0 + 1e-9
