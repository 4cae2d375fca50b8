"""Team benchmark (issue 23, item 5): does a server keep up with N agents at their real pace?

``record`` keeps the keyframe streams of a finished multi-agent run once: every agent's outbox (the
frames it sent, in order) with its hello fields and known start pose. ``run`` replays N copies of them
(N = 4, 8, 16, 32) into a real server on a real port over real WebSockets, each keyframe at its recorded
time (the messages before a keyframe go right before it), and prints per N: query lag p50/p95
(keyframe arrival -> its place recognition done), keyframes dropped from the query queue, correction
latency p50/p95 (detection -> correction sent), the server's CPU use and peak RSS, and the largest N
kept up with (query lag p95 <= 2 s, nothing dropped, every query done) per core given to the server.

Copy ``c`` of the team is shifted by ``c`` km in x (poses, points, GNSS fixes, start poses) and its
descriptors are XOR-ed with a mask of its own: Hamming distances within a copy are unchanged (its
matching is the recorded team's), while its places share no appearance with the other copies, so the
copies are separate teams of agents rather than N duplicates of one place.

    # a finished run: e.g. the GNSS-denied co-location mode of a (short) scenario
    hivemap eval experiment --scenarios f01short --seeds 1 --modes denied --data data --out data/exp
    .venv/bin/python bench/team.py record --scenario-dir data/f01short-s1 \\
        --run-dir data/exp/work/f01short-s1/denied --out data/team-f01short-s1
    .venv/bin/python bench/team.py run --recording data/team-f01short-s1 --agents 4,8,16,32 --cores 1

``--cores``: CPUs the server process (and its verification workers) may run on (``sched_setaffinity``),
the "per core" of the result; the workers: ``--server-toml "[backend.scheduler]" --server-toml
"workers = 2"`` (``executor = "ray"`` for Ray tasks). Server CPU and RSS include the workers'.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from hivemap.protocol import Ack, Correction, decode, encode
from hivemap.protocol import Error as ErrorMsg

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling module below, also when imported
from team_streams import Stream, make_streams, record  # noqa: E402

LAG_OK_S = 2.0  # issue 23: query lag p95 <= 2 s


# ------------------------------------------------------------------------------------------ replay
@dataclass
class AgentStats:
    keyframes: int = 0
    acked: int = 0
    corrections: int = 0
    last_ack: int = 0  # the highest seq the server acked or refused
    errors: list[str] = field(default_factory=list)
    late_s: list[float] = field(default_factory=list)  # how far behind its recorded time a keyframe went out


async def replay_agent(url: str, s: Stream, t_start: float, window: int = 512) -> AgentStats:
    import websockets

    st = AgentStats()
    inflight = asyncio.Semaphore(window)
    last = len(s.frames)
    done = asyncio.Event()
    # no client keepalive: a server far behind reads its socket late, and a lost connection would end
    # this stream (the real agent reconnects from its outbox; the bench measures the server behind)
    async with websockets.connect(url, max_size=None, compression=None, ping_interval=None) as ws:
        await ws.send(encode(s.hello, 0))
        _, welcome = decode(await ws.recv())
        if isinstance(welcome, ErrorMsg):
            raise RuntimeError(f"{s.agent_id}: server refused: {welcome.message}")

        def answered(seq: int) -> None:  # an ack, or a refusal: the message is done with either way
            st.last_ack = max(st.last_ack, seq)
            inflight.release()
            if seq >= last:
                done.set()

        async def reader() -> None:
            async for frame in ws:
                assert isinstance(frame, bytes)
                _, msg = decode(frame)
                if isinstance(msg, Ack):
                    st.acked += 1
                    answered(msg.seq)
                elif isinstance(msg, Correction):
                    st.corrections += 1
                elif isinstance(msg, ErrorMsg):
                    st.errors.append(f"{msg.code}: {msg.message}")
                    if msg.seq is not None:
                        answered(msg.seq)

        task = asyncio.create_task(reader())
        for t, frame, is_kf in s.frames:
            delay = t_start + t - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            await inflight.acquire()
            if is_kf:
                st.keyframes += 1
                st.late_s.append(max(0.0, -delay))
            await ws.send(frame)
        if s.frames:
            try:
                await asyncio.wait_for(done.wait(), 300.0)
            except TimeoutError:  # reported, not raised: the other streams' figures still count
                st.errors.append(f"{s.agent_id}: no answer to seq {last} in 300 s (last {st.last_ack})")
        task.cancel()
    return st


async def replay(url: str, streams: list[Stream]) -> list[AgentStats]:
    t_start = time.perf_counter() + 1.0
    return list(await asyncio.gather(*(replay_agent(url, s, t_start) for s in streams)))


# ------------------------------------------------------------------------------------------ server
def serve(port: int, data_dir: Path, config: Path, profile: Path | None = None) -> None:
    """The hivemap server app plus one bench route, ``/bench/figures``: the back-end's figures.
    ``profile``: cProfile every place-recognition query (the back-end's thread) into this file."""
    import uvicorn

    from hivemap.server.app import create_app, uvicorn_config_kwargs
    from hivemap.server.cli import make_uvicorn_server, preload_signal_installers
    from hivemap.server.settings import load_settings

    preload_signal_installers()
    settings = load_settings(config, host="127.0.0.1", port=port, data_dir=data_dir)
    app = create_app(settings)

    @app.get("/bench/figures")
    async def figures() -> dict[str, Any]:
        be = app.state.hive.backend
        return {
            "queries": be.queries,
            "query_ms": be.query_ms,
            "query_cpu_ms": be.query_cpu_ms,
            "verify_cpu_ms": be.verify_cpu_ms,
            "job_bytes": be.job_bytes,
            "ship": app.state.bench_ship,
            "sent": app.state.bench_sent,
            "query_lags": be.query_lags,
            "lag_timeline": app.state.bench_timeline,
            "dropped": be.dropped_queries,
            "skipped": be.skipped_queries,
            "queued": len(be.queue),
            "idle": be.idle(),
            "verifications": be.verifications,
            # a back-end from before two-phase verification verified every candidate fully
            "full_verifications": getattr(be, "full_verifications", be.verifications),
            "correction_latencies": be.correction_latencies,
            "visual_merges": sum(1 for m in be.merges if m.get("by") != "start_pose"),
            "loops": len(be.loops),
            "maps": len(app.state.hive.stack.maps),
        }

    # when each query finished and how late (seconds since the server started, lag, agent): where lag builds
    from hivemap.server.backend.backlog import QueryQueue

    timeline: list[tuple[float, float, str]] = []
    queue_done, t_start = QueryQueue.done, time.monotonic()

    def timed_done(self: Any, key: Any) -> float:
        lag = queue_done(self, key)
        timeline.append((time.monotonic() - t_start, lag, str(key[0])))
        return lag

    QueryQueue.done = timed_done  # type: ignore[method-assign]
    app.state.bench_timeline = timeline

    # CPU time of each query's look-up and job in the place-recognition thread, plus its verification's
    # (measured in whichever process ran it: the back-end's figures); with ``profile``, cProfile of the
    # look-ups on that thread's clock
    from hivemap.server.backend import detect

    prof = None
    if profile is not None:
        import cProfile

        prof = cProfile.Profile(time.thread_time)

        def profiled(fn: Any) -> Any:
            def run(*args: Any, **kwargs: Any) -> Any:
                assert prof is not None
                prof.enable()
                try:
                    return fn(*args, **kwargs)
                finally:
                    prof.disable()

            return run

        detect.prepare = profiled(detect.prepare)  # type: ignore[assignment]
        if hasattr(detect, "second_phase"):  # two-phase verification: its phase-2 jobs too
            detect.second_phase = profiled(detect.second_phase)  # type: ignore[assignment]

    # the cost of shipping a job to a worker: pickling every 10th job once more (CPU ms, bytes)
    import pickle

    ship: list[tuple[float, int]] = []
    prepare_job = detect.prepare

    def shipped(*args: Any, **kwargs: Any) -> Any:
        out = prepare_job(*args, **kwargs)
        if out is not None and len(ship) * 10 <= len(app.state.hive.backend.query_ms):
            t = time.thread_time()
            n = len(pickle.dumps(out[1], protocol=pickle.HIGHEST_PROTOCOL))
            ship.append(((time.thread_time() - t) * 1e3, n))
        return out

    detect.prepare = shipped  # type: ignore[assignment]
    app.state.bench_ship = ship
    # what a worker is actually sent when it keeps keyframes' features (every 10th packed job, bytes)
    from hivemap.server.placerec import shipping

    sent: list[int] = []
    pack = shipping.Shipper.pack

    def packed(self: Any, job: Any) -> Any:
        out = pack(self, job)
        if len(sent) * 10 <= len(app.state.hive.backend.query_ms):
            sent.append(len(pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)))
        return out

    shipping.Shipper.pack = packed  # type: ignore[method-assign]
    app.state.bench_sent = sent
    make_uvicorn_server(uvicorn.Config(app, **uvicorn_config_kwargs(settings))).run()
    if prof is not None and profile is not None:
        prof.dump_stats(str(profile))


