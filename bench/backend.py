"""Collaboration back-end benchmark.

1. Place-recognition BoW step of a query (feasibility check + merge candidates + loop candidates, as
   ``PlaceRecognizer.detect`` runs them before verification) vs keyframe-database size (1k/10k/50k).
   Database keyframes: BoW vectors of synthetic keyframes (600 descriptors drawn from a 30k-descriptor
   world with bit flips), 300 distinct ones repeated under new keys across 20 maps.
2. End to end on a real server (uvicorn in a thread, real WebSocket agents): K pairs of overlapping agents
   (a UGV and a UAV under scale 2.5) stream their maps; reported: full query time (with geometric
   verification), merge time (``apply_merge``), global BA of the merged maps, correction latency
   (detection -> correction handed to the agent's connection; loopback delivery adds ~1 ms) median/p95,
   correction bytes per agent.
3. Global BA (pycolmap, one thread) of synthetic maps with 500 and 2000 keyframes.

Run: .venv/bin/python bench/backend.py [--sizes 1000 10000 50000] [--pairs 4] [--ba 500 2000]
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp


def _stats(a: list[float] | np.ndarray, unit: str = "ms") -> str:
    x = np.asarray(a, dtype=float)
    if len(x) == 0:
        return "n/a"
    p95 = np.percentile(x, 95)
    return f"median {np.median(x):.1f} {unit}, p95 {p95:.1f} {unit}, max {x.max():.1f} (n={len(x)})"


def bench_query(sizes: list[int], n_queries: int = 40) -> None:
    from hivemap.maps.kfdb import KeyframeDatabase
    from hivemap.maps.vocabulary import default_vocabulary
    from hivemap.server.backend_synth import flip_bits

    rng = np.random.default_rng(0)
    vocab = default_vocabulary()
    world = rng.integers(0, 256, (30000, 32), dtype=np.uint8)
    t0 = time.perf_counter()
    bows = [vocab.transform(flip_bits(world[rng.choice(len(world), 600, replace=False)], rng, 3))[0]
            for _ in range(300)]  # fmt: skip
    print(
        f"vocabulary transform (600 features): {(time.perf_counter() - t0) / 300 * 1e3:.2f} ms per keyframe"
    )
    for n in sizes:
        db = KeyframeDatabase()
        for i in range(n):
            db.add((f"a{i % 20}", i), i % 20, bows[i % len(bows)])
        ts = []
        for q in range(n_queries):
            bow = bows[q % len(bows)]
            t = time.perf_counter()
            s = db.scores(bow)  # as PlaceRecognizer.detect: one scoring shared by the three look-ups
            db.feasibility(bow, 0, ratio=0.3, scores=s)
            db.query(bow, 16, exclude_map=0, scores=s)
            db.query(bow, 16, only_map=0, exclude_keys=[("a0", j) for j in range(5)], scores=s)
            ts.append((time.perf_counter() - t) * 1e3)
        print(f"BoW query step, {n:>6} keyframes: {_stats(ts)}")


class _Server:
    def __init__(self, data_dir: Path, tokens: dict[str, str]) -> None:
        import socket

        import uvicorn

        from hivemap.server.app import create_app, uvicorn_config_kwargs
        from hivemap.server.backend import installer, preset
        from hivemap.server.settings import ServerSettings

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        settings = ServerSettings(port=port, data_dir=data_dir, tokens=tokens, log_level="warning")
        opts = preset("monocular")  # UAVs at scale 2.5
        self.app = create_app(settings, extensions=[installer(opts)])
        self.server = uvicorn.Server(uvicorn.Config(self.app, **uvicorn_config_kwargs(settings)))  # type: ignore[arg-type]
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        while not self.server.started:
            time.sleep(0.05)
        self.hive: Any = self.app.state.hive
        self.ws_url = f"ws://127.0.0.1:{port}/ws"

    def call(self, fn: Any) -> Any:
        async def run() -> Any:
            return fn()

        return asyncio.run_coroutine_threadsafe(run(), self.hive.loop).result(30)

    def wait_idle(self, timeout: float = 600) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.call(self.hive.backend.idle):
                time.sleep(0.5)
                if self.call(self.hive.backend.idle):
                    return
            time.sleep(0.2)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30)


def bench_end_to_end(pairs: int) -> None:
    from websockets.sync.client import connect

    from hivemap.protocol import Ack, Correction, decode, encode
    from hivemap.server.backend_synth import agent_stream, make_world
    from hivemap.server.loadgen import hello

    rng = np.random.default_rng(1)
    tokens = {f"{k}{i}": f"tok-{k}{i}" for i in range(pairs) for k in ("ugv", "uav")}
    ugv_from_world = Sim3(so3_exp(np.array([0.0, 0.0, 0.4])), np.array([3.0, -2.0, 0.5]), 1.0)
    uav_from_world = Sim3(so3_exp(np.array([0.3, -0.5, 1.2])), np.array([12.0, -7.0, 4.0]), 2.5)
    with tempfile.TemporaryDirectory() as tmp:
        srv = _Server(Path(tmp) / "data", tokens)
        conns = []
        t_start = time.monotonic()
        try:
            for i in range(pairs):
                x0 = 300.0 * i  # disjoint areas: one merge per pair
                pts, desc = make_world(rng, 2500, (x0 - 20, x0 + 30))
                # agents' local (VIO) frames start where they start (far-from-origin frames make the Sim(3)
                # refinement of place recognition ill-conditioned: t, R and s correlate over the lever arm)
                shift = Sim3(np.eye(3), np.array([-x0, 0.0, 0.0]), 1.0)
                plan = [
                    ("ugv", ugv_from_world @ shift, np.linspace(x0 - 6, x0 + 8, 10)),
                    ("uav", uav_from_world @ shift, np.linspace(x0 - 2, x0 + 12, 12)),
                ]
                for kind, frame, xs in plan:
                    msgs, _, _ = agent_stream(rng, pts, desc, xs, frame, pose_noise=(0.03, 0.2))
                    aid = f"{kind}{i}"
                    ws = connect(srv.ws_url, max_size=None, compression=None, legacy=True)
                    ws.send(encode(hello(aid, tokens[aid], kind), 0))
                    decode(ws.recv(timeout=10))
                    for s, m in enumerate(msgs, 1):
                        ws.send(encode(m, s))
                    conns.append((aid, ws, len(msgs)))
            got: dict[str, list[Correction]] = {aid: [] for aid, _, _ in conns}
            for _aid, ws, n in conns:
                acks = 0
                while acks < n:
                    msg = decode(ws.recv(timeout=60))[1]
                    acks += isinstance(msg, Ack)
            srv.wait_idle()
            elapsed = time.monotonic() - t_start
            for aid, ws, _ in conns:
                while True:
                    try:
                        msg = decode(ws.recv(timeout=0.5))[1]
                    except TimeoutError:
                        break
                    if isinstance(msg, Correction):
                        got[aid].append(msg)
            be = srv.hive.backend
            n_maps = srv.call(lambda: len(srv.hive.stack.maps))
            print(f"end to end: {pairs} pairs, {2 * pairs} agents -> {n_maps} maps, {len(be.merges)} merges")
            print(
                f"  full query (BoW + verification): {_stats(be.query_ms)}; {be.verifications} verifications"
            )
            print(f"  merge (apply_merge incl. persist): {_stats([m['merge_ms'] for m in be.merges])}")
            print(f"  global BA of merged maps: {_stats([b['ms'] for b in be.ba_runs])}"
                  f" ({[b['n_keyframes'] for b in be.ba_runs][:6]} keyframes)")  # fmt: skip
            print(
                f"  correction latency (detection -> sent): {_stats(np.array(be.correction_latencies) * 1e3)}"
            )
            per_agent = [be.correction_bytes.get(aid, 0) for aid, _, _ in conns]
            print(f"  downlink per agent: median {np.median(per_agent):.0f} B, max {max(per_agent)} B, "
                  f"{elapsed:.1f} s session -> {max(per_agent) / elapsed:.0f} B/s worst agent")  # fmt: skip
            print(f"  corrections received by agents: {sum(len(v) for v in got.values())}")
        finally:
            for _, ws, _ in conns:
                ws.close()
            srv.stop()


def bench_ba(sizes: list[int]) -> None:
    from hivemap.server.loadgen import CAMERA
    from hivemap.server.optim import BundleAdjustmentOptions, global_bundle_adjustment

    for n in sizes:
        rng = np.random.default_rng(n)
        # a corridor: keyframes every 0.5 m along x, facades at z = 8..14 m
        n_pts = n * 40
        length = 0.5 * n
        pts = np.stack(
            [rng.uniform(-10, length + 10, n_pts), rng.uniform(-5, 5, n_pts), rng.uniform(8, 14, n_pts)], 1
        )
        true = [
            se3(so3_exp(rng.normal(0, 0.03, 3)), np.array([0.5 * k, rng.normal(0, 0.2), 0.0]))
            for k in range(n)
        ]
        order = np.argsort(pts[:, 0])
        xs = pts[order, 0]
        obs_kf, obs_pt, obs_uv = [], [], []
        for k, T in enumerate(true):
            lo, hi = np.searchsorted(xs, [T[0, 3] - 12, T[0, 3] + 12])
            cand = order[lo:hi]
            pc = (pts[cand] - T[:3, 3]) @ T[:3, :3]
            uv, ok = CAMERA.project(pc)
            ok &= CAMERA.in_image(uv) & (pc[:, 2] > 1)
            sel = np.flatnonzero(ok)
            if len(sel) > 150:
                sel = rng.choice(sel, 150, replace=False)
            obs_kf += [k] * len(sel)
            obs_pt += cand[sel].tolist()
            obs_uv.append(uv[sel] + rng.normal(0, 0.7, (len(sel), 2)))
        noisy = np.array([T @ se3(so3_exp(rng.normal(0, 0.003, 3)), rng.normal(0, 0.03, 3)) for T in true])
        noisy[:2] = np.array(true[:2])
        true_arr = np.array(true)
        noisy_pts = pts + rng.normal(0, 0.03, pts.shape)
        for prior in (None, 0.1):
            t0 = time.perf_counter()
            res = global_bundle_adjustment(
                [CAMERA], np.zeros(n, np.int64), noisy, noisy_pts,
                np.array(obs_kf), np.array(obs_pt), np.concatenate(obs_uv), {0, 1},
                BundleAdjustmentOptions(max_iterations=30, num_threads=1, position_prior_m=prior),
            )  # fmt: skip
            dt = time.perf_counter() - t0
            err0 = np.linalg.norm(noisy[:, :3, 3] - true_arr[:, :3, 3], axis=1).mean()
            err1 = np.linalg.norm(res.world_from_cam[:, :3, 3] - true_arr[:, :3, 3], axis=1).mean()
            s0 = _scale_error(noisy[:, :3, 3], true_arr[:, :3, 3])
            s1 = _scale_error(res.world_from_cam[:, :3, 3], true_arr[:, :3, 3])
            mode = "monocular" if prior is None else f"metric prior {prior} m"
            print(f"global BA {n} keyframes ({mode}), {len(obs_kf)} observations: {dt:.1f} s (1 thread), "
                  f"rmse {res.initial_rmse_px:.2f} -> {res.final_rmse_px:.2f} px, position error "
                  f"{err0 * 100:.1f} -> {err1 * 100:.1f} cm, scale error {s0 * 100:.2f} -> {s1 * 100:.2f} %, "
                  f"accepted {res.accepted}")  # fmt: skip


def _scale_error(est: np.ndarray, ref: np.ndarray, window: int = 50) -> float:
    """Worst local scale error: max over windows of ``window`` consecutive keyframes of |s - 1|, s the scale
    of the least-squares similarity taking ``est`` onto ``ref`` (Umeyama)."""
    starts = range(0, len(est), window)
    return max(_umeyama_scale_error(est[i : i + window], ref[i : i + window]) for i in starts)


def _umeyama_scale_error(est: np.ndarray, ref: np.ndarray) -> float:
    a, b = est - est.mean(0), ref - ref.mean(0)
    u, d, vt = np.linalg.svd(b.T @ a / len(a))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt))
    return float(abs((d * sign).sum() / (a**2).sum(1).mean() - 1.0))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--ba", type=int, nargs="+", default=[500, 2000])
    ap.add_argument("--skip", nargs="*", default=[], choices=["query", "e2e", "ba"])
    args = ap.parse_args(argv)
    if "query" not in args.skip:
        bench_query(args.sizes)
    if "e2e" not in args.skip:
        bench_end_to_end(args.pairs)
    if "ba" not in args.skip:
        bench_ba(args.ba)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
