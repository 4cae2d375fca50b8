"""What one place-recognition query reads of each keyframe, computed once per query.

A query verifies many candidates whose windows (candidate + best covisible keyframes) overlap, and
every verification reads the query keyframe again: their point keys, which of those points are still
in the map, and the windows' points were recomputed per candidate. The cache lives for one query only,
as the event loop changes the maps between queries.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.placerec.match import _has_point, _point_keys

KfKey = tuple[str, int]
PointKey = tuple[str, int]


class HasCache:
    """ "Which keypoints reference a point of the map" per keyframe, kept across queries, with what a job's
    slice reads of it (the referencing keypoints and their point keys), and each map's keyframe order.

    Valid while the keyframe's references are unchanged (removing or fusing a point rewrites them, and a
    merge moves the keyframe to another map); references still pending (the point not yet in the map)
    are looked up again on every use, as their point may have arrived since."""

    def __init__(self) -> None:
        self._masks: dict[KfKey, _Refs] = {}
        self._arrival: dict[int, tuple[int, KfKey | None, dict[KfKey, int]]] = {}
        self._agents: dict[str, int] = {}
        self._names: list[str] = []

    def _entry(self, m: Any, kf: Any, pk: list[PointKey | None] | None = None) -> _Refs:
        stamp = hash((kf.point_ids.tobytes(), tuple(sorted(kf.point_agents.items()))))
        hit = self._masks.get(kf.key)
        if hit is not None and hit.map_id == id(m) and hit.stamp == stamp:
            has = hit.has
            arrived = [
                i for i in np.flatnonzero(~has & (kf.point_ids >= 0)).tolist() if hit.pk[i] in m.points
            ]
            if arrived:
                has[arrived] = True
                hit.idx = None
            return hit
        pk = _point_keys(kf) if pk is None else pk
        e = _Refs(id(m), stamp, pk, _has_point(pk, m.points))
        self._masks[kf.key] = e
        return e

    def get(self, m: Any, kf: Any, pk: list[PointKey | None]) -> NDArray[np.bool_]:
        return self._entry(m, kf, pk).has

    def refs(self, m: Any, kf: Any) -> tuple[NDArray[np.intp], NDArray[np.int64]]:
        """The keypoints of ``kf`` referencing a point of ``m`` and those points' keys as one integer each
        (agent and id, :meth:`decode`; equal keys, equal codes) for array work on a slice's points."""
        e = self._entry(m, kf)
        if e.idx is None:
            e.idx = np.flatnonzero(e.has)
            if e.all_codes is None:
                e.all_codes = self._codes_of(kf)
            e.codes = e.all_codes[e.idx]
        return e.idx, e.codes

    def _agent(self, a: str) -> int:
        n = self._agents.get(a)
        if n is None:
            n = self._agents[a] = len(self._agents)
            self._names.append(a)
        return n

    def _codes_of(self, kf: Any) -> NDArray[np.int64]:
        """Per keypoint the code of the point it references (its own agent's, or another agent's after a
        fusion); meaningless where it references none."""
        ids = np.asarray(kf.point_ids, dtype=np.int64)
        codes = (np.int64(self._agent(kf.agent_id)) << _ID_BITS) | ids
        for i, a in kf.point_agents.items():
            codes[i] = (self._agent(a) << _ID_BITS) | int(ids[i])
        return codes

    def decode(self, codes: NDArray[np.int64]) -> tuple[list[str], NDArray[np.int64], NDArray[np.int64]]:
        """Codes -> (the agents they name, each code's agent as an index into them, point ids)."""
        return self._names, codes >> _ID_BITS, codes & ((1 << _ID_BITS) - 1)

    def arrival(self, m: Any) -> dict[KfKey, int]:
        """Each keyframe of ``m`` -> its rank in the order the map added them (rebuilt when it changed:
        a keyframe added, or removed, or one re-added at the end)."""
        kfs = m.keyframes
        last = next(reversed(kfs), None)
        hit = self._arrival.get(id(m))
        if hit is not None and hit[0] == len(kfs) and hit[1] == last:
            return hit[2]
        order = {k: i for i, k in enumerate(kfs)}
        self._arrival[id(m)] = (len(kfs), last, order)
        return order

    def forget(self, key: KfKey) -> None:
        self._masks.pop(key, None)


_ID_BITS = 40  # point ids stay below 2**40; the agent's number goes above


class _Refs:
    __slots__ = ("map_id", "stamp", "pk", "has", "idx", "all_codes", "codes")

    def __init__(self, map_id: int, stamp: int, pk: list[PointKey | None], has: NDArray[np.bool_]) -> None:
        self.map_id, self.stamp, self.pk, self.has = map_id, stamp, pk, has
        self.idx: NDArray[np.intp] | None = None
        self.all_codes: NDArray[np.int64] | None = None
        self.codes = np.zeros(0, np.int64)


class KeyframeViews:
    """Per keyframe of one query: point keys and "has a map point" masks (``cache``: kept across
    queries, see :class:`HasCache`)."""

    def __init__(self, cache: HasCache | None = None) -> None:
        self._pk: dict[KfKey, list[PointKey | None]] = {}
        self._has: dict[KfKey, NDArray[np.bool_]] = {}
        self._cache = cache

    def point_keys(self, kf: Any) -> list[PointKey | None]:
        pk = self._pk.get(kf.key)
        if pk is None:
            pk = self._pk[kf.key] = _point_keys(kf)
        return pk

    def has(self, m: Any, kf: Any) -> NDArray[np.bool_]:
        """Which keypoints of ``kf`` (a keyframe of map ``m``) reference a point of ``m``."""
        h = self._has.get(kf.key)
        if h is None:
            pk = self.point_keys(kf)
            h = _has_point(pk, m.points) if self._cache is None else self._cache.get(m, kf, pk)
            self._has[kf.key] = h
        return h

    def window_points(self, m: Any, window_kfs: list[Any]) -> list[PointKey]:
        """The points of map ``m`` the window's keyframes observe, each once, in window order."""
        seen: dict[PointKey, None] = {}
        for w in window_kfs:
            pk = self.point_keys(w)
            for i in np.flatnonzero(self.has(m, w)).tolist():
                seen.setdefault(pk[i], None)  # type: ignore[arg-type]
        return list(seen)
