"""The map model shared by agents and server: ``Keyframe``, ``MapPoint``, ``Map`` and ``MapStack``.

Keys: a keyframe or a map point is named by ``(agent_id, id)`` (``KfKey`` / ``PointKey``); ids are unique
per agent. The server folds an agent's map session into the agent id when needed (e.g. ``"uav1#1"``).

Source of truth for observations: each keyframe's per-keypoint point reference
(``Keyframe.point_ids`` + the owning agent of each referenced point). ``MapPoint.observations`` is the
inverse index (keyframe key -> keypoint index) kept by the ``Map``; it only holds *linked* observations,
i.e. those whose keyframe and point are both in the map. A keyframe may reference a point that has not
arrived yet (pending); the reference is linked as soon as the point is added.

Graphs (ORB-SLAM style), all maintained incrementally:
- covisibility: ``dict[KfKey, dict[KfKey, int]]``, weight = number of map points both keyframes observe;
- spanning tree (a forest in general): each keyframe's ``parent`` is the keyframe it shared most points
  with when it was inserted; re-parented on keyframe removal; source trees are attached on merges;
- loop edges (``add_loop_edge``);
- essential graph = spanning tree + strong covisibility (weight >= ``STRONG_COVISIBILITY``) + loop edges.

Fusing points (``fuse_points(keep, drop)``) moves every observation of ``drop`` to ``keep`` (a keyframe
that already observes ``keep`` loses its ``drop`` keypoint reference) and records ``drop -> keep`` in
``point_redirects`` so late references to ``drop`` (e.g. a keyframe an agent sends after a merge) resolve
to ``keep``.

Not thread-safe: callers serialise access (e.g. one asyncio task or a lock).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, se3_inverse

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]

#: Covisibility weight from which an edge belongs to the essential graph (ORB-SLAM uses 100).
STRONG_COVISIBILITY = 100


def _key(k: Sequence[Any]) -> tuple[str, int]:
    return (str(k[0]), int(k[1]))


class MapPoint:
    """A 3D landmark.

    ``xyz``: f64 (3,) position in the map's frame; ``descriptor``: u8 (32,) representative ORB descriptor;
    ``observations``: keyframe key -> keypoint index (maintained by the ``Map`` once the point is in one).
    """

    __slots__ = ("agent_id", "id", "xyz", "descriptor", "observations")

    def __init__(
        self,
        agent_id: str,
        id: int,
        xyz: ArrayLike,
        descriptor: ArrayLike | None = None,
        observations: dict[KfKey, int] | None = None,
    ) -> None:
        self.agent_id = str(agent_id)
        self.id = int(id)
        self.xyz: F64 = np.array(xyz, dtype=np.float64).reshape(3)
        d = np.zeros(32, np.uint8) if descriptor is None else np.array(descriptor, dtype=np.uint8)
        if d.shape != (32,):
            raise ValueError(f"MapPoint descriptor must have shape (32,), got {d.shape}")
        self.descriptor: NDArray[np.uint8] = d
        self.observations: dict[KfKey, int] = {_key(k): int(v) for k, v in (observations or {}).items()}

    @property
    def key(self) -> PointKey:
        return (self.agent_id, self.id)

    def __repr__(self) -> str:
        n_obs = len(self.observations)
        return f"MapPoint({self.agent_id!r}, {self.id}, xyz={self.xyz.tolist()}, obs={n_obs})"


class Keyframe:
    """A keyframe: pose, camera, ORB features and the map point referenced by each keypoint.

    Arrays: ``world_from_cam`` f64 (4, 4); ``keypoints`` f32 (N, 2) distorted pixels; ``octaves`` u8 (N,);
    ``descriptors`` u8 (N, 32); ``point_ids`` i64 (N,) (-1 = no point); ``gnss_enu`` f64 (3,) or None;
    ``gnss_cov`` f64 (3, 3) or None; ``up_cam`` f64 (3,) or None (the agent's IMU up direction in the
    camera frame).

    Point references: keypoint ``i`` references point ``(agent, point_ids[i])`` where ``agent`` is
    ``point_agents.get(i, agent_id)`` (``point_agents`` only lists keypoints that reference another agent's
    point, which happens after fusions). Either pass ``point_ids`` (points of this agent) or ``point_keys``
    (a per-keypoint list of ``(agent, id)`` or None). Inside a ``Map`` change references only through the
    map (``add_observation``, ``remove_observation``, ``fuse_points``) so its indices stay consistent.

    ``parent`` is the spanning-tree parent, maintained by the ``Map`` (None for a root).
    """

    __slots__ = (
        "agent_id",
        "id",
        "timestamp",
        "world_from_cam",
        "camera",
        "keypoints",
        "octaves",
        "descriptors",
        "point_ids",
        "point_agents",
        "gnss_enu",
        "gnss_cov",
        "up_cam",
        "parent",
    )

    def __init__(
        self,
        agent_id: str,
        id: int,
        timestamp: float,
        world_from_cam: ArrayLike,
        camera: PinholeCamera,
        keypoints: ArrayLike,
        octaves: ArrayLike | None = None,
        descriptors: ArrayLike | None = None,
        point_ids: ArrayLike | None = None,
        gnss_enu: ArrayLike | None = None,
        gnss_cov: ArrayLike | None = None,
        *,
        point_keys: Sequence[PointKey | None] | None = None,
        up_cam: ArrayLike | None = None,
    ) -> None:
        self.agent_id = str(agent_id)
        self.id = int(id)
        self.timestamp = float(timestamp)
        self.world_from_cam: F64 = np.array(world_from_cam, dtype=np.float64).reshape(4, 4)
        self.camera = camera
        kp = np.ascontiguousarray(keypoints, dtype=np.float32)
        if kp.size == 0:
            kp = kp.reshape(0, 2)
        if kp.ndim != 2 or kp.shape[1] != 2:
            raise ValueError(f"keypoints must have shape (N, 2), got {kp.shape}")
        n = len(kp)
        self.keypoints: NDArray[np.float32] = kp
        self.octaves: NDArray[np.uint8] = (
            np.zeros(n, np.uint8) if octaves is None else np.ascontiguousarray(octaves, dtype=np.uint8)
        )
        self.descriptors: NDArray[np.uint8] = (
            np.zeros((n, 32), np.uint8)
            if descriptors is None
            else np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, 32)
        )
        if self.octaves.shape != (n,) or self.descriptors.shape != (n, 32):
            raise ValueError(
                f"octaves {self.octaves.shape} / descriptors {self.descriptors.shape} "
                f"do not match {n} keypoints"
            )
        self.point_agents: dict[int, str] = {}
        if point_keys is not None:
            if point_ids is not None:
                raise ValueError("pass point_ids or point_keys, not both")
            if len(point_keys) != n:
                raise ValueError(f"point_keys has {len(point_keys)} entries for {n} keypoints")
            self.point_ids: NDArray[np.int64] = np.full(n, -1, np.int64)
            for i, pk in enumerate(point_keys):
                if pk is not None:
                    self.set_point_key(i, _key(pk))
        elif point_ids is None:
            self.point_ids = np.full(n, -1, np.int64)
        else:
            # always a private, writable copy (protocol arrays are read-only)
            self.point_ids = np.array(point_ids, dtype=np.int64).reshape(-1)
            if self.point_ids.shape != (n,):
                raise ValueError(f"point_ids {self.point_ids.shape} does not match {n} keypoints")
        self.gnss_enu: F64 | None = None if gnss_enu is None else np.array(gnss_enu, np.float64).reshape(3)
        self.gnss_cov: F64 | None = None if gnss_cov is None else np.array(gnss_cov, np.float64).reshape(3, 3)
        # up direction (unit, against gravity) in the camera frame as the agent's IMU measured it
        self.up_cam: F64 | None = None if up_cam is None else np.array(up_cam, np.float64).reshape(3)
        self.parent: KfKey | None = None

    @property
    def key(self) -> KfKey:
        return (self.agent_id, self.id)

    @property
    def n_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def cam_from_world(self) -> F64:
        return se3_inverse(self.world_from_cam)

    @property
    def center(self) -> F64:
        """Camera centre in the world frame (3,)."""
        return self.world_from_cam[:3, 3].copy()

    def point_key(self, i: int) -> PointKey | None:
        pid = int(self.point_ids[i])
        if pid < 0:
            return None
        return (self.point_agents.get(i, self.agent_id), pid)

    def set_point_key(self, i: int, key: PointKey | None) -> None:
        """Low-level: set keypoint ``i``'s reference. Inside a Map use the Map's methods instead."""
        if key is None:
            self.point_ids[i] = -1
            self.point_agents.pop(i, None)
            return
        agent, pid = key
        if pid < 0:
            raise ValueError(f"point id must be >= 0, got {pid}")
        self.point_ids[i] = pid
        if agent == self.agent_id:
            self.point_agents.pop(i, None)
        else:
            self.point_agents[i] = agent

    @property
    def point_keys(self) -> list[PointKey | None]:
        """Per keypoint: the referenced point key or None (a fresh list; editing it changes nothing)."""
        return [self.point_key(i) for i in range(self.n_keypoints)]

    def referenced_points(self) -> Iterator[tuple[int, PointKey]]:
        """(keypoint index, point key) for every keypoint that references a point."""
        for i in np.flatnonzero(self.point_ids >= 0).tolist():
            yield i, (self.point_agents.get(i, self.agent_id), int(self.point_ids[i]))

    def __repr__(self) -> str:
        n_ref = int((self.point_ids >= 0).sum())
        return (
            f"Keyframe({self.agent_id!r}, {self.id}, t={self.timestamp}, kps={self.n_keypoints}"
            f", refs={n_ref})"
        )


class Map:
    """One map: keyframes, map points, and their covisibility / spanning-tree / loop graphs."""

    def __init__(self, id: int) -> None:
        self.id = int(id)
        self.keyframes: dict[KfKey, Keyframe] = {}
        self.points: dict[PointKey, MapPoint] = {}
        self.agents: set[str] = set()
        self.merge_history: list[dict[str, Any]] = []
        #: fused (dropped) point key -> the key that absorbed it
        self.point_redirects: dict[PointKey, PointKey] = {}
        self._covis: dict[KfKey, dict[KfKey, int]] = {}
        self._children: dict[KfKey, set[KfKey]] = {}
        self._loops: dict[KfKey, set[KfKey]] = {}
        # point key -> {keyframe key: keypoint index} for references to points not in the map yet
        self._pending: dict[PointKey, dict[KfKey, int]] = {}
        # keyframes inserted without any covisible keyframe while the map was not empty: attached to the
        # tree by their first covisibility link
        self._orphans: set[KfKey] = set()
        # keyframes whose spanning-tree parent changed since the last ``drain_tree_changes`` (persistence)
        self._tree_changed: set[KfKey] = set()

    def __repr__(self) -> str:
        return (
            f"Map(id={self.id}, keyframes={len(self.keyframes)}, points={len(self.points)}, "
            f"agents={sorted(self.agents)})"
        )

    # ------------------------------------------------------------------ covisibility internals
    def _inc(self, a: KfKey, b: KfKey) -> None:
        ca, cb = self._covis[a], self._covis[b]
        w = ca.get(b, 0) + 1
        ca[b] = w
        cb[a] = w
        if w == 1 and self._orphans:
            if a in self._orphans:
                self._attach_orphan(a, b)
            elif b in self._orphans:
                self._attach_orphan(b, a)

    def _dec(self, a: KfKey, b: KfKey) -> None:
        ca, cb = self._covis[a], self._covis[b]
        w = ca[b] - 1
        if w:
            ca[b] = w
            cb[a] = w
        else:
            del ca[b]
            del cb[a]

    def _link(self, kf: Keyframe, idx: int, mp: MapPoint) -> None:
        """Keypoint ``idx`` of ``kf`` observes ``mp`` (``mp`` not yet observed by ``kf``)."""
        key = kf.key
        for other in mp.observations:
            self._inc(key, other)
        mp.observations[key] = idx
        kf.set_point_key(idx, mp.key)

    def _unlink(self, kf: Keyframe, mp: MapPoint) -> int:
        key = kf.key
        idx = mp.observations.pop(key)
        for other in mp.observations:
            self._dec(key, other)
        kf.set_point_key(idx, None)
        return idx

    # ------------------------------------------------------------------ spanning tree internals
    def _root_of(self, key: KfKey) -> KfKey:
        seen = 0
        while True:
            p = self.keyframes[key].parent
            if p is None:
                return key
            key = p
            seen += 1
            if seen > len(self.keyframes):  # pragma: no cover - guarded by set_parent
                raise RuntimeError("cycle in the spanning tree")

    def _set_parent_unchecked(self, child: KfKey, parent: KfKey | None) -> None:
        kf = self.keyframes[child]
        if kf.parent is not None:
            self._children[kf.parent].discard(child)
        kf.parent = parent
        if parent is not None:
            self._children[parent].add(child)
        self._tree_changed.add(child)

    def _attach_orphan(self, orphan: KfKey, other: KfKey) -> None:
        if self._root_of(other) != orphan:
            self._orphans.discard(orphan)
            self._set_parent_unchecked(orphan, other)

    def _reroot(self, key: KfKey) -> None:
        """Make ``key`` the root of its tree by reversing the path to the current root."""
        path = [key]
        while (p := self.keyframes[path[-1]].parent) is not None:
            path.append(p)
        for i in range(len(path) - 1, 0, -1):
            self._set_parent_unchecked(path[i], path[i - 1])
        self._set_parent_unchecked(key, None)

    # ------------------------------------------------------------------ insertion
    def add_point(self, mp: MapPoint) -> MapPoint:
        """Insert a point. Links its observations of keyframes in the map (others are dropped) and every
        pending keyframe reference to its key. Raises ``ValueError`` if the key is already present."""
        key = mp.key
        if key in self.points:
            raise ValueError(f"point {key} already in map {self.id}")
        if key in self.point_redirects:
            logger.debug("point %s was fused into %s and is re-added", key, self.point_redirects[key])
            del self.point_redirects[key]
        wanted = dict(mp.observations)
        wanted.update(self._pending.pop(key, {}))
        mp.observations = {}
        self.points[key] = mp
        self.agents.add(mp.agent_id)
        for kf_key, idx in wanted.items():
            kf = self.keyframes.get(kf_key)
            if kf is None:
                logger.debug("point %s: observation by unknown keyframe %s dropped", key, kf_key)
                continue
            if kf_key in mp.observations:  # already linked at another keypoint
                if mp.observations[kf_key] != idx and kf.point_key(idx) == key:
                    kf.set_point_key(idx, None)
                continue
            self._free_slot(kf, idx)
            self._link(kf, idx, mp)
        return mp

    def _free_slot(self, kf: Keyframe, idx: int) -> None:
        """Drop whatever keypoint ``idx`` of ``kf`` references (linked or pending)."""
        old = kf.point_key(idx)
        if old is None:
            return
        old_mp = self.points.get(old)
        if old_mp is not None and old_mp.observations.get(kf.key) == idx:
            self._unlink(kf, old_mp)
        else:
            pend = self._pending.get(old)
            if pend is not None and pend.get(kf.key) == idx:
                del pend[kf.key]
                if not pend:
                    del self._pending[old]
            kf.set_point_key(idx, None)

    def add_keyframe(self, kf: Keyframe) -> Keyframe:
        """Insert a keyframe: link its point references (resolving fused keys; references to points not
        in the map stay pending), update covisibility and choose its spanning-tree parent (the keyframe it
        shares most points with). A second reference to the same point within ``kf`` is cleared."""
        key = kf.key
        if key in self.keyframes:
            raise ValueError(f"keyframe {key} already in map {self.id}")
        was_empty = not self.keyframes
        self.keyframes[key] = kf
        self._covis[key] = {}
        self._children[key] = set()
        self.agents.add(kf.agent_id)
        kf.parent = None
        for idx, pk in list(kf.referenced_points()):
            pk2 = self.resolve_point(pk)
            if pk2 != pk:
                kf.set_point_key(idx, pk2)
            mp = self.points.get(pk2)
            if mp is None:
                pend = self._pending.setdefault(pk2, {})
                if key in pend:
                    kf.set_point_key(idx, None)
                else:
                    pend[key] = idx
            elif key in mp.observations:
                kf.set_point_key(idx, None)
            else:
                self._link(kf, idx, mp)
        cov = self._covis[key]
        if cov:
            best = max(cov.items(), key=lambda kv: kv[1])[0]
            self._set_parent_unchecked(key, best)
        elif not was_empty:
            self._orphans.add(key)
        return kf

    # ------------------------------------------------------------------ observations
    def add_observation(self, point_key: PointKey, kf_key: KfKey, idx: int) -> None:
        """Keypoint ``idx`` of keyframe ``kf_key`` observes point ``point_key`` (replacing what that
        keypoint referenced; if the keyframe already observes the point elsewhere, that is moved)."""
        pk = self.resolve_point(_key(point_key))
        mp = self.points[pk]
        kf = self.keyframes[_key(kf_key)]
        if kf.key in mp.observations:
            if mp.observations[kf.key] == idx:
                return
            self._unlink(kf, mp)
        self._free_slot(kf, int(idx))
        self._link(kf, int(idx), mp)

    def remove_observation(self, point_key: PointKey, kf_key: KfKey) -> None:
        """Keyframe ``kf_key`` no longer observes point ``point_key`` (its keypoint becomes unmatched)."""
        mp = self.points[self.resolve_point(_key(point_key))]
        self._unlink(self.keyframes[_key(kf_key)], mp)

    # ------------------------------------------------------------------ removal / fusion
    def remove_point(self, key: PointKey) -> MapPoint:
        """Remove a point; keyframes observing it lose the reference."""
        key = _key(key)
        mp = self.points[key]
        for kf_key in list(mp.observations):
            self._unlink(self.keyframes[kf_key], mp)
        del self.points[key]
        return mp

    def remove_keyframe(self, key: KfKey) -> Keyframe:
        """Remove a keyframe: its observations, covisibility and loop edges go; its children in the
        spanning tree are re-parented (ORB-SLAM's rule: repeatedly attach the child with the strongest
        covisibility to an already attached node; the rest go to the removed keyframe's parent)."""
        key = _key(key)
        kf = self.keyframes[key]
        for nb in list(self._covis[key]):
            del self._covis[nb][key]
        del self._covis[key]
        for _idx, pk in kf.referenced_points():
            mp = self.points.get(pk)
            if mp is not None and mp.observations.get(key) is not None:
                del mp.observations[key]
            else:
                pend = self._pending.get(pk)
                if pend is not None:
                    pend.pop(key, None)
                    if not pend:
                        del self._pending[pk]
        for other in self._loops.pop(key, set()):
            self._loops[other].discard(key)
            if not self._loops[other]:
                del self._loops[other]
        self._orphans.discard(key)
        # spanning tree
        parent = kf.parent
        children = set(self._children[key])
        for c in children:
            self._set_parent_unchecked(c, None)
        self._set_parent_unchecked(key, None)
        del self._children[key]
        del self.keyframes[key]
        candidates: set[KfKey] = set() if parent is None else {parent}
        if parent is None and children:
            # the removed keyframe was a root: its best-connected child becomes the new root
            root = max(sorted(children), key=lambda c: len(self._covis[c]))
            children.discard(root)
            candidates.add(root)
        while children:
            best: tuple[int, KfKey, KfKey] | None = None
            for c in sorted(children):
                for nb, w in self._covis[c].items():
                    if nb in candidates and (best is None or w > best[0]):
                        best = (w, c, nb)
            if best is None:
                break
            _, c, nb = best
            self._set_parent_unchecked(c, nb)
            candidates.add(c)
            children.discard(c)
        fallback = parent if parent is not None else (next(iter(candidates)) if candidates else None)
        for c in children:
            self._set_parent_unchecked(c, fallback)
        return kf

    def resolve_point(self, key: PointKey) -> PointKey:
        """Follow fusion redirects: the key that now stands for ``key`` (``key`` itself if not fused)."""
        key = _key(key)
        if key not in self.point_redirects:
            return key
        path = []
        while key in self.point_redirects:
            path.append(key)
            key = self.point_redirects[key]
            if len(path) > len(self.point_redirects):  # pragma: no cover
                raise RuntimeError("cycle in point redirects")
        for k in path[:-1]:
            self.point_redirects[k] = key
        return key

    def fuse_points(self, keep: PointKey, drop: PointKey) -> PointKey:
        """Fuse duplicate point ``drop`` into ``keep``: ``keep`` inherits every observation of ``drop``
        (a keyframe observing both keeps only its ``keep`` keypoint), ``drop`` leaves the map and its key
        redirects to ``keep``. Keys are resolved through earlier fusions first. Returns the surviving key."""
        keep, drop = self.resolve_point(keep), self.resolve_point(drop)
        if keep == drop:
            return keep
        mk, md = self.points[keep], self.points[drop]
        for kf_key in list(md.observations):
            kf = self.keyframes[kf_key]
            idx = self._unlink(kf, md)
            if kf_key not in mk.observations:
                self._link(kf, idx, mk)
        del self.points[drop]
        self.point_redirects[drop] = keep
        return keep

    # ------------------------------------------------------------------ graph queries
    def covisibility(self, key: KfKey) -> dict[KfKey, int]:
        """Covisible keyframes of ``key`` -> number of shared map points (a copy)."""
        return dict(self._covis[_key(key)])

    def best_covisible(self, key: KfKey, n: int) -> list[KfKey]:
        """The ``n`` keyframes sharing most points with ``key`` (weight descending, then key)."""
        items = sorted(self._covis[_key(key)].items(), key=lambda kv: (-kv[1], kv[0]))
        return [k for k, _ in items[: max(int(n), 0)]]

    def covisible_min_weight(self, key: KfKey, min_weight: int) -> list[KfKey]:
        """Keyframes sharing at least ``min_weight`` points with ``key`` (weight descending)."""
        items = sorted(self._covis[_key(key)].items(), key=lambda kv: (-kv[1], kv[0]))
        return [k for k, w in items if w >= min_weight]

    def parent(self, key: KfKey) -> KfKey | None:
        return self.keyframes[_key(key)].parent

    def children(self, key: KfKey) -> set[KfKey]:
        return set(self._children[_key(key)])

    def set_parent(self, child: KfKey, parent: KfKey | None) -> None:
        """Set a spanning-tree edge by hand (raises ``ValueError`` if it would create a cycle)."""
        child = _key(child)
        if parent is not None:
            parent = _key(parent)
            if parent not in self.keyframes:
                raise KeyError(parent)
            k: KfKey | None = parent
            while k is not None:
                if k == child:
                    raise ValueError(f"{parent} is in the subtree of {child}: cycle")
                k = self.keyframes[k].parent
        self._orphans.discard(child)
        self._set_parent_unchecked(child, parent)

    def _restore_tree(self, parents: dict[KfKey, KfKey | None], orphans: set[KfKey]) -> None:
        """Set every keyframe's parent as stored (persistence); unknown keys are ignored."""
        for k in self._children:
            self._children[k] = set()
        for k, kf in self.keyframes.items():
            p = parents.get(k)
            kf.parent = p if p in self.keyframes else None
            if kf.parent is not None:
                self._children[kf.parent].add(k)
        self._orphans = {k for k in orphans if k in self.keyframes}
        self._tree_changed = set()

    def drain_tree_changes(self) -> set[KfKey]:
        """Keyframes whose ``parent`` changed since the last call (still in the map), then forget them."""
        out = {k for k in self._tree_changed if k in self.keyframes}
        self._tree_changed = set()
        return out

    @property
    def orphans(self) -> set[KfKey]:
        """Keyframes inserted without covisible keyframes, waiting for their first link to join the tree."""
        return set(self._orphans)

    def add_loop_edge(self, a: KfKey, b: KfKey) -> None:
        a, b = _key(a), _key(b)
        if a == b:
            raise ValueError("a loop edge needs two different keyframes")
        if a not in self.keyframes or b not in self.keyframes:
            raise KeyError(f"loop edge {a} - {b}: keyframe not in map {self.id}")
        self._loops.setdefault(a, set()).add(b)
        self._loops.setdefault(b, set()).add(a)

    def loop_neighbours(self, key: KfKey) -> set[KfKey]:
        return set(self._loops.get(_key(key), ()))

    def spanning_tree_edges(self) -> list[tuple[KfKey, KfKey]]:
        """(parent, child) for every non-root keyframe."""
        return [(kf.parent, k) for k, kf in self.keyframes.items() if kf.parent is not None]

    def loop_edges(self) -> list[tuple[KfKey, KfKey]]:
        """Loop edges as ordered pairs ``(a, b)`` with ``a < b``."""
        return sorted((a, b) for a, bs in self._loops.items() for b in bs if a < b)

    def strong_covisibility_edges(
        self, min_weight: int = STRONG_COVISIBILITY
    ) -> list[tuple[KfKey, KfKey, int]]:
        """Covisibility edges ``(a, b, weight)`` with ``a < b`` and weight >= ``min_weight``."""
        return [
            (a, b, w) for a, nbs in self._covis.items() for b, w in nbs.items() if a < b and w >= min_weight
        ]

    def essential_edges(self, min_weight: int = STRONG_COVISIBILITY) -> list[tuple[KfKey, KfKey]]:
        """Essential graph: spanning tree + strong covisibility (weight >= ``min_weight``) + loop edges,
        as sorted unique pairs ``(a, b)`` with ``a < b``. Typed parts: ``spanning_tree_edges()``,
        ``strong_covisibility_edges()``, ``loop_edges()``."""
        edges: set[tuple[KfKey, KfKey]] = set()
        for p, c in self.spanning_tree_edges():
            edges.add((p, c) if p < c else (c, p))
        for a, b, _ in self.strong_covisibility_edges(min_weight):
            edges.add((a, b))
        edges.update(self.loop_edges())
        return sorted(edges)

    # ------------------------------------------------------------------ geometry
    def transform(self, sim: Sim3) -> None:
        """Move every keyframe (``Sim3.transform_pose``) and every point (``Sim3.apply``) by ``sim``."""
        for kf in self.keyframes.values():
            # (GNSS fixes are measurements in the ENU frame: they do not move with the map)
            kf.world_from_cam = sim.transform_pose(kf.world_from_cam)
        if self.points:
            pts = list(self.points.values())
            xyz = sim.apply(np.stack([p.xyz for p in pts]))
            for p, x in zip(pts, xyz, strict=True):
                p.xyz = x.copy()

    def points_xyz(self, keys: Iterable[PointKey] | None = None) -> tuple[list[PointKey], F64]:
        """(keys, xyz (M, 3)) of the given points (default: all)."""
        ks = list(self.points) if keys is None else [_key(k) for k in keys]
        if not ks:
            return ks, np.zeros((0, 3))
        return ks, np.stack([self.points[k].xyz for k in ks])

    def keyframes_of_agent(self, agent_id: str) -> list[Keyframe]:
        return [kf for kf in self.keyframes.values() if kf.agent_id == agent_id]

    def pending_references(self) -> dict[PointKey, dict[KfKey, int]]:
        """Keyframe references to points not (yet) in the map: point key -> {keyframe: keypoint index}."""
        return {k: dict(v) for k, v in self._pending.items()}

    # ------------------------------------------------------------------ checks
    def check_consistency(self) -> list[str]:
        """Brute-force check of every invariant (slow: tests and debugging). Returns the problems found."""
        problems: list[str] = []
        expected: dict[KfKey, dict[KfKey, int]] = {k: {} for k in self.keyframes}
        for pk, mp in self.points.items():
            for kf_key, idx in mp.observations.items():
                kf = self.keyframes.get(kf_key)
                if kf is None:
                    problems.append(f"point {pk} observed by missing keyframe {kf_key}")
                elif kf.point_key(idx) != pk:
                    problems.append(f"point {pk}: keyframe {kf_key}[{idx}] references {kf.point_key(idx)}")
            obs = sorted(mp.observations)
            for i, a in enumerate(obs):
                for b in obs[i + 1 :]:
                    expected[a][b] = expected[a].get(b, 0) + 1
                    expected[b][a] = expected[b].get(a, 0) + 1
        for k, kf in self.keyframes.items():
            seen: set[PointKey] = set()
            for idx, pk in kf.referenced_points():
                if pk in seen:
                    problems.append(f"keyframe {k} references {pk} twice")
                seen.add(pk)
                mp2 = self.points.get(pk)
                if mp2 is None:
                    if self._pending.get(pk, {}).get(k) != idx:
                        problems.append(f"keyframe {k}[{idx}] references missing point {pk} not pending")
                elif mp2.observations.get(k) != idx:
                    problems.append(f"keyframe {k}[{idx}] -> {pk} not in the point's observations")
            bad_parent = kf.parent not in self.keyframes or k not in self._children[kf.parent]
            if kf.parent is not None and bad_parent:
                problems.append(f"keyframe {k}: bad parent {kf.parent}")
        if self._covis != expected:
            problems.append("covisibility differs from a brute-force recount")
        for p, cs in self._children.items():
            for c in cs:
                if self.keyframes[c].parent != p:
                    problems.append(f"children index: {c} listed under {p}")
        for k in self.keyframes:  # acyclic
            try:
                self._root_of(k)
            except RuntimeError:
                problems.append(f"cycle through {k}")
                break
        return problems


class MapStack:
    """All maps of a session (the server holds one per agent until they merge)."""

    def __init__(self) -> None:
        self.maps: dict[int, Map] = {}
        self.next_map_id = 0

    def __repr__(self) -> str:
        return f"MapStack({list(self.maps.values())})"

    def new_map(self, map_id: int | None = None) -> Map:
        """A new empty map (next free id unless ``map_id`` is given)."""
        mid = self.next_map_id if map_id is None else int(map_id)
        if mid in self.maps:
            raise ValueError(f"map {mid} already exists")
        m = Map(mid)
        self.maps[mid] = m
        self.next_map_id = max(self.next_map_id, mid + 1)
        return m

    def add_map(self, m: Map) -> Map:
        if m.id in self.maps:
            raise ValueError(f"map {m.id} already exists")
        self.maps[m.id] = m
        self.next_map_id = max(self.next_map_id, m.id + 1)
        return m

    def remove_map(self, map_id: int) -> Map:
        return self.maps.pop(int(map_id))

    def map_of_agent(self, agent_id: str) -> Map | None:
        for m in self.maps.values():
            if agent_id in m.agents:
                return m
        return None

    def merge(
        self,
        target_id: int,
        source_id: int,
        target_from_source: Sim3,
        fused_pairs: Sequence[tuple[PointKey, PointKey]] = (),
    ) -> Map:
        """Merge map ``source_id`` into map ``target_id``; the source leaves the stack.

        Every source keyframe pose is moved with ``target_from_source.transform_pose`` and every source
        point with ``.apply``; then each ``(target_point, source_point)`` pair in ``fused_pairs`` is fused:
        the first (target) point survives and inherits all observations (``Map.fuse_points``; pairs whose
        points are gone or already the same are skipped). The source's spanning tree is re-rooted at its
        keyframe most covisible with the target and attached there. A record is appended to
        ``merge_history``. Raises ``ValueError`` (before changing anything) if keys collide.
        """
        if target_id == source_id:
            raise ValueError("cannot merge a map with itself")
        tgt, src = self.maps[target_id], self.maps[source_id]
        clash_kf = tgt.keyframes.keys() & src.keyframes.keys()
        clash_pt = tgt.points.keys() & src.points.keys()
        if clash_kf or clash_pt:
            raise ValueError(
                f"maps {target_id} and {source_id} share keys: "
                f"{len(clash_kf)} keyframes, {len(clash_pt)} points"
            )
        t0 = time.perf_counter()
        src.transform(target_from_source)
        src_keys = list(src.keyframes)
        tgt.keyframes.update(src.keyframes)
        tgt.points.update(src.points)
        tgt._covis.update(src._covis)
        tgt._children.update(src._children)
        for a, bs in src._loops.items():
            tgt._loops.setdefault(a, set()).update(bs)
        tgt._orphans.update(src._orphans)
        tgt._tree_changed.update(src._tree_changed)
        tgt.agents.update(src.agents)
        for k, v in src.point_redirects.items():
            tgt.point_redirects.setdefault(k, v)
        # pending references of either side may now name a present point
        for pk, refs in src._pending.items():
            tgt._pending.setdefault(pk, {}).update(refs)
        for pk in [pk for pk in tgt._pending if pk in tgt.points]:
            refs = tgt._pending.pop(pk)
            mp = tgt.points[pk]
            for kf_key, idx in refs.items():
                kf = tgt.keyframes[kf_key]
                if kf_key in mp.observations:
                    kf.set_point_key(idx, None)
                else:
                    tgt._link(kf, idx, mp)
        tgt.merge_history.extend(src.merge_history)
        n_fused = 0
        for keep, drop in fused_pairs:
            k2, d2 = tgt.resolve_point(keep), tgt.resolve_point(drop)
            if k2 == d2 or k2 not in tgt.points or d2 not in tgt.points:
                logger.debug("merge %s<-%s: fused pair %s/%s skipped", target_id, source_id, keep, drop)
                continue
            tgt.fuse_points(k2, d2)
            n_fused += 1
        # attach each source tree to the target at its strongest covisibility link
        src_set = set(src_keys)
        roots: dict[KfKey, list[KfKey]] = {}
        for k in src_keys:
            roots.setdefault(tgt._root_of(k), []).append(k)
        n_attached = 0
        for root, members in roots.items():
            if root not in src_set:
                continue  # already attached (through an orphan link)
            best: tuple[int, KfKey, KfKey] | None = None
            for k in members:
                for nb, w in tgt._covis[k].items():
                    if nb not in src_set and (best is None or w > best[0]):
                        best = (w, k, nb)
            if best is not None:
                _, k, nb = best
                tgt._reroot(k)
                tgt._set_parent_unchecked(k, nb)
                tgt._orphans.discard(k)
                n_attached += 1
        record: dict[str, Any] = {
            "time": time.time(),
            "target": int(target_id),
            "source": int(source_id),
            "target_from_source": target_from_source.matrix().tolist(),
            "n_fused": n_fused,
            "n_keyframes_moved": len(src_keys),
            "n_trees_attached": n_attached,
            "source_agents": sorted(src.agents),
        }
        tgt.merge_history.append(record)
        del self.maps[source_id]
        logger.info(
            "merged map %d into %d: %d keyframes moved, %d points fused (%.1f ms)",
            source_id,
            target_id,
            len(src_keys),
            n_fused,
            (time.perf_counter() - t0) * 1e3,
        )
        return tgt


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
        for f in (*arrays, "gnss_enu", "gnss_cov", "up_cam"):
            if not _arr_eq(getattr(x, f), getattr(y, f)):
                d.append(f"keyframe {k}: {f} differs")
        if np.float64(x.timestamp).tobytes() != np.float64(y.timestamp).tobytes():
            d.append(f"keyframe {k}: timestamp differs")
        for f in ("camera", "point_agents", "parent"):
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
