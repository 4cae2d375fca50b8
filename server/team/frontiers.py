"""Frontier goals from a map's sparse points (seed 001, 4.1): down-sample, project onto the ground plane,
take the boundary between the explored region and the unknown, cluster it, and say which agent kinds can
reach each cluster.

The explored region is a grid on the ground plane (cell = the voxel): cells holding a down-sampled point,
plus the cells the agents' paths cross and those their lines of sight cross (from a keyframe's camera to
the points it observed, up to ``view_range_m``: the space between was seen free, as an occupancy map
carves it), with small gaps closed. Its boundary cells (a 4-neighbour unknown) hold the frontier points.
Without the lines of sight a sparse map's holes (textureless ground, a facade's points seen from afar
standing alone) were frontiers inside ground the team had seen, and the auction sent the agents back and
forth among them. Heights are along the map's z axis (gravity-aligned map
frames, see :mod:`.options`); a fitted ground plane makes them heights above ground, which decide
reachability: a UGV reaches frontiers with points near the ground, a UAV those with points within its
altitude band.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from hivemap.server.team.options import FrontierOptions

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
KINDS = ("ugv", "uav")


@dataclass(frozen=True)
class Frontier:
    """One frontier cluster. ``goal`` (3,): the frontier point nearest the cluster's centroid (so on the
    boundary), its z the median of the cluster's points; ``goals`` per kind that can reach it: the same
    x, y at the kind's height (UGV: on the ground plane; UAV: the median height of its in-band points)."""

    id: int
    goal: F64
    points: int  # frontier points in the cluster
    reachable: tuple[str, ...]
    goals: dict[str, F64] = field(default_factory=dict)

    def goal_for(self, kind: str) -> F64:
        """Where an agent of ``kind`` goes for this frontier."""
        return self.goals.get(kind, self.goal)


@dataclass(frozen=True)
class FrontierResult:
    frontiers: list[Frontier]
    ground: tuple[float, float, float]  # plane z = a x + b y + c
    known_cells: int  # explored cells after closing
    frontier_points: F64  # (K, 3) every frontier point (down-sampled)


