"""Levels of detail of a map's point cloud, for viewers that draw millions of points progressively.

Each point belongs to one of ``parts`` parts by a hash of its key (agent id, point id): every part is an
even random subsample of the map, the parts are disjoint and together hold every point, and a point
stays in its part while the map grows (the hash depends on nothing else). A viewer fetches part 0, draws
it, fetches part 1, ... so the whole map is on screen at 1/parts density after the first request.

The map's point list and key hashes are computed once and reused while its keyframe and point counts stay
the same (the cheap change detector ``hivemap.server.foxglove`` uses too); a part's positions are read
when it is asked for.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

U64 = NDArray[np.uint64]


@dataclass(frozen=True)
class Cloud:
    """A map's points at one moment (the point objects, so positions are read when a part is asked for)
    and each point's 64-bit key hash."""

    version: tuple[int, int]
    points: list[Any]
    hash: U64


def _mix(x: U64) -> U64:
    """splitmix64's finaliser: a well-spread 64-bit hash of each value."""
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def key_hash(agent_ids: list[str], ids: NDArray[np.int64]) -> U64:
    """The hash of each point key ``(agent_ids[i], ids[i])`` (CRC-32 of the agent id in the high bits)."""
    crc = {a: zlib.crc32(a.encode()) for a in set(agent_ids)}
    agent = np.fromiter((crc[a] for a in agent_ids), np.uint64, len(agent_ids))
    return _mix((agent << np.uint64(32)) ^ ids.astype(np.uint64))


async def cloud(m: Any, cache: dict[int, Cloud], live: set[int]) -> Cloud:
    """The map's :class:`Cloud`, from ``cache`` when the map's counts did not change. Called on the event
    loop (the maps' thread): the point list is copied there, the hashes are computed in a worker thread so
    ingest goes on meanwhile. Entries of maps not in ``live`` (merged away) are dropped."""
    import asyncio

    version = (len(m.keyframes), len(m.points))
    c = cache.get(m.id)
    if c is not None and c.version == version:
        return c
    pts = list(m.points.values())
    c = await asyncio.to_thread(_build, version, pts)
    for k in [k for k in cache if k not in live]:
        del cache[k]
    cache[m.id] = c
    return c


def _build(version: tuple[int, int], pts: list[Any]) -> Cloud:
    ids = np.fromiter((p.id for p in pts), np.int64, len(pts))
    return Cloud(version, pts, key_hash([p.agent_id for p in pts], ids))


async def part(c: Cloud, index: int, parts: int) -> NDArray[np.float32]:
    """The positions (float32) of part ``index`` of ``parts`` (see the module docstring), read in a worker
    thread: a part costs in proportion to its size, so the first, coarse one comes quickly."""
    import asyncio

    if not 0 <= index < parts:
        raise ValueError(f"part {index} is not in 0..{parts - 1}")
    idx = np.flatnonzero(c.hash % np.uint64(parts) == np.uint64(index))

    def gather() -> NDArray[np.float32]:
        if not len(idx):
            return np.zeros((0, 3), np.float32)
        pts = c.points
        return np.concatenate([pts[i].xyz for i in idx.tolist()]).reshape(-1, 3).astype(np.float32)

    return await asyncio.to_thread(gather)


def ply_float(xyz: NDArray[np.float32], comment: str) -> Iterator[bytes]:
    """Binary little-endian PLY with ``float x, y, z`` per vertex."""
    yield (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {comment}\n"
        f"element vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode("ascii")
    yield np.ascontiguousarray(xyz, dtype="<f4").tobytes()
