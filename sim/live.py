"""A simulated agent rendered on the fly (issue 26, closed loop): ``LiveSim`` moves one agent of a scenario
under :class:`~hivemap.sim.live_control.Controller` and renders its stereo frames, IMU samples and GNSS
fixes as it goes, with the renderer, camera, IMU and GNSS models and calibration of the rendered datasets
(:mod:`hivemap.sim.dataset`).

Time is the simulation's own: each :meth:`LiveSim.step` advances one camera period whatever the wall clock
says, so a slow machine only makes the run slower, and the run is deterministic given the same
advisories at the same frames. The agent starts where the scenario's planned trajectory starts (the UAVs on
the UGV's roof), stands still for the scenario's hold time (its take-off delay included), then follows its
controller; the motion is replanned every ``replan_period_s`` (:class:`~hivemap.sim.live_motion.LiveMotion`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.sim.live_control import Controller, ControlOptions, RoadPaths, WorldAdvisory
from hivemap.sim.live_motion import LiveMotion, MotionLimits

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]


@dataclass(frozen=True)
class LiveOptions:
    """One live agent: which scenario agent, which world, how long, how it moves."""

    scenario: str = "factory01"  # preset name or scenario .toml
    agent: str = "uav1"
    seed: int | None = None  # world seed (None: the scenario's)
    duration_s: float = 120.0  # mission time (simulated)
    hold_s: float | None = None  # standstill at the start (None: the scenario's, plus take-off delay)
    backend: str = "auto"  # renderer: auto | gl | numpy
    replan_period_s: float = 0.25
    limits: MotionLimits = field(default_factory=MotionLimits)
    control: ControlOptions = field(default_factory=ControlOptions)


@dataclass(frozen=True)
class SimFrame:
    """One camera period's sensor data; ``stamp`` and the IMU/GNSS times are absolute seconds."""

    index: int
    t: float  # simulated seconds from the start
    stamp: float
    left: U8
    right: U8
    imu: F64  # (N, 7): t, gyro xyz, accel xyz (body frame)
    fixes: list[tuple[float, F64, F64]]  # (t, enu (3,), covariance (3, 3))
    world_from_body: F64


class _GaussMarkov:
    """The bias process of :func:`hivemap.sim.sensors._gauss_markov`, one sample at a time."""

    def __init__(
        self, dt: float, sigma_rw: float, tau: float, turn_on: float, rng: np.random.Generator
    ) -> None:
        self.phi = math.exp(-dt / tau)
        self.sd = math.sqrt(sigma_rw**2 * tau / 2.0 * (1.0 - math.exp(-2.0 * dt / tau)))
        self.b0 = rng.normal(0.0, turn_on, 3) if turn_on > 0 else np.zeros(3)
        self.cur = np.zeros(3)
        self.rng = rng
        self.n = 0

    def next(self) -> F64:
        if self.n > 0 and self.sd > 0:
            self.cur = self.phi * self.cur + self.rng.normal(0.0, self.sd, 3)
        self.n += 1
        return self.cur + self.b0


def start_pose(world: Any, scenario: Any, agent_id: str) -> tuple[F64, float, float]:
    """(position, yaw, hold seconds) where and how long the scenario's planned agent starts."""
    from hivemap.sim.takeoff import takeoff_plan
    from hivemap.sim.trajectories import plan_trajectories

    plan = plan_trajectories(world, scenario)
    T = plan.trajectories[agent_id].world_from_body(0.0)[0]
    yaw = math.atan2(T[1, 0], T[0, 0])
    return T[:3, 3].copy(), yaw, takeoff_plan(scenario)[agent_id].leave_t


def road_lines(world: Any, kind: str) -> list[F64]:
    """Centre lines a kind may travel: the roads (UGV), plus the air lines across blocks (UAV)."""
    from hivemap.sim.roads import _with_air_edges, build_road_graph

    snap = max(2.0, float(world.road_width))
    g = build_road_graph(list(world.roads), snap_tol=snap)
    if kind == "uav":
        g = _with_air_edges(g, list(world.roads), snap, float(world.road_width))
    return [np.asarray(e.pts, dtype=np.float64) for e in g.edges]


