"""Map persistence in one SQLite file (stdlib ``sqlite3``, WAL journal).

Two ways to write, one set of tables, one way to read:

- full: ``save_stack(stack)`` replaces every map in one transaction (a save killed half way leaves the
  previous one intact: SQLite's atomic commit); ``save_map(m)`` replaces one map the same way;
- incremental, for the server, cheap per call: ``put_keyframe``, ``put_points``, ``update_poses``,
  ``sync_graph`` (spanning-tree parents that changed, orphans, loop edges, fusion redirects, agents),
  ``delete_map``, ``record_merge``, and ``set_meta`` / ``get_meta`` (small JSON key/value table);
- ``load_stack()`` / ``load_map(map_id)`` rebuild maps from the rows whichever way they were written.

Lossless: arrays are stored as raw bytes with their dtype and shape (``pack_array``), floats that are not
in arrays (timestamps) as 8 raw bytes, so everything reloads bit-identical; covisibility is re-derived
from the keyframes' point references (the model's source of truth) and the spanning tree is restored
from the stored parents. Positions written after a point's insertion are kept in blocks of consecutive
point ids (:mod:`hivemap.maps.store_xyz`), so rewriting every point after an optimisation writes a page per
block rather than a page per point.

Transactions: each write method runs in its own transaction and commits, unless a transaction is
already open on ``conn`` or ``autocommit`` is False; then the caller commits (``conn.commit()``), so
map rows can commit atomically with the caller's own rows in the same file.

The file carries a schema version (table ``map_schema``); a file with a newer or unknown schema is
refused with ``SchemaError``.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3
from hivemap.maps.model import Keyframe, KfKey, Map, MapPoint, PointKey
from hivemap.maps.stack import MapStack
from hivemap.maps.store_load import read_map
from hivemap.maps.store_rows import MapRows, _kf_row, _pt_row, map_rows, pack_array, unpack_array
from hivemap.maps.store_schema import _KF_UPSERT, _PT_UPSERT, _SCHEMA, _TABLES
from hivemap.maps.store_xyz import put_positions

logger = logging.getLogger(__name__)

__all__ = [
    "SCHEMA_VERSION", "MapRows", "MapStore", "SchemaError", "StoreError", "map_rows", "pack_array",
    "unpack_array",
]  # fmt: skip

# 2: map_keyframes.up_cam; 3: u_right, stereo_baseline; 4: odom_sigma; 5: map_rendezvous; 6: track_sigma;
# 7: vio_from_cam; 8: map_point_xyz
SCHEMA_VERSION = 8


class StoreError(RuntimeError):
    """The file cannot be used as a map store."""


class SchemaError(StoreError):
    """The file's schema version is newer than or unknown to this hivemap."""


