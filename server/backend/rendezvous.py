"""Rendezvous observations in the back-end (the observations: :mod:`hivemap.server.rendezvous`; geometry:
:mod:`.rendezvous_fit`).

An observation is resolved into a pose-graph edge once the observer's reference keyframe and keyframes of
the observed agent around its time are in the stack (held until then; retried on every keyframe of
either agent). Within one map it is a loop-like edge (kind ``rendezvous``) of the same robust pose graph
as the loops: kept or rejected, with its reason, at each pose graph. Between two maps it is merge
evidence: the maps merge when ``RendezvousOptions.min_observations`` of their observations agree on one
transform (:func:`.rendezvous_fit.consensus`), by their least-squares transform, as a merge on trial of the
evidence book (undone like any other when its edge is rejected); the other agreeing observations are its
loop-like edges, the disagreeing ones are refused.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any

import numpy as np

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.server.backend import evidence_store, surgery
from hivemap.server.backend.evidence import Evidence, MergeHypothesis
from hivemap.server.backend.optimise import NewEdge
from hivemap.server.backend.rendezvous_fit import Oriented, bracket, chi2, consensus, edge_chi2, edge_of
from hivemap.server.rendezvous import RendezvousObs

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
BY = "rendezvous"
KIND = "rendezvous"


def _edge_dict(e: NewEdge) -> dict[str, Any]:
    return {"candidate": list(e.candidate), "query": list(e.query), "measured": e.measured.matrix().tolist(),
            "sigma_rot": e.sigma_rot, "sigma_trans": e.sigma_trans,
            "covariance": None if e.covariance is None else np.asarray(e.covariance).tolist()}  # fmt: skip


def edge_from(d: dict[str, Any]) -> NewEdge:
    cov = None if d.get("covariance") is None else np.asarray(d["covariance"], dtype=np.float64)
    return NewEdge((str(d["candidate"][0]), int(d["candidate"][1])), (str(d["query"][0]), int(d["query"][1])),
                   Sim3.from_matrix(np.asarray(d["measured"], dtype=np.float64)), float(d["sigma_rot"]),
                   float(d["sigma_trans"]), cov)  # fmt: skip


def _persist(server: Any, obs: RendezvousObs) -> None:
    rec = obs.record()
    server.writer.submit(lambda store: store.maps.put_rendezvous(obs.id, rec))


def resolve(server: Any, obs: RendezvousObs, bk: Any) -> NewEdge | str:
    """The observation's edge, or why it is held."""
    m = server.stack.map_of_agent(obs.observer)
    if m is None or obs.ref_key not in m.keyframes:
        return f"reference keyframe {obs.ref_kf_id} of {obs.observer} not arrived yet"
    agent = server.agents.get(obs.observed_agent)
    if agent is None:
        return f"observed agent '{obs.observed_agent}' not known yet"
    why = f"observed agent '{obs.observed_agent}' has no keyframes"
    # the latest session of the observed agent whose keyframes cover the time
    for am in sorted(agent.maps.values(), key=lambda a: -a.session):
        om = server.stack.map_of_agent(am.folded)
        if om is None:
            continue
        kfs = sorted((kf.timestamp, kf.key, kf.world_from_cam) for kf in om.keyframes.values()
                     if kf.agent_id == am.folded)  # fmt: skip
        br = bracket(kfs, obs.timestamp, bk.options.rendezvous)
        if isinstance(br, str):
            why = br
            continue
        ups = (bk._up_cam(m, obs.ref_key), bk._up_cam(om, br.a))
        return edge_of(obs.ref_key, obs.ref_from_cam, obs.cam_from_observed, obs.covariance, br,
                       bk.options.rendezvous, ups)  # fmt: skip
    return why


def _map_id(server: Any, key: KfKey) -> int | None:
    m = server.stack.map_of_agent(key[0])
    return None if m is None or key not in m.keyframes else int(m.id)


