"""Brute-force checks of a map's invariants and comparisons of two maps (tests, debugging, persistence)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from hivemap.maps.elements import KfKey, PointKey

if TYPE_CHECKING:
    from hivemap.maps.model import Map


def check_consistency(m: Map) -> list[str]:
    """Brute-force check of every invariant (slow: tests and debugging). Returns the problems found."""
    problems: list[str] = []
    expected: dict[KfKey, dict[KfKey, int]] = {k: {} for k in m.keyframes}
    for pk, mp in m.points.items():
        for kf_key, idx in mp.observations.items():
            kf = m.keyframes.get(kf_key)
            if kf is None:
                problems.append(f"point {pk} observed by missing keyframe {kf_key}")
            elif kf.point_key(idx) != pk:
                problems.append(f"point {pk}: keyframe {kf_key}[{idx}] references {kf.point_key(idx)}")
        obs = sorted(mp.observations)
        for i, a in enumerate(obs):
            for b in obs[i + 1 :]:
                expected[a][b] = expected[a].get(b, 0) + 1
                expected[b][a] = expected[b].get(a, 0) + 1
    for k, kf in m.keyframes.items():
        seen: set[PointKey] = set()
        for idx, pk in kf.referenced_points():
            if pk in seen:
                problems.append(f"keyframe {k} references {pk} twice")
            seen.add(pk)
            mp2 = m.points.get(pk)
            if mp2 is None:
                if m._pending.get(pk, {}).get(k) != idx:
                    problems.append(f"keyframe {k}[{idx}] references missing point {pk} not pending")
            elif mp2.observations.get(k) != idx:
                problems.append(f"keyframe {k}[{idx}] -> {pk} not in the point's observations")
        bad_parent = kf.parent not in m.keyframes or k not in m._children[kf.parent]
        if kf.parent is not None and bad_parent:
            problems.append(f"keyframe {k}: bad parent {kf.parent}")
    if m._covis != expected:
        problems.append("covisibility differs from a brute-force recount")
    for p, cs in m._children.items():
        for c in cs:
            if m.keyframes[c].parent != p:
                problems.append(f"children index: {c} listed under {p}")
    for k in m.keyframes:  # acyclic
        try:
            m._root_of(k)
        except RuntimeError:
            problems.append(f"cycle through {k}")
            break
    return problems


def _arr_eq(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def map_differences(a: Map, b: Map) -> list[str]:
    """Every difference between two maps (bit-exact arrays, graphs, history); empty if identical."""
    d: list[str] = []
    if a.id != b.id:
        d.append(f"id {a.id} != {b.id}")
    if a.agents != b.agents:
        d.append(f"agents {a.agents} != {b.agents}")
    if a.keyframes.keys() != b.keyframes.keys():
        d.append("keyframe keys differ")
    if a.points.keys() != b.points.keys():
        d.append("point keys differ")
    for k in a.keyframes.keys() & b.keyframes.keys():
        x, y = a.keyframes[k], b.keyframes[k]
        arrays: tuple[str, ...] = ("world_from_cam", "keypoints", "octaves", "descriptors", "point_ids")
        optional = ("gnss_enu", "gnss_cov", "up_cam", "u_right", "odom_sigma", "track_sigma", "vio_from_cam")
        for f in (*arrays, *optional):
            if not _arr_eq(getattr(x, f), getattr(y, f)):
                d.append(f"keyframe {k}: {f} differs")
        if np.float64(x.timestamp).tobytes() != np.float64(y.timestamp).tobytes():
            d.append(f"keyframe {k}: timestamp differs")
        for f in ("camera", "point_agents", "parent", "stereo_baseline"):
            if getattr(x, f) != getattr(y, f):
                d.append(f"keyframe {k}: {f} differs")
    for k in a.points.keys() & b.points.keys():
        x2, y2 = a.points[k], b.points[k]
        if not _arr_eq(x2.xyz, y2.xyz) or not _arr_eq(x2.descriptor, y2.descriptor):
            d.append(f"point {k}: xyz/descriptor differs")
        if x2.observations != y2.observations:
            d.append(f"point {k}: observations differ")
    if a._covis != b._covis:
        d.append("covisibility differs")
    if a.loop_edges() != b.loop_edges():
        d.append("loop edges differ")
    if a.point_redirects != b.point_redirects:
        d.append("point redirects differ")
    if a._pending != b._pending:
        d.append("pending references differ")
    if a._orphans != b._orphans:
        d.append("orphans differ")
    if a.merge_history != b.merge_history:
        d.append("merge history differs")
    return d
