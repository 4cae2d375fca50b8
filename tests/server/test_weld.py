"""The weld (backend.weld): a detection's transform refined by stereo reprojection over both covisible
windows.

Scene: a room's walls 4-9 m from two windows of 5 stereo keyframes each (0.12 m baseline, 1 px keypoint
noise; each side's map points triangulated from them by maximum likelihood). The query
side lives in a map frame that the true transform carries onto the candidate's; the detection's transform
starts 3 deg / 0.3 m off. A weld brings the two keyframes' relative pose back to within 2 cm / 0.1 deg of
the truth; one whose points are all on one distant patch, or too few, is refused.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
import pytest

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, se3_inverse, so3_exp
from hivemap.maps.model import Keyframe, Map, MapPoint
from hivemap.server.backend.options import FitOptions
from hivemap.server.backend.weld import build, solve, welded
from hivemap.server.placerec import Detection

CAM = PinholeCamera(640, 480, 458.0, 457.0, 320.0, 240.0)
BASELINE = 0.12
PX = 1.0
UP = np.array([0.0, 0.0, 1.0])
# world_from_cam of a camera looking along +x (camera z forward, x right, y down)
LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _walls(rng: np.random.Generator, n: int, near: float, far: float, spread: float) -> np.ndarray:
    """Points in front of cameras near the origin looking along +x, ``near``-``far`` m away, across
    ``spread`` times the field of view."""
    d = rng.uniform(near, far, n)
    return np.column_stack(
        [d, spread * rng.uniform(-0.6, 0.6, n) * d, spread * rng.uniform(-0.4, 0.4, n) * d]
    )


def _poses(rng: np.random.Generator, centre: np.ndarray) -> list[np.ndarray]:
    out = []
    for i in range(5):
        R = so3_exp(np.array([0.0, 0.0, 0.04 * (i - 2)])) @ so3_exp(rng.normal(0, 0.01, 3)) @ LOOK_X
        out.append(se3(R, centre + np.array([0.0, 0.25 * (i - 2), 0.05 * i])))
    return out


def _triangulate(obs: list[list[tuple[np.ndarray, float, float, float]]]) -> list[np.ndarray]:
    """Each point's maximum-likelihood position from its stereo observations (world_from_cam, u, v, uR),
    poses held: one gtsam graph of GenericStereoFactor3D, as a local BA with fixed keyframes would give."""
    K = gtsam.Cal3_S2Stereo(CAM.fx, CAM.fy, 0.0, CAM.cx, CAM.cy, BASELINE)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, PX)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    poses: dict[bytes, int] = {}
    for i, ob in enumerate(obs):
        init = []
        for Tw, u, v, ur in ob:
            key = poses.setdefault(Tw.tobytes(), len(poses))
            if key == len(poses) - 1 and not values.exists(gtsam.symbol("x", key)):
                values.insert(gtsam.symbol("x", key), gtsam.Pose3(Tw))
                graph.add(gtsam.NonlinearEqualityPose3(gtsam.symbol("x", key), gtsam.Pose3(Tw)))
            graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, ur, v), noise, gtsam.symbol("x", key),
                                                  gtsam.symbol("p", i), K))  # fmt: skip
            z = CAM.fx * BASELINE / max(u - ur, 0.5)  # a start no nearer than a half-pixel disparity allows
            xyz = np.array([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z])
            init.append(Tw[:3, :3] @ xyz + Tw[:3, 3])
        values.insert(gtsam.symbol("p", i), np.median(init, axis=0))
    out = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return [out.atPoint3(gtsam.symbol("p", i)) for i in range(len(obs))]


def _side(rng: np.random.Generator, agent: str, X: np.ndarray, world_poses: list[np.ndarray],
          map_from_world: np.ndarray) -> tuple[list[Keyframe], list[MapPoint], dict[int, int]]:  # fmt: skip
    """One side's keyframes (in its map's frame) observing the true points ``X`` (1 px noise), and its map
    points triangulated from them (:func:`_triangulate`); returns the point id per index of ``X``."""
    pid: dict[int, int] = {}
    obs: list[list[tuple[np.ndarray, float, float, float]]] = []
    kfs = []
    for j, Tw in enumerate(world_poses):
        cfw = se3_inverse(Tw)
        pc = X @ cfw[:3, :3].T + cfw[:3, 3]
        uv, ok = CAM.project(pc)
        ok &= CAM.in_image(uv, 5.0) & (pc[:, 2] > 0.5)
        idx = np.flatnonzero(ok)
        kp = uv[idx] + rng.normal(0, PX, (len(idx), 2))
        ur = uv[idx, 0] - CAM.fx * BASELINE / pc[idx, 2] + rng.normal(0, PX, len(idx))
        ids = np.empty(len(idx), np.int64)
        for r, i in enumerate(idx.tolist()):
            if i not in pid:
                pid[i] = len(obs)
                obs.append([])
            obs[pid[i]].append((Tw, float(kp[r, 0]), float(kp[r, 1]), float(ur[r])))
            ids[r] = pid[i]
        kfs.append(Keyframe(agent, j, float(j), map_from_world @ Tw, CAM, kp.astype(np.float32),
                            np.zeros(len(idx), np.uint8), None, ids, up_cam=Tw[:3, :3].T @ UP,
                            u_right=ur.astype(np.float32), stereo_baseline=BASELINE))  # fmt: skip
    R, t = map_from_world[:3, :3], map_from_world[:3, 3]
    pts = [MapPoint(agent, k, R @ p + t) for k, p in enumerate(_triangulate(obs))]
    return kfs, pts, pid


def _scene(seed: int, n_points: int = 1500, near: float = 4.0, far: float = 9.0, spread: float = 1.0,
           ) -> dict[str, Any]:  # fmt: skip
    """Two maps of one room and a detection between their middle keyframes; ``true``: the true
    target_from_source (candidate map from query map)."""
    rng = np.random.default_rng(seed)
    X = _walls(rng, n_points, near, far, spread)
    true = se3(so3_exp(np.radians(40.0) * UP), np.array([5.0, -3.0, 0.2]))  # candidate map from query map
    kq, ptq, pidq = _side(rng, "uav1", X, _poses(rng, np.array([0.0, 0.0, 1.5])), se3_inverse(true))
    kc, ptc, pidc = _side(rng, "uav2", X, _poses(rng, np.array([-0.8, 0.6, 1.3])), np.eye(4))
    maps = {}
    for mid, kfs, pts in ((0, kq, ptq), (1, kc, ptc)):
        m = Map(mid)
        for p in pts:
            m.add_point(p)
        for kf in kfs:
            m.add_keyframe(kf)
        maps[mid] = m
    qk, ck = ("uav1", 2), ("uav2", 2)
    seen_q = {int(i) for i in maps[0].keyframes[qk].point_ids if i >= 0}
    seen_c = {int(i) for i in maps[1].keyframes[ck].point_ids if i >= 0}
    both = [i for i in pidq if pidq[i] in seen_q and i in pidc and pidc[i] in seen_c]
    return {"maps": maps, "true": true, "qk": qk, "ck": ck,
            "pairs": ([("uav1", pidq[i]) for i in both], [("uav2", pidc[i]) for i in both])}  # fmt: skip


def _detection(s: dict[str, Any], start: np.ndarray, n_pairs: int | None = None) -> Detection:
    q, c = s["pairs"]
    q, c = q[:n_pairs], c[:n_pairs]
    return Detection(s["qk"], 0, s["ck"], 1, Sim3(start[:3, :3], start[:3, 3]), len(q), q, c, "merge")


def _rel_error(s: dict[str, Any], det: Detection) -> tuple[float, float]:
    """The detection's cam_candidate_from_cam_query against the truth: (m, deg)."""
    mq, mc = s["maps"][0], s["maps"][1]
    Tq, Tc = mq.keyframes[s["qk"]].world_from_cam, mc.keyframes[s["ck"]].world_from_cam
    meas = se3_inverse(Tc) @ det.target_from_source.matrix() @ Tq
    true = se3_inverse(Tc) @ s["true"] @ Tq
    d = se3_inverse(true) @ meas
    return float(np.linalg.norm(d[:3, 3])), rotation_angle_deg(d[:3, :3])


