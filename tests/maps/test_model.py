"""Map model: covisibility / spanning tree / essential graph consistency, fusion, merge under a Sim(3)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hivemap.maps import Keyframe, Map, MapPoint, MapStack
from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.maps.testing import DEFAULT_CAMERA, random_map


def brute_covisibility(m: Map) -> dict[tuple, dict[tuple, int]]:
    """Recount from the keyframes' own point references only (independent of the map's indices)."""
    seen = {k: {pk for _, pk in kf.referenced_points() if pk in m.points} for k, kf in m.keyframes.items()}
    out: dict[tuple, dict[tuple, int]] = {k: {} for k in m.keyframes}
    for a, b in itertools.combinations(m.keyframes, 2):
        w = len(seen[a] & seen[b])
        if w:
            out[a][b] = w
            out[b][a] = w
    return out


def assert_consistent(m: Map) -> None:
    assert m.check_consistency() == []
    brute = brute_covisibility(m)
    for k in m.keyframes:
        assert m.covisibility(k) == brute[k], k


def make_kf(agent: str, kid: int, point_keys: list, rng: np.random.Generator) -> Keyframe:
    n = len(point_keys)
    return Keyframe(
        agent,
        kid,
        float(kid),
        se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3)),
        DEFAULT_CAMERA,
        rng.uniform(0, 400, (n, 2)),
        rng.integers(0, 8, n),
        rng.integers(0, 256, (n, 32)),
        point_keys=point_keys,
    )


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_covisibility_equals_shared_point_counts_under_random_edits(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = Map(0)
    agents = ["uav1", "ugv"]
    next_pt = dict.fromkeys(agents, 0)
    next_kf = dict.fromkeys(agents, 0)
    counts: dict[str, int] = {}
    for step in range(400):
        op = rng.choice(
            ["point", "point", "kf", "kf", "rm_kf", "rm_pt", "fuse", "obs", "unobs", "loop"],
            p=[0.2, 0.15, 0.15, 0.08, 0.05, 0.05, 0.1, 0.1, 0.05, 0.07],
        )
        agent = str(rng.choice(agents))
        kfs = list(m.keyframes)
        pts = list(m.points)
        if op == "point":
            pid = next_pt[agent]
            next_pt[agent] += 1
            obs = {}
            for k in rng.permutation(len(kfs))[: rng.integers(0, 4)]:
                kf = m.keyframes[kfs[k]]
                obs[kfs[k]] = int(rng.integers(kf.n_keypoints))  # may replace an existing reference
            m.add_point(MapPoint(agent, pid, rng.normal(size=3), observations=obs))
        elif op == "kf":
            n = int(rng.integers(5, 40))
            keys: list = [None] * n
            for i in range(n):
                r = rng.random()
                if r < 0.6 and pts:
                    keys[i] = pts[int(rng.integers(len(pts)))]  # duplicates get cleared
                elif r < 0.7:  # a point that arrives later (pending) or was fused (redirect)
                    keys[i] = (agent, int(rng.integers(0, next_pt[agent] + 5)))
            m.add_keyframe(make_kf(agent, next_kf[agent], keys, rng))
            next_kf[agent] += 1
        elif op == "rm_kf" and kfs:
            m.remove_keyframe(kfs[int(rng.integers(len(kfs)))])
        elif op == "rm_pt" and pts:
            m.remove_point(pts[int(rng.integers(len(pts)))])
        elif op == "fuse" and len(pts) >= 2:
            a, b = rng.choice(len(pts), 2, replace=False)
            keep, drop = pts[a], pts[b]
            expect = set(m.points[keep].observations) | set(m.points[drop].observations)
            assert m.fuse_points(keep, drop) == keep
            assert drop not in m.points
            assert set(m.points[keep].observations) == expect  # the survivor inherits every observation
            assert m.resolve_point(drop) == keep
        elif op == "obs" and kfs and pts:
            kf = m.keyframes[kfs[int(rng.integers(len(kfs)))]]
            m.add_observation(pts[int(rng.integers(len(pts)))], kf.key, int(rng.integers(kf.n_keypoints)))
        elif op == "unobs" and pts:
            mp = m.points[pts[int(rng.integers(len(pts)))]]
            if mp.observations:
                m.remove_observation(mp.key, next(iter(mp.observations)))
        elif op == "loop" and len(kfs) >= 2:
            a, b = rng.choice(len(kfs), 2, replace=False)
            m.add_loop_edge(kfs[a], kfs[b])
        counts[str(op)] = counts.get(str(op), 0) + 1
        if step % 5 == 0 or step > 380:
            assert_consistent(m)
    assert_consistent(m)
    assert len(m.keyframes) > 10 and len(m.points) > 10
    assert counts.get("fuse", 0) > 20 and counts.get("rm_kf", 0) > 5
    # essential graph = spanning tree + strong covisibility + loops
    ess = set(m.essential_edges(min_weight=3))
    for p, c in m.spanning_tree_edges():
        assert (min(p, c), max(p, c)) in ess
    for a, b in m.loop_edges():
        assert (a, b) in ess
    for a, b, w in m.strong_covisibility_edges(3):
        assert w >= 3 and (a, b) in ess
    for a, b in ess:
        tree = m.parent(a) == b or m.parent(b) == a
        assert tree or m.covisibility(a).get(b, 0) >= 3 or b in m.loop_neighbours(a)


def test_spanning_tree_parent_is_best_covisible_and_reparenting_keeps_a_tree() -> None:
    rng = np.random.default_rng(5)
    m = random_map(rng, 0, "uav1", 60, 3000, obs_per_keyframe=200)
    assert_consistent(m)
    roots = [k for k, kf in m.keyframes.items() if kf.parent is None]
    assert roots == [("uav1", 0)]  # a sliding-window trajectory is one connected tree
    for k, kf in m.keyframes.items():
        if kf.parent is not None:  # parent = strongest covisible among the keyframes before it
            earlier = {o: w for o, w in m.covisibility(k).items() if o[1] < k[1]}
            assert m.covisibility(k)[kf.parent] == max(earlier.values())
    # the strong covisibility graph exists in this map (sliding window: neighbours share > 100 points)
    assert len(m.strong_covisibility_edges()) > 30
    # remove a third of the keyframes, including the root: still a single tree
    for k in list(m.keyframes)[::3]:
        m.remove_keyframe(k)
    assert_consistent(m)
    assert sum(kf.parent is None for kf in m.keyframes.values()) == 1
    tree = m.spanning_tree_edges()
    assert len(tree) == len(m.keyframes) - 1


def test_pending_references_and_redirects() -> None:
    rng = np.random.default_rng(1)
    m = Map(3)
    m.add_keyframe(make_kf("a", 0, [("a", 0), ("a", 1), None, ("a", 2)], rng))
    m.add_keyframe(make_kf("a", 1, [("a", 1), ("a", 2), ("a", 2)], rng))  # duplicate cleared
    assert m.keyframes[("a", 1)].point_keys == [("a", 1), ("a", 2), None]
    assert m.covisibility(("a", 0)) == {}
    assert set(m.pending_references()) == {("a", 0), ("a", 1), ("a", 2)}
    for i in range(3):
        m.add_point(MapPoint("a", i, [0, 0, i]))
    assert m.pending_references() == {}
    assert m.covisibility(("a", 0)) == {("a", 1): 2}
    assert m.parent(("a", 1)) == ("a", 0)  # an orphan kf joins the tree on its first covisibility link
    m.add_point(MapPoint("b", 7, [1, 1, 1], observations={("a", 0): 2}))
    m.fuse_points(("b", 7), ("a", 0))
    # a late keyframe naming the dropped point gets the survivor, with its agent recorded per keypoint
    m.add_keyframe(make_kf("a", 2, [("a", 0), ("a", 1)], rng))
    kf2 = m.keyframes[("a", 2)]
    assert kf2.point_keys == [("b", 7), ("a", 1)]
    assert kf2.point_agents == {0: "b"} and kf2.point_ids.tolist() == [7, 1]
    assert m.covisibility(("a", 2)) == {("a", 0): 2, ("a", 1): 1}
    assert_consistent(m)


def _two_maps(rng: np.random.Generator) -> tuple[MapStack, dict, Sim3]:
    stack = MapStack()
    tgt = stack.new_map()
    src = stack.new_map()
    a = random_map(rng, 0, "ugv", 40, 2000, obs_per_keyframe=100)
    b = random_map(rng, 1, "uav1", 40, 2000, obs_per_keyframe=100)
    stack.maps[tgt.id], stack.maps[src.id] = a, b
    target_from_source = Sim3(so3_exp([0.3, -1.2, 0.7]), np.array([12.0, -4.0, 3.5]), 2.7)
    orig = {
        "pts": {k: p.xyz.copy() for k, p in b.points.items()},
        "poses": {k: kf.world_from_cam.copy() for k, kf in b.keyframes.items()},
        "tgt_pts": {k: p.xyz.copy() for k, p in a.points.items()},
        "tgt_obs": {k: dict(p.observations) for k, p in a.points.items()},
        "src_obs": {k: dict(p.observations) for k, p in b.points.items()},
    }
    return stack, orig, target_from_source


def test_merge_moves_every_point_and_pose_by_the_sim3_and_fuses_pairs() -> None:
    rng = np.random.default_rng(11)
    stack, orig, sim = _two_maps(rng)
    # duplicates: target point i <-> source point i for the first 300 (keep = target point)
    pairs = [(("ugv", i), ("uav1", i)) for i in range(0, 300)]
    merged = stack.merge(0, 1, sim, pairs)
    assert list(stack.maps) == [0] and merged is stack.maps[0]
    assert stack.map_of_agent("uav1") is merged and stack.map_of_agent("ugv") is merged
    fused_src = {d for _, d in pairs}
    for k, xyz in orig["pts"].items():
        if k in fused_src:
            assert k not in merged.points and merged.resolve_point(k) == ("ugv", k[1])
            continue
        # 1e-9 m: a Sim(3) applied to points within ~100 m is exact to ~1e-13; 1e-9 is the acceptance bound
        np.testing.assert_allclose(merged.points[k].xyz, sim.apply(xyz), rtol=0, atol=1e-9)
    for k, T in orig["poses"].items():
        got = merged.keyframes[k].world_from_cam
        exp_R = sim.R @ T[:3, :3]
        np.testing.assert_allclose(got[:3, :3], exp_R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[:3, 3], sim.s * sim.R @ T[:3, 3] + sim.t, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[3], [0, 0, 0, 1], atol=0)
    for k, xyz in orig["tgt_pts"].items():  # the target does not move
        assert merged.points[k].xyz.tobytes() == xyz.tobytes()
    for keep, drop in pairs:  # survivor inherits every observation; keyframes point at it
        expect = orig["tgt_obs"][keep] | orig["src_obs"][drop]
        assert merged.points[keep].observations == expect
        for kf_key, idx in orig["src_obs"][drop].items():
            assert merged.keyframes[kf_key].point_key(idx) == keep
    assert_consistent(merged)
    # cross-agent covisibility now exists and the two spanning trees are one
    assert any(o[0] == "ugv" for o in merged.covisibility(("uav1", 0)))
    assert sum(kf.parent is None for kf in merged.keyframes.values()) == 1
    assert len(merged.spanning_tree_edges()) == len(merged.keyframes) - 1
    rec = merged.merge_history[-1]
    assert rec["target"] == 0 and rec["source"] == 1 and rec["n_fused"] == 300
    np.testing.assert_array_equal(np.array(rec["target_from_source"]), sim.matrix())


def test_merge_rejects_colliding_keys_without_changes() -> None:
    rng = np.random.default_rng(2)
    stack = MapStack()
    a, b = stack.new_map(), stack.new_map()
    for m in (a, b):
        m.add_point(MapPoint("x", 1, [1, 2, 3]))
    with pytest.raises(ValueError):
        stack.merge(a.id, b.id, Sim3(so3_exp(rng.normal(size=3)), np.ones(3), 2.0))
    assert b.points[("x", 1)].xyz.tolist() == [1, 2, 3] and len(stack.maps) == 2


def test_chained_merges_keep_history_and_transforms_compose() -> None:
    rng = np.random.default_rng(4)
    stack = MapStack()
    maps = [random_map(rng, i, f"agent{i}", 10, 300) for i in range(3)]
    for m in maps:
        stack.add_map(m)
    p = maps[2].points[("agent2", 5)].xyz.copy()
    s21 = Sim3(so3_exp([0.1, 0.2, 0.3]), np.array([1.0, 2, 3]), 1.5)
    s10 = Sim3(so3_exp([-0.4, 0.0, 0.9]), np.array([-3.0, 0, 7]), 0.8)
    stack.merge(1, 2, s21)
    merged = stack.merge(0, 1, s10)
    np.testing.assert_allclose(merged.points[("agent2", 5)].xyz, (s10 @ s21).apply(p), atol=1e-9)
    assert [(r["target"], r["source"]) for r in merged.merge_history] == [(1, 2), (0, 1)]
    assert merged.agents == {"agent0", "agent1", "agent2"}
    assert_consistent(merged)


def test_merges_never_make_a_cycle_in_the_spanning_tree() -> None:
    # Two ways an online map got a cycle (the server then refused every later keyframe of that map):
    # (1) a merge re-roots a source orphan tree, its old root gets a parent but stayed an "orphan", and a
    # later first covisibility with its own grandchild hung it below that grandchild; (2) a target orphan
    # attached below a source keyframe during the merge was then chosen as that source tree's link.
    rng = np.random.default_rng(0)
    stack = MapStack()
    tgt, src = stack.new_map(), stack.new_map()
    tgt.add_point(MapPoint("t", 0, [0, 0, 5]))
    tgt.add_keyframe(make_kf("t", 0, [("t", 0)], rng))
    for i in range(5):
        src.add_point(MapPoint("s", i, [1, 0, 5]))
    for kid, pts in enumerate([[0], [1], [1, 2], [3, 4], [2, 3, None]]):
        # s0 the source's root; s1 below s2; s4 the root of an orphan tree holding s2 and s3
        src.add_keyframe(make_kf("s", kid, [("s", p) if p is not None else None for p in pts], rng))
    assert (
        src.parent(("s", 1)) == ("s", 2) and src.parent(("s", 2)) == ("s", 4) and src.parent(("s", 4)) is None
    )
    merged = stack.merge(tgt.id, src.id, Sim3(np.eye(3), np.zeros(3), 1.0), [(("t", 0), ("s", 4))])
    assert merged.parent(("s", 3)) == ("t", 0) and merged.parent(("s", 4)) == ("s", 3)  # re-rooted at s3
    merged.add_observation(("s", 1), ("s", 4), 2)  # s4's first covisibility with its grandchild s1
    assert merged.check_consistency() == []
    merged.add_keyframe(make_kf("t", 1, [("t", 0), ("s", 1)], rng))
    assert merged.check_consistency() == []

    stack = MapStack()
    tgt, src = stack.new_map(), stack.new_map()
    for i in range(2):
        tgt.add_point(MapPoint("t", i, [0, 0, 5]))
    tgt.add_keyframe(make_kf("t", 0, [("t", 0)], rng))
    tgt.add_keyframe(make_kf("t", 1, [("t", 1)], rng))  # an orphan of the target
    for i in range(2):
        src.add_point(MapPoint("s", i, [1, 0, 5]))
    src.add_keyframe(make_kf("s", 0, [("s", 0)], rng))
    src.add_keyframe(make_kf("s", 1, [("s", 0), ("s", 1)], rng))
    merged = stack.merge(tgt.id, src.id, Sim3(np.eye(3), np.zeros(3), 1.0), [(("t", 1), ("s", 1))])
    assert merged.check_consistency() == []
    merged.add_keyframe(make_kf("t", 2, [("t", 1), ("s", 0)], rng))
    assert merged.check_consistency() == []
