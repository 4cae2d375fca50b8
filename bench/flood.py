"""Flood benchmark (issue 21, case 5): one authenticated agent floods a real `hivemap server` with valid map
points while a second agent streams normally.

Prints, per phase, what the flooder sent and what the server stored of it, the replies it got (acks,
``rate`` and ``quota`` errors), the server's RSS (``/proc``) before, at its peak and after, against the
memory bound its ``[quotas]`` imply, and whether the normal agent was served (every message acknowledged,
ack latency p50/p99).

Phases: ``defaults`` (the default quotas: the rate limit refuses most of the flood) and ``totals`` (rate
limits lifted, so the per-agent total ``max_points`` is what stops the flood).

    .venv/bin/python bench/flood.py [--mb 164] [--points-per-msg 4000] [--phases defaults,totals]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from hivemap.protocol import Ack, MapPoints, decode, encode
from hivemap.protocol import Error as ErrorMsg
from hivemap.server.loadgen import hello, stream_agent, synthetic_stream
from hivemap.server.settings import QuotaSettings

POINT_BYTES_ON_WIRE = 8 + 24 + 32  # id, xyz, descriptor
# Server memory per stored item, for the bound the quotas imply. Points: measured with this bench's
# "totals" phase (RSS growth / points stored: 850-1200 B). Keyframes: estimated, not measured: a
# 1000-feature keyframe holds ~50 kB of arrays (descriptors, keypoints, point ids) plus Python objects.
RSS_PER_POINT = 1200
RSS_PER_KEYFRAME = 60_000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def implied_bound_mb(q: QuotaSettings, agents: int, baseline_mb: float) -> float:
    per_agent = q.max_points * RSS_PER_POINT + q.max_keyframes * RSS_PER_KEYFRAME
    return baseline_mb + agents * per_agent / 2**20


@dataclass
class FloodStats:
    sent: int = 0
    points_sent: int = 0
    bytes_sent: int = 0
    acked: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    elapsed: float = 0.0


async def flood(url: str, agent_id: str, token: str, total_bytes: int, per_msg: int) -> FloodStats:
    """Valid, new map points as fast as the server reads them; replies are counted, not awaited."""
    import websockets

    st = FloodStats()
    rng = np.random.default_rng(1)
    n_msgs = max(1, total_bytes // (per_msg * POINT_BYTES_ON_WIRE))
    xyz = rng.normal(0, 20, (per_msg, 3))
    desc = rng.integers(0, 256, (per_msg, 32), dtype=np.uint8)
    t0 = time.perf_counter()
    async with websockets.connect(url, max_size=None, compression=None) as ws:
        await ws.send(encode(hello(agent_id, token), 0))
        await ws.recv()
        replies = 0

        async def reader() -> None:
            nonlocal replies
            async for frame in ws:
                _, msg = decode(frame)  # type: ignore[arg-type]
                if isinstance(msg, Ack):
                    st.acked += 1
                elif isinstance(msg, ErrorMsg):
                    st.errors[msg.code] += 1
                replies += 1

        task = asyncio.create_task(reader())
        for i in range(n_msgs):
            ids = np.arange(i * per_msg, (i + 1) * per_msg, dtype=np.int64)
            frame = encode(MapPoints(ids, xyz, desc, 0), i + 1)
            await ws.send(frame)
            st.sent += 1
            st.points_sent += per_msg
            st.bytes_sent += len(frame)
        deadline = time.monotonic() + 60
        while replies < n_msgs and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        task.cancel()
    st.elapsed = time.perf_counter() - t0
    return st


async def sample_rss(pid: int, out: list[float], stop: asyncio.Event) -> None:
    while not stop.is_set():
        out.append(rss_mb(pid))
        await asyncio.sleep(0.2)


def run_phase(name: str, quotas: dict[str, float], mb: float, per_msg: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        port = free_port()
        cfg = data / "server.toml"
        table = "".join(f"{k} = {v!r}\n" for k, v in quotas.items())
        cfg.write_text(
            'log_level = "warning"\nbackend = false\n'
            f'[quotas]\n{table}[tokens]\nflood = "t-flood"\nnormal = "t-normal"\n'
        )
        q = QuotaSettings(**quotas)
        cmd = [sys.executable, "-m", "hivemap.cli.main", "server", "--port", str(port),
               "--data-dir", str(data / "store"), "--config", str(cfg)]  # fmt: skip
        env = {k: v for k, v in os.environ.items() if not k.startswith("HIVEMAP_")}
        proc = subprocess.Popen(cmd, env=env)
        base = f"http://127.0.0.1:{port}"
        try:
            for _ in range(300):
                try:
                    if httpx.get(base + "/health", timeout=1).json()["status"] == "ok":
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.1)
            time.sleep(0.5)
            baseline = rss_mb(proc.pid)
            url = f"ws://127.0.0.1:{port}/ws"
            normal_msgs, _ = synthetic_stream("normal", 100, features=1000, new_points_per_kf=100)

            async def main() -> tuple[FloodStats, object, list[float]]:
                samples: list[float] = []
                stop = asyncio.Event()
                sampler = asyncio.create_task(sample_rss(proc.pid, samples, stop))
                fl = asyncio.create_task(flood(url, "flood", "t-flood", int(mb * 2**20), per_msg))
                normal = asyncio.create_task(
                    stream_agent(url, "normal", "t-normal", normal_msgs, rate_hz=10.0, timeout=120)
                )
                f, n = await fl, await normal
                await asyncio.sleep(1.0)
                stop.set()
                await sampler
                return f, n, samples

            f, n, samples = asyncio.run(main())
            agents = {a["agent_id"]: a for a in httpx.get(base + "/agents", timeout=10).json()["agents"]}
            events = httpx.get(base + "/events", params={"kind": "quota"}, timeout=10).json()["events"]
            final = rss_mb(proc.pid)
        finally:
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(60)
        stored = agents["flood"]["points"]
        lat = np.asarray(n.latencies) * 1000  # type: ignore[attr-defined]
        served = n.acked == len(normal_msgs) and not n.errors  # type: ignore[attr-defined]
        bound = implied_bound_mb(q, 2, baseline)
        print(f"\n== phase {name}: quotas {quotas or 'defaults'}")
        print(f"flood: {f.bytes_sent / 2**20:.0f} MB sent in {f.sent} frames ({f.points_sent} points) "
              f"in {f.elapsed:.1f} s; acked {f.acked}, errors {dict(f.errors)}; stored {stored} points "
              f"(max_points {q.max_points})")  # fmt: skip
        print(f"server RSS: {baseline:.0f} MB before, {max(samples, default=final):.0f} MB peak, "
              f"{final:.0f} MB after; bound the quotas imply for 2 agents: {bound:.0f} MB "
              f"({'under' if max(samples, default=final) <= bound else 'OVER'})")  # fmt: skip
        if stored:
            growth = (max(samples, default=final) - baseline) * 2**20 / stored
            print(f"  RSS growth per stored flood point: {growth:.0f} B")
        print(f"normal agent: {n.acked}/{len(normal_msgs)} acked, errors {len(n.errors)}, "  # type: ignore[attr-defined]
              f"ack p50 {np.percentile(lat, 50):.1f} ms p99 {np.percentile(lat, 99):.1f} ms -> "
              f"{'served' if served else 'NOT served'}")  # fmt: skip
        print(f"quota events: {len(events)}; server exit code on SIGTERM: {rc}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mb", type=float, default=164.0, help="map point payload the flooder sends (MB)")
    ap.add_argument("--points-per-msg", type=int, default=4000)
    ap.add_argument("--phases", default="defaults,totals")
    args = ap.parse_args()
    phases: dict[str, dict[str, float]] = {
        "defaults": {},
        "totals": {"points_per_s": 1e9, "points_burst": 10**9},
    }
    for name in args.phases.split(","):
        run_phase(name, phases[name], args.mb, args.points_per_msg)


if __name__ == "__main__":
    main()
