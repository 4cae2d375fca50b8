"""`make demo`: render a small scenario, start the server, stream four agents to it, print per-agent ATE.

Usage: .venv/bin/python scripts/demo.py [--scenario tiny] [--port 8765] [--exit]
Without --exit the server keeps running for the viewer until Ctrl-C.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HIVEMAP = [sys.executable, "-m", "hivemap.cli.main"]


def log(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="tiny")
    ap.add_argument("--port", type=int, default=8765)
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "demo")
    ap.add_argument("--exit", action="store_true", help="stop after printing the results")
    args = ap.parse_args()

    from hivemap.client.dataset import load_scenario
    from hivemap.eval.processes import clean_env, stop, wait_health, write_server_config
    from hivemap.eval.startposes import StartPoseOptions, describe, start_poses
    from hivemap.eval.trajectory import AgentRun, ate, evaluate_team, groundtruth_trajectory, read_tum

    work: Path = args.work
    scen_dir = work / args.scenario
    log(f"rendering scenario '{args.scenario}' into {scen_dir} (reused when already complete)")
    subprocess.run(
        [*HIVEMAP, "sim", "render", "--scenario", args.scenario, "--out", str(scen_dir)], check=True
    )
    scenario = load_scenario(scen_dir)
    agents = [a.id for a in scenario.agents]
    tokens = {a: f"demo-{a}-token" for a in agents}

    server_dir = work / "server"
    shutil.rmtree(server_dir, ignore_errors=True)
    server_dir.mkdir(parents=True)
    cfg = server_dir / "server.toml"
    # The UAVs take off from the UGV's roof (paper 2.4): their nominal mounting is a prior (0.2 m / 5 deg)
    # that place recognition's merges are checked against; here the true start poses perturbed by it.
    starts = start_poses(scen_dir, agents, StartPoseOptions("perturbed"), scenario.seed)
    log(describe(starts))
    write_server_config(cfg, tokens, starts)
    url = f"http://127.0.0.1:{args.port}"
    env = clean_env()
    server_log = open(server_dir / "server.log", "wb")  # noqa: SIM115
    log(f"starting the server on {url} (log: {server_dir / 'server.log'})")
    server = subprocess.Popen(
        [*HIVEMAP, "server", "--host", "127.0.0.1", "--port", str(args.port),
         "--data-dir", str(server_dir / "data"), "--config", str(cfg), "--groundtruth", str(scen_dir)],
        stdout=server_log, stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    procs: list[subprocess.Popen[bytes]] = []
    try:
        wait_health(url, server)
        log(f"streaming {len(agents)} agents: {', '.join(agents)}")
        t0 = time.monotonic()
        for a in agents:
            out = work / "agents" / a
            shutil.rmtree(out, ignore_errors=True)
            procs.append(
                subprocess.Popen(
                    [
                        *HIVEMAP,
                        "agent",
                        "--dataset",
                        str(scen_dir / a),
                        "--server",
                        f"ws://127.0.0.1:{args.port}/ws",
                        "--agent-id",
                        a,
                        "--token",
                        tokens[a],
                        "--out",
                        str(out),
                        "--no-progress",
                    ],
                    env=env,
                )  # fmt: skip
            )
        codes = [p.wait() for p in procs]
        log(f"agents finished in {time.monotonic() - t0:.1f} s (exit codes {codes})")
        if any(codes):
            log("an agent failed; see its output above")
        time.sleep(2.0)  # let the back-end finish its last optimisation
        maps = httpx.get(url + "/maps").json()["maps"]
        agent_map = {a["agent_id"]: a["map_id"] for a in httpx.get(url + "/agents").json()["agents"]}
        # Per agent: aligned on its own (as a single-agent run would be). Team: one SE(3) per server map for
        # all its agents together, so the figures are only as good when the maps really merged.
        rows: list[tuple[str, object, int, float, float]] = []
        runs = []
        for a in agents:
            r = httpx.get(url + f"/agents/{a}/trajectory", params={"frame": "global", "format": "tum"})
            if r.status_code != 200 or not r.text.strip():
                rows.append((a, None, 0, 0.0, float("nan")))
                continue
            tum = work / "agents" / f"{a}.server.tum"
            tum.parent.mkdir(parents=True, exist_ok=True)
            tum.write_text(r.text)
            est = read_tum(tum)
            gt = groundtruth_trajectory(scenario.agent(a).path, sensor="cam0")
            res = ate(est, gt, "se3", max_diff=0.02)
            xyz = np.asarray(gt.positions_xyz)
            path = float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())
            rows.append((a, agent_map.get(a), len(est.timestamps), path, res.stats.rmse))
            runs.append(AgentRun(a, est, gt, [(-np.inf, f"map{agent_map.get(a)}")]))
        team = evaluate_team(runs, "se3", max_diff=0.02, rpe_delta=None) if runs else None
        print()
        print(f"{'agent':<8}{'map':>5}{'keyframes':>11}{'path m':>9}{'ATE RMSE m':>12}{'ATE % path':>12}"
              f"{'team-aligned m':>16}")  # fmt: skip
        for a, map_id, n, path, rmse in rows:
            if n == 0:
                print(f"{a:<8}{'-':>5}{0:>11}   (no keyframes on the server)")
                continue
            pct = 100 * rmse / max(path, 1e-9)
            team_rmse = team.agents[a].ate.rmse if team is not None else float("nan")
            print(f"{a:<8}{map_id!s:>5}{n:>11}{path:>9.1f}{rmse:>12.3f}{pct:>11.2f}%{team_rmse:>16.3f}")
        if team is not None:
            per_map = ", ".join(f"{fid}: {', '.join(fa.agents)}" for fid, fa in sorted(team.frames.items()))
            print(f"{'team':<8}{'':>5}{'':>11}{'':>9}{'':>12}{'':>12}{team.team.rmse:>16.3f}"
                  f"   (one SE(3) per server map: {per_map})")  # fmt: skip
        print(f"\nmaps on the server: {len(maps)} " + ", ".join(f"#{m['id']} {m['agents']}" for m in maps))
        print(f"viewer: {url}/   REST: {url}/docs")
        if not args.exit:
            log("server keeps running for the viewer; Ctrl-C to stop")
            while server.poll() is None:
                time.sleep(0.5)
        return 0 if not any(codes) else 1
    except KeyboardInterrupt:
        log("stopping")
        return 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        stop(server)
        server_log.close()


if __name__ == "__main__":
    raise SystemExit(main())
