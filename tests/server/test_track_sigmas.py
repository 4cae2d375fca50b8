"""Odometry edges weighed by how well each agent tracked (``Keyframe.track_sigma``, issue 27): two agents
drive the same 10 m square, loops join them at four places. One tracked well (its odometry is the truth,
2 mm / 0.02 deg per keyframe), the other drifted 0.3 deg of yaw per keyframe (1.3 m at the end) and said
so (2 cm / 0.4 deg). With the fixed sigmas every agent's odometry is equally sure, so the loops split the
drift between them and the good agent is bent by half a metre; weighed by tracking, the drifted agent takes
the correction and the good one stays where it was."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp
from hivemap.maps.odometry import Chains
from hivemap.server.backend.optimise import edge_sigmas, odometry_sigmas, odometry_sigmas_many
from hivemap.server.backend.options import OptimiseOptions
from hivemap.server.optim import PoseGraphEdge, PoseGraphOptions, relative_sim3, solve_pose_graph_se3

N = 40
LOOPS = (10, 20, 30, 39)


def _square() -> list[np.ndarray]:
    truth, T = [], np.eye(4)
    for k in range(N):
        truth.append(T.copy())
        turn = np.pi / 2 if (k + 1) % 10 == 0 else 0.0
        T = T @ se3(so3_exp(np.array([0.0, 0.0, turn])), np.array([1.0, 0, 0]))
    return truth


def _drifted(truth: list[np.ndarray], drift_deg: float) -> list[np.ndarray]:
    out, D = [truth[0].copy()], truth[0].copy()
    step = se3(so3_exp(np.array([0, 0, np.radians(drift_deg)])), np.zeros(3))
    for k in range(1, N):
        D = D @ se3_inverse(truth[k - 1]) @ truth[k] @ step
        out.append(D.copy())
    return out


def _keyframe(pose: np.ndarray, k: int, track: tuple[float, float] | None) -> SimpleNamespace:
    sigma = None if track is None else np.array(track)
    return SimpleNamespace(timestamp=0.5 * k, world_from_cam=pose, odom_sigma=None, track_sigma=sigma)


def _solve(o: OptimiseOptions, tracks: dict[str, tuple[float, float] | None]) -> dict[str, np.ndarray]:
    """Both agents' solved positions (N, 3) after the pose graph of their odometry and the loops."""
    truth = _square()
    est = {"good": truth, "drifted": _drifted(truth, 0.3)}
    keys = [(a, k) for a in ("good", "drifted") for k in range(N)]
    kfs = {(a, k): _keyframe(est[a][k], k, tracks[a]) for a, k in keys}
    chains = Chains(SimpleNamespace(keyframes=kfs))
    index = {key: i for i, key in enumerate(keys)}
    edges = []
    for a in est:
        for k in range(N - 1):
            sr, st, _ = odometry_sigmas(chains.between((a, k), (a, k + 1)), o)
            rel = relative_sim3(est[a][k], est[a][k + 1])
            edges.append(PoseGraphEdge(index[a, k], index[a, k + 1], rel, sigma_rot=sr, sigma_trans=st))
    tight = {"sigma_rot": 0.005, "sigma_trans": 0.02}  # a loop fitted on hundreds of inliers
    for k in (0, *LOOPS):  # at the shared start, then where both pass again
        rel = Sim3.from_se3(se3_inverse(truth[k]) @ truth[k])
        edges.append(PoseGraphEdge(index["good", k], index["drifted", k], rel, robust=True, **tight))
    poses = np.array([kfs[key].world_from_cam for key in keys])
    res = solve_pose_graph_se3(poses, edges, {index["good", 0]}, PoseGraphOptions(gnc=True))
    assert all(res.inlier), res.chi2[-len(LOOPS) - 1 :]  # every loop is true: none may be rejected
    xyz = np.array([p.t for p in res.poses])
    return {a: xyz[[index[a, k] for k in range(N)]] for a in est}


def _errors(solved: dict[str, np.ndarray]) -> dict[str, float]:
    truth = np.array([T[:3, 3] for T in _square()])
    return {a: float(np.linalg.norm(x - truth, axis=1).max()) for a, x in solved.items()}


def test_the_agent_that_tracked_badly_takes_the_loops_correction() -> None:
    o = replace(OptimiseOptions(), pose_graph_tracked=True)
    drift = float(np.linalg.norm(_drifted(_square(), 0.3)[-1][:3, 3] - _square()[-1][:3, 3]))
    assert drift > 1.0  # what the drifted agent's odometry alone puts it off by
    tracked = _errors(_solve(o, {"good": (0.002, 0.02), "drifted": (0.02, 0.4)}))
    fixed = _errors(_solve(replace(o, pose_graph_tracked=False), {"good": None, "drifted": None}))
    # fixed sigmas: the loops split the drift, bending the good agent by decimetres
    assert fixed["good"] > 0.15, fixed
    # weighed by tracking: the good agent stays within 3 cm, the drifted one comes within 0.15 m
    assert tracked["good"] < 0.03, tracked
    assert tracked["drifted"] < 0.15, tracked
    assert tracked["drifted"] < 0.5 * drift