async def process(bk: Any, rids: list[int]) -> None:
    """Resolve the held observations among ``rids``; add those within one map to its robust pose graph,
    try merges for the map pairs the others join."""
    server = bk.server
    pairs: set[tuple[int, int]] = set()
    for rid in rids:
        obs = server.rendezvous.get(rid)
        if obs is None or obs.state != "held":
            continue
        edge = resolve(server, obs, bk)
        if isinstance(edge, str):
            if edge != obs.reason:
                obs.reason = edge
                _persist(server, obs)
            continue
        last: dict[tuple[str, str], float] = bk.__dict__.setdefault("_rv_last_used", {})
        who = (obs.observer, obs.observed_agent)
        gap = bk.options.rendezvous.min_interval_s
        if who in last and abs(obs.timestamp - last[who]) < gap:
            obs.state = "redundant"
            obs.reason = (
                f"within {gap:g} s of the last used observation of {obs.observed_agent} by {obs.observer}"
            )
            _persist(server, obs)
            continue
        last[who] = obs.timestamp
        obs.edge, obs.reason = _edge_dict(edge), ""
        mc, mq = _map_id(server, edge.candidate), _map_id(server, edge.query)
        assert mc is not None and mq is not None
        obs.map_id = mc
        if mc == mq:
            add_to_map(bk, obs, edge, mc)
        else:
            obs.state = "pending"
            obs.reason = f"between maps {mc} and {mq}: waiting for consistent observations to merge"
            pairs.add((min(mc, mq), max(mc, mq)))
        _persist(server, obs)
    for a, b in sorted(pairs):
        schedule_try(bk, a, b)


def schedule_try(bk: Any, a: int, b: int) -> None:
    """A merge try for maps ``a`` and ``b`` now, or once ``agree_interval_s`` has passed since the last
    one (a try already waiting covers the observations that arrive meanwhile)."""
    pair = (min(a, b), max(a, b))
    last_try: dict[tuple[int, int], float] = bk.__dict__.setdefault("_rv_last_try", {})
    waiting: dict[tuple[int, int], asyncio.Task[None]] = bk.__dict__.setdefault("_rv_waiting", {})
    if pair in waiting and not waiting[pair].done():
        return
    delay = max(
        0.0, last_try.get(pair, -math.inf) + bk.options.rendezvous.agree_interval_s - time.monotonic()
    )

    async def run() -> None:
        if delay > 0:
            await asyncio.sleep(delay)
        last_try[pair] = time.monotonic()
        try:
            await try_merge(bk, *pair)
        except asyncio.CancelledError:
            raise
        except Exception:
            logger.exception("rendezvous merge try of maps %s failed", pair)
            bk.server.events.add("error", f"rendezvous merge try of maps {pair} failed (see log)")

    task = asyncio.get_running_loop().create_task(run())
    waiting[pair] = task
    bk._tasks.add(task)
    task.add_done_callback(bk._tasks.discard)


def add_to_map(bk: Any, obs: RendezvousObs, edge: NewEdge, map_id: int) -> None:
    """A loop-like edge of map ``map_id``, judged by its next robust pose graph."""
    obs.state, obs.map_id = "judging", map_id
    obs.reason = "waiting for the robust pose graph's verdict"
    rec = {"rendezvous_id": obs.id, "map": map_id, "query": list(edge.query),
           "candidate": list(edge.candidate),
           "candidate_from_query": edge.measured.matrix().tolist(), "time": time.time(),
           "observed_agent": obs.observed_agent, "timestamp": obs.timestamp}  # fmt: skip
    if bk.options.optimise.gnc:
        bk.evidence.add_loop(map_id, edge, rec, [], kind=KIND)
        m = bk.server.stack.maps.get(map_id)
        settled = bk.options.rendezvous.settled_chi2
        if m is not None and settled >= 0.0:
            kc, kq = m.keyframes[edge.candidate], m.keyframes[edge.query]
            c = edge_chi2(edge, kc.world_from_cam, kq.world_from_cam)
            if c <= settled:
                obs.reason = f"agrees with the map (chi-square {c:.1f}): judged by its next robust pose graph"
                return
    bk._schedule_optimisation(map_id, [edge], time.monotonic())


