"""Map point positions in blocks: one row of ``map_point_xyz`` holds the positions of up to
:data:`BLOCK` points of one agent with consecutive ids.

Why: after every optimisation the server writes every point's new position. SQLite writes whole pages,
so an update of one row per point rewrote about one 4 kB page per point; a block row is one page for
:data:`BLOCK` points, and the points an agent's local BA moves (its newest ids) share a few blocks.

A point's position is its block slot when the slot is set, else the ``xyz`` of its ``map_points`` row (as
inserted, or as written whole by ``save_map``). Every position written after the row's insertion goes to the
block, so a slot is always the newer of the two. A point's row still decides whether it exists: a slot of a
deleted point is never read (and a point put again sets its slot again).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from operator import attrgetter

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.elements import positions
from hivemap.maps.model import MapPoint

BLOCK = 128  # points per row: 128 x 24 bytes + a 128-byte mask fit one 4 kB page
_SHIFT = BLOCK.bit_length() - 1
_XYZ_BYTES = BLOCK * 3 * 8

Block = tuple[NDArray[np.uint8], NDArray[np.float64]]  # (slot set?, positions)
_ID = attrgetter("id")
_AGENT = attrgetter("agent_id")


def _decode(data: bytes) -> Block:
    mask = np.frombuffer(data, dtype=np.uint8, count=BLOCK).copy()
    xyz = np.frombuffer(data, dtype="<f8", offset=BLOCK).reshape(BLOCK, 3).astype(np.float64)
    return mask, xyz


def _empty() -> Block:
    return np.zeros(BLOCK, dtype=np.uint8), np.zeros((BLOCK, 3))


def _encode(block: Block) -> bytes:
    mask, xyz = block
    return mask.tobytes() + np.ascontiguousarray(xyz, dtype="<f8").tobytes()


def put_positions(conn: sqlite3.Connection, map_id: int, points: Iterable[MapPoint]) -> int:
    """Write the current ``xyz`` of ``points`` (of map ``map_id``) into their blocks, reading each block
    once and writing it once; returns the number of blocks written. Runs in the caller's transaction."""
    pts = list(points)
    if not pts:
        return 0
    agents = list(map(_AGENT, pts))
    codes = {a: i for i, a in enumerate(dict.fromkeys(agents))}
    agent_of = np.fromiter(map(codes.__getitem__, agents), dtype=np.int64, count=len(pts))
    xyz_all = positions(pts)
    ids_all = np.fromiter(map(_ID, pts), dtype=np.int64, count=len(pts))
    rows = []
    for agent, code in codes.items():
        idx = np.flatnonzero(agent_of == code)
        ids = ids_all[idx]
        order = np.argsort(ids >> _SHIFT, kind="stable")  # a later duplicate of a point wins, as one by one
        idx, ids = idx[order], ids[order]
        blocks, starts = np.unique(ids >> _SHIFT, return_index=True)
        # the agent's blocks in the range this write touches, in one query (an optimisation's write
        # touches all of them, and a query per block was most of its time)
        sql = "SELECT block, data FROM map_point_xyz WHERE map_id = ? AND agent = ? AND block BETWEEN ? AND ?"
        stored = dict(conn.execute(sql, (map_id, agent, int(blocks[0]), int(blocks[-1]))).fetchall())
        for block, lo, hi in zip(blocks.tolist(), starts, [*starts[1:], len(ids)], strict=True):
            data = stored.get(block)
            mask, xyz = _decode(data) if data is not None else _empty()
            slots = ids[lo:hi] & (BLOCK - 1)
            xyz[slots] = xyz_all[idx[lo:hi]]
            mask[slots] = 1
            rows.append((map_id, agent, block, _encode((mask, xyz))))
    conn.executemany("INSERT OR REPLACE INTO map_point_xyz (map_id, agent, block, data) VALUES (?, ?, ?, ?)",
                     rows)  # fmt: skip
    return len(rows)


def read_positions(conn: sqlite3.Connection, map_id: int) -> dict[tuple[str, int], Block]:
    """Every block of map ``map_id``, by (agent, block number)."""
    return {
        (agent, int(block)): _decode(data)
        for agent, block, data in conn.execute(
            "SELECT agent, block, data FROM map_point_xyz WHERE map_id = ?", (map_id,)
        )
    }


def position(
    blocks: dict[tuple[str, int], Block], agent: str, pid: int, row_xyz: bytes
) -> NDArray[np.float64]:
    """A point's stored position: its block slot if set, else its row's ``xyz``."""
    b = blocks.get((agent, pid >> _SHIFT))
    if b is not None and b[0][pid & (BLOCK - 1)]:
        return b[1][pid & (BLOCK - 1)].copy()
    return np.frombuffer(row_xyz, dtype="<f8").astype(np.float64)
