"""The front-end's local mapping: when a frame becomes a keyframe, creating it (stereo points, the
relative pose covariance), multi-view triangulation, local BA and map-point culling."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.emit import emit_ready
from hivemap.client.frontend.events import PoseUpdateEvent, TrackingState
from hivemap.client.frontend.mapdata import Frame, KeyframeData
from hivemap.client.frontend.optim import (
    BAProblem,
    bundle_adjust,
    chi2_of,
    chi2_thresholds,
    pose_hessian,
)
from hivemap.client.frontend.preint import InertialEdge, InertialWindow

if TYPE_CHECKING:
    from hivemap.client.frontend.tracker import Frontend

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def need_keyframe(fe: Frontend, frame: Frame, n_tracked: int, gnss_epoch: bool, state: TrackingState) -> bool:
    o = fe.options
    if gnss_epoch or state == TrackingState.RELOCALIZED:
        return True
    last = fe._kfs.get(fe._kf_last_id)
    if last is None:
        return True
    if frame.t - last.timestamp >= o.kf_max_interval_s:
        return True
    tracked = frame.point_ids >= 0
    close_th = o.close_depth_baselines * fe.rig.baseline
    z = frame.pts_cam[:, 2]
    close = np.isfinite(z) & (z < close_th)
    n_close_tracked = int((tracked & close).sum())
    n_close_untracked = int((~tracked & close).sum())
    weak_close = n_close_tracked < o.kf_min_close_tracked and n_close_untracked > o.kf_min_close_tracked
    return n_tracked < o.kf_min_tracked_ratio * fe._ref_tracked or weak_close


def keyframe_while_lost(fe: Frontend, frame: Frame) -> bool:
    """Lost for want of matches, with the IMU holding the pose: does the frame give a keyframe to track
    on (the caller leaves out frames the IMU gate refused: there the image, not the map, disagrees)?"""
    o = fe.options
    if not (o.imu_lost_keyframes and fe._filter is not None and fe._gravity_aligned):
        return False
    last = fe._kfs.get(fe._kf_last_id)
    if last is not None and frame.t - last.timestamp < o.imu_lost_keyframe_interval_s:
        return False
    # any depth: when a close object leaves the view, the far background it hid has no map points (a
    # keyframe makes only its close points when it has enough of them), and it is all there is
    return int(np.isfinite(frame.pts_cam[:, 2]).sum()) >= o.imu_lost_keyframe_min_points


def create_keyframe(fe: Frontend, frame: Frame, gnss_epoch: bool, first: bool = False) -> int:
    import time

    o = fe.options
    kid = fe._kf_counter
    fe._kf_counter += 1
    prev = fe._kfs.get(fe._kf_last_id)
    kf = KeyframeData(
        kid, fe.session, frame, frame.T_cw.copy(), gnss_epoch, prev_id=prev.id if prev else None
    )
    fe._kfs[kid] = kf
    fe.stats.keyframes += 1
    odom = fe.take_odom_sigma()
    kf.odom_sigma = odom if prev is not None else None
    if fe.kf_imu is not None and fe.imu is not None:
        bias = fe.imu.bias_vector()
        pre = fe.kf_imu.take(bias)
        kf.preint = pre if prev is not None else None
        kf.bias = bias
        kf.v_w = fe._filter.v.copy() if fe._filter is not None else fe._velocity_w.copy()
    pts = fe._pts
    tracked_before = int((frame.point_ids >= 0).sum())
    for i in np.flatnonzero(frame.point_ids >= 0):
        pid = int(frame.point_ids[i])
        pts.obs[pid][kid] = int(i)
        pts.desc[pid] = frame.desc[i]
    # stereo points: all close ones, at least 100 (closest first) as ORB-SLAM
    z = frame.pts_cam[:, 2]
    cand = np.flatnonzero(np.isfinite(z) & (frame.point_ids < 0))
    cand = cand[np.argsort(z[cand])]
    close_th = o.close_depth_baselines * fe.rig.baseline
    n_close = int((z[cand] < close_th).sum())
    n_take = max(n_close, min(len(cand), 100 if not first else len(cand)))
    new = cand[:n_take]
    if len(new):
        Xw = frame.pts_cam[new] @ kf.T_wc[:3, :3].T + kf.T_wc[:3, 3]
        ids = pts.add(Xw, frame.desc[new], kid)
        frame.point_ids[new] = ids
        for pid, i in zip(ids, new, strict=True):
            pts.obs[int(pid)][kid] = int(i)
    t0 = time.perf_counter()
    if not first:
        triangulate(fe, kf)
    t1 = time.perf_counter()
    if not first:
        local_ba(fe, kf)
        cull_points(fe, kid)
    t2 = time.perf_counter()
    fe.stats.timing["triangulate"] = fe.stats.timing.get("triangulate", 0.0) + t1 - t0
    fe.stats.timing["local_ba"] = fe.stats.timing.get("local_ba", 0.0) + t2 - t1
    frame.T_cw = kf.T_cw
    # relative pose covariance from the keyframe's own observations (motion-only information)
    if prev is not None:
        tr = frame.point_ids >= 0
        idx = np.flatnonzero(tr)
        H = pose_hessian(fe.k, kf.T_cw, pts.xyz[frame.point_ids[idx]], frame.meas[idx], frame.inv_sigma2[idx])
        try:
            cov = np.linalg.inv(H + 1e-6 * np.eye(6))
        except np.linalg.LinAlgError:
            cov = np.eye(6)
        # left perturbation of cam_from_world == (minus) right perturbation of world_from_cam
        dist = float(np.linalg.norm(kf.T_wc[:3, 3] - prev.T_wc[:3, 3]))
        floor = np.array([1e-3 + 2e-3 * np.radians(1.0)] * 3 + [1e-3 + 4e-3 * dist] * 3) ** 2
        kf.rel_cov_cam = cov + np.diag(floor)
    fe._kf_last_id = kid
    fe._ref_tracked = tracked_before if not first else int((frame.point_ids >= 0).sum())
    fe._update_local_map()
    emit_ready(fe)
    return kid


def triangulate(fe: Frontend, kf: KeyframeData) -> None:
    """Multi-view triangulation of unmatched keypoints with the previous keyframes."""
    o = fe.options
    f1 = kf.frame
    un1 = np.flatnonzero(f1.point_ids < 0)
    if len(un1) < 10:
        return
    nbrs = sorted((k for k in fe._kfs if k != kf.id), reverse=True)[: o.triangulation_neighbours]
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    K = fe.cam.K
    Kinv = np.linalg.inv(K)
    C1 = kf.T_wc[:3, 3]
    for nid in nbrs:
        nk = fe._kfs[nid]
        f2 = nk.frame
        un2 = np.flatnonzero(f2.point_ids < 0)
        un1 = np.flatnonzero(f1.point_ids < 0)
        if len(un2) < 10 or len(un1) < 10:
            continue
        C2 = nk.T_wc[:3, 3]
        if np.linalg.norm(C2 - C1) < 0.5 * fe.rig.baseline:
            continue
        knn = bf.knnMatch(f1.desc[un1], f2.desc[un2], k=2)
        a, b = [], []
        for m in knn:
            if len(m) == 2 and m[0].distance <= 50 and m[0].distance < 0.7 * m[1].distance:
                a.append(un1[m[0].queryIdx])
                b.append(un2[m[0].trainIdx])
        if len(a) < 5:
            continue
        ia, ib = np.array(a), np.array(b)
        _, u = np.unique(ib, return_index=True)
        ia, ib = ia[u], ib[u]
        x1 = np.c_[f1.kpu[ia], np.ones(len(ia))] @ Kinv.T
        x2 = np.c_[f2.kpu[ib], np.ones(len(ib))] @ Kinv.T
        r1 = x1 @ kf.T_wc[:3, :3].T
        r2 = x2 @ nk.T_wc[:3, :3].T
        cosp = (r1 * r2).sum(1) / np.linalg.norm(r1, axis=1) / np.linalg.norm(r2, axis=1)
        ok = cosp < o.min_parallax_cos
        if not ok.any():
            continue
        ia, ib, x1, x2 = ia[ok], ib[ok], x1[ok], x2[ok]
        Xh = cv2.triangulatePoints(kf.T_cw[:3], nk.T_cw[:3], x1[:, :2].T, x2[:, :2].T)
        Xw = (Xh[:3] / np.where(np.abs(Xh[3]) > 1e-12, Xh[3], 1e-12)).T
        good = np.isfinite(Xw).all(1)
        # Each view's reprojection, with the right-image coordinate where the keypoint has one (as
        # local BA will weigh it): two views alone only check the epipolar line, so a wrong match
        # along it (repeated posters on a wall) triangulates at a wrong depth that its stereo
        # measurement contradicts, and such points pull local BA's keyframes (docs/decisions.md).
        for T, f, idx in ((kf.T_cw, f1, ia), (nk.T_cw, f2, ib)):
            pc = Xw @ T[:3, :3].T + T[:3, 3]
            meas = f.meas[idx]
            chi2 = chi2_of(fe.k, pc, meas, f.inv_sigma2[idx])
            good &= (pc[:, 2] > 0.1) & (chi2 < chi2_thresholds(meas))
        if not good.any():
            continue
        ia, ib, Xw = ia[good], ib[good], Xw[good]
        ids = fe._pts.add(Xw, f1.desc[ia], kf.id)
        f1.point_ids[ia] = ids
        f2.point_ids[ib] = ids
        for pid, i, j in zip(ids, ia, ib, strict=True):
            fe._pts.obs[int(pid)][kf.id] = int(i)
            fe._pts.obs[int(pid)][nid] = int(j)


def local_ba(fe: Frontend, kf: KeyframeData) -> None:
    o = fe.options
    cov = fe._covisibility(kf.id)
    inertial_on = vi_ba_active(fe)
    if inertial_on:
        # ORB-SLAM3's visual-inertial window: the last keyframes in time, chained by their IMU terms,
        # so that keyframes with few points are held by their neighbours' (and the IMU's) motion
        window = sorted(fe._kfs)[-o.ba_window :][::-1]
    else:
        # covisible keyframes as ORB-SLAM's graph has them: a handful of (likely false) matches is no
        # link, and would chain a keyframe made on the IMU alone to a part of the map it does not see
        strong = [k for k, c in sorted(cov.items(), key=lambda kv: -kv[1]) if c >= o.ba_min_shared]
        window = [kf.id] + strong[: o.ba_window - 1]
    wset = set(window)
    pids_l = [fe._kfs[k].frame.point_ids for k in window]
    pids = np.unique(np.concatenate(pids_l))
    pids = pids[pids >= 0]
    pids = pids[fe._pts.alive[pids]]
    if len(pids) < 10:
        return
    # every observation of the window's points: keyframe, point (index into pids), keypoint
    cams: list[int] = []
    kp_i: list[int] = []
    n_obs = np.zeros(len(pids), np.int64)
    for j, pid in enumerate(pids.tolist()):
        seen = fe._pts.obs[pid]
        cams.extend(seen)
        kp_i.extend(seen.values())
        n_obs[j] = len(seen)
    cam_arr = np.array(cams, np.int64)
    pt_all = np.repeat(np.arange(len(pids)), n_obs)
    # keyframes outside the window by the number of those points they see, in the order first seen
    others, first, counts = np.unique(
        cam_arr[~np.isin(cam_arr, window)], return_index=True, return_counts=True
    )
    seen_order = np.argsort(first)
    fixed_count = dict(zip(others[seen_order].tolist(), counts[seen_order].tolist(), strict=True))
    # nor does such a keyframe hold the window's gauge through its few shared points
    ranked = sorted(fixed_count.items(), key=lambda kv: -kv[1])
    fixed = [k for k, c in ranked if c >= o.ba_min_shared][: o.ba_fixed_max]
    before = fe._kfs[min(window)].prev_id if inertial_on else None
    if before is not None and before in fe._kfs and before not in fixed:
        fixed.append(before)  # the inertial anchor: its pose, velocity and bias held
    if not fixed:
        # gauge: hold the oldest keyframe of the window
        oldest = min(window)
        window.remove(oldest)
        fixed = [oldest]
    all_k = window + fixed
    # keyframe id -> its camera in the problem (-1: not in it)
    problem_index = np.full(max(max(cams, default=0), max(all_k)) + 1, -1, np.int64)
    problem_index[all_k] = np.arange(len(all_k))
    cam_all = problem_index[cam_arr]
    use = cam_all >= 0
    cam_idx = cam_all[use]
    pt_idx = pt_all[use]
    kp_arr = np.array(kp_i, np.int64)[use]
    cam_ids = cam_arr[use]
    meas = np.empty((len(cam_idx), 3))
    inv_s2 = np.empty(len(cam_idx))
    for k_id in all_k:
        m = cam_ids == k_id
        f = fe._kfs[k_id].frame
        meas[m] = f.meas[kp_arr[m]]
        inv_s2[m] = f.inv_sigma2[kp_arr[m]]
    poses = np.stack([fe._kfs[k].T_cw for k in all_k])
    is_fixed = np.array([k not in wset or k in fixed for k in all_k])
    prob = BAProblem(poses, is_fixed, fe._pts.xyz[pids].copy(), cam_idx, pt_idx, meas, inv_s2)
    iw = inertial_window(fe, all_k, is_fixed) if inertial_on else None
    n1 = max(2, o.ba_iterations // 2)
    poses2, X2, inl = bundle_adjust(fe.k, prob, n1, inertial=iw)
    prob2 = BAProblem(poses2, is_fixed, X2, cam_idx, pt_idx, meas, inv_s2)
    poses2, X2, inl2 = bundle_adjust(fe.k, prob2, o.ba_iterations - n1, active=inl, inertial=iw)
    # drop outlier observations
    for n in np.flatnonzero(~inl2):
        k_id = int(cam_ids[n])
        pid = int(pids[pt_idx[n]])
        fe._pts.obs[pid].pop(k_id, None)
        f = fe._kfs[k_id].frame
        if f.point_ids[kp_arr[n]] == pid:
            f.point_ids[kp_arr[n]] = -1
    for k_id, T in zip(all_k, poses2, strict=True):
        if k_id in wset and k_id not in fixed:
            fe._kfs[k_id].T_cw = T
            fe._kfs[k_id].frame.T_cw = T
    fe._pts.xyz[pids] = X2
    if iw is not None:
        for j, kf_id in enumerate(all_k):
            if kf_id in wset and kf_id not in fixed:
                fe._kfs[kf_id].v_w = iw.v[j].copy()
                fe._kfs[kf_id].bias = iw.b[j].copy()
                fe._kfs[kf_id].vi_refined = True
        inertial_feedback(fe, kf)
    upd = [k for k in window if k not in fixed and fe._kfs[k].emitted]
    if upd:
        pp = pids[fe._pts.emitted[pids]]
        # only points local BA moved by more than the bound since they were last streamed
        moved = np.linalg.norm(fe._pts.xyz[pp] - fe._pts.sent_xyz[pp], axis=1) > o.point_update_min_m
        pp = pp[moved]
        fe._pts.sent_xyz[pp] = fe._pts.xyz[pp]
        fe._events.append(
            PoseUpdateEvent(
                fe.session,
                np.array(upd, np.int64),
                np.stack([fe._kfs[k].T_wc for k in upd]),
                pp,
                fe._pts.xyz[pp].copy(),
            )
        )


def vi_ba_active(fe: Frontend) -> bool:
    """Local BA carries IMU terms: an IMU, the VIO frame gravity-aligned (the residuals use gravity)."""
    return bool(fe.options.vi_ba and fe.kf_imu is not None and fe._gravity_aligned and fe._filter is not None)


def inertial_window(fe: Frontend, all_k: list[int], is_fixed: NDArray[np.bool_]) -> InertialWindow:
    """Velocities, biases and the IMU edges between consecutive keyframes among ``all_k``.

    A held keyframe anchors an edge only once a visual-inertial BA has estimated its velocity and
    biases; before that they are the tracker's guesses (zero velocity at the start), and holding them
    would pull the window onto them."""
    o = fe.options
    assert fe.kf_imu is not None
    kidx = {k: n for n, k in enumerate(all_k)}
    v = np.zeros((len(all_k), 3))
    b = np.zeros((len(all_k), 6))
    edges: list[InertialEdge] = []
    for n, k_id in enumerate(all_k):
        kf = fe._kfs[k_id]
        if kf.v_w is not None:
            v[n] = kf.v_w
        if kf.bias is not None:
            b[n] = kf.bias
        prev = kf.prev_id
        if kf.preint is None or prev not in kidx:
            continue
        pk = fe._kfs[prev]
        usable = [k.v_w is not None and (k.vi_refined or not is_fixed[kidx[k.id]]) for k in (pk, kf)]
        if all(usable):
            edges.append(InertialEdge(kidx[prev], n, kf.preint, anchor=bool(is_fixed[kidx[prev]])))
    prior = np.array([o.vi_ba_gyro_bias_sigma**-2] * 3 + [o.vi_ba_acc_bias_sigma**-2] * 3)
    return InertialWindow(v, b, edges, fe.cam_from_body, fe.kf_imu.gyro_walk2, fe.kf_imu.acc_walk2, prior)


def inertial_feedback(fe: Frontend, kf: KeyframeData) -> None:
    """The newest keyframe's velocity and biases become the tracker's: the IMU prediction of the next
    frames integrates with them (ORB-SLAM3 predicts from the last keyframe's inertial state)."""
    if fe.imu is None or kf.bias is None or kf.v_w is None:
        return
    fe.imu.set_bias(kf.bias)
    fe._vi_ba_ran = True
    filt = fe._filter
    if filt is not None:
        filt.v = kf.v_w.copy()
        filt.c = np.zeros(3)  # the accelerometer bias is now estimated, not absorbed


def cull_points(fe: Frontend, kid: int) -> None:
    o = fe.options
    pts = fe._pts
    ids = pts.alive_ids()
    ids = ids[pts.first_kf[ids] >= kid - 6]  # recently created points only (ORB-SLAM's recent list)
    if len(ids) == 0:
        return
    nobs = np.array([len(pts.obs[i]) for i in ids])
    ratio = pts.found[ids] / np.maximum(pts.visible[ids], 1)
    age = kid - pts.first_kf[ids]
    bad = (nobs == 0) | ((ratio < o.culling_min_found_ratio) & (age >= 2)) | ((age >= 3) & (nobs <= 1))
    bad &= ~pts.emitted[ids] | (nobs == 0)
    for pid in ids[bad]:
        for k_id, i in pts.obs[pid].items():
            f = fe._kfs[k_id].frame
            if f.point_ids[i] == pid:
                f.point_ids[i] = -1
        pts.obs[pid] = {}
        pts.alive[pid] = False


# ------------------------------------------------------------------ events
