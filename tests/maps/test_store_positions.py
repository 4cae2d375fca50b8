"""MapStore: point positions written after insertion live in blocks (``map_point_xyz``) and reload exactly,
whatever happened to the points since (real SQLite files)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from hivemap.maps import MapPoint, MapStack, map_differences
from hivemap.maps.store import SCHEMA_VERSION, MapStore
from hivemap.maps.store_xyz import BLOCK
from hivemap.maps.testing import random_map


def _map_in_store(tmp_path: Path, seed: int, n_kf: int, n_pts: int) -> tuple[MapStack, MapStore]:
    stack = MapStack()
    m = stack.add_map(random_map(np.random.default_rng(seed), 0, "uav1", n_kf, n_pts, obs_per_keyframe=120))
    store = MapStore(tmp_path / "pos.sqlite")
    store.put_points(m.id, m.points.values())
    for kf in m.keyframes.values():
        store.put_keyframe(m.id, kf)
    store.sync_graph(m)
    return stack, store


def _blocks(store: MapStore) -> int:
    return int(store.conn.execute("SELECT COUNT(*) FROM map_point_xyz").fetchone()[0])


def test_every_point_moved_reloads_exactly_and_writes_one_row_per_block(tmp_path: Path) -> None:
    """An optimisation's write of every point: the rows written are blocks, not points, and the reloaded
    positions are bit-identical, special floats included."""
    stack, store = _map_in_store(tmp_path, 1, 30, 3000)
    m = stack.maps[0]
    rng = np.random.default_rng(2)
    for p in m.points.values():
        p.xyz = p.xyz + rng.normal(scale=0.01, size=3)
    odd = next(iter(m.points.values()))
    odd.xyz = np.array([-0.0, 5e-324, 1e300])
    for kf in m.keyframes.values():
        kf.world_from_cam = kf.world_from_cam.copy()
        kf.world_from_cam[:3, 3] += 0.5
    store.update_poses(m.id, m.keyframes.values(), m.points.values())
    one = list(m.points.values())[1]
    one.xyz = one.xyz + 0.25
    store.update_poses(m.id, (), [one])  # a write of one point keeps its block's other slots
    ids = {p.id // BLOCK for p in m.points.values()}
    assert _blocks(store) == len(ids) < len(m.points) / 20
    store.close()
    with MapStore(tmp_path / "pos.sqlite") as again:
        loaded = again.load_stack().maps[0]
    assert map_differences(m, loaded) == []
    assert np.array_equal(np.signbit(loaded.points[odd.key].xyz), np.signbit(odd.xyz))


def test_a_point_removed_and_put_again_reloads_at_its_new_position(tmp_path: Path) -> None:
    """A slot left by a moved point that was then removed never hides the position of the point put again
    under its key; a point never moved reloads from its row."""
    stack, store = _map_in_store(tmp_path, 3, 12, 800)
    m = stack.maps[0]
    pts = list(m.points.values())
    moved, untouched = pts[5], pts[6]
    moved.xyz = moved.xyz + 1.0
    store.update_poses(m.id, (), [moved])
    store.delete_points(m.id, [moved.key])
    again = MapPoint(moved.agent_id, moved.id, np.array([7.0, 8.0, 9.0]), moved.descriptor)
    m.points[moved.key].xyz = again.xyz
    store.put_points(m.id, [again])
    store.close()
    with MapStore(tmp_path / "pos.sqlite") as s:
        loaded = s.load_stack().maps[0]
    assert np.array_equal(loaded.points[moved.key].xyz, [7.0, 8.0, 9.0])
    assert np.array_equal(loaded.points[untouched.key].xyz, untouched.xyz)
    assert map_differences(m, loaded) == []


def test_a_whole_map_save_replaces_its_blocks(tmp_path: Path) -> None:
    """``save_map`` writes every position into the rows and drops the map's blocks; the positions moved
    after it go to blocks again."""
    stack, store = _map_in_store(tmp_path, 4, 12, 800)
    m = stack.maps[0]
    for p in list(m.points.values())[:50]:
        p.xyz = p.xyz * 2.0
    store.update_poses(m.id, (), list(m.points.values())[:50])
    assert _blocks(store) > 0
    for p in m.points.values():
        p.xyz = p.xyz + 3.0
    store.save_map(m)
    assert _blocks(store) == 0
    last = list(m.points.values())[-1]
    last.xyz = np.array([1.0, 2.0, 3.0])
    store.update_poses(m.id, (), [last])
    store.close()
    with MapStore(tmp_path / "pos.sqlite") as s:
        assert map_differences(m, s.load_stack().maps[0]) == []


def test_version_7_file_gains_position_blocks_and_keeps_its_maps(tmp_path: Path) -> None:
    """A store from before position blocks (schema 7: positions only in the rows) opens with its maps as
    they were, and its points' moves are kept in blocks from then on."""
    stack, store = _map_in_store(tmp_path, 5, 12, 800)
    store.close()
    con = sqlite3.connect(tmp_path / "pos.sqlite")
    con.execute("DROP TABLE map_point_xyz")
    con.execute("UPDATE map_schema SET version = 7")
    con.commit()
    con.close()
    m = stack.maps[0]
    with MapStore(tmp_path / "pos.sqlite") as s:
        assert s.conn.execute("SELECT version FROM map_schema").fetchone()[0] == SCHEMA_VERSION
        assert map_differences(m, s.load_stack().maps[0]) == []
        for p in list(m.points.values())[::7]:
            p.xyz = p.xyz - 4.0
        s.update_poses(m.id, (), list(m.points.values())[::7])
    with MapStore(tmp_path / "pos.sqlite") as s:
        assert map_differences(m, s.load_stack().maps[0]) == []
