"""The place recogniser: BoW retrieval, the verification job of a query's candidates (:mod:`.job`,
:mod:`.verify`) and the choice of the winner."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg
from hivemap.maps.kfdb import KeyframeDatabase
from hivemap.maps.odometry import correction_slack
from hivemap.maps.vocabulary import BowVector, FeatureVector, Vocabulary
from hivemap.server.placerec.job import Candidate, QueryJob, slice_of
from hivemap.server.placerec.match import _best_covisible
from hivemap.server.placerec.phases import combine_phases, survivors
from hivemap.server.placerec.retrieve import group_candidates
from hivemap.server.placerec.types import (
    CandidateReport,
    Detection,
    PlaceRecOptions,
    RecognitionResult,
    Thresholds,
)
from hivemap.server.placerec.verify import run_job
from hivemap.server.placerec.views import HasCache

log = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ----------------------------------------------------------------------------------------------
@dataclass
class _Consistency:
    query_key: KfKey
    sim: Sim3
    count: int
    best: Detection


def _covisible_keys(m: Any, key: KfKey) -> list[KfKey]:
    return list(m.covisibility(key).keys())


_DEFAULT_OPTIONS = PlaceRecOptions()
_UNINDEXED_MAX = 4096


class PlaceRecognizer:
    """Place recognition over a map stack; holds the per-map-pair consistency state.

    ``maps``: ``Mapping[int, Map]`` (e.g. ``MapStack.maps``). Keyframes must be indexed with
    ``add_keyframe`` (BoW + direct index into the shared ``KeyframeDatabase``).
    """

    def __init__(
        self,
        vocabulary: Vocabulary,
        kfdb: KeyframeDatabase | None = None,
        options: PlaceRecOptions = _DEFAULT_OPTIONS,
    ) -> None:
        self.vocabulary = vocabulary
        self.kfdb = kfdb if kfdb is not None else KeyframeDatabase()
        self.options = options
        self._consistency: dict[tuple[int, int, str], _Consistency] = {}
        self._has = HasCache()
        self._unindexed: dict[KfKey, tuple[NDArray[np.uint8], BowVector, FeatureVector]] = {}
        # agent groups of one map joined only by a loose edge (a session guess on trial): a loop between
        # them may ask for any correction, it is the evidence that judges the guess (set by the back-end
        # from the event loop, replaced whole)
        self.loose_pairs: tuple[tuple[frozenset[str], frozenset[str]], ...] = ()

    # --- database ------------------------------------------------------------------------------
    def add_keyframe(self, map_id: int, kf: Any) -> BowVector:
        bow, fv = self._transform(kf)
        self._unindexed.pop(kf.key, None)
        self.kfdb.add(kf.key, map_id, bow, fv)
        return bow

    def remove_keyframe(self, key: KfKey) -> None:
        self.kfdb.remove(key)
        self._has.forget(key)
        self._unindexed.pop(key, None)

    def on_merge(self, target_map: int, source_map: int) -> None:
        """After ``source_map`` was merged into ``target_map``: relabel the index, drop stale state."""
        self.kfdb.reassign_map(source_map, target_map)
        for k in [k for k in self._consistency if source_map in k[:2] or target_map in k[:2]]:
            del self._consistency[k]

    def _fv(self, kf: Any) -> tuple[BowVector, FeatureVector]:
        fv = self.kfdb.features(kf.key) if kf.key in self.kfdb else None
        if fv is None:
            return self._transform(kf)
        return self.kfdb.bow(kf.key), fv

    def _transform(self, kf: Any) -> tuple[BowVector, FeatureVector]:
        """The keyframe's BoW vector and direct index; kept for keyframes a job reads before (or without)
        their own query (a window's neighbours skipped in a backlog): its descriptors never change."""
        hit = self._unindexed.get(kf.key)
        if hit is not None and hit[0] is kf.descriptors:
            return hit[1], hit[2]
        bow, fv = self.vocabulary.transform(kf.descriptors)
        if len(self._unindexed) >= _UNINDEXED_MAX:  # culled keyframes are never indexed nor removed
            for k in list(self._unindexed)[: _UNINDEXED_MAX // 2]:
                del self._unindexed[k]
        self._unindexed[kf.key] = (kf.descriptors, bow, fv)
        return bow, fv

    # --- main entry ------------------------------------------------------------------------------
    def detect(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        fix_scale: bool | Callable[[int, int], bool] = False,
        merge: bool = True,
        loop: bool = True,
    ) -> RecognitionResult:
        """Look for the query keyframe's place in other maps (merge) and in its own map (loop); what it
        retrieves and verifies does not grow with the number of agents (:mod:`.retrieve`).

        ``fix_scale``: True for metric agents (SE(3)), or a function (query map, candidate map) -> bool.
        The steps (:meth:`prepare`, :func:`~.verify.run_job`, with two phases :meth:`second_phase` and
        :func:`~.phases.combine_phases`, then :meth:`conclude`) in this thread.
        """
        result, job = self.prepare(maps, query_map, query_key, fix_scale, merge, loop)
        reports = run_job(job)
        if job.phase == 1:
            second = self.second_phase(maps, job, reports)
            reports = combine_phases(job, reports, run_job(second) if second is not None else None)
        return self.conclude(result, reports)

    def prepare(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        fix_scale: bool | Callable[[int, int], bool] = False,
        merge: bool = True,
        loop: bool = True,
    ) -> tuple[RecognitionResult, QueryJob]:
        """Retrieve the query's candidates and take what verifying them reads of the maps (:mod:`.job`);
        the job may run in another process while the maps change. With ``two_phase``, the job is phase 1
        (:mod:`.phases`): its reports go to :meth:`second_phase`."""
        t0 = time.perf_counter()
        o = self.options
        mq = maps[query_map]
        q = mq.keyframes[query_key]
        bow, _ = self._fv(q)
        n_cand = max(1, o.retrieve_max)
        result = RecognitionResult(query_key, query_map, [])
        todo: list[tuple[KfKey, float, str]] = []
        scores = self.kfdb.scores(bow)  # shared by the feasibility check, the merge and the loop look-ups
        if merge:
            feas = self.kfdb.feasibility(bow, query_map, ratio=o.feasibility_ratio, scores=scores)
            result.feasibility = feas
            if feas.best_key is None:
                result.reason = "no_other_map_keyframes"
            elif o.use_feasibility and not feas.feasible:
                result.reason = "bow_infeasible"
            else:
                found = self.kfdb.query(bow, n_cand, exclude_map=query_map, scores=scores)
                result.retrieved += len(found)
                todo += [(k, s, "merge") for k, s in self._grouped(maps, found, scores)]
        if loop:
            covis = set(_covisible_keys(mq, query_key)) | {query_key}
            # ORB-SLAM: a loop candidate must score above the worst covisible neighbour (the query's
            # scores against them are in ``scores`` already)
            neigh = [k for k in covis if k != query_key and k in self.kfdb]
            min_score = float(self.kfdb.scores_of(neigh, scores).min()) if neigh else 0.0
            found = self.kfdb.query(
                bow, n_cand, only_map=query_map, exclude_keys=covis, min_score=min_score, scores=scores
            )
            result.retrieved += len(found)
            todo += [(k, s, "loop") for k, s in self._grouped(maps, found, scores, lambda k: k not in covis)]
        cands = []
        for ck, score, kind in todo[: o.max_verifications]:
            cmap = self.kfdb.map_of(ck)
            fs = fix_scale(query_map, cmap) if callable(fix_scale) else bool(fix_scale)
            cands.append((ck, cmap, kind, score, fs))
        job = self._job(maps, query_map, query_key, cands, o.thresholds, phase=1 if o.two_phase else 0)
        result.reason = result.reason or ("" if todo else "no_bow_candidates")
        result.time_ms = (time.perf_counter() - t0) * 1e3
        return result, job

    def _job(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        cands: list[tuple[KfKey, int, str, float, bool]],
        th: Thresholds,
        phase: int = 0,
    ) -> QueryJob:
        """The job verifying ``cands`` (key, map, kind, BoW score, fixed scale) for the query (``phase``:
        :attr:`QueryJob.phase`; phase 1 takes light slices)."""
        o = self.options
        by_map: dict[int, list[KfKey]] = {query_map: [query_key]}
        best: dict[KfKey, list[KfKey]] = {}
        out: list[Candidate] = []
        for ck, cmap, kind, score, fs in cands:
            mc = maps.get(cmap)
            window = (
                _best_covisible(mc, ck, o.covisible_window) if mc is not None and ck in mc.keyframes else []
            )
            best[ck] = window
            by_map.setdefault(cmap, []).extend([ck, *window])
            a, b = query_key[0], ck[0]
            loose = any((a in s and b in t) or (a in t and b in s) for s, t in self.loose_pairs)
            # across a loose edge (a merge on trial) the graph, not a limit, judges how far a loop may move
            if kind != "loop":
                slack = (0.0, 0.0)
            else:
                slack = (math.inf, math.inf) if loose else correction_slack(maps[query_map], query_key, ck)
            out.append(Candidate(ck, cmap, kind, score, fs, window, correction_slack=slack))
        light = phase == 1
        slices = [slice_of(maps[mid], mid, ks, self._has, light) for mid, ks in by_map.items() if mid in maps]
        features = {kf.key: self._fv(kf)[1] for s in slices for kf in s.keyframes}
        return QueryJob(o, th, query_key, query_map, out, slices, features, best, phase=phase)

    def second_phase(
        self, maps: Mapping[int, Any], job: QueryJob, reports: list[CandidateReport]
    ) -> QueryJob | None:
        """Phase 2 of a two-phase query: the full verification job of the candidates that passed phase 1
        (``reports``, :func:`~.verify.run_job` of ``job``), with slices taken now. None: no survivor, or
        the query's map or keyframe is gone (merged meanwhile)."""
        keep = survivors(job, reports)
        mq = maps.get(job.query_map)
        if not keep or mq is None or job.query_key not in mq.keyframes:
            return None
        cands = [(c.key, c.map_id, c.kind, c.bow_score, c.fix_scale) for c in keep]
        second = self._job(maps, job.query_map, job.query_key, cands, job.thresholds, phase=2)
        second.skip_covered = job.skip_covered
        return second

    def conclude(self, result: RecognitionResult, reports: list[CandidateReport]) -> RecognitionResult:
        """The query's outcome from its candidates' reports: the best accepted candidate, after the
        consistency check (this recogniser's state: call in query order)."""
        result.candidates = reports
        best: CandidateReport | None = None
        for rep in reports:
            if rep.accepted and (best is None or rep.n_inliers > best.n_inliers):
                best = rep
        if best is not None:
            det = self._to_detection(best, result.query_map)
            result.detection = self._update_consistency(det)
            result.reason = "confirmed" if result.detection.confirmed else "awaiting_consistency"
        elif not result.reason:
            result.reason = "no_candidate_verified"
        result.time_ms += sum(r.time_ms for r in reports)
        log.debug(
            "placerec %s: %s (%d candidates, %.1f ms)",
            result.query_key,
            result.reason,
            len(result.candidates),
            result.time_ms,
        )
        return result

    def verify_pair(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        candidate_map: int,
        candidate_keys: Iterable[KfKey],
        fix_scale: bool = False,
        thresholds: Thresholds | None = None,
    ) -> RecognitionResult:
        """GNSS-guided retry (paper 2.5.3): verify given candidates with lowered thresholds.

        No BoW gate and no consistency wait: GNSS already says the trajectories meet here. The best
        accepted candidate is returned as a confirmed detection.
        """
        t0 = time.perf_counter()
        th = thresholds if thresholds is not None else self.options.gnss_retry_thresholds
        result = RecognitionResult(query_key, query_map, [])
        q_bow, _ = self._fv(maps[query_map].keyframes[query_key])
        cands = []
        for ck in candidate_keys:
            ckf = maps[candidate_map].keyframes.get(ck)
            score = q_bow.score(self._fv(ckf)[0]) if ckf is not None else 0.0
            cands.append((ck, candidate_map, "gnss_retry", score, fix_scale))
        job = self._job(maps, query_map, query_key, cands, th)
        job.skip_covered = False  # each given candidate is verified
        best: CandidateReport | None = None
        for rep in run_job(job):
            result.candidates.append(rep)
            if rep.accepted and (best is None or rep.n_inliers > best.n_inliers):
                best = rep
        if best is not None:
            det = self._to_detection(best, query_map)
            det.confirmed = True
            result.detection = det
            result.reason = "confirmed_gnss_retry"
        else:
            result.reason = "no_candidate_verified"
        result.time_ms = (time.perf_counter() - t0) * 1e3
        return result

    # --- internals -------------------------------------------------------------------------------
    def _grouped(
        self,
        maps: Mapping[int, Any],
        found: list[tuple[KfKey, float]],
        scores: NDArray[np.float64],
        allowed: Callable[[KfKey], bool] = lambda k: True,
    ) -> list[tuple[KfKey, float]]:
        """The retrieved keyframes to verify: one per covisibility group (``group_covisible = 0``: all)."""
        o = self.options
        if o.group_covisible <= 0:
            return found
        groups = group_candidates(
            self.kfdb, maps, found, scores, o.group_covisible, o.group_min_ratio, allowed, o.max_groups
        )
        return [(g.key, g.score) for g in groups]

    def _to_detection(self, rep: CandidateReport, query_map: int) -> Detection:
        assert rep.target_from_source is not None
        return Detection(
            query_key=rep.query_key,
            query_map=query_map,
            candidate_key=rep.candidate_key,
            candidate_map=rep.candidate_map,
            target_from_source=rep.target_from_source,
            n_inliers=rep.n_inliers,
            query_points=rep.query_points,
            candidate_points=rep.candidate_points,
            kind=rep.kind,
            query_xyz=rep.query_xyz,
        )

    def _update_consistency(self, det: Detection) -> Detection:
        """ORB-SLAM3-style: consecutive query keyframes (same agent) whose Sim(3)s agree."""
        o = self.options
        gkey = (det.query_map, det.candidate_map, det.query_key[0])
        prev = self._consistency.get(gkey)
        consistent = False
        if prev is not None and 0 < det.query_key[1] - prev.query_key[1] <= o.consistency_max_gap:
            consistent = self._sims_agree(prev.sim, det.target_from_source, det)
        if consistent and prev is not None:
            det.consistent = prev.count + 1
        else:
            det.consistent = 1
        best = det if prev is None or not consistent or det.n_inliers >= prev.best.n_inliers else prev.best
        if det.consistent >= o.consistency_required:
            det.confirmed = True
            self._consistency.pop(gkey, None)
            log.info(
                "place recognition confirmed: %s (map %d) <-> %s (map %d), %d inliers, scale %.4f",
                det.query_key,
                det.query_map,
                det.candidate_key,
                det.candidate_map,
                det.n_inliers,
                det.target_from_source.s,
            )
        else:
            self._consistency[gkey] = _Consistency(
                det.query_key, det.target_from_source, det.consistent, best
            )
        return det

    def _sims_agree(self, a: Sim3, b: Sim3, det: Detection) -> bool:
        o = self.options
        rel = a.inverse() @ b
        if rotation_angle_deg(rel.R) > o.consistency_max_rot_deg:
            return False
        if abs(np.log(rel.s)) > o.consistency_max_log_scale:
            return False
        # displacement of the detection's query points, relative to their spread (unit-free)
        return self._rel_shift(a, b, det) <= o.consistency_max_rel_shift

    def _rel_shift(self, a: Sim3, b: Sim3, det: Detection) -> float:
        pts = det.query_xyz
        if pts is None or len(pts) == 0:
            return 0.0
        pa, pb = a.apply(pts), b.apply(pts)
        spread = float(np.median(np.linalg.norm(pb - np.median(pb, axis=0), axis=1))) + 1e-9
        return float(np.median(np.linalg.norm(pa - pb, axis=1))) / spread
