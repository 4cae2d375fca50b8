"""Marginal covariances of the agents' latest keyframes and of every keyframe, from the map's pose graph
(:mod:`hivemap.server.marginals`; its docstring gives the map-frame convention), kept for REST and for
the corrections.

The graph is the one the pipeline's pose-graph step solves (:func:`.optimise.pose_graph_problem`: each
agent's essential graph plus the map's kept loop, merge and rendezvous edges, the same gauge), linearised
at the map's poses now; never on the event loop. Two kinds:

* every keyframe of a map, after new keyframes or an optimisation: at most once per
  ``min_interval_s`` per map, and no sooner after the last than its CPU time / ``max_duty``, so a large
  map costs a bounded share of a core (``max_duty_behind`` while place recognition has a backlog: the
  queries are real time, these are not); where the verification jobs run
  (:meth:`~.executor.Verifier.call`);
* the latest keyframe of each agent of a map, just before its corrections go out
  (:meth:`Uncertainty.latest_now`), so a correction carries the covariance of the poses it sends; these
  follow the optimisations, merges and undos, which are one at a time per map; in the optimisation thread
  (only the factorisation and a few recoveries: quick, and not queued behind verification jobs).

The covariances hold only what the pose graph holds: GNSS fixes (the GNSS stage is a separate solve) do
not shrink them, and they are as calibrated as the edges' sigmas are (``docs/decisions.md``).
"""

from __future__ import annotations

import asyncio
import bisect
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.backend import optimise
from hivemap.server.backend.options import OptimiseOptions, UncertaintyOptions
from hivemap.server.marginals import MarginalsResult, pose_marginals
from hivemap.server.optim import PoseGraphOptions

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PoseCovariance:
    """One keyframe's (6, 6) map-frame covariance (:mod:`hivemap.server.marginals`), computed at unix
    time ``computed_at`` on map ``map_id``'s graph of ``n_keyframes``; ``velocity``: the (3, 3) covariance
    of the agent's velocity differenced from this keyframe and its :func:`velocity_reference` (None with no
    other keyframe)."""

    map_id: int
    key: KfKey
    covariance: F64
    computed_at: float
    n_keyframes: int
    velocity: F64 | None = None


@dataclass(frozen=True)
class RelativeCovariance:
    """The (3, 3) map-frame covariance of ``p_a - p_b``, the camera centres of two agents' latest
    keyframes ``keys`` (a, b) in map ``map_id``, from their joint marginal at unix time ``computed_at``:
    what the pose graph knows of where one agent is from the other (the drift both share from the map's
    anchor cancels), which an agent's own marginal does not say."""

    map_id: int
    keys: tuple[KfKey, KfKey]
    covariance: F64
    computed_at: float


@dataclass(frozen=True)
class MapCovariances:
    """Every keyframe's covariance of one map at ``computed_at`` (``keys`` and ``covariances`` parallel)."""

    map_id: int
    keys: list[KfKey]
    covariances: F64
    computed_at: float
    cpu_s: float


def compute(
    problem: optimise.PoseGraphProblem,
    poses: F64,
    o: OptimiseOptions,
    indices: list[int] | None,
    pairs: Sequence[tuple[int, int]] = (),
) -> MarginalsResult:
    """Worker: the marginals of ``problem``'s pose graph at its initial poses (module-level: picklable)."""
    edges = optimise.problem_edges(problem, poses, o)
    opts = PoseGraphOptions(gnc=o.gnc, gnc_inlier_probability=o.gnc_inlier_probability)
    return pose_marginals(problem.initial, edges, set(problem.fixed), opts, problem.loose, indices, pairs)


def velocity_reference(stamps: Sequence[float], baseline_s: float) -> int | None:
    """Of keyframe times ``stamps`` (sorted), the index the last one's velocity is differenced from: the
    newest at least ``baseline_s`` before it, else the oldest (None: a single keyframe). Keyframes come
    0.05-0.5 s apart, and a difference over 0.05 s divides the edge's error between them by 0.05 s."""
    if len(stamps) < 2:
        return None
    i = bisect.bisect_right(stamps, stamps[-1] - baseline_s + 1e-9, 0, len(stamps) - 1) - 1
    return max(i, 0)


