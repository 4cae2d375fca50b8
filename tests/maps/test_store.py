"""MapStore: lossless full save/load, incremental writes, schema version, crash safety (real SQLite files)."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from hivemap.maps import Keyframe, MapPoint, MapStack, map_differences
from hivemap.maps.geometry import Sim3, so3_exp
from hivemap.maps.store import SCHEMA_VERSION, MapStore, SchemaError, StoreError, pack_array, unpack_array
from hivemap.maps.testing import DEFAULT_CAMERA, random_keyframes_and_points, random_map


def assert_stacks_equal(a: MapStack, b: MapStack) -> None:
    assert sorted(a.maps) == sorted(b.maps)
    assert a.next_map_id == b.next_map_id
    for mid in a.maps:
        assert map_differences(a.maps[mid], b.maps[mid]) == [], mid


def build_stack(seed: int, n_kf: int, n_pts: int) -> MapStack:
    """A stack exercising every stored feature: big map, fusions, removals, pending refs, loops, merges."""
    rng = np.random.default_rng(seed)
    stack = MapStack()
    big = stack.add_map(random_map(rng, 0, "ugv", n_kf, n_pts, obs_per_keyframe=250, extra_keypoints=50))
    stack.add_map(random_map(rng, 1, "uav1", 30, 1500))
    stack.add_map(random_map(rng, 2, "uav2#1", 20, 1000))
    stack.next_map_id = 3
    sim = Sim3(so3_exp([0.1, 0.5, -0.2]), np.array([3.0, 1, 2]), 1.3)
    stack.merge(1, 2, sim, [(("uav1", 0), ("uav2#1", 0))])
    stack.maps[1].merge_history[-1]["time"] = 0.0  # deterministic (the crash test rebuilds this stack)
    keys = list(big.points)
    for i in range(0, 400, 2):
        big.fuse_points(keys[i], keys[i + 1])
    for k in list(big.keyframes)[5 : n_kf - 5 : max(n_kf // 6, 3)]:
        big.remove_keyframe(k)
    for k in keys[1000:1050]:
        big.remove_point(k)
    big.add_loop_edge(("ugv", 0), ("ugv", n_kf - 1))
    big.add_loop_edge(("ugv", 2), ("ugv", n_kf - 3))
    # a keyframe from another agent referencing a fused point, a point of its own not yet arrived, and
    # special floats that a lossy store would change (-0.0, subnormal)
    kfs, _ = random_keyframes_and_points(rng, "uav3", 1, 10, obs_per_keyframe=5, extra_keypoints=3)
    kf = kfs[0]
    kf.point_ids[:3] = [1, 3, 99999]
    kf.point_agents = {0: "ugv", 1: "ugv"}
    kf.timestamp = -0.0
    big.add_keyframe(kf)
    big.add_point(MapPoint("uav3", 5, [-0.0, 5e-324, 1e300], np.arange(32, dtype=np.uint8)))
    return stack


def test_pack_array_round_trip_bit_identical() -> None:
    rng = np.random.default_rng(0)
    for a in (
        rng.normal(size=(7, 3)),
        rng.normal(size=(5, 2)).astype(np.float32),
        rng.integers(0, 256, (4, 32), dtype=np.uint8),
        np.array([-0.0, np.nan, np.inf, 5e-324]),
        np.zeros((0, 32), np.uint8),
        np.arange(6, dtype=">i8").reshape(2, 3),
    ):
        b = unpack_array(pack_array(a))
        assert b.dtype == a.dtype and b.shape == a.shape and b.tobytes() == a.tobytes()


def test_full_save_load_is_lossless_on_200_keyframes_20k_points(tmp_path: Path) -> None:
    stack = build_stack(0, 206, 20000)
    big = stack.maps[0]
    assert len(big.keyframes) >= 200 and len(big.points) >= 19500
    assert big.pending_references() and big.point_redirects and big.loop_edges()
    path = tmp_path / "maps.sqlite"
    t0 = time.perf_counter()
    with MapStore(path) as store:
        store.save_stack(stack)
    t_save = time.perf_counter() - t0
    t0 = time.perf_counter()
    with MapStore(path) as store:
        loaded = store.load_stack()
    t_load = time.perf_counter() - t0
    assert_stacks_equal(stack, loaded)  # bit-identical arrays, same covisibility/tree/loops/history
    lb = loaded.maps[0]
    assert lb.keyframes[("uav3", 0)].timestamp.hex() == "-0x0.0p+0"
    assert lb.check_consistency() == []
    assert lb.essential_edges() == big.essential_edges()
    assert [kf.parent for kf in lb.keyframes.values()] == [kf.parent for kf in big.keyframes.values()]
    # a second save over the first replaces it (no leftovers)
    stack.remove_map(1)
    with MapStore(path) as store:
        store.save_stack(stack)
        assert_stacks_equal(stack, store.load_stack())
    # generous bounds (measured 0.11 s / 0.24 s on the 2-core box): a full save/load is not a hot path
    assert t_save < 10 and t_load < 10


def test_incremental_writes_reload_to_the_same_map(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    kfs, pts = random_keyframes_and_points(rng, "uav1", 60, 4000, obs_per_keyframe=150)
    stack = MapStack()
    m = stack.new_map()
    store = MapStore(tmp_path / "inc.sqlite")
    t_kf = []
    for i, kf in enumerate(kfs):  # as the server does: points first, then the keyframe
        new = [p for p in pts if i * 66 <= p.id < (i + 1) * 66 + 200 and p.key not in m.points]
        for p in new:
            m.add_point(p)
        store.put_points(m.id, new)
        m.add_keyframe(kf)
        t0 = time.perf_counter()
        store.put_keyframe(m.id, kf)
        t_kf.append(time.perf_counter() - t0)
    store.sync_graph(m)
    # local-BA style pose updates: only poses and positions are rewritten
    for kf in list(m.keyframes.values())[-10:]:
        kf.world_from_cam = kf.world_from_cam @ np.diag([1.0, -1, -1, 1])
    moved = list(m.points.values())[-300:]
    for p in moved:
        p.xyz = p.xyz + rng.normal(size=3)
    store.update_poses(m.id, list(m.keyframes.values())[-10:], moved)
    # fusions and a removal: rewrite the touched keyframes, delete the dropped rows, sync the graphs
    touched = set()
    keys = list(m.points)
    for i in range(0, 100, 2):
        touched |= set(m.points[keys[i + 1]].observations)
        m.fuse_points(keys[i], keys[i + 1])
    gone = ("uav1", 10)
    touched |= set(m.covisibility(gone))
    m.remove_keyframe(gone)
    touched.discard(gone)
    for k in touched:
        store.put_keyframe(m.id, m.keyframes[k])
    store.delete_points(m.id, [keys[i + 1] for i in range(0, 100, 2)])
    store.delete_keyframes(m.id, [gone])
    m.add_loop_edge(("uav1", 0), ("uav1", 50))
    store.sync_graph(m)
    store.set_meta("last_seq/uav1", 1234)
    store.close()
    with MapStore(tmp_path / "inc.sqlite") as again:
        loaded = again.load_stack()
        assert again.get_meta("last_seq/uav1") == 1234 and again.get_meta("nope", 7) == 7
    assert map_differences(m, loaded.maps[m.id]) == []
    assert loaded.next_map_id == 1
    # cheap per call: a keyframe upsert (with its commit) does not grow with the map; 50 ms is a loose
    # bound for one fsync'd row on a shared disk
    assert float(np.median(t_kf[-20:])) < 0.05


def test_graph_syncs_write_only_changed_redirects_and_reload_to_the_map(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    kfs, pts = random_keyframes_and_points(rng, "uav1", 20, 1500, obs_per_keyframe=120)
    stack = MapStack()
    m = stack.new_map()
    for p in pts:
        m.add_point(p)
    for kf in kfs:
        m.add_keyframe(kf)
    store = MapStore(tmp_path / "red.sqlite")
    store.save_map(m)
    keys = list(m.points)

    def rows() -> set[tuple]:
        return set(store.conn.execute("SELECT * FROM map_redirects").fetchall())

    for start in (0, 100):  # two rounds of fusions, each followed by a sync
        for i in range(start, start + 60, 2):
            m.fuse_points(keys[i], keys[i + 1])
        store.delete_points(m.id, [keys[i + 1] for i in range(start, start + 60, 2)])
        store.sync_graph(m)
    assert len(rows()) == len(m.point_redirects) == 60
    # a fused-away point that comes back (an agent re-sends it) loses its redirect, in the rows too
    back = MapPoint(keys[1][0], keys[1][1], np.zeros(3), np.zeros(32, np.uint8))
    m.add_point(back)
    assert keys[1] not in m.point_redirects
    store.put_points(m.id, [back])
    # a sync rolled back leaves rows the sync cache must not trust: the next sync rewrites them all
    store.autocommit = False
    store.conn.execute("BEGIN")
    store.sync_graph(m)
    store.conn.rollback()
    store.forget_caches()
    store.autocommit = True
    assert len(rows()) == 60
    store.sync_graph(m)
    assert len(rows()) == 59
    store.close()
    with MapStore(tmp_path / "red.sqlite") as again:
        assert again.load_stack().maps[m.id].point_redirects == m.point_redirects


def test_writes_join_the_callers_transaction(tmp_path: Path) -> None:
    store = MapStore(tmp_path / "tx.sqlite")
    store.conn.execute("CREATE TABLE other (x INTEGER)")
    store.conn.commit()
    store.conn.execute("INSERT INTO other VALUES (1)")  # the caller opens a transaction
    store.put_points(0, [MapPoint("a", 1, [1, 2, 3])])
    store.set_meta("k", [1, 2])
    store.conn.rollback()  # ... and rolls everything back: the map rows went with it
    assert store.load_stack().maps == {} and store.get_meta("k") is None
    with pytest.raises(RuntimeError), store.transaction():  # a failed group leaves nothing behind
        store.put_points(0, [MapPoint("a", 2, [1, 2, 3])])
        store.set_meta("k", 1)
        raise RuntimeError("boom")
    assert store.load_stack().maps == {} and store.get_meta("k") is None
    store.autocommit = False
    store.put_points(0, [MapPoint("a", 1, [1, 2, 3])])
    store.conn.commit()
    assert list(store.load_stack().maps[0].points) == [("a", 1)]
    store.close()


def _older_file(
    path: Path, stack: MapStack, version: int, columns: tuple[str, ...], drop_tables: tuple[str, ...] = ()
) -> None:
    """``stack`` saved at ``path`` as a store of schema ``version`` would hold it: without the keyframe
    ``columns`` and the tables that came later."""
    store = MapStore(path)
    store.save_stack(stack)
    store.close()
    con = sqlite3.connect(path)
    for col in columns:
        con.execute(f"ALTER TABLE map_keyframes DROP COLUMN {col}")
    for table in drop_tables:
        con.execute(f"DROP TABLE {table}")
    con.execute("UPDATE map_schema SET version = ?", (version,))
    con.commit()
    con.close()


def test_version_1_file_is_migrated_and_keeps_its_maps(tmp_path: Path) -> None:
    """A store written before keyframes carried ``up_cam`` (schema 1), stereo observations (2) or
    ``odom_sigma`` (3) opens, keeps every map, and stores them from then on."""
    path = tmp_path / "v1.sqlite"
    stack = build_stack(11, 40, 2000)
    _older_file(path, stack, 1, ("up_cam", "u_right", "stereo_baseline", "odom_sigma", "track_sigma"))
    store = MapStore(path)
    assert store.conn.execute("SELECT version FROM map_schema").fetchone()[0] == SCHEMA_VERSION
    loaded = store.load_stack()
    for m in stack.maps.values():
        for kf in m.keyframes.values():
            kf.up_cam = kf.u_right = kf.stereo_baseline = kf.odom_sigma = None  # what a version-1 file held
            kf.track_sigma = None
    assert_stacks_equal(stack, loaded)
    kf = next(iter(loaded.maps[0].keyframes.values()))
    kf.up_cam = np.array([0.0, 0.6, 0.8])
    kf.odom_sigma = np.array([0.9, 3.0])
    store.put_keyframe(0, kf)
    store.close()
    again = MapStore(path).load_stack()
    assert np.array_equal(again.maps[0].keyframes[kf.key].up_cam, [0.0, 0.6, 0.8])
    assert np.array_equal(again.maps[0].keyframes[kf.key].odom_sigma, [0.9, 3.0])
    assert again.maps[0].keyframes[kf.key].u_right is None


def test_version_2_file_is_migrated_and_its_keyframes_load_as_mono(tmp_path: Path) -> None:
    """A store written before keyframes carried stereo observations (schema 2) opens with every keyframe
    mono, and stores ``u_right`` from then on."""
    path = tmp_path / "v2.sqlite"
    stack = build_stack(12, 40, 2000)
    assert any(kf.u_right is not None for m in stack.maps.values() for kf in m.keyframes.values())
    _older_file(path, stack, 2, ("u_right", "stereo_baseline", "odom_sigma", "track_sigma"))
    store = MapStore(path)
    loaded = store.load_stack()
    for m in stack.maps.values():
        for kf in m.keyframes.values():
            kf.u_right = kf.stereo_baseline = kf.odom_sigma = kf.track_sigma = None
    assert_stacks_equal(stack, loaded)
    kf = next(iter(loaded.maps[0].keyframes.values()))
    kf.u_right = np.full(kf.n_keypoints, 100.5, np.float32)
    kf.stereo_baseline = 0.12
    store.put_keyframe(0, kf)
    store.close()
    again = MapStore(path).load_stack().maps[0].keyframes[kf.key]
    assert again.stereo_baseline == 0.12 and again.u_right is not None
    assert again.u_right.dtype == np.float32 and (again.u_right == 100.5).all()


@pytest.mark.parametrize("dropped", [("odom_sigma",), ("u_right", "stereo_baseline")])
def test_version_3_file_is_migrated_and_keeps_its_keyframes(tmp_path: Path, dropped: tuple[str, ...]) -> None:
    """A schema-3 store opens whichever optional keyframe field it lacked (stereo observations, or the
    weak-tracking ``odom_sigma`` of a store written before both were in one schema), keeps every other
    field, and stores both from then on."""
    path = tmp_path / "v3.sqlite"
    stack = build_stack(13, 40, 2000)
    kfs = [kf for m in stack.maps.values() for kf in m.keyframes.values()]
    assert any(kf.odom_sigma is not None for kf in kfs) and any(kf.u_right is not None for kf in kfs)
    _older_file(path, stack, 3, dropped)
    store = MapStore(path)
    assert store.conn.execute("SELECT version FROM map_schema").fetchone()[0] == SCHEMA_VERSION
    loaded = store.load_stack()
    for kf in kfs:
        for col in dropped:
            setattr(kf, col, None)
    assert_stacks_equal(stack, loaded)
    kf = next(iter(loaded.maps[0].keyframes.values()))
    kf.u_right = np.full(kf.n_keypoints, 50.25, np.float32)
    kf.stereo_baseline = 0.12
    kf.odom_sigma = np.array([0.4, 2.0])
    store.put_keyframe(0, kf)
    store.close()
    again = MapStore(path).load_stack().maps[0].keyframes[kf.key]
    assert again.u_right is not None and (again.u_right == 50.25).all() and again.stereo_baseline == 0.12
    assert again.odom_sigma is not None and np.array_equal(again.odom_sigma, [0.4, 2.0])


def test_refuses_newer_or_unknown_schema(tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    MapStore(path).close()
    con = sqlite3.connect(path)
    con.execute("UPDATE map_schema SET version = 99")
    con.commit()
    con.close()
    with pytest.raises(SchemaError, match="version 99"):
        MapStore(path)
    path2 = tmp_path / "unknown.sqlite"
    con = sqlite3.connect(path2)
    con.execute("CREATE TABLE map_keyframes (x)")
    con.commit()
    con.close()
    with pytest.raises(SchemaError, match="unknown format"):
        MapStore(path2)
    path3 = tmp_path / "garbage.sqlite"
    path3.write_bytes(b"definitely not sqlite" * 100)
    with pytest.raises(StoreError):
        MapStore(path3)


CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from hivemap.maps.store import MapStore
    from hivemap.maps.testing import random_map
    sys.path.insert(0, {testdir!r})
    from test_store import build_stack

    store = MapStore({path!r})
    store.save_stack(build_stack(1, 40, 3000))
    print("saved A", flush=True)
    big = build_stack(2, 150, 15000)
    for i in range(3, 8):
        big.add_map(random_map(np.random.default_rng(i), i, f"agent{{i}}", 20, 1000))

    def progress(i, n):
        print(f"progress {{i}}/{{n}}", flush=True)
        if i == 2:
            time.sleep(120)  # the parent kills us here, in the middle of the transaction

    store.save_stack(big, progress=progress)
    print("saved B", flush=True)
    """
)