def quality(rec: Path, events: list[dict[str, Any]]) -> dict[str, Any]:
    """Recognition figures from the server's events: queries with a detection, accepted candidates, and
    the accepted loops' errors against the ground truth (a copy's agents have the original's)."""
    from hivemap.eval.trajectory import groundtruth_trajectory

    try:
        from hivemap.eval.globalmap import loop_errors
    except ImportError:  # a hivemap from before eval.globalmap (the bench replays into older servers too)
        from hivemap.eval.trajectory import loop_errors  # type: ignore[attr-defined,no-redef]

    meta = json.loads((rec / "team.json").read_text())
    scen = Path(meta["scenario_dir"])
    gt = {a["agent_id"]: groundtruth_trajectory(scen / a["agent_id"], sensor="cam0") for a in meta["agents"]}
    for e in events:  # copy ids "uav1c3" -> "uav1" for the ground truth
        d = e.get("data") or {}
        if e.get("kind") == "loop" and "query" in d and "candidate" in d:
            for k in ("query", "candidate"):
                d[k] = [_base_id(str(d[k][0])), *d[k][1:]]
    errs = loop_errors(events, gt)
    kinds = [(e.get("kind"), e.get("data") or {}) for e in events]
    t = [x["trans_err_m"] for x in errs]
    r = [x["rot_err_deg"] for x in errs]
    return {
        "detections": sum(1 for k, d in kinds if k == "placerec" and "detection" in d),
        "accepted": sum(1 for k, d in kinds if k == "placerec_candidate" and d.get("accepted")),
        "loop_errors": len(errs),
        "loop_err_m_median": float(np.median(t)) if t else float("nan"),
        "loop_err_m_max": max(t, default=float("nan")),
        "loop_err_deg_median": float(np.median(r)) if r else float("nan"),
    }  # fmt: skip


