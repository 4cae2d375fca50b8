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

from hivemap.server.placerec.descmatch import match_bow, match_projected
from hivemap.server.placerec.match import (
    _Obs,
    correction_of,
    estimate_sim3_ransac,
    pair_observations,
    refine_sim3,
)
from hivemap.server.placerec.recognizer import PlaceRecognizer
from hivemap.server.placerec.types import (
    CandidateReport,
    Detection,
    PlaceRecOptions,
    RecognitionResult,
    Thresholds,
)

__all__ = [
    "CandidateReport",
    "Detection",
    "PlaceRecOptions",
    "PlaceRecognizer",
    "RecognitionResult",
    "Thresholds",
    "_Obs",
    "correction_of",
    "estimate_sim3_ransac",
    "match_bow",
    "match_projected",
    "pair_observations",
    "refine_sim3",
]
