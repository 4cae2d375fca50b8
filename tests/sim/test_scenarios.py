"""Scenario presets reproduce paper Table 4 and the small test presets stay small."""

from __future__ import annotations

import dataclasses

import pytest

from hivemap.sim.conditions import Lighting, Weather
from hivemap.sim.scenarios import SCENARIOS, get_scenario

# paper 003 Table 4: dataset -> (lighting, meteorology, camera angles UAV1..3)
TABLE4 = {
    "factory01": ("bright", "clear", (45, 45, 45)),
    "factory02": ("bright", "fog", (45, 45, 45)),
    "factory03": ("somber", "clear", (45, 45, 45)),
    "factory04": ("somber", "fog", (45, 45, 45)),
    "factory05": ("bright", "mist", (45, 45, 45)),
    "factory06": ("somber", "mist", (45, 45, 45)),
    "factory07": ("bright", "clear", (25, 25, 25)),
    "factory08": ("bright", "clear", (25, 45, 75)),
}
LENGTHS = {"uav1": 162.47, "uav2": 161.29, "uav3": 168.96, "ugv": 106.43}


@pytest.mark.parametrize("name", sorted(TABLE4))
def test_factory_presets_match_table4(name):
    s = get_scenario(name)
    light, weather, pitches = TABLE4[name]
    assert (s.lighting, s.weather) == (light, weather)
    assert [a.agent_id for a in s.agents] == ["uav1", "uav2", "uav3", "ugv"]
    assert tuple(a.camera_pitch_deg for a in s.agents[:3]) == pitches
    assert s.agent("ugv").camera_pitch_deg == 0 and s.agent("ugv").kind == "ugv"
    assert {a.agent_id: a.path_length_m for a in s.agents} == LENGTHS
    assert {a.baseline_m for a in s.agents[:3]} == {0.12} and s.agent("ugv").baseline_m == 0.30
    assert s.duration_s is None and s.camera.rate_hz == 20 and (s.camera.width, s.camera.height) == (640, 480)
    assert s.imu_rate_hz == 200 and s.gnss_rate_hz == 5
    # the condition names resolve in hivemap.sim.conditions (mist V=150 m, fog V=50 m)
    assert Lighting.preset(s.lighting).name == light
    assert (
        Weather.preset(s.weather).visibility_m == {"clear": float("inf"), "mist": 150.0, "fog": 50.0}[weather]
    )


def test_noise_is_paper_tables_2_and_3():
    s = get_scenario("factory03")
    n = s.imu_noise
    assert (n.gyroscope_noise_density, n.gyroscope_random_walk) == (0.0003394, 0.000038785)
    assert (n.accelerometer_noise_density, n.accelerometer_random_walk) == (0.004, 0.006)
    assert (n.gyroscope_bias_correlation_time, n.accelerometer_bias_correlation_time) == (1000.0, 300.0)
    assert n.gyroscope_turn_on_bias_sigma == 0.0087
    assert (s.gnss_noise.sigma_horizontal, s.gnss_noise.sigma_vertical) == (0.05, 0.15)


def test_small_presets():
    tiny = get_scenario("tiny")
    assert 2 <= len(tiny.agents) <= 4 and tiny.duration_s is not None and 10 <= tiny.duration_s <= 15
    assert tiny.camera.width <= 640 and tiny.camera.rate_hz <= 20
    dis = get_scenario("disjoint")
    assert len(dis.agents) == 2 and {a.region for a in dis.agents} == {"west", "east"}


def test_lookup_and_frozen():
    assert get_scenario("Factory_01") is SCENARIOS["factory01"]
    with pytest.raises(KeyError, match="factory01"):
        get_scenario("factory09")
    with pytest.raises(dataclasses.FrozenInstanceError):
        get_scenario("tiny").seed = 4  # type: ignore[misc]