def velocity_pairs(m: Any, baseline_s: float) -> dict[str, tuple[KfKey, KfKey | None]]:
    """Each agent's latest keyframe in map ``m`` (by timestamp, then id) and its
    :func:`velocity_reference`."""
    by_agent: dict[str, list[tuple[float, int]]] = {}
    for k, kf in m.keyframes.items():
        by_agent.setdefault(k[0], []).append((kf.timestamp, k[1]))
    out: dict[str, tuple[KfKey, KfKey | None]] = {}
    for a, stamps in by_agent.items():
        stamps.sort()
        ref = velocity_reference([t for t, _ in stamps], baseline_s)
        out[a] = ((a, stamps[-1][1]), (a, stamps[ref][1]) if ref is not None else None)
    return out


def velocity_covariance(res: MarginalsResult, pair: tuple[int, int], dt: float) -> F64 | None:
    """The (3, 3) covariance of ``(p_a - p_b) / dt`` from the pair's difference covariance, None when the
    pair was left out or ``dt`` is not positive."""
    rel = res.relative.get(pair)
    if rel is None or not dt > 0.0:
        return None
    return np.asarray(rel / dt**2, dtype=np.float64)


class Uncertainty:
    """The back-end's covariances (module docstring); ``bk`` is the :class:`~.pipeline.Pipeline`."""

    def __init__(self, bk: Any, options: UncertaintyOptions) -> None:
        self.bk = bk
        self.options = options
        self.maps: dict[int, MapCovariances] = {}
        self.agents: dict[str, PoseCovariance] = {}  # folded agent id -> its latest keyframe's
        self.relative: dict[tuple[str, str], RelativeCovariance] = {}  # (folded a, folded b), a < b
        self.runs: list[dict[str, float]] = []  # per solve: n_keyframes, n_wanted, cpu_s, wall_s
        self._tasks: dict[int, asyncio.Task[None]] = {}
        self._again: set[int] = set()
        self._last: dict[int, tuple[float, float]] = {}  # map -> its last full solve's start, CPU seconds
        self._failed: set[int] = set()  # maps whose last solve failed (logged once)

    # -- results ------------------------------------------------------------------------------------
    def of_agent(self, folded: str) -> PoseCovariance | None:
        return self.agents.get(folded)

    def between(self, a: str, b: str) -> RelativeCovariance | None:
        """The latest solve's covariance of ``p_a - p_b`` for agent sessions ``a`` and ``b`` (folded)."""
        if a == b:
            return None
        got = self.relative.get((a, b) if a < b else (b, a))
        if got is None or a < b:
            return got
        return RelativeCovariance(got.map_id, (got.keys[1], got.keys[0]), got.covariance, got.computed_at)

    def of_map(self, map_id: int) -> MapCovariances | None:
        res = self.maps.get(map_id)
        return res if res is not None and map_id in self.bk.server.stack.maps else None

    # -- scheduling ---------------------------------------------------------------------------------
    def request(self, map_id: int) -> None:
        """Every keyframe's covariance of the map again, as soon as its rate allows."""
        if not self.options.enabled:
            return
        if map_id in self._tasks:
            self._again.add(map_id)
            return
        task = asyncio.create_task(self._run(map_id), name=f"hive-uncertainty-{map_id}")
        self._tasks[map_id] = task
        task.add_done_callback(partial(self._done, map_id))

    def _done(self, map_id: int, _task: asyncio.Task[None]) -> None:
        self._tasks.pop(map_id, None)

    async def _run(self, map_id: int) -> None:
        while True:
            self._again.discard(map_id)
            while True:  # checked again each second: a backlog may start or clear meanwhile
                wait = self._next_at(map_id) - time.monotonic()
                if wait <= 0:
                    break
                await asyncio.sleep(min(wait, 1.0))
            t0 = time.monotonic()
            try:
                res = await self._solve(map_id, full=True)
            except Exception:  # a bug here must not end the map's covariances silently
                logger.exception("covariances of map %d failed", map_id)
                res = None
            self._last[map_id] = (t0, res.cpu_s if res is not None else 0.0)
            if map_id not in self._again or map_id not in self.bk.server.stack.maps:
                return

    def _next_at(self, map_id: int) -> float:
        """When the map's next full solve may start: its last one's CPU time at the duty that holds now."""
        last = self._last.get(map_id)
        if last is None:
            return 0.0
        o = self.options
        duty = o.max_duty_behind if self._behind() else o.max_duty
        return last[0] + max(o.min_interval_s, last[1] / max(duty, 1e-3))

    def _behind(self) -> bool:
        """Place recognition has a backlog (its queue is thinned then: :mod:`~.backlog`)."""
        return len(self.bk.queue) > self.bk.options.scheduler.backlog

    async def latest_now(self, map_id: int) -> None:
        """The map's agents' latest keyframes' covariances now (before corrections go out)."""
        if self.options.enabled:
            await self._solve(map_id, full=False)

    def stop(self) -> list[asyncio.Task[None]]:
        """Cancel the pending solves; returns their tasks (to await)."""
        tasks = list(self._tasks.values())
        for t in tasks:
            t.cancel()
        return tasks

    # -- one solve ----------------------------------------------------------------------------------
    async def _solve(self, map_id: int, full: bool) -> MarginalsResult | None:
        bk = self.bk
        m = bk.server.stack.maps.get(map_id)
        if m is None or not 2 <= len(m.keyframes) <= self.options.max_keyframes or bk._verifier is None:
            return None
        o = bk.options.optimise
        snap = bk._snapshot(m)
        index = {k: i for i, k in enumerate(snap.keys)}
        fixed = optimise.anchor(m, snap.keys, bk._agent_kind, 1)
        kept = bk.evidence.held_edges(map_id, m.keyframes) if o.gnc else []
        problem = optimise.pose_graph_problem(m, snap, kept, None, fixed, o, o.gnc, bk.options.fix_scale)
        two = velocity_pairs(m, self.options.velocity_baseline_s)
        latest = {a: k for a, (k, _) in two.items()}
        kfs = m.keyframes
        # per agent: (latest, its velocity reference) as graph indices, and their time apart
        pairs = {a: ((index[k], index[p]), kfs[k].timestamp - kfs[p].timestamp)
                 for a, (k, p) in two.items() if p is not None}  # fmt: skip
        # and between every two agents' latest keyframes, for the team's collision advisories
        across = [(a, b) for a in sorted(latest) for b in sorted(latest) if a < b]
        asked = [pair for pair, _ in pairs.values()]
        asked += [(index[latest[a]], index[latest[b]]) for a, b in across]
        wanted = None if full else sorted(index[k] for k in latest.values())
        t0 = time.monotonic()
        try:
            if full:
                res: MarginalsResult = await bk.verifier.call(compute, problem, snap.poses, o, wanted, asked)
            elif bk.options.scheduler.executor == "thread":  # no processes: the optimisation thread
                res = await asyncio.get_running_loop().run_in_executor(
                    bk._opt_exec, compute, problem, snap.poses, o, wanted, asked
                )
            else:
                # the pose graph's process: corrections wait for it, verification jobs may queue behind
                # it, and in the server's own process it would hold the GIL against ingest
                res = await bk._pg_proc.run(compute, problem, snap.poses, o, wanted, asked)
        except RuntimeError as exc:
            if map_id not in self._failed:
                logger.warning("map %d: no covariances (%s)", map_id, exc)
            self._failed.add(map_id)
            return None
        self._failed.discard(map_id)
        wall = time.monotonic() - t0
        self.runs.append({"n_keyframes": float(len(snap.keys)), "n_wanted": float(len(res.indices)),
                          "cpu_s": res.cpu_s, "wall_s": wall})  # fmt: skip
        if bk._current(snap) is None:
            return res  # the map changed frame meanwhile: these covariances are of the old one
        now = time.time()
        covs = {snap.keys[i]: c for i, c in zip(res.indices, res.covariances, strict=True)}
        for folded, k in latest.items():
            if k in covs:
                vel = velocity_covariance(res, *pairs[folded]) if folded in pairs else None
                self.agents[folded] = PoseCovariance(map_id, k, covs[k], now, len(snap.keys), vel)
        for a, b in across:
            rel = res.relative.get((index[latest[a]], index[latest[b]]))
            if rel is not None:
                self.relative[(a, b)] = RelativeCovariance(map_id, (latest[a], latest[b]), rel, now)
        if full:
            self.maps[map_id] = MapCovariances(map_id, list(snap.keys), res.covariances, now, res.cpu_s)
        return res
