"""Matching map points to a frame's keypoints by projection (ORB-SLAM's SearchByProjection): the
tracker's search around a predicted pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.mapdata import Frame, PointStore, hamming
from hivemap.client.frontend.optim import Intrinsics, project
from hivemap.client.frontend.options import FrontendOptions
from hivemap.maps.camera import PinholeCamera

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def match_by_projection(
    pts: PointStore,
    frame: Frame,
    k: Intrinsics,
    cam: PinholeCamera,
    o: FrontendOptions,
    T_cw: F64,
    pids: I64,
    radius: float,
    taken: NDArray[np.bool_],
) -> tuple[I64, NDArray[np.bool_]]:
    """Project points ``pids`` into ``frame`` at ``T_cw``: -> (kp index per point or -1, visible mask).
    A keypoint within ``radius`` (times its octave's scale) with the best descriptor distance, under the
    ratio test against the second best, is taken; one point per keypoint."""
    m = len(pids)
    res = -np.ones(m, np.int64)
    if m == 0 or frame.n == 0:
        return res, np.zeros(m, bool)
    X = pts.xyz[pids]
    pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    uvr = project(k, pc)
    vis = (pc[:, 2] > 0.1) & (uvr[:, 0] >= -5) & (uvr[:, 1] >= -5)
    vis &= (uvr[:, 0] <= cam.width + 5) & (uvr[:, 1] <= cam.height + 5)
    idx_vis = np.flatnonzero(vis)
    if len(idx_vis) == 0:
        return res, vis
    kmax = 8
    max_r = radius * o.scale_factor ** (o.n_levels - 1)
    dist, nn = frame.tree.query(uvr[idx_vis, :2], k=kmax, distance_upper_bound=max_r)
    valid = nn < frame.n
    nn_c = np.where(valid, nn, 0)
    kscale = o.scale_factor ** frame.octaves[nn_c].astype(np.float64)
    valid &= dist <= radius * kscale
    valid &= ~taken[nn_c]
    hd = hamming(pts.desc[pids[idx_vis]][:, None, :], frame.desc[nn_c])
    hd = np.where(valid, hd, 999)
    order = np.argsort(hd, axis=1)
    best = np.take_along_axis(hd, order[:, :1], 1)[:, 0]
    second = np.take_along_axis(hd, order[:, 1:2], 1)[:, 0]
    ok = (best <= o.max_descriptor_distance) & ((second >= 999) | (best < o.ratio * second))
    kp = np.take_along_axis(nn_c, order[:, :1], 1)[:, 0]
    sel = np.flatnonzero(ok)
    if len(sel) == 0:
        return res, vis
    # one point per keypoint: keep the best descriptor distance
    srt = sel[np.argsort(best[sel], kind="stable")]
    _, first = np.unique(kp[srt], return_index=True)
    keep = srt[first]
    res[idx_vis[keep]] = kp[keep]
    return res, vis