def _oriented(server: Any, obs: RendezvousObs, target: int) -> Oriented | None:
    assert obs.edge is not None
    e = edge_from(obs.edge)
    mc, mq = server.stack.map_of_agent(e.candidate[0]), server.stack.map_of_agent(e.query[0])
    if mc is None or mq is None or e.candidate not in mc.keyframes or e.query not in mq.keyframes:
        return None
    return Oriented(e, mc.keyframes[e.candidate].world_from_cam.copy(),
                    mq.keyframes[e.query].world_from_cam.copy(), mc.id == target, obs.timestamp)  # fmt: skip


async def try_merge(bk: Any, a: int, b: int) -> None:
    """Merge maps ``a`` and ``b`` if enough of the observations between them agree (on trial)."""
    server = bk.server
    maps = server.stack.maps
    if a not in maps or b not in maps or a == b:
        settle_pending(bk)
        return
    target = surgery.target_of(maps, a, b, bk._agent_kind)
    source = b if target == a else a
    pend: list[tuple[RendezvousObs, Oriented]] = []
    for obs in server.rendezvous.values():
        if obs.state != "pending" or obs.edge is None:
            continue
        x = _oriented(server, obs, target)
        ends = {_map_id(server, edge_from(obs.edge).candidate), _map_id(server, edge_from(obs.edge).query)}
        if x is not None and ends == {a, b}:
            pend.append((obs, x))
    o = bk.options.rendezvous
    if len(pend) < o.min_observations:
        return
    pend = sorted(pend, key=lambda p: p[0].timestamp)[-o.agree_window :]
    # (a tenth of a second for a full window: off the event loop, on copies of the poses)
    loop = asyncio.get_running_loop()
    res = await loop.run_in_executor(None, consensus, [x for _, x in pend], o)
    if res is None or a not in maps or b not in maps:
        return
    if any(p[0].state != "pending" for p in pend):  # another try took them meanwhile
        return
    sim = Sim3.from_se3(res.target_from_source)
    sides = (set(maps[target].agents), set(maps[source].agents))
    refuted = bk.evidence.refuted_like(sides, sim) if bk.options.optimise.gnc else None
    if refuted is not None:
        server.events.add("merge", f"rendezvous merge {source} -> {target} refused: it repeats merge "
                          f"{refuted.id}, undone ({refuted.record.get('undo_reason')})", map_id=target,
                          data={"refused": True, "by": BY, "repeats_merge": refuted.id})  # fmt: skip
        return
    inl = sorted(res.inliers, key=lambda i: pend[i][0].timestamp)
    first_obs, first = pend[inl[0]]
    e0 = first.edge
    ids = [pend[i][0].id for i in inl]
    rec: dict[str, Any] = {
        "target": target, "source": source, "by": BY, "time": time.time(), "merge_ms": 0.0,
        # data time of the observation that completed the agreeing set (eval: when the agents joined)
        "query_t": max(pend[i][0].timestamp for i in inl), "scale": 1.0, "n_fused": 0,
        "target_from_source": sim.matrix().tolist(), "rendezvous": ids, "rendezvous_id": first_obs.id,
        "n_observations": len(inl), "query": list(e0.query), "candidate": list(e0.candidate),
        "candidate_from_query": e0.measured.matrix().tolist(),
        "sigma_rot_deg": math.degrees(e0.sigma_rot), "sigma_trans_m": e0.sigma_trans,
        "chi2_max": max(res.chi2[i] for i in inl),
    }  # fmt: skip
    edges = [e0]

    def record(merged: Any) -> None:
        # the data times of the edge's two keyframes, so the eval can check the edge against ground truth
        for name, key in (("query_kf_t", e0.query), ("candidate_t", e0.candidate)):
            kf = merged.keyframes.get(tuple(key))
            if kf is not None:
                rec[name] = float(kf.timestamp)
        first_obs.state, first_obs.map_id, first_obs.chi2 = "judging", target, res.chi2[inl[0]]
        first_obs.reason = f"merged maps {source} -> {target} (with {len(inl) - 1} agreeing observations)"
        if bk.options.optimise.gnc:
            bk.evidence.add_merge(target, source, e0, sim, sides, rec)
        for i in inl[1:]:
            obs, x = pend[i]
            obs.chi2 = res.chi2[i]
            add_to_map(bk, obs, x.edge, target)
            edges.append(x.edge)

    _, rec["merge_ms"] = await bk._apply_merge(target, source, sim, [], by=BY, record=record)
    bk.merges.append(rec)
    for i, (obs, _) in enumerate(pend):
        if i in res.inliers:
            continue
        obs.state, obs.map_id, obs.chi2 = "rejected", target, res.chi2[i]
        obs.reason = (f"inconsistent with the {len(inl)} observations that merged maps {source} -> {target} "
                      f"(chi-square {res.chi2[i]:.0f} > {o.gate_chi2:g})")  # fmt: skip
        server.events.add("rendezvous_rejected", f"rendezvous {obs.id} ({obs.observer} saw "
                          f"{obs.observed_agent}) rejected: {obs.reason}", map_id=target,
                          data=obs.record())  # fmt: skip
    for obs, _ in pend:
        _persist(server, obs)
    if bk.options.optimise.gnc:
        book = evidence_store.to_json(bk.evidence)
        await server.persist(lambda store: store.maps.set_meta(evidence_store.META_KEY, book))
    T = sim.matrix()
    server.events.add("merge_detail", f"merge {source} -> {target} by {len(inl)} rendezvous observations",
                      map_id=target, data=rec)  # fmt: skip
    server.events.add(
        "rendezvous_merge",
        f"map {source} merged into map {target} by {len(inl)} agreeing rendezvous observations "
        f"({len(pend) - len(inl)} refused): {np.linalg.norm(T[:3, 3]):.2f} m, "
        f"{rotation_angle_deg(T[:3, :3]):.1f} deg",
        map_id=target, data=rec,
    )  # fmt: skip
    t_det = time.monotonic()
    await bk._send_corrections(target, {}, t_det)
    bk._schedule_optimisation(target, edges, t_det)
    settle_pending(bk)


