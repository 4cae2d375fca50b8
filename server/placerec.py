"""Place recognition and Sim(3) estimation between keyframes of the map stack (paper 2.4, 2.5.1).

Pipeline for a query keyframe ``Q`` of map ``Mq`` (one call of ``PlaceRecognizer.detect``):

1. BoW retrieval in the keyframe database: ``4 x number of agents`` candidates from other maps
   (merge) and/or from ``Mq`` itself outside ``Q``'s covisible keyframes (intra-map loop, with
   ORB-SLAM's minimum covisible score). A cheap feasibility check (seed 004) runs first.
2. For each candidate ``C``: 2D-2D ORB matches between ``Q`` and each keyframe of the window
   ``C + its 5 best covisible keyframes`` through the BoW direct index (features compared only under
   the same vocabulary node) -> 3D-3D correspondences through the map points (as ORB-SLAM3 does, the
   query keyframe is matched against the candidate's window).
3. Sim(3) (or SE(3) for metric agents) RANSAC with ``pycolmap.estimate_sim3d_robust`` /
   ``estimate_rigid3d_robust``; threshold relative to the scene depth.
4. Guided search in both directions (candidate-window points projected into ``Q``; ``Q``'s points
   projected into ``C``) adds matches; the Sim(3) is refined by minimising the bidirectional
   reprojection error (paper 2.5.1; scipy ``least_squares``, Huber loss, parameters
   ``[rotvec, t, log s]``), then a second guided search; the candidate's votes are its matches.
5. Acceptance thresholds (peers: >= 20 matches, >= 20 inliers, >= 40 after projection), sanity gates
   (scale range, metric agents' free-scale estimate close to 1, refinement did not jump), the
   candidate with most votes wins, and a detection is confirmed after 3 consistent detections
   (consecutive query keyframes of the same agent whose Sim(3)s agree, ORB-SLAM3-style).

Every candidate and the reason it was rejected is returned (``CandidateReport.to_dict()``) for the
server's event stream. ``verify_pair`` is the entry point for the GNSS-guided retry (paper 2.5.3):
specific candidates, lowered thresholds, no BoW gate.

Conventions: ``target_from_source`` of a detection maps points of the QUERY map (source) into the
CANDIDATE map (target) frame: ``p_cand = s R p_query + t`` (``Sim3``). The map model is used through
its contract (``Map.keyframes``, ``Map.points``, ``Map.best_covisible``, ``Keyframe.point_keys``...).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse, so3_exp
from hivemap.maps.kfdb import Feasibility, KeyframeDatabase
from hivemap.maps.vocabulary import BowVector, FeatureVector, Vocabulary

log = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ----------------------------------------------------------------------------------------------
# options and results
@dataclass(frozen=True)
class Thresholds:
    """Acceptance thresholds of one geometric verification (peers: 20 / 20 / 40)."""

    min_matches: int = 20  # BoW 2D-2D matches giving 3D-3D correspondences
    min_inliers: int = 20  # RANSAC inliers
    min_projected: int = 40  # matches after guided search + refinement


@dataclass(frozen=True)
class PlaceRecOptions:
    candidates_per_agent: int = 4  # paper 2.4: 4 x number of agents
    covisible_window: int = 5  # candidate + its 5 best covisible keyframes
    thresholds: Thresholds = Thresholds()
    gnss_retry_thresholds: Thresholds = Thresholds(min_matches=12, min_inliers=10, min_projected=25)
    consistency_required: int = 3  # detections before a merge / loop is confirmed
    consistency_max_gap: int = 8  # max keyframe-id gap between consecutive consistent detections
    consistency_max_rot_deg: float = 3.0
    consistency_max_rel_shift: float = 0.05  # query points moved / their median depth
    consistency_max_log_scale: float = 0.05
    # BoW matching (ORB-SLAM: TH_LOW = 50, ratio 0.75)
    bow_max_distance: int = 50
    bow_ratio: float = 0.75
    # guided search
    search_radius_px: float = 8.0  # scaled by 1.2^octave of the keypoint
    search_max_distance: int = 50
    # RANSAC: 3D error threshold = ransac_rel_error x median depth of the target points (>= floor)
    ransac_rel_error: float = 0.03
    ransac_min_error: float = 0.01
    ransac_min_trials: int = 200
    # refinement: residuals whitened by sigma = 1.2^octave px; Huber at 2.45 (chi2 2 dof 95%)
    huber_px: float = 2.45
    inlier_chi2: float = 9.21  # chi2 2 dof 99%: per-direction inlier test of a correspondence
    refine_max_points: int = 300  # correspondences used by the refinement (random subset beyond)
    # weak 3D term in the refinement: sigma = this x distance of the point from the candidate camera
    # (reprojection dominates sideways: 1 px ~ 0.2 % of depth; the 3D term fixes scale along the rays)
    refine_depth_sigma_rel: float = 0.02
    # sanity gates
    min_scale: float = 0.05
    max_scale: float = 20.0
    metric_max_log_scale: float = 0.15  # metric agents: free-scale estimate must be within ~16% of 1
    max_refine_rot_deg: float = 10.0
    # feasibility check (seed 004): ext >= ratio * internal, else skip verification of merge candidates
    feasibility_ratio: float = 0.3
    use_feasibility: bool = True
    max_verifications: int = 64  # budget per query
    # Loops (query and candidate in one map, whose frame already holds both): a candidate whose transform
    # would move the query keyframe farther, or turn it more, than this is a false match and is rejected
    # as "implausible_correction" right after RANSAC and again after refinement, so it neither costs the
    # guided search nor displaces a true candidate of the same query. 0 disables (the server sets them
    # from BackendOptions.loop_max_correction_* for metric agents). Factory01, four runs at bb84f09
    # behaviour: 41-44 % of the queries that had an accepted loop candidate had a best one asking for
    # more than 1 m (up to 40 m and 13 deg: the rendered site repeats its textures), and each of those
    # restarted its agent's consistency count.
    loop_max_correction_m: float = 0.0
    loop_max_correction_deg: float = 0.0


@dataclass
class CandidateReport:
    """One verified (or skipped) candidate and why it was accepted or rejected."""

    query_key: KfKey
    candidate_key: KfKey
    candidate_map: int
    kind: str  # "merge" | "loop" | "gnss_retry"
    bow_score: float = 0.0
    n_matches: int = 0
    n_ransac_inliers: int = 0
    n_projected: int = 0
    n_inliers: int = 0
    scale: float | None = None
    accepted: bool = False
    reason: str = ""
    time_ms: float = 0.0
    target_from_source: Sim3 | None = field(default=None, repr=False)
    query_points: list[PointKey] = field(default_factory=list, repr=False)
    candidate_points: list[PointKey] = field(default_factory=list, repr=False)
    query_xyz: F64 | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        skip = ("target_from_source", "query_points", "candidate_points", "query_xyz")
        d = {k: v for k, v in asdict(self).items() if k not in skip}
        d["query_key"] = list(self.query_key)
        d["candidate_key"] = list(self.candidate_key)
        if self.target_from_source is not None:
            d["target_from_source"] = self.target_from_source.matrix().tolist()
        return d


@dataclass
class Detection:
    """A verified place match between the query map and a candidate map.

    ``target_from_source``: candidate-map frame from query-map frame. ``query_points[i]`` and
    ``candidate_points[i]`` are the same physical point (for fusing duplicates).
    ``consistent``: how many consistent detections so far; ``confirmed`` when it reached the required.
    """

    query_key: KfKey
    query_map: int
    candidate_key: KfKey
    candidate_map: int
    target_from_source: Sim3
    n_inliers: int
    query_points: list[PointKey]
    candidate_points: list[PointKey]
    kind: str
    consistent: int = 1
    confirmed: bool = False
    query_xyz: F64 | None = field(default=None, repr=False)  # inlier query points (consistency check)

    @property
    def is_loop(self) -> bool:
        return self.query_map == self.candidate_map

    def merge_args(self, target_map: int) -> tuple[int, int, Sim3, list[tuple[PointKey, PointKey]]]:
        """Arguments of ``MapStack.merge(target_id, source_id, target_from_source, fused_pairs)`` with
        ``target_map`` (the query's or the candidate's map, e.g. the one holding the UGV) kept as the
        frame of the result; ``fused_pairs`` are ``(target_point, source_point)``."""
        if target_map == self.candidate_map:
            pairs = list(zip(self.candidate_points, self.query_points, strict=True))
            return self.candidate_map, self.query_map, self.target_from_source, pairs
        if target_map == self.query_map:
            pairs = list(zip(self.query_points, self.candidate_points, strict=True))
            return self.query_map, self.candidate_map, self.target_from_source.inverse(), pairs
        raise ValueError(f"map {target_map} is not part of this detection")

    def to_dict(self) -> dict[str, Any]:
        return {
            "query_key": list(self.query_key),
            "query_map": self.query_map,
            "candidate_key": list(self.candidate_key),
            "candidate_map": self.candidate_map,
            "kind": self.kind,
            "n_inliers": self.n_inliers,
            "consistent": self.consistent,
            "confirmed": self.confirmed,
            "scale": self.target_from_source.s,
            "target_from_source": self.target_from_source.matrix().tolist(),
        }


@dataclass
class RecognitionResult:
    query_key: KfKey
    query_map: int
    candidates: list[CandidateReport]
    detection: Detection | None = None  # best verified candidate of this query (may be unconfirmed)
    feasibility: Feasibility | None = None
    reason: str = ""
    time_ms: float = 0.0

    @property
    def confirmed(self) -> Detection | None:
        return self.detection if self.detection is not None and self.detection.confirmed else None

    def events(self) -> list[dict[str, Any]]:
        """JSON-able records for /events: one per candidate plus a summary."""
        out: list[dict[str, Any]] = [{"type": "placerec_candidate", **c.to_dict()} for c in self.candidates]
        summary: dict[str, Any] = {
            "type": "placerec",
            "query_key": list(self.query_key),
            "query_map": self.query_map,
            "n_candidates": len(self.candidates),
            "reason": self.reason,
            "time_ms": round(self.time_ms, 2),
        }
        if self.feasibility is not None:
            summary["feasibility"] = {
                "feasible": self.feasibility.feasible,
                "external_score": self.feasibility.external_score,
                "internal_score": self.feasibility.internal_score,
            }
        if self.detection is not None:
            summary["detection"] = self.detection.to_dict()
        out.append(summary)
        return out


# ----------------------------------------------------------------------------------------------
# matching primitives
def _u64(d: NDArray[np.uint8]) -> NDArray[np.uint64]:
    return np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, 32).view(np.uint64)


def match_bow(
    fv_a: FeatureVector,
    desc_a: NDArray[np.uint8],
    fv_b: FeatureVector,
    desc_b: NDArray[np.uint8],
    max_distance: int = 50,
    ratio: float = 0.75,
    mask_a: NDArray[np.bool_] | None = None,
    mask_b: NDArray[np.bool_] | None = None,
) -> I64:
    """Direct-index-accelerated matching (DBoW2 / ORB-SLAM ``SearchByBoW``), fully vectorised.

    Features are compared only when they fall under the same vocabulary node. For every feature of
    ``a`` the best ``b`` must be within ``max_distance`` bits and pass the ratio test against the
    second best; each ``b`` is used once (the closest wins). Returns (K, 2) index pairs (a, b).
    """
    ia = np.arange(len(desc_a)) if mask_a is None else np.flatnonzero(mask_a)
    ib = np.arange(len(desc_b)) if mask_b is None else np.flatnonzero(mask_b)
    if len(ia) == 0 or len(ib) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    na = fv_a.node_of_feature[ia]
    nb = fv_b.node_of_feature[ib]
    order = np.argsort(nb, kind="stable")
    ib_sorted, nb_sorted = ib[order], nb[order]
    start = np.searchsorted(nb_sorted, na, side="left")
    cnt = np.searchsorted(nb_sorted, na, side="right") - start
    total = int(cnt.sum())
    if total == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a_rep = np.repeat(ia, cnt)
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    b_rep = ib_sorted[np.repeat(start, cnt) + offs]
    dist = np.bitwise_count(_u64(desc_a)[a_rep] ^ _u64(desc_b)[b_rep]).sum(axis=1)
    return _best_unique(a_rep, b_rep, dist, max_distance, ratio)


def _best_unique(a: I64, b: I64, dist: NDArray[Any], max_distance: float, ratio: float | None) -> I64:
    """Per ``a``: best ``b`` (ratio test vs the second best if ``ratio``); then one ``a`` per ``b``."""
    if len(a) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    o = np.lexsort((dist, a))
    a, b, dist = a[o], b[o], dist[o]
    first = np.ones(len(a), dtype=bool)
    first[1:] = a[1:] != a[:-1]
    idx = np.flatnonzero(first)
    best_d = dist[idx]
    ok = best_d <= max_distance
    if ratio is not None:
        has_second = np.zeros(len(idx), dtype=bool)
        nxt = idx + 1
        in_range = nxt < len(a)
        has_second[in_range] = a[nxt[in_range]] == a[idx[in_range]]
        second_d = np.where(has_second, dist[np.minimum(nxt, len(a) - 1)], np.inf)
        ok &= best_d < ratio * second_d
    idx = idx[ok]
    pa, pb, pd = a[idx], b[idx], dist[idx]
    o = np.lexsort((pd, pb))
    pa, pb = pa[o], pb[o]
    keep = np.ones(len(pb), dtype=bool)
    keep[1:] = pb[1:] != pb[:-1]
    return np.stack([pa[keep], pb[keep]], axis=1).astype(np.int64)


def match_projected(
    uv: F64,
    desc_pts: NDArray[np.uint8],
    keypoints: NDArray[np.floating],
    octaves: NDArray[np.integer],
    descriptors: NDArray[np.uint8],
    radius: float,
    max_distance: int,
    kp_mask: NDArray[np.bool_] | None = None,
) -> I64:
    """Guided search: points projected to ``uv`` (M, 2) -> (K, 2) pairs (point index, keypoint index).

    A keypoint is a candidate when within ``radius * 1.2^octave`` pixels; the closest descriptor within
    ``max_distance`` bits wins; each keypoint is used once.
    """
    kidx = np.arange(len(keypoints)) if kp_mask is None else np.flatnonzero(kp_mask)
    if len(uv) == 0 or len(kidx) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    kp = np.asarray(keypoints, dtype=np.float64)[kidx]
    scale = 1.2 ** np.asarray(octaves, dtype=np.float64)[kidx]
    tree_kp = cKDTree(kp)
    tree_uv = cKDTree(np.asarray(uv, dtype=np.float64))
    sdm = tree_uv.sparse_distance_matrix(tree_kp, radius * float(scale.max()), output_type="ndarray")
    if len(sdm) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pi = sdm["i"].astype(np.int64)
    kj = sdm["j"].astype(np.int64)
    near = sdm["v"] <= radius * scale[kj]
    pi, kj = pi[near], kj[near]
    dist = np.bitwise_count(_u64(desc_pts)[pi] ^ _u64(descriptors)[kidx[kj]]).sum(axis=1)
    pairs = _best_unique(pi, kidx[kj], dist, max_distance, None)
    return pairs


# ----------------------------------------------------------------------------------------------
# geometry
def estimate_sim3_ransac(
    src: F64,
    tgt: F64,
    max_error: float,
    fix_scale: bool,
    min_trials: int = 200,
    seed: int = 0,
    max_trials: int = 3000,
) -> tuple[Sim3, NDArray[np.bool_]] | None:
    """Robust ``tgt_from_src`` with pycolmap LO-RANSAC (Sim3d, or Rigid3d when ``fix_scale``)."""
    import pycolmap

    if len(src) < 3:
        return None
    opts = pycolmap.RANSACOptions()
    opts.max_error = float(max_error)
    opts.min_num_trials = int(min_trials)
    # bounded: a wrong candidate has ~0 % inliers and would otherwise run to 100k trials
    opts.max_num_trials = max(int(max_trials), int(min_trials))
    opts.random_seed = int(seed)
    src = np.ascontiguousarray(src, dtype=np.float64)
    tgt = np.ascontiguousarray(tgt, dtype=np.float64)
    # both return a dict (tgt_from_src, num_inliers, inlier_mask) or None, despite their docstrings
    res: Any = (
        pycolmap.estimate_rigid3d_robust(src, tgt, opts)
        if fix_scale
        else pycolmap.estimate_sim3d_robust(src, tgt, opts)
    )
    if res is None:
        return None
    M = np.asarray(res["tgt_from_src"].matrix())
    if fix_scale:
        sim = Sim3(M[:3, :3], M[:3, 3], 1.0)
    else:
        sim = Sim3.from_matrix(np.vstack([M[:3, :4], [0, 0, 0, 1]]))
    return sim, np.asarray(res["inlier_mask"]).astype(bool)


@dataclass
class _Obs:
    """Observations for the bidirectional reprojection refinement (paper 2.5.1).

    Direction A: candidate point ``Xc`` -> query map (S^-1) -> query keyframe camera, vs ``uv_q``.
    Direction B (where the query keypoint has a map point): query point ``Xq`` -> candidate map (S) ->
    candidate keyframe camera ``cam_b``, vs ``uv_b``.
    """

    xc: F64  # (N, 3) candidate-map points
    uv_q: F64  # (N, 2)
    sig_q: F64  # (N,)
    xq: F64  # (N, 3) query-map points (nan where none)
    uv_b: F64  # (N, 2)
    sig_b: F64  # (N,)
    has_b: NDArray[np.bool_]  # (N,) direction B available
    groups_b: list[tuple[I64, Any, F64]]  # (indices, camera, cam_from_world) per candidate keyframe
    sig3: F64 | None = None  # (N,) sigma of the optional 3D term (``S Xq - Xc``), None = off

    def subset(self, idx: I64) -> _Obs:
        pos = np.full(len(self.xc), -1, dtype=np.int64)
        pos[idx] = np.arange(len(idx))
        groups = []
        for g, cam, cfw in self.groups_b:
            gi = pos[g]
            gi = gi[gi >= 0]
            if len(gi):
                groups.append((gi, cam, cfw))
        return _Obs(
            self.xc[idx],
            self.uv_q[idx],
            self.sig_q[idx],
            self.xq[idx],
            self.uv_b[idx],
            self.sig_b[idx],
            self.has_b[idx],
            groups,
        )


def _project(camera: Any, cam_from_world: F64, pts: F64) -> tuple[F64, NDArray[np.bool_]]:
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv, valid = camera.project(pc)
    return uv, valid


def _residuals(
    sim: Sim3, obs: _Obs, q_camera: Any, q_cam_from_world: F64
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Whitened residuals (N, 2) of directions A and B (B zero where unavailable) and B availability."""
    inv = sim.inverse()
    uv_a, va = _project(q_camera, q_cam_from_world, inv.apply(obs.xc))
    ra = (uv_a - obs.uv_q) / obs.sig_q[:, None]
    ra[~va] = 1e3
    rb = np.zeros_like(ra)
    if obs.groups_b:
        xs = sim.apply(np.where(np.isfinite(obs.xq), obs.xq, 0.0))
        for idx, cam, cfw in obs.groups_b:
            uv_b, vb = _project(cam, cfw, xs[idx])
            r = (uv_b - obs.uv_b[idx]) / obs.sig_b[idx, None]
            r[~vb] = 1e3
            rb[idx] = r
    return ra, rb, obs.has_b


