"""The map model shared by agents and server: ``Keyframe``, ``MapPoint`` and ``Map`` (the stack of a
session's maps is ``hivemap.maps.stack.MapStack``).

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
from collections import Counter
from collections.abc import Iterable
from typing import Any

import numpy as np

from hivemap.maps.checks import map_differences
from hivemap.maps.elements import F64, Keyframe, KfKey, MapPoint, PointKey, _key, positions
from hivemap.maps.geometry import Sim3

logger = logging.getLogger(__name__)

#: Covisibility weight from which an edge belongs to the essential graph (ORB-SLAM uses 100).
STRONG_COVISIBILITY = 100


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
            # an orphan is a parentless root waiting for a link: one that got a parent (a merge re-rooting
            # its tree) and stayed listed would later be hung below its own descendants, a cycle
            self._orphans.discard(child)
        self._tree_changed.add(child)

    def _attach_orphan(self, orphan: KfKey, other: KfKey) -> None:
        if self.keyframes[orphan].parent is not None:
            self._orphans.discard(orphan)
        elif self._root_of(other) != orphan:
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
        shared: Counter[KfKey] = Counter()  # keyframe -> points it shares with this one
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
                # linked at once, its covisibility counted below: one update per co-observer, not one per
                # observation (a keyframe's few hundred points have thousands of observations)
                shared.update(mp.observations.keys())
                mp.observations[key] = idx
                kf.set_point_key(idx, mp.key)
        cov = self._covis[key]
        for other, n in shared.items():
            cov[other] = n
            self._covis[other][key] = n
            if other in self._orphans:
                self._attach_orphan(other, key)
        # orphan trees that this keyframe's points just attached to it hang below it: no parent candidates
        if self._children[key]:
            cov = {k: w for k, w in cov.items() if self._root_of(k) != key}
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

    def remove_loop_edge(self, a: KfKey, b: KfKey) -> None:
        """Drop the loop edge ``a``-``b`` (a loop the robust pose graph rejected); absent ones are ignored."""
        a, b = _key(a), _key(b)
        for x, y in ((a, b), (b, a)):
            nbs = self._loops.get(x)
            if nbs is not None:
                nbs.discard(y)
                if not nbs:
                    del self._loops[x]

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
        return ks, positions([self.points[k] for k in ks])

    def keyframes_of_agent(self, agent_id: str) -> list[Keyframe]:
        return [kf for kf in self.keyframes.values() if kf.agent_id == agent_id]

    def pending_references(self) -> dict[PointKey, dict[KfKey, int]]:
        """Keyframe references to points not (yet) in the map: point key -> {keyframe: keypoint index}."""
        return {k: dict(v) for k, v in self._pending.items()}

    def check_consistency(self) -> list[str]:
        """Brute-force check of every invariant (slow: tests and debugging). Returns the problems found."""
        from hivemap.maps.checks import check_consistency

        return check_consistency(self)


__all__ = [
    "STRONG_COVISIBILITY",
    "F64",
    "Keyframe",
    "KfKey",
    "Map",
    "MapPoint",
    "PointKey",
    "map_differences",
]
