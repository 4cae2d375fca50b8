"""Renderer benchmark: frames/s for gray + depth at 640x480 in one process (target >= 60 fps GL).

Run: .venv/bin/python bench/render.py [--samples docs/img]   (--samples also writes the four README frames)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.sim.conditions import apply_conditions
from hivemap.sim.render import GLRenderer, NumpyRenderer
from hivemap.sim.world import World, generate_world

CAM = PinholeCamera(640, 480, 430.0, 430.0, 319.5, 239.5, (-0.05, 0.01, 0.0002, -0.0001))
R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looks along +x, level


def pose(x: float, y: float, z: float, yaw_deg: float, pitch_down_deg: float) -> np.ndarray:
    R = so3_exp([0, 0, np.radians(yaw_deg)]) @ R_LEVEL @ so3_exp([-np.radians(pitch_down_deg), 0, 0])
    return se3(R, [x, y, z])


def sample_poses(world: World) -> dict[str, np.ndarray]:
    """UAV 45 deg down at 10 m over a crossing, UGV on a road at 1 m, fog along a road, somber UAV."""
    xs = [float(r[0, 0]) for r in world.roads[:4]]
    ys = [float(r[0, 1]) for r in world.roads[4:]]
    return {
        "uav": pose(xs[1] - 2, ys[0] + 3, 12.0, 60, 45),
        "ugv": pose(xs[1] + 1.8, ys[0] + 6, 1.0, 90, 0),
        "fog": pose(xs[2] - 1.8, ys[0] + 2, 1.0, 93, 0),
        "somber": pose(xs[2], ys[2] - 10, 8.0, 100, 45),
    }


def write_samples(world: World, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    r = GLRenderer(world, CAM)
    conditions = {"uav": ("bright", "clear"), "ugv": ("bright", "clear"), "fog": ("bright", "fog")}
    conditions["somber"] = ("somber", "clear")
    for name, T in sample_poses(world).items():
        gray, depth = r.render(T)
        img = apply_conditions(gray, depth, *conditions[name], np.random.default_rng(0))
        cv2.imwrite(str(out / f"sample_{name}.png"), img)
        print(f"wrote {out / f'sample_{name}.png'}")
    r.close()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=Path, help="also write sample_{uav,ugv,fog,somber}.png here")
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    t0 = time.perf_counter()
    world = generate_world(1)
    print(f"world generation: {time.perf_counter() - t0:.1f} s ({world.layers.shape[0]} texture layers)")
    if args.samples:
        write_samples(world, args.samples)
    # A UAV-like sweep (45 deg down, 10 m) and a UGV-like drive (forward, 1 m), 640x480 with distortion.
    x0, y0 = float(world.roads[0][0, 0]), float(world.roads[5][0, 1])
    n = args.frames
    uav = [pose(x0 + 0.1 * k, y0 - 20, 10, 10 + 0.5 * k, 45) for k in range(n // 2)]
    ugv = [pose(x0 + 1.5, y0 - 40 + 0.075 * k, 1.0, 90, 0) for k in range(n - n // 2)]
    for name, cls, poses in (
        ("gl (EGL, llvmpipe)", GLRenderer, uav + ugv),
        ("numpy (fallback)", NumpyRenderer, [uav[0], ugv[0]]),
    ):
        r = cls(world, CAM)
        r.render(poses[0])
        t = time.perf_counter()
        for T in poses:
            r.render(T)
        dt = (time.perf_counter() - t) / len(poses)
        print(f"{name:<20} {1 / dt:8.1f} frames/s  ({dt * 1e3:.1f} ms per gray+depth frame, 640x480)")
        r.close()
    print("target: gl >= 60 frames/s")


if __name__ == "__main__":
    main()