def _weld(
    s: dict[str, Any],
    det: Detection,
    up: bool,
    o: FitOptions,
    fit_sigmas: tuple[float, float] | None = None,
) -> tuple[Any, Detection | None]:
    mq = s["maps"][0]
    up_q = np.asarray(mq.keyframes[s["qk"]].up_cam) if up else None
    job = build(s["maps"], det, up_q, o, fit_sigmas)
    assert job is not None
    res = solve(job)
    return res, welded(s["maps"], det, job, res) if res.ok else None


@pytest.mark.parametrize(("seed", "levelled"), [(1, True), (2, True), (3, False)])
def test_a_perturbed_transform_is_welded_back_to_the_truth(seed: int, levelled: bool) -> None:
    s = _scene(seed)
    # levelled: the start has the true tilt (as the 4-DoF fit's) and is 3 deg off in yaw; otherwise about a
    # tilted axis (6 DoF); both 0.3 m off
    axis = UP if levelled else np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    start = se3(so3_exp(np.radians(3.0) * axis), np.array([0.2, -0.2, 0.1])) @ s["true"]
    det = _detection(s, start)
    before = _rel_error(s, det)
    assert before[0] > 0.25 and before[1] > 2.9
    res, out = _weld(s, det, levelled, FitOptions())
    assert res.ok, res.reason
    assert res.dof == ("tilt0.2" if levelled else "6dof")  # the default: tilt free within 0.2 deg
    assert out is not None
    err = _rel_error(s, out)
    assert err[0] < 0.02 and err[1] < 0.1, (before, err)
    # a close, well-spread scene: the 99 % bound covers the error and is centimetres
    bound = (res.bound_m, res.bound_deg)
    assert err[0] < bound[0] < 0.05 and err[1] < bound[1] < 0.2, (err, bound)
    assert res.n_inliers > 0.8 * res.n_obs


