"""The experiment runner's exploration modes (issue 26): a server with its team services and live simulated
agents (``hivemap agent --sim WORLD:AGENT --live``) that go where the server's auction sends them.

- ``explore``: the team (the run's ``--agents``, default the scenario's 3 UAVs + UGV);
- ``explore1``: the first UAV alone, on the same world, for the comparison the issue asks for.

Each run reports coverage of the site over time (:mod:`hivemap.eval.coverage`, from ground-truth camera
poses, occlusion by the rendered depth), the time to the target coverage, each agent's path length and
ATE (its ``local.tum``, SE(3)-aligned as GNSS-denied runs are; the server's global keyframes too), and per
pair of agents their clearance against the sum of their inflated radii (those of the latest advisories),
leaving out the take-off from the shared start.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from hivemap.eval.coverage import CoverageOptions, coverage_curve, site_grid, time_to

log = logging.getLogger(__name__)

EXPLORE_MODES = ("explore", "explore1")
START_ZONE_M = 3.0  # pairs closer than this to their own start points are still taking off together
GOAL_JUMP_M = 1.0  # a first goal that moved by more than this between advisories sent its agent elsewhere
# the server pushes advisories twice a second and recomputes goals at most once a second
TEAM_TOML = "[team]\nmin_interval_s = 1.0\npush_interval_s = 0.5\n"
# a live agent streams a few hundred map points a second: the server's per-agent point cap (sized for
# replayed missions of a few minutes) would refuse a long exploration's later map, so it grows with the run
POINTS_PER_S = 1000


def explore_server_toml(duration_s: float) -> str:
    """The explore runs' server tables: the team services' rates and the point quota for ``duration_s``."""
    from hivemap.server.settings import QuotaSettings

    points = max(QuotaSettings().max_points, int(POINTS_PER_S * duration_s))
    return TEAM_TOML + f"[quotas]\nmax_points = {points}\n"


def explore_agents(scenario: Any, mode: str, wanted: Any) -> list[tuple[str, str]]:
    """(agent id, kind) of a run: the team, or the first UAV alone."""
    agents = [(a.agent_id, a.kind) for a in scenario.agents if not wanted or a.agent_id in wanted]
    if mode == "explore1":
        agents = [a for a in agents if a[1] == "uav"][:1] or agents[:1]
    return agents


def run_explore(
    name: str, seed: int | None, mode: str, work: Path, mode_dir: Path, opts: Any, bar: Any
) -> dict[str, Any]:
    """One exploration run of scenario ``name`` on world ``seed`` (see the module docstring)."""
    import httpx

    from hivemap.eval import experiment as ex
    from hivemap.eval import processes as proc
    from hivemap.eval.startposes import start_poses_from
    from hivemap.eval.trajectory import read_tum
    from hivemap.sim.dataset import cached_world
    from hivemap.sim.live import start_pose
    from hivemap.sim.scenario_file import resolve_scenario
    from hivemap.sim.sensor_files import stereo_extrinsics

    sc = resolve_scenario(name, seed)
    agents = explore_agents(sc, mode, opts.agents)
    world = cached_world(sc.seed, sc.world_size_m)
    truth = {}
    for aid, _ in agents:
        p, yaw, _ = start_pose(world, sc, aid)
        T = np.eye(4)
        c, s = np.cos(yaw), np.sin(yaw)
        T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[:3, 3] = p
        truth[aid] = T @ stereo_extrinsics(sc.agent(aid))[0]
    tokens = {aid: f"exp-{aid}-token" for aid, _ in agents}
    start_table = start_poses_from(truth, opts.start_poses, seed)
    extra = explore_server_toml(opts.explore_duration_s) + opts.server_toml
    url, ws_url, server, slog = proc.start_server(work, tokens, start_table, extra)
    env = proc.clean_env()
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs = []
    results: dict[str, Any] = {}
    try:
        proc.wait_health(url, server)
        t_server = time.time()
        for aid, kind in agents:
            out = work / aid
            shutil.rmtree(out, ignore_errors=True)
            results[aid] = ex.AgentResult(
                aid, kind, "denied", source="live agent local.tum after corrections"
            )
            results[aid].start_wall = time.time()
            cmd = [*proc.HIVEMAP, "agent", "--sim", f"{name}:{aid}", "--live", "--duration",
                   str(opts.explore_duration_s), "--server", ws_url, "--agent-id", aid,
                   "--token", tokens[aid], "--out", str(out), "--wait-corrections", "30"]  # fmt: skip
            if seed is not None:
                cmd += ["--seed", str(seed)]
            lf = open(work / f"{aid}.log", "wb")  # noqa: SIM115
            logs.append(lf)
            procs[aid] = subprocess.Popen(cmd, stdout=lf, stderr=subprocess.STDOUT, env=env)
        ex.wait_agents(procs, results, opts.agent_timeout_s, bar, poll_s=0.5)
        time.sleep(opts.settle_s)
        agents_info, events, maps = proc.server_state(url)
        for aid, _ in agents:
            res, out = results[aid], work / aid
            res.run = ex._read_run(out)
            live = out / "live.json"
            res.run["live"] = json.loads(live.read_text()) if live.exists() else {}
            info = agents_info.get(aid, {})
            res.bandwidth = {k: float(v) for k, v in (info.get("bandwidth") or {}).items()}
            res.run["map_id"] = info.get("map_id")
            if procs[aid].returncode != 0 or not (out / "groundtruth.tum").exists():
                res.status = f"failed (exit {procs[aid].returncode}, log {work / (aid + '.log')})"
                continue
            ex._evaluate(res, out / "local.tum", read_tum(out / "groundtruth.tum"), mode_dir, "se3")
            r = httpx.get(url + f"/agents/{aid}/trajectory", params={"frame": "global", "format": "tum"},
                          timeout=60)  # fmt: skip
            if r.status_code == 200 and r.text.strip():
                (out / "server_global.tum").write_text(r.text)
                srv = ex.AgentResult(aid, res.kind, res.gnss)
                ex._evaluate(srv, out / "server_global.tum", read_tum(out / "groundtruth_cam0.tum"),
                          mode_dir / "server", "se3")  # fmt: skip
                res.server_ate_rmse, res.server_ate_mean, res.server_n = srv.ate_rmse, srv.ate_mean, srv.n
    finally:
        for pr in procs.values():
            proc.stop(pr)
        proc.stop(server)
        slog.close()
        for lf in logs:
            lf.close()
    ok = [aid for aid, _ in agents if results[aid].status == "ok"]
    return {
        "agents": [asdict(r) for r in results.values()],
        "coverage": coverage_of(world, sc, [(a, k) for a, k in agents if a in ok], work),
        "pairs": pair_distances([(a, k) for a, k in agents if a in ok], work),
        "start_poses": start_table,
        "explore_duration_s": opts.explore_duration_s,
        "events": events,
        "maps": maps,
        "server_start_wall": t_server,
    }


def _cam_poses(out: Path, t0: float) -> tuple[Any, Any]:
    from hivemap.eval.trajectory import read_tum

    tr = read_tum(out / "groundtruth_cam0.tum")
    return np.asarray(tr.timestamps) - t0, np.asarray(tr.poses_se3)


def coverage_of(world: Any, sc: Any, agents: list[tuple[str, str]], work: Path,
                options: CoverageOptions | None = None) -> dict[str, Any]:  # fmt: skip
    """Coverage over time of the team's reachable area and of each kind's, occlusion by rendered depth."""
    from hivemap.sim.render import make_renderer

    o = options or CoverageOptions()
    if not agents:
        return {}
    t0 = sc.start_time_ns * 1e-9
    poses = {aid: _cam_poses(work / aid, t0) for aid, _ in agents}
    grid = site_grid(world, o.cell_m)
    cam = sc.camera.pinhole()
    renderer = make_renderer(world, cam)
    try:

        def depth_of(_aid: str, T: Any) -> Any:
            return renderer.render(T)[1]

        out: dict[str, Any] = {"kinds": sorted({k for _, k in agents}), "cell_m": o.cell_m,
                               "max_range_m": o.max_range_m, "target": o.target}  # fmt: skip
        for key, kinds in (("team", [k for _, k in agents]), ("uav_area", ["uav"]), ("ugv_area", ["ugv"])):
            t, f = coverage_curve(grid, kinds, poses, cam, o, depth_of)
            out[key] = {"times": np.round(t, 3).tolist(), "fraction": np.round(f, 4).tolist(),
                        "cells": int(grid.area(kinds).sum()), "final": float(f[-1]) if len(f) else 0.0,
                        "t_target": time_to(t, f, o.target)}  # fmt: skip
    finally:
        renderer.close()
    return out


def _logged_at(log_: list[dict[str, Any]], t: Any, key: str) -> Any:
    """The value ``key`` (``radius``, ``half_height``) the latest advisory at each time ``t`` (s from the
    start) gave (the first one before it arrived); None without advisories. A log without half heights
    (a server before protocol v7, whose cylinders were as high as their radii) gives the radius."""
    if not log_:
        return None
    if key == "half_height" and not all("half_height" in a for a in log_):
        key = "radius"
    lt = np.array([float(a["t"]) for a in log_])
    r = np.array([float(a.get(key, 0.0)) for a in log_])
    return r[np.clip(np.searchsorted(lt, t, side="right") - 1, 0, len(r) - 1)]


def pair_distances(agents: list[tuple[str, str]], work: Path) -> list[dict[str, Any]]:
    """Per pair as the server's ORCA models agents (upright cylinders of their inflated radius and half
    height): the smallest horizontal clearance ``distance - (r_a + r_b)`` at times when their vertical gap
    is within ``h_a + h_b``, radii and half heights those of the latest advisories then; and the minimum
    3-D distance. Both leave out the take-off: times when neither agent is yet ``START_ZONE_M``
    (horizontally) from its start."""
    from hivemap.eval.trajectory import read_tum

    pos, logs = {}, {}
    for aid, _ in agents:
        tr = read_tum(work / aid / "groundtruth.tum")
        stamps = np.asarray(tr.timestamps)
        pos[aid] = (np.round(stamps * 1e3).astype(np.int64), np.asarray(tr.positions_xyz), stamps[0])
        logs[aid] = json.loads((work / aid / "live.json").read_text()).get("advisory_log", [])
    out = []
    ids = [a for a, _ in agents]
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            (ta, pa, t0), (tb, pb, _) = pos[a], pos[b]
            common, ia, ib = np.intersect1d(ta, tb, return_indices=True)
            if not len(common):
                continue
            qa, qb = pa[ia], pb[ib]
            d3 = np.linalg.norm(qa - qb, axis=1)
            dh = np.linalg.norm(qa[:, :2] - qb[:, :2], axis=1)
            away = (np.linalg.norm(qa[:, :2] - pa[0, :2], axis=1) > START_ZONE_M) | (
                np.linalg.norm(qb[:, :2] - pb[0, :2], axis=1) > START_ZONE_M
            )
            t = common / 1e3 - t0
            ra, rb = _logged_at(logs[a], t, "radius"), _logged_at(logs[b], t, "radius")
            ha, hb = _logged_at(logs[a], t, "half_height"), _logged_at(logs[b], t, "half_height")
            row: dict[str, Any] = {"a": a, "b": b, "min_m": float(d3[away].min()) if away.any() else None,
                                   "min_all_m": float(d3.min()), "margin_m": None, "radii_m": None,
                                   "clear": None}  # fmt: skip
            if ra is not None and rb is not None:
                need = ra + rb
                near = away & (np.abs(qa[:, 2] - qb[:, 2]) < ha + hb)
                row["clear"] = True
                if near.any():
                    k = np.flatnonzero(near)[int(np.argmin((dh - need)[near]))]
                    row.update(
                        margin_m=float(dh[k] - need[k]), radii_m=float(need[k]), clear=bool(dh[k] >= need[k])
                    )
            out.append(row)
    return out


def explore_section(out: Path, results: dict[tuple[str, str], dict[str, Any]], dest: Path) -> list[str]:
    """The report's exploration section: coverage table, pair distances, coverage-over-time plot."""
    runs = {k: v for k, v in results.items() if k[1] in EXPLORE_MODES and v.get("coverage")}
    if not runs:
        return []
    md = ["## Exploration (issue 26): live agents on the server's goals", ""]
    md.append(
        "Coverage: fraction of the team's reachable area (UGV: drivable ground; UAV: the site's ground, "
        "building footprints excluded) seen by any agent's camera, from ground-truth poses on a 1 m grid, "
        "within the coverage range and not hidden (rendered depth). explore1 is the first UAV alone."
    )
    md.append("")
    md.append("| world | mode | agents | sim time [s] | coverage | time to target [s] | path lengths [m] | "
              "ATE RMSE [m] |")  # fmt: skip
    md.append("|---|---|---|---|---|---|---|---|")
    for (s, m), d in runs.items():
        c = d["coverage"]["team"]
        ags = d["agents"]
        paths = ", ".join(
            f"{a['agent_id']} {a['run'].get('live', {}).get('path_length_m', 0):.0f}" for a in ags
        )
        ates = ", ".join(f"{a['agent_id']} {_f(a.get('ate_rmse'))}" for a in ags)
        tt = c["t_target"]
        md.append(f"| {s} | {m} | {len(ags)} | {d.get('explore_duration_s', 0):.0f} | {c['final']:.1%} | "
                  f"{'-' if tt is None else f'{tt:.1f}'} (target {d['coverage']['target']:.0%}) | {paths} | "
                  f"{ates} |")  # fmt: skip
    md += ["", "Pairs: the smallest horizontal clearance (distance - the two inflated radii of the latest "
           "advisories) while their vertical gap is within their two half heights, as the server's ORCA sees "
           "agents; and the minimum 3-D distance. Both after the take-off (one agent 3 m from its start).",
           "",
           "| world | mode | pair | min clearance [m] | radii sum then [m] | clear | min distance [m] "
           "(incl. take-off) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for (s, m), d in runs.items():
        for p in d.get("pairs", []):
            md.append(f"| {s} | {m} | {p['a']}-{p['b']} | {_f(p.get('margin_m'))} | {_f(p['radii_m'])} | "
                      f"{p['clear']} | {_f(p['min_m'])} ({_f(p['min_all_m'])}) |")  # fmt: skip
    md += ["", f"Goals: how often an agent's first goal moved by more than {GOAL_JUMP_M:g} m from one "
           "advisory to the next (turning it towards another place), and how many of those moves went back "
           "to one of its previous six first goals; ATE as a share of the path.", "",
           "| world | mode | agent | advisories | goals reached | first goal moved | back to a recent one "
           "| ATE / path |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for (s, m), d in runs.items():
        for a in d["agents"]:
            live = a["run"].get("live", {})
            moved, back = goal_changes(live.get("advisory_log", []))
            path = live.get("path_length_m") or 0.0
            share = "-" if a.get("ate_rmse") is None or path <= 0 else f"{100 * a['ate_rmse'] / path:.3f} %"
            md.append(f"| {s} | {m} | {a['agent_id']} | {live.get('advisories', 0)} | "
                      f"{live.get('goals_reached', 0)} | {moved} | {back} | {share} |")  # fmt: skip
    md.append("")
    img = _coverage_plot(runs, dest)
    md += [f"![coverage over time]({img})", ""]
    return md


def goal_changes(advisory_log: list[dict[str, Any]], jump_m: float = GOAL_JUMP_M) -> tuple[int, int]:
    """(times the first goal moved by more than ``jump_m`` between advisories, of those the moves back to
    within ``jump_m`` of one of the previous six first goals) from a live agent's advisory log."""
    firsts = [np.asarray(e["goals"][0][:2], dtype=np.float64) for e in advisory_log if e.get("goals")]
    moved = back = 0
    recent: list[Any] = []
    for a, b in zip(firsts, firsts[1:], strict=False):
        if np.linalg.norm(b - a) > jump_m:
            moved += 1
            back += any(np.linalg.norm(b - r) <= jump_m for r in recent[-6:])
            recent.append(a)
    return moved, back


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _coverage_plot(runs: dict[tuple[str, str], dict[str, Any]], dest: Path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for (s, m), d in runs.items():
        c = d["coverage"]["team"]
        ax.plot(c["times"], [100 * f for f in c["fraction"]], label=f"{s} {m} ({len(d['agents'])} agents)")
    target = 100 * next(iter(runs.values()))["coverage"]["target"]
    ax.axhline(target, color="k", ls=":", lw=1)
    ax.set_xlabel("mission time [s]")
    ax.set_ylabel("reachable area seen [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    img = dest / "img" / "coverage.png"
    img.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(img, dpi=90)
    plt.close(fig)
    return str(img.relative_to(dest))