@pytest.mark.parametrize("missing", ["good", "drifted"])
def test_an_agent_that_does_not_say_how_it_tracked_keeps_the_fixed_sigmas(missing: str) -> None:
    """An older agent sends no ``track_sigma``: its edges keep the options' fixed sigmas, the other's are
    weighed by its tracking (a chain with any keyframe lacking it is not summed)."""
    o = replace(OptimiseOptions(), pose_graph_tracked=True)
    kfs = {
        (a, k): _keyframe(np.eye(4), k, None if a == missing else (0.004, 0.05))
        for a in ("good", "drifted")
        for k in range(3)
    }
    chains = Chains(SimpleNamespace(keyframes=kfs))
    other = "drifted" if missing == "good" else "good"
    assert odometry_sigmas(chains.between((missing, 0), (missing, 1)), o)[:2] == (
        o.pose_graph_sigma_rot,
        o.pose_graph_sigma_trans,
    )
    sr, st, _ = odometry_sigmas(chains.between((other, 0), (other, 2)), o)
    # two keyframes' tracking summed in quadrature, times the scale
    assert st == pytest.approx(o.pose_graph_track_scale * 0.004 * np.sqrt(2))
    assert sr == pytest.approx(o.pose_graph_track_scale * np.radians(0.05) * np.sqrt(2))
    # across agents (fused points) the fixed sigmas hold
    assert odometry_sigmas(chains.between((other, 0), (missing, 0)), o)[:2] == (
        o.pose_graph_sigma_rot,
        o.pose_graph_sigma_trans,
    )


def test_an_edge_across_agents_is_weighed_by_both_keyframes_tracking() -> None:
    """Two agents' keyframes joined by fused points: both say how well they tracked, so the edge gets
    their errors in quadrature (times the scale), as sure as the odometry around it; where either does
    not say, and by default (off), the fixed sigmas."""
    o = replace(OptimiseOptions(), pose_graph_tracked=True)
    kfs = {("a", 0): _keyframe(np.eye(4), 0, (0.003, 0.04)), ("b", 0): _keyframe(np.eye(4), 0, (0.004, 0.03)),
           ("c", 0): _keyframe(np.eye(4), 0, None)}  # fmt: skip
    m = SimpleNamespace(keyframes=kfs)
    chains = Chains(m)
    keys = [("a", 0), ("b", 0), ("c", 0)]
    (sr, st, _), across_c = edge_sigmas(m, chains, keys, [(0, 1), (0, 2)], o)
    assert st == pytest.approx(o.pose_graph_track_scale * 0.005)
    assert sr == pytest.approx(o.pose_graph_track_scale * np.radians(0.05))
    fixed = (o.pose_graph_sigma_rot, o.pose_graph_sigma_trans)
    assert across_c[:2] == fixed
    assert edge_sigmas(m, chains, keys, [(0, 1)], OptimiseOptions())[0][:2] == fixed


def test_batched_chains_equal_the_per_edge_ones_and_weigh_weak_tracking() -> None:
    """``Chains.between_many`` (the pose graph's per-edge work, batched) gives what ``between`` gives edge by
    edge: within an agent, across weak tracking, with and without tracked sigmas, across agents and for an
    unknown keyframe; ``odometry_sigmas_many`` gives the fixed sigmas across agents and adds the weak
    sigma (as extra yaw) exactly where an edge crosses weak tracking."""
    rng = np.random.default_rng(5)
    kfs = {}
    for agent in ("a", "b"):
        for k in range(30):
            kf = _keyframe(se3(so3_exp(rng.normal(size=3) * 0.1), rng.normal(size=3)), k,
                           None if k % 7 == 3 else (0.002 * (1 + k % 3), 0.03))  # fmt: skip
            kf.odom_sigma = np.array([0.2, 1.5]) if k in (11, 12, 20) else None
            kfs[(agent, k)] = kf
    m = SimpleNamespace(keyframes=kfs)
    chains = Chains(m)
    keys = list(kfs)
    pairs = [(keys[i], keys[j]) for i, j in rng.integers(0, len(keys), size=(300, 2))] + [
        (("a", 0), ("c", 1))
    ]
    d, same = chains.between_many([p for p, _ in pairs], [q for _, q in pairs])
    o = OptimiseOptions()
    many = odometry_sigmas_many(d, same, o)
    for n, (p, q) in enumerate(pairs):
        one = chains.between(p, q)
        assert same[n] == (one is not None)
        if one is None:
            assert tuple(many[n]) == (o.pose_graph_sigma_rot, o.pose_graph_sigma_trans, 0.0)
            continue
        np.testing.assert_array_equal(d[n], one)
        lo, hi = sorted((p[1], q[1]))
        crosses = any(lo < k <= hi for k in (11, 12, 20))
        assert (many[n][2] > 0) == crosses
        if crosses:  # the weak sigma in quadrature: never below it
            assert many[n][1] >= np.hypot(o.pose_graph_sigma_trans, 0.2) - 1e-12
