"""Dataset writer: render a scenario into EuRoC/ASL-layout agent folders plus a manifest.

``render_scenario(scenario, out_dir, backend="auto", agents=None, duration=None)`` plans the trajectories
on the scenario's world, writes for each agent::

    <out>/manifest.yaml
    <out>/<agent>/agent.yaml
    <out>/<agent>/mav0/cam0/{data/<t_ns>.png, data.csv, sensor.yaml}   (cam1 the same)
    <out>/<agent>/mav0/imu0/{data.csv, sensor.yaml}                     200 Hz, Table 2 noise
    <out>/<agent>/mav0/state_groundtruth_estimate0/{data.csv, data_cam0_rate.csv, sensor.yaml}
    <out>/<agent>/mav0/gnss0/{data.csv, nmea.txt, sensor.yaml}          5 Hz, Table 3 noise

and marks an agent complete with ``<agent>/.render_complete`` (a fingerprint of its configuration), so a
re-run skips complete agents and, for an interrupted agent, renders only frames whose PNGs are missing
(frames are written atomically and rendered deterministically from the seed).

Extrinsics (``T_BS`` = body_from_sensor, body = IMU frame x forward, y left, z up): cam0 is pitched
down by the agent's camera pitch; cam1 = cam0 shifted by the baseline along cam0's x axis (right).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from hivemap.sim.scenarios import AgentSpec, Scenario
from hivemap.sim.sensor_files import stereo_extrinsics as stereo_extrinsics
from hivemap.sim.sensor_files import (
    timestamps_ns,
    write_agent_sensors,
    write_marker_layout,
    write_text,
)
from hivemap.sim.sensors import (
    sample_times,
)
from hivemap.sim.trajectories import Trajectory, TrajectoryPlan, plan_trajectories

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
COMPLETE_MARK = ".render_complete"
STARTED_MARK = ".render_started"
FORMAT_VERSION = 1

# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------


@dataclass
class AgentReport:
    agent_id: str
    n_frames: int
    rendered: int
    skipped: bool
    seconds: float
    bytes: int


def fingerprint(scenario: Scenario, spec: AgentSpec, duration: float, traj: Trajectory | None = None) -> str:
    """Hash of everything an agent's files depend on (config, and the planned camera poses)."""
    d = {"v": FORMAT_VERSION, "scenario": asdict(scenario), "agent": asdict(spec), "duration": duration}
    if scenario.markers:
        from hivemap.sim.carriers import CarrierDesign

        # the carriers' layout is drawn in every frame: a render begun with another one is not resumed
        d["carriers"] = asdict(CarrierDesign())
    h = hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode())
    if traj is not None:
        t = sample_times(duration, scenario.camera.rate_hz)
        h.update(np.round(traj.world_from_body(t), 9).tobytes())
    return h.hexdigest()[:16]