def team_ate(url: str, rec: Path, work: Path) -> dict[str, Any]:
    """The first copy's team ATE in the server's global frame (one SE(3) alignment per map, as the
    experiment runner's): replaying a recorded run into a server with other options judges the back-end
    alone on the same keyframe streams."""
    from hivemap.eval.globalmap import team_by_map
    from hivemap.eval.trajectory import groundtruth_trajectory, write_tum

    meta = json.loads((rec / "team.json").read_text())
    scen, out = Path(meta["scenario_dir"]), work / "server_tum"
    out.mkdir(parents=True, exist_ok=True)
    agents = []
    for a in meta["agents"]:
        aid = a["agent_id"]
        info = httpx.get(url + f"/agents/{aid}", timeout=60)
        r = httpx.get(url + f"/agents/{aid}/trajectory", params={"frame": "global", "format": "tum"},
                      timeout=60)  # fmt: skip
        if info.status_code != 200 or r.status_code != 200 or not r.text.strip():
            continue
        (out / f"{aid}.est.tum").write_text(r.text)
        write_tum(out / f"{aid}.gt.tum", groundtruth_trajectory(scen / aid, sensor="cam0"))
        agents.append((aid, info.json().get("map_id")))
    maps = team_by_map(out, agents)
    worst = max((m["team_ate_rmse"] for m in maps if m["team_ate_rmse"] is not None), default=float("nan"))
    return {"team_ate_worst": worst, "team_maps": maps}


