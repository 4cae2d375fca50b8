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

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.distance import pdist, squareform

from hivemap.server.placerec.job import Candidate, QueryJob
from hivemap.server.placerec.types import CandidateReport

PASSED = "phase1_passed"
# above this many matches the pre-test is not run (its pair matrix grows with the square), above this
# many matches left in the core its links are not peeled (a matrix product: beyond ~400 it costs more
# than the RANSAC it would save); peeling rounds of the links (stopping early: a looser, valid bound)
_PRETEST_MAX = 600
_TRUSS_MAX = 400
_TRUSS_ROUNDS = 4


def rigid_consensus_bound(xq: NDArray[np.float64], xc: NDArray[np.float64], max_err: float, k: int) -> int:
    """An upper bound on the inliers of a rigid transform ``xc ~ T xq`` (matched points (N, 3)) at error
    ``max_err`` that has ``k`` or more of them; below ``k``: no rigid transform has ``k`` inliers.

    Two inliers of a rigid transform keep their distance to within ``2 max_err`` (triangle inequality;
    pycolmap counts a match within ``max_err`` as an inlier), so a transform's inliers are a clique of the
    graph linking the matches that do. In a clique of ``k`` every match has ``k - 1`` links and every link
    ``k - 2`` common neighbours, so matches and links with fewer are peeled off (the graph's ``k``-core,
    then its ``k``-truss); the matches left are returned. Wrong matches rarely keep their distances to
    each other, so little is left of them."""
    n = len(xq)
    if n < k or n > _PRETEST_MAX or k < 3:
        return n
    tol = 2.0 * max_err * (1 + 1e-9)  # a hair wider: a pair exactly at the bound stays linked
    adj = squareform(np.abs(pdist(xq) - pdist(xc)) <= tol)
    alive = _core(adj, k - 1)
    if alive.sum() < k or alive.sum() > _TRUSS_MAX:
        return int(alive.sum())
    # links: common neighbours by a product of the core's adjacency (float32: exact for these counts)
    a = adj[np.ix_(alive, alive)].astype(np.float32)
    for _ in range(_TRUSS_ROUNDS):
        weak = (a > 0) & ((a @ a) < k - 2)
        if not weak.any():
            break
        a[weak] = 0.0
        left = _core(a > 0, k - 1)
        if left.sum() < k:
            return int(left.sum())
        a = a[np.ix_(left, left)]
    return int(_core(a > 0, k - 1).sum())


def _core(adj: NDArray[np.bool_], d: int) -> NDArray[np.bool_]:
    """The nodes of the graph ``adj`` left after removing, again and again, those with fewer than ``d``
    links."""
    deg = adj.sum(axis=1)
    alive = np.ones(len(adj), dtype=bool)
    while True:
        drop = alive & (deg < d)
        if not drop.any():
            return alive
        alive &= ~drop
        deg = deg - adj[:, drop].sum(axis=1)


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