def _dir_bytes(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _condition_presets(scenario: Scenario) -> tuple[Any, Any]:
    from hivemap.sim import conditions

    def get(kind: str, name: str) -> Any:
        cls = getattr(conditions, kind)
        for attr in ("preset", "from_name", "named"):
            f = getattr(cls, attr, None)
            if callable(f):
                return f(name)
        for table in (kind.upper(), f"{kind.upper()}_PRESETS", f"{kind}s".upper()):
            tab = getattr(conditions, table, None)
            if isinstance(tab, dict) and name in tab:
                return tab[name]
        v = getattr(cls, name.upper(), None)
        if v is not None:
            return v
        return name  # let apply_conditions resolve names itself

    return get("Lighting", scenario.lighting), get("Weather", scenario.weather)


def _fast_texture_filtering(renderer: Any) -> None:
    """Work-around: anisotropic filtering on Mesa llvmpipe costs ~400x at grazing angles (measured:
    UGV 0-deg frame 640x480 3.6 s with anisotropy 16, 2 or 4; 8.6 ms with 1). Trilinear mipmapping
    stays on."""
    tex = getattr(renderer, "tex", None)
    if tex is not None and float(getattr(tex, "anisotropy", 1.0)) > 1.0:
        log.info("texture anisotropy %.0f -> 1 (too slow on llvmpipe)", tex.anisotropy)
        tex.anisotropy = 1.0


def render_agent(
    world: Any,
    scenario: Scenario,
    spec: AgentSpec,
    agent_index: int,
    traj: Trajectory,
    agent_dir: Path,
    backend: str = "auto",
    duration: float | None = None,
    progress: bool = True,
    renderer_factory: Callable[..., Any] | None = None,
    team: dict[str, Trajectory] | None = None,
) -> AgentReport:
    """Render (or resume) one agent into ``agent_dir``; with ``scenario.markers`` every frame also draws
    the marker carriers of the other agents of ``team`` (all trajectories of the plan) at their poses."""
    dur = traj.duration if duration is None else min(duration, traj.duration)
    fp = fingerprint(scenario, spec, dur, traj)
    mark = agent_dir / COMPLETE_MARK
    started = agent_dir / STARTED_MARK
    t_start = time.perf_counter()
    if mark.is_file() and mark.read_text().strip() == fp:
        n = len(sample_times(dur, scenario.camera.rate_hz))
        log.info("%s: already complete, skipped", spec.agent_id)
        return AgentReport(spec.agent_id, n, 0, True, 0.0, _dir_bytes(agent_dir))
    if mark.exists():
        mark.unlink()
    if started.is_file() and started.read_text().strip() != fp:
        # an earlier render with another configuration or trajectory: its frames cannot be reused
        log.warning(
            "%s: existing frames were rendered for another configuration; re-rendering", spec.agent_id
        )
        for cam in ("cam0", "cam1"):
            shutil.rmtree(agent_dir / "mav0" / cam / "data", ignore_errors=True)
    elif not started.is_file() and (agent_dir / "mav0").exists():
        for cam in ("cam0", "cam1"):
            shutil.rmtree(agent_dir / "mav0" / cam / "data", ignore_errors=True)
    write_text(started, fp + "\n")
    write_agent_sensors(agent_dir, scenario, spec, agent_index, traj, dur)

    import cv2

    from hivemap.sim.conditions import apply_conditions

    if renderer_factory is None:
        from hivemap.sim.render import make_renderer

        renderer_factory = make_renderer
    lighting, weather = _condition_presets(scenario)
    cam = scenario.camera.pinhole()
    T0, T1 = stereo_extrinsics(spec)
    t_cam = sample_times(dur, scenario.camera.rate_hz)
    cam_ns = timestamps_ns(t_cam, scenario.start_time_ns)
    W = traj.world_from_body(t_cam)
    dirs = [agent_dir / "mav0" / "cam0" / "data", agent_dir / "mav0" / "cam1" / "data"]
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
    todo = [i for i in range(len(t_cam)) if not all((d / f"{cam_ns[i]}.png").is_file() for d in dirs)]
    rendered = 0
    scene, team_poses = None, {}
    if scenario.markers and team:
        from hivemap.sim.carriers import DICTIONARY, CarrierScene, team_geometry

        scene = CarrierScene(team_geometry(scenario), len(world.layers), world.layers.shape[1], DICTIONARY)
        team_poses = {k: tr.world_from_body(t_cam) for k, tr in team.items() if k != spec.agent_id}
    if todo:
        extra = {} if scene is None else {"extra_layers": scene.layers}
        renderer = renderer_factory(world, cam, backend=backend, **extra)
        _fast_texture_filtering(renderer)
        try:
            from tqdm import tqdm

            bar = tqdm(todo, desc=f"{scenario.name}/{spec.agent_id}", unit="frame", disable=not progress)
            for i in bar:
                quads = (
                    None
                    if scene is None
                    else scene.quads({k: P[i] for k, P in team_poses.items()}, spec.agent_id)
                )
                for c, (T_BS, d) in enumerate(zip((T0, T1), dirs, strict=True)):
                    gray, depth = renderer.render(W[i] @ T_BS, quads)
                    rng = np.random.default_rng([scenario.seed, agent_index, int(i), c, 7])
                    img = apply_conditions(gray, depth, lighting, weather, rng)
                    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img, dtype=np.uint8))
                    if not ok:
                        raise RuntimeError("PNG encoding failed")
                    out = d / f"{cam_ns[i]}.png"
                    tmp = d / f".{cam_ns[i]}.png.tmp"
                    tmp.write_bytes(buf.tobytes())
                    os.replace(tmp, out)
                rendered += 1
        finally:
            renderer.close()
    write_text(mark, fp + "\n")
    secs = time.perf_counter() - t_start
    return AgentReport(spec.agent_id, len(t_cam), rendered, False, secs, _dir_bytes(agent_dir))


def manifest_dict(
    scenario: Scenario, reports: dict[str, dict[str, Any]], duration: float | None
) -> dict[str, Any]:
    c = scenario.camera
    return {
        "format": "hivemap-euroc",
        "format_version": FORMAT_VERSION,
        "scenario": scenario.name,
        "description": scenario.description,
        "seed": scenario.seed,
        "world_size_m": scenario.world_size_m,
        "lighting": scenario.lighting,
        "weather": scenario.weather,
        "markers": scenario.markers,
        "takeoff": {"interval_s": scenario.takeoff_interval_s, "climb_m": scenario.takeoff_climb_m},
        "duration_s": duration,
        "start_time_ns": scenario.start_time_ns,
        "origin": {"lat": scenario.origin_lat, "lon": scenario.origin_lon, "alt": scenario.origin_alt},
        "camera": {
            "width": c.width,
            "height": c.height,
            "fx": c.fx,
            "fy": c.fy,
            "cx": c.cx,
            "cy": c.cy,
            "dist": list(c.dist),
            "rate_hz": c.rate_hz,
        },  # fmt: skip
        "imu_rate_hz": scenario.imu_rate_hz,
        "gnss_rate_hz": scenario.gnss_rate_hz,
        "agents": [
            {
                "id": a.agent_id,
                "kind": a.kind,
                "path": a.agent_id,
                "camera_pitch_deg": a.camera_pitch_deg,
                "baseline_m": a.baseline_m,
                **reports.get(a.agent_id, {"complete": False}),
            }  # fmt: skip
            for a in scenario.agents
            if a.agent_id in reports
        ],
    }