def test_save_killed_half_way_leaves_the_previous_save_loadable(tmp_path: Path) -> None:
    path = tmp_path / "crash.sqlite"
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(testdir=str(Path(__file__).parent), path=str(path)))
    proc = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append(line.strip())
        if line.startswith("progress 2/"):
            os.kill(proc.pid, signal.SIGKILL)
            break
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, (lines, proc.stderr.read() if proc.stderr else "")
    assert lines[0] == "saved A" and "saved B" not in lines
    assert Path(str(path) + "-wal").exists()  # the killed writer left its uncommitted frames behind
    with MapStore(path) as store:
        assert store.conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        loaded = store.load_stack()
    assert_stacks_equal(build_stack(1, 40, 3000), loaded)


def test_keyframe_without_points_and_gnss_round_trip(tmp_path: Path) -> None:
    stack = MapStack()
    m = stack.new_map(5)
    kf = Keyframe("ugv", 0, 12.5, np.eye(4), DEFAULT_CAMERA, np.zeros((0, 2)), gnss_enu=[1.0, 2, 3])
    m.add_keyframe(kf)
    with MapStore(tmp_path / "e.sqlite") as store:
        store.save_stack(stack)
        loaded = store.load_stack()
    assert map_differences(m, loaded.maps[5]) == [] and loaded.next_map_id == 6


