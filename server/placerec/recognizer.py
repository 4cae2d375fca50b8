"""The place recogniser: BoW retrieval, verification of each candidate and the choice of the winner."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.maps.kfdb import KeyframeDatabase
from hivemap.maps.vocabulary import BowVector, FeatureVector, Vocabulary
from hivemap.server.placerec.match import (
    PointSet,
    _best_covisible,
    _observations,
    _residuals,
    correction_of,
    estimate_sim3_ransac,
    guided_search,
    match_bow,
    refine_sim3,
)
from hivemap.server.placerec.retrieve import group_candidates
from hivemap.server.placerec.types import (
    CandidateReport,
    Detection,
    PlaceRecOptions,
    RecognitionResult,
    Thresholds,
)
from hivemap.server.placerec.views import HasCache, KeyframeViews

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
        # agent groups of one map joined only by a loose edge (a session guess on trial): a loop between
        # them may ask for any correction, it is the evidence that judges the guess (set by the back-end
        # from the event loop, replaced whole)
        self.loose_pairs: tuple[tuple[frozenset[str], frozenset[str]], ...] = ()

    # --- database ------------------------------------------------------------------------------
    def add_keyframe(self, map_id: int, kf: Any) -> BowVector:
        bow, fv = self.vocabulary.transform(kf.descriptors)
        self.kfdb.add(kf.key, map_id, bow, fv)
        return bow

    def remove_keyframe(self, key: KfKey) -> None:
        self.kfdb.remove(key)
        self._has.forget(key)

    def on_merge(self, target_map: int, source_map: int) -> None:
        """After ``source_map`` was merged into ``target_map``: relabel the index, drop stale state."""
        self.kfdb.reassign_map(source_map, target_map)
        for k in [k for k in self._consistency if source_map in k[:2] or target_map in k[:2]]:
            del self._consistency[k]

    def _fv(self, kf: Any) -> tuple[BowVector, FeatureVector]:
        fv = self.kfdb.features(kf.key) if kf.key in self.kfdb else None
        if fv is None:
            bow, fv = self.vocabulary.transform(kf.descriptors)
            return bow, fv
        return self.kfdb.bow(kf.key), fv

    # --- main entry ------------------------------------------------------------------------------
    def detect(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        n_agents: int,
        fix_scale: bool | Callable[[int, int], bool] = False,
        merge: bool = True,
        loop: bool = True,
    ) -> RecognitionResult:
        """Look for the query keyframe's place in other maps (merge) and in its own map (loop).

        ``fix_scale``: True for metric agents (SE(3)), or a function (query map, candidate map) -> bool.
        """
        t0 = time.perf_counter()
        o = self.options
        mq = maps[query_map]
        q = mq.keyframes[query_key]
        bow, _ = self._fv(q)
        n_cand = max(1, o.candidates_per_agent * max(1, n_agents))
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
        best: CandidateReport | None = None
        views = KeyframeViews(self._has)
        covered: set[KfKey] = set()  # windows of accepted candidates (ORB-SLAM3 skips those)
        for ck, score, kind in todo[: o.max_verifications]:
            cmap_id = self.kfdb.map_of(ck)
            if ck in covered:
                rep = CandidateReport(query_key, ck, cmap_id, kind, bow_score=score)
                rep.reason = "covered_by_accepted_window"
                result.candidates.append(rep)
                continue
            fs = fix_scale(query_map, cmap_id) if callable(fix_scale) else bool(fix_scale)
            rep = self._verify(maps, query_map, query_key, cmap_id, ck, fs, o.thresholds, kind, views)
            rep.bow_score = score
            result.candidates.append(rep)
            if rep.accepted:
                covered.add(ck)
                covered.update(_best_covisible(maps[cmap_id], ck, o.covisible_window))
                if best is None or rep.n_inliers > best.n_inliers:
                    best = rep
        if best is not None:
            det = self._to_detection(best, query_map)
            result.detection = self._update_consistency(det)
            result.reason = "confirmed" if result.detection.confirmed else "awaiting_consistency"
        elif not result.reason:
            result.reason = "no_candidate_verified" if todo else "no_bow_candidates"
        result.time_ms = (time.perf_counter() - t0) * 1e3
        log.debug(
            "placerec %s: %s (%d candidates, %.1f ms)",
            query_key,
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
        best: CandidateReport | None = None
        q_bow, _ = self._fv(maps[query_map].keyframes[query_key])
        views = KeyframeViews(self._has)
        for ck in candidate_keys:
            rep = self._verify(
                maps, query_map, query_key, candidate_map, ck, fix_scale, th, "gnss_retry", views
            )
            ckf = maps[candidate_map].keyframes.get(ck)
            if ckf is not None:
                rep.bow_score = q_bow.score(self._fv(ckf)[0])
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
            self.kfdb, maps, found, scores, o.group_covisible, o.group_min_ratio, allowed
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

    def _verify(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        cand_map: int,
        cand_key: KfKey,
        fix_scale: bool,
        th: Thresholds,
        kind: str,
        views: KeyframeViews | None = None,
    ) -> CandidateReport:
        t0 = time.perf_counter()
        rep = CandidateReport(query_key, cand_key, cand_map, kind)
        views = views if views is not None else KeyframeViews()
        try:
            self._verify_inner(maps, query_map, query_key, cand_map, cand_key, fix_scale, th, rep, views)
        except KeyError as e:
            # a point or keyframe the verification reads was fused away by the event loop meanwhile (about
            # ten per factory run): skipped, as a merged-away map is
            log.debug("verification of %s against %s: %r fused meanwhile", query_key, cand_key, e)
            rep.accepted = False
            rep.reason = "points_fused_meanwhile"
        except Exception as e:  # a bad candidate must never break ingest; it is logged and reported
            log.exception("verification of %s against %s failed", query_key, cand_key)
            rep.accepted = False
            rep.reason = f"error:{type(e).__name__}"
        rep.time_ms = (time.perf_counter() - t0) * 1e3
        return rep

    def _verify_inner(
        self,
        maps: Mapping[int, Any],
        query_map: int,
        query_key: KfKey,
        cand_map: int,
        cand_key: KfKey,
        fix_scale: bool,
        th: Thresholds,
        rep: CandidateReport,
        views: KeyframeViews,
    ) -> None:
        o = self.options
        mq, mc = maps.get(query_map), maps.get(cand_map)
        if mq is None or mc is None:
            # merged into another map since the query started (the event loop merges while this thread
            # verifies): this candidate is skipped, the agents' next keyframes query the merged map
            rep.reason = "map_merged_meanwhile"
            return
        q = mq.keyframes[query_key]
        c = mc.keyframes.get(cand_key)
        if c is None:
            rep.reason = "candidate_missing"
            return
        _, q_fv = self._fv(q)
        q_pk = views.point_keys(q)
        q_has = views.has(mq, q)
        if int(q_has.sum()) < th.min_matches:  # not enough query points for a verification to pass
            rep.reason = "few_bow_matches"
            return

        # 1. BoW matches against the candidate window -> 3D-3D correspondences
        window = [cand_key] + [k for k in _best_covisible(mc, cand_key, o.covisible_window) if k != cand_key]
        corr_q: list[int] = []  # query keypoint index
        corr_c: list[PointKey] = []
        seen_c: set[PointKey] = set()
        seen_q: set[int] = set()
        for wk in window:
            w = mc.keyframes.get(wk)
            if w is None:
                continue
            _, w_fv = self._fv(w)
            w_pk = views.point_keys(w)
            w_has = views.has(mc, w)
            bow_pairs = match_bow(
                q_fv, q.descriptors, w_fv, w.descriptors, o.bow_max_distance, o.bow_ratio, q_has, w_has
            )
            for iq, iw in bow_pairs.tolist():
                pc = w_pk[iw]
                if iq in seen_q or pc is None or pc in seen_c:
                    continue
                seen_q.add(iq)
                seen_c.add(pc)
                corr_q.append(iq)
                corr_c.append(pc)
        rep.n_matches = len(corr_q)
        if rep.n_matches < th.min_matches:
            rep.reason = "few_bow_matches"
            return
        xq = np.array([mq.points[q_pk[i]].xyz for i in corr_q], dtype=np.float64)
        xc = np.array([mc.points[k].xyz for k in corr_c], dtype=np.float64)

        # 2. RANSAC (3D threshold relative to the candidate scene depth)
        c_cfw = se3_inverse(np.asarray(c.world_from_cam, dtype=np.float64))
        depth_c = np.median(np.linalg.norm(xc @ c_cfw[:3, :3].T + c_cfw[:3, 3], axis=1))
        max_err = max(o.ransac_min_error, o.ransac_rel_error * float(depth_c))
        est = estimate_sim3_ransac(xq, xc, max_err, fix_scale, o.ransac_min_trials)
        if est is None:
            rep.reason = "ransac_failed"
            return
        sim, inl = est
        rep.n_ransac_inliers = int(inl.sum())
        if rep.n_ransac_inliers < th.min_inliers:
            rep.reason = "few_ransac_inliers"
            return
        if fix_scale and o.metric_max_log_scale > 0:
            # metric agents: the free-scale estimate must agree with scale 1 (sanity gate); run only for
            # a candidate the rigid estimate accepted, as it rejects nothing else
            free = estimate_sim3_ransac(xq, xc, max_err, False, o.ransac_min_trials)
            if (
                free is not None
                and free[1].sum() >= th.min_inliers
                and abs(np.log(free[0].s)) > o.metric_max_log_scale
            ):
                rep.n_ransac_inliers = int(free[1].sum())
                rep.scale = free[0].s
                rep.reason = "metric_scale_inconsistent"
                return
        sim_ransac = sim
        if rep.kind == "loop" and self._implausible_correction(sim, q.world_from_cam, rep):
            return

        # 3. guided search both ways, refine, guided search again, refine again
        q_cfw = se3_inverse(np.asarray(q.world_from_cam, dtype=np.float64))
        window_kfs = [mc.keyframes[k] for k in window if k in mc.keyframes]
        cand = PointSet.of(mc, views.window_points(mc, window_kfs))
        qpts = PointSet.of(mq, list(dict.fromkeys(q_pk[i] for i in np.flatnonzero(q_has).tolist())))  # type: ignore[misc]
        c_pk, c_has = views.point_keys(c), views.has(mc, c)
        pairs: dict[int, PointKey] = {corr_q[i]: corr_c[i] for i in np.flatnonzero(inl)}
        for _ in range(2):
            pairs = guided_search(o, q, q_cfw, q_pk, c, c_cfw, c_pk, c_has, cand, qpts, sim, pairs)
            obs = _observations(pairs, q, q_pk, mq, mc, window_kfs)
            if len(obs.xc) < 3:
                break
            if o.refine_depth_sigma_rel > 0:
                obs.sig3 = o.refine_depth_sigma_rel * np.maximum(
                    np.linalg.norm(obs.xc - np.asarray(c.world_from_cam)[:3, 3], axis=1), 1e-6
                )
            if len(obs.xc) > o.refine_max_points:  # plenty for 7 parameters; keeps refinement ~10 ms
                sub = np.random.default_rng(0).choice(len(obs.xc), o.refine_max_points, replace=False)
                obs = obs.subset(np.sort(sub))
            sim = refine_sim3(sim, obs, q.camera, q_cfw, fix_scale, o.huber_px)
        pairs = guided_search(o, q, q_cfw, q_pk, c, c_cfw, c_pk, c_has, cand, qpts, sim, pairs)
        obs = _observations(pairs, q, q_pk, mq, mc, window_kfs)
        ra, rb, has_b = _residuals(sim, obs, q.camera, q_cfw)
        ok = ((ra**2).sum(axis=1) < o.inlier_chi2) & (~has_b | ((rb**2).sum(axis=1) < o.inlier_chi2))
        keys = list(pairs.items())
        rep.n_projected = len(keys)
        rep.n_inliers = int(ok.sum())
        rep.scale = sim.s
        rep.target_from_source = sim
        inl_pairs = [keys[i] for i in np.flatnonzero(ok)]
        rep.query_points = [q_pk[iq] for iq, _ in inl_pairs if q_pk[iq] is not None]  # type: ignore[misc]
        rep.candidate_points = [pc for iq, pc in inl_pairs if q_pk[iq] is not None]
        if not (o.min_scale <= sim.s <= o.max_scale):
            rep.reason = "scale_out_of_range"
            return
        if rotation_angle_deg(sim.R @ sim_ransac.R.T) > o.max_refine_rot_deg:
            rep.reason = "refinement_jump"
            return
        if rep.n_inliers < th.min_projected:
            rep.reason = "few_projected_inliers"
            return
        if rep.kind == "loop" and self._implausible_correction(sim, q.world_from_cam, rep):
            return
        rep.accepted = True
        rep.reason = "accepted"
        rep.query_xyz = np.array([mq.points[k].xyz for k in rep.query_points], dtype=np.float64)

    def _implausible_correction(self, sim: Sim3, world_from_cam: Any, rep: CandidateReport) -> bool:
        """True (and ``rep.reason`` set) when a loop's ``sim`` moves the query keyframe beyond the limits."""
        o = self.options
        if o.loop_max_correction_m <= 0 and o.loop_max_correction_deg <= 0:
            return False
        a, b = rep.query_key[0], rep.candidate_key[0]
        if any((a in s and b in t) or (a in t and b in s) for s, t in self.loose_pairs):
            return False
        move, turn = correction_of(sim, world_from_cam)
        if (0 < o.loop_max_correction_m < move) or (0 < o.loop_max_correction_deg < turn):
            rep.reason = "implausible_correction"
            return True
        return False
