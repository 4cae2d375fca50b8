"""Fitting a detection's transform: trimmed Umeyama on its 3D point pairs, levelled by the keyframes'
IMU up directions (4 DoF), refined by reprojection, and its bootstrap spread (the edge's sigmas).

Pure functions over maps; they run on the event loop (quick) and never change a map.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, levelled_similarity, rotation_angle_deg, rotation_between, se3_inverse
from hivemap.server.backend.gnss import bend_corrections
from hivemap.server.backend.options import BackendOptions
from hivemap.server.backend.weld import BOUND_SIGMAS
from hivemap.server.placerec import Detection, pair_observations, refine_sim3

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

# Each point pair of a levelled fit is weighted by its distances to the two keyframes, as stereo depth
# error grows with the square of the distance.
DEPTH_WEIGHTED = True
# Fewer pairs seen in both keyframes than this: the levelled fit is not refined by reprojection.
MIN_REFINE_OBSERVATIONS = 20


def fit_pairs(
    tgt: Any,
    src: Any,
    pairs: list[tuple[Any, Any]],
    min_inlier_ratio: float,
    with_scale: bool = True,
    up: tuple[F64, F64] | None = None,
    centres: tuple[F64, F64] | None = None,
    bootstrap: int = 0,
    depth_weighted: bool = True,
) -> tuple[Sim3 | None, F64, int, tuple[float, float] | None]:
    """``target_from_source`` fitted to duplicate point pairs ``(target_point, source_point)`` by trimmed
    Umeyama; returns (Sim3 or None if most pairs do not fit, inlier source points, number of inliers,
    spread). ``bootstrap`` (with ``centres``): the trimmed fit is repeated on that many resamples of the
    pairs, and the spread is the rms of their rotation angles from it (rad) and of the source camera
    centre's displacement under them (m; None without).
    ``up``: the up direction in the source and the target frame; the rotation then takes one onto the
    other and only its part about the up axis is fitted (:func:`levelled_similarity`). ``centres``: the
    camera centres in the source and the target frame that saw the points; with ``up`` and
    ``depth_weighted`` each pair is then weighted as stereo depth error grows, by 1 / (d_src^4 + d_tgt^4),
    its distances to them."""
    a, b = [], []
    for kt, ks in pairs:
        pt, ps = tgt.points.get(tgt.resolve_point(kt)), src.points.get(src.resolve_point(ks))
        if pt is not None and ps is not None:
            a.append(ps.xyz)
            b.append(pt.xyz)
    if len(a) < 20:
        return None, np.zeros((0, 3)), 0, None
    A, B = np.array(a), np.array(b)
    sig = np.ones(len(A))
    if up is not None and centres is not None and depth_weighted:
        d_src, d_tgt = np.linalg.norm(A - centres[0], axis=1), np.linalg.norm(B - centres[1], axis=1)
        sig = np.sqrt(d_src**4 + d_tgt**4) + 1e-9

    level = rotation_between(*up) if up is not None else None

    def fit(idx: NDArray[np.int64]) -> Sim3:
        if up is None:
            return umeyama(A[idx], B[idx], with_scale)
        return levelled_similarity(A[idx], B[idx], *up, with_scale, 1.0 / sig[idx] ** 2, level)

    def trimmed(idx: NDArray[np.int64]) -> tuple[Sim3 | None, NDArray[np.int64]]:
        """The fit to pairs ``idx`` (repeats allowed) and the ones its trimming keeps."""
        est, ok = fit(idx), np.ones(len(idx), dtype=bool)
        for _ in range(4):
            r = np.linalg.norm(est.apply(A[idx]) - B[idx], axis=1) / sig[idx]
            ok = r <= max(2.5 * float(np.median(r[ok])), 1e-12)
            if ok.sum() < 20:
                return None, idx[ok]
            est = fit(idx[ok])
        return est, idx[ok]

    est, keep = trimmed(np.arange(len(A)))
    if est is None:
        return None, np.zeros((0, 3)), len(keep), None
    n_in = len(keep)
    if n_in < min_inlier_ratio * len(A):
        return None, A[keep], n_in, None
    spread = None
    if bootstrap > 0 and centres is not None:
        # the same resamples for the same pairs (reproducible runs); each resample of all the pairs is
        # trimmed again (resampling the inliers alone gave a 0.65 m-wrong UGV loop a spread of 0.15 m)
        rng = np.random.default_rng(len(A))
        c = est.apply(centres[0][None])[0]
        rot, move = [], []
        for _ in range(bootstrap):
            eb, _ = trimmed(rng.integers(0, len(A), len(A)))
            if eb is None:
                continue
            rot.append(math.radians(rotation_angle_deg(eb.R @ est.R.T)))
            move.append(float(np.linalg.norm(eb.apply(centres[0][None])[0] - c)))
        if rot:
            spread = (float(np.sqrt(np.mean(np.square(rot)))), float(np.sqrt(np.mean(np.square(move)))))
    return est, A[keep], n_in, spread


def umeyama(src: F64, dst: F64, with_scale: bool = True) -> Sim3:
    """The Sim(3) ``dst ~ s R src + t`` (least squares, evo's Umeyama); s = 1 without ``with_scale``."""
    from evo.core.geometry import umeyama_alignment

    R, t, s = umeyama_alignment(src.T, dst.T, with_scale=with_scale)
    return Sim3(np.asarray(R), np.asarray(t).reshape(3), float(s))


def frame_correction(corrections: list[Sim3], centres: F64, with_scale: bool = True) -> Sim3:
    """The one Sim(3) that moves an agent's frame as its recent keyframes' ``corrections`` move them
    (``centres``: those keyframes' camera centres before): rotation the chordal mean of theirs, scale
    their geometric mean (1 without ``with_scale``), translation the least-squares one at the centres.
    A point fit to the moved centres instead would get its rotation from their spread: for a standing
    agent (centres a millimetre apart) each correction's millimetre of noise turns it by tens of degrees."""
    R_sum = np.sum([c.R for c in corrections], axis=0)
    U, _, Vt = np.linalg.svd(R_sum)
    R = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt
    s = float(np.exp(np.mean([math.log(c.s) for c in corrections]))) if with_scale else 1.0
    P = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    moved = np.array([c.apply(p) for c, p in zip(corrections, P, strict=True)])
    t = np.mean(moved - s * (P @ R.T), axis=0)
    return Sim3(R, t, s)


def levelled(
    o: BackendOptions,
    maps: Any,
    gnss_unbend: dict[int, dict[KfKey, Sim3]],
    det: Detection,
    ups: tuple[F64 | None, F64 | None] | None = None,
) -> tuple[Sim3 | None, tuple[float, float]]:
    """The detection's Sim(3) re-fitted to its 3D pairs with roll/pitch taken from the two keyframes' IMU
    up directions, then refined in yaw and translation by the pairs' reprojections (``FitOptions.
    level_gravity``, ``level_reprojection``; ``ups``: the query's and the candidate's from
    :func:`up_cam` if the caller has them), and the sigmas (rad, m) of its pose-graph edge: the fit's
    spread (``FitOptions.loop_sigma_bootstrap``), at least the essential edges'. The Sim(3) is
    None when off, when either keyframe has no up direction, or when the pairs do not fit (the
    sigmas are then the essential edges')."""
    floor = (o.optimise.pose_graph_sigma_rot, o.optimise.pose_graph_sigma_trans)
    mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
    if not o.fit.level_gravity or mq is None or mc is None:
        return None, floor
    qkf, ckf = mq.keyframes.get(det.query_key), mc.keyframes.get(det.candidate_key)
    if qkf is None or ckf is None:
        return None, floor
    w = o.fit.level_up_window
    uq, uc = ups or (up_cam(mq, det.query_key, w, gnss_unbend), up_cam(mc, det.candidate_key, w, gnss_unbend))
    if uq is None or uc is None:
        return None, floor
    # the IMU's up in either map's frame, at either keyframe
    up = (qkf.world_from_cam[:3, :3] @ uq, ckf.world_from_cam[:3, :3] @ uc)
    centres = (qkf.world_from_cam[:3, 3], ckf.world_from_cam[:3, 3])
    pairs = list(zip(det.candidate_points, det.query_points, strict=True))
    sim, _, _, spread = fit_pairs(
        mc, mq, pairs, o.accept.min_pair_inlier_ratio, not o.fix_scale, up, centres,
        o.fit.loop_sigma_bootstrap, depth_weighted=DEPTH_WEIGHTED,
    )  # fmt: skip
    if sim is None:
        return None, floor
    if o.fit.level_reprojection:
        sim = refine_levelled(mq, mc, det, sim, up[1], o.fix_scale)
    sd_rot, sd_trans = spread or (0.0, 0.0)
    return sim, (max(sd_rot, floor[0]), max(sd_trans, floor[1]))


def welded_sigmas(
    o: BackendOptions, weld_rec: dict[str, Any] | None, sigmas: tuple[float, float]
) -> tuple[float, float]:
    """The pose-graph edge's sigmas (rad, m) of a detection after its weld: an edge carries the covariance
    of the estimate it carries, so a welded one the weld's own (its 99 % bound over the chi point it was
    drawn at), at least the essential edges'; ``sigmas`` (the fit's) when there was no weld. With the
    fit's wider spread on the weld's transform, a weld that slid along a valley of far points stayed
    within its edge's sigmas, and the robust graph kept it (docs/decisions.md)."""
    if not weld_rec or not weld_rec.get("ok"):
        return sigmas
    floor = (o.optimise.pose_graph_sigma_rot, o.optimise.pose_graph_sigma_trans)
    rot = math.radians(float(weld_rec["bound_deg"])) / BOUND_SIGMAS
    return max(rot, floor[0]), max(float(weld_rec["bound_m"]) / BOUND_SIGMAS, floor[1])


def refine_levelled(mq: Any, mc: Any, det: Detection, sim: Sim3, up_c: F64, fix_scale: bool) -> Sim3:
    """The levelled fit refined by its pairs' bidirectional reprojection error (paper 2.5.1) in yaw and
    translation only (``FitOptions.level_reprojection``); the fit itself if too few pairs are seen."""
    obs = pair_observations(mq, mc, det.query_key, det.candidate_key, det.query_points,
                            det.candidate_points)  # fmt: skip
    if len(obs.xc) < MIN_REFINE_OBSERVATIONS:
        return sim
    q = mq.keyframes[det.query_key]
    world_from_cam = np.asarray(q.world_from_cam, dtype=np.float64)
    q_cfw = se3_inverse(world_from_cam)
    out = refine_sim3(sim, obs, q.camera, q_cfw, fix_scale, yaw_axis=up_c)
    if logger.isEnabledFor(logging.DEBUG):
        c = world_from_cam[:3, 3][None]
        logger.debug("levelled %s -> %s refined on %d reprojections: query camera moved %.3f m",
                     det.query_key, det.candidate_key, len(obs.xc),
                     float(np.linalg.norm(out.apply(c) - sim.apply(c))))  # fmt: skip
    return out


def up_cam(m: Any, key: KfKey, window: int, gnss_unbend: dict[int, dict[KfKey, Sim3]]) -> F64 | None:
    """The IMU's up direction in keyframe ``key``'s camera: the mean of its agent's keyframes' up
    directions within ``window`` ids (``FitOptions.level_up_window``), each carried to ``key`` by the map's
    visual relative rotation (the GNSS stage's bend, which holds keyframes to those very directions,
    taken out); None if the keyframe has none. An agent sends each keyframe's up direction once, from
    its filter's estimate at that time, and it can be off for a few seconds; the mean smooths that."""
    kf = m.keyframes[key]
    if kf.up_cam is None:
        return None
    w = window
    unbend = gnss_unbend.get(m.id)
    corr = bend_corrections(m, unbend, invert=False) if unbend and w > 0 else {}

    def rot(k: KfKey) -> F64:
        R = np.asarray(m.keyframes[k].world_from_cam, dtype=np.float64)[:3, :3]
        c = corr.get(k)
        return R if c is None else c.R @ R

    acc = np.zeros(3)
    for j in range(key[1] - w, key[1] + w + 1):
        n = m.keyframes.get((key[0], j))
        if n is not None and n.up_cam is not None:
            acc += rot((key[0], j)) @ np.asarray(n.up_cam, dtype=np.float64)
    up: F64 = rot(key).T @ acc
    return up / np.linalg.norm(up)


def edge_measure(m: Any, det: Detection) -> Sim3:
    """``cand_from_query`` between the two detection keyframes as measured by the detection (after the
    merge both are in one frame, so it equals their current relative pose up to the merge)."""
    Tc = Sim3.from_se3(m.keyframes[det.candidate_key].world_from_cam)
    Tq = Sim3.from_se3(m.keyframes[det.query_key].world_from_cam)
    return Tc.inverse() @ Tq
