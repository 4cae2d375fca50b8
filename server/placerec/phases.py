"""Two-phase verification of a query's candidates: a cheap first phase for all, the full one for few.

Most candidates a look-up retrieves are refused (about 1 in 60 was accepted on the team bench), yet each
cost the full verification's job: a slice of its window with every point's descriptor and observations,
taken on the serial place-recognition thread, then BoW matching, RANSAC, guided search and refinement.
As ORB-SLAM3 does (BoW matches and a RANSAC before any projection search), phase 1 runs only the
verification's first stage (:func:`.verify._first_stage`: BoW matches of the query against the window,
RANSAC on the matched points' positions, the inlier threshold) on light slices (positions only), for
every candidate. Phase 2 is the full verification, unchanged, of phase 1's survivors, on full slices of
their windows, taken after phase 1. It starts again from the BoW matches on its own slices (the maps may
have changed meanwhile), so what it reports does not depend on phase 1; :func:`combine_phases` gives the
reports one full verification of every candidate would give, except for the time they took.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.placerec.consensus import ransac_stage
from hivemap.server.placerec.descmatch import match_bow
from hivemap.server.placerec.job import Candidate, MapSlice, QueryJob
from hivemap.server.placerec.types import CandidateReport

log = logging.getLogger(__name__)
KfKey = tuple[str, int]

PASSED = "phase1_passed"


def screen_job(job: QueryJob) -> list[CandidateReport]:
    """Phase 1 of every candidate of ``job`` (a phase-1 job, light slices), in order."""
    slices = {s.map_id: _Rows(s) for s in job.slices}
    return [_screen(job, c, slices) for c in job.candidates]


class _Rows:
    """A light slice read by keyframe: per keypoint, the slice's row of the point it references (-1:
    none), from the slice's observations. Array work: the full verification's map-like view of a slice
    builds an object per point, most of phase 1's time when it used it."""

    def __init__(self, s: MapSlice) -> None:
        self.slice = s
        self._index = {kf.key: i for i, kf in enumerate(s.keyframes)}
        order = np.argsort(s.obs_kf, kind="stable")
        bounds = np.searchsorted(s.obs_kf[order], np.arange(len(s.keyframes) + 1))
        self._refs = [order[a:b] for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)]
        self._rows: dict[KfKey, NDArray[np.int64]] = {}

    def keyframe(self, key: KfKey) -> object | None:
        i = self._index.get(key)
        return None if i is None else self.slice.keyframes[i]

    def rows(self, key: KfKey) -> NDArray[np.int64]:
        r = self._rows.get(key)
        if r is None:
            i = self._index[key]
            sel = self._refs[i]
            r = np.full(len(self.slice.keyframes[i].point_ids), -1, dtype=np.int64)
            r[self.slice.obs_kp[sel]] = self.slice.obs_point[sel]
            self._rows[key] = r
        return r


def _screen(job: QueryJob, c: Candidate, slices: dict[int, _Rows]) -> CandidateReport:
    """Phase 1 of one candidate: what the full verification's first stage does
    (:func:`.verify._first_stage`: BoW matches of the query against the window, each query keypoint and
    each point used once, in the window's order; RANSAC; the inlier threshold), on point rows instead of
    point keys. ``reason`` is :data:`PASSED` for a survivor."""
    t0, c0 = time.perf_counter(), time.thread_time()
    rep = CandidateReport(job.query_key, c.key, c.map_id, c.kind, bow_score=c.bow_score, phase=1)
    try:
        if _first_stage(job, c, slices, rep):
            rep.reason = PASSED
    except Exception as e:  # a bad candidate must never break ingest; it is logged and reported
        log.exception("phase 1 of %s against %s failed", job.query_key, c.key)
        rep.reason = f"error:{type(e).__name__}"
    rep.time_ms = (time.perf_counter() - t0) * 1e3
    rep.cpu_ms = (time.thread_time() - c0) * 1e3
    return rep