def _base_id(folded: str) -> str:
    aid, _, rest = folded.partition("#")
    head, sep, tail = aid.rpartition("c")
    aid = head if sep and tail.isdigit() and head else aid
    return aid + ("#" + rest if rest else "")


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (the server's verification workers)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        with contextlib.suppress(OSError):
            todo += [int(c) for t in Path(f"/proc/{p}/task").iterdir()
                     for c in (t / "children").read_text().split()]  # fmt: skip
    return out


def _proc_cpu_s(pid: int) -> float:
    """CPU seconds of the server process and its workers."""
    total = 0.0
    for p in _tree(pid):
        try:
            f = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _proc_rss_mb(pid: int, key: str = "VmHWM") -> float:
    """Peak RSS of the server process plus its workers' (MB)."""
    total = 0.0
    for p in _tree(pid):
        try:
            lines = Path(f"/proc/{p}/status").read_text().splitlines()
        except OSError:
            continue
        total += next((int(x.split()[1]) / 1024 for x in lines if x.startswith(key + ":")), 0.0)
    return total


def _mean(x: list[float]) -> float:
    return float(np.mean(x)) if x else float("nan")


def _pct(x: list[float], q: float) -> float:
    return float(np.percentile(x, q)) if x else float("nan")


def run_one(rec: Path, n: int, cores: int, speed: float, duration_s: float | None, drain_s: float,
            start_poses: bool, profile: Path | None = None,
            extra_toml: tuple[str, ...] = (), keep: Path | None = None) -> dict[str, Any]:  # fmt: skip
    streams = make_streams(rec, n, speed, duration_s)
    work = Path(tempfile.mkdtemp(prefix="hivemap-team-"))
    cfg = work / "server.toml"
    # keepalive of 10 min: on a shared machine a busy server answers pings late and would drop agents
    lines = ["event_buffer = 100000", "ping_interval_s = 600.0", "[tokens]"]
    lines += [f'{s.agent_id} = "{s.hello.token}"' for s in streams]
    if start_poses:
        lines += ["[start_poses]"] + [f"{s.agent_id} = {s.start_pose}" for s in streams]
    lines += extra_toml
    cfg.write_text("\n".join(lines) + "\n")
    from hivemap.eval.processes import free_port

    port = free_port()
    log = open(work / "server.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, __file__, "serve", "--port", str(port), "--data-dir", str(work / "data"),
         "--config", str(cfg)] + ([] if profile is None else ["--profile", str(profile)]),
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    os.sched_setaffinity(proc.pid, set(sorted(os.sched_getaffinity(0))[:cores]))
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240  # imports take long on a loaded machine
        while True:
            try:
                if httpx.get(url + "/health", timeout=1).json().get("status") == "ok":
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"error: server did not start (log {work / 'server.log'})")
            time.sleep(0.3)
        cpu0, t0 = _proc_cpu_s(proc.pid), time.monotonic()
        stats = asyncio.run(replay(f"ws://127.0.0.1:{port}/ws", streams))
        t_sent = time.monotonic()
        while time.monotonic() < t_sent + drain_s:
            if httpx.get(url + "/bench/figures", timeout=30).json()["idle"]:
                break
            time.sleep(0.5)
        t_end = time.monotonic()
        cpu = _proc_cpu_s(proc.pid) - cpu0
        fig = httpx.get(url + "/bench/figures", timeout=30).json()
        rss = _proc_rss_mb(proc.pid)
        events = httpx.get(url + "/events", params={"limit": 100_000}, timeout=60).json()["events"]
        team = team_ate(url, rec, work)
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    n_kf = sum(s.keyframes for s in stats)
    lags = fig["query_lags"]
    res = {
        "agents": n, "cores": cores, "keyframes": n_kf, "queries": fig["queries"],
        "unfinished": fig["queued"],
        "lag_p50": _pct(lags, 50), "lag_p95": _pct(lags, 95), "lag_max": max(lags, default=float("nan")),
        "dropped": fig["dropped"], "skipped": fig.get("skipped", 0),
        "job_kb_mean": float(np.mean(fig["job_bytes"])) / 1e3 if fig.get("job_bytes") else float("nan"),
        "pickle_ms_mean": _mean([x[0] for x in fig.get("ship", [])]),
        "pickle_kb_mean": _mean([x[1] for x in fig.get("ship", [])]) / 1e3,
        "sent_kb_mean": _mean(fig.get("sent", [])) / 1e3,
        "corr_p50": _pct(fig["correction_latencies"], 50),
        "corr_p95": _pct(fig["correction_latencies"], 95), "n_corr": len(fig["correction_latencies"]),
        "query_ms_mean": float(np.mean(fig["query_ms"])) if fig["query_ms"] else float("nan"),
        "query_cpu_ms_mean": float(np.mean(fig["query_cpu_ms"])) if fig["query_cpu_ms"] else float("nan"),
        "query_cpu_ms_p95": _pct(fig["query_cpu_ms"], 95),
        "verify_cpu_ms_per_query": fig["verify_cpu_ms"] / max(1, fig["queries"]),
        "verifications": fig["verifications"],
        "full_verifications": fig.get("full_verifications", fig["verifications"]),
        "merges": fig["visual_merges"], "loops": fig["loops"],
        "maps": fig["maps"], "cpu_pct": 100 * cpu / max(t_end - t0, 1e-9), "rss_mb": rss,
        "wall_s": t_end - t0, "send_late_p95": _pct([x for s in stats for x in s.late_s], 95),
        "errors": sorted({e for s in stats for e in s.errors})[:5],
    }  # fmt: skip
    res.update(quality(rec, events))
    res.update(team)
    res["kept_up"] = bool(res["dropped"] == 0 and res["unfinished"] == 0 and res["lag_p95"] <= LAG_OK_S)
    if keep is not None:  # the server's store, log, events and lag timeline, to look at what it did
        (work / "events.json").write_text(json.dumps(events))
        (work / "lag_timeline.json").write_text(json.dumps(fig.get("lag_timeline", [])))
        shutil.copytree(work, keep / f"n{n}", dirs_exist_ok=True)
    shutil.rmtree(work, ignore_errors=True)
    return res


