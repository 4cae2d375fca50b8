"""Reading one map back from a map store's rows (:class:`hivemap.maps.store.MapStore` writes them)."""

from __future__ import annotations

import json
import logging
import sqlite3
import time

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.model import Keyframe, KfKey, Map, MapPoint
from hivemap.maps.store_rows import unpack_array
from hivemap.maps.store_schema import _KF_COLS
from hivemap.maps.store_xyz import position, read_positions

logger = logging.getLogger(__name__)


def read_map(conn: sqlite3.Connection, map_id: int) -> Map:
    """Rebuild one map from its rows (points, then keyframes in insertion order, then graphs)."""
    mid = int(map_id)
    m = Map(mid)
    c = conn
    for f_a, f_i, t_a, t_i in c.execute(
        "SELECT from_agent, from_id, to_agent, to_id FROM map_redirects WHERE map_id = ?", (mid,)
    ):
        m.point_redirects[(f_a, int(f_i))] = (t_a, int(t_i))
    t0 = time.perf_counter()
    blocks = read_positions(c, mid)
    rows = c.execute(
        "SELECT agent, id, xyz, descriptor FROM map_points WHERE map_id = ? ORDER BY seq", (mid,)
    )
    for n, (agent, pid, xyz, desc) in enumerate(rows):
        if n and n % 500_000 == 0:
            logger.info("map %d: %d map points loaded (%.1f s)", mid, n, time.perf_counter() - t0)
        m.add_point(
            MapPoint(
                agent,
                pid,
                position(blocks, agent, int(pid), xyz),
                np.frombuffer(desc, dtype=np.uint8),
            )
        )
    parents: dict[KfKey, KfKey | None] = {}
    cameras: dict[str, PinholeCamera] = {}
    for row in c.execute(
        f"SELECT {_KF_COLS} FROM map_keyframes WHERE map_id = ? ORDER BY seq", (mid,)
    ).fetchall():
        (_, agent, kid, _, ts, pose, cam, kps, octs, descs, pids, pag, genu, gcov, up, ur, base, odom,
         track, vio, pa, pi) = row  # fmt: skip
        camera = cameras.get(cam)
        if camera is None:
            camera = cameras[cam] = PinholeCamera.from_dict(json.loads(cam))
        kf = Keyframe(
            agent,
            kid,
            float(np.frombuffer(ts, dtype=np.float64)[0]),
            unpack_array(pose),
            camera,
            unpack_array(kps),
            unpack_array(octs),
            unpack_array(descs),
            unpack_array(pids),
            None if genu is None else unpack_array(genu),
            None if gcov is None else unpack_array(gcov),
            up_cam=None if up is None else unpack_array(up),
            u_right=None if ur is None else unpack_array(ur),
            stereo_baseline=base,
            odom_sigma=None if odom is None else unpack_array(odom),
            track_sigma=None if track is None else unpack_array(track),
            vio_from_cam=None if vio is None else unpack_array(vio),
        )
        if pag:
            kf.point_agents = {int(i): a for i, a in json.loads(pag).items()}
        m.add_keyframe(kf)
        parents[kf.key] = None if pa is None else (pa, int(pi))
    row = c.execute("SELECT agents, orphans FROM map_maps WHERE map_id = ?", (mid,)).fetchone()
    orphans: set[KfKey] = set()
    if row is not None:
        m.agents |= set(json.loads(row[0]))
        orphans = {(a, int(i)) for a, i in json.loads(row[1])}
    m._restore_tree(parents, orphans)
    for a_a, a_i, b_a, b_i in c.execute(
        "SELECT a_agent, a_id, b_agent, b_id FROM map_loops WHERE map_id = ?", (mid,)
    ):
        m.add_loop_edge((a_a, int(a_i)), (b_a, int(b_i)))
    m.merge_history = [
        json.loads(r[0])
        for r in c.execute("SELECT record FROM map_merges WHERE map_id = ? ORDER BY seq", (mid,))
    ]
    return m
