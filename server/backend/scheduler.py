"""The back-end's scheduler: what runs when, and applying results on the event loop.

Threads and ownership:

* the event loop (core's rule): every map mutation (merge, applying optimisation results, agent transforms);
* one place-recognition thread: BoW + keyframe database + detection (:mod:`.detect`; the recogniser and
  its database are only touched there, so they need no lock); it takes each query's verification job
  (its slices of the maps, as arrays), which the verifier runs (:mod:`.executor`: worker processes, or
  Ray tasks), up to ``workers`` queries at once; results are concluded and applied in query order;
* one optimisation thread: pose graph, global BA, GNSS stage (:mod:`.optimise`, :mod:`.gnss`), on
  snapshots taken on the loop. Results are applied on the loop (:mod:`.corrections`); keyframes that
  arrived meanwhile follow their spanning-tree parent's correction. Ingest never waits for them.

Per inserted keyframe (observer, quick): enqueue. Worker: index, then detect against the other maps
(merge) and the same map outside the covisible keyframes (loop), as fast as the CPU allows (the queue's
order: :mod:`.backlog`); accept (:mod:`.accept`), fit (:mod:`.fit`), merge or add the loop
(:mod:`.surgery`), then optimise: pose graph with the new edge, global BA, GNSS stage, corrections to the
agents.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3
from hivemap.server.backend import (
    accept,
    detect,
    evidence_store,
    executor,
    fit,
    rendezvous,
    sessionguess,
    surgery,
    weld,
)
from hivemap.server.backend.optimise import NewEdge
from hivemap.server.backend.pipeline import Pipeline
from hivemap.server.convert import split_folded
from hivemap.server.placerec import Detection
from hivemap.server.placerec.phases import combine_phases

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

# Reloaded keyframes are indexed in chunks of this many (a merge may relabel maps between chunks).
INDEX_CHUNK = 200
# The GNSS stage runs whenever a map gets a new keyframe with a fix (runs coalesce while one is busy).
GNSS_EVERY_KFS = 1


class Backend(Pipeline):
    """Schedules detection and applies merges and loops (the optimisation pipeline: :class:`Pipeline`)."""

    # -- lifecycle ----------------------------------------------------------------------------------
    async def start(self, server: Any) -> None:
        loop = asyncio.get_running_loop()

        def init() -> None:
            self.recognizer = detect.make_recognizer(self._vocabulary, self.options)

        await loop.run_in_executor(self._pr_exec, init)
        so = self.options.scheduler
        self._verifier = await loop.run_in_executor(
            None,
            executor.make_verifier,
            so.executor,
            so.workers,
            so.ray_address,
            self._pr_exec,
            so.worker_keyframe_cache,
        )
        server.events.add("info", f"back-end verification: {so.executor} executor, "
                          f"{self._verifier.workers} worker(s)")  # fmt: skip
        # the first merge comes at take-off, when its correction matters most: its solve must not wait
        # for a process to start
        if so.executor != "thread":
            self._pg_proc.start()
        if self.options.optimise.global_ba:
            self._ba_proc.start()
        await self._load_evidence(server)
        self._refresh_loose()
        await self._rendezvous_after_restart()
        # keyframes reloaded from the store are indexed by the worker first (no detection on them); the
        # server is ready meanwhile
        keys = [(m.id, k) for m in server.stack.maps.values() for k in m.keyframes]
        self._worker = asyncio.create_task(self._run(keys), name="hive-backend")
        server.events.add("info", f"back-end started ({len(keys)} reloaded keyframes to index)")

    async def _load_evidence(self, server: Any) -> None:
        """The evidence book of the stored maps (merges on trial stay on trial across a restart)."""
        data = await server.persist(lambda store: store.maps.get_meta(evidence_store.META_KEY))
        try:
            book = evidence_store.from_json(data)
        except (ValueError, KeyError, TypeError) as exc:
            server.events.add("error", f"stored back-end evidence not usable ({exc}): starting without it")
            return
        live = set(server.stack.maps)
        for table in (book.edges, book.merges):
            for mid in [mid for mid in table if mid not in live]:
                del table[mid]
        self.evidence = book

    async def stop(self, server: Any) -> None:
        if self._worker is not None:
            self._worker.cancel()
        for t in [*self._tasks, *self._inflight]:
            t.cancel()
        covs = self.uncertainty.stop()
        await asyncio.gather(
            *(t for t in [self._worker, *self._tasks, *self._inflight, *covs] if t is not None),
            return_exceptions=True,
        )
        if self._verifier is not None:
            self._verifier.shutdown()
        # a running global BA is not waited for: its task is cancelled, so its result is never applied
        self._pr_exec.shutdown(wait=False, cancel_futures=True)
        self._opt_exec.shutdown(wait=False, cancel_futures=True)
        self._ba_proc.stop()
        self._pg_proc.stop()

    def idle(self) -> bool:
        """Nothing queued and nothing in flight (tests and benches wait for this)."""
        return not self.queue and self._busy == 0 and not self._tasks and not self._inflight

    def optimising(self) -> bool:
        """An optimisation (or a merge's task) is running or asked for: corrections are still to come."""
        return bool(self._opt_running or self._tasks)

    # -- observers ----------------------------------------------------------------------------------
    async def on_rendezvous(self, rid: int) -> None:
        await rendezvous.process(self, [rid])

    async def _rendezvous_after_restart(self) -> None:
        """Held observations may resolve now; pending ones may merge with the reloaded maps."""
        obs = self.server.rendezvous
        await rendezvous.process(self, sorted(r for r, o in obs.items() if o.state == "held"))
        await rendezvous.retry_pending(self)

    async def on_keyframe(self, map_id: int, key: KfKey) -> None:
        held = rendezvous.held_for(self.server, key[0])
        if held:
            await rendezvous.process(self, held)
        if self._prior.wants(key[0]):
            self._record_start(map_id, key)
        am = self.server._agent_map_by_folded(key[0])
        guess = am.session_guess if am is not None else None
        if guess is not None and guess[0] == key[1] and self.options.accept.session_guess:
            am.session_guess = None
            task = asyncio.create_task(self._merge_by_guess(key, guess[1], guess[2]))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        dropped = self.queue.push(key)
        if dropped is not None:
            self.server.events.add("placerec", f"query queue full: {dropped} dropped")
        self.uncertainty.request(map_id)
        self._wake.set()
        # GNSS stage also without a merge or loop: every ``GNSS_EVERY_KFS`` keyframes with a fix in a map
        m = self.server.stack.maps.get(map_id)
        kf = m.keyframes.get(key) if m is not None else None
        if self.options.gnss.enabled and kf is not None and kf.gnss_enu is not None:
            n = self._gnss_count[map_id] = self._gnss_count.get(map_id, 0) + 1
            if n % GNSS_EVERY_KFS == 0:
                self._schedule_optimisation(map_id, [], time.monotonic())

    def _requery(self, keys: list[KfKey]) -> None:
        """Look these keyframes up again (after the maps changed under their first look-up)."""
        for key in keys:
            if key not in self.queue.arrived:
                self.queue.push(key)
        self._wake.set()

    # -- nominal start configuration (paper 2.4) -----------------------------------------------------
    async def on_mission_end(self, agent_id: str) -> None:
        """An agent said bye: its maps are optimised once more. Its last pose updates brought the odometry
        edges up to its final, smoothed odometry, so the robust pose graph is solved again over every kept
        edge; then the global BA, when on, refines the map with its points. The agent waits for this
        before it reads its final estimate (``hivemap.client.health``)."""
        o = self.options.optimise
        if not (o.gnc or o.global_ba):
            return
        for m in list(self.server.stack.maps.values()):
            if any(split_folded(a)[0] == agent_id for a in m.agents):
                self._schedule_optimisation(m.id, [], time.monotonic(), resolve=True)

    def _record_start(self, map_id: int, key: KfKey) -> None:
        """An agent with a nominal start pose sent its first keyframe (taken at the start pose): its map's
        place in the common start frame is known to the prior's sigmas (no merge by itself)."""
        m = self.server.stack.maps.get(map_id)
        kf = m.keyframes.get(key) if m is not None else None
        if kf is None:
            return
        self._prior.record(key[0], map_id, kf.world_from_cam)
        p = self._prior
        self.server.events.add(
            "start_anchor",
            f"{key[0]}: map {map_id} has a nominal start pose (prior, {p.sigma_m} m / {p.sigma_deg} deg)",
            map_id=map_id,
        )

    def _accept(self, det: Detection) -> tuple[Detection | None, dict[str, Any] | None]:
        """The detection once accepted (else None) and how it compares with the start prior (None
        without one): a merge that agrees with the prior is taken at once; one that contradicts it only
        once independent places agree on it (:class:`~.accept.PriorOverride`); any other needs the
        consecutive confirmations (:class:`~.accept.Consistency`)."""
        o, maps, events = self.options, self.server.stack.maps, self.server.events
        chk = self._prior.check(det, maps, o.accept.min_pair_inlier_ratio, o.fix_scale)
        prior = chk.to_dict() if chk is not None else None
        if chk is not None and chk.agrees:
            ok = self._consistency.check(det, maps, replace(o.accept, consistency_required=1),
                                         o.fix_scale, events)  # fmt: skip
            if ok is not None:
                return ok, prior
        if chk is None or chk.agrees:
            return self._consistency.check(det, maps, o.accept, o.fix_scale, events), prior
        ok, places = self._override.check(det, maps, o.accept, o.fix_scale)
        need = o.accept.prior_override_places
        data = {**(prior or {}), "query": list(det.query_key), "candidate": list(det.candidate_key),
                "places": [p.to_dict() for p in places], "places_required": need}  # fmt: skip
        what = (f"merge {det.query_key} -> {det.candidate_key} contradicts the start prior by "
                f"{chk.diff_m:.2f} m / {chk.diff_deg:.1f} deg (gates {chk.gate_m:.2f} m / "
                f"{chk.gate_deg:.1f} deg)")  # fmt: skip
        if ok is None:
            events.add("start_prior", f"{what}: {len(places)}/{need} independent places agree on it",
                       map_id=det.query_map, data=data)  # fmt: skip
            return None, prior
        events.add("start_prior_overridden", f"{what}: overridden by {len(places)} independent places",
                   map_id=det.query_map, data=data)  # fmt: skip
        return ok, {**data, "overridden": True}

    # -- place-recognition worker -------------------------------------------------------------------
    async def _run(self, reloaded: list[tuple[int, KfKey]]) -> None:
        loop = asyncio.get_running_loop()
        assert self.recognizer is not None
        recognizer, stack = self.recognizer, self.server.stack
        if reloaded:
            self._busy += 1
            try:
                for i in range(0, len(reloaded), INDEX_CHUNK):
                    chunk = reloaded[i : i + INDEX_CHUNK]
                    await loop.run_in_executor(self._pr_exec, detect.index_many, recognizer, stack, chunk)
            except Exception:
                logger.exception("indexing the reloaded keyframes failed")
            finally:
                self._busy -= 1
        # up to ``workers`` queries in flight: each is prepared in the place-recognition thread, verified
        # by the verifier, and concluded and applied on the loop in the order they were taken
        prev: asyncio.Future[None] | None = None
        while True:
            if not self.queue or len(self._inflight) >= self.verifier.workers:
                self._wake.clear()
                await self._wake.wait()
                continue
            key, skipped = self.queue.pop(partial(detect.best_covisible, stack))
            if skipped:
                msg = f"backlog: {len(skipped)} keyframes not queried (their agent just queried their place)"
                self.server.events.add("placerec", msg, data={"skipped": [list(k) for k in skipped]})
                # a skipped keyframe is still indexed, or no later query could retrieve it as a candidate
                # (the place-recognition thread runs this before the next query's look-up)
                await loop.run_in_executor(
                    self._pr_exec, detect.index_many, recognizer, stack, [(0, k) for k in skipped]
                )
            done: asyncio.Future[None] = loop.create_future()
            task = asyncio.create_task(self._query(key, prev, done), name=f"hive-query-{key}")
            prev = done
            self._inflight.add(task)
            task.add_done_callback(self._query_done)

    def _query_done(self, task: asyncio.Task[None]) -> None:
        self._inflight.discard(task)
        self._wake.set()

    async def _query(self, key: KfKey, prev: asyncio.Future[None] | None, done: asyncio.Future[None]) -> None:
        """One query: its look-up and job, the job's verification, then (after the query before it) its
        conclusion, acceptance and the merge or loop it gives."""
        loop = asyncio.get_running_loop()
        assert self.recognizer is not None
        recognizer, stack = self.recognizer, self.server.stack
        self._busy += 1
        try:
            prep = await loop.run_in_executor(
                self._pr_exec, detect.prepare, recognizer, stack, key, self.options.fix_scale
            )
            reports = await self.verifier.run(prep[1]) if prep is not None and prep[1].candidates else []
            more_cpu_ms, more_bytes = 0.0, 0
            if prep is not None and prep[1].phase == 1:
                # phase 2: the full verification of phase 1's survivors, on slices taken now
                second, more_cpu_ms = await loop.run_in_executor(
                    self._pr_exec, detect.second_phase, recognizer, stack, prep[1], reports
                )
                full = await self.verifier.run(second) if second is not None else None
                more_bytes = second.nbytes if second is not None else 0
                reports = combine_phases(prep[1], reports, full)
            if prev is not None:
                await asyncio.shield(prev)
            if prep is None:
                self.query_lags.append(self.queue.done(key))
                return
            res = await loop.run_in_executor(self._pr_exec, recognizer.conclude, prep[0], reports)
            self.query_lags.append(self.queue.done(key))
            self.queries += 1
            self.query_ms.append(res.time_ms)
            verify_ms = sum(r.cpu_ms for r in reports)
            self.query_cpu_ms.append(prep[2] + more_cpu_ms + verify_ms)
            self.verify_cpu_ms += verify_ms
            self.job_bytes.append(prep[1].nbytes + more_bytes)
            verified = [c for c in res.candidates if c.reason != "covered_by_accepted_window"]
            self.verifications += len(verified)
            # candidates that got the full verification: all of them with one phase, phase 2's with two
            self.full_verifications += sum(1 for c in verified if c.phase != 1)
            detect.publish(self.server.events, res)
            det, prior = self._accept(res.detection) if res.detection is not None else (None, None)
            if det is not None:
                t_det = time.monotonic()
                if det.is_loop:
                    await self._close_loop(det, t_det)
                else:
                    await self._merge(det, t_det, prior)
        except asyncio.CancelledError:
            raise
        except Exception:
            logger.exception("back-end query %s failed", key)
            self.server.events.add("error", f"back-end query {key} failed (see log)")
        finally:
            # finished only now: the merge or loop it found has been applied and its optimisation asked for
            self.queue.finished(key)
            self._busy -= 1
            done.set_result(None)

    # -- merge ----------------------------------------------------------------------------------------
    async def _merge(self, det: Detection, t_det: float, prior: dict[str, Any] | None = None) -> None:
        server = self.server
        maps = server.stack.maps
        if det.query_map not in maps or det.candidate_map not in maps or det.query_map == det.candidate_map:
            server.events.add("merge", f"stale merge detection {det.query_key} dropped", data=det.to_dict())
            return
        levelled, sigmas = fit.levelled(self.options, maps, self._gnss_unbend, det)
        if levelled is not None:
            det = replace(det, target_from_source=levelled)
        up_q = self._up_cam(maps[det.query_map], det.query_key) if levelled is not None else None
        welded, weld_rec = await weld.run(self, det, up_q, sigmas if levelled is not None else None)
        if welded is None:
            return
        det, sigmas = welded, fit.welded_sigmas(self.options, weld_rec, sigmas)
        if det.query_map not in maps or det.candidate_map not in maps or det.query_map == det.candidate_map:
            server.events.add("merge", f"stale merge detection {det.query_key} dropped", data=det.to_dict())
            return
        target = surgery.target_of(maps, det.query_map, det.candidate_map, self._agent_kind)
        target_id, source_id, sim, pairs = det.merge_args(target)
        sides = (set(maps[target_id].agents), set(maps[source_id].agents))
        refuted = self.evidence.refuted_like(sides, sim) if self.options.optimise.gnc else None
        if refuted is not None:
            why = f"it repeats merge {refuted.id}, undone ({refuted.record.get('undo_reason')})"
            data = {"refused": True, "repeats_merge": refuted.id, **det.to_dict()}
            server.events.add(
                "merge", f"merge {source_id} -> {target_id} refused: {why}", map_id=target_id, data=data
            )
            return
        self._consistency.forget_maps(source_id, target_id)
        self._override.forget_maps(source_id, target_id)
        made: list[tuple[NewEdge, dict[str, Any]]] = []

        def record(merged: Any) -> None:
            # both keyframes are in the merged map now; the measured edge is the detection's Sim(3)
            edge = NewEdge(det.candidate_key, det.query_key, fit.edge_measure(merged, det), *sigmas)
            both = det.candidate_key in merged.keyframes and det.query_key in merged.keyframes
            if both:
                merged.add_loop_edge(det.candidate_key, det.query_key)
            rec = surgery.merge_record(merged, det, target_id, source_id, sim, len(pairs), 0.0,
                                       levelled is not None, sigmas)  # fmt: skip
            if both:
                # the measured relative pose of the two keyframes (eval: merge accuracy, as a loop's)
                rec.update(query=list(det.query_key), candidate=list(det.candidate_key),
                           candidate_t=float(merged.keyframes[det.candidate_key].timestamp),
                           candidate_from_query=edge.measured.matrix().tolist(),
                           n_inliers=det.n_inliers)  # fmt: skip
            agrees = prior is not None and prior["agrees"]
            rec["by"] = "place_recognition+prior" if agrees else "place_recognition"
            if prior is not None:
                rec["prior"] = prior
            if weld_rec is not None:
                rec["weld"] = weld_rec
            if self.options.optimise.gnc:  # on trial until loops between its sides confirm it
                self.evidence.add_merge(target_id, source_id, edge, sim, sides, rec)
            made.append((edge, rec))

        _, merge_ms = await self._apply_merge(target_id, source_id, sim, pairs, record=record)
        edge, rec = made[0]
        rec["merge_ms"] = merge_ms
        self.merges.append(rec)
        if self.options.optimise.gnc:
            book = evidence_store.to_json(self.evidence)
            await server.persist(lambda store: store.maps.set_meta(evidence_store.META_KEY, book))
        server.events.add(
            "merge_detail",
            f"merge {source_id} -> {target_id}: scale {sim.s:.4f}, {len(pairs)} duplicate points fused, "
            f"{merge_ms:.0f} ms",
            map_id=target_id,
            data=rec,
        )
        # agents of the source map get their new global_from_local at once (no keyframe moved locally)
        await self._send_corrections(target_id, {}, t_det)
        self._schedule_optimisation(target_id, [edge], t_det)

    # -- a new session merged back by its agent's guess (:mod:`.sessionguess`) -------------------------
    async def _merge_by_guess(self, key: KfKey, prev_from_new: F64, sigma: F64) -> None:
        """The first keyframe ``key`` of a session carries the agent's guess of its frame in the previous
        session's: merge the new session into that session's map by it, on trial."""
        server = self.server
        try:
            am = server._agent_map_by_folded(key[0])
            agent = server.agents.get(am.agent_id) if am is not None else None
            prev = sessionguess.previous_session(agent, am, server.stack) if agent is not None else None
            unused = {"refused": True, "by": sessionguess.BY, "query": list(key)}
            if prev is None:
                why = f"session guess of {key}: no previous session on the server"
                server.events.add("merge", why, data=unused)
                return
            plan = sessionguess.plan(server.stack, prev, am, key, prev_from_new, sigma, self._agent_kind)
            if isinstance(plan, str):
                server.events.add("merge", f"session guess of {key} not used: {plan}", data=unused)
                return
            maps = server.stack.maps
            sides = (set(maps[plan.target].agents), set(maps[plan.source].agents))
            self._consistency.forget_maps(plan.source, plan.target)
            t_det = time.monotonic()
            rec = sessionguess.record(plan, 0.0)

            def record(_merged: Any) -> None:
                if self.options.optimise.gnc:  # on trial until loops between the sessions confirm it
                    self.evidence.add_merge(
                        plan.target, plan.source, plan.edge, plan.target_from_source, sides, rec
                    )
                    self._refresh_loose()

            _, rec["merge_ms"] = await self._apply_merge(
                plan.target, plan.source, plan.target_from_source, [], by=sessionguess.BY, record=record
            )
            self.merges.append(rec)
            if self.options.optimise.gnc:
                book = evidence_store.to_json(self.evidence)
                await server.persist(lambda store: store.maps.set_meta(evidence_store.META_KEY, book))
            server.events.add(
                "merge_detail",
                f"merge {plan.source} -> {plan.target} by the session guess of {key} ({plan.sigma_m:.2f} m / "
                f"{plan.sigma_deg:.1f} deg) to {plan.edge.candidate}",
                map_id=plan.target,
                data=rec,
            )
            await self._send_corrections(plan.target, {}, t_det)
            self._schedule_optimisation(plan.target, [plan.edge], t_det)
        except asyncio.CancelledError:
            raise
        except Exception:
            logger.exception("session guess merge of %s failed", key)
            server.events.add("error", f"session guess merge of {key} failed (see log)")

    # -- loop closure ---------------------------------------------------------------------------------
    async def _close_loop(self, det: Detection, t_det: float) -> None:
        m = self.server.stack.maps.get(det.query_map)
        if m is None or det.query_key not in m.keyframes or det.candidate_key not in m.keyframes:
            return
        Tc = Sim3.from_se3(m.keyframes[det.candidate_key].world_from_cam)
        Tq = Sim3.from_se3(m.keyframes[det.query_key].world_from_cam)
        # the detection maps the query's (drifted) frame onto the candidate's: corrected query pose
        measured = Tc.inverse() @ det.target_from_source @ Tq
        o = self.options
        ups = (self._up_cam(m, det.query_key), self._up_cam(m, det.candidate_key))
        loose = o.optimise.gnc and sessionguess.across(
            sessionguess.loose_pairs(self.evidence), det.query_key, det.candidate_key
        )
        refused = accept.loop_refusal(det, m, measured, ups, o.accept, o.fix_scale, loose)
        if refused is not None:
            self.server.events.add("loop", refused[0], map_id=m.id, data=refused[1])
            return
        tilt = accept.gravity_disagreement_deg(measured, *ups)
        pairs = list(zip(det.candidate_points, det.query_points, strict=True))
        levelled, sigmas = fit.levelled(o, self.server.stack.maps, self._gnss_unbend, det, ups)
        if levelled is not None:
            det = replace(det, target_from_source=levelled)
        up_q, fitted = (ups[0], sigmas) if levelled is not None else (None, None)
        welded, weld_rec = await weld.run(self, det, up_q, fitted)
        if welded is None or det.query_map not in self.server.stack.maps:
            return
        det, m = welded, self.server.stack.maps[det.query_map]
        sigmas = fit.welded_sigmas(o, weld_rec, sigmas)
        Tc = Sim3.from_se3(m.keyframes[det.candidate_key].world_from_cam)
        Tq = Sim3.from_se3(m.keyframes[det.query_key].world_from_cam)
        measured = Tc.inverse() @ det.target_from_source @ Tq
        m.add_loop_edge(det.candidate_key, det.query_key)
        rec = surgery.loop_record(m, det, measured, tilt, levelled is not None, len(pairs), sigmas)
        if weld_rec is not None:
            rec["weld"] = weld_rec
        self.loops.append(rec)
        pre = (det.target_from_source, surgery.loop_neighbourhood(m, det.query_key))
        edge = NewEdge(det.candidate_key, det.query_key, measured, *sigmas)
        gnc = o.optimise.gnc
        dependent = self.evidence.dependent_on(m, det.candidate_key, det.query_key) if gnc else None
        if gnc and dependent is None:
            # the robust pose graph judges it first: its event (kept or rejected, and why) and the fusion
            # of its duplicate points follow that verdict
            self.evidence.add_loop(m.id, edge, rec, pairs)
            self._schedule_optimisation(m.id, [edge], t_det, pre=pre)
            return
        if dependent is not None:  # it stands or falls with the merge it repeats
            self.evidence.add_loop(m.id, edge, rec, pairs, dependent)
            pairs = []
        self.server.events.add(
            "loop",
            f"loop {det.query_key} -> {det.candidate_key} in map {m.id} ({det.n_inliers} inliers)",
            map_id=m.id,
            data=rec,
        )
        self._schedule_optimisation(m.id, [edge], t_det, fuse=pairs, pre=pre)
