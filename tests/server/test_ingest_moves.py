"""An agent's pose updates move the server's points in batches (``ingest._points_follow`` and
``ingest._place_listed``), with what the one-by-one definitions give: a moved keyframe carries the points
it observed first and the update does not list; a listed point is placed where the agent now sees it from
its first observer (through the agent's transform when the server has no VIO pose of that keyframe)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.maps.testing import random_map
from hivemap.server.ingest import _place_listed, _points_follow


def _rigid(rng: np.random.Generator) -> np.ndarray:
    return se3(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.3, 3))


def test_moved_keyframes_carry_the_points_they_observed_first() -> None:
    rng = np.random.default_rng(8)
    m = random_map(rng, 1, "uav1", 20, 500)
    keys = sorted(m.keyframes)
    xyz0 = {k: p.xyz.copy() for k, p in m.points.items()}
    first = {k: next(iter(p.observations), None) for k, p in m.points.items()}
    D = {k: _rigid(rng) for k in keys[3:6]}
    D2 = _rigid(rng)
    moves = [(m.keyframes[k], D[k]) for k in keys[3:6]] + [(m.keyframes[keys[4]], D2)]  # one twice
    listed = {p for (_, p), f in first.items() if f == keys[5]}
    listed = set(sorted(listed)[:5])  # the update lists five of keys[5]'s points: they stay
    moved = _points_follow(m, moves, listed, "uav1")
    total = {k: D[k] for k in D}
    total[keys[4]] = D2 @ D[keys[4]]
    want_moved = set()
    for k, p in m.points.items():
        f = first[k]
        if f in total and k[1] not in listed:
            T = total[f]
            np.testing.assert_allclose(p.xyz, T[:3, :3] @ xyz0[k] + T[:3, 3], atol=1e-9)
            want_moved.add(k)
        else:
            np.testing.assert_array_equal(p.xyz, xyz0[k])
    assert {p.key for p in moved} == want_moved and len(moved) == len(want_moved) > 30


@dataclass
class _AgentMap:
    folded: str
    global_from_vio: Sim3


def test_listed_points_are_placed_from_their_first_observer() -> None:
    rng = np.random.default_rng(9)
    m = random_map(rng, 1, "uav1", 20, 500)
    g = Sim3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 2.0, 3), 1.3)
    keys = sorted(m.keyframes)
    for k in keys[::2]:  # the server knows the VIO pose of every other keyframe
        m.keyframes[k].vio_from_cam = _rigid(rng)
    ids = [int(i) for i in rng.choice(500, 120, replace=False)] + [9999]  # 9999: not in the map
    ids.append(ids[0])  # listed twice: the later position wins
    sent = rng.normal(0, 5.0, (len(ids), 3))
    placed = _place_listed(m, _AgentMap("uav1", g), ids, sent)
    assert [p.id for p in placed] == [i for i in ids if i != 9999]
    n_own = 0
    for row, pid in enumerate(ids):
        p = m.points.get(("uav1", pid))
        if p is None or (pid == ids[0] and row == 0):
            continue
        obs = next(iter(p.observations), None)
        kf = m.keyframes.get(obs) if obs is not None else None
        if kf is not None and kf.vio_from_cam is not None:
            V, W = kf.vio_from_cam, kf.world_from_cam
            in_cam = V[:3, :3].T @ (sent[row] - V[:3, 3]) * g.s
            want = W[:3, :3] @ in_cam + W[:3, 3]
            n_own += 1
        else:
            want = g.apply(sent[row])
        np.testing.assert_allclose(p.xyz, want, atol=1e-9)
    assert 0 < n_own < len(ids) - 2