def summary(r: dict[str, Any]) -> str:
    parts = [
        f"{r['keyframes']} keyframes, {r['queries']} queries ({r['unfinished']} unfinished, "
        f"{r['dropped']} dropped, {r['skipped']} skipped in a backlog)",
        f"query lag p50 {r['lag_p50']:.2f} s p95 {r['lag_p95']:.2f} s max {r['lag_max']:.2f} s",
        f"query {r['query_ms_mean']:.0f} ms mean (CPU {r['query_cpu_ms_mean']:.0f} ms mean, "
        f"p95 {r['query_cpu_ms_p95']:.0f} ms), {r['verifications']} verifications, "
        f"{r['full_verifications']} of them full (phase 2) "
        f"(CPU {r['verify_cpu_ms_per_query']:.0f} ms per query), job {r['job_kb_mean']:.0f} kB mean "
        f"(pickled {r['pickle_kb_mean']:.0f} kB in {r['pickle_ms_mean']:.1f} ms CPU, "
        f"sent to a worker {r['sent_kb_mean']:.0f} kB)",
        f"corrections {r['n_corr']} p50 {r['corr_p50'] * 1e3:.0f} ms p95 {r['corr_p95'] * 1e3:.0f} ms",
        f"visual merges {r['merges']} loops {r['loops']} maps {r['maps']}",
        f"detections {r['detections']}, accepted candidates {r['accepted']}",
        f"loop error median {r['loop_err_m_median']:.3f} m max {r['loop_err_m_max']:.3f} m "
        f"({r['loop_errors']} loops)",
        f"first copy's team ATE {r['team_ate_worst']:.3f} m (worst map; "
        + ", ".join(f"{'+'.join(m['agents'])} {m['team_ate_rmse']:.3f}" for m in r["team_maps"])
        + ")",
        f"server CPU {r['cpu_pct']:.0f} % RSS {r['rss_mb']:.0f} MB",
        "kept up" if r["kept_up"] else "BEHIND",
    ]
    if r["errors"]:
        parts.append(f"errors {r['errors']}")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="keep a finished run's keyframe streams")
    r.add_argument("--scenario-dir", type=Path, required=True)
    r.add_argument("--run-dir", type=Path, required=True, help="holds <agent>/outbox.sqlite")
    r.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("run", help="replay N copies into a real server")
    p.add_argument("--recording", type=Path, required=True)
    p.add_argument("--agents", default="4,8,16,32")
    p.add_argument("--cores", type=int, default=1, help="CPUs the server process may use")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed (1 = the recorded pace)")
    p.add_argument("--duration", type=float, default=None, help="replay only the first S seconds")
    p.add_argument("--drain", type=float, default=120.0, help="wait at most S seconds for the queue")
    p.add_argument("--no-start-poses", action="store_true", help="the server is not told the start poses")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    p.add_argument("--profile", type=Path, default=None, help="cProfile the queries into DIR/N.prof")
    p.add_argument("--server-toml", action="append", default=[], metavar="LINE",
                   help="a line appended to the server's config, e.g. '[backend.scheduler]'")  # fmt: skip
    p.add_argument("--keep", type=Path, default=None, help="keep each run's server store and log in DIR/nN")
    s = sub.add_parser("serve", help=argparse.SUPPRESS)
    s.add_argument("--port", type=int, required=True)
    s.add_argument("--data-dir", type=Path, required=True)
    s.add_argument("--config", type=Path, required=True)
    s.add_argument("--profile", type=Path, default=None)
    if not (sys.argv[1:] if argv is None else argv):  # `make bench` runs every bench bare
        print("bench/team.py: nothing to replay without a recording (`record`, then `run`; see --help)")
        return 0
    args = ap.parse_args(argv)
    if args.cmd == "record":
        record(args.scenario_dir, args.run_dir, args.out)
        return 0
    if args.cmd == "serve":
        serve(args.port, args.data_dir, args.config, args.profile)
        return 0
    results = []
    for n in [int(x) for x in args.agents.split(",")]:
        prof = None
        if args.profile is not None:
            args.profile.mkdir(parents=True, exist_ok=True)
            prof = args.profile / f"{n}.prof"
        res = run_one(args.recording, n, args.cores, args.speed, args.duration, args.drain,
                      not args.no_start_poses, prof, tuple(args.server_toml), args.keep)  # fmt: skip
        results.append(res)
        print(f"N={n:3d} cores={args.cores}: " + summary(res), flush=True)
    ok = [r["agents"] for r in results if r["kept_up"]]
    best = max(ok, default=0)
    print(f"largest N kept up with: {best} on {args.cores} core(s) = {best / args.cores:.1f} agents per core")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
