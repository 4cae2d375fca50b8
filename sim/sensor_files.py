"""An agent's EuRoC/ASL sensor files (everything a render writes but the images): extrinsics, IMU, ground
truth, GNSS (csv + NMEA), the sensor.yaml files, agent.yaml, and the team's marker layout."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from hivemap.maps.geometry import quat_wxyz_from_rotmat
from hivemap.sim.scenarios import AgentSpec, Scenario
from hivemap.sim.sensors import (
    GeodeticOrigin,
    GnssData,
    ImuData,
    enu_to_geodetic,
    format_gpgga,
    sample_times,
    simulate_gnss,
    simulate_imu,
)
from hivemap.sim.trajectories import Trajectory

F64 = NDArray[np.float64]

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
CAM_HEADER = "#timestamp [ns],filename"
GNSS_HEADER = "#timestamp [ns],east,north,up,sigma_h,sigma_v"


# ---------------------------------------------------------------------------------------------
# Extrinsics
# ---------------------------------------------------------------------------------------------


def camera_rotation(pitch_deg: float) -> F64:
    """body_from_cam rotation for a forward camera pitched ``pitch_deg`` below the horizon."""
    th = np.deg2rad(pitch_deg)
    x_c = np.array([0.0, -1.0, 0.0])
    z_c = np.array([np.cos(th), 0.0, -np.sin(th)])
    y_c = np.cross(z_c, x_c)
    return np.stack([x_c, y_c, z_c], axis=1)


def stereo_extrinsics(spec: AgentSpec) -> tuple[F64, F64]:
    """(T_BS cam0, T_BS cam1) for an agent: cam0 left, cam1 = cam0 + baseline along cam x."""
    R = camera_rotation(spec.camera_pitch_deg)
    b = spec.baseline_m
    c0 = np.array([0.25, b / 2, 0.15]) if spec.kind == "ugv" else np.array([0.10, b / 2, -0.05])
    T0 = np.eye(4)
    T0[:3, :3] = R
    T0[:3, 3] = c0
    T1 = T0.copy()
    T1[:3, 3] = c0 + R[:, 0] * b
    return T0, T1


def timestamps_ns(t: F64, start_ns: int) -> NDArray[np.int64]:
    """Seconds from the start -> absolute ns (rounded to the ns)."""
    return start_ns + np.round(np.asarray(t) * 1e9).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------------------------


def _fmt(x: float) -> str:
    return repr(float(x))


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _csv(header: str, t_ns: Iterable[int], rows: F64) -> str:
    lines = [header]
    for t, r in zip(t_ns, rows, strict=True):
        lines.append(str(int(t)) + "," + ",".join(_fmt(v) for v in r))
    return "\n".join(lines) + "\n"


def _matrix_yaml(T: F64) -> str:
    vals = [f"{v:.12g}" for v in np.asarray(T, dtype=np.float64).reshape(-1)]
    rows = [", ".join(vals[i : i + 4]) for i in range(0, 16, 4)]
    return "T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def camera_sensor_yaml(scenario: Scenario, T_BS: F64, comment: str) -> str:
    c = scenario.camera
    return (
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        f"comment: {comment}\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        + _matrix_yaml(T_BS)
        + "\n# Camera specific definitions.\n"
        f"rate_hz: {c.rate_hz:g}\n"
        f"resolution: [{c.width}, {c.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{c.fx:g}, {c.fy:g}, {c.cx:g}, {c.cy:g}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(f'{d:g}' for d in c.dist)}]\n"
    )


def imu_sensor_yaml(scenario: Scenario) -> str:
    n = scenario.imu_noise
    return (
        "#Default imu sensor yaml file\n"
        "sensor_type: imu\n"
        "comment: hivemap simulated IMU (paper Table 2 noise, RotorS model)\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        + _matrix_yaml(np.eye(4))
        + f"rate_hz: {scenario.imu_rate_hz:g}\n\n"
        "# inertial sensor noise model parameters (static)\n"
        f"gyroscope_noise_density: {n.gyroscope_noise_density:g}  # [ rad / s / sqrt(Hz) ]\n"
        f"gyroscope_random_walk: {n.gyroscope_random_walk:g}  # [ rad / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_noise_density: {n.accelerometer_noise_density:g}  # [ m / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_random_walk: {n.accelerometer_random_walk:g}  # [ m / s^3 / sqrt(Hz) ]\n"
        f"gyroscope_bias_correlation_time: {n.gyroscope_bias_correlation_time:g}  # [ s ]\n"
        f"accelerometer_bias_correlation_time: {n.accelerometer_bias_correlation_time:g}  # [ s ]\n"
        f"gyroscope_turn_on_bias_sigma: {n.gyroscope_turn_on_bias_sigma:g}  # [ rad / s ]\n"
        f"accelerometer_turn_on_bias_sigma: {n.accelerometer_turn_on_bias_sigma:g}  # [ m / s^2 ]\n"
    )  # fmt: skip


def gnss_sensor_yaml(scenario: Scenario) -> str:
    g = scenario.gnss_noise
    return (
        "sensor_type: gnss\n"
        "comment: hivemap simulated GNSS (paper Table 3 noise); antenna at the body origin\n"
        + _matrix_yaml(np.eye(4))
        + f"rate_hz: {scenario.gnss_rate_hz:g}\n"
        f"sigma_horizontal: {g.sigma_horizontal:g}  # [ m ] per axis (east, north)\n"
        f"sigma_vertical: {g.sigma_vertical:g}  # [ m ]\n"
        "frame: ENU  # data.csv east, north, up [m] around origin\n"
        f"origin: {{lat: {scenario.origin_lat!r}, lon: {scenario.origin_lon!r}, "
        f"alt: {scenario.origin_alt!r}}}\n"
        "nmea: nmea.txt  # one $GPGGA per data.csv row; altitude = ellipsoidal height (geoid separation 0)\n"
    )


GT_SENSOR_YAML = (
    "sensor_type: visual-inertial\n"
    "comment: hivemap simulation ground truth (exact); pose = world_from_body (body = IMU), world z up\n"
    + _matrix_yaml(np.eye(4))
)


def groundtruth_rows(traj: Trajectory, t: F64, imu: ImuData | None) -> F64:
    """(N, 16) EuRoC ground-truth columns for times t (biases from ``imu`` at matching rows)."""
    T = traj.world_from_body(t)
    q = np.array([quat_wxyz_from_rotmat(R) for R in T[:, :3, :3]])
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    v = traj.velocity(t)
    if imu is not None:
        idx = np.clip(np.searchsorted(imu.t, t - 1e-9), 0, len(imu.t) - 1)
        bg, ba = imu.bias_gyro[idx], imu.bias_accel[idx]
    else:
        bg = ba = np.zeros((len(t), 3))
    return np.concatenate([T[:, :3, 3], q, v, bg, ba], axis=1)


def imu_rng(scenario: Scenario, agent_index: int) -> np.random.Generator:
    """The generator of an agent's IMU noise (offline files and the live simulator alike)."""
    return np.random.default_rng([scenario.seed, agent_index, 1])


