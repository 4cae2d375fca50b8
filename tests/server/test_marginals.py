"""Pose-graph marginals (:mod:`hivemap.server.marginals`) against Monte Carlo: a synthetic odometry chain
with one loop, measurements drawn from the edges' stated noise, re-solved many times by the server's own
SE(3) pose-graph solve; the spread of the last pose must match the reported marginal within 20 %."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp, so3_log
from hivemap.server.marginals import FEW, inside_ellipsoid, pose_marginals, position_covariance
from hivemap.server.optim import PoseGraphEdge, solve_pose_graph_se3

N = 25
# [rot (rad), trans (m)] in gtsam's Between perturbation: anisotropic, so a covariance left in the camera
# frame would not match the map frame's spread
EDGE_SIGMAS = np.array([0.004, 0.006, 0.012, 0.02, 0.05, 0.01])
EDGE_COV = np.diag(EDGE_SIGMAS**2)
LOOP = (3, N - 1)
TRIALS = 1000


def truth() -> np.ndarray:
    """A turning, climbing chain: 1 m steps, 9 deg of yaw and a little pitch per step."""
    out, T = [], np.eye(4)
    step = se3(so3_exp(np.array([0.03, 0.0, np.radians(9.0)])), np.array([1.0, 0.0, 0.1]))
    for _ in range(N):
        out.append(T.copy())
        T = T @ step
    return np.array(out)


def pairs() -> list[tuple[int, int]]:
    return [(k, k + 1) for k in range(N - 1)] + [LOOP]


def noisy_edges(true: np.ndarray, rng: np.random.Generator) -> list[PoseGraphEdge]:
    edges = []
    for i, j in pairs():
        n = rng.multivariate_normal(np.zeros(6), EDGE_COV)
        rel = se3_inverse(true[i]) @ true[j] @ se3(so3_exp(n[:3]), n[3:])
        edges.append(PoseGraphEdge(i, j, Sim3.from_se3(rel), covariance=EDGE_COV))
    return edges


def dead_reckoning(edges: list[PoseGraphEdge], start: np.ndarray) -> np.ndarray:
    poses = [start]
    for e in edges[: N - 1]:
        poses.append(poses[-1] @ se3(e.i_from_j.R, e.i_from_j.t))
    return np.array(poses)


@pytest.fixture(scope="module")
def monte_carlo() -> tuple[np.ndarray, np.ndarray, np.ndarray, list[PoseGraphEdge], np.ndarray]:
    """Per trial, the last pose's map-frame rotation and position error; one trial's solution and edges
    (what the server would report from); per trial, the error of the last two poses' position difference."""
    true = truth()
    rng = np.random.default_rng(26)
    rot, pos, diff = [], [], []
    first = None
    for _ in range(TRIALS):
        edges = noisy_edges(true, rng)
        res = solve_pose_graph_se3(dead_reckoning(edges, true[0]), edges, {0})
        T = res.poses[-1]
        rot.append(so3_log(T.R @ true[-1][:3, :3].T))
        pos.append(T.t - true[-1][:3, 3])
        diff.append(T.t - res.poses[-2].t - (true[-1][:3, 3] - true[-2][:3, 3]))
        if first is None:
            first = (np.array([se3(p.R, p.t) for p in res.poses]), edges)
    assert first is not None
    return np.array(rot), np.array(pos), first[0], first[1], np.array(diff)


def test_last_pose_marginal_matches_monte_carlo_spread(monte_carlo) -> None:  # type: ignore[no-untyped-def]
    rot, pos, solved, edges, _ = monte_carlo
    cov = pose_marginals(solved, edges, {0}, indices=[N - 1]).covariances[0]
    mc_pos, mc_rot = np.cov(pos.T), np.cov(rot.T)
    rep_pos, rep_rot = position_covariance(cov), cov[:3, :3]
    # 1000 trials: a variance is estimated to ~4.5 % (1 sigma), so 20 % is a 4-sigma bound
    np.testing.assert_allclose(np.diag(rep_pos), np.diag(mc_pos), rtol=0.2)
    np.testing.assert_allclose(np.diag(rep_rot), np.diag(mc_rot), rtol=0.2)
    assert abs(np.trace(rep_pos) / np.trace(mc_pos) - 1) < 0.1
    # the position spread is ~0.3 m here (rotation noise times the lever arm): not a trivial case
    assert np.sqrt(np.trace(mc_pos)) > 0.25
    # the same marginal left in gtsam's camera-frame perturbation does not match: the test tells the
    # frames apart
    R = solved[-1][:3, :3]
    cam = R.T @ rep_pos @ R
    assert np.max(np.abs(np.diag(cam) / np.diag(mc_pos) - 1)) > 0.5


