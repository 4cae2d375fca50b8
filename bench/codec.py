"""Protocol codec benchmark: encode/decode time and size of a 1000-feature keyframe.

Targets (issue 2): under 50 µs each way and under 50 KB.
Run: .venv/bin/python bench/codec.py
"""

from __future__ import annotations

import time

import numpy as np

from hivemap.protocol import Keyframe, MapPoints, decode, encode


def _median_us(fn, repeat: int = 2000) -> float:  # type: ignore[no-untyped-def]
    for _ in range(100):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def main() -> None:
    rng = np.random.default_rng(0)
    n = 1000
    kf = Keyframe(
        kf_id=42,
        timestamp=12.5,
        world_from_cam=np.eye(4),
        keypoints=rng.uniform(0, 640, (n, 2)).astype(np.float32),
        octaves=rng.integers(0, 8, n).astype(np.uint8),
        descriptors=rng.integers(0, 256, (n, 32)).astype(np.uint8),
        point_ids=rng.integers(-1, 10**6, n).astype(np.int64),
        gnss_enu=np.zeros(3),
        gnss_cov=np.eye(3) * 0.01,
    )
    pts = MapPoints(
        np.arange(n, dtype=np.int64), rng.normal(size=(n, 3)), rng.integers(0, 256, (n, 32)).astype(np.uint8)
    )
    print(f"{'message':<28}{'bytes':>9}{'encode µs':>12}{'decode µs':>12}")
    for name, msg in (("keyframe (1000 features)", kf), ("map_points (1000 points)", pts)):
        frame = encode(msg, 1)
        enc = _median_us(lambda m=msg: encode(m, 1))
        dec = _median_us(lambda f=frame: decode(f))
        print(f"{name:<28}{len(frame):>9}{enc:>12.1f}{dec:>12.1f}")
    print("targets: keyframe < 50 µs each way, < 50 KB")


if __name__ == "__main__":
    main()
