"""The metric-map pose graph (SE(3)): a loop edge removes drift and poses stay rigid."""

from __future__ import annotations

import numpy as np

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp
from hivemap.server.optim import PoseGraphEdge, relative_sim3, solve_pose_graph_se3


def test_loop_edge_removes_drift_and_keeps_rotations_orthonormal() -> None:
    """A 40-keyframe square loop (10 m sides) drifted by 0.5 deg of yaw per keyframe; one robust loop
    edge (last -> first, true relative pose) brings the end back within 5 cm of truth (the odometry
    edges hold the drifted shape, so the residual spreads over the loop) and every rotation stays
    orthonormal to 1e-9 (the Sim(3) graph with a pinned scale did not: rotations came out scaled)."""
    truth, T = [], np.eye(4)
    for k in range(40):
        truth.append(T.copy())
        T = T @ se3(
            so3_exp(np.array([0.0, 0.0, np.pi / 2 if (k + 1) % 10 == 0 else 0.0])), np.array([1.0, 0, 0])
        )
    drifted, D = [truth[0]], truth[0].copy()
    for k in range(1, 40):
        D = (
            D
            @ se3_inverse(truth[k - 1])
            @ truth[k]
            @ se3(so3_exp(np.array([0, 0, np.radians(0.5)])), np.zeros(3))
        )
        drifted.append(D.copy())
    poses = np.array(drifted)
    edges = [PoseGraphEdge(k, k + 1, relative_sim3(poses[k], poses[k + 1])) for k in range(39)]
    loop = Sim3.from_se3(se3_inverse(truth[39]) @ truth[0])
    edges.append(PoseGraphEdge(39, 0, loop, robust=True))
    before = np.linalg.norm(poses[39, :3, 3] - truth[39][:3, 3])
    out = solve_pose_graph_se3(poses, edges, {0}).poses
    after = np.linalg.norm(out[39].t - truth[39][:3, 3])
    assert before > 1.0, before
    assert after < 0.05, after
    for s in out:
        assert s.s == 1.0
        np.testing.assert_allclose(s.R @ s.R.T, np.eye(3), atol=1e-9)


def _yaw_chain(n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Gravity-aligned camera poses (z forward, y down) driving 1 m per keyframe along a gentle curve,
    and the up direction in the camera frame."""
    # world_from_cam rotation: camera x = world -y, camera y = world -z (down), camera z = world x
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    truth, yaw, p = [], 0.0, np.zeros(3)
    for _ in range(n):
        R = so3_exp(np.array([0.0, 0.0, yaw])) @ base
        truth.append(se3(R, p.copy()))
        p = p + R @ np.array([0.0, 0.0, 1.0])
        yaw += np.radians(2.0)
    up_cam = base.T @ np.array([0.0, 0.0, 1.0])
    return truth, up_cam


def test_yaw_sigma_keeps_a_loops_yaw_error_out_of_the_trajectory() -> None:
    """Odometry exact; one loop edge from keyframe 10 back to 0 that is 2 deg off in yaw (as the UGV ->
    UAV loops of factory01, 10 m apart, were up to 1.7 deg). Keyframe 0 fixed. With isotropic 0.01 rad
    odometry sigmas the loop turns the chain: keyframe 20 ends more than 0.2 m off. With the yaw held
    at 0.001 rad about the IMU up (``sigma_yaw`` + ``up_j``), it stays within 0.05 m."""
    truth, up_cam = _yaw_chain(21)
    poses = np.array(truth)
    wrong = se3(so3_exp(np.array([0.0, 0.0, np.radians(2.0)])), np.zeros(3))
    loop = Sim3.from_se3(se3_inverse(truth[10]) @ wrong @ truth[0])
    up = (float(up_cam[0]), float(up_cam[1]), float(up_cam[2]))

    def solve(sigma_yaw: float | None) -> float:
        edges = [
            PoseGraphEdge(k, k + 1, relative_sim3(poses[k], poses[k + 1]), sigma_yaw=sigma_yaw, up_j=up)
            for k in range(20)
        ]
        edges.append(PoseGraphEdge(10, 0, loop, sigma_rot=0.01, sigma_trans=0.05, robust=True))
        out = solve_pose_graph_se3(poses, edges, {0}).poses
        return float(np.linalg.norm(out[20].t - truth[20][:3, 3]))

    loose, held = solve(None), solve(0.001)
    print(f"keyframe 20 off by {loose:.3f} m (isotropic) vs {held:.3f} m (yaw held)")
    assert loose > 0.2, loose
    assert held < 0.05, held


def test_yaw_sigma_covariance_is_about_the_up_axis() -> None:
    """The rotation covariance has sigma_yaw along up and sigma_rot across it, in the camera frame."""
    _, up_cam = _yaw_chain(1)
    e = PoseGraphEdge(0, 1, Sim3.identity(), sigma_rot=0.01, sigma_yaw=0.001, up_j=tuple(up_cam))
    cov = e.rotation_covariance()
    np.testing.assert_allclose(up_cam @ cov @ up_cam, 0.001**2, rtol=1e-9)
    side = np.cross(up_cam, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    np.testing.assert_allclose(side @ cov @ side, 0.01**2, rtol=1e-9)
    np.testing.assert_allclose(PoseGraphEdge(0, 1, Sim3.identity()).rotation_covariance(), np.eye(3) * 1e-4)