def refine_sim3(
    sim0: Sim3,
    obs: _Obs,
    q_camera: Any,
    q_cam_from_world: F64,
    fix_scale: bool,
    huber: float = 2.45,
    max_nfev: int = 50,
    yaw_axis: F64 | None = None,
) -> Sim3:
    """Minimise the bidirectional reprojection error over ``[rotvec, t, log s]`` (Huber loss).

    With ``obs.sig3`` set, a weak 3D term ``(S Xq - Xc) / sigma`` is added: when the query and the
    candidate keyframes see the place from (almost) the same viewpoint, a similarity centred on the
    camera is invisible in the reprojections, and only the maps' 3D structure fixes the scale.
    ``yaw_axis`` (unit up direction in the candidate map's frame): only the rotation about it is refined
    (``sim0``'s roll/pitch kept: a levelled loop, see BackendOptions.level_reprojection).
    """
    n_rot = 3 if yaw_axis is None else 1
    n_par = n_rot + 3 + (0 if fix_scale else 1)
    axis = None if yaw_axis is None else np.asarray(yaw_axis, dtype=np.float64) / np.linalg.norm(yaw_axis)

    def make(x: F64) -> Sim3:
        R = (so3_exp(x[:3]) if axis is None else so3_exp(axis * x[0])) @ sim0.R
        s = sim0.s if fix_scale else sim0.s * float(np.exp(x[n_rot + 3]))
        return Sim3(R, sim0.t + x[n_rot : n_rot + 3], s)

    use3 = obs.sig3 is not None and bool(obs.has_b.any())
    if use3:
        assert obs.sig3 is not None
        i3 = np.flatnonzero(obs.has_b)
        xq3, xc3, s3 = obs.xq[i3], obs.xc[i3], obs.sig3[i3, None]

    def fun(x: F64) -> F64:
        sim = make(x)
        ra, rb, _ = _residuals(sim, obs, q_camera, q_cam_from_world)
        parts = [ra.ravel(), rb.ravel()]
        if use3:
            parts.append(((sim.apply(xq3) - xc3) / s3).ravel())
        return np.concatenate(parts)

    # translation steps are scaled to the scene (x_scale) so the numeric Jacobian is well conditioned
    depth = float(np.median(np.linalg.norm(obs.xc - np.median(obs.xc, axis=0), axis=1))) + 1e-9
    x_scale = np.array([0.01] * n_rot + [0.01 * depth] * 3 + ([0.01] if not fix_scale else []))
    res = least_squares(
        fun, np.zeros(n_par), loss="huber", f_scale=huber, x_scale=x_scale, max_nfev=max_nfev, method="trf"
    )
    return make(res.x)


