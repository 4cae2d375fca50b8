"""Scenario presets: paper Table 4 (Factory 01-08) plus small test scenarios.

A scenario fixes everything a render needs: the world seed, the agents (kind, camera pitch, target path
length, speed, stereo baseline), the camera intrinsics and rate, the sensor rates and noise, lighting and
weather, and the geodetic origin of the ENU frame. All presets are frozen dataclasses; ``get_scenario``
looks one up by name and ``SCENARIOS`` lists them.

Table 4 (paper 003): lighting bright/somber, weather "High visibility" (clear) / "mist" / "thick-foggy"
(fog), UAV camera pitch 45 deg (25 deg in Factory 07, 25/45/75 deg in Factory 08), UGV camera 0 deg; path
lengths UAV1 162.47 m, UAV2 161.29 m, UAV3 168.96 m, UGV 106.43 m.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from hivemap.maps.camera import PinholeCamera


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise (paper Table 2; the RotorS/Gazebo IMU plugin model).

    Densities are continuous-time: white noise in [unit / sqrt(Hz)], bias random walk in
    [unit / s / sqrt(Hz)]. The bias is a first-order Gauss-Markov process with the given correlation
    time, started from a constant turn-on bias drawn with ``*_turn_on_bias_sigma``.
    """

    gyroscope_noise_density: float = 0.0003394  # rad / s / sqrt(Hz)
    gyroscope_random_walk: float = 0.000038785  # rad / s^2 / sqrt(Hz)
    gyroscope_bias_correlation_time: float = 1000.0  # s
    gyroscope_turn_on_bias_sigma: float = 0.0087  # rad / s
    accelerometer_noise_density: float = 0.004  # m / s^2 / sqrt(Hz)
    accelerometer_random_walk: float = 0.006  # m / s^3 / sqrt(Hz)
    accelerometer_bias_correlation_time: float = 300.0  # s
    accelerometer_turn_on_bias_sigma: float = 0.0  # m / s^2 (not given in Table 2)

    def noise_free(self) -> ImuNoise:
        return ImuNoise(0.0, 0.0, self.gyroscope_bias_correlation_time, 0.0, 0.0, 0.0,
                        self.accelerometer_bias_correlation_time, 0.0)  # fmt: skip


@dataclass(frozen=True)
class GnssNoise:
    """GNSS noise (paper Table 3): white Gaussian position noise, metres (1 sigma)."""

    sigma_horizontal: float = 0.05  # per horizontal axis (east, north)
    sigma_vertical: float = 0.15
    sigma_velocity_horizontal: float = 0.05  # m/s, not written (GPGGA carries no velocity)
    sigma_velocity_vertical: float = 0.05


@dataclass(frozen=True)
class CameraSpec:
    """Intrinsics shared by cam0 and cam1 of every agent (mild radial-tangential distortion)."""

    width: int = 640
    height: int = 480
    fx: float = 430.0
    fy: float = 430.0
    cx: float = 319.5
    cy: float = 239.5
    dist: tuple[float, float, float, float] = (-0.05, 0.01, 0.0002, -0.0001)
    rate_hz: float = 20.0

    def pinhole(self) -> PinholeCamera:
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.dist)


@dataclass(frozen=True)
class AgentSpec:
    """One agent: ``kind`` "uav" or "ugv"; camera pitch in degrees below the horizon."""

    agent_id: str
    kind: str
    camera_pitch_deg: float
    path_length_m: float
    speed_mps: float
    baseline_m: float
    cruise_height_m: float = 1.0  # UAV cruise height above ground (UGV: ignored, body at 0.9 m)
    region: str = "all"  # "all" | "west" | "east": part of the site the route may use


UGV_BODY_HEIGHT = 0.9  # IMU height of the UGV above ground, m (camera ~1.05 m)
UGV_ROOF_HEIGHT = 1.4  # the UAVs take off from the UGV's roof
UAV_LOW_HEIGHT = 3.0  # UAV height at UAV-UGV meeting points


def paper_agents(uav_pitches: tuple[float, float, float] = (45.0, 45.0, 45.0)) -> tuple[AgentSpec, ...]:
    """The four agents of paper Table 4 with the given UAV camera pitches."""
    lengths = (162.47, 161.29, 168.96)
    heights = (10.0, 9.0, 11.0)
    uavs = tuple(
        AgentSpec(f"uav{i + 1}", "uav", uav_pitches[i], lengths[i], 2.0, 0.12, heights[i]) for i in range(3)
    )
    return (*uavs, AgentSpec("ugv", "ugv", 0.0, 106.43, 1.5, 0.30))


