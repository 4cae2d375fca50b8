"""Map model, store and ORB benchmark: prints the figures (not a test).

Run: .venv/bin/python bench/maps.py [--big]   (--big: 3000 keyframes / 300k points for the model)
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import skimage.data

from hivemap.maps import Map, MapStack
from hivemap.maps.features import extract_orb, match_bf, match_by_projection
from hivemap.maps.store import MapStore
from hivemap.maps.testing import random_keyframes_and_points, random_map


def model(n_kf: int, n_pts: int) -> None:
    rng = np.random.default_rng(0)
    kfs, pts = random_keyframes_and_points(rng, "a", n_kf, n_pts, obs_per_keyframe=400, extra_keypoints=600)
    m = Map(0)
    for p in pts:
        m.add_point(p)
    t = time.perf_counter()
    for kf in kfs:
        m.add_keyframe(kf)
    dt = time.perf_counter() - t
    print(f"model: add_keyframe (1000 kps, 400 points) {dt / n_kf * 1e3:.2f} ms each at {n_kf} keyframes")
    t = time.perf_counter()
    e = m.essential_edges()
    print(f"model: essential_edges {len(e)} edges in {(time.perf_counter() - t) * 1e3:.1f} ms")
    keys = list(m.points)
    t = time.perf_counter()
    for i in range(0, 2000, 2):
        m.fuse_points(keys[i], keys[i + 1])
    print(f"model: fuse_points {(time.perf_counter() - t) / 1000 * 1e6:.1f} us each")
    gone = list(m.keyframes)[::50]
    t = time.perf_counter()
    for k in gone:
        m.remove_keyframe(k)
    print(f"model: remove_keyframe {(time.perf_counter() - t) / len(gone) * 1e3:.2f} ms each")


def store() -> None:
    rng = np.random.default_rng(1)
    stack = MapStack()
    stack.add_map(random_map(rng, 0, "ugv", 200, 20000, obs_per_keyframe=250, extra_keypoints=750))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "maps.sqlite"
        with MapStore(path) as s:
            t = time.perf_counter()
            s.save_stack(stack)
            t_save = time.perf_counter() - t
        with MapStore(path) as s:
            t = time.perf_counter()
            s.load_stack()
            t_load = time.perf_counter() - t
        size = path.stat().st_size / 1e6
        print(
            f"store: 200 kf (1000 kps) / 20k points: save {t_save:.2f} s, load {t_load:.2f} s, {size:.1f} MB"
        )
        kfs, pts = random_keyframes_and_points(
            rng, "b", 300, 30000, obs_per_keyframe=400, extra_keypoints=600
        )
        m = Map(1)
        for p in pts:
            m.add_point(p)
        with MapStore(Path(d) / "inc.sqlite") as s:
            times = []
            for kf in kfs:
                m.add_keyframe(kf)
                t = time.perf_counter()
                s.put_keyframe(1, kf)
                times.append(time.perf_counter() - t)
            t = time.perf_counter()
            s.put_points(1, pts[:1000])
            t_pts = time.perf_counter() - t
            t = time.perf_counter()
            s.update_poses(1, kfs[-10:], pts[-500:])
            t_upd = time.perf_counter() - t
            s.put_points(1, pts[1000:])
            for p in pts:  # an optimisation: every keyframe and point written, one commit
                p.xyz = p.xyz + 0.01
            t, c = time.perf_counter(), time.process_time()
            s.update_poses(1, kfs, pts)
            t_all, c_all = time.perf_counter() - t, time.process_time() - c
        first, last = np.median(times[:30]) * 1e3, np.median(times[-30:]) * 1e3
        print(f"store: put_keyframe (own commit, sync FULL) median {first:.2f} ms first / {last:.2f} ms last")
        print(f"store: put_points 1000 {t_pts * 1e3:.1f} ms; update_poses 10kf+500pts {t_upd * 1e3:.1f} ms")
        print(
            f"store: update_poses every keyframe and point ({len(kfs)} kf, {len(pts)} points) "
            f"{t_all * 1e3:.0f} ms ({c_all * 1e3:.0f} ms CPU)"
        )


def features() -> None:
    g = cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY)
    g = cv2.resize(g, (640, 480))
    extract_orb(g)
    t = time.perf_counter()
    for _ in range(10):
        k, o, d = extract_orb(g)
    print(f"orb: extract_orb 640x480 -> {len(k)} features in {(time.perf_counter() - t) / 10 * 1e3:.1f} ms")
    H = np.vstack([cv2.getRotationMatrix2D((320, 240), 12, 0.9), [0, 0, 1]])
    g2 = cv2.warpPerspective(g, H, (640, 480))
    k2, o2, d2 = extract_orb(g2)
    t = time.perf_counter()
    m = match_bf(d, d2)
    print(f"orb: match_bf 1000 x 1000 -> {len(m)} matches in {(time.perf_counter() - t) * 1e3:.1f} ms")
    uv = cv2.perspectiveTransform(k.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    t = time.perf_counter()
    got = match_by_projection(uv, d, k2, o2, d2, radius=4.0, max_distance=50)
    dt = (time.perf_counter() - t) * 1e3
    print(f"orb: match_by_projection 1000 pts x 1000 kps, r=4 -> {(got >= 0).sum()} matches in {dt:.1f} ms")


if __name__ == "__main__":
    big = "--big" in sys.argv
    model(3000 if big else 500, 300000 if big else 50000)
    store()
    features()
