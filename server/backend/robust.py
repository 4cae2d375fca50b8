"""The robust pose graph's verdicts applied on the event loop: loops it rejects are reported with their reason
and lose their loop edge (and their duplicate points stay apart), loops it takes back regain them, merges
whose edge it rejects are undone: the merged map splits back (:func:`hivemap.maps.merge.split_map`, one
store commit), the moved agents are re-framed, corrections go out and an event says why.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.merge import split_map
from hivemap.maps.store import map_rows
from hivemap.server.backend import evidence_store, rendezvous
from hivemap.server.backend.evidence import Evidence, MergeHypothesis
from hivemap.server.backend.fit import umeyama
from hivemap.server.backend.gnss import antenna_fixes
from hivemap.server.backend.sessionguess import is_guess
from hivemap.server.optim import PoseGraphResult
from hivemap.server.persist import GraphSnapshot

logger = logging.getLogger(__name__)

PointPair = tuple[Any, Any]
F64 = NDArray[np.float64]


def loop_message(ev: Evidence) -> str:
    rec = ev.record
    q, c = tuple(rec["query"]), tuple(rec["candidate"])
    if ev.rejected:
        why = rec["reject_reason"]
        return f"loop {q} -> {c} in map {rec['map']} rejected ({rec['n_inliers']} inliers): {why}"
    return f"loop {q} -> {c} in map {rec['map']} ({rec['n_inliers']} inliers)"


def publish_first(events: Any, ev: Evidence) -> None:
    """A loop's ``loop`` event, once the robust pose graph has judged it: a rejected one says so and why
    (``refused``, so it counts as not accepted wherever accepted loops are counted)."""
    data = dict(ev.record)
    if ev.rejected:
        data["refused"] = True
    events.add("loop", loop_message(ev), map_id=ev.record["map"], data=data)


async def apply_verdict(bk: Any, m: Any, judged: list[Evidence], problem: Any, res: PoseGraphResult) -> bool:
    """Record the verdict of one pose graph on ``judged`` (the map's kept edges, in the order they went
    into ``problem``) and act on it. False if a merge was undone (the solve's poses are void then)."""
    inlier, chi2 = [True] * len(judged), [0.0] * len(judged)
    for n, src in enumerate(problem.new_edge_source):
        inlier[src], chi2[src] = res.inlier[n], res.chi2[n]
    first = [ev for ev in judged if ev.judged == 0 and ev.kind == "loop"]
    v = bk.evidence.judge(m.id, judged, inlier, chi2, bk.options.accept.merge_confirmations)
    events = bk.server.events
    for ev in first:
        publish_first(events, ev)
    for ev in v.rejected:
        m.remove_loop_edge(ev.edge.candidate, ev.edge.query)
        if ev not in first and ev.kind != rendezvous.KIND:  # (rendezvous: their own events, below)
            what = f"{ev.kind} {ev.edge.query} -> {ev.edge.candidate} in map {m.id}"
            events.add(f"{ev.kind}_rejected", f"{what} rejected after the fact: {ev.record['reject_reason']}",
                       map_id=m.id, data=dict(ev.record))  # fmt: skip
    for ev in v.readmitted:
        # (a rendezvous edge is no covisibility: it has no loop edge in the map)
        if ev.kind != rendezvous.KIND and ev.edge.candidate in m.keyframes and ev.edge.query in m.keyframes:
            m.add_loop_edge(ev.edge.candidate, ev.edge.query)
        events.add(f"{ev.kind}_readmitted", f"{ev.kind} {ev.edge.query} -> {ev.edge.candidate} in map {m.id} "
                   f"kept again by the robust pose graph", map_id=m.id, data=dict(ev.record))  # fmt: skip
    rendezvous.judged(bk, judged)
    for hyp in v.confirmed:
        events.add("merge_confirmed", f"merge {hyp.source} -> {hyp.target} confirmed by "
                   f"{len(hyp.confirmations)} loops between its sides", map_id=m.id,
                   data={"merge_id": hyp.id, "confirmations": len(hyp.confirmations)})  # fmt: skip
    if v.contradicted:
        hyp = v.contradicted[0]
        own = next(ev for ev in judged if ev.merge is hyp)
        await undo_merge(bk, m.id, hyp, own.record.get("reject_reason", "its edge was rejected"))
        return False
    out = rendezvous.outvoted(bk, m)
    if out is not None:
        await undo_merge(bk, m.id, *out)
        return False
    return True


def fusable(bk: Any, map_id: int) -> list[PointPair]:
    """The duplicate points of the map's kept loops not fused yet (a rejected loop's stay apart)."""
    out: list[PointPair] = []
    for ev in bk.evidence.edges.get(map_id, []):
        if (ev.judged or ev.dependent is not None) and not ev.rejected and not ev.fused:
            out += ev.fuse
            ev.fuse, ev.fused = [], True
    return out


async def undo_merge(bk: Any, map_id: int, hyp: MergeHypothesis, reason: str) -> None:
    """Split ``hyp``'s source agents out of map ``map_id`` back into their own frame, persist both maps and
    the re-framed agents in one commit, and tell every agent of both maps."""
    server = bk.server
    m = server.stack.maps.get(map_id)
    side = set(hyp.source_agents) & (set(m.agents) if m is not None else set())
    record = {"time": time.time(), "undone_merge": hyp.id, "map": map_id, "agents": sorted(side),
              "reason": reason}  # fmt: skip
    if m is None or not side:
        return
    source_from_target = hyp.target_from_source.inverse()
    server._ingest_open.clear()
    try:
        try:
            kept, new = split_map(server.stack, map_id, side, source_from_target, record)
        except ValueError as exc:
            bk.evidence.merges[map_id] = [h for h in bk.evidence.merges.get(map_id, []) if h is not hyp]
            server.events.add("merge_undone", f"merge {hyp.source} -> {hyp.target} contradicted ({reason}) "
                              f"but cannot be undone: {exc}", map_id=map_id)  # fmt: skip
            return
        moved = [am for agent in server.agents.values() for am in agent.maps.values() if am.folded in side]
        for am in moved:
            am.global_from_vio = source_from_target @ am.global_from_vio
        rows = [am.row() for am in moved]
        dropped = bk.evidence.split(map_id, new.id, hyp)
        hyp.record.update(undone=True, undo_reason=reason, on_trial=False, split_into=new.id)
        rendezvous.undone(bk, hyp, reason)
        book = evidence_store.to_json(bk.evidence)
        # the maps go on changing during the write: the new map whole, the kept one by what left it
        new_rows, kept_graph = map_rows(new), GraphSnapshot(kept)
        left_kfs, left_points, kept_agents = list(new.keyframes), list(new.points), set(kept.agents)

        def op(store: Any) -> None:
            store.maps.remove_side(map_id, left_kfs, left_points, kept_agents, record)
            store.maps.sync_graph(kept_graph)
            store.maps.save_map(new_rows)
            for row in rows:
                store.put_agent_map(row)
            store.maps.set_meta(evidence_store.META_KEY, book)

        # the back-end's per-map state changes in the step that splits, as a merge's does
        # (Pipeline._apply_merge): a solve started during the write sees both maps as they are now
        for mid in (map_id, new.id):
            bk._generation[mid] = bk._generation.get(mid, 0) + 1
            bk._gnss_unbend.pop(mid, None)
        bk._enu_maps.discard(new.id)
        bk._consistency.forget_maps(map_id, new.id)
        bk._override.forget_maps(map_id, new.id)
        bk._prior.split(map_id, new.id, side, hyp.target_from_source)
        await server.writer.call(op)
    finally:
        server._ingest_open.set()
    if bk.recognizer is not None:
        keys = list(new.keyframes)
        await asyncio.get_running_loop().run_in_executor(bk._pr_exec, relabel, bk.recognizer, keys, new.id)
    server.events.add(
        "merge_undone",
        f"merge {hyp.source} -> {hyp.target} undone ({reason}): {sorted(side)} split from map {map_id} into "
        f"map {new.id}, {len(dropped)} edges between the sides dropped",
        map_id=map_id,
        data={"merge_id": hyp.id, "map": map_id, "new_map": new.id, "agents": sorted(side), "reason": reason,
              "n_dropped_edges": len(dropped)},
    )  # fmt: skip
    logger.warning("map %d: merge %d undone (%s); %s now map %d", map_id, hyp.id, reason, sorted(side),
                   new.id)  # fmt: skip
    t = time.monotonic()
    await bk._send_corrections(map_id, {}, t)
    await bk._send_corrections(new.id, {}, t)
    if is_guess(hyp):
        # the loops that refuted the guess were place recognition's view of the true relation: their
        # query keyframes are looked up again, now against the other map, so that the sessions merge by it
        bk._requery(again_after_guess(new, dropped, bk.options.accept.consistency_max_gap))


def again_after_guess(new: Any, dropped: list[Evidence], window: int) -> list[Any]:
    """Keyframes of the split-off map ``new`` to look up again after its session guess was undone: those
    within ``window`` ids (the consistency window) of each dropped loop's end on its side, in id order."""
    ends = {k for ev in dropped if ev.kind == "loop" for k in (ev.edge.query, ev.edge.candidate)}
    ends = {k for k in ends if k in new.keyframes}
    keys = {k for k in new.keyframes for e in ends if k[0] == e[0] and abs(k[1] - e[1]) <= window}
    return sorted(keys, key=lambda k: (k[0], k[1]))


def gnss_disagreement(
    m: Any,
    hyp: MergeHypothesis,
    lever_of: Any,
    with_scale: bool,
    min_fixes: int = 5,
    min_spread_m: float = 2.0,
) -> tuple[float, float] | None:
    """How the agents' GNSS fixes judge merge ``hyp`` of map ``m``: (median residual of one rigid
    alignment of all its fixes, the worse of each side's own), in m; None while a side has fewer than
    ``min_fixes`` fixes or they lie within ``min_spread_m`` of their centre (nothing to align)."""
    ant: dict[bool, list[F64]] = {True: [], False: []}
    fix: dict[bool, list[F64]] = {True: [], False: []}
    for k, antenna, kf in antenna_fixes(m, lever_of, {*hyp.source_agents, *hyp.target_agents}):
        side = k[0] in hyp.source_agents
        ant[side].append(antenna)
        fix[side].append(np.asarray(kf.gnss_enu, dtype=np.float64))

    def residual(a: F64, f: F64) -> float:
        T = umeyama(a, f, with_scale=with_scale)
        return float(np.median(np.linalg.norm(T.apply(a) - f, axis=1)))

    own = []
    for side in (True, False):
        a = np.array(ant[side]).reshape(-1, 3)
        if len(a) < min_fixes or np.median(np.linalg.norm(a - a.mean(axis=0), axis=1)) < min_spread_m:
            return None
        own.append(residual(a, np.array(fix[side])))
    both = residual(np.array(ant[True] + ant[False]), np.array(fix[True] + fix[False]))
    return both, max(own)


async def gnss_check(bk: Any, m: Any) -> bool:
    """Before the GNSS stage: undo a merge on trial that the agents' fixes contradict (one alignment of
    all of them is off by ``AcceptOptions.merge_gnss_factor`` times, and at least ``merge_gnss_min_m``,
    more than each side's own). False if a merge was undone."""
    o = bk.options.accept
    for hyp in bk.evidence.on_trial(m.id):
        d = gnss_disagreement(m, hyp, bk._cam_from_antenna, not bk.options.fix_scale)
        if d is None or not (d[0] > o.merge_gnss_min_m and d[0] > o.merge_gnss_factor * d[1]):
            continue
        reason = (f"GNSS: the agents' fixes fit the merged map to {d[0]:.2f} m (median), each side alone to "
                  f"{d[1]:.2f} m")  # fmt: skip
        hyp.record["gnss_residuals_m"] = list(d)
        await undo_merge(bk, m.id, hyp, reason)
        return False
    return True


def relabel(recognizer: Any, keys: list[Any], map_id: int) -> None:
    """Place-recognition thread: the split-off keyframes belong to map ``map_id`` now."""
    for k in keys:
        if k in recognizer.kfdb:
            recognizer.kfdb.set_map(k, map_id)