def gnss_rng(scenario: Scenario, agent_index: int) -> np.random.Generator:
    """The generator of an agent's GNSS noise: seeded by the world seed and the agent, so every preset of
    one seed (same routes) draws the same fixes, offline and live."""
    return np.random.default_rng([scenario.seed, agent_index, 2])


def write_agent_sensors(
    agent_dir: Path, scenario: Scenario, spec: AgentSpec, agent_index: int, traj: Trajectory, duration: float
) -> dict[str, Any]:
    """Everything but the images: IMU, ground truth, GNSS, sensor.yaml files, agent.yaml, camera csvs."""
    mav0 = agent_dir / "mav0"
    start = scenario.start_time_ns
    rng_imu = imu_rng(scenario, agent_index)
    rng_gnss = gnss_rng(scenario, agent_index)
    imu = simulate_imu(traj, scenario.imu_rate_hz, scenario.imu_noise, rng_imu, duration)
    imu_ns = timestamps_ns(imu.t, start)
    write_text(mav0 / "imu0" / "data.csv", _csv(IMU_HEADER, imu_ns, np.concatenate([imu.gyro, imu.accel], 1)))
    write_text(mav0 / "imu0" / "sensor.yaml", imu_sensor_yaml(scenario))

    gt_dir = mav0 / "state_groundtruth_estimate0"
    write_text(gt_dir / "data.csv", _csv(GT_HEADER, imu_ns, groundtruth_rows(traj, imu.t, imu)))
    t_cam = sample_times(duration, scenario.camera.rate_hz)
    cam_ns = timestamps_ns(t_cam, start)
    write_text(gt_dir / "data_cam0_rate.csv", _csv(GT_HEADER, cam_ns, groundtruth_rows(traj, t_cam, imu)))
    write_text(gt_dir / "sensor.yaml", GT_SENSOR_YAML)

    gnss = simulate_gnss(traj, scenario.gnss_rate_hz, scenario.gnss_noise, rng_gnss, duration)
    write_gnss(mav0 / "gnss0", scenario, gnss)

    T0, T1 = stereo_extrinsics(spec)
    for name, T in (("cam0", T0), ("cam1", T1)):
        write_text(
            mav0 / name / "sensor.yaml",
            camera_sensor_yaml(
                scenario, T, f"hivemap {spec.kind} {name}, pitch {spec.camera_pitch_deg:g} deg"
            ),
        )
        text = CAM_HEADER + "\n" + "".join(f"{t},{t}.png\n" for t in cam_ns)
        write_text(mav0 / name / "data.csv", text)
    info = {
        "agent_id": spec.agent_id,
        "kind": spec.kind,
        "scenario": scenario.name,
        "camera_pitch_deg": spec.camera_pitch_deg,
        "baseline_m": spec.baseline_m,
        "path_length_m": round(traj.path_length(duration), 3),
        "duration_s": round(float(duration), 6),
        "n_frames": len(cam_ns),
        "lighting": scenario.lighting,
        "weather": scenario.weather,
    }
    write_text(agent_dir / "agent.yaml", yaml.safe_dump(info, sort_keys=False))
    return info