def correction_of(sim: Sim3, world_from_cam: Any) -> tuple[float, float]:
    """How far (m) and how much (deg) the similarity ``sim`` moves and turns a camera pose."""
    c = np.asarray(world_from_cam, dtype=np.float64)[:3, 3]
    return float(np.linalg.norm(sim.apply(c) - c)), rotation_angle_deg(sim.R)


def pair_observations(
    mq: Any,
    mc: Any,
    query_key: KfKey,
    candidate_key: KfKey,
    query_points: Sequence[PointKey],
    candidate_points: Sequence[PointKey],
    n_covisible: int = 5,
) -> _Obs:
    """The reprojection observations of a detection's point pairs (``query_points[i]`` is
    ``candidate_points[i]``): the query keyframe's keypoints of its paired points, and those points'
    keypoints in the candidate keyframe and its ``n_covisible`` best covisible keyframes."""
    q = mq.keyframes[query_key]
    q_pk = _point_keys(q)
    index: dict[PointKey, int] = {}
    for i, k in enumerate(q_pk):
        if k is not None:
            index.setdefault(mq.resolve_point(k), i)
    pairs: dict[int, PointKey] = {}
    for kq, kc in zip(query_points, candidate_points, strict=True):
        iq, pc = index.get(mq.resolve_point(kq)), mc.resolve_point(kc)
        if iq is not None and pc in mc.points:
            pairs.setdefault(iq, pc)
    keys = [candidate_key, *_best_covisible(mc, candidate_key, n_covisible)]
    window = [mc.keyframes[k] for k in dict.fromkeys(keys) if k in mc.keyframes]
    return _observations(pairs, q, q_pk, mq, mc, window)