class MapStore:
    """A map store in one SQLite file. ``conn`` is the (single) connection; close with ``close()``."""

    def __init__(self, path: str | Path, *, autocommit: bool = True, synchronous: str = "FULL") -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.autocommit = autocommit
        try:
            self.conn = sqlite3.connect(str(self.path), check_same_thread=False)
            self.conn.execute("PRAGMA journal_mode=WAL")
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path}: not a usable SQLite file ({e})") from e
        self.conn.execute(f"PRAGMA synchronous={'FULL' if synchronous.upper() == 'FULL' else 'NORMAL'}")
        self._check_schema()
        self._seq = {
            "map_keyframes": self._max_seq("map_keyframes"),
            "map_points": self._max_seq("map_points"),
        }
        self._agents_cache: dict[int, set[str]] = {}
        # per map the fusion redirects its rows hold, so a sync writes only the changed ones (dropped at
        # every other write of the map's redirects and on a rollback: the next sync then rewrites all)
        self._redirects_cache: dict[int, dict[PointKey, PointKey]] = {}

    # ------------------------------------------------------------------ set-up
    def _check_schema(self) -> None:
        tables = {r[0] for r in self.conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "map_schema" in tables:
            rows = self.conn.execute("SELECT version FROM map_schema").fetchall()
            if len(rows) != 1:
                raise SchemaError(f"{self.path}: corrupt schema version table ({len(rows)} rows)")
            version = rows[0][0]
            if not isinstance(version, int) or version > SCHEMA_VERSION or version < 1:
                raise SchemaError(
                    f"{self.path}: map store schema version {version!r} is not supported by this hivemap "
                    f"(it reads version {SCHEMA_VERSION}); use a newer hivemap or another data directory"
                )
            if version < SCHEMA_VERSION:
                # each step adds NULL columns (old rows: no up direction, mono, tracked well); a column is
                # added by its absence, not by the version, as a development store may hold a later one only
                cols = {r[1] for r in self.conn.execute("PRAGMA table_info(map_keyframes)").fetchall()}
                added = (
                    ("up_cam", "BLOB"),  # 1 -> 2: keyframes carry the agent's IMU up direction
                    ("u_right", "BLOB"),  # 2 -> 3: and their stereo observations
                    ("stereo_baseline", "REAL"),
                    ("odom_sigma", "BLOB"),  # 3 -> 4: and the error weak or lost tracking added
                    # 4 -> 5: the table map_rendezvous, created below with the others
                    ("track_sigma", "BLOB"),  # 5 -> 6: and how well the agent tracked
                    ("vio_from_cam", "BLOB"),  # 6 -> 7: and the agent's own pose of it
                    # 7 -> 8: the table map_point_xyz (positions by block), created below
                )
                with self._tx():
                    for col, kind in added:
                        if col not in cols:
                            self.conn.execute(f"ALTER TABLE map_keyframes ADD COLUMN {col} {kind}")
                    self.conn.execute("UPDATE map_schema SET version = ?", (SCHEMA_VERSION,))
                logger.info(
                    "%s: map store schema migrated from version %d to %d", self.path, version, SCHEMA_VERSION
                )
            self.conn.executescript(_SCHEMA)
            return
        if tables & set(_TABLES):
            raise SchemaError(f"{self.path}: map tables without a schema version: unknown format")
        self.conn.executescript(_SCHEMA)
        with self._tx():
            self.conn.execute("INSERT INTO map_schema (version) VALUES (?)", (SCHEMA_VERSION,))

    def _max_seq(self, table: str) -> int:
        return int(self.conn.execute(f"SELECT COALESCE(MAX(seq), 0) FROM {table}").fetchone()[0])

    def _next_seq(self, table: str) -> int:
        self._seq[table] += 1
        return self._seq[table]

    @contextmanager
    def _tx(self) -> Iterator[None]:
        """A transaction, unless the caller already holds one (or autocommit is off): then join it."""
        if self.conn.in_transaction or not self.autocommit:
            yield
            return
        self.conn.execute("BEGIN")
        try:
            yield
        except BaseException:
            self.conn.rollback()
            self.forget_caches()
            raise
        self.conn.commit()

    def forget_caches(self) -> None:
        """After a rollback: what this object remembers of the rows may not be what they hold."""
        self._agents_cache.clear()
        self._redirects_cache.clear()

    def transaction(self) -> AbstractContextManager[None]:
        """Group several writes into one transaction (commits at the end unless the caller already holds
        one), e.g. ``with store.transaction(): store.save_map(merged); store.delete_map(source_id)``."""
        return self._tx()

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> MapStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ key/value
    def set_meta(self, key: str, value: Any) -> None:
        """Store a JSON-serialisable value under ``key``."""
        with self._tx():
            self.conn.execute(
                "INSERT INTO map_meta (key, value) VALUES (?, ?) "
                "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
                (str(key), json.dumps(value)),
            )

    def get_meta(self, key: str, default: Any = None) -> Any:
        row = self.conn.execute("SELECT value FROM map_meta WHERE key = ?", (str(key),)).fetchone()
        return default if row is None else json.loads(row[0])

    # ------------------------------------------------------------------ rendezvous observations
    def put_rendezvous(self, rid: int, record: dict[str, Any]) -> None:
        """Store (or update) rendezvous observation ``rid``: ``record`` is JSON (its matrices as lists;
        Python's JSON floats round-trip exactly)."""
        with self._tx():
            self.conn.execute(
                "INSERT INTO map_rendezvous (id, record) VALUES (?, ?) "
                "ON CONFLICT (id) DO UPDATE SET record = excluded.record",
                (int(rid), json.dumps(record)),
            )

    def load_rendezvous(self) -> dict[int, dict[str, Any]]:
        """Every stored rendezvous observation by id, in id order."""
        rows = self.conn.execute("SELECT id, record FROM map_rendezvous ORDER BY id")
        return {int(i): json.loads(r) for i, r in rows}

    # ------------------------------------------------------------------ incremental writes
    def _ensure_map(self, map_id: int, agents: Iterable[str] = ()) -> None:
        cache = self._agents_cache.get(map_id)
        if cache is None:
            row = self.conn.execute("SELECT agents FROM map_maps WHERE map_id = ?", (map_id,)).fetchone()
            if row is None:
                self.conn.execute("INSERT INTO map_maps (map_id) VALUES (?)", (map_id,))
                self.conn.execute(
                    "INSERT INTO map_state (key, value) VALUES ('next_map_id', ?) ON CONFLICT (key) "
                    "DO UPDATE SET value = MAX(CAST(value AS INTEGER), CAST(excluded.value AS INTEGER))",
                    (json.dumps(map_id + 1),),
                )
                cache = set()
            else:
                cache = set(json.loads(row[0]))
            self._agents_cache[map_id] = cache
        new = set(agents) - cache
        if new:
            cache |= new
            self.conn.execute(
                "UPDATE map_maps SET agents = ? WHERE map_id = ?", (json.dumps(sorted(cache)), map_id)
            )

    def put_keyframe(self, map_id: int, kf: Keyframe) -> None:
        """Insert or replace one keyframe (with its current point references and parent)."""
        map_id = int(map_id)
        with self._tx():
            self._ensure_map(map_id, [kf.agent_id])
            self.conn.execute(_KF_UPSERT, _kf_row(map_id, kf, self._next_seq("map_keyframes")))

    def put_points(self, map_id: int, points: Iterable[MapPoint]) -> None:
        """Insert or replace points (position and descriptor; observations come from the keyframes)."""
        map_id = int(map_id)
        pts = list(points)
        if not pts:
            return
        with self._tx():
            self._ensure_map(map_id, {p.agent_id for p in pts})
            self.conn.executemany(_PT_UPSERT, [_pt_row(map_id, p, self._next_seq("map_points")) for p in pts])
            put_positions(self.conn, map_id, pts)  # a slot left from an earlier write must not hide xyz

    def update_poses(
        self,
        map_id: int,
        keyframes: Iterable[Keyframe] = (),
        points: Iterable[MapPoint] = (),
        vio: bool = False,
    ) -> None:
        """Write only the current ``world_from_cam`` of ``keyframes`` (with ``vio`` their ``vio_from_cam``
        too: an agent's pose update changes it, a back-end correction does not; rows not stored are
        ignored) and ``xyz`` of ``points`` (into their position blocks, :mod:`hivemap.maps.store_xyz`; the
        slot of a point without a row is not read, and is set again if the point is put)."""
        map_id = int(map_id)
        with self._tx():
            sets = "world_from_cam = ?, vio_from_cam = ?" if vio else "world_from_cam = ?"

            def row(kf: Keyframe) -> tuple[Any, ...]:
                own = (None if kf.vio_from_cam is None else pack_array(kf.vio_from_cam),) if vio else ()
                return (pack_array(kf.world_from_cam), *own, map_id, kf.agent_id, kf.id)

            self.conn.executemany(
                f"UPDATE map_keyframes SET {sets} WHERE map_id = ? AND agent = ? AND id = ?",
                [row(kf) for kf in keyframes],
            )
            put_positions(self.conn, map_id, points)

    def put_fusion(
        self,
        map_id: int,
        references: Iterable[tuple[KfKey, NDArray[np.int64], dict[int, str]]],
        dropped: Iterable[PointKey],
    ) -> None:
        """Write a point fusion: the point references (``point_ids``, ``point_agents``) of the keyframes it
        changed, and the removal of the fused-away points (their redirects go with ``sync_graph``)."""
        map_id = int(map_id)
        with self._tx():
            self.conn.executemany(
                "UPDATE map_keyframes SET point_ids = ?, point_agents = ? "
                "WHERE map_id = ? AND agent = ? AND id = ?",
                [
                    (
                        pack_array(ids),
                        json.dumps({str(i): a for i, a in sorted(agents.items())}) if agents else None,
                        map_id,
                        k[0],
                        k[1],
                    )
                    for k, ids, agents in references
                ],
            )
            self.conn.executemany(
                "DELETE FROM map_points WHERE map_id = ? AND agent = ? AND id = ?",
                [(map_id, k[0], k[1]) for k in dropped],
            )

    def delete_keyframes(self, map_id: int, keys: Iterable[KfKey]) -> None:
        with self._tx():
            self.conn.executemany(
                "DELETE FROM map_keyframes WHERE map_id = ? AND agent = ? AND id = ?",
                [(int(map_id), a, int(i)) for a, i in keys],
            )

    def delete_points(self, map_id: int, keys: Iterable[PointKey]) -> None:
        with self._tx():
            self.conn.executemany(
                "DELETE FROM map_points WHERE map_id = ? AND agent = ? AND id = ?",
                [(int(map_id), a, int(i)) for a, i in keys],
            )

    def remove_side(
        self,
        map_id: int,
        keyframes: Iterable[KfKey],
        points: Iterable[PointKey],
        agents: Iterable[str],
        record: dict[str, Any],
    ) -> None:
        """The rows of a split's kept map (:func:`hivemap.maps.merge.split_map`) other than its graph
        (``sync_graph``): the leaving ``keyframes`` and ``points`` go, its agents become ``agents``, and
        ``record`` is appended to its merge history."""
        map_id = int(map_id)
        with self._tx():
            self.delete_keyframes(map_id, keyframes)
            self.delete_points(map_id, points)
            left = sorted(set(agents))
            self.conn.execute("UPDATE map_maps SET agents = ? WHERE map_id = ?", (json.dumps(left), map_id))
            self._agents_cache[map_id] = set(left)
            self.conn.execute(
                "INSERT INTO map_merges (map_id, record) VALUES (?, ?)", (map_id, json.dumps(record))
            )

    def sync_graph(self, m: Map) -> None:
        """Write what the per-item calls do not carry: the parents that changed since the last sync
        (``Map.drain_tree_changes``), orphans, loop edges, fusion redirects and agents of map ``m``."""
        map_id = m.id
        changed = m.drain_tree_changes()
        with self._tx():
            self._ensure_map(map_id, m.agents)
            self.conn.executemany(
                "UPDATE map_keyframes SET parent_agent = ?, parent_id = ? "
                "WHERE map_id = ? AND agent = ? AND id = ?",
                [
                    (
                        *(m.keyframes[k].parent or (None, None)),
                        map_id,
                        k[0],
                        k[1],
                    )
                    for k in changed
                ],
            )
            self.conn.execute(
                "UPDATE map_maps SET orphans = ? WHERE map_id = ?",
                (json.dumps(sorted(m.orphans)), map_id),
            )
            self.conn.execute("DELETE FROM map_loops WHERE map_id = ?", (map_id,))
            self.conn.executemany(
                "INSERT INTO map_loops VALUES (?, ?, ?, ?, ?)",
                [(map_id, a[0], a[1], b[0], b[1]) for a, b in m.loop_edges()],
            )
            cur = m.point_redirects
            last = self._redirects_cache.pop(map_id, None)
            if last is None:
                self.conn.execute("DELETE FROM map_redirects WHERE map_id = ?", (map_id,))
                last = {}
            gone = [f for f in last if f not in cur]
            self.conn.executemany(
                "DELETE FROM map_redirects WHERE map_id = ? AND from_agent = ? AND from_id = ?",
                [(map_id, f[0], f[1]) for f in gone],
            )
            self.conn.executemany(
                "INSERT OR REPLACE INTO map_redirects VALUES (?, ?, ?, ?, ?)",
                [(map_id, f[0], f[1], t[0], t[1]) for f, t in cur.items() if last.get(f) != t],
            )
            self._redirects_cache[map_id] = dict(cur)

    def delete_map(self, map_id: int) -> None:
        """Remove a map's rows (keyframes, points, graphs, its merge records)."""
        with self._tx():
            self._delete_map_rows(int(map_id), merges=True)

    def _delete_map_rows(self, map_id: int, merges: bool) -> None:
        for t in _TABLES:
            if t != "map_merges" or merges:
                self.conn.execute(f"DELETE FROM {t} WHERE map_id = ?", (map_id,))
        self._agents_cache.pop(map_id, None)
        self._redirects_cache.pop(map_id, None)

    def record_merge(
        self,
        target_id: int,
        source_id: int,
        target_from_source: Sim3 | NDArray[np.float64] | None = None,
        record: dict[str, Any] | None = None,
    ) -> None:
        """Append a merge record to the target's history; the source's earlier records move to the target.
        ``record`` (e.g. ``merged_map.merge_history[-1]``) is stored as given; without it a minimal one is
        built from ``target_from_source``. (The moved keyframes and points are written by ``save_map``.)"""
        if record is None:
            M = target_from_source.matrix() if isinstance(target_from_source, Sim3) else target_from_source
            record = {
                "time": time.time(),
                "target": int(target_id),
                "source": int(source_id),
                "target_from_source": None if M is None else np.asarray(M, dtype=np.float64).tolist(),
            }
        with self._tx():
            self.conn.execute(
                "UPDATE map_merges SET map_id = ? WHERE map_id = ?", (int(target_id), int(source_id))
            )
            self.conn.execute(
                "INSERT INTO map_merges (map_id, record) VALUES (?, ?)", (int(target_id), json.dumps(record))
            )

    # ------------------------------------------------------------------ full writes
    def _write_map(self, rows: MapRows, merges: bool) -> None:
        mid = rows.map_id
        self.conn.execute(
            "INSERT INTO map_maps (map_id, agents, orphans) VALUES (?, ?, ?)",
            (mid, json.dumps(rows.agents), json.dumps(rows.orphans)),
        )
        self._agents_cache[mid] = set(rows.agents)
        pt_seq, kf_seq = "map_points", "map_keyframes"
        self.conn.executemany(_PT_UPSERT, [(*r[:3], self._next_seq(pt_seq), *r[4:]) for r in rows.points])
        self.conn.executemany(_KF_UPSERT, [(*r[:3], self._next_seq(kf_seq), *r[4:]) for r in rows.keyframes])
        self.conn.executemany("INSERT INTO map_loops VALUES (?, ?, ?, ?, ?)", rows.loops)
        self.conn.executemany("INSERT INTO map_redirects VALUES (?, ?, ?, ?, ?)", rows.redirects)
        self._redirects_cache.pop(mid, None)
        if merges:
            self.conn.executemany("INSERT INTO map_merges (map_id, record) VALUES (?, ?)", rows.merges)

    def save_map(self, m: Map | MapRows) -> None:
        """Replace map ``m``'s rows (one transaction), e.g. after a merge. Its merge records are rewritten
        from ``m.merge_history``. From another thread than the one changing the map, pass
        ``map_rows(m)`` taken on that thread: iterating a live map while it changes fails."""
        rows = m if isinstance(m, MapRows) else map_rows(m)
        with self._tx():
            self._delete_map_rows(rows.map_id, merges=True)
            self._write_map(rows, merges=True)

    def save_stack(self, stack: MapStack, progress: Callable[[int, int], None] | None = None) -> None:
        """Replace every stored map with ``stack`` in one transaction (the meta table is kept).
        ``progress(i, n)`` is called after each map is written."""
        t0 = time.perf_counter()
        with self._tx():
            for t in _TABLES:
                self.conn.execute(f"DELETE FROM {t}")
            self._agents_cache.clear()
            self._redirects_cache.clear()
            n = len(stack.maps)
            for i, m in enumerate(stack.maps.values()):
                self._write_map(map_rows(m), merges=True)
                if progress is not None:
                    progress(i + 1, n)
            self.conn.execute(
                "INSERT OR REPLACE INTO map_state (key, value) VALUES ('next_map_id', ?)",
                (json.dumps(stack.next_map_id),),
            )
        logger.info("saved %d maps to %s in %.2f s", len(stack.maps), self.path, time.perf_counter() - t0)

    # ------------------------------------------------------------------ reads
    def map_ids(self) -> list[int]:
        ids = {r[0] for r in self.conn.execute("SELECT map_id FROM map_maps")}
        ids |= {r[0] for r in self.conn.execute("SELECT DISTINCT map_id FROM map_keyframes")}
        ids |= {r[0] for r in self.conn.execute("SELECT DISTINCT map_id FROM map_points")}
        return sorted(ids)

    def load_map(self, map_id: int) -> Map:
        """Rebuild one map from its rows (points, then keyframes in insertion order, then graphs)."""
        return read_map(self.conn, map_id)

    def load_stack(self) -> MapStack:
        """Every stored map as a ``MapStack`` (full saves and incremental writes alike)."""
        t0 = time.perf_counter()
        stack = MapStack()
        ids = self.map_ids()
        for i, mid in enumerate(ids):
            m = self.load_map(mid)
            stack.add_map(m)
            # progress of a long start-up (a large store takes tens of seconds): one line per map
            logger.info(
                "loaded map %d (%d/%d): %d keyframes, %d map points, %.1f s so far",
                mid, i + 1, len(ids), len(m.keyframes), len(m.points), time.perf_counter() - t0,
            )  # fmt: skip
        row = self.conn.execute("SELECT value FROM map_state WHERE key = 'next_map_id'").fetchone()
        if row is not None:
            stack.next_map_id = max(stack.next_map_id, int(json.loads(row[0])))
        logger.info("loaded %d maps from %s in %.2f s", len(stack.maps), self.path, time.perf_counter() - t0)
        return stack