def even_subsample(n: int, max_points: int) -> slice:
    """The slice taking an even subsample of at most ``max_points`` of ``n`` items (all when they fit)."""
    return slice(None, None, max(1, -(-n // max_points)))


def voxel_downsample(xyz: F64, voxel: float) -> F64:
    """(N, 3) -> (M, 3): the centroid of the points in each occupied cube of side ``voxel``."""
    if len(xyz) == 0:
        return np.zeros((0, 3))
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, xyz)
    out: F64 = sums / counts[:, None]
    return out


def fit_ground(xyz: F64, percentile: float, band: float) -> tuple[float, float, float]:
    """The plane ``z = a x + b y + c`` through the low points: those within ``band`` above the
    ``percentile``-th height, refitted once on the ones within ``band`` of the first fit (a flat plane at
    that height when they are too few or collinear)."""
    z0 = float(np.percentile(xyz[:, 2], percentile))
    flat = (0.0, 0.0, z0)
    sel = xyz[xyz[:, 2] <= z0 + band]
    for _ in range(2):
        if len(sel) < 3:
            return flat
        A = np.column_stack([sel[:, 0], sel[:, 1], np.ones(len(sel))])
        if np.linalg.matrix_rank(A) < 3:
            return flat
        coef, *_ = np.linalg.lstsq(A, sel[:, 2], rcond=None)
        a, b, c = (float(v) for v in coef)
        near = np.abs(xyz[:, 2] - (a * xyz[:, 0] + b * xyz[:, 1] + c)) <= band
        sel = xyz[near]
    return a, b, c


def _height(xyz: F64, plane: tuple[float, float, float]) -> F64:
    a, b, c = plane
    out: F64 = xyz[:, 2] - (a * xyz[:, 0] + b * xyz[:, 1] + c)
    return out


def _segment_points(a: F64, b: F64, step: float) -> F64:
    """Points every ``step`` (at most) along each segment ``a[i]``-``b[i]`` (S, 2), ends included."""
    if len(a) == 0:
        return np.zeros((0, 2))
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(np.int64))
    seg = np.repeat(np.arange(len(a)), n + 1)
    t = _fractions(n)
    out: F64 = a[seg] + t[:, None] * (b[seg] - a[seg])
    return out


def _fractions(n: NDArray[np.int64]) -> F64:
    """0, 1/n_i, ..., 1 for each i, concatenated (vectorised ``linspace``)."""
    start = np.repeat(np.cumsum(n + 1) - (n + 1), n + 1)
    k = np.arange(int((n + 1).sum())) - start
    out: F64 = k / np.repeat(n, n + 1)
    return out


def _path_cells(paths: Sequence[F64], voxel: float) -> F64:
    """Points every half cell along each path (K_i, 3), so that the cells they cross are all hit."""
    out = []
    for p in paths:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        out.append(p[:1, :2] if len(p) == 1 else _segment_points(p[:-1, :2], p[1:, :2], 0.5 * voxel))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _sight_cells(rays: F64, voxel: float, max_len: float) -> F64:
    """Points every half cell along each line of sight's ground projection (camera -> seen point, (R, 2, 3)),
    cut at ``max_len`` from the camera (a far point's line crosses ground seen too coarsely to count)."""
    r = np.asarray(rays, dtype=np.float64).reshape(-1, 2, 3)
    a, b = r[:, 0, :2], r[:, 1, :2]
    d = b - a
    n = np.linalg.norm(d, axis=1)
    scale = np.minimum(1.0, max_len / np.maximum(n, 1e-9))
    return _segment_points(a, a + d * scale[:, None], 0.5 * voxel)


def extract(
    xyz: F64, options: FrontierOptions, paths: Sequence[F64] = (), rays: F64 | None = None
) -> FrontierResult:
    """Frontier clusters of the points ``xyz`` (N, 3) in a map's frame; ``paths``: the agents' paths
    (camera centres, (K, 3) each) and ``rays``: lines of sight (R, 2, 3) from a camera centre to a point it
    observed, whose cells count as explored free space (module docstring)."""
    o = options
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    xyz = xyz[even_subsample(len(xyz), o.max_points)]
    if len(xyz) == 0:
        return FrontierResult([], (0.0, 0.0, 0.0), 0, np.zeros((0, 3)))
    vox = voxel_downsample(xyz, o.voxel_m)
    plane = fit_ground(vox, o.ground_percentile, o.ground_band_m)
    h = _height(vox, plane)
    free = _path_cells(paths, o.voxel_m)
    if rays is not None and len(rays) and o.view_range_m > 0:
        free = np.concatenate([free, _sight_cells(rays, o.voxel_m, o.view_range_m)])

    # the grid, padded so that closing and the boundary never touch its edge
    pad = o.close_cells + 2
    all_xy = np.concatenate([vox[:, :2], free]) if len(free) else vox[:, :2]
    origin = np.floor(all_xy.min(axis=0) / o.voxel_m).astype(np.int64) - pad
    cell = np.floor(vox[:, :2] / o.voxel_m).astype(np.int64) - origin
    top = np.floor(all_xy.max(axis=0) / o.voxel_m).astype(np.int64) - origin + pad + 1
    shape = (int(top[0]), int(top[1]))
    known = np.zeros(shape, dtype=bool)
    known[cell[:, 0], cell[:, 1]] = True
    if len(free):
        fc = np.floor(free / o.voxel_m).astype(np.int64) - origin
        known[fc[:, 0], fc[:, 1]] = True
    if o.close_cells > 0:
        known = ndimage.binary_closing(known, structure=np.ones((3, 3), bool), iterations=o.close_cells)
    four = ndimage.generate_binary_structure(2, 1)
    boundary = known & ~ndimage.binary_erosion(known, structure=four, border_value=0)

    on_boundary = boundary[cell[:, 0], cell[:, 1]]
    fpts, fcell, fh = vox[on_boundary], cell[on_boundary], h[on_boundary]
    labels, _ = ndimage.label(boundary, structure=np.ones((3, 3), bool))
    comp = labels[fcell[:, 0], fcell[:, 1]]
    tile = np.floor(fpts[:, :2] / o.cluster_m).astype(np.int64)
    keys = np.column_stack([comp, tile])
    frontiers: list[Frontier] = []
    if len(keys):
        uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        for g in range(len(uniq)):
            idx = np.flatnonzero(inverse == g)
            if len(idx) < o.min_cluster_points:
                continue
            frontiers.append(_cluster(len(frontiers), fpts[idx], fh[idx], plane, o))
    logger.debug("%d frontier clusters from %d voxels", len(frontiers), len(vox))
    return FrontierResult(frontiers, plane, int(known.sum()), fpts)


def _cluster(cid: int, pts: F64, h: F64, plane: tuple[float, float, float], o: FrontierOptions) -> Frontier:
    centroid = pts[:, :2].mean(axis=0)
    nearest = pts[int(np.argmin(np.linalg.norm(pts[:, :2] - centroid, axis=1)))]
    goal = np.array([nearest[0], nearest[1], float(np.median(pts[:, 2]))])
    a, b, c = plane
    ground_z = a * goal[0] + b * goal[1] + c
    goals: dict[str, F64] = {}
    if (h <= o.ugv_max_height_m).any():
        goals["ugv"] = np.array([goal[0], goal[1], ground_z])
    band = (h >= o.uav_min_alt_m) & (h <= o.uav_max_alt_m)
    if band.any():
        goals["uav"] = np.array([goal[0], goal[1], ground_z + float(np.median(h[band]))])
    return Frontier(cid, goal, len(pts), tuple(k for k in KINDS if k in goals), goals)
