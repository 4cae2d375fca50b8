"""Experiment runner of the paper's Tables 5-8 (issue 7): scenarios x GNSS modes -> results JSON -> report.

``run_experiment(options)`` renders (or reuses) each scenario, runs each mode and writes
``<out>/results/<scenario>/<mode>.json`` (skipped when it already exists: the run is resumable), then
``<out>/report.md`` and ``<out>/report.html`` (:mod:`hivemap.eval.report`).

Modes (paper Table 8):

- ``single``: each agent alone, offline (``hivemap agent --offline``), GNSS denied ("ORB-SLAM3");
- ``single+gnss``: each agent alone, offline, one valid fix every 20 s (``--gnss every:20s``, the fixes of
  ``challenged1``: "ORB-SLAM3 fusion GPS" is the single-agent counterpart of GNSS co-location);
- ``denied``: co-location, every agent streams to one server, no GNSS;
- ``challenged1``: co-location, every agent one valid fix every 20 s (``--gnss every:20s``);
- ``challenged2``: co-location, UAVs 4 random fixes each (``--gnss random:4``), the UGV none.

Per agent the headline estimate is the trajectory the agent ends with: its ``local.tum`` (every tracked
frame, body poses; in co-location modes after the server's corrections were fused). The alignment is
explicit per agent: none when the agent used GNSS (its local frame is ENU), SE(3) otherwise. In
co-location modes the server's global-frame keyframe trajectory (camera poses, SE(3)) is evaluated too
(``server_*`` fields). Estimates and ground truth are copied next to the results JSON as TUM files, so the
numbers can be recomputed from the raw trajectories.

Co-location servers get the agents' nominal start configuration (paper 2.4: the UAVs take off from the
UGV's roof) as ``[start_poses]``, a prior with stated sigmas (:mod:`hivemap.eval.startposes`): by default
the true cam0 start poses perturbed by those sigmas (seeded), or none, or the exact ones on request.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hivemap.eval.processes import (
    HIVEMAP,
    clean_env,
    git_revision,
    server_state,
    start_server,
    stop,
    versions,
    wait_health,
)
from hivemap.eval.realtime import realtime
from hivemap.eval.rendezvous import all_together_s, merge_timeline
from hivemap.eval.startposes import StartPoseOptions, start_poses
from hivemap.maps.markers import LAYOUT_FILE

log = logging.getLogger(__name__)

MODES = ("single", "single+gnss", "denied", "challenged1", "challenged2")
COLOCATION = {"denied", "challenged1", "challenged2"}
MAX_DIFF = 0.02  # s; frames are at >= 10 Hz, ground truth at the IMU/ground-truth rate


def gnss_mode(mode: str, kind: str) -> str:
    """The ``--gnss`` argument of an agent of ``kind`` ("uav"/"ugv") in ``mode``."""
    if mode in ("single", "denied"):
        return "denied"
    if mode == "single+gnss":
        # the same fixes as challenged1: the paper's "ORB-SLAM3 fusion GPS" is the single-agent
        # counterpart of co-location with GNSS; with every 5 Hz fix it would only compare fix counts
        return "every:20s"
    if mode == "challenged1":
        return "every:20s"
    if mode == "challenged2":
        return "random:4" if kind == "uav" else "denied"
    raise ValueError(f"unknown mode {mode!r}; expected one of {', '.join(MODES)}")


@dataclass(frozen=True)
class ExperimentOptions:
    scenarios: Sequence[str]
    modes: Sequence[str] = MODES
    out: Path = Path("experiment")
    data: Path = Path("data")
    agents: Sequence[str] | None = None
    max_frames: int | None = None
    seed: int = 0
    progress: bool = True
    settle_s: float = 3.0  # wait for the back-end's last optimisation after the agents finish
    # co-location: the server's nominal start configuration (perturbed / none / truth, with its sigmas)
    start_poses: StartPoseOptions = field(default_factory=StartPoseOptions)
    agent_timeout_s: float = 6 * 3600.0
    report_only: bool = False  # run nothing: write the report from the results already in ``out``
    report_dir: Path | None = None  # where the report goes (default ``out``)
    # world seeds: each scenario runs once per seed (None in the list: the preset's own seed); None: once
    seeds: Sequence[int | None] | None = None
    server_toml: str = ""  # appended to every run's server config (back-end options under comparison)
    # issue 25: agents detect the marker carriers their datasets describe (off: same images, no detection)
    markers: bool = True
    stream_imu_odometry: bool = True  # agents stream an IMU-only fusion of their odometry (`hivemap agent`)
    pace: str = "asap"  # how agents replay their datasets (hivemap.client.pacing)
    explore_duration_s: float = 120.0  # issue 26: mission time of the live agents of the explore modes

    def worlds(self) -> list[tuple[str, str, int | None]]:
        """(results key, scenario, world seed) of every world to run: ``factory01-s7`` for seed 7."""
        seeds = list(self.seeds) if self.seeds else [None]
        return [(world_key(n, s), n, s) for n in self.scenarios for s in seeds]


def world_key(scenario: str, seed: int | None) -> str:
    """The name of one world of a scenario: its data and results folders (``factory01``, ``factory01-s7``;
    a scenario file ``dir/my.toml`` is named by its stem, ``my-s7``, so its world lands under ``--data``)."""
    base = Path(scenario).stem if scenario.lower().endswith(".toml") else scenario
    return base if seed is None else f"{base}-s{seed}"


def ensure_scenario(name: str, data: Path, seed: int | None = None) -> Path:
    """The rendered directory of scenario ``name`` with world ``seed`` (``hivemap sim render``, resumable;
    reused when every agent is complete)."""
    scen = data / world_key(name, seed)
    man = scen / "manifest.yaml"
    done = False
    if man.exists():
        from hivemap.sim.dataset import check_render
        from hivemap.sim.scenario_file import resolve_scenario

        m = check_render(man, resolve_scenario(name, seed))  # a render of another world is an error
        done = bool(m.get("agents")) and all(a.get("complete") for a in m["agents"])
    if not done:
        log.info("rendering scenario %s (seed %s) into %s", name, "preset" if seed is None else seed, scen)
        cmd = [*HIVEMAP, "sim", "render", "--scenario", name, "--out", str(scen), "--no-progress"]
        subprocess.run(cmd + ([] if seed is None else ["--seed", str(seed)]), check=True)
    return scen


# ------------------------------------------------------------------------------------------ results
@dataclass
class AgentResult:
    agent_id: str
    kind: str
    gnss: str
    status: str = "ok"  # ok | failed | no trajectory | not available
    est_tum: str | None = None  # relative to the results JSON's directory
    gt_tum: str | None = None
    source: str = ""  # local.tum (offline) | server global | agent local (fallback)
    alignment: str = "se3"  # none when the agent used GNSS (local frame = ENU), else se3
    ate_rmse: float | None = None
    ate_mean: float | None = None
    # co-location: the server's global-frame keyframes of the agent (camera poses, SE(3) alignment)
    server_ate_rmse: float | None = None
    server_ate_mean: float | None = None
    server_n: int = 0
    n: int = 0
    path_length: float | None = None
    bandwidth: dict[str, float] = field(default_factory=dict)
    run: dict[str, Any] = field(default_factory=dict)
    start_wall: float | None = None
    end_wall: float | None = None


def _agent_cmd(ds: Path, out: Path, gnss: str, opts: ExperimentOptions) -> list[str]:
    cmd = [*HIVEMAP, "agent", "--dataset", str(ds), "--out", str(out), "--gnss", gnss]
    cmd += ["--seed", str(opts.seed), "--no-progress"]
    if opts.max_frames is not None:
        cmd += ["--max-frames", str(opts.max_frames)]
    if not opts.markers:
        cmd += ["--no-markers"]
    if not opts.stream_imu_odometry:
        cmd += ["--stream-tracking"]
    if opts.pace != "asap":
        cmd += ["--pace", opts.pace]
    return cmd


def _evaluate(res: AgentResult, est_path: Path, gt: Any, mode_dir: Path, alignment: str) -> None:
    import numpy as np

    from hivemap.eval.trajectory import ate, read_tum, write_tum

    if not est_path.exists() or not est_path.read_text().strip():
        res.status = "no trajectory"
        return
    mode_dir.mkdir(parents=True, exist_ok=True)
    est_copy = mode_dir / f"{res.agent_id}.est.tum"
    gt_copy = mode_dir / f"{res.agent_id}.gt.tum"
    shutil.copyfile(est_path, est_copy)
    write_tum(gt_copy, gt)
    est = read_tum(est_copy)
    gt_r = read_tum(gt_copy)
    try:
        a = ate(est, gt_r, alignment, max_diff=MAX_DIFF)
    except Exception as exc:  # evo raises on no associated poses
        res.status = f"no trajectory ({exc})"
        return
    res.est_tum, res.gt_tum = est_copy.name, gt_copy.name
    res.alignment = alignment
    res.ate_rmse, res.ate_mean, res.n = float(a.stats.rmse), float(a.stats.mean), int(a.stats.n)
    xyz = np.asarray(gt_r.positions_xyz)
    res.path_length = float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()) if len(xyz) > 1 else 0.0


def _read_run(out: Path) -> dict[str, Any]:
    p = out / "run.json"
    if p.exists():
        try:
            return dict(json.loads(p.read_text()))
        except json.JSONDecodeError:
            return {}
    return {}


def run_single(scen: Path, agents: list[tuple[str, str]], mode: str, work: Path, mode_dir: Path,
               opts: ExperimentOptions, bar: Any, world_seed: int | None = None,
               ) -> dict[str, Any]:  # fmt: skip
    """Each agent alone, offline, one after another."""
    from hivemap.eval.trajectory import groundtruth_trajectory

    results = []
    for aid, kind in agents:
        g = gnss_mode(mode, kind)
        out = work / aid
        shutil.rmtree(out, ignore_errors=True)
        res = AgentResult(aid, kind, g, source="offline local.tum (body)")
        res.start_wall = time.time()
        with open(work / f"{aid}.log", "wb") as logf:
            cmd = [*_agent_cmd(scen / aid, out, g, opts), "--offline"]
            rc = subprocess.run(
                cmd, stdout=logf, stderr=subprocess.STDOUT, env=clean_env(), timeout=opts.agent_timeout_s
            ).returncode
        res.end_wall = time.time()
        res.run = _read_run(out)
        if rc != 0:
            res.status = f"failed (exit {rc}, log {work / (aid + '.log')})"
        else:
            align = "se3" if g == "denied" else "none"
            _evaluate(res, out / "local.tum", groundtruth_trajectory(scen / aid), mode_dir, align)
        results.append(asdict(res))
        bar.update(1)
    return {"agents": results, "events": [], "maps": []}


def run_colocation(scen: Path, agents: list[tuple[str, str]], mode: str, work: Path, mode_dir: Path,
                   opts: ExperimentOptions, bar: Any, world_seed: int | None = None,
               ) -> dict[str, Any]:  # fmt: skip
    """One server, every agent streaming to it at once."""
    import httpx

    from hivemap.eval.globalmap import loop_errors, team_by_map
    from hivemap.eval.trajectory import groundtruth_trajectory
    from hivemap.eval.uncertainty import covariance_coverage

    tokens = {aid: f"exp-{aid}-token" for aid, _ in agents}
    start_table = start_poses(scen, list(tokens), opts.start_poses, world_seed)
    url, ws_url, server, slog = start_server(work, tokens, start_table, opts.server_toml)
    env = clean_env()
    procs: dict[str, subprocess.Popen[bytes]] = {}
    results: dict[str, AgentResult] = {}
    logs = []
    try:
        wait_health(url, server)
        t_server = time.time()
        for aid, kind in agents:
            g = gnss_mode(mode, kind)
            out = work / aid
            shutil.rmtree(out, ignore_errors=True)
            res = AgentResult(aid, kind, g, source="agent local.tum after corrections (body)")
            res.start_wall = time.time()
            results[aid] = res
            lf = open(work / f"{aid}.log", "wb")  # noqa: SIM115
            logs.append(lf)
            cmd = _agent_cmd(scen / aid, out, g, opts)
            cmd += ["--server", ws_url, "--agent-id", aid, "--token", tokens[aid]]
            procs[aid] = subprocess.Popen(cmd, stdout=lf, stderr=subprocess.STDOUT, env=env)
        wait_agents(procs, results, opts.agent_timeout_s, bar)
        time.sleep(opts.settle_s)
        agents_info, events, maps = server_state(url)
        gt_cam = {aid: groundtruth_trajectory(scen / aid, sensor="cam0") for aid, _ in agents}
        t_first = min(float(g.timestamps[0]) for g in gt_cam.values())
        timeline = merge_timeline(events, t_first)
        for aid, _kind in agents:
            res = results[aid]
            out = work / aid
            res.run = _read_run(out)
            info = agents_info.get(aid, {})
            res.bandwidth = {k: float(v) for k, v in (info.get("bandwidth") or {}).items()}
            res.run["map_id"] = info.get("map_id")
            rc = procs[aid].returncode
            if rc != 0:
                text = (work / f"{aid}.log").read_text(errors="replace")
                res.status = (
                    "not available (streaming agent not implemented)"
                    if "not implemented" in text.lower() or "not available" in text.lower()
                    else f"failed (exit {rc}, log {work / (aid + '.log')})"
                )
                continue
            r = httpx.get(url + f"/agents/{aid}/trajectory", params={"frame": "global", "format": "tum"},
                          timeout=60)  # fmt: skip
            align = "se3" if res.gnss == "denied" else "none"
            _evaluate(res, out / "local.tum", groundtruth_trajectory(scen / aid), mode_dir, align)
            if r.status_code == 200 and r.text.strip():
                tum = out / "server_global.tum"
                tum.write_text(r.text)
                srv = AgentResult(aid, res.kind, res.gnss)
                _evaluate(srv, tum, gt_cam[aid], mode_dir / "server", "se3")
                res.server_ate_rmse, res.server_ate_mean, res.server_n = srv.ate_rmse, srv.ate_mean, srv.n
        return {
            "agents": [asdict(r) for r in results.values()],
            "uncertainty": covariance_coverage(url, maps, gt_cam),
            "loop_errors": loop_errors(events, gt_cam),
            "team": team_by_map(
                mode_dir / "server", [(aid, results[aid].run.get("map_id")) for aid, _ in agents]
            ),
            "start_poses": start_table,
            "all_merged_s": all_together_s(timeline, [aid for aid, _ in agents]),
            "merge_timeline": timeline,
            "markers": {
                "condition": "on" if opts.markers else "off",
                "layouts": sorted(a for a, _ in agents if (scen / a / LAYOUT_FILE).exists()),
            },
            "stream_imu_odometry": opts.stream_imu_odometry,
            "realtime": realtime(results, {aid: work / aid for aid, _ in agents}, opts.pace),
            "events": events,
            "maps": maps,
            "server_start_wall": t_server,
        }
    finally:
        for p in procs.values():
            stop(p)
        stop(server)
        slog.close()
        for lf in logs:
            lf.close()


def wait_agents(procs: dict[str, subprocess.Popen[bytes]], results: dict[str, AgentResult], timeout_s: float,
                bar: Any, poll_s: float = 0.2) -> None:  # fmt: skip
    """Until every agent process has ended (its end time into its result) or ``timeout_s`` has passed,
    then stop the ones still running."""
    deadline = time.monotonic() + timeout_s
    pending = dict(procs)
    while pending and time.monotonic() < deadline:
        for aid, p in list(pending.items()):
            if p.poll() is not None:
                results[aid].end_wall = time.time()
                del pending[aid]
                bar.update(1)
        time.sleep(poll_s)
    for p in pending.values():
        stop(p)


def run_experiment(opts: ExperimentOptions) -> Path:
    """Run every (scenario, mode) not done yet, then write the report; returns the report.md path."""
    from tqdm import tqdm

    from hivemap.client.dataset import load_scenario
    from hivemap.eval.explore import EXPLORE_MODES, explore_agents, run_explore
    from hivemap.eval.report import write_report

    for m in opts.modes:
        if m not in MODES and m not in EXPLORE_MODES:
            raise ValueError(f"unknown mode {m!r}; expected one of {', '.join(MODES + EXPLORE_MODES)}")
    out = Path(opts.out)
    worlds = opts.worlds()
    keys = [k for k, _, _ in worlds]
    todo = []
    for key, _, _ in worlds:
        for mode in opts.modes:
            if not (out / "results" / key / f"{mode}.json").exists():
                todo.append((key, mode))
    if opts.report_only:
        if not any((out / "results" / k / f"{m}.json").exists() for k in keys for m in opts.modes):
            raise FileNotFoundError(f"no results of {', '.join(keys)} in {out / 'results'}")
        return write_report(out, keys, list(opts.modes), opts.report_dir)
    out.mkdir(parents=True, exist_ok=True)
    # the explore modes' live agents render as they go: no dataset to render first
    needed = {k for k, m in todo if m not in EXPLORE_MODES}
    scen_dirs = {k: ensure_scenario(n, Path(opts.data), s) for k, n, s in worlds if k in needed}
    source = {k: (n, s) for k, n, s in worlds}
    n_runs = 0
    plan = []
    for name, mode in todo:
        if mode in EXPLORE_MODES:
            from hivemap.sim.scenario_file import resolve_scenario

            sc = resolve_scenario(*source[name])
            agents = explore_agents(sc, mode, opts.agents)
            plan.append((name, mode, agents, source[name][1]))
            n_runs += len(agents)
            continue
        man = load_scenario(scen_dirs[name])
        agents = [(a.id, a.kind) for a in man.agents if not opts.agents or a.id in opts.agents]
        plan.append((name, mode, agents, man.seed))
        n_runs += len(agents)
    with tqdm(total=n_runs, desc="experiment", unit="agent run", disable=not opts.progress) as bar:
        for name, mode, agents, seed in plan:
            bar.set_postfix_str(f"{name} {mode}")
            mode_dir = out / "results" / name / mode
            work = out / "work" / name / mode
            shutil.rmtree(mode_dir, ignore_errors=True)
            work.mkdir(parents=True, exist_ok=True)
            t0 = time.time()
            if mode in EXPLORE_MODES:
                data = run_explore(source[name][0], source[name][1], mode, work, mode_dir, opts, bar)
            else:
                fn = run_colocation if mode in COLOCATION else run_single
                data = fn(scen_dirs[name], agents, mode, work, mode_dir, opts, bar, seed)
            data.update(
                scenario=name,
                mode=mode,
                scenario_dir=str(scen_dirs.get(name, "")),
                scenario_seed=seed,
                alignment="per agent: none when it used GNSS, else se3",
                max_diff=MAX_DIFF,
                agent_seed=opts.seed,
                max_frames=opts.max_frames,
                wall_s=time.time() - t0,
                finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                git=git_revision(),
                versions=versions(),
            )
            tmp = out / "results" / name / f"{mode}.json.tmp"
            tmp.write_text(json.dumps(data, indent=1, default=str))
            tmp.replace(out / "results" / name / f"{mode}.json")  # atomic: a crash leaves no half JSON
    return write_report(out, keys, list(opts.modes), opts.report_dir)
