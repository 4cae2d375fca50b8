"""The pose graph's odometry is each agent's own (issue 27): between consecutive keyframes it holds the
relative pose the agent measured (``Keyframe.vio_from_cam``), not the map's shape, which an earlier solve
may have bent. Two agents fly parallel 20 m lines; the map holds b's second half turned 3 deg (a bend an
earlier solve left), b's own odometry is straight. Loops at the lines' two ends say where b is."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hivemap.maps.geometry import Sim3, se3
from hivemap.maps.odometry import Chains
from hivemap.server.backend.optimise import (
    NewEdge,
    Snapshot,
    chain_sigmas,
    pose_graph_problem,
    solve_pose_graph,
)
from hivemap.server.backend.options import OptimiseOptions

N = 20
BEND_AT, BEND_DEG = 10, 3.0


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _map(own: bool) -> tuple[SimpleNamespace, Snapshot, list[NewEdge], dict[tuple[str, int], np.ndarray]]:
    truth = {(a, k): se3(np.eye(3), np.array([float(k), 1.0 if a == "b" else 0.0, 0.0]))
             for a in ("a", "b") for k in range(N)}  # fmt: skip
    now = {key: T.copy() for key, T in truth.items()}
    pivot = truth["b", BEND_AT][:3, 3]
    bend = se3(_rot_z(BEND_DEG), pivot - _rot_z(BEND_DEG) @ pivot)
    for k in range(BEND_AT + 1, N):
        now["b", k] = bend @ truth["b", k]
    # the agent's own frame is anywhere: only relative poses within one agent count
    frame = se3(_rot_z(40.0), np.array([3.0, -7.0, 0.5]))
    kfs = {
        key: SimpleNamespace(world_from_cam=T, odom_sigma=None, track_sigma=None, timestamp=0.5 * key[1],
                             vio_from_cam=frame @ truth[key] if own else None)
        for key, T in now.items()
    }  # fmt: skip
    m = SimpleNamespace(keyframes=kfs, essential_edges=lambda: [], loop_edges=lambda: [])
    keys = sorted(kfs)
    snap = Snapshot(0, 0, keys, np.array([now[k] for k in keys]))
    a_from_b = Sim3.from_se3(se3(np.eye(3), np.array([0.0, 1.0, 0.0])))
    loops = [NewEdge(("a", k), ("b", k), a_from_b, 0.005, 0.02) for k in (0, N - 1)]
    return m, snap, loops, truth


def _solve(own: bool) -> tuple[float, int]:
    """(the largest keyframe error in m, a's first keyframe held; loops rejected)."""
    m, snap, loops, truth = _map(own)
    o = OptimiseOptions()
    p = pose_graph_problem(m, snap, loops, None, [snap.keys.index(("a", 0))], o, True)
    assert len(p.graph_edges) == 2 * (N - 1)  # each agent's consecutive keyframes, nothing else
    res = solve_pose_graph(p, snap.poses, True, o)
    err = max(float(np.linalg.norm(res.poses[i].t - truth[k][:3, 3])) for i, k in enumerate(snap.keys))
    return err, int(np.sum(~np.asarray(res.inlier)))


def test_the_agents_own_odometry_undoes_a_bend_the_map_held() -> None:
    err, rejected = _solve(own=True)
    assert rejected == 0
    assert err < 0.01, err


def test_without_the_agents_odometry_the_maps_bend_is_held() -> None:
    """A keyframe stored before ``vio_from_cam`` was kept: its edges hold the map's shape, bend and all,
    and the robust solve rejects the true loop the bend contradicts."""
    err, rejected = _solve(own=False)
    assert rejected >= 1 or err > 0.1, (err, rejected)


def test_odometry_sigmas_are_a_floor_and_a_random_walk_over_the_path() -> None:
    o = OptimiseOptions()
    # [path m, rotation rad, weak m, weak deg, tracked m, tracked deg, untracked steps]
    d = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [16.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                  [16.0, 0.0, 0.3, 4.0, 0.0, 0.0, 1.0]])  # fmt: skip
    s = chain_sigmas(d, o)
    assert np.allclose(s[0, :2], [np.radians(o.odometry_sigma_deg), o.odometry_sigma_m])  # the floor
    walk = [np.radians(4 * o.odometry_walk_deg), 4 * o.odometry_walk_m]  # sqrt(16 m)
    assert np.allclose(s[1, :2], np.hypot(s[0, :2], walk))
    assert np.isclose(s[2, 1], np.hypot(s[1, 1], 0.3))  # weak tracking adds in quadrature
    assert np.isclose(s[2, 2], np.radians(4.0))  # and its own yaw sigma


def test_chains_order_each_agent_by_time() -> None:
    m, snap, _, _ = _map(own=True)
    chains = Chains(m, snap.keys, dict(zip(snap.keys, snap.poses, strict=True)))
    assert chains.order["b"] == [("b", k) for k in range(N)]


def test_chains_sum_each_agents_steps_in_path_rotation_and_sigmas() -> None:
    """The cumulative path (m), rotation (rad) and variances between two keyframes are the sums of the
    steps between them, each step from the keyframes' poses one by one."""
    from hivemap.maps.geometry import rotation_angle_deg
    from hivemap.maps.testing import random_map

    m = random_map(np.random.default_rng(4), 1, "uav1", 25, 400)
    ks = sorted(m.keyframes, key=lambda k: (m.keyframes[k].timestamp, k[1]))
    c = Chains(m)
    path = rot = weak_m2 = 0.0
    for i in range(1, len(ks)):
        a, b = m.keyframes[ks[i - 1]].world_from_cam, m.keyframes[ks[i]].world_from_cam
        path += float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
        rot += np.radians(rotation_angle_deg(a[:3, :3].T @ b[:3, :3]))
        sig = m.keyframes[ks[i]].odom_sigma
        weak_m2 += 0.0 if sig is None else float(sig[0]) ** 2
    d = c.between(ks[0], ks[-1])
    assert d is not None
    np.testing.assert_allclose(d[:3], [path, rot, np.sqrt(weak_m2)], rtol=1e-12)
    assert rot > 1.0 and weak_m2 > 0.0  # the random poses turn, and some keyframes tracked weakly
