"""The back-end's per-optimisation steps on a real map: a finished run's server store, timed step by step.

Loads one map of a server's store (``<run>/server/data/hivemap.sqlite``, the kept loop and merge edges from
its evidence book) and prints the CPU time (best of ``--repeat``) of what every optimisation does besides
the solve: building the pose graph problem (on the event loop), the latest keyframes' covariances with
their pairs' difference covariances (which every correction waits for), and with ``--all`` every
keyframe's covariance (the rate-limited full solve).

    .venv/bin/python bench/map_steps.py runs/x/work/factory03-s2/denied/server/data/hivemap.sqlite
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any


def _best(label: str, fn: Callable[[], Any], repeat: int) -> Any:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    print(f"  {label:48s} {best * 1e3:9.1f} ms CPU", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("store", nargs="?", help="a server's hivemap.sqlite")
    ap.add_argument("--map", type=int, default=None, help="map id (default: the one with most keyframes)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--all", action="store_true", help="also every keyframe's covariance")
    a = ap.parse_args()
    if a.store is None:  # `make bench` runs every bench bare
        print("bench/map_steps.py: on request only (a server store; see --help)")
        return
    from hivemap.maps.store import MapStore
    from hivemap.server.backend import evidence_store, optimise, uncertainty
    from hivemap.server.backend.options import BackendOptions

    store = MapStore(a.store, synchronous="NORMAL")
    ids = store.map_ids()
    if not ids:
        sys.exit(f"{a.store}: no maps")
    t0 = time.perf_counter()
    maps = {i: store.load_map(i) for i in ([a.map] if a.map is not None else ids)}
    mid = a.map if a.map is not None else max(maps, key=lambda i: len(maps[i].keyframes))
    m = maps[mid]
    book = evidence_store.from_json(store.get_meta(evidence_store.META_KEY))
    store.close()
    o = BackendOptions().optimise
    kept = [ev.edge for ev in book.kept_edges(mid, m.keyframes) if not ev.rejected]
    print(f"map {mid}: {len(m.keyframes)} keyframes, {len(m.points)} points, {len(kept)} kept loop/merge "
          f"edges (loaded in {time.perf_counter() - t0:.1f} s)")  # fmt: skip
    snap = optimise.snapshot(m, 0)
    fixed = optimise.anchor(m, snap.keys, lambda f: "ugv" if f.startswith("ugv") else "uav", 1)
    _best("essential edges", lambda: m.essential_edges(), a.repeat)

    def build() -> Any:
        return optimise.pose_graph_problem(m, snap, kept, None, fixed, o, o.gnc)

    problem = _best("pose graph problem", build, a.repeat)
    print(f"  ({len(problem.graph_edges)} odometry or essential edges)")
    index = {k: i for i, k in enumerate(snap.keys)}
    two = uncertainty.latest_two(m)
    wanted = sorted(index[k] for k, _ in two.values())
    pairs = [(index[k], index[p]) for k, p in two.values() if p is not None]

    def covariances(indices: list[int] | None) -> Any:
        return uncertainty.compute(problem, snap.poses, o, indices, pairs)

    _best("latest keyframes' covariances + pairs", lambda: covariances(wanted), a.repeat)
    if a.all:
        _best("every keyframe's covariance", lambda: covariances(None), 1)


if __name__ == "__main__":
    main()
