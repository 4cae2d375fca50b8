"""A content digest of a map: the same for two maps exactly when ``map_differences`` finds nothing.

A running server and a reloaded store are compared through it (``/maps/{id}`` reports it), so a test can
check that a restart gives back the map stack it had, bit for bit, without reading the server's memory.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np

from hivemap.maps.model import Map
from hivemap.maps.stack import MapStack


def _arr(h: Any, a: Any) -> None:
    if a is None:
        h.update(b"\x00none")
        return
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())


def map_digest(m: Map) -> str:
    """SHA-256 over the map's keyframes (poses, features, point references, parents), points
    (positions, descriptors, observations), covisibility, loop edges, fusion redirects, pending
    references, orphans, agents and merge history; bit-exact for arrays."""
    h = hashlib.sha256()
    h.update(json.dumps([m.id, sorted(m.agents)]).encode())
    for k in sorted(m.keyframes):
        kf = m.keyframes[k]
        head = [list(k), kf.camera.to_dict(), sorted(kf.point_agents.items()), kf.parent]
        h.update(json.dumps(head).encode())
        h.update(np.float64(kf.timestamp).tobytes())
        for name in ("world_from_cam", "keypoints", "octaves", "descriptors", "point_ids"):
            _arr(h, getattr(kf, name))
        for name in ("gnss_enu", "gnss_cov", "up_cam"):
            _arr(h, getattr(kf, name))
        if kf.u_right is not None:  # a mono keyframe's digest is what it was before stereo existed
            _arr(h, kf.u_right)
            h.update(np.float64(kf.stereo_baseline).tobytes())
        if kf.odom_sigma is not None:  # (absent from older maps' digests)
            _arr(h, kf.odom_sigma)
        if kf.track_sigma is not None:
            _arr(h, kf.track_sigma)
        if kf.vio_from_cam is not None:
            _arr(h, kf.vio_from_cam)
    for k in sorted(m.points):
        p = m.points[k]
        h.update(json.dumps([list(k), sorted((list(o), i) for o, i in p.observations.items())]).encode())
        _arr(h, p.xyz)
        _arr(h, p.descriptor)
    covis = sorted((list(a), sorted((list(b), w) for b, w in nb.items())) for a, nb in m._covis.items() if nb)
    h.update(json.dumps(covis).encode())
    h.update(json.dumps(sorted([list(a), list(b)] for a, b in m.loop_edges())).encode())
    h.update(json.dumps(sorted([list(a), list(b)] for a, b in m.point_redirects.items())).encode())
    pending = sorted((list(k), sorted((list(kk), i) for kk, i in v.items())) for k, v in m._pending.items())
    h.update(json.dumps(pending).encode())
    h.update(json.dumps(sorted(map(list, m._orphans))).encode())
    h.update(json.dumps(m.merge_history, sort_keys=True, default=str).encode())
    return h.hexdigest()


def stack_digest(stack: MapStack) -> dict[int, str]:
    """``map_digest`` of every map of the stack, by map id."""
    return {mid: map_digest(m) for mid, m in sorted(stack.maps.items())}
