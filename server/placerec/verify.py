"""Geometric verification of one candidate (paper 2.5.1), and of a query's candidates as a job.

BoW matches between the query keyframe and the candidate's window give 3D-3D correspondences; a
Sim(3) (SE(3) for metric maps) RANSAC, then guided search both ways and the bidirectional reprojection
refinement, twice, decide. :func:`verify` reads maps (or a job's slices of them, :mod:`.job`) through
``keyframes``, ``points`` and ``best_covisible``; :func:`run_job` verifies a query's candidates in
order, skipping those inside an accepted candidate's window (ORB-SLAM3), in whichever process runs it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.maps.vocabulary import FeatureVector
from hivemap.server.placerec.consensus import ransac_stage
from hivemap.server.placerec.descmatch import match_bow
from hivemap.server.placerec.job import QueryJob, maps_of
from hivemap.server.placerec.match import (
    PointSet,
    _best_covisible,
    _observations,
    _residuals,
    correction_of,
    estimate_sim3_ransac,
    guided_search,
    refine_sim3,
)
from hivemap.server.placerec.phases import screen_job
from hivemap.server.placerec.types import CandidateReport, PlaceRecOptions, Thresholds
from hivemap.server.placerec.views import KeyframeViews

log = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]


def run_job(job: QueryJob) -> list[CandidateReport]:
    """Verify the job's candidates in order; a candidate inside the window of one accepted before it is
    reported as covered, not verified. A phase-1 job screens every candidate instead (:mod:`.phases`)."""
    if job.phase == 1:
        return screen_job(job)
    maps = maps_of(job)
    views = KeyframeViews()

    def fv_of(kf: Any) -> FeatureVector:
        return job.features[kf.key]

    covered: set[KfKey] = set()
    out: list[CandidateReport] = []
    for c in job.candidates:
        if job.skip_covered and c.key in covered:
            rep = CandidateReport(job.query_key, c.key, c.map_id, c.kind, bow_score=c.bow_score)
            rep.reason = "covered_by_accepted_window"
            out.append(rep)
            continue
        rep = verify(job.options, fv_of, maps, job.query_map, job.query_key, c.map_id, c.key,
                     c.fix_scale, job.thresholds, c.kind, views,
                     c.correction_slack)  # fmt: skip
        rep.bow_score = c.bow_score
        rep.phase = job.phase
        out.append(rep)
        if rep.accepted:
            covered.add(c.key)
            covered.update(c.window)
    return out


def verify(
    o: PlaceRecOptions,
    fv_of: Callable[[Any], FeatureVector],
    maps: Mapping[int, Any],
    query_map: int,
    query_key: KfKey,
    cand_map: int,
    cand_key: KfKey,
    fix_scale: bool,
    th: Thresholds,
    kind: str,
    views: KeyframeViews | None = None,
    correction_slack: tuple[float, float] = (0.0, 0.0),
) -> CandidateReport:
    t0, c0 = time.perf_counter(), time.thread_time()
    rep = CandidateReport(query_key, cand_key, cand_map, kind)
    views = views if views is not None else KeyframeViews()
    try:
        _verify_inner(o, fv_of, maps, query_map, query_key, cand_map, cand_key, fix_scale, th, rep, views,
                      correction_slack)  # fmt: skip
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
    rep.cpu_ms = (time.thread_time() - c0) * 1e3
    return rep


@dataclass
class _Stage1:
    """What the first stage found: the maps, keyframes, the window, the 3D-3D correspondences and the
    RANSAC estimate (``inl``: its inliers among them)."""

    mq: Any
    mc: Any
    q: Any
    c: Any
    q_pk: list[PointKey | None]
    q_has: NDArray[np.bool_]
    window: list[KfKey]
    corr_q: list[int]
    corr_c: list[PointKey]
    xq: F64
    xc: F64
    c_cfw: F64
    max_err: float
    sim: Sim3
    inl: NDArray[np.bool_]


def _first_stage(
    o: PlaceRecOptions,
    fv_of: Callable[[Any], FeatureVector],
    maps: Mapping[int, Any],
    query_map: int,
    query_key: KfKey,
    cand_map: int,
    cand_key: KfKey,
    fix_scale: bool,
    th: Thresholds,
    rep: CandidateReport,
    views: KeyframeViews,
) -> _Stage1 | None:
    """BoW matches against the candidate window -> 3D-3D correspondences -> RANSAC; None (and
    ``rep.reason`` set) when the candidate cannot reach the thresholds. Reads the points' positions only."""
    mq, mc = maps.get(query_map), maps.get(cand_map)
    if mq is None or mc is None:
        # merged into another map since the query started (the event loop merges while this thread
        # verifies): this candidate is skipped, the agents' next keyframes query the merged map
        rep.reason = "map_merged_meanwhile"
        return None
    q = mq.keyframes[query_key]
    c = mc.keyframes.get(cand_key)
    if c is None:
        rep.reason = "candidate_missing"
        return None
    q_fv = fv_of(q)
    q_pk = views.point_keys(q)
    q_has = views.has(mq, q)
    if int(q_has.sum()) < th.min_matches:  # not enough query points for a verification to pass
        rep.reason = "few_bow_matches"
        return None

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
        w_fv = fv_of(w)
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
        return None
    xq = np.array([mq.points[q_pk[i]].xyz for i in corr_q], dtype=np.float64)
    xc = np.array([mc.points[k].xyz for k in corr_c], dtype=np.float64)

    # 2. RANSAC (3D threshold relative to the candidate scene depth)
    est = ransac_stage(o, xq, xc, c.world_from_cam, fix_scale, th, rep)
    if est is None:
        return None
    sim, inl, max_err = est
    c_cfw = se3_inverse(np.asarray(c.world_from_cam, dtype=np.float64))
    return _Stage1(mq, mc, q, c, q_pk, q_has, window, corr_q, corr_c, xq, xc, c_cfw, max_err, sim, inl)


