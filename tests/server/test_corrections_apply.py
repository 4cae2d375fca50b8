"""The batched moves of an optimisation's result (``corrections.apply_corrections``, ``chosen_keyframes``,
``optimise.pose_graph_corrections``) give what their one-by-one definitions give: a keyframe moved by its
correction or, when it has none, by its nearest corrected ancestor's; a point by ``new_xyz`` or by its
first observer's correction; a point nobody observes stays."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_frame_refit import _AgentMap, _Agents  # noqa: E402

from hivemap.maps.geometry import Sim3, rotation_angle_deg, so3_exp  # noqa: E402
from hivemap.maps.model import MapPoint  # noqa: E402
from hivemap.maps.testing import random_map  # noqa: E402
from hivemap.server.backend.corrections import apply_corrections, chosen_keyframes, local_poses  # noqa: E402
from hivemap.server.backend.optimise import Snapshot, pose_graph_corrections  # noqa: E402
from hivemap.server.backend.options import CorrectionOptions  # noqa: E402


def _sim(rng: np.random.Generator) -> Sim3:
    return Sim3(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.5, 3), float(np.exp(rng.normal(0, 0.02))))


def test_points_follow_their_first_observer_and_keyframes_their_corrected_ancestor() -> None:
    rng = np.random.default_rng(5)
    m = random_map(rng, 1, "uav1", 40, 900)
    m.agents.add("uav1")
    lonely = m.add_point(MapPoint("uav1", 5000, [1.0, 2.0, 3.0]))  # observed by no keyframe
    keys = sorted(m.keyframes)
    corr = {k: _sim(rng) for k in keys[::3]}  # the others arrived "after the snapshot"
    new_xyz = {("uav1", 7): np.array([9.0, 9.0, 9.0])}
    poses0 = {k: kf.world_from_cam.copy() for k, kf in m.keyframes.items()}
    xyz0 = {k: p.xyz.copy() for k, p in m.points.items()}
    firsts = {k: next(iter(p.observations), None) for k, p in m.points.items()}

    def expected(k: tuple[str, int]) -> Sim3:
        cur: tuple[str, int] | None = k
        while cur is not None and cur not in corr:
            cur = m.parent(cur)
        return corr[cur] if cur is not None else Sim3.identity()

    server = _Agents({"uav1": _AgentMap("uav1")})
    apply_corrections(server, m, corr, new_xyz, CorrectionOptions(), fix_scale=False)
    n_followers = sum(k not in corr for k in keys)
    assert 0 < n_followers < len(keys)
    for k in keys:
        want = expected(k).transform_pose(poses0[k])
        np.testing.assert_allclose(m.keyframes[k].world_from_cam, want, atol=1e-9)
    for k, p in m.points.items():
        if k in new_xyz:
            want = new_xyz[k]
        elif firsts[k] is None:
            want = xyz0[k]
        else:
            want = expected(firsts[k]).apply(xyz0[k])
        np.testing.assert_allclose(p.xyz, want, atol=1e-9)
    np.testing.assert_array_equal(lonely.xyz, [1.0, 2.0, 3.0])


def test_pose_graph_corrections_and_the_keyframes_a_correction_carries() -> None:
    rng = np.random.default_rng(6)
    m = random_map(rng, 1, "uav1", 30, 600)
    keys = sorted(m.keyframes)
    poses = np.array([m.keyframes[k].world_from_cam for k in keys])
    sims = [_sim(rng) @ Sim3.from_se3(P) for P in poses]
    corr, moved = pose_graph_corrections(Snapshot(1, 0, keys, poses), sims)
    for i, k in enumerate(keys):
        want = sims[i] @ Sim3.from_se3(poses[i]).inverse()
        np.testing.assert_allclose(corr[k].matrix(), want.matrix(), atol=1e-9)
    assert moved == max(float(np.linalg.norm(s.t - P[:3, 3])) for s, P in zip(sims, poses, strict=True))

    server = _Agents({"uav1": _AgentMap("uav1", _sim(rng))})
    before = local_poses(server, m)
    g_inv = server.maps["uav1"].global_from_vio.inverse()
    for k in keys:
        np.testing.assert_allclose(before[k], g_inv.transform_pose(m.keyframes[k].world_from_cam), atol=1e-9)
    after = {k: T.copy() for k, T in before.items()}
    for k in keys[::4]:  # some move by 0.1-1 m, some turn by 2 deg, the rest stay
        after[k][:3, 3] += rng.uniform(0.1, 1.0, 3)
    for k in keys[1::4]:
        after[k][:3, :3] = so3_exp(np.radians(2.0) * np.array([0.0, 0.0, 1.0])) @ after[k][:3, :3]
    o = CorrectionOptions()
    got = chosen_keyframes(m, "uav1", before, after, o, enu=False)
    moves = []
    for k in keys:
        dt = float(np.linalg.norm(after[k][:3, 3] - before[k][:3, 3]))
        dr = rotation_angle_deg(after[k][:3, :3] @ before[k][:3, :3].T)
        if dt >= o.min_move_m or dr >= o.min_rot_deg:
            moves.append((dt + 0.05 * dr, k))
    assert moves and len(moves) < len(keys)
    moved = sorted(k for _, k in sorted(moves, reverse=True)[: o.max_kfs])
    sample = keys[:: o.stride][-o.max_kfs :]
    extra = [k for k in moved if k not in set(sample)]
    assert got == sorted(set(sample) | set(extra[: max(0, o.max_kfs - len(sample))]))
    assert set(got) - set(sample), "some moved keyframes are carried beyond the sample"
