"""The eval's calibration figure of the server's covariances (:mod:`hivemap.eval.uncertainty`) on
synthetic data: errors drawn from the reported covariances fill the 2-sigma ellipsoids as a Gaussian does
(73.9 % in 3-D), covariances four times too small do not, in a map frame unlike the ground truth's."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from hivemap.eval.uncertainty import ellipsoid_coverage
from hivemap.maps.geometry import se3, so3_exp

MAP_FROM_GT = se3(so3_exp(np.array([0.1, -0.2, 1.3])), np.array([50.0, -3.0, 2.0]))


def synthetic(
    n: int, shrink: float, seed: int = 0
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict]:
    rng = np.random.default_rng(seed)
    ts = np.arange(n) * 0.5
    gt = [se3(so3_exp(rng.normal(0, 0.3, 3)), np.array([0.5 * k, np.sin(k / 20), 0.0])) for k in range(n)]
    kfs, unc = [], []
    for k in range(n):
        A = rng.normal(size=(3, 3)) * 0.05 * (1 + k / n)
        P = A @ A.T + 1e-4 * np.eye(3)
        T = MAP_FROM_GT @ gt[k]
        if k > 0:
            T[:3, 3] += rng.multivariate_normal(np.zeros(3), P)
        cov = np.zeros((6, 6))
        if k > 0:
            cov[:3, :3] = 1e-4 * np.eye(3)
            cov[3:, 3:] = P / shrink
        agent = "uav1" if k % 2 else "ugv1#1"  # a session id takes its agent's ground truth
        kfs.append({"agent_id": agent, "id": k, "timestamp": float(ts[k]), "world_from_cam": T.tolist()})
        unc.append({"agent_id": agent, "kf_id": k, "pose_cov": cov.tolist()})
    gt_traj = SimpleNamespace(timestamps=ts, poses_se3=gt)
    return kfs, unc, {"uav1": gt_traj, "ugv1": gt_traj}


def test_calibrated_covariances_hold_a_gaussian_share() -> None:
    kfs, unc, gt = synthetic(3000, 1.0)
    res = ellipsoid_coverage(kfs, unc, gt)
    assert res is not None and res["n"] == 2999 and res["anchor"] == ["ugv1#1", 0]
    # 3000 draws: the share to +-0.8 % (1 sigma), NEES to +-1.5 %
    assert abs(res["inside"] - 0.739) < 0.03, res
    assert abs(res["mean_nees"] - 1.0) < 0.06, res


def test_overconfident_covariances_are_told() -> None:
    kfs, unc, gt = synthetic(3000, 4.0)
    res = ellipsoid_coverage(kfs, unc, gt)
    assert res is not None and res["inside"] < 0.3 and abs(res["mean_nees"] - 4.0) < 0.3, res


def test_no_anchor_with_ground_truth_gives_none() -> None:
    kfs, unc, gt = synthetic(20, 1.0)
    assert ellipsoid_coverage(kfs[1:], unc[1:], gt) is None
    assert ellipsoid_coverage(kfs, unc, {}) is None