def test_gross_outliers_are_dropped() -> None:
    s = _scene(4)
    q, c = s["pairs"]
    rng = np.random.default_rng(0)
    wrong = rng.permutation(len(c))[: len(c) // 5]  # a fifth of the pairs matched to random other points
    c = list(c)
    for i, j in zip(wrong, rng.permutation(wrong), strict=True):
        c[i] = s["pairs"][1][j]
    s["pairs"] = (q, c)
    start = se3(so3_exp(np.radians(3.0) * UP), np.array([0.2, -0.2, 0.1])) @ s["true"]
    res, out = _weld(s, _detection(s, start), True, FitOptions())
    assert res.ok and out is not None, res.reason
    err = _rel_error(s, out)
    assert err[0] < 0.02 and err[1] < 0.1, err


def test_a_weld_that_disagrees_with_the_fit_beyond_both_bounds_is_refused() -> None:
    """The fit is 0.3 m / 3 deg off. Had it claimed 1 cm / 0.06 deg (its bootstrap sigmas), the weld's
    move would contradict it beyond both estimates' 99 % bounds together: one of the two is wrong, and
    the detection is refused. With the spread such a fit really has (0.15 m / 1.1 deg) it is welded."""
    s = _scene(8)
    start = se3(so3_exp(np.radians(3.0) * UP), np.array([0.2, -0.2, 0.1])) @ s["true"]
    res, out = _weld(s, _detection(s, start), True, FitOptions(), fit_sigmas=(0.001, 0.01))
    assert not res.ok and out is None
    assert "moved the fit" in res.reason, res.reason
    assert res.moved_m > 0.25 and res.bound_m < 0.05, (res.moved_m, res.bound_m)
    res, out = _weld(s, _detection(s, start), True, FitOptions(), fit_sigmas=(0.02, 0.15))
    assert res.ok and out is not None, res.reason
    err = _rel_error(s, out)
    assert err[0] < 0.02 and err[1] < 0.1, err


def test_far_points_or_too_few_pairs_are_refused() -> None:
    # every point on one distant patch (40-60 m from 0.12 m-baseline cameras, a twentieth of the field of
    # view): the translation along the view is barely observed
    far = _scene(5, n_points=200, near=40.0, far=60.0, spread=0.05)
    start = se3(so3_exp(np.radians(3.0) * UP), np.array([0.2, -0.2, 0.1])) @ far["true"]
    res, out = _weld(far, _detection(far, start), True, FitOptions())
    assert not res.ok and out is None
    assert res.bound_m > 0.5, res.bound_m
    # ten pairs: too few points to weld on
    s = _scene(6)
    start = se3(so3_exp(np.radians(3.0) * UP), np.array([0.2, -0.2, 0.1])) @ s["true"]
    res, out = _weld(s, _detection(s, start, n_pairs=10), True, FitOptions())
    assert not res.ok and out is None and "point pairs" in res.reason


def test_a_tilt_error_is_corrected_within_the_tilt_prior_and_kept_in_4_dof() -> None:
    s = _scene(7)
    # the levelled fit's tilt is off by 0.5 deg (its keyframes' IMU up directions were), its yaw by 3 deg
    tilt = so3_exp(np.radians(0.5) * np.array([1.0, 0.0, 0.0]))
    start = se3(so3_exp(np.radians(3.0) * UP) @ tilt, np.array([0.2, -0.2, 0.1])) @ s["true"]
    det = _detection(s, start)
    held, out_held = _weld(s, det, True, FitOptions(weld_tilt_sigma_deg=0.0))
    free, out_free = _weld(s, det, True, FitOptions(weld_tilt_sigma_deg=0.2))
    assert held.dof == "4dof"
    assert held.ok and free.ok and out_held is not None and out_free is not None
    assert free.dof == "tilt0.2"
    # 4 DoF keeps the tilt it was given; a 0.2 deg prior lets thousands of stereo observations take it out
    assert 0.4 < _rel_error(s, out_held)[1] < 0.6, _rel_error(s, out_held)
    err = _rel_error(s, out_free)
    assert err[0] < 0.02 and err[1] < 0.1, err
