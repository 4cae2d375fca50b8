"""Merging one map of a stack into another (``MapStack.merge``), and splitting a merge apart again."""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

from hivemap.maps.elements import KfKey, PointKey
from hivemap.maps.geometry import Sim3

if TYPE_CHECKING:
    from hivemap.maps.model import Map
    from hivemap.maps.stack import MapStack

logger = logging.getLogger(__name__)


def merge_maps(
    stack: MapStack,
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
    tgt, src = stack.maps[target_id], stack.maps[source_id]
    clash_kf = tgt.keyframes.keys() & src.keyframes.keys()
    clash_pt = tgt.points.keys() & src.points.keys()
    if clash_kf or clash_pt:
        raise ValueError(
            f"maps {target_id} and {source_id} share keys: {len(clash_kf)} keyframes, {len(clash_pt)} points"
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
        # members share neighbours and each walk is a tree's depth; per tree, as attaching one moves roots
        root_of: dict[KfKey, KfKey] = {}
        for k in members:
            for nb, w in tgt._covis[k].items():
                if nb in src_set or (best is not None and w <= best[0]):
                    continue
                if nb not in root_of:
                    root_of[nb] = tgt._root_of(nb)
                if root_of[nb] != root:
                    best = (w, k, nb)  # nb's tree is another one: a target orphan may hang in this one
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
    del stack.maps[source_id]
    logger.info(
        "merged map %d into %d: %d keyframes moved, %d points fused (%.1f ms)",
        source_id,
        target_id,
        len(src_keys),
        n_fused,
        (time.perf_counter() - t0) * 1e3,
    )
    return tgt


def split_map(
    stack: MapStack, map_id: int, agents: Iterable[str], source_from_target: Sim3, record: dict[str, Any]
) -> tuple[Map, Map]:
    """Undo a merge: the keyframes and points of ``agents`` leave map ``map_id`` for a new map of the
    stack, moved by ``source_from_target`` (back into their own map's frame). Returns (kept, new); ``kept``
    is the map object ``map_id`` was, changed in place.

    The new map is built (from copies) from the leaving keyframes' point references (the model's source of
    truth), so its covisibility and spanning tree are its side's alone. The kept map loses them in place,
    as keyframe culling removes a keyframe (covisibility, loop edges and the spanning tree follow), which
    costs what the leaving side holds rather than a rebuild of the whole map. A reference across the sides
    (a point fused by the merge or by a loop between them) stays in its keyframe as a pending reference:
    nothing is lost, and a later merge links it again. Loop edges within a side stay, those across go;
    ``record`` is appended to both maps' ``merge_history``. Raises ``ValueError`` (before changing
    anything) if ``agents`` leaves either side without keyframes.
    """
    from hivemap.maps.model import Map, MapPoint

    m = stack.maps[map_id]
    side = set(agents)
    moving = [k for k in m.keyframes if k[0] in side]
    if not moving or len(moving) == len(m.keyframes):
        raise ValueError(f"map {map_id}: agents {sorted(side)} do not split it in two")
    t0 = time.perf_counter()
    leaving = [pk for pk, mp in m.points.items() if mp.agent_id in side]
    new = Map(stack.next_map_id)
    new.point_redirects = dict(m.point_redirects)
    new.merge_history = [*m.merge_history, record]
    # copies: the place-recognition thread may still be reading the merged map's objects
    for pk in leaving:
        mp = m.points[pk]
        new.add_point(MapPoint(mp.agent_id, mp.id, mp.xyz, mp.descriptor))
    for k in moving:
        kf = m.keyframes[k]
        kf2 = copy.copy(kf)
        kf2.world_from_cam = kf.world_from_cam.copy()
        kf2.point_ids, kf2.point_agents = kf.point_ids.copy(), dict(kf.point_agents)
        new.add_keyframe(kf2)
    for a, b in m.loop_edges():
        if a[0] in side and b[0] in side:
            new.add_loop_edge(a, b)
    new.agents |= {a for a in m.agents if a in side}
    new._tree_changed.update(new.keyframes)
    new.transform(source_from_target)
    for k in moving:
        m.remove_keyframe(k)
    for pk in leaving:  # observed now only by kept keyframes: their references become pending
        mp = m.points.pop(pk)
        obs = list(mp.observations.items())
        for i, (a, _) in enumerate(obs):
            for b, _ in obs[i + 1 :]:
                m._dec(a, b)
        if obs:
            m._pending.setdefault(pk, {}).update(obs)
    m.agents -= side
    m.merge_history.append(record)
    stack.add_map(new)
    logger.info(
        "split map %d: %d keyframes of %s into map %d (%.1f ms)",
        map_id, len(moving), sorted(side), new.id, (time.perf_counter() - t0) * 1e3,
    )  # fmt: skip
    return m, new
