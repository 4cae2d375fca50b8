"""Follow-the-leader (seeds 000, 004): a follower's reference keeps a set arc length behind its leader
along the leader's own path, so that it drives where the leader went (a constant offset in the map
frame, seed 000's formation, would cut corners through what the leader went around).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Reference:
    point: F64  # (3,) where the follower should be now
    tangent: F64  # (3,) unit direction of the leader's path there (zero on a path of one point)
    behind_m: float  # arc length from the point to the leader's latest position (< distance: path short)
    path: F64  # (K, 3) the leader's path from its start up to ``point``, resampled


def arc_lengths(path: F64) -> F64:
    """Cumulative arc length at each vertex of the polyline ``path`` (N, 3)."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    out: F64 = np.concatenate([[0.0], np.cumsum(seg)])
    return out


def point_at(path: F64, s: F64 | float) -> F64:
    """Points at arc lengths ``s`` (clamped to the path) along the polyline ``path`` (N, 3)."""
    cum = arc_lengths(path)
    s_arr = np.clip(np.atleast_1d(np.asarray(s, dtype=np.float64)), 0.0, cum[-1])
    out: F64 = np.column_stack([np.interp(s_arr, cum, path[:, k]) for k in range(path.shape[1])])
    return out


def reference(leader_path: F64, distance: float, spacing: float = 0.25) -> Reference:
    """The follower's reference ``distance`` metres of arc behind the end of ``leader_path`` (N, 3, oldest
    first; at its start while the path is shorter), with the path up to it every ``spacing`` metres."""
    p = np.asarray(leader_path, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError("empty leader path")
    keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 0.0])
    p = p[keep]  # repeated positions (a leader standing still) would make the arc length flat
    if len(p) == 1:
        return Reference(p[0].copy(), np.zeros(3), 0.0, p.copy())
    cum = arc_lengths(p)
    s = max(0.0, cum[-1] - distance)
    point = point_at(p, s)[0]
    k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(p) - 2))
    t = p[k + 1] - p[k]
    n = max(1, int(np.ceil(s / spacing))) if s > 0 else 0
    path = point_at(p, np.linspace(0.0, s, n + 1)) if n else p[:1].copy()
    return Reference(point, t / np.linalg.norm(t), float(cum[-1] - s), path)
