"""The back-end's optimisation pipeline on the event loop: when a map's pose graph, global BA and GNSS stage
run (one at a time per map; requests arriving meanwhile coalesce), and applying their results. The
solves themselves are :mod:`.optimise` and :mod:`.gnss`, run in the optimisation thread on snapshots.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3
from hivemap.server.backend import (
    accept,
    corrections,
    evidence_store,
    fit,
    optimise,
    robust,
    selfcheck,
    sessionguess,
)
from hivemap.server.backend.backlog import QueryQueue
from hivemap.server.backend.evidence import EvidenceBook
from hivemap.server.backend.executor import SolverProcess, Verifier
from hivemap.server.backend.gnss_steps import GnssSteps
from hivemap.server.backend.optimise import NewEdge, Snapshot
from hivemap.server.backend.options import BackendOptions
from hivemap.server.backend.startprior import StartPrior
from hivemap.server.backend.uncertainty import Uncertainty
from hivemap.server.convert import split_folded
from hivemap.server.persist import GraphSnapshot
from hivemap.server.placerec import Detection, PlaceRecognizer

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

# The pose graph holds one keyframe per connected start, global BA two (its gauge includes scale).
POSE_GRAPH_ANCHORS_PER_AGENT = 1
# A metric map's global BA needs this share of its observations stereo (they hold its scale).
STEREO_BA_MIN_SHARE = 0.2


class Pipeline(GnssSteps):
    """The back-end's state and its optimisation pipeline; :class:`~.scheduler.Backend` adds the
    place-recognition worker, merges and loops."""

    def __init__(self, server: Any, options: BackendOptions | None = None, vocabulary: Any = None) -> None:
        self.server = server
        self.options = options or BackendOptions()
        self._generation: dict[int, int] = {}  # bumped when a map changes frame (merge / GNSS)
        starts = getattr(getattr(server, "settings", None), "start_poses", None)
        self._prior = StartPrior.from_settings(starts, self._generation)
        self._vocabulary = vocabulary
        self.recognizer: PlaceRecognizer | None = None
        so = self.options.scheduler
        self.queue = QueryQueue(so.queue_max, so.backlog)
        self._wake = asyncio.Event()
        self._pr_exec = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="hive-placerec")
        self._opt_exec = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="hive-optim")
        # pycolmap holds the GIL through a whole Ceres solve, which stalled the event loop (agents dropped,
        # REST timed out: docs/decisions.md), so global BA runs in a process of its own; the pose graph's
        # gtsam solve too (tens of seconds on a map of a thousand keyframes), except with the thread
        # executor
        self._ba_proc = SolverProcess("global BA")
        self._pg_proc = SolverProcess("pose graph")
        self._tasks: set[asyncio.Task[Any]] = set()
        self._worker: asyncio.Task[None] | None = None
        self._inflight: set[asyncio.Task[None]] = set()  # queries being prepared, verified or applied
        self._verifier: Verifier | None = None
        self._busy = 0  # queries or optimisations in flight
        self._opt_running: set[int] = set()
        self._gnss_count: dict[int, int] = {}
        self._enu_maps: set[int] = set()  # maps the GNSS stage has put into ENU
        # per map, what undoes the bend the last GNSS stage gave each keyframe (visual = U @ bent). The map
        # holds the bent poses between optimisations; each optimisation takes the bend out first, so that
        # the pose graph, global BA and the next stage work on the visual shape, not on one with the
        # previous fixes' noise baked in.
        self._gnss_unbend: dict[int, dict[KfKey, Sim3]] = {}
        self._retry_at: dict[tuple[int, int], float] = {}  # map pair -> last GNSS-guided retry
        self._gnss_scale: dict[int, tuple[int, float]] = {}  # map -> (fixes at its last CV, chosen scale)
        self._consistency = accept.Consistency()
        self._override = accept.PriorOverride()  # merges against the start prior, by independent places
        self.evidence = EvidenceBook()  # the maps' loop and merge edges, judged again at each pose graph
        # per map, the edges waiting for the running optimisation and when the first of them was detected
        # (their corrections' latency counts from it)
        self._opt_again: dict[int, tuple[list[NewEdge], float]] = {}
        self._resolve_again: set[int] = set()  # maps whose next optimisation solves the pose graph anyway
        # figures
        self.queries = 0
        self.query_ms: list[float] = []
        self.query_lags: list[float] = []  # keyframe arrival -> its place recognition done (s)
        self.query_cpu_ms: list[float] = []  # per query: look-up and job (this process) + verification
        self.verify_cpu_ms = 0.0  # all verifications (in whichever process ran them)
        self.job_bytes: list[int] = []  # per query: the arrays its verification job carries
        self.verifications = 0  # candidates verified (with two phases: that went through phase 1)
        self.full_verifications = 0  # candidates that got the full verification (two phases: phase 2's)
        self.merges: list[dict[str, Any]] = []
        self.loops: list[dict[str, Any]] = []
        self.correction_bytes: dict[str, int] = {}
        self.correction_latencies: list[float] = []
        self.ba_runs: list[dict[str, Any]] = []
        self.selfcheck: dict[int, dict[str, Any]] = {}  # map -> its last self-check (/maps/{id})
        self.uncertainty = Uncertainty(self, self.options.uncertainty)

    @property
    def verifier(self) -> Verifier:
        assert self._verifier is not None, "the back-end is not started"
        return self._verifier

    @property
    def dropped_queries(self) -> int:
        """Query keyframes pushed out of the full queue."""
        return self.queue.dropped

    @property
    def skipped_queries(self) -> int:
        """Query keyframes not queried in a backlog (their agent's covisible keyframe was)."""
        return self.queue.skipped

    # -- helpers over the server's state ------------------------------------------------------------
    def _agent_kind(self, folded: str) -> str:
        a = self.server.agents.get(split_folded(folded)[0])
        return str(a.kind) if a is not None else "uav"

    def _self_check(self, map_id: int) -> None:
        """The map's self-check after an optimisation (:mod:`.selfcheck`); each new alarm is an event."""
        m = self.server.stack.maps.get(map_id)
        if m is None:
            return
        enu = map_id in self._enu_maps
        # loops the robust pose graph rejects and merges undone are no measurements of the map
        kept = [r for r in [*self.merges, *self.loops] if not r.get("rejected") and not r.get("undone")]
        res = selfcheck.check(m, kept, self._cam_from_antenna, enu)
        seen = {a["subject"] for a in self.selfcheck.get(map_id, {}).get("alarms", [])}
        self.selfcheck[map_id] = res
        for a in res["alarms"]:
            if a["subject"] not in seen:
                self.server.events.add("selfcheck_alarm", a["message"], map_id=map_id, data=a)

    def _refresh_loose(self) -> None:
        """Tell place recognition which agent groups only a session guess on trial joins (their loops
        skip the correction gate: they judge the guess)."""
        if self.recognizer is not None:
            self.recognizer.loose_pairs = sessionguess.loose_pairs(self.evidence)

    def _cam_from_antenna(self, folded: str) -> F64:
        am = self.server._agent_map_by_folded(folded)
        agent = self.server.agents.get(am.agent_id) if am is not None else None
        lever = getattr(agent, "cam_from_antenna", None)
        return np.zeros(3) if lever is None else np.asarray(lever, dtype=np.float64).reshape(3)

    def _up_cam(self, m: Any, key: KfKey) -> F64 | None:
        return fit.up_cam(m, key, self.options.fit.level_up_window, self._gnss_unbend)

    def _snapshot(self, m: Any) -> Snapshot:
        return optimise.snapshot(m, self._generation.get(m.id, 0))

    def _current(self, snap: Snapshot) -> Any:
        """The snapshot's map if it has not changed frame since (else its result is dropped)."""
        m = self.server.stack.maps.get(snap.map_id)
        if m is None or self._generation.get(snap.map_id, 0) != snap.generation:
            return None
        return m

    def _apply_corrections(self, m: Any, corr: dict[KfKey, Sim3], new_xyz: dict[Any, F64]) -> None:
        corrections.apply_corrections(
            self.server, m, corr, new_xyz, self.options.corrections, self.options.fix_scale
        )

    async def _send_corrections(
        self, map_id: int, before: dict[KfKey, F64], t_det: float, covariances: Any = None
    ) -> None:
        # the corrections carry each agent's latest keyframe's covariance in the map as it is now
        # (``covariances``: that solve already started, awaited here)
        await (covariances if covariances is not None else self.uncertainty.latest_now(map_id))
        await corrections.send_corrections(
            self.server, map_id, before, t_det, self.options.corrections, map_id in self._enu_maps,
            self.correction_bytes, self.correction_latencies, self.uncertainty.of_agent,
        )  # fmt: skip
        self.uncertainty.request(map_id)

    async def _apply_merge(
        self,
        target: int,
        source: int,
        target_from_source: Sim3,
        pairs: list[Any],
        by: str | None = None,
        record: Callable[[Any], None] | None = None,
    ) -> tuple[Any, float]:
        """Merge through the server (one commit); returns the merged map and the merge time in ms. The
        back-end's per-map state is re-keyed, and ``record(merged)`` (the merge's own edge and evidence)
        runs, in the step that merges the maps: a solve started while the merge is written or place
        recognition re-keyed would otherwise see the source's agents joined to the map by no edge, held
        only by their loose gauge prior (covariances of ~100 m)."""

        def bookkeeping(merged: Any) -> None:
            self._generation[target] = self._generation.get(target, 0) + 1
            self._generation.pop(source, None)
            self._prior.merged(target, source, target_from_source)
            self.selfcheck.pop(source, None)
            self.evidence.on_merge(target, source)
            self._enu_maps.discard(source)  # the merged map keeps the target's frame
            self._gnss_unbend.pop(source, None)  # its keyframes' poses count as visual from now on
            if record is not None:
                record(merged)

        t0 = time.perf_counter()
        merged = await self.server.apply_merge(
            target, source, target_from_source, pairs, by=by, on_merged=bookkeeping
        )
        merge_ms = (time.perf_counter() - t0) * 1e3
        if self.recognizer is not None:
            await asyncio.get_running_loop().run_in_executor(
                self._pr_exec, self.recognizer.on_merge, target, source
            )
        return merged, merge_ms

    # -- optimisation pipeline ------------------------------------------------------------------------
    def _schedule_optimisation(
        self,
        map_id: int,
        edges: list[NewEdge],
        t_det: float,
        fuse: list[tuple[Any, Any]] | None = None,
        pre: tuple[Sim3, list[KfKey]] | None = None,
        resolve: bool = False,
    ) -> None:
        """Optimise map ``map_id`` with the new loop or merge ``edges`` (after the running optimisation, if
        one runs). ``resolve``: solve the pose graph even without new edges (an agent's odometry changed)."""
        if map_id in self._opt_running:
            waiting, t_first = self._opt_again.get(map_id, ([], t_det))
            self._opt_again[map_id] = (waiting + list(edges), min(t_first, t_det))
            if resolve:
                self._resolve_again.add(map_id)
            return
        # busy from now, not from when the task first runs: requests in the same stretch of the loop (a
        # batch of rendezvous edges) would otherwise start optimisations side by side, each applying its
        # correction from the same snapshot on top of the others'
        self._opt_running.add(map_id)
        task = asyncio.create_task(self._optimise(map_id, edges, t_det, fuse or [], pre, resolve))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _optimise(
        self,
        map_id: int,
        edges: list[NewEdge],
        t_det: float,
        fuse: list[tuple[Any, Any]],
        pre: tuple[Sim3, list[KfKey]] | None = None,
        resolve: bool = False,
    ) -> None:
        try:
            while True:
                await self._optimise_once(map_id, edges, t_det, fuse, pre, resolve)
                self._self_check(map_id)
                self._refresh_loose()  # the verdict may have confirmed or undone a session guess
                pre = None
                again = self._opt_again.pop(map_id, None)
                resolve = map_id in self._resolve_again
                self._resolve_again.discard(map_id)
                if again is None or map_id not in self.server.stack.maps:
                    break
                (edges, t_det), fuse = again, []
        except asyncio.CancelledError:
            raise
        except Exception:
            logger.exception("optimisation of map %d failed", map_id)
            self.server.events.add("error", f"optimisation of map {map_id} failed (see log)", map_id=map_id)
        finally:
            self._opt_running.discard(map_id)
            self._resolve_again.discard(map_id)

    async def _optimise_once(
        self,
        map_id: int,
        edges: list[NewEdge],
        t_det: float,
        fuse: list[tuple[Any, Any]],
        pre: tuple[Sim3, list[KfKey]] | None = None,
        resolve: bool = False,
    ) -> None:
        m = self.server.stack.maps.get(map_id)
        if m is None or len(m.keyframes) < 2:
            return
        before = corrections.local_poses(self.server, m)
        unbend = self._unbend_map(m) if self.options.gnss.enabled else None
        try:
            await self._optimise_steps(map_id, edges, t_det, fuse, pre, before, unbend, resolve)
        finally:
            m = self.server.stack.maps.get(map_id)
            if unbend is not None and m is not None and map_id not in self._gnss_unbend:
                self._rebend_map(m, unbend)  # a step gave up before the GNSS stage

    async def _optimise_steps(
        self,
        map_id: int,
        edges: list[NewEdge],
        t_det: float,
        fuse: list[tuple[Any, Any]],
        pre: tuple[Sim3, list[KfKey]] | None,
        before: dict[KfKey, F64],
        unbend: dict[KfKey, Sim3] | None,
        resolve: bool = False,
    ) -> None:
        server = self.server
        m = server.stack.maps.get(map_id)
        if m is None:
            return
        # 1. pose graph over the essential graph + the new edges (the robust one over every kept edge also
        # when asked to solve again without new ones: its odometry edges hold what the agents sent last)
        solve = bool(edges) or (resolve and self.options.optimise.gnc)
        if solve and not await self._pose_graph_step(m, edges, pre):
            return
        # the loop's duplicate points become one only now (fused earlier, their covisibility edges would
        # hold the uncorrected relative poses in the pose graph); the fusion is committed at once
        await server.fuse_points(map_id, fuse + robust.fusable(self, map_id))
        m = server.stack.maps.get(map_id)
        if m is None:
            return
        # 2. global BA (background; keyframes arriving meanwhile follow their parent). A BA dropped because
        # the map changed skips the GNSS stage, but the pose graph it followed is still persisted and sent.
        o = self.options.optimise
        ba_ok = True
        if o.global_ba and 2 <= len(m.keyframes) <= o.ba_max_keyframes:
            ba_ok = await self._ba_step(m)
        # 3. GNSS stage: the whole map into ENU once enough spread fixes
        m = server.stack.maps.get(map_id)
        if m is None:
            return
        if self.options.gnss.enabled:
            if self.options.optimise.gnc and not await robust.gnss_check(self, m):
                return  # a merge was undone: the maps are new
            if ba_ok:
                await self._gnss_stage(m)
            if unbend is not None and map_id not in self._gnss_unbend:
                self._rebend_map(m, unbend)  # no new stage result: the last one's bend stands
        # 4. persist (poses, and the loop edges this optimisation added, in one commit), 5. corrections
        kfs, pts = list(m.keyframes.values()), list(m.points.values())
        graph = GraphSnapshot(m)
        book = evidence_store.to_json(self.evidence)  # the verdicts go with the poses they led to
        # the covariances the corrections carry are solved (in the pose graph's process) while the writer
        # thread persists: both read the map as it is now, and neither changes it
        covs = asyncio.create_task(self.uncertainty.latest_now(map_id))
        try:
            await server.persist_exclusive(
                lambda store: (store.maps.update_poses(map_id, kfs, pts), store.sync_graph(graph),
                               store.maps.set_meta(evidence_store.META_KEY, book))
            )  # fmt: skip
        except BaseException:
            covs.cancel()
            raise
        await self._send_corrections(map_id, before, t_det, covs)
        if map_id in self._enu_maps:
            await self._gnss_retry(map_id)

    async def _solve_pose_graph(self, problem: Any, poses: F64) -> Any:
        """:func:`optimise.solve_pose_graph` in the pose graph's process (the optimisation thread with the
        thread executor)."""
        o = self.options
        solve = partial(optimise.solve_pose_graph, problem, poses, o.fix_scale, o.optimise)
        if o.scheduler.executor == "thread":
            return await asyncio.get_running_loop().run_in_executor(self._opt_exec, solve)
        return await self._pg_proc.run(solve)

    async def _pose_graph_step(
        self, m: Any, edges: list[NewEdge], pre: tuple[Sim3, list[KfKey]] | None
    ) -> bool:
        """Solve and apply the pose graph; False if the map changed meanwhile or the result is refused."""
        o, map_id = self.options.optimise, m.id
        snap = self._snapshot(m)
        fixed = optimise.anchor(m, snap.keys, self._agent_kind, POSE_GRAPH_ANCHORS_PER_AGENT)
        # robust: every kept loop and merge edge of the map is judged again, and only they join its agents
        judged = self.evidence.kept_edges(map_id, m.keyframes) if o.gnc else []
        problem = optimise.pose_graph_problem(
            m, snap, [ev.edge for ev in judged] if o.gnc else edges, pre, fixed, o, o.gnc,
            metric=self.options.fix_scale,
        )  # fmt: skip
        t0 = time.perf_counter()
        res = await self._solve_pose_graph(problem, snap.poses)
        pg_ms = (time.perf_counter() - t0) * 1e3
        cur = self._current(snap)
        if cur is None:
            return False
        if judged and not await robust.apply_verdict(self, cur, judged, problem, res):
            return False
        corr, moved = optimise.pose_graph_corrections(snap, res.poses)
        limit = o.pose_graph_max_move_m + problem.move_slack_m  # weak tracking may have jumped farther
        if moved > limit:
            self.server.events.add("pose_graph", f"map {map_id}: pose graph refused (a keyframe would move "
                                   f"{moved:.1f} m > {limit:.1f} m)", map_id=map_id,
                                   data={"refused": True, "max_move_m": moved})  # fmt: skip
            return False
        self._apply_corrections(cur, corr, {})
        n_edges = len(problem.graph_edges) + len(problem.new_edges)
        self.server.events.add("pose_graph", f"map {map_id}: pose graph over {len(snap.keys)} keyframes, "
                               f"{n_edges} edges ({pg_ms:.0f} ms, {res.cpu_ms:.0f} ms CPU)", map_id=map_id,
                               data={"n_keyframes": len(snap.keys), "n_edges": n_edges, "ms": pg_ms,
                                     "cpu_ms": res.cpu_ms})  # fmt: skip
        return True

    async def _ba_step(self, m: Any) -> bool:
        """Run and apply global BA; False if the map changed meanwhile (the result is dropped)."""
        map_id = m.id
        snap = self._snapshot(m)
        problem = optimise.ba_problem(m, snap.keys, self.options.optimise)
        if self.options.fix_scale and problem.n_stereo < STEREO_BA_MIN_SHARE * len(problem.obs_kf):
            # monocular residuals alone let a metric map's scale drift: no BA without the stereo ones
            self.server.events.add("global_ba", f"map {map_id}: global BA skipped (metric map, "
                                   f"{problem.n_stereo} stereo observations)", map_id=map_id,
                                   data={"skipped": True, "n_stereo": problem.n_stereo})  # fmt: skip
            return True
        fixed = optimise.anchor(m, snap.keys, self._agent_kind)
        t0 = time.perf_counter()
        res = await self._ba_proc.run(
            optimise.run_ba, snap.poses, problem, fixed, self.options.optimise.ba_max_iterations
        )
        ba_ms = (time.perf_counter() - t0) * 1e3
        cur = self._current(snap)
        if cur is None:
            self.server.events.add(
                "global_ba", f"map {map_id}: BA result dropped (map changed)", map_id=map_id
            )
            return False
        corr, new_xyz = optimise.ba_corrections(snap, res, problem)
        self._apply_corrections(cur, corr, new_xyz)
        info = {"n_keyframes": len(snap.keys), "n_points": len(problem.point_keys), "ms": ba_ms,
                "n_stereo": float(res.extras.get("n_stereo", 0.0)),
                "rmse_before_px": res.initial_rmse_px, "rmse_after_px": res.final_rmse_px}  # fmt: skip
        info["accepted"] = bool(getattr(res, "accepted", True))  # rejected: inputs returned unchanged
        self.ba_runs.append(info)
        self.server.events.add("global_ba", f"map {map_id}: global BA {len(snap.keys)} keyframes, rmse "
                               f"{res.initial_rmse_px:.2f} -> {res.final_rmse_px:.2f} px ({ba_ms:.0f} ms)"
                               f"{'' if info['accepted'] else ', rejected by its checks'}",
                               map_id=map_id, data=info)  # fmt: skip
        return True

    async def _merge(self, det: Detection, t_det: float) -> None:
        raise NotImplementedError  # the scheduler's (a GNSS-guided retry merges)
