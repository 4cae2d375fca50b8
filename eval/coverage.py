"""Coverage of a site by a team's cameras (issue 26, the ``explore`` mode): which cells of a ground grid
any agent's camera has seen, over time, from ground-truth poses.

The reachable area of a kind is a set of ground cells: drivable ground for a UGV (within half a road width
of a road's centre line), the site's ground for a UAV (every cell of the site but building footprints); a
team's is the union over its kinds. A cell is seen at a frame when its centre (on the ground, z = 0) lies in
front of the camera, within ``max_range_m``, inside the image, and, when a depth image of the frame is
given, not hidden behind something nearer (the rendered depth at its pixel is no shorter than its own,
within ``depth_tol_m``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
B = NDArray[np.bool_]


@dataclass(frozen=True)
class CoverageOptions:
    cell_m: float = 1.0
    max_range_m: float = 30.0  # ground farther from the camera than this is not counted as seen
    sample_s: float = 0.5  # camera poses are taken this often
    depth_tol_m: float = 0.5  # occlusion test: rendered depth may be this much shorter than the cell's
    target: float = 0.8  # the coverage whose time is reported


@dataclass(frozen=True)
class Grid:
    """Cell centres (N, 2) of the site and which cells each kind can reach."""

    centres: F64
    reachable: dict[str, B]

    def area(self, kinds: Sequence[str]) -> B:
        """The team's reachable cells: the union over its kinds."""
        out = np.zeros(len(self.centres), bool)
        for k in set(kinds):
            out |= self.reachable[k]
        return out


def site_grid(world: object, cell_m: float = 1.0) -> Grid:
    """The site's ground grid (the world's tiled square) and the cells a UGV and a UAV can reach."""
    from hivemap.sim.roads import inside_box_footprint
    from hivemap.sim.world import road_distance

    w: object = world
    lo = np.asarray(w.tiles_origin, dtype=np.float64)  # type: ignore[attr-defined]
    size = float(w.tiles_n * w.tile_m)  # type: ignore[attr-defined]
    n = int(round(size / cell_m))
    c = (
        lo[None, :]
        + (np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="xy"), -1).reshape(-1, 2) + 0.5) * cell_m
    )
    dist, _ = road_distance(c, list(w.roads))  # type: ignore[attr-defined]
    ground = np.ones(len(c), bool)
    for b in w.buildings:  # type: ignore[attr-defined]
        ground &= ~inside_box_footprint(b, c)
    return Grid(c, {"ugv": (dist <= w.road_width / 2) & ground, "uav": ground})  # type: ignore[attr-defined]


def seen_cells(
    centres: F64,
    world_from_cam: F64,
    camera: object,
    max_range_m: float,
    depth: NDArray[np.floating] | None = None,
    depth_tol_m: float = 0.5,
) -> B:
    """Cells (N, 2) on the ground that the pinhole ``camera`` (fx, fy, cx, cy, width, height; distortion
    ignored) at ``world_from_cam`` sees; with ``depth`` (H, W, metres along the optical axis), only those
    not hidden."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    pts = np.concatenate([centres, np.zeros((len(centres), 1))], axis=1)
    p = (pts - T[:3, 3]) @ T[:3, :3]  # camera frame
    z = p[:, 2]
    ok = (z > 1e-3) & (np.linalg.norm(pts - T[:3, 3], axis=1) <= max_range_m)
    cam: object = camera
    u = np.full(len(z), -1.0)
    v = np.full(len(z), -1.0)
    u[ok] = cam.fx * p[ok, 0] / z[ok] + cam.cx  # type: ignore[attr-defined]
    v[ok] = cam.fy * p[ok, 1] / z[ok] + cam.cy  # type: ignore[attr-defined]
    W, H = int(cam.width), int(cam.height)  # type: ignore[attr-defined]
    ok &= (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    if depth is not None and ok.any():
        iu, iv = np.rint(u[ok]).astype(int), np.rint(v[ok]).astype(int)
        d = np.asarray(depth, dtype=np.float64)[iv, iu]
        visible = ~(d < z[ok] - depth_tol_m)  # nothing nearer at that pixel (sky reads as inf)
        idx = np.flatnonzero(ok)
        ok[idx[~visible]] = False
    return ok


def coverage_curve(
    grid: Grid,
    kinds: Sequence[str],
    poses: Mapping[str, tuple[F64, F64]],
    camera: object,
    options: CoverageOptions,
    depth_of: Callable[[str, F64], NDArray[np.floating] | None] | None = None,
) -> tuple[F64, F64]:
    """(times (K,), fraction (K,)) of the team's reachable area seen by time t, sampled every
    ``options.sample_s`` from the earliest pose; ``poses``: agent -> (times (N,), world_from_cam (N, 4, 4))
    (times relative to the mission start); ``depth_of(agent, world_from_cam)``: a depth image or None."""
    area = grid.area(kinds)
    total = int(area.sum())
    t_end = max(float(t[-1]) for t, _ in poses.values() if len(t))
    times = np.arange(0.0, t_end + 1e-9, options.sample_s)
    seen = np.zeros(len(grid.centres), bool)
    cand = area.copy()
    frac = np.zeros(len(times))
    for k, tk in enumerate(times):
        for aid, (t, T) in poses.items():
            if not len(t) or tk < t[0] - 1e-9 or tk > t[-1] + 1e-9:
                continue
            i = int(np.argmin(np.abs(t - tk)))
            todo = cand & ~seen
            if not todo.any():
                break
            idx = np.flatnonzero(todo)
            d = depth_of(aid, T[i]) if depth_of is not None else None
            hit = seen_cells(grid.centres[idx], T[i], camera, options.max_range_m, d, options.depth_tol_m)
            seen[idx[hit]] = True
        frac[k] = float((seen & area).sum()) / total if total else 0.0
    return times, frac


def time_to(times: F64, frac: F64, target: float) -> float | None:
    """The first time the coverage reaches ``target`` (None: never)."""
    hit = np.flatnonzero(np.asarray(frac) >= target - 1e-12)
    return float(times[hit[0]]) if len(hit) else None
