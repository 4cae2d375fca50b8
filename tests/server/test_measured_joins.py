"""Only measured edges join a map's agents in the pose graph (issue 27): two agents fly the same 20 m
line; points fused between them at some time made covisibility edges across the agents whose relative
pose is the map's at that time, with agent b 0.4 m off to the side. Five true loops say where b is. With
the fused edges in the graph, the bend they hold outvotes the loops (the robust solve rejects true loops
and b stays off); with only the measured edges joining the agents, b comes back to the truth."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hivemap.maps.geometry import Sim3, se3
from hivemap.server.backend.optimise import NewEdge, Snapshot, pose_graph_problem, solve_pose_graph
from hivemap.server.backend.options import OptimiseOptions

N = 20
LOOPS = (0, 5, 10, 15, 19)
FUSED = range(6, 14)  # b's keyframes that share fused points with a's
OFF = np.array([0.0, 0.4, 0.0])


def _map() -> tuple[SimpleNamespace, Snapshot, list[NewEdge], dict[tuple[str, int], np.ndarray]]:
    truth = {(a, k): se3(np.eye(3), np.array([float(k), 0.0, 0.0])) for a in ("a", "b") for k in range(N)}
    now = {key: T.copy() for key, T in truth.items()}
    for k in range(N):
        now["b", k][:3, 3] += OFF  # the map holds b off to the side
    kfs = {key: SimpleNamespace(world_from_cam=T, odom_sigma=None, track_sigma=None, vio_from_cam=None,
                                timestamp=0.5 * key[1])
           for key, T in now.items()}  # fmt: skip
    within = [((a, k), (a, k + 1)) for a in ("a", "b") for k in range(N - 1)]
    across = [(("a", k), ("b", k)) for k in FUSED] + [(("a", k), ("b", k + 1)) for k in FUSED]
    m = SimpleNamespace(keyframes=kfs, essential_edges=lambda: sorted(within + across), loop_edges=lambda: [])
    keys = sorted(kfs)
    snap = Snapshot(0, 0, keys, np.array([now[k] for k in keys]))
    loops = [NewEdge(("a", k), ("b", k), Sim3.from_se3(np.eye(4)), 0.005, 0.02) for k in LOOPS]
    return m, snap, loops, truth


def _solve(measured_only: bool) -> tuple[float, int, int]:
    """(the largest keyframe error in m, a's first keyframe held; loops rejected; cross-agent edges)."""
    m, snap, loops, truth = _map()
    o = OptimiseOptions()
    fixed = [snap.keys.index(("a", 0))]
    p = pose_graph_problem(m, snap, loops, None, fixed, o, measured_only)
    res = solve_pose_graph(p, snap.poses, True, o)
    err = max(float(np.linalg.norm(res.poses[i].t - truth[k][:3, 3])) for i, k in enumerate(snap.keys))
    cross = sum(snap.keys[i][0] != snap.keys[j][0] for i, j in p.graph_edges)
    return err, int(np.sum(~np.asarray(res.inlier))), cross


def test_fused_edges_across_agents_hold_the_bend_and_reject_true_loops() -> None:
    err, rejected, cross = _solve(measured_only=False)
    assert cross == 2 * len(FUSED) - 1  # the one pair a loop also joins holds the loop's measurement
    assert rejected >= 1 or err > 0.15, (err, rejected)


def test_only_measured_edges_join_the_agents_and_the_loops_bring_b_back() -> None:
    err, rejected, cross = _solve(measured_only=True)
    assert cross == 0
    assert rejected == 0
    assert err < 0.01, err


def test_an_agent_no_measured_edge_joins_keeps_its_place() -> None:
    """No loop joins b yet: with the fused edges left out, b's loose prior on its first keyframe is its
    gauge, so the solve neither fails nor moves it."""
    m, snap, _, _ = _map()
    o = OptimiseOptions()
    p = pose_graph_problem(m, snap, [], None, [snap.keys.index(("a", 0))], o, True)
    assert [snap.keys[i] for i in p.loose] == [("b", 0)]
    res = solve_pose_graph(p, snap.poses, True, o)
    moved = max(float(np.linalg.norm(res.poses[i].t - snap.poses[i][:3, 3])) for i in range(len(snap.keys)))
    assert moved < 1e-3, moved