# ----------------------------------------------------------------------------------------------
@dataclass
class _Consistency:
    query_key: KfKey
    sim: Sim3
    count: int
    best: Detection


def _point_keys(kf: Any) -> list[PointKey | None]:
    return list(kf.point_keys)


def _best_covisible(m: Any, key: KfKey, n: int) -> list[KfKey]:
    out = m.best_covisible(key, n)
    res: list[KfKey] = []
    for item in out:
        if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], tuple):
            res.append(item[0])  # (key, weight)
        elif isinstance(item, tuple):
            res.append(item)  # type: ignore[arg-type]
        else:
            res.append(item.key)
    return res


def _covisible_keys(m: Any, key: KfKey) -> list[KfKey]:
    return list(m.covisibility(key).keys())


class PlaceRecognizer:
    """Place recognition over a map stack; holds the per-map-pair consistency state.

    ``maps``: ``Mapping[int, Map]`` (e.g. ``MapStack.maps``). Keyframes must be indexed with
    ``add_keyframe`` (BoW + direct index into the shared ``KeyframeDatabase``).
    """

    def __init__(
        self,
        vocabulary: Vocabulary,
        kfdb: KeyframeDatabase | None = None,
        options: PlaceRecOptions = PlaceRecOptions(),
    ) -> None:
        self.vocabulary = vocabulary
        self.kfdb = kfdb if kfdb is not None else KeyframeDatabase()
        self.options = options
        self._consistency: dict[tuple[int, int, str], _Consistency] = {}

    # --- database ------------------------------------------------------------------------------
    def add_keyframe(self, map_id: int, kf: Any) -> BowVector:
        bow, fv = self.vocabulary.transform(kf.descriptors)
        self.kfdb.add(kf.key, map_id, bow, fv)
        return bow

    def remove_keyframe(self, key: KfKey) -> None:
        self.kfdb.remove(key)

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
                todo += [
                    (k, s, "merge")
                    for k, s in self.kfdb.query(bow, n_cand, exclude_map=query_map, scores=scores)
                ]
        if loop:
            covis = set(_covisible_keys(mq, query_key)) | {query_key}
            # ORB-SLAM: a loop candidate must score above the worst covisible neighbour
            min_score = min(
                (bow.score(self.kfdb.bow(k)) for k in covis if k != query_key and k in self.kfdb),
                default=0.0,
            )
            todo += [
                (k, s, "loop")
                for k, s in self.kfdb.query(
                    bow, n_cand, only_map=query_map, exclude_keys=covis, min_score=min_score, scores=scores
                )
            ]
        best: CandidateReport | None = None
        covered: set[KfKey] = set()  # windows of accepted candidates (ORB-SLAM3 skips those)
        for ck, score, kind in todo[: o.max_verifications]:
            cmap_id = self.kfdb.map_of(ck)
            if ck in covered:
                rep = CandidateReport(query_key, ck, cmap_id, kind, bow_score=score)
                rep.reason = "covered_by_accepted_window"
                result.candidates.append(rep)
                continue
            fs = fix_scale(query_map, cmap_id) if callable(fix_scale) else bool(fix_scale)
            rep = self._verify(maps, query_map, query_key, cmap_id, ck, fs, o.thresholds, kind)
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
        for ck in candidate_keys:
            rep = self._verify(maps, query_map, query_key, candidate_map, ck, fix_scale, th, "gnss_retry")
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
    ) -> CandidateReport:
        t0 = time.perf_counter()
        rep = CandidateReport(query_key, cand_key, cand_map, kind)
        try:
            self._verify_inner(maps, query_map, query_key, cand_map, cand_key, fix_scale, th, rep)
        except KeyError as e:
            # a point or keyframe the verification reads was fused away by the event loop meanwhile (9 and
            # 12 such errors logged in two factory01 challenged1 runs): skipped, as a merged-away map is
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
        q_pk = _point_keys(q)
        q_has = np.array([k is not None and k in mq.points for k in q_pk], dtype=bool)

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
            w_pk = _point_keys(w)
            w_has = np.array([k is not None and k in mc.points for k in w_pk], dtype=bool)
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
        if fix_scale and o.metric_max_log_scale > 0:
            # metric agents: the free-scale estimate must agree with scale 1 (sanity gate)
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
        est = estimate_sim3_ransac(xq, xc, max_err, fix_scale, o.ransac_min_trials)
        if est is None:
            rep.reason = "ransac_failed"
            return
        sim, inl = est
        rep.n_ransac_inliers = int(inl.sum())
        if rep.n_ransac_inliers < th.min_inliers:
            rep.reason = "few_ransac_inliers"
            return
        sim_ransac = sim
        if rep.kind == "loop" and self._implausible_correction(sim, q.world_from_cam, rep):
            return

        # 3. guided search both ways, refine, guided search again, refine again
        q_cfw = se3_inverse(np.asarray(q.world_from_cam, dtype=np.float64))
        window_kfs = [mc.keyframes[k] for k in window if k in mc.keyframes]
        cand_pts = _window_points(mc, window_kfs)
        q_pts = [k for k in dict.fromkeys(k for k in q_pk if k is not None and k in mq.points)]
        pairs: dict[int, PointKey] = {corr_q[i]: corr_c[i] for i in np.flatnonzero(inl)}
        for _ in range(2):
            pairs = self._guided(q, q_cfw, q_pk, mq, c, c_cfw, mc, cand_pts, q_pts, sim, pairs)
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
        pairs = self._guided(q, q_cfw, q_pk, mq, c, c_cfw, mc, cand_pts, q_pts, sim, pairs)
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
        move, turn = correction_of(sim, world_from_cam)
        if (0 < o.loop_max_correction_m < move) or (0 < o.loop_max_correction_deg < turn):
            rep.reason = "implausible_correction"
            return True
        return False

    def _guided(
        self,
        q: Any,
        q_cfw: F64,
        q_pk: Sequence[PointKey | None],
        mq: Any,
        c: Any,
        c_cfw: F64,
        mc: Any,
        cand_pts: list[PointKey],
        q_pts: list[PointKey],
        sim: Sim3,
        pairs: dict[int, PointKey],
    ) -> dict[int, PointKey]:
        """Add matches by projection both ways; returns query keypoint -> candidate point."""
        o = self.options
        out = dict(pairs)
        used_c = set(out.values())
        # A: candidate-window points -> query keyframe
        free_c = [k for k in cand_pts if k not in used_c]
        if free_c:
            xyz = sim.inverse().apply(np.array([mc.points[k].xyz for k in free_c]))
            uv, valid = _project(q.camera, q_cfw, xyz)
            valid &= q.camera.in_image(uv)
            vi = np.flatnonzero(valid)
            desc = np.array([mc.points[free_c[i]].descriptor for i in vi], dtype=np.uint8).reshape(-1, 32)
            mask = np.ones(len(q.keypoints), dtype=bool)
            mask[list(out.keys())] = False
            m = match_projected(
                uv[vi],
                desc,
                q.keypoints,
                q.octaves,
                q.descriptors,
                o.search_radius_px,
                o.search_max_distance,
                mask,
            )
            for pi, kq in m.tolist():
                out[int(kq)] = free_c[vi[pi]]
                used_c.add(free_c[vi[pi]])
        # B: query points -> candidate keyframe
        used_q = {q_pk[i] for i in out if q_pk[i] is not None}
        free_q = [k for k in q_pts if k not in used_q]
        c_pk = _point_keys(c)
        if free_q:
            xyz = sim.apply(np.array([mq.points[k].xyz for k in free_q]))
            uv, valid = _project(c.camera, c_cfw, xyz)
            valid &= c.camera.in_image(uv)
            vi = np.flatnonzero(valid)
            desc = np.array([mq.points[free_q[i]].descriptor for i in vi], dtype=np.uint8).reshape(-1, 32)
            cmask = np.array([k is not None and k in mc.points and k not in used_c for k in c_pk], dtype=bool)
            m = match_projected(
                uv[vi],
                desc,
                c.keypoints,
                c.octaves,
                c.descriptors,
                o.search_radius_px,
                o.search_max_distance,
                cmask,
            )
            q_index = {k: i for i, k in enumerate(q_pk) if k is not None}
            for pi, kc in m.tolist():
                qk = free_q[vi[pi]]
                iq = q_index[qk]
                pc = c_pk[kc]
                if iq not in out and pc is not None:
                    out[iq] = pc
        return out


