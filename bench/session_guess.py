"""A tracking loss end to end: the real front-end, the real link, a real server with its back-end.

    .venv/bin/python bench/session_guess.py [--radius 4] [--speed 2.5] [--blackout 1.5] [--hold 1.0]
        [--no-guess]

The synthetic scene's circle at 10 Hz with the IMU; black frames from t = 2 s for ``--blackout`` s, longer
than the IMU hold, so the agent starts session 1 with its guess; then it flies on to complete a lap and
returns to where session 0 began. Prints the tracking states, the maps, merges and loops at the end, and
session 1's keyframe errors on the server (m) in session 0's frame (SE(3)-aligned on session 0's
keyframes). ~90 s CPU.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import threading
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import uvicorn

from hivemap.client import Agent
from hivemap.client.agent import AgentOptions
from hivemap.client.frontend import FrontendOptions
from hivemap.client.frontend.synthetic import make_sequence
from hivemap.maps.geometry import Sim3
from hivemap.server.app import create_app, uvicorn_config_kwargs
from hivemap.server.backend import installer, preset
from hivemap.server.backend.options import SchedulerOptions
from hivemap.server.settings import ServerSettings


def _serve(data: Path, port: int, guess: bool) -> tuple[Any, Any, threading.Thread]:
    settings = ServerSettings(port=port, data_dir=data, tokens={"uav1": "t"}, log_level="warning")
    opts = preset("default", scheduler=SchedulerOptions(verifications_per_s=1000.0))
    opts = replace(opts, accept=replace(opts.accept, session_guess=guess))
    app = create_app(settings, extensions=[installer(opts)])
    server = uvicorn.Server(uvicorn.Config(app, **uvicorn_config_kwargs(settings)))  # type: ignore[arg-type]
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not (server.started and app.state.hive.loaded.is_set()):
        time.sleep(0.05)
    return app.state.hive, server, thread


def _call(hive: Any, fn: Any) -> Any:
    async def run() -> Any:
        return fn()

    return asyncio.run_coroutine_threadsafe(run(), hive.loop).result(30)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, default=4.0)
    ap.add_argument("--speed", type=float, default=2.5)
    ap.add_argument("--blackout", type=float, default=1.5)
    ap.add_argument("--hold", type=float, default=1.0)
    ap.add_argument("--no-guess", action="store_true", help="the server ignores the guess (as before)")
    a = ap.parse_args()
    rate = 10.0
    n = int((2 * np.pi * a.radius / a.speed + 3.0) * rate)
    black = range(int(2.0 * rate), int((2.0 + a.blackout) * rate))
    seq = make_sequence(n, rate=rate, seed=3, radius=a.radius, speed=a.speed)
    port = 18000 + int(time.time()) % 1000
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        hive, server, thread = _serve(Path(tmp) / "data", port, not a.no_guess)
        try:
            opts = AgentOptions(frontend=FrontendOptions(imu_hold_s=a.hold))
            agent = Agent(seq.rig, agent_id="uav1", imu_noise={}, options=opts)
            agent.connect(f"ws://127.0.0.1:{port}/ws", "t", Path(tmp) / "agent")
            states: Counter[str] = Counter()
            ti = 0
            for i in range(n):
                t = float(seq.times[i])
                while ti < len(seq.imu) and seq.imu[ti, 0] <= t:
                    agent.feed_imu(seq.imu[ti, 0], seq.imu[ti, 1:4], seq.imu[ti, 4:7])
                    ti += 1
                left, right = seq.images(i)
                if i in black:
                    left, right = np.zeros_like(left), np.zeros_like(right)
                states[agent.feed_stereo(t, left, right).state] += 1
            agent.close(timeout=60)
            idle = 0
            while idle < 3:  # the back-end idle three polls in a row
                idle = idle + 1 if _call(hive, hive.backend.idle) else 0
                time.sleep(0.3)
            maps = _call(hive, lambda: {mid: (sorted(m.agents), {k: (kf.timestamp, kf.world_from_cam.copy())
                                                                 for k, kf in m.keyframes.items()})
                                        for mid, m in hive.stack.maps.items()})  # fmt: skip
            merges = _call(hive, lambda: [dict(r) for r in hive.backend.merges])
            loops = _call(hive, lambda: [dict(r) for r in hive.backend.loops])
        finally:
            server.should_exit = True
            thread.join(15)
    cpu = time.process_time() - cpu0
    print(f"{n} frames, black {black.start}-{black.stop - 1}, states {dict(states)}")
    print("maps", {mid: agents for mid, (agents, _) in maps.items()})
    for r in merges:
        by = r.get("by", "place_recognition")
        sig = f"{r['sigma_trans_m']:.2f} m / {r['sigma_rot_deg']:.1f} deg"
        print(f"merge by {by}: on_trial {r.get('on_trial')}, undone {bool(r.get('undone'))}, sigma {sig}")
    across = [lp for lp in loops if lp["query"][0].split("#")[0] == lp["candidate"][0].split("#")[0]
              and lp["query"][0] != lp["candidate"][0] and not lp.get("rejected")]  # fmt: skip
    print(f"loops {len(loops)}, across the sessions {len(across)}")

    def truth(ts: float) -> np.ndarray:
        i = int(np.argmin(np.abs(seq.times - ts)))
        return np.asarray(seq.world_from_body[i] @ seq.rig.body_from_left)[:3, 3]

    from evo.core.geometry import umeyama_alignment

    for agents, kfs in maps.values():
        if "uav1" not in agents or "uav1#1" not in agents:
            continue
        s0 = [v for k, v in sorted(kfs.items()) if k[0] == "uav1"]
        s1 = [v for k, v in sorted(kfs.items()) if k[0] == "uav1#1"]
        est0 = np.array([T[:3, 3] for _, T in s0])
        R, t, _ = umeyama_alignment(est0.T, np.array([truth(ts) for ts, _ in s0]).T, False)
        align = Sim3(R, t, 1.0)
        err = [np.linalg.norm(align.apply(T[:3, 3]) - truth(ts)) for ts, T in s1]
        err0 = np.linalg.norm(align.apply(est0) - np.array([truth(ts) for ts, _ in s0]), axis=1)
        print(f"session 0 on the server: ATE max {err0.max():.3f} m; session 1 at the end: mean "
              f"{np.mean(err):.3f} m, max {np.max(err):.3f} m over {len(s1)} keyframes")  # fmt: skip
    print(f"cpu {cpu:.0f} s")


if __name__ == "__main__":
    main()
