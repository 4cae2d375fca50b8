"""Place recognition's options and results (candidates, detections)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3
from hivemap.maps.kfdb import Feasibility

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
    # keyframes a look-up (merge, loop) retrieves by BoW score, whatever the size of the team: the paper's
    # 4 x agents made a query's cost grow with the team and the server's with its square
    retrieve_max: int = 16
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
    # Retrieved keyframes are grouped with their best covisible keyframes and one per group, the best
    # scoring, is verified; groups scoring (sum of the members' BoW scores) below ``group_min_ratio`` x
    # the best group are not (ORB-SLAM2: 10 covisible, 0.75). 0 disables (every retrieved keyframe).
    group_covisible: int = 10
    group_min_ratio: float = 0.75
    # at most this many groups per look-up are verified, best first (ORB-SLAM3's DetectNBestCandidates: 3)
    max_groups: int = 3
    # Loops (query and candidate in one map, whose frame already holds both): a candidate whose transform
    # would move the query keyframe farther, or turn it more, than this is a false match, rejected as
    # "implausible_correction" right after RANSAC and again after refinement, so it neither costs the
    # guided search nor displaces a true candidate of the same query. 0 disables; the back-end sets them
    # from ``AcceptOptions.loop_max_correction_*`` for metric agents (docs/decisions.md).
    loop_max_correction_m: float = 0.0
    loop_max_correction_deg: float = 0.0
    # Two phases (:mod:`.phases`): every candidate's BoW matches and RANSAC first, on slices of the maps
    # without descriptors or observations; the full verification only for candidates that reached the
    # inlier threshold (most never do, and their slices were most of a look-up's cost).
    two_phase: bool = True
    # Metric maps: a candidate whose 3D-3D matches hold no ``min_inliers`` keeping their mutual distances
    # (what a rigid transform's inliers must do) is refused before RANSAC (``phases.rigid_consensus_bound``).
    consensus_pretest: bool = True


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
    cpu_ms: float = 0.0  # CPU time of the verification (thread time, in whichever process ran it)
    phase: int = 0  # two-phase verification: 1 refused in phase 1, 2 fully verified; 0 one phase
    target_from_source: Sim3 | None = field(default=None, repr=False)
    query_points: list[PointKey] = field(default_factory=list, repr=False)
    candidate_points: list[PointKey] = field(default_factory=list, repr=False)
    query_xyz: F64 | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        # field by field: ``asdict`` deep-copied the point lists (hundreds of pairs per candidate) only to
        # drop them, on the event loop, for every candidate of every query
        skip = ("target_from_source", "query_points", "candidate_points", "query_xyz")
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in skip}
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
    cpu_ms: float = 0.0  # CPU time of the verification (thread time, in whichever process ran it)
    retrieved: int = 0  # keyframes the BoW look-ups returned (``candidates``: those verified)

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
            "n_retrieved": self.retrieved,
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