def settle_pending(bk: Any) -> None:
    """Pending observations whose two keyframes are in one map by now (resolved between two maps while a
    merge of them was being tried) become edges of that map."""
    for obs in bk.server.rendezvous.values():
        if obs.state != "pending" or obs.edge is None:
            continue
        e = edge_from(obs.edge)
        mc, mq = _map_id(bk.server, e.candidate), _map_id(bk.server, e.query)
        if mc is not None and mc == mq:
            add_to_map(bk, obs, e, mc)
            _persist(bk.server, obs)


def judged(bk: Any, evs: list[Evidence]) -> None:
    """After a pose graph's verdict: the observations behind rendezvous edges (and rendezvous merges' own
    edges) take their state from it; the first verdict and every change is an event."""
    server = bk.server
    for ev in evs:
        rid = ev.record.get("rendezvous_id")
        obs = server.rendezvous.get(rid) if rid is not None else None
        if obs is None:
            continue
        state = "rejected" if ev.rejected else "kept"
        obs.chi2 = float(ev.record.get("chi2", 0.0))
        if state == obs.state:
            continue
        first = obs.state == "judging"
        obs.state = state
        obs.map_id = ev.record.get("map", ev.record.get("target", obs.map_id))
        obs.reason = ev.record.get("reject_reason", "") if ev.rejected else "kept by the robust pose graph"
        _persist(server, obs)
        what = f"rendezvous {obs.id} ({obs.observer} saw {obs.observed_agent} at t={obs.timestamp:.2f})"
        if ev.rejected:
            server.events.add("rendezvous_rejected", f"{what} rejected: {obs.reason}", map_id=obs.map_id,
                              data=obs.record())  # fmt: skip
        elif first or state == "kept":
            server.events.add("rendezvous", f"{what} kept (chi-square {obs.chi2:.1f})", map_id=obs.map_id,
                              data=obs.record())  # fmt: skip