class RenderMismatch(ValueError):
    """The output folder already holds agents of another world (scenario, seed or conditions)."""


# what makes two renders the same world: resuming into a folder that differs in one of them would mix
# frames of two worlds in one dataset
_SAME_WORLD = (
    "scenario",
    "seed",
    "world_size_m",
    "lighting",
    "weather",
    "camera",
    "start_time_ns",
    "markers",
    "takeoff",
)
# what a manifest written before a key existed meant by its absence
_SAME_WORLD_BEFORE = {"markers": False, "takeoff": {"interval_s": 0.0, "climb_m": 0.0}}


def _check_same_world(path: Path, old: dict[str, Any], new: dict[str, Any]) -> None:
    if not old.get("agents"):
        return
    for key in _SAME_WORLD:
        was = old.get(key, _SAME_WORLD_BEFORE.get(key, new[key]))
        if was != new[key]:
            raise RenderMismatch(
                f"{path} holds a render with {key} = {was!r}, not {new[key]!r}; render into another --out"
            )


def check_render(path: Path, scenario: Scenario) -> dict[str, Any]:
    """The manifest at ``path``; :class:`RenderMismatch` unless its render is of ``scenario``'s world (a
    render made before a preset changed is not silently reused)."""
    old = yaml.safe_load(path.read_text()) or {}
    _check_same_world(path, old, manifest_dict(scenario, {}, scenario.duration_s))
    return old


@dataclass
class RenderResult:
    out_dir: Path
    plan: TrajectoryPlan
    agents: list[AgentReport]
    seconds: float


@functools.lru_cache(maxsize=2)
def cached_world(seed: int, size_m: float) -> Any:
    """``generate_world(seed, size_m)``, cached per process (generation takes seconds)."""
    from hivemap.sim.world import generate_world

    return generate_world(seed, size_m)


def render_scenario(
    scenario: Scenario,
    out_dir: str | Path,
    backend: str = "auto",
    agents: list[str] | None = None,
    duration: float | None = None,
    progress: bool = True,
    world: Any = None,
) -> RenderResult:
    """Render ``scenario`` (optionally only some agents / a shorter duration) into ``out_dir``."""
    t0 = time.perf_counter()
    if duration is not None:
        scenario = replace(scenario, duration_s=duration)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if world is None:
        world = cached_world(scenario.seed, scenario.world_size_m)
    plan = plan_trajectories(world, scenario)
    wanted = agents if agents else [a.agent_id for a in scenario.agents]
    for a in wanted:
        scenario.agent(a)  # KeyError for unknown ids
    # Keep entries of agents rendered earlier into the same folder.
    reports: dict[str, dict[str, Any]] = {}
    man_path = out / "manifest.yaml"
    if man_path.is_file():
        try:
            old = yaml.safe_load(man_path.read_text()) or {}
        except yaml.YAMLError:
            old = {}
            log.warning("ignoring unreadable %s", man_path)
        _check_same_world(man_path, old, manifest_dict(scenario, {}, scenario.duration_s))
        try:
            if old.get("scenario") == scenario.name:
                for a in old.get("agents", []):
                    keep = ("complete", "n_frames", "path_length_m", "duration_s")
                    reports[str(a["id"])] = {k: v for k, v in a.items() if k in keep}
        except (KeyError, TypeError, AttributeError):
            log.warning("ignoring unreadable %s", man_path)
    results = []
    for a in wanted:
        reports.setdefault(a, {"complete": False})
    write_text(
        man_path, yaml.safe_dump(manifest_dict(scenario, reports, scenario.duration_s), sort_keys=False)
    )
    for idx, spec in enumerate(scenario.agents):
        if spec.agent_id not in wanted:
            continue
        traj = plan.trajectories[spec.agent_id]
        dur = traj.duration if scenario.duration_s is None else min(scenario.duration_s, traj.duration)
        write_marker_layout(out / spec.agent_id, scenario)
        rep = render_agent(
            world,
            scenario,
            spec,
            idx,
            traj,
            out / spec.agent_id,
            backend,
            dur,
            progress,
            team=plan.trajectories,
        )
        results.append(rep)
        reports[spec.agent_id] = {
            "complete": True,
            "n_frames": rep.n_frames,
            "path_length_m": round(traj.path_length(dur), 3),
            "duration_s": round(float(dur), 6),
        }
        write_text(
            man_path, yaml.safe_dump(manifest_dict(scenario, reports, scenario.duration_s), sort_keys=False)
        )
    return RenderResult(out, plan, results, time.perf_counter() - t0)