def test_two_sigma_ellipsoid_holds_about_its_share(monte_carlo) -> None:  # type: ignore[no-untyped-def]
    """A 3-D Gaussian lies inside its 2-sigma ellipsoid with probability 73.9 % (chi-square, 3 dof)."""
    _, pos, solved, edges, _ = monte_carlo
    cov3 = position_covariance(pose_marginals(solved, edges, {0}, indices=[N - 1]).covariances[0])
    share = np.mean([inside_ellipsoid(e, cov3) for e in pos])
    assert abs(share - 0.739) < 0.05, share


def test_the_last_two_poses_difference_matches_monte_carlo_and_not_the_sum(monte_carlo) -> None:  # type: ignore[no-untyped-def]
    """What an agent's velocity uncertainty is differenced from: the joint marginal of its last two
    keyframes, in which the drift both share from the gauge cancels."""
    _, pos, solved, edges, diff = monte_carlo
    res = pose_marginals(solved, edges, {0}, indices=[N - 1, N - 2], pairs=[(N - 1, N - 2)])
    rel = res.relative[(N - 1, N - 2)]
    mc = np.cov(diff.T)
    np.testing.assert_allclose(np.diag(rel), np.diag(mc), rtol=0.2)
    # the shared drift is most of each marginal: ignoring the cross-covariance overstates it many times
    naive = position_covariance(res.covariances[0]) + position_covariance(res.covariances[1])
    assert np.trace(naive) > 20 * np.trace(mc)
    # a held pose contributes nothing; a pair with a pose no edge reaches is left out
    one = pose_marginals(solved, edges, {0}, indices=[1], pairs=[(1, 0)])
    np.testing.assert_allclose(one.relative[(1, 0)], position_covariance(one.covariances[0]), rtol=1e-9)
    cut = pose_marginals(solved, edges[: N - 2], {0}, indices=[5], pairs=[(N - 1, N - 2), (5, 4)])
    assert list(cut.relative) == [(5, 4)]


def test_the_loop_shrinks_the_marginal_and_the_gauge_is_exact() -> None:
    true = truth()
    edges = noisy_edges(true, np.random.default_rng(1))
    with_loop = pose_marginals(true, edges, {0}).covariances
    chain = pose_marginals(true, edges[: N - 1], {0}).covariances
    assert np.all(with_loop[0] == 0.0)
    # the few-poses path (eliminated last) gives the same covariance as the whole tree's
    few = pose_marginals(true, edges, {0}, indices=[N - 1, 7]).covariances
    np.testing.assert_allclose(few, with_loop[[N - 1, 7]], rtol=1e-9, atol=1e-15)
    # along the open chain the uncertainty grows; the loop to keyframe 3 cuts the last pose's
    assert np.all(np.diff([np.trace(c[3:, 3:]) for c in chain]) > 0)
    assert np.trace(with_loop[-1][3:, 3:]) < 0.5 * np.trace(chain[-1][3:, 3:])
    for c in with_loop:
        np.testing.assert_allclose(c, c.T, atol=1e-15)
        assert np.linalg.eigvalsh(c).min() > -1e-12


def test_a_pose_no_edge_reaches_is_refused_whole_and_left_out_by_index() -> None:
    true = truth()
    edges = noisy_edges(true, np.random.default_rng(1))[: N - 2]  # pose N-1 hangs on no edge
    with pytest.raises(RuntimeError, match="without an edge"):
        pose_marginals(true, edges, {0})
    res = pose_marginals(true, edges, {0}, indices=[N - 1, 7])
    assert res.indices == [7]
    whole = pose_marginals(true[: N - 1], edges, {0}).covariances
    np.testing.assert_allclose(res.covariances[0], whole[7], rtol=1e-9, atol=1e-15)


def test_every_pose_at_once_matches_the_per_pose_marginals_on_a_dense_graph() -> None:
    """A map's covisibility graph ties each keyframe to dozens of others, so the Bayes tree's root clique
    holds most poses; every keyframe's covariance then comes from one pass over the cliques
    (:func:`clique_marginals`), and must equal gtsam's per-pose marginals (the few-poses path)."""
    rng = np.random.default_rng(3)
    n, held = 120, {0, 60}  # two held poses: a constrained conditional inside the tree
    true = np.array([se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 5.0, 3)) for _ in range(n)])
    edges = []
    for i in range(n):
        for j in range(i + 1, min(n, i + 25)):  # 24 covisible neighbours, as a dense map has
            rel = Sim3.from_se3(se3_inverse(true[i]) @ true[j])
            edges.append(PoseGraphEdge(i, j, rel, covariance=EDGE_COV))
    whole = pose_marginals(true, edges, held)
    assert whole.indices == list(range(n)) and len(whole.indices) > FEW
    for start in range(0, n, FEW):
        chunk = list(range(start, min(n, start + FEW)))
        per_pose = pose_marginals(true, edges, held, indices=chunk).covariances
        np.testing.assert_allclose(whole.covariances[chunk], per_pose, rtol=1e-8, atol=1e-18)
    assert np.all(whole.covariances[sorted(held)] == 0.0)
    assert np.all(np.array([np.trace(c) for i, c in enumerate(whole.covariances) if i not in held]) > 0)