def outvoted(bk: Any, m: Any) -> tuple[MergeHypothesis, str] | None:
    """A rendezvous merge on trial in map ``m`` that more of the observations between its sides contradict
    than support: they agree on another transform (:func:`.rendezvous_fit.consensus`, as for a merge),
    which its own observations fail. The robust pose graph alone keeps whichever side its start (the merge
    itself) favours; a merge made by agreement is refuted by a larger agreement."""
    o = bk.options.rendezvous
    for hyp in bk.evidence.on_trial(m.id):
        own = set(hyp.record.get("rendezvous") or []) if hyp.record.get("by") == BY else set()
        if not own:
            continue
        xs: list[tuple[RendezvousObs, Oriented]] = []
        for obs in bk.server.rendezvous.values():
            if obs.edge is None or obs.state in ("held", "pending"):
                continue
            e = edge_from(obs.edge)
            if e.candidate in m.keyframes and e.query in m.keyframes and hyp.across(e.candidate, e.query):
                xs.append((obs, Oriented(e, m.keyframes[e.candidate].world_from_cam,
                                         m.keyframes[e.query].world_from_cam,
                                         e.candidate[0] in hyp.target_agents, obs.timestamp)))  # fmt: skip
        xs = sorted(xs, key=lambda p: p[0].timestamp)[-o.agree_window :]
        res = consensus([x for _, x in xs], o)
        if res is None:
            continue
        winners = {xs[i][0].id for i in res.inliers}
        support = [obs.id for obs, x in xs if chi2(np.eye(4), x, _floors(o)) < o.gate_chi2]
        if not winners & own and len(winners) > len(support):
            return hyp, (f"{len(winners)} rendezvous observations between its sides agree on another "
                         f"transform, {len(support)} on the merged map")  # fmt: skip
    return None


def _floors(o: Any) -> tuple[float, float]:
    return math.radians(o.agree_sigma_rot_deg), o.agree_sigma_trans_m


def undone(bk: Any, hyp: MergeHypothesis, reason: str) -> None:
    """A merge was undone: the observations a rendezvous merge was made of are refused (they would make
    it again); every other observation between its two sides is merge evidence again (pending), judged
    once more when the split is done."""
    ids = set(hyp.record.get("rendezvous") or []) if hyp.record.get("by") == BY else set()
    again = False
    for obs in bk.server.rendezvous.values():
        if obs.id in ids:
            obs.state, obs.reason = "rejected", f"the merge they made was undone ({reason})"
        elif obs.edge is not None and obs.state != "held":
            e = edge_from(obs.edge)
            if not hyp.across(e.candidate, e.query):
                continue
            obs.state, obs.reason = "pending", f"merge {hyp.id} between its maps was undone: evidence again"
            again = True
        else:
            continue
        _persist(bk.server, obs)
    if again:
        task = asyncio.get_running_loop().create_task(retry_pending(bk))
        bk._tasks.add(task)
        task.add_done_callback(bk._tasks.discard)


async def retry_pending(bk: Any) -> None:
    """Try a merge for every map pair that pending observations join."""
    server = bk.server
    pairs = set()
    for obs in server.rendezvous.values():
        if obs.state == "pending" and obs.edge is not None:
            e = edge_from(obs.edge)
            a, b = _map_id(server, e.candidate), _map_id(server, e.query)
            if a is not None and b is not None and a != b:
                pairs.add((min(a, b), max(a, b)))
    for a, b in sorted(pairs):
        schedule_try(bk, a, b)


def held_for(server: Any, folded: str) -> list[int]:
    """Held observations that a new keyframe of agent map ``folded`` may resolve."""
    agent_id = folded.partition("#")[0]
    return [rid for rid, r in server.rendezvous.items()
            if r.state == "held" and (r.observer == folded or r.observed_agent == agent_id)]  # fmt: skip


def residual(server: Any, obs: RendezvousObs) -> tuple[float, float] | None:
    """The edge's residual in the current map (m, deg), None while unresolved or across maps."""
    if obs.edge is None:
        return None
    e = edge_from(obs.edge)
    m = server.stack.map_of_agent(e.candidate[0])
    if m is None or e.candidate not in m.keyframes or e.query not in m.keyframes:
        return None
    pred = se3_inverse(m.keyframes[e.candidate].world_from_cam) @ m.keyframes[e.query].world_from_cam
    E = se3_inverse(e.measured.matrix()) @ pred
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])
