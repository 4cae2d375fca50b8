"""Place-recognition benchmark: vocabulary transform time, keyframe-database query time vs size
(1k / 10k / 50k keyframes), and geometric verification time on a synthetic scene.

Run: .venv/bin/python bench/placerec.py [--sizes 1000 10000 50000]

Database keyframes are real BoW vectors (ORB on warped scikit-image photos) with 20 % of their words
dropped and their weights jittered, so the word distribution (and the posting-list lengths of frequent
words) is that of real images rather than uniform.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import skimage.data

from hivemap.maps.kfdb import KeyframeDatabase
from hivemap.maps.vocabulary import BowVector, default_vocabulary

PHOTOS = (
    "astronaut", "brick", "camera", "chelsea", "coffee", "coins", "grass", "gravel", "moon",
    "retina", "rocket", "text", "page", "clock", "hubble_deep_field", "immunohistochemistry",
)  # fmt: skip


def _gray(name: str) -> np.ndarray:
    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return img.astype(np.uint8)


def _descriptor_sets(n_warps: int, rng: np.random.Generator) -> list[np.ndarray]:
    orb = cv2.ORB_create(nfeatures=1000)  # type: ignore[attr-defined]
    out = []
    for name in PHOTOS:
        g = _gray(name)
        h, w = g.shape
        src = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
        for _ in range(n_warps):
            dst = (src + rng.uniform(-0.1, 0.1, (4, 2)) * [w, h]).astype(np.float32)
            img = cv2.warpPerspective(g, cv2.getPerspectiveTransform(src, dst), (w, h))
            _, d = orb.detectAndCompute(img, None)
            if d is not None and len(d) >= 500:
                out.append(d)
    return out


def _stats(ts: list[float]) -> str:
    a = np.asarray(ts) * 1e3
    return f"median {np.median(a):.2f} ms, p95 {np.percentile(a, 95):.2f} ms"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    ap.add_argument("--queries", type=int, default=30)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    vocab = default_vocabulary()
    print(f"vocabulary: {vocab}")

    descs = _descriptor_sets(4, rng)
    d1000 = [d[:1000] for d in descs if len(d) >= 1000]
    for d in d1000[:3]:
        vocab.transform(d)
    ts = []
    for d in d1000 * 3:
        t = time.perf_counter()
        vocab.transform(d)
        ts.append(time.perf_counter() - t)
    print(f"transform 1000 descriptors: {_stats(ts)} ({len(ts)} runs)")

    pool = [vocab.transform(d)[0] for d in descs]
    print(f"BoW words per keyframe: median {np.median([len(b) for b in pool]):.0f}")

    def jittered(b: BowVector) -> BowVector:
        keep = rng.random(len(b)) < 0.8
        w = b.weights[keep] * rng.uniform(0.7, 1.3, int(keep.sum()))
        return BowVector(b.words[keep], w / w.sum())

    db = KeyframeDatabase()
    n = 0
    for size in sorted(args.sizes):
        t = time.perf_counter()
        while n < size:
            db.add((f"agent{n % 4}", n), n % 4, jittered(pool[int(rng.integers(len(pool)))]))
            n += 1
        add_ms = (time.perf_counter() - t) / max(size, 1) * 1e3
        qs = [jittered(pool[int(rng.integers(len(pool)))]) for _ in range(args.queries)]
        db.query(qs[0], 16)
        tq = []
        for i, q in enumerate(qs):
            t = time.perf_counter()
            db.query(q, 16, exclude_map=i % 4)
            tq.append(time.perf_counter() - t)
        tf = []
        for i, q in enumerate(qs[:10]):
            t = time.perf_counter()
            db.feasibility(q, i % 4)
            tf.append(time.perf_counter() - t)
        print(
            f"db {size:6d} keyframes: query (16 best, other maps) {_stats(tq)}; "
            f"feasibility check {_stats(tf)}; add {add_ms:.2f} ms/kf"
        )

    # geometric verification on the synthetic two-agent scene of the tests
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "server"))
    import test_placerec as tp  # the synthetic scene generator of tests/server/test_placerec.py

    srng = np.random.default_rng(42)
    pts, desc = tp._world(srng, 2500, (-20, 30))
    a = tp._make_map(srng, 0, "uavA", pts, desc, np.linspace(-6, 8, 10), tp.Sim3.identity())
    b = tp._make_map(srng, 1, "uavB", pts, desc, np.linspace(-2, 12, 10), tp.S_TRUE)
    maps = {0: a, 1: b}
    pr = tp._recognizer(maps)
    tv, tdet = [], []
    for k in range(10):
        r = pr.detect(maps, 0, ("uavA", k), loop=False)
        tdet.append(r.time_ms / 1e3)
        tv += [c.time_ms / 1e3 for c in r.candidates if c.n_matches > 0]
    n_kp = np.median([len(kf.keypoints) for kf in a.keyframes.values()])
    print(f"detect() per query keyframe ({n_kp:.0f} keypoints, 8 candidates): {_stats(tdet)}")
    print(f"one geometric verification (BoW match x6, RANSAC, 2x guided search + refine): {_stats(tv)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