def write_gnss(gdir: Path, scenario: Scenario, gnss: GnssData) -> None:
    t_ns = timestamps_ns(gnss.t, scenario.start_time_ns)
    n = len(t_ns)
    rows = np.concatenate([gnss.enu, np.full((n, 1), gnss.sigma_h), np.full((n, 1), gnss.sigma_v)], axis=1)
    write_text(gdir / "data.csv", _csv(GNSS_HEADER, t_ns, rows))
    origin = GeodeticOrigin(scenario.origin_lat, scenario.origin_lon, scenario.origin_alt)
    lla = enu_to_geodetic(gnss.enu, origin)
    write_text(
        gdir / "nmea.txt",
        "".join(format_gpgga(int(t), *row) + "\r\n" for t, row in zip(t_ns, lla, strict=True)),
    )
    write_text(gdir / "sensor.yaml", gnss_sensor_yaml(scenario))


def write_marker_layout(agent_dir: Path, scenario: Scenario) -> None:
    """``markers.yaml`` with the whole team's carriers when the scenario has markers (else none)."""
    from hivemap.maps.markers import LAYOUT_FILE, save_layout
    from hivemap.sim.carriers import team_carriers

    path = agent_dir / LAYOUT_FILE
    if not scenario.markers:
        path.unlink(missing_ok=True)
        return
    agent_dir.mkdir(parents=True, exist_ok=True)
    save_layout(path, team_carriers(scenario, {a.agent_id: stereo_extrinsics(a)[0] for a in scenario.agents}))