class LiveSim:
    """One agent of a scenario, moved and rendered frame by frame (see the module docstring)."""

    def __init__(self, options: LiveOptions, world: Any = None) -> None:
        from hivemap.sim.dataset import cached_world
        from hivemap.sim.scenario_file import resolve_scenario

        self.options = options
        # live agents draw no carriers and leave the roof under their controller, not by the planned climb
        sc = resolve_scenario(options.scenario, options.seed)
        sc = replace(sc, markers=False, takeoff_interval_s=0.0, takeoff_climb_m=0.0)
        self.scenario = sc
        self.spec = sc.agent(options.agent)  # KeyError naming the scenario's agents
        self.index = [a.agent_id for a in sc.agents].index(self.spec.agent_id)
        self.world = cached_world(sc.seed, sc.world_size_m) if world is None else world
        p0, yaw0, hold = start_pose(self.world, sc, self.spec.agent_id)
        self.hold_s = hold if options.hold_s is None else options.hold_s
        self.motion = LiveMotion(self.spec.agent_id, self.spec.kind, p0, yaw0, options.limits)
        uav = self.spec.kind == "uav"
        co = options.control
        # a UGV keeps clear of obstacles, passing them within its road, a metre from the road's edge
        paths = RoadPaths(road_lines(self.world, self.spec.kind), co.node_spacing_m, co.join_m,
                          () if uav else self.world.boxes, co.obstacle_margin_m,
                          float(self.world.road_width) / 2 - 1.0)  # fmt: skip
        self.controller = Controller(
            self.spec.kind, self.spec.speed_mps, paths, self.spec.cruise_height_m if uav else 0.0,
            self.world.boxes if uav else (), options.control,
            None if uav else float(self.world.road_width) / 2,
        )  # fmt: skip
        from hivemap.sim.sensor_files import gnss_rng, imu_rng, stereo_extrinsics

        self.T_BS = stereo_extrinsics(self.spec)
        self.camera = sc.camera.pinhole()
        self.rate = float(sc.camera.rate_hz)
        self.t0 = sc.start_time_ns * 1e-9
        rng_imu = imu_rng(sc, self.index)
        dt = 1.0 / sc.imu_rate_hz
        n = sc.imu_noise
        self._bg = _GaussMarkov(dt, n.gyroscope_random_walk, n.gyroscope_bias_correlation_time,
                                n.gyroscope_turn_on_bias_sigma, rng_imu)  # fmt: skip
        self._ba = _GaussMarkov(dt, n.accelerometer_random_walk, n.accelerometer_bias_correlation_time,
                                n.accelerometer_turn_on_bias_sigma, rng_imu)  # fmt: skip
        self._rng_imu = rng_imu
        self._rng_gnss = gnss_rng(sc, self.index)
        self._next_imu = 0  # index of the next IMU sample (time = index / rate)
        self._next_fix = 0
        self._last_replan = -math.inf
        self.frame_index = 0
        self._renderer: Any = None
        self.gt_t: list[float] = []
        self.gt_poses: list[F64] = []

    # ------------------------------------------------------------------------------------------ sensors
    def _imu_until(self, t: float) -> F64:
        sc = self.scenario
        rate = sc.imu_rate_hz
        last = int(math.floor(t * rate + 1e-9))
        if last < self._next_imu:
            return np.zeros((0, 7))
        k = np.arange(self._next_imu, last + 1)
        self._next_imu = last + 1
        ts = k / rate
        traj = self.motion.trajectory
        gyro = traj.angular_velocity(ts)
        acc = traj.specific_force(ts)
        n = sc.imu_noise
        sg, sa = n.gyroscope_noise_density * math.sqrt(rate), n.accelerometer_noise_density * math.sqrt(rate)
        rows = np.zeros((len(k), 7))
        for j in range(len(k)):
            rows[j, 1:4] = gyro[j] + self._bg.next() + (self._rng_imu.normal(0.0, sg, 3) if sg > 0 else 0.0)
            rows[j, 4:7] = acc[j] + self._ba.next() + (self._rng_imu.normal(0.0, sa, 3) if sa > 0 else 0.0)
        rows[:, 0] = self.t0 + ts
        return rows

    def _fixes_until(self, t: float) -> list[tuple[float, F64, F64]]:
        sc = self.scenario
        rate, noise = sc.gnss_rate_hz, sc.gnss_noise
        last = int(math.floor(t * rate + 1e-9))
        out = []
        cov = np.diag([noise.sigma_horizontal**2] * 2 + [noise.sigma_vertical**2])
        for k in range(self._next_fix, last + 1):
            tk = k / rate
            truth = self.motion.trajectory.position(tk)[0]
            err = np.concatenate([self._rng_gnss.normal(0.0, noise.sigma_horizontal, 2),
                                  self._rng_gnss.normal(0.0, noise.sigma_vertical, 1)])  # fmt: skip
            out.append((self.t0 + tk, truth + err, cov.copy()))
        self._next_fix = max(self._next_fix, last + 1)
        return out

    def _render(self, i: int, W: F64) -> tuple[U8, U8]:
        from hivemap.sim.conditions import apply_conditions
        from hivemap.sim.dataset import _condition_presets, _fast_texture_filtering

        if self._renderer is None:
            from hivemap.sim.render import make_renderer

            self._renderer = make_renderer(self.world, self.camera, backend=self.options.backend)
            _fast_texture_filtering(self._renderer)
            self._conditions = _condition_presets(self.scenario)
        lighting, weather = self._conditions
        out = []
        for c, T_BS in enumerate(self.T_BS):
            gray, depth = self._renderer.render(W @ T_BS)
            rng = np.random.default_rng([self.scenario.seed, self.index, int(i), c, 7])
            out.append(np.ascontiguousarray(apply_conditions(gray, depth, lighting, weather, rng), np.uint8))
        return out[0], out[1]

    # ------------------------------------------------------------------------------------------ stepping
    def step(self) -> SimFrame:
        """Render the next frame with the IMU samples and GNSS fixes since the previous one."""
        i = self.frame_index
        t = i / self.rate
        imu = self._imu_until(t)
        fixes = self._fixes_until(t)
        W = self.motion.trajectory.world_from_body(t)[0]
        left, right = self._render(i, W)
        self.gt_t.append(self.t0 + t)
        self.gt_poses.append(W)
        self.frame_index += 1
        return SimFrame(i, t, self.t0 + t, left, right, imu, fixes, W)

    @property
    def t(self) -> float:
        """Simulated time of the last frame."""
        return (self.frame_index - 1) / self.rate

    def advise(self, advisory: WorldAdvisory) -> None:
        self.controller.advise(advisory)

    def steer(self) -> bool:
        """After a frame: replan the motion from the controller's command when a period has passed (never
        during the hold); True if it replanned."""
        t = self.t
        if t < self.hold_s or t - self._last_replan < self.options.replan_period_s - 1e-9:
            return False
        P, Y = self.motion.state(t)
        v, heading = self.controller.command(t, P[0], float(Y[0]))
        self.motion.replan(t, v, heading)
        self._last_replan = t
        return True

    def intent_cam(self, world_from_body: F64) -> F64:
        """The controller's intent (:meth:`Controller.intent`) at the frame of true pose ``world_from_body``,
        in that frame's cam0 frame (zero during the hold)."""
        if self.t < self.hold_s:
            return np.zeros(3)
        W = np.asarray(world_from_body, dtype=np.float64)
        v = self.controller.intent(W[:3, 3])
        return (W @ self.T_BS[0])[:3, :3].T @ v

    def path_length(self) -> float:
        P = np.array([T[:3, 3] for T in self.gt_poses]).reshape(-1, 3)
        return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) if len(P) > 1 else 0.0

    def write_calibration(self, out: Path) -> Path:
        """The dataset's ``mav0`` sensor files (cameras, IMU, GNSS) under ``out``; returns the mav0 dir."""
        from hivemap.sim.sensor_files import camera_sensor_yaml, gnss_sensor_yaml, imu_sensor_yaml, write_text

        mav0 = out / "mav0"
        sc, spec = self.scenario, self.spec
        for name, T in zip(("cam0", "cam1"), self.T_BS, strict=True):
            comment = f"hivemap {spec.kind} {name}, pitch {spec.camera_pitch_deg:g} deg"
            write_text(mav0 / name / "sensor.yaml", camera_sensor_yaml(sc, T, comment))
        write_text(mav0 / "imu0" / "sensor.yaml", imu_sensor_yaml(sc))
        write_text(mav0 / "gnss0" / "sensor.yaml", gnss_sensor_yaml(sc))
        return mav0

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
