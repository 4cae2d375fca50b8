"""Which candidates can still pass: the rigid-consensus pre-test and the RANSAC stage of a verification.

Both phases of a verification (:mod:`.phases`, :mod:`.verify`) end their first stage here: 3D-3D matches
-> (metric maps) the pre-test -> RANSAC -> the inlier threshold.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.distance import pdist, squareform

from hivemap.maps.geometry import Sim3, se3_inverse
from hivemap.server.placerec.match import estimate_sim3_ransac
from hivemap.server.placerec.types import CandidateReport, PlaceRecOptions, Thresholds

F64 = NDArray[np.float64]


def ransac_stage(
    o: PlaceRecOptions,
    xq: F64,
    xc: F64,
    cand_world_from_cam: F64,
    fix_scale: bool,
    th: Thresholds,
    rep: CandidateReport,
) -> tuple[Sim3, NDArray[np.bool_], float] | None:
    """RANSAC of ``xc ~ S xq`` (the query's and the candidate's matched points, (N, 3)) with its 3D
    threshold relative to the candidate keyframe's scene depth: the estimate, its inliers and the
    threshold, or None (``rep.reason`` set) when it cannot reach ``th.min_inliers``."""
    c_cfw = se3_inverse(np.asarray(cand_world_from_cam, dtype=np.float64))
    depth_c = np.median(np.linalg.norm(xc @ c_cfw[:3, :3].T + c_cfw[:3, 3], axis=1))
    max_err = max(o.ransac_min_error, o.ransac_rel_error * float(depth_c))
    pretest = o.consensus_pretest and fix_scale
    if pretest and rigid_consensus_bound(xq, xc, max_err, th.min_inliers) < th.min_inliers:
        # no rigid transform can have enough inliers (they would keep their distances): RANSAC would
        # run to its trial limit for nothing
        rep.reason = "few_consistent_matches"
        return None
    est = estimate_sim3_ransac(xq, xc, max_err, fix_scale, o.ransac_min_trials)
    if est is None:
        rep.reason = "ransac_failed"
        return None
    sim, inl = est
    rep.n_ransac_inliers = int(inl.sum())
    if rep.n_ransac_inliers < th.min_inliers:
        rep.reason = "few_ransac_inliers"
        return None
    return sim, inl, max_err


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