def _verify_inner(
    o: PlaceRecOptions,
    fv_of: Callable[[Any], FeatureVector],
    maps: Mapping[int, Any],
    query_map: int,
    query_key: KfKey,
    cand_map: int,
    cand_key: KfKey,
    fix_scale: bool,
    th: Thresholds,
    rep: CandidateReport,
    views: KeyframeViews,
    correction_slack: tuple[float, float] = (0.0, 0.0),
) -> None:
    st = _first_stage(o, fv_of, maps, query_map, query_key, cand_map, cand_key, fix_scale, th, rep, views)
    if st is None:
        return
    mq, mc, q, c, q_pk, q_has, window = st.mq, st.mc, st.q, st.c, st.q_pk, st.q_has, st.window
    xq, xc, c_cfw, max_err, sim, inl = st.xq, st.xc, st.c_cfw, st.max_err, st.sim, st.inl
    corr_q, corr_c = st.corr_q, st.corr_c
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
    if rep.kind == "loop" and _implausible_correction(o, sim, q.world_from_cam, rep, correction_slack):
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
    if rep.kind == "loop" and _implausible_correction(o, sim, q.world_from_cam, rep, correction_slack):
        return
    rep.accepted = True
    rep.reason = "accepted"
    rep.query_xyz = np.array([mq.points[k].xyz for k in rep.query_points], dtype=np.float64)


def _implausible_correction(
    o: PlaceRecOptions, sim: Sim3, world_from_cam: Any, rep: CandidateReport, slack: tuple[float, float]
) -> bool:
    """True (and ``rep.reason`` set) when a loop's ``sim`` moves the query keyframe beyond the limits,
    each widened by ``slack`` [m, deg] (:func:`hivemap.maps.odometry.correction_slack`)."""
    if o.loop_max_correction_m <= 0 and o.loop_max_correction_deg <= 0:
        return False
    move, turn = correction_of(sim, world_from_cam)
    lim_m, lim_deg = o.loop_max_correction_m + slack[0], o.loop_max_correction_deg + slack[1]
    if (o.loop_max_correction_m > 0 and lim_m < move) or (o.loop_max_correction_deg > 0 and lim_deg < turn):
        rep.reason = "implausible_correction"
        return True
    return False