def _window_points(mc: Any, window_kfs: list[Any]) -> list[PointKey]:
    seen: dict[PointKey, None] = {}
    for w in window_kfs:
        for k in _point_keys(w):
            if k is not None and k in mc.points:
                seen.setdefault(k, None)
    return list(seen)


def _observations(
    pairs: dict[int, PointKey],
    q: Any,
    q_pk: Sequence[PointKey | None],
    mq: Any,
    mc: Any,
    window_kfs: list[Any],
) -> _Obs:
    n = len(pairs)
    xc = np.zeros((n, 3))
    uv_q = np.zeros((n, 2))
    sig_q = np.ones(n)
    xq = np.full((n, 3), np.nan)
    uv_b = np.zeros((n, 2))
    sig_b = np.ones(n)
    kf_of: list[KfKey | None] = [None] * n
    wpos = {
        w.key: (w, (w.camera, se3_inverse(np.asarray(w.world_from_cam, dtype=np.float64))))
        for w in window_kfs
    }
    for i, (iq, pc) in enumerate(pairs.items()):
        mp = mc.points[pc]
        xc[i] = mp.xyz
        uv_q[i] = q.keypoints[iq]
        sig_q[i] = 1.2 ** float(q.octaves[iq])
        qk = q_pk[iq]
        if qk is not None and qk in mq.points:
            for wk, idx in mp.observations.items():
                hit = wpos.get(wk)
                if hit is not None:
                    w, cam = hit
                    xq[i] = mq.points[qk].xyz
                    uv_b[i] = w.keypoints[idx]
                    sig_b[i] = 1.2 ** float(w.octaves[idx])
                    kf_of[i] = wk
                    break
    groups: list[tuple[I64, Any, F64]] = []
    by_kf: dict[KfKey, list[int]] = {}
    for i, wk in enumerate(kf_of):
        if wk is not None:
            by_kf.setdefault(wk, []).append(i)
    for wk, idx_list in by_kf.items():
        cam, cfw = wpos[wk][1]
        groups.append((np.asarray(idx_list, dtype=np.int64), cam, cfw))
    has_b = np.array([k is not None for k in kf_of], dtype=bool)
    return _Obs(xc, uv_q, sig_q, xq, uv_b, sig_b, has_b, groups)


__all__ = [
    "CandidateReport",
    "Detection",
    "PlaceRecOptions",
    "PlaceRecognizer",
    "RecognitionResult",
    "Thresholds",
    "correction_of",
    "estimate_sim3_ransac",
    "match_bow",
    "match_projected",
    "pair_observations",
    "refine_sim3",
]
