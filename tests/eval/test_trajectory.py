"""Trajectory evaluation (eval/trajectory.py): known perturbations of a ground truth give known errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hivemap.eval.trajectory import (
    AgentRun,
    ate,
    evaluate_team,
    read_frame_timeline,
    read_tum,
    rpe,
    trajectory_from_poses,
    write_frame_timeline,
    write_tum,
)
from hivemap.maps.geometry import se3

# Numerical noise of a 4x4 float64 pipeline through evo (quaternion round trips): 1e-9 m is ample.
EXACT = 1e-9


def gt_poses(n: int = 200, t0: float = 0.0, phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A 3D Lissajous-like path (non-degenerate for alignment), 10 Hz."""
    t = t0 + 0.1 * np.arange(n)
    poses = np.zeros((n, 4, 4))
    for i, ti in enumerate(t):
        a = 0.05 * ti + phase
        p = np.array([20 * math.cos(a), 15 * math.sin(2 * a), 3 + 2 * math.sin(a)])
        R = Rotation.from_euler("zyx", [a + 1.0, 0.1 * math.sin(a), 0.05]).as_matrix()
        poses[i] = se3(R, p)
    return t, poses


def rigid(yaw: float, t: tuple[float, float, float], roll: float = 0.0) -> np.ndarray:
    return se3(Rotation.from_euler("zx", [yaw, roll]).as_matrix(), np.array(t))


def test_rigid_perturbation_se3_zero_none_expected():
    t, P = gt_poses()
    T = rigid(0.7, (5.0, -3.0, 2.0), roll=0.2)
    gt = trajectory_from_poses(t, P)
    est = trajectory_from_poses(t, T[None] @ P)
    assert ate(est, gt, "se3").stats.rmse < EXACT
    assert ate(est, gt, "sim3").stats.rmse < EXACT
    # Without alignment: the error of each position is |R p + t - p|, computed independently here.
    pos = P[:, :3, 3]
    expected = np.sqrt(np.mean(np.sum((pos @ T[:3, :3].T + T[:3, 3] - pos) ** 2, axis=1)))
    res = ate(est, gt, "none")
    assert res.stats.rmse == pytest.approx(expected, rel=1e-12)
    assert expected > 5.0  # the check is meaningful


def test_constant_offset_gives_exactly_that_ate():
    t, P = gt_poses()
    offset = np.array([0.3, -0.4, 0.0])  # |offset| = 0.5 m
    Q = P.copy()
    Q[:, :3, 3] += offset
    res = ate(trajectory_from_poses(t, Q), trajectory_from_poses(t, P), "none")
    for v in (res.stats.rmse, res.stats.mean, res.stats.median, res.stats.max, res.stats.min):
        assert v == pytest.approx(0.5, abs=EXACT)
    # se3 alignment absorbs a constant offset entirely.
    assert ate(trajectory_from_poses(t, Q), trajectory_from_poses(t, P), "se3").stats.rmse < EXACT


def test_sim3_recovers_scale_se3_does_not():
    t, P = gt_poses()
    S = P.copy()
    S[:, :3, 3] *= 1.5  # a monocular trajectory at the wrong scale
    gt, est = trajectory_from_poses(t, P), trajectory_from_poses(t, S)
    res = ate(est, gt, "sim3")
    assert res.stats.rmse < 1e-6
    assert res.scale == pytest.approx(1 / 1.5, rel=1e-9)
    assert ate(est, gt, "se3").stats.rmse > 1.0


def test_association_by_timestamp():
    t, P = gt_poses()
    gt = trajectory_from_poses(t, P)
    # The estimate only at every 3rd ground-truth time, 2 ms late: matched within max_diff.
    est = trajectory_from_poses(t[::3] + 0.002, P[::3])
    res = ate(est, gt, "none", max_diff=0.005)
    assert res.stats.n == len(t[::3])
    assert res.stats.rmse < EXACT


def test_rpe_of_a_scale_drift():
    # Straight line along x at 1 m per pose, estimate 1% too long: RPE over 10 m is 0.1 m.
    n = 100
    t = np.arange(n, dtype=float)
    P = np.stack([se3(np.eye(3), np.array([i, 0.0, 0.0])) for i in range(n)])
    Q = np.stack([se3(np.eye(3), np.array([1.01 * i, 0.0, 0.0])) for i in range(n)])
    r = rpe(trajectory_from_poses(t, Q), trajectory_from_poses(t, P), delta=10, unit="m", alignment="none")
    assert r.trans.mean == pytest.approx(0.1, abs=1e-9)
    assert r.rot_deg.max < 1e-6