def _first_stage(job: QueryJob, c: Candidate, slices: dict[int, _Rows], rep: CandidateReport) -> bool:
    o, th = job.options, job.thresholds
    sq, sc = slices.get(job.query_map), slices.get(c.map_id)
    if sq is None or sc is None:
        rep.reason = "map_merged_meanwhile"
        return False
    q: Any = sq.keyframe(job.query_key)
    ck: Any = sc.keyframe(c.key)
    if q is None:
        rep.reason = "points_fused_meanwhile"
        return False
    if ck is None:
        rep.reason = "candidate_missing"
        return False
    q_rows = sq.rows(q.key)
    q_has = q_rows >= 0
    if int(q_has.sum()) < th.min_matches:
        rep.reason = "few_bow_matches"
        return False
    window = [c.key] + [k for k in job.best_covisible.get(c.key, [])[: o.covisible_window] if k != c.key]
    seen_q = np.zeros(len(q_rows), dtype=bool)
    seen_c = np.zeros(len(sc.slice.xyz), dtype=bool)
    corr_q: list[NDArray[np.int64]] = []
    corr_c: list[NDArray[np.int64]] = []
    q_fv = job.features[q.key]
    for wk in window:
        w: Any = sc.keyframe(wk)
        if w is None:
            continue
        w_rows = sc.rows(wk)
        pairs = match_bow(q_fv, q.descriptors, job.features[wk], w.descriptors, o.bow_max_distance,
                          o.bow_ratio, q_has, w_rows >= 0)  # fmt: skip
        iq, pc = pairs[:, 0], w_rows[pairs[:, 1]]
        # a window's pairs use each query keypoint once; keypoints of one keyframe may share a point
        idx = np.flatnonzero(~seen_q[iq] & ~seen_c[pc])
        _, first = np.unique(pc[idx], return_index=True)
        idx = idx[np.sort(first)]
        iq, pc = iq[idx], pc[idx]
        seen_q[iq] = True
        seen_c[pc] = True
        corr_q.append(iq)
        corr_c.append(pc)
    cq = np.concatenate(corr_q) if corr_q else np.zeros(0, np.int64)
    cc = np.concatenate(corr_c) if corr_c else np.zeros(0, np.int64)
    rep.n_matches = len(cq)
    if rep.n_matches < th.min_matches:
        rep.reason = "few_bow_matches"
        return False
    xq, xc = sq.slice.xyz[q_rows[cq]], sc.slice.xyz[cc]
    return ransac_stage(o, xq, xc, ck.world_from_cam, c.fix_scale, th, rep) is not None


def survivors(job: QueryJob, reports: list[CandidateReport]) -> list[Candidate]:
    """The candidates of a phase-1 job that passed it, in the job's order."""
    return [c for c, r in zip(job.candidates, reports, strict=True) if r.reason == PASSED]


def combine_phases(
    job: QueryJob, first: list[CandidateReport], second: list[CandidateReport] | None
) -> list[CandidateReport]:
    """The query's reports from phase 1's (``first``, one per candidate of ``job``) and phase 2's
    (``second``, one per survivor in order; None: phase 2 did not run, the query's map changed), as a full
    verification of every candidate in order gives them: a survivor's phase-2 report (its time includes
    phase 1's), a refused candidate's phase-1 report, or ``covered_by_accepted_window`` for a candidate
    inside the window of one accepted before it (the full verification skips those)."""
    if second is not None and len(second) != sum(r.reason == PASSED for r in first):
        raise ValueError("phase 2 reports one report per phase-1 survivor")
    rest = iter(second or [])
    covered: set[tuple[str, int]] = set()
    out: list[CandidateReport] = []
    for c, r1 in zip(job.candidates, first, strict=True):
        if r1.reason == PASSED and second is not None:
            r = next(rest)
            r.phase = 2
        elif job.skip_covered and c.key in covered:
            r = CandidateReport(job.query_key, c.key, c.map_id, c.kind, bow_score=c.bow_score, phase=1)
            r.reason = "covered_by_accepted_window"
        else:
            r = r1
            if r.reason == PASSED:
                r.reason = "map_merged_meanwhile"
        if r is not r1:
            r.time_ms += r1.time_ms
            r.cpu_ms += r1.cpu_ms
        out.append(r)
        if r.accepted:
            covered.add(c.key)
            covered.update(c.window)
    return out
