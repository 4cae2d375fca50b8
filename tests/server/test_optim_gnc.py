"""The robust pose graph (gtsam GNC, truncated least squares; ``PoseGraphOptions.gnc``) on a synthetic graph:
wrong loop edges, 10 m off and as tight as a loop with hundreds of inliers, are rejected and leave the
solution where it is without them; a true loop closing 1.3 m of drift is kept. What a loop may correct is
what the odometry edges' sigmas allow: the same loop over 0.5 deg of drift per edge (0.9 sigma each, all
one way: 2.1 m) is rejected as inconsistent with them."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp
from hivemap.server.optim import (
    PoseGraphEdge,
    PoseGraphOptions,
    relative_sim3,
    solve_pose_graph_se3,
    solve_pose_graph_sim3,
)

TIGHT = {"sigma_rot": 0.005, "sigma_trans": 0.02}  # a loop fitted on hundreds of inliers


def _square(drift_deg: float = 0.3, n: int = 40) -> tuple[list[np.ndarray], np.ndarray]:
    """A square loop (10 m sides) and its odometry drifted by ``drift_deg`` of yaw per keyframe (0.3 deg:
    1.3 m at the end, 0.5 sigma per odometry edge of 0.01 rad)."""
    truth, T = [], np.eye(4)
    for k in range(n):
        truth.append(T.copy())
        turn = np.pi / 2 if (k + 1) % 10 == 0 else 0.0
        T = T @ se3(so3_exp(np.array([0.0, 0.0, turn])), np.array([1.0, 0, 0]))
    drifted, D = [truth[0]], truth[0].copy()
    step = se3(so3_exp(np.array([0, 0, np.radians(drift_deg)])), np.zeros(3))
    for k in range(1, n):
        D = D @ se3_inverse(truth[k - 1]) @ truth[k] @ step
        drifted.append(D.copy())
    return truth, np.array(drifted)


def _wrong(truth: list[np.ndarray], i: int, j: int, off: np.ndarray) -> PoseGraphEdge:
    """A loop ``i`` - ``j`` whose relative pose puts ``j`` ``off`` (in ``i``'s frame) from where it is."""
    rel = se3_inverse(truth[i]) @ truth[j]
    rel[:3, 3] += off
    return PoseGraphEdge(i, j, Sim3.from_se3(rel), robust=True, **TIGHT)


@pytest.mark.parametrize("metric", [True, False])
def test_gnc_rejects_wrong_loops_and_keeps_the_true_one(metric: bool) -> None:
    truth, poses = _square()
    odo = [PoseGraphEdge(k, k + 1, relative_sim3(poses[k], poses[k + 1])) for k in range(39)]
    true_loop = PoseGraphEdge(39, 0, Sim3.from_se3(se3_inverse(truth[39]) @ truth[0]), robust=True, **TIGHT)
    wrong = [_wrong(truth, 2, 22, np.array([10.0, 0, 0])), _wrong(truth, 5, 25, np.array([0, 10.0, 0])),
             _wrong(truth, 12, 33, np.array([-7.0, 7.0, 0]))]  # fmt: skip
    solve = solve_pose_graph_se3 if metric else solve_pose_graph_sim3
    gnc = PoseGraphOptions(gnc=True)
    without = solve(poses, [*odo, true_loop], {0}, gnc)
    robust = solve(poses, [*odo, true_loop, *wrong], {0}, gnc)
    huber = solve(poses, [*odo, true_loop, *wrong], {0}, PoseGraphOptions())
    # every odometry edge kept (known inliers), the true loop kept, the three wrong ones rejected
    assert robust.inlier == [True] * 40 + [False] * 3
    assert without.inlier == [True] * 40
    pos = lambda res: np.array([p.t for p in res.poses])  # noqa: E731
    assert np.linalg.norm(pos(without) - np.array([T[:3, 3] for T in truth]), axis=1).max() < 0.3
    # the map with the wrong loops is the map without them, to 5 cm (to 1 mm, in fact: they get no weight)
    assert np.linalg.norm(pos(robust) - pos(without), axis=1).max() < 0.05
    # a Huber loss still lets them bend the map by more than half a metre
    assert np.linalg.norm(pos(huber) - pos(without), axis=1).max() > 0.5
    # the rejected edges' residuals show how far off they are; the kept loop's is small
    assert min(robust.chi2[40:]) > 1e4 and robust.chi2[39] < 20.0, robust.chi2[39:]


def test_gnc_rejects_a_loop_asking_more_than_the_odometry_sigmas_allow() -> None:
    truth, poses = _square(drift_deg=0.5)
    odo = [PoseGraphEdge(k, k + 1, relative_sim3(poses[k], poses[k + 1])) for k in range(39)]
    loop = PoseGraphEdge(39, 0, Sim3.from_se3(se3_inverse(truth[39]) @ truth[0]), robust=True, **TIGHT)
    res = solve_pose_graph_se3(poses, [*odo, loop], {0}, PoseGraphOptions(gnc=True))
    assert res.inlier[39] is False
    # a Huber loss takes it: the odometry absorbs 0.75 chi2 per edge, 29 over the chain (> 16.8,
    # the 99% quantile for a 6-dof edge, which is what the GNC's threshold is)
    lsq = solve_pose_graph_se3(poses, [*odo, loop], {0}, PoseGraphOptions())
    assert 16.8 < sum(lsq.chi2[:39]) < 40.0, sum(lsq.chi2[:39])