@dataclass(frozen=True)
class Scenario:
    """Everything a render needs. ``duration_s`` truncates every agent (None = full trajectories)."""

    name: str
    description: str
    agents: tuple[AgentSpec, ...]
    seed: int = 3
    world_size_m: float = 120.0
    lighting: str = "bright"  # hivemap.sim.conditions preset: "bright" | "somber"
    weather: str = "clear"  # "clear" | "mist" (V=150 m) | "fog" (V=50 m)
    camera: CameraSpec = field(default_factory=CameraSpec)
    imu_rate_hz: float = 200.0
    gnss_rate_hz: float = 5.0
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    gnss_noise: GnssNoise = field(default_factory=GnssNoise)
    duration_s: float | None = None
    origin_lat: float = 30.5286  # geodetic origin of the ENU frame (Wuhan, Hubei), WGS84 degrees
    origin_lon: float = 114.3555
    origin_alt: float = 23.0  # ellipsoidal height, m
    start_time_ns: int = 1_700_000_000_000_000_000  # timestamp of t = 0 (2023-11-14T22:13:20Z)
    hold_s: float = 2.0  # all agents stand still this long at the start (static IMU init)
    # issue 25: agents carry fiducial marker carriers (sim/carriers.py). On in the factory presets, whose
    # climb take-off keeps every carrier metres from the cameras; off here, since a formation take-off
    # puts a carrier right in front of a camera
    markers: bool = False
    # issue 25: with a UGV, the UAVs leave its roof one after the other, the front one first, this many
    # seconds apart, the first one this long after the UGV starts (0: all with the UGV, in formation)
    takeoff_interval_s: float = 0.0
    # issue 25: with a UGV, the UAVs first climb straight up off its roof by this much (the front one 0.5 m
    # more per UAV behind it) and hover while the UGV drives off below them, so they see its carrier from
    # metres away and never from under a metre (0: they ramp up along their route)
    takeoff_climb_m: float = 0.0

    def agent(self, agent_id: str) -> AgentSpec:
        for a in self.agents:
            if a.agent_id == agent_id:
                return a
        raise KeyError(
            f"scenario {self.name!r} has no agent {agent_id!r} (has {[a.agent_id for a in self.agents]})"
        )


def _factory(n: int, lighting: str, weather: str, pitches: tuple[float, float, float]) -> Scenario:
    # the UAVs climb off the UGV's roof one after the other and watch it leave, from a few metres up: they
    # see its carrier (issue 25) and the scene it faces, so the team shares a view from the start
    return Scenario(
        name=f"factory{n:02d}",
        description=f"paper Table 4 Factory {n:02d}: {lighting}, {weather}, UAV camera {pitches} deg",
        agents=paper_agents(pitches),
        lighting=lighting,
        weather=weather,
        markers=True,
        takeoff_interval_s=3.0,
        takeoff_climb_m=3.0,
    )


_P45 = (45.0, 45.0, 45.0)
FACTORY = {
    1: _factory(1, "bright", "clear", _P45),
    2: _factory(2, "bright", "fog", _P45),
    3: _factory(3, "somber", "clear", _P45),
    4: _factory(4, "somber", "fog", _P45),
    5: _factory(5, "bright", "mist", _P45),
    6: _factory(6, "somber", "mist", _P45),
    7: _factory(7, "bright", "clear", (25.0, 25.0, 25.0)),
    8: _factory(8, "bright", "clear", (25.0, 45.0, 75.0)),
}

TINY = replace(
    FACTORY[1],
    name="tiny",
    description="test preset: Factory 01's first 12 s (take-off from the UGV), 320x240 at 10 Hz",
    camera=CameraSpec(320, 240, 215.0, 215.0, 159.5, 119.5, (-0.05, 0.01, 0.0002, -0.0001), 10.0),
    duration_s=12.0,
    # the UAVs take off in formation 0.35 m apart within the 12 s (the climb would take them all): uav2's
    # carrier would fill uav1's image (tracking lost), so no carriers either
    markers=False,
    takeoff_interval_s=0.0,
    takeoff_climb_m=0.0,
)

DISJOINT = Scenario(
    name="disjoint",
    description="two UAVs in disjoint halves of the site (no shared view): false-merge test, 20 s, 320x240",
    agents=(
        AgentSpec("uav1", "uav", 45.0, 40.0, 2.0, 0.12, 6.0, region="west"),
        AgentSpec("uav2", "uav", 45.0, 40.0, 2.0, 0.12, 6.0, region="east"),
    ),
    camera=CameraSpec(320, 240, 215.0, 215.0, 159.5, 119.5, (-0.05, 0.01, 0.0002, -0.0001), 10.0),
    duration_s=20.0,
)

SCENARIOS: dict[str, Scenario] = {s.name: s for s in (*FACTORY.values(), TINY, DISJOINT)}


def get_scenario(name: str) -> Scenario:
    """Preset by name ("factory01".."factory08", "tiny", "disjoint"); KeyError lists the names."""
    key = name.strip().lower().replace(" ", "").replace("_", "")
    if key not in SCENARIOS:
        raise KeyError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    return SCENARIOS[key]
