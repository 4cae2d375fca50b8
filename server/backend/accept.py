"""Acceptance of place-recognition detections: the consistency of consecutive detections (merges and loops
alike) and the sanity gates a loop must pass (the correction it asks for, its agreement with the IMU's up
directions). Where are loops accepted? Here: :meth:`Consistency.check`, then :func:`loop_refusal`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg
from hivemap.server.backend.fit import fit_pairs
from hivemap.server.backend.options import AcceptOptions
from hivemap.server.placerec import Detection, correction_of

F64 = NDArray[np.float64]


class Consistency:
    """Per (query map, candidate map, query agent): the last detection's re-fitted Sim(3) and how many
    consecutive ones agreed with it.

    It is checked on the Sim(3) re-fitted to each detection's hundreds of 3D-3D duplicate pairs (trimmed
    Umeyama), not on place recognition's single-keyframe estimate, which scatters by 10-50 % in scale
    when query and candidate cameras are close."""

    def __init__(self) -> None:
        self._state: dict[tuple[int, int, str], tuple[int, Sim3, int]] = {}

    def forget_maps(self, *map_ids: int) -> None:
        """Drop the counts involving these maps (they merged)."""
        for k in [k for k in self._state if k[0] in map_ids or k[1] in map_ids]:
            del self._state[k]

    def check(
        self, det: Detection, maps: Any, o: AcceptOptions, fix_scale: bool, events: Any
    ) -> Detection | None:
        """The detection with its re-fitted Sim(3) once ``consistency_required`` consecutive query keyframes
        of the same agent agree on it; else None."""
        mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
        if mq is None or mc is None:
            return None
        pairs = list(zip(det.candidate_points, det.query_points, strict=True))
        sim, src_xyz, n_in, _ = fit_pairs(mc, mq, pairs, o.min_pair_inlier_ratio, with_scale=not fix_scale)
        key = (det.query_map, det.candidate_map, det.query_key[0])
        data: dict[str, Any] = {"query_key": list(det.query_key), "candidate_key": list(det.candidate_key),
                                "n_pairs": len(pairs), "n_pair_inliers": n_in}  # fmt: skip
        if sim is None:
            events.add("consistency", f"{det.query_key}: 3D pairs do not fit one Sim(3)",
                       map_id=det.query_map, data=data)  # fmt: skip
            return None
        prev = self._state.get(key)
        ok = False
        if prev is not None and 0 < det.query_key[1] - prev[0] <= o.consistency_max_gap:
            rel = prev[1].inverse() @ sim
            pa, pb = prev[1].apply(src_xyz), sim.apply(src_xyz)
            spread = float(np.median(np.linalg.norm(pb - np.median(pb, axis=0), axis=1))) + 1e-9
            shift = float(np.median(np.linalg.norm(pa - pb, axis=1))) / spread
            ok = (
                rotation_angle_deg(rel.R) <= o.consistency_max_rot_deg
                and abs(np.log(rel.s)) <= o.consistency_max_log_scale
                and shift <= o.consistency_max_rel_shift
            )
        count = prev[2] + 1 if ok and prev is not None else 1
        data.update(consistent=count, scale=sim.s, target_from_source=sim.matrix().tolist())
        events.add(
            "consistency",
            f"{det.kind} {det.query_key} -> {det.candidate_key}: {count}/{o.consistency_required} consistent",
            map_id=det.query_map,
            data=data,
        )
        if count >= o.consistency_required:
            self._state.pop(key, None)
            return replace(det, target_from_source=sim, consistent=count, confirmed=True)
        self._state[key] = (det.query_key[1], sim, count)
        return None


def loop_refusal(
    det: Detection,
    m: Any,
    measured: Sim3,
    ups: tuple[F64 | None, F64 | None],
    o: AcceptOptions,
    fix_scale: bool,
    loose: bool = False,
) -> tuple[str, dict[str, Any]] | None:
    """Why a confirmed loop is refused (message, event data), or None. ``measured``: the loop's
    cam_candidate_from_cam_query; ``ups``: the query's and the candidate's IMU up directions. ``loose``:
    the loop joins two sides held together only by a session guess on trial: the correction gate assumes
    one continuous map's drift, while across the guess the correction is the guess's error, which the
    robust pose graph weighs against the loops."""
    if fix_scale and not loose:
        # Metric (stereo-inertial) maps drift by decimetres, not metres: a loop that would move the
        # query farther or turn it more is a false match (it bends the map until the GNSS stage rejects
        # every fix).
        move, turn = correction_of(det.target_from_source, m.keyframes[det.query_key].world_from_cam)
        if move > o.loop_max_correction_m or turn > o.loop_max_correction_deg:
            return (
                f"loop {det.query_key} -> {det.candidate_key} refused: it would move the query "
                f"{move:.2f} m / {turn:.1f} deg (limits {o.loop_max_correction_m} m, "
                f"{o.loop_max_correction_deg} deg)",
                {"refused": True, "move_m": move, "turn_deg": turn, "n_inliers": det.n_inliers},
            )
    tilt = gravity_disagreement_deg(measured, *ups)
    if o.loop_max_gravity_deg > 0 and tilt is not None and tilt > o.loop_max_gravity_deg:
        # its tilt error would put the far keyframe off in height
        return (
            f"loop {det.query_key} -> {det.candidate_key} refused: its rotation disagrees with the "
            f"agents' IMU up directions by {tilt:.2f} deg (limit {o.loop_max_gravity_deg} deg)",
            {"refused": True, "gravity_deg": tilt, "n_inliers": det.n_inliers},
        )
    return None


def gravity_disagreement_deg(
    candidate_from_query: Sim3, up_query: F64 | None, up_candidate: F64 | None
) -> float | None:
    """Angle (deg) between the candidate's IMU up direction and the query's (unit, in their cameras)
    carried into the candidate's camera by the measured relative rotation; None if either is missing."""
    if up_query is None or up_candidate is None:
        return None
    up = candidate_from_query.R @ np.asarray(up_query, dtype=np.float64)
    c = float(np.dot(up, np.asarray(up_candidate, dtype=np.float64)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))
