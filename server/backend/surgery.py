"""Map surgery for merges and loops: which map keeps its frame, the known start configuration's merge
transform, fusing a loop's duplicate points, and the records a merge or loop leaves for the experiment.
The merge itself (one store commit, agents re-framed) is the server's ``apply_merge``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.server.placerec import Detection

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

# A loop's query starts the pose graph with this many of its best covisible keyframes corrected too.
LOOP_NEIGHBOURHOOD = 30


def target_of(maps: Any, map_a: int, map_b: int, agent_kind: Callable[[str], str]) -> int:
    """The map that keeps its frame (paper 2.4): the one holding a UGV, else the older (lower id) one."""
    ugv = [mid for mid in (map_a, map_b) if any(agent_kind(f) == "ugv" for f in maps[mid].agents)]
    if len(ugv) == 1:
        return ugv[0]
    return min(map_a, map_b)


def common_from_map(start: F64, first_world_from_cam: F64) -> Sim3:
    """An agent's map in the common start frame: its first keyframe is taken at the start pose."""
    return Sim3.from_se3(start @ se3_inverse(first_world_from_cam))


def loop_neighbourhood(m: Any, query: KfKey) -> list[KfKey]:
    """The query and its covisible keyframes that start the pose graph already corrected by the loop's
    Sim(3) (ORB-SLAM; their odometry edges keep their uncorrected relative poses)."""
    hood = [query, *m.best_covisible(query, LOOP_NEIGHBOURHOOD)]
    return [k for k in hood if k not in m.loop_neighbours(query) or k == query]


def loop_record(
    m: Any,
    det: Detection,
    measured: Sim3,
    tilt: float | None,
    levelled: bool,
    n_pairs: int,
    sigmas: tuple[float, float],
) -> dict[str, Any]:
    """What a closed loop records (``Backend.loops``, the ``loop`` event)."""
    Tq = Sim3.from_se3(m.keyframes[det.query_key].world_from_cam)
    return {
        "map": m.id,
        "query": list(det.query_key),
        "query_t": float(m.keyframes[det.query_key].timestamp),  # data time (plots mark it)
        "candidate": list(det.candidate_key),
        "candidate_t": float(m.keyframes[det.candidate_key].timestamp),
        "scale": det.target_from_source.s,
        "n_inliers": det.n_inliers,
        "n_pairs": n_pairs,
        # the measured relative pose (cam_candidate_from_cam_query): the experiment compares it with
        # ground truth (eval: loop accuracy per agent pair)
        "candidate_from_query": measured.matrix().tolist(),
        "gravity_deg": tilt,  # the detection's own tilt disagreement (before levelling)
        "levelled": levelled,
        # what the loop asks of the query keyframe (the correction the pose graph starts from)
        "move_m": float(np.linalg.norm(det.target_from_source.apply(Tq.t) - Tq.t)),
        "turn_deg": rotation_angle_deg(det.target_from_source.R),
        # the pose-graph edge's sigmas (the weld's, else the fit's bootstrap spread; at least the essential
        # edges')
        "sigma_rot_deg": math.degrees(sigmas[0]),
        "sigma_trans_m": sigmas[1],
    }


def merge_record(
    merged: Any,
    det: Detection,
    target_id: int,
    source_id: int,
    sim: Sim3,
    n_fused: int,
    merge_ms: float,
    levelled: bool,
    sigmas: tuple[float, float],
) -> dict[str, Any]:
    """What a visual merge records (``Backend.merges``, the ``merge_detail`` event)."""
    qkf = merged.keyframes.get(det.query_key)
    return {
        "target": target_id,
        "source": source_id,
        "query_t": None if qkf is None else float(qkf.timestamp),  # data time (plots mark it)
        "scale": sim.s,
        "n_fused": n_fused,
        "merge_ms": merge_ms,
        "target_from_source": sim.matrix().tolist(),
        "levelled": levelled,
        "sigma_rot_deg": math.degrees(sigmas[0]),
        "sigma_trans_m": sigmas[1],
        "detection": det.to_dict(),
    }