def test_tum_and_timeline_round_trip(tmp_path):
    t, P = gt_poses(50)
    write_tum(tmp_path / "a.tum", trajectory_from_poses(t, P))
    back = read_tum(tmp_path / "a.tum")
    assert np.allclose(back.timestamps, t)
    assert np.abs(np.asarray(back.poses_se3) - P).max() < 1e-6  # TUM text precision
    line = (tmp_path / "a.tum").read_text().splitlines()[0].split()
    assert len(line) == 8  # t tx ty tz qx qy qz qw
    write_frame_timeline(tmp_path / "f.csv", [(0.0, "uav1"), (12.5, "global")])
    assert read_frame_timeline(tmp_path / "f.csv") == [(0.0, "uav1"), (12.5, "global")]


def _two_agents(extra_offset_b: float = 0.0):
    """Agent A in the global frame all along; agent B in its own frame until t=10 s, then global."""
    ta, Pa = gt_poses(200, phase=0.0)
    tb, Pb = gt_poses(200, phase=1.0)
    G = rigid(0.4, (10.0, 2.0, -1.0))  # global_from_world
    B_own = rigid(-1.1, (-3.0, 7.0, 0.5))  # B's own frame before the merge
    est_a = G[None] @ Pa
    est_b = np.where((tb < 10.0)[:, None, None], B_own[None] @ Pb, G[None] @ Pb)
    est_b[tb >= 10.0, :3, 3] += np.array([extra_offset_b, 0.0, 0.0])
    runs = [
        AgentRun("a", trajectory_from_poses(ta, est_a), trajectory_from_poses(ta, Pa), [(0.0, "global")]),
        AgentRun(
            "b",
            trajectory_from_poses(tb, est_b),
            trajectory_from_poses(tb, Pb),
            [(0.0, "b"), (10.0, "global")],
        ),
    ]
    return runs


def test_segments_with_frame_change_are_evaluated_in_their_frame():
    runs = _two_agents()
    rep = evaluate_team(runs, "se3", rpe_delta=5.0)
    assert rep.agents["b"].merge_time == 10.0
    assert rep.agents["a"].merge_time is None
    segs = rep.agents["b"].segments
    assert [s.frame_id for s in segs] == ["b", "global"]
    assert segs[0].t_end < 10.0 <= segs[1].t_start
    assert segs[0].ate.n + segs[1].ate.n == 200
    assert rep.agents["a"].ate.rmse < EXACT
    assert rep.agents["b"].ate.rmse < EXACT
    assert rep.team.rmse < EXACT
    assert rep.frames["global"].agents == ["a", "b"]
    assert rep.agents["b"].rpe is not None and rep.agents["b"].rpe.trans.rmse < 1e-6
    (pair,) = rep.inter_agent
    assert (pair.agent_a, pair.agent_b, pair.frame_id) == ("a", "b", "global")
    assert pair.trans.max < 1e-6
    # Ignoring the frame change (one frame for the whole of B) gives a large, wrong error.
    naive = ate(runs[1].est, runs[1].gt, "se3")
    assert naive.stats.rmse > 1.0


def test_relative_error_between_agents_after_merge():
    """B's post-merge poses 0.5 m off in the shared frame: one alignment cannot hide it."""
    runs = _two_agents(extra_offset_b=0.5)
    rep = evaluate_team(runs, "se3", rpe_delta=None)
    (pair,) = rep.inter_agent
    # inv(Ta) Tb translation differs by Ra^T c: its norm is exactly |c| = 0.5 m at every time.
    assert pair.trans.min == pytest.approx(0.5, abs=1e-9)
    assert pair.trans.max == pytest.approx(0.5, abs=1e-9)
    assert pair.rot_deg.max < 1e-6
    assert rep.team.rmse > 0.1
    # B's pre-merge segment (its own frame) is still exact.
    assert rep.agents["b"].segments[0].ate.rmse < EXACT
    # Per-agent errors in the jointly aligned frame: with alignment "none" and no frame offset
    # (est = gt exactly for A, B offset by 0.5 m after merge), B's post-merge ATE is exactly 0.5.
    ta, Pa = gt_poses(200, phase=0.0)
    tb, Pb = gt_poses(200, phase=1.0)
    Qb = Pb.copy()
    Qb[tb >= 10.0, :3, 3] += np.array([0.5, 0.0, 0.0])
    runs_enu = [
        AgentRun("a", trajectory_from_poses(ta, Pa), trajectory_from_poses(ta, Pa), [(0.0, "enu")]),
        AgentRun("b", trajectory_from_poses(tb, Qb), trajectory_from_poses(tb, Pb), [(0.0, "enu")]),
    ]
    rep2 = evaluate_team(runs_enu, "none", rpe_delta=None)
    assert rep2.agents["a"].ate.rmse < EXACT
    n_after = int(np.sum(tb >= 10.0))
    assert rep2.agents["b"].ate.rmse == pytest.approx(0.5 * math.sqrt(n_after / 200), abs=1e-9)
