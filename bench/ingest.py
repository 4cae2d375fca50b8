"""Ingest benchmark: a real `hivemap server` subprocess and a load generator on loopback.

Prints sustained keyframes/s for 1000-feature keyframes (agents sending as fast as acks allow), the p50/p99
ack latency (send -> ack, measured by the agent) with 4 and 16 agents, paced at 5 keyframes/s per agent and
saturated, and the bytes per keyframe on the wire. Bounded: a fixed number of keyframes per phase and a
time limit per phase.

    .venv/bin/python bench/ingest.py [--kf-per-agent 300] [--paced-seconds 8]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from hivemap.protocol import Keyframe
from hivemap.server.loadgen import StreamStats, stream_agent, synthetic_stream

FEATURES = 1000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(data: Path, n_agents: int, synchronous: str) -> tuple[subprocess.Popen[bytes], int]:
    port = free_port()
    cfg = data / "server.toml"
    cfg.write_text(
        f'sqlite_synchronous = "{synchronous}"\nlog_level = "warning"\nbackend = false\n[tokens]\n'
        + "".join(f'a{i} = "t{i}"\n' for i in range(n_agents))
    )
    cmd = [sys.executable, "-m", "hivemap.cli.main", "server", "--port", str(port),
           "--data-dir", str(data / "store"), "--config", str(cfg)]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
    proc = subprocess.Popen(cmd, env=env)
    for _ in range(300):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                return proc, port
        except httpx.HTTPError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("server did not start")


async def run_phase(
    port: int, streams: list[list], rate_hz: float | None, time_limit: float
) -> tuple[list[StreamStats], float]:
    url = f"ws://127.0.0.1:{port}/ws"
    t0 = time.perf_counter()
    tasks = [
        stream_agent(
            url,
            f"a{i}",
            f"t{i}",
            msgs,
            rate_hz=rate_hz,
            window=32,
            first_seq=1,
            timeout=time_limit,
            phase=(i / len(streams) / rate_hz) if rate_hz else 0.0,  # agents spread over one period
        )  # fmt: skip
        for i, msgs in enumerate(streams)
    ]
    stats = await asyncio.wait_for(asyncio.gather(*tasks), time_limit)
    return list(stats), time.perf_counter() - t0


def report(name: str, stats: list[StreamStats], elapsed: float) -> dict[str, float]:
    kfs = sum(s.keyframes for s in stats)
    lat = np.concatenate([np.asarray(s.latencies) for s in stats]) * 1000.0
    errors = sum(len(s.errors) for s in stats)
    out = {
        "kf_per_s": kfs / elapsed,
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(lat.max()),
    }
    print(
        f"{name:<34} {kfs:5d} kf in {elapsed:6.2f} s = {out['kf_per_s']:7.1f} kf/s   "
        f"ack latency p50 {out['p50_ms']:6.1f} ms  p99 {out['p99_ms']:6.1f} ms  max {out['max_ms']:6.1f} ms"
        + (f"  ERRORS {errors}" if errors else ""),
        flush=True,
    )
    return out


def make_streams(n_agents: int, n_kf: int, seed: int) -> list[list]:
    return [
        synthetic_stream(
            f"a{i}", n_kf, features=FEATURES, new_points_per_kf=80, observed_per_kf=400, seed=seed + i
        )[0]
        for i in range(n_agents)
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--kf-per-agent", type=int, default=300, help="keyframes per agent at 4 agents, saturated"
    )
    ap.add_argument("--paced-seconds", type=float, default=8.0, help="length of the 5 kf/s phases")
    ap.add_argument("--synchronous", default="FULL", choices=["FULL", "NORMAL"], help="SQLite durability")
    ap.add_argument("--time-limit", type=float, default=120.0, help="per phase, seconds")
    args = ap.parse_args()

    print(f"hivemap ingest bench: {FEATURES}-feature keyframes, SQLite synchronous={args.synchronous}, "
          f"{os.cpu_count()} CPUs (server and load generator share them)", flush=True)  # fmt: skip
    results: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="hivemap-bench-") as tmp:
        for n_agents in (4, 16):
            data = Path(tmp) / f"run{n_agents}"
            data.mkdir()
            proc, port = start_server(data, n_agents, args.synchronous)
            try:
                n_paced = max(1, int(5 * args.paced_seconds))
                paced = make_streams(n_agents, n_paced, seed=1000 * n_agents)
                gc.collect()
                gc.freeze()
                stats, elapsed = asyncio.run(run_phase(port, paced, 5.0, args.time_limit))
                results[f"paced{n_agents}"] = report(f"{n_agents:2d} agents x 5 kf/s (paced)", stats, elapsed)
                if n_agents == 4:
                    kf_frames = [s.keyframe_bytes / max(1, s.keyframes) for s in stats]
                    all_bytes = sum(s.bytes_sent for s in stats) / max(1, sum(s.keyframes for s in stats))
                    ex = next(m for m in paced[0] if isinstance(m, Keyframe))
                    print(
                        f"bytes per keyframe on the wire: keyframe message {np.mean(kf_frames):,.0f} B "
                        f"({len(ex.keypoints)} features); all messages (points, pose updates) per keyframe "
                        f"{all_bytes:,.0f} B",
                        flush=True,
                    )
                # Saturated: new agent sessions so the ids are fresh.
                n_kf = max(1, args.kf_per_agent * 4 // n_agents)
                sat = [
                    synthetic_stream(
                        f"a{i}", n_kf, features=FEATURES, new_points_per_kf=80, observed_per_kf=400,
                        seed=7 + i, session=1,
                    )[0]
                    for i in range(n_agents)
                ]  # fmt: skip
                gc.collect()
                gc.freeze()  # the generated messages are long-lived: keep the collector off them
                stats, elapsed = asyncio.run(run_phase_offset(port, sat, paced, args.time_limit))
                results[f"sat{n_agents}"] = report(f"{n_agents:2d} agents, as fast as acked", stats, elapsed)
            finally:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()
    ok_rate = max(results["sat4"]["kf_per_s"], results["sat16"]["kf_per_s"]) >= 200
    ok_lat = results["paced4"]["p99_ms"] <= 50
    print(f"targets: >= 200 kf/s {'MET' if ok_rate else 'MISSED'}; p99 <= 50 ms at 4 agents x 5 kf/s "
          f"{'MET' if ok_lat else 'MISSED'}")  # fmt: skip


async def run_phase_offset(
    port: int, streams: list[list], previous: list[list], time_limit: float
) -> tuple[list[StreamStats], float]:
    """Like run_phase, with seqs continuing after the previous phase's messages (one seq space per agent)."""
    url = f"ws://127.0.0.1:{port}/ws"
    t0 = time.perf_counter()
    tasks = [
        stream_agent(
            url, f"a{i}", f"t{i}", msgs, window=32, first_seq=len(previous[i]) + 1, timeout=time_limit
        )
        for i, msgs in enumerate(streams)
    ]
    stats = await asyncio.wait_for(asyncio.gather(*tasks), time_limit)
    return list(stats), time.perf_counter() - t0


if __name__ == "__main__":
    main()
