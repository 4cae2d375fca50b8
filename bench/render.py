"""Renderer benchmark: frames/s for gray + depth at 640x480 in one process (target >= 60 fps GL).

Run: .venv/bin/python bench/render.py
"""

from __future__ import annotations

import time

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.sim.render import GLRenderer, NumpyRenderer
from hivemap.sim.world import generate_world


def main() -> None:
    t0 = time.perf_counter()
    world = generate_world(1)
    print(f"world generation: {time.perf_counter() - t0:.1f} s ({world.layers.shape[0]} texture layers)")
    cam = PinholeCamera(640, 480, 430.0, 430.0, 319.5, 239.5, (-0.05, 0.01, 0.0002, -0.0001))
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ so3_exp([-np.pi / 4, 0, 0])
    poses = [se3(so3_exp([0, 0, 0.01 * k]) @ R, [-45 + 0.1 * k, -20, 10]) for k in range(200)]
    for name, cls, n in (("gl (EGL, llvmpipe)", GLRenderer, 200), ("numpy (fallback)", NumpyRenderer, 3)):
        r = cls(world, cam)
        r.render(poses[0])
        t = time.perf_counter()
        for T in poses[:n]:
            r.render(T)
        dt = (time.perf_counter() - t) / n
        print(f"{name:<20} {1 / dt:8.1f} frames/s  ({dt * 1e3:.1f} ms per gray+depth frame, 640x480)")
        r.close()
    print("target: gl >= 60 frames/s")


if __name__ == "__main__":
    main()
