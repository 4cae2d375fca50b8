"""Pose-graph and bundle-adjustment primitives recover synthetic ground truth."""

from __future__ import annotations

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, se3_inverse, so3_exp
from hivemap.server.optim import (
    PoseGraphEdge,
    global_bundle_adjustment,
    relative_sim3,
    solve_pose_graph_sim3,
)


def _circle_poses(n: int, radius: float = 20.0) -> np.ndarray:
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        R = so3_exp([0.0, 0.0, a]) @ so3_exp([-np.pi / 2, 0.0, 0.0])
        poses.append(se3(R, [radius * np.cos(a), radius * np.sin(a), 2.0]))
    return np.array(poses)


def test_pose_graph_closes_loop_with_drift() -> None:
    """Odometry with a yaw bias and a 0.5% scale drift around a loop (the systematic drift a VO has);
    one loop edge with the true relative pose pulls the whole trajectory back: the worst position
    error drops by more than 5x and the loop end lands within 5 cm."""
    rng = np.random.default_rng(0)
    n = 40
    truth = _circle_poses(n)
    # Drifted odometry: every step gets a small rotation error and a 0.5% scale error.
    drifted = [truth[0]]
    edges = []
    for k in range(1, n):
        rel = se3_inverse(truth[k - 1]) @ truth[k]
        noisy = rel.copy()
        noisy[:3, :3] = rel[:3, :3] @ so3_exp([0.0, 0.003, 0.0]) @ so3_exp(rng.normal(0, 0.0005, 3))
        noisy[:3, 3] *= 1.005
        drifted.append(drifted[-1] @ noisy)
        edges.append(PoseGraphEdge(k - 1, k, Sim3.from_se3(noisy), 0.01, 0.05, 0.01))
    drifted_arr = np.array(drifted)
    before = np.linalg.norm(drifted_arr[:, :3, 3] - truth[:, :3, 3], axis=1).max()
    edges.append(
        PoseGraphEdge(n - 1, 0, relative_sim3(truth[n - 1], truth[0]), 0.001, 0.005, 0.001, robust=True)
    )
    out = solve_pose_graph_sim3(drifted_arr, edges, fixed={0}).poses
    after = np.array([np.linalg.norm(s.t - truth[k, :3, 3]) for k, s in enumerate(out)])
    assert before > 1.0, before  # the drift is real
    assert after.max() < 0.2 * before, (before, after.max())
    assert after[n - 1] < 0.05, after[n - 1]
    assert rotation_angle_deg(out[n - 1].R.T @ truth[n - 1, :3, :3]) < 0.5


def test_global_ba_recovers_perturbed_poses_and_points() -> None:
    """Perturb 20 poses by ~5 cm / 0.5 deg and 2000 points by ~5 cm; BA with two fixed keyframes
    brings poses back within 3 cm (the two fixed keyframes are only 0.5 m apart, so the small scale
    uncertainty grows along the 10 m path) and the reprojection error to the noise level (0.5 px)."""
    rng = np.random.default_rng(1)
    cam = PinholeCamera(640, 480, 420.0, 420.0, 320.0, 240.0, (-0.05, 0.01, 0.0005, -0.0003))
    n = 20
    truth = []
    for k in range(n):
        R = so3_exp([0.0, 0.02 * k, 0.0])
        truth.append(se3(R, [0.5 * k, 0.0, 0.0]))
    truth_arr = np.array(truth)
    pts = np.column_stack([rng.uniform(-5, 15, 2000), rng.uniform(-4, 4, 2000), rng.uniform(6, 20, 2000)])
    obs_kf, obs_pt, obs_uv = [], [], []
    for k in range(n):
        pc = (pts - truth_arr[k, :3, 3]) @ truth_arr[k, :3, :3]
        uv, valid = cam.project(pc)
        ok = valid & cam.in_image(uv)
        idx = np.flatnonzero(ok)
        obs_kf += [k] * len(idx)
        obs_pt += idx.tolist()
        obs_uv.append(uv[idx] + rng.normal(0, 0.5, (len(idx), 2)))
    kf_a = np.array(obs_kf)
    pt_a = np.array(obs_pt)
    uv_a = np.vstack(obs_uv)
    init = truth_arr.copy()
    for k in range(2, n):
        init[k, :3, :3] = init[k, :3, :3] @ so3_exp(rng.normal(0, 0.005, 3))
        init[k, :3, 3] += rng.normal(0, 0.05, 3)
    pts0 = pts + rng.normal(0, 0.05, pts.shape)
    res = global_bundle_adjustment([cam], np.zeros(n, dtype=np.int64), init, pts0, kf_a, pt_a, uv_a, {0, 1})
    err = np.linalg.norm(res.world_from_cam[:, :3, 3] - truth_arr[:, :3, 3], axis=1)
    assert np.linalg.norm(init[:, :3, 3] - truth_arr[:, :3, 3], axis=1).max() > 0.05
    assert err.max() < 0.03, err
    assert err.mean() < np.linalg.norm(init[:, :3, 3] - truth_arr[:, :3, 3], axis=1).mean() / 3
    assert res.final_rmse_px < 0.9 < res.initial_rmse_px
    np.testing.assert_allclose(res.world_from_cam[:2], truth_arr[:2], atol=1e-9)


def test_global_ba_ignores_gross_outliers_and_flags_them() -> None:
    """5% of the observations are wrong matches (random pixels): they are left out, BA still brings
    the poses within 3 cm, and the result is accepted."""
    rng = np.random.default_rng(2)
    cam = PinholeCamera(640, 480, 420.0, 420.0, 320.0, 240.0)
    n = 12
    truth = np.array([se3(so3_exp([0.0, 0.02 * k, 0.0]), [0.5 * k, 0.0, 0.0]) for k in range(n)])
    pts = np.column_stack([rng.uniform(-5, 10, 1500), rng.uniform(-4, 4, 1500), rng.uniform(6, 20, 1500)])
    kf, pt, uvs = [], [], []
    for k in range(n):
        pc = (pts - truth[k, :3, 3]) @ truth[k, :3, :3]
        uv, valid = cam.project(pc)
        idx = np.flatnonzero(valid & cam.in_image(uv))
        kf += [k] * len(idx)
        pt += idx.tolist()
        uvs.append(uv[idx] + rng.normal(0, 0.5, (len(idx), 2)))
    kf_a, pt_a, uv_a = np.array(kf), np.array(pt), np.vstack(uvs)
    wrong = rng.random(len(kf_a)) < 0.05
    uv_a[wrong] = rng.uniform([0, 0], [640, 480], (int(wrong.sum()), 2))
    init = truth.copy()
    for k in range(2, n):
        init[k, :3, 3] += rng.normal(0, 0.05, 3)
    res = global_bundle_adjustment([cam], np.zeros(n, dtype=np.int64), init, pts, kf_a, pt_a, uv_a, {0, 1})
    assert res.accepted
    assert res.obs_inlier is not None
    assert not res.obs_inlier[wrong].mean() > 0.05  # wrong matches are (almost all) left out
    assert np.linalg.norm(res.world_from_cam[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.03