def test_incremental_merge_save_map_and_delete_source(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    stack = MapStack()
    a = stack.add_map(random_map(rng, 0, "ugv", 15, 800))
    b = stack.add_map(random_map(rng, 1, "uav1", 15, 800))
    store = MapStore(tmp_path / "merge.sqlite")
    for m in (a, b):  # written incrementally first, as the server does
        store.put_points(m.id, m.points.values())
        for kf in m.keyframes.values():
            store.put_keyframe(m.id, kf)
        store.sync_graph(m)
    merged = stack.merge(0, 1, Sim3(so3_exp([0.2, 0.1, 0.0]), np.ones(3), 0.5), [(("ugv", 3), ("uav1", 3))])
    with store.transaction():
        store.save_map(merged)
        store.delete_map(1)
    loaded = store.load_stack()
    store.close()
    assert list(loaded.maps) == [0]
    assert map_differences(merged, loaded.maps[0]) == []


def test_a_map_saved_from_its_rows_is_the_map_at_that_instant(tmp_path: Path) -> None:
    """The server serialises a merged map on its event loop (``map_rows``) and writes it from the store
    thread while back-end tasks go on changing the map: the stored map is the one at the snapshot, and
    the later changes cannot break the write."""
    import copy

    from hivemap.maps.store import map_rows

    rng = np.random.default_rng(9)
    stack = MapStack()
    m = stack.add_map(random_map(rng, 0, "ugv", 15, 800))
    at_snapshot = copy.deepcopy(m)
    rows = map_rows(m)
    # what a fusion or culling does meanwhile: points go, keyframes move
    for key in list(m.points)[:100]:
        del m.points[key]
    for kf in m.keyframes.values():
        kf.world_from_cam = kf.world_from_cam.copy()
        kf.world_from_cam[:3, 3] += 1.0
    store = MapStore(tmp_path / "rows.sqlite")
    store.save_map(rows)
    loaded = store.load_stack()
    store.close()
    assert map_differences(at_snapshot, loaded.maps[0]) == []
    assert map_differences(m, loaded.maps[0]) != []


def test_version_4_file_gains_the_rendezvous_table_and_keeps_its_maps(tmp_path: Path) -> None:
    """A store written before rendezvous observations (no ``map_rendezvous``) opens, keeps its maps and
    stores observations from then on, across a reopen."""
    path = tmp_path / "v4.sqlite"
    stack = build_stack(17, 20, 800)
    _older_file(path, stack, 4, (), drop_tables=("map_rendezvous",))
    store = MapStore(path)
    assert store.conn.execute("SELECT version FROM map_schema").fetchone()[0] == SCHEMA_VERSION
    assert_stacks_equal(stack, store.load_stack())
    assert store.load_rendezvous() == {}
    rec = {"observer": "uav1", "cam_from_observed": np.eye(4).tolist(), "timestamp": 0.1 + 0.2}
    store.put_rendezvous(3, rec)
    store.put_rendezvous(3, {**rec, "state": "kept"})
    store.close()
    store = MapStore(path)
    assert store.load_rendezvous() == {3: {**rec, "state": "kept"}}
    store.close()


def test_version_5_file_is_migrated_and_stores_track_sigma(tmp_path: Path) -> None:
    """A store written before keyframes said how well their agent tracked (schema 5) opens with no
    ``track_sigma`` anywhere, keeps every other field, and stores it from then on."""
    path = tmp_path / "v5.sqlite"
    stack = build_stack(14, 40, 2000)
    assert any(kf.track_sigma is not None for m in stack.maps.values() for kf in m.keyframes.values())
    _older_file(path, stack, 5, ("track_sigma",))
    store = MapStore(path)
    assert store.conn.execute("SELECT version FROM map_schema").fetchone()[0] == SCHEMA_VERSION
    loaded = store.load_stack()
    for m in stack.maps.values():
        for kf in m.keyframes.values():
            kf.track_sigma = None
    assert_stacks_equal(stack, loaded)
    kf = next(iter(loaded.maps[0].keyframes.values()))
    kf.track_sigma = np.array([0.007, 0.04])
    store.put_keyframe(0, kf)
    store.close()
    again = MapStore(path).load_stack().maps[0].keyframes[kf.key]
    assert np.array_equal(again.track_sigma, [0.007, 0.04])
