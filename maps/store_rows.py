"""Map rows as the store writes them: arrays as raw bytes with their dtype and shape (lossless), a
keyframe's and a point's row, and a whole map's rows taken at one instant (:func:`map_rows`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.model import Keyframe, KfKey, Map, MapPoint


def pack_array(a: NDArray[Any]) -> bytes:
    """Array -> ``b"<dtype>|<d0,d1,..>\\n" + raw C-order bytes`` (lossless, any dtype without objects)."""
    a = np.asarray(a)
    if a.dtype.hasobject:
        raise TypeError("object arrays cannot be stored")
    header = f"{a.dtype.str}|{','.join(str(d) for d in a.shape)}\n".encode()
    return header + np.ascontiguousarray(a).tobytes()


def unpack_array(b: bytes) -> NDArray[Any]:
    """Inverse of ``pack_array``; returns a writable array."""
    nl = b.index(b"\n")
    dtype_s, shape_s = b[:nl].decode().rsplit("|", 1)
    shape = tuple(int(x) for x in shape_s.split(",")) if shape_s else ()
    return np.frombuffer(b, dtype=np.dtype(dtype_s), offset=nl + 1).reshape(shape).copy()


def _f64(x: float) -> bytes:
    return np.float64(x).tobytes()


def _kf_row(map_id: int, kf: Keyframe, seq: int) -> tuple[Any, ...]:
    parent = kf.parent
    return (
        int(map_id),
        kf.agent_id,
        kf.id,
        seq,
        _f64(kf.timestamp),
        pack_array(kf.world_from_cam),
        json.dumps(kf.camera.to_dict()),
        pack_array(kf.keypoints),
        pack_array(kf.octaves),
        pack_array(kf.descriptors),
        pack_array(kf.point_ids),
        json.dumps({str(i): a for i, a in sorted(kf.point_agents.items())}) if kf.point_agents else None,
        None if kf.gnss_enu is None else pack_array(kf.gnss_enu),
        None if kf.gnss_cov is None else pack_array(kf.gnss_cov),
        None if kf.up_cam is None else pack_array(kf.up_cam),
        None if kf.u_right is None else pack_array(kf.u_right),
        kf.stereo_baseline,
        None if kf.odom_sigma is None else pack_array(kf.odom_sigma),
        None if kf.track_sigma is None else pack_array(kf.track_sigma),
        None if kf.vio_from_cam is None else pack_array(kf.vio_from_cam),
        None if parent is None else parent[0],
        None if parent is None else parent[1],
    )


def _pt_row(map_id: int, p: MapPoint, seq: int) -> tuple[Any, ...]:
    return (
        int(map_id),
        p.agent_id,
        p.id,
        seq,
        np.ascontiguousarray(p.xyz, dtype="<f8").tobytes(),
        np.ascontiguousarray(p.descriptor, dtype=np.uint8).tobytes(),
    )


@dataclass(frozen=True)
class MapRows:
    """A map's rows for :meth:`MapStore.save_map`, taken at one instant (``map_rows``); point and
    keyframe rows carry a placeholder seq that the store fills in when it writes them."""

    map_id: int
    agents: list[str]
    orphans: list[KfKey]
    points: list[tuple[Any, ...]]
    keyframes: list[tuple[Any, ...]]
    loops: list[tuple[Any, ...]]
    redirects: list[tuple[Any, ...]]
    merges: list[tuple[int, str]]


def map_rows(m: Map) -> MapRows:
    """Serialise map ``m`` on the calling thread (the one that changes it), so a writer thread can store
    it while the map goes on changing. Forgets the map's pending tree changes: all parents are in it."""
    mid = int(m.id)
    rows = MapRows(
        mid,
        sorted(m.agents),
        sorted(m.orphans),
        [_pt_row(mid, p, 0) for p in m.points.values()],
        [_kf_row(mid, kf, 0) for kf in m.keyframes.values()],
        [(mid, a[0], a[1], b[0], b[1]) for a, b in m.loop_edges()],
        [(mid, f[0], f[1], t[0], t[1]) for f, t in m.point_redirects.items()],
        [(mid, json.dumps(r)) for r in m.merge_history],
    )
    m.drain_tree_changes()
    return rows
