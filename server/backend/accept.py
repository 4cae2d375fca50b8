"""Acceptance of place-recognition detections: the consistency of consecutive detections (merges and loops
alike) and the sanity gates a loop must pass (the correction it asks for, its agreement with the IMU's up
directions). Where are loops accepted? Here: :meth:`Consistency.check`, then :func:`loop_refusal`. Merges
that contradict the start prior: :class:`PriorOverride`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg
from hivemap.maps.odometry import correction_slack
from hivemap.server.backend.fit import fit_pairs
from hivemap.server.backend.options import AcceptOptions
from hivemap.server.placerec import Detection, correction_of

F64 = NDArray[np.float64]
KfKey = tuple[str, int]

# Contradicting detections kept per pair of maps (the latest; a long aliased stretch must not grow the list
# or the search through it without bound).
PLACES_KEPT = 100


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


@dataclass(frozen=True)
class Place:
    """One merge detection against the start prior: its keyframe in each map and the re-fitted transform
    of the pair's higher map id into the lower's frame."""

    keys: dict[int, KfKey]  # map id -> that side's keyframe
    lo_from_hi: Sim3

    def to_dict(self) -> dict[str, Any]:
        return {"keys": {str(mid): list(k) for mid, k in self.keys.items()}}


class PriorOverride:
    """Merge detections that contradict the start prior, per pair of maps, until enough independent places
    agree on one transform to override the prior (:attr:`AcceptOptions.prior_override_places`).

    Consecutive detections of one place are one piece of evidence: an aliased place (a twin room, a
    repeated rack) looks the same from each keyframe that sees it, so its detections agree with each
    other however wrong they are. Two places count as independent when neither side's keyframes share a
    map point (not covisible): their 3D-3D pairs are then disjoint sets of features on both sides, so no
    feature, and no look-alike patch of scene, is counted twice."""

    def __init__(self) -> None:
        self._places: dict[tuple[int, int], list[Place]] = {}

    def forget_maps(self, *map_ids: int) -> None:
        """Drop the places involving these maps (they merged or split: their frames changed)."""
        for k in [k for k in self._places if k[0] in map_ids or k[1] in map_ids]:
            del self._places[k]

    def check(
        self, det: Detection, maps: Any, o: AcceptOptions, fix_scale: bool
    ) -> tuple[Detection | None, list[Place]]:
        """The detection with its re-fitted Sim(3) once it and ``prior_override_places - 1`` earlier ones
        at independent places agree on the transform (else None), and the places found so far that agree
        with it (itself first)."""
        mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
        if mq is None or mc is None:
            return None, []
        pairs = list(zip(det.candidate_points, det.query_points, strict=True))
        sim, _, _, _ = fit_pairs(mc, mq, pairs, o.min_pair_inlier_ratio, with_scale=not fix_scale)
        if sim is None:
            return None, []
        lo, hi = sorted((det.query_map, det.candidate_map))
        new = Place({det.query_map: det.query_key, det.candidate_map: det.candidate_key},
                    sim if det.candidate_map == lo else sim.inverse())  # fmt: skip
        chosen = [new]
        places = self._places.setdefault((lo, hi), [])
        for p in reversed(places):  # the latest first: the maps' frames drift least between them
            if all(_agree(p, c, maps[hi], hi, o) and _independent(p, c, maps) for c in chosen):
                chosen.append(p)
        if len(chosen) >= o.prior_override_places:
            del self._places[(lo, hi)]
            return replace(det, target_from_source=sim, consistent=len(chosen), confirmed=True), chosen
        places.append(new)
        del places[:-PLACES_KEPT]
        return None, chosen


def _agree(a: Place, b: Place, m_hi: Any, hi: int, o: AcceptOptions) -> bool:
    """The two places' transforms put both places' cameras of the higher map to within the error a merge may
    have (``prior_override_max_m`` / ``_deg``, and the consistency check's scale)."""
    rel = a.lo_from_hi.inverse() @ b.lo_from_hi
    if (
        rotation_angle_deg(rel.R) > o.prior_override_max_deg
        or abs(np.log(rel.s)) > o.consistency_max_log_scale
    ):
        return False
    for p in (a, b):
        if p.keys.get(hi) not in m_hi.keyframes:
            return False
        c = np.asarray(m_hi.keyframes[p.keys[hi]].world_from_cam, dtype=np.float64)[:3, 3]
        if float(np.linalg.norm(a.lo_from_hi.apply(c) - b.lo_from_hi.apply(c))) > o.prior_override_max_m:
            return False
    return True


def _independent(a: Place, b: Place, maps: Any) -> bool:
    """Neither map's keyframes of the two places share a map point (nor are one keyframe)."""
    for mid, ka in a.keys.items():
        kb, m = b.keys.get(mid), maps.get(mid)
        if m is None or kb is None or ka == kb or (ka in m.keyframes and kb in m.covisibility(ka)):
            return False
    return True


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
        # (unless weak or lost tracking between the two keyframes may have put the error there: the
        # limits grow by that, and the robust pose graph judges the loop)
        move, turn = correction_of(det.target_from_source, m.keyframes[det.query_key].world_from_cam)
        slack = correction_slack(m, det.query_key, det.candidate_key)
        lim_m, lim_deg = o.loop_max_correction_m + slack[0], o.loop_max_correction_deg + slack[1]
        if move > lim_m or turn > lim_deg:
            return (
                f"loop {det.query_key} -> {det.candidate_key} refused: it would move the query "
                f"{move:.2f} m / {turn:.1f} deg (limits {lim_m:.2f} m, {lim_deg:.1f} deg)",
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
