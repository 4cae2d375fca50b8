"""Undoing a merge (``hivemap.maps.merge.split_map``): each side gets back its keyframes and points in its own
frame, references across the sides stay as pending ones, and both maps persist and reload in one commit."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from test_model import _two_maps, assert_consistent

from hivemap.maps.checks import map_differences
from hivemap.maps.merge import split_map
from hivemap.maps.store import MapStore


def test_split_undoes_a_merge_with_fused_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    stack, orig, sim = _two_maps(rng)
    tgt_poses = {k: kf.world_from_cam.copy() for k, kf in stack.maps[0].keyframes.items()}
    tgt_cov = {k: stack.maps[0].covisibility(k) for k in stack.maps[0].keyframes}
    src_cov = {k: stack.maps[1].covisibility(k) for k in stack.maps[1].keyframes}
    pairs = [(("ugv", i), ("uav1", i)) for i in range(0, 300)]  # the target point survives each fusion
    stack.merge(0, 1, sim, pairs)
    store = MapStore(tmp_path / "split.sqlite")
    store.save_stack(stack)
    kept, new = split_map(stack, 0, {"uav1"}, sim.inverse(), {"undone": 0})
    with store.transaction():  # both sides in one commit
        store.save_map(kept)
        store.save_map(new)
    assert sorted(stack.maps) == [0, 2] and new.id == 2 and kept is stack.maps[0]
    assert kept.agents == {"ugv"} and new.agents == {"uav1"}
    assert set(new.keyframes) == set(orig["poses"]) and set(kept.keyframes) == set(tgt_poses)
    for k, T in orig["poses"].items():  # back in the source's frame to float precision
        np.testing.assert_allclose(new.keyframes[k].world_from_cam, T, rtol=0, atol=1e-9)
    for k, T in tgt_poses.items():
        assert kept.keyframes[k].world_from_cam.tobytes() == T.tobytes()
    for k, xyz in orig["pts"].items():
        if k in new.points:
            np.testing.assert_allclose(new.points[k].xyz, xyz, rtol=0, atol=1e-9)
    # the source's keyframes still name the fused (target) points: pending in the new map, not lost
    pending = new.pending_references()
    for keep, drop in pairs:
        assert pending.get(keep, {}) == orig["src_obs"][drop]
        assert kept.points[keep].observations == orig["tgt_obs"][keep]
    # each side's covisibility is its own again, minus the fused points (which now live on one side)
    for k, cov in tgt_cov.items():
        assert kept.covisibility(k) == cov
    assert all(set(new.covisibility(k)) <= set(src_cov[k]) for k in src_cov)
    assert_consistent(kept)
    assert_consistent(new)
    assert kept.merge_history[-1] == {"undone": 0} and new.merge_history[-1] == {"undone": 0}
    loaded = store.load_stack()
    store.close()
    assert sorted(loaded.maps) == [0, 2]
    assert map_differences(kept, loaded.maps[0]) == [] and map_differences(new, loaded.maps[2]) == []


def test_split_refuses_to_empty_a_side() -> None:
    rng = np.random.default_rng(3)
    stack, _, sim = _two_maps(rng)
    stack.merge(0, 1, sim)
    n = len(stack.maps[0].keyframes)
    for agents in ({"nobody"}, {"ugv", "uav1"}):
        with pytest.raises(ValueError, match="do not split"):
            split_map(stack, 0, agents, sim.inverse(), {})
    assert list(stack.maps) == [0] and len(stack.maps[0].keyframes) == n


def test_split_in_place_equals_a_rebuild_when_the_sides_grew_into_each_other(tmp_path: Path) -> None:
    """After the merge, keyframes of the kept agent observe the leaving agent's points (so their spanning-
    tree parents are the leaving agent's keyframes) and the other way round. The kept map, changed in place,
    holds what a map rebuilt from its side's keyframes and points holds: the same observations,
    covisibility and pending references; its tree is a consistent tree of its own keyframes. Written
    as the server writes a split (what left the kept map, the new map whole), both reload as they are."""
    from test_model import make_kf

    from hivemap.maps.model import Map, MapPoint

    rng = np.random.default_rng(5)
    stack, _, sim = _two_maps(rng)
    stack.merge(0, 1, sim, [(("ugv", i), ("uav1", i)) for i in range(0, 200)])
    m = stack.maps[0]
    for j in range(12):  # ugv keyframes on uav1 points, uav1 keyframes on ugv points
        theirs = [("uav1", int(i)) for i in rng.choice(np.arange(200, 2000), 60, replace=False)]
        mine = [("ugv", int(i)) for i in rng.choice(np.arange(200, 2000), 10, replace=False)]
        m.add_keyframe(make_kf("ugv", 1000 + j, theirs + mine, rng))
        m.add_keyframe(
            make_kf("uav1", 1000 + j, [("ugv", int(i)) for i in rng.choice(2000, 60, replace=False)], rng)
        )
    assert any(kf.parent is not None and kf.parent[0] == "uav1" for kf in m.keyframes_of_agent("ugv"))
    ref = Map(0)
    for mp in m.points.values():
        if mp.agent_id != "uav1":
            ref.add_point(MapPoint(mp.agent_id, mp.id, mp.xyz, mp.descriptor))
    for k, kf in m.keyframes.items():
        if k[0] != "uav1":
            kf2 = copy.copy(kf)
            kf2.point_ids, kf2.point_agents = kf.point_ids.copy(), dict(kf.point_agents)
            ref.add_keyframe(kf2)
    store = MapStore(tmp_path / "split.sqlite")
    store.save_stack(stack)
    store.sync_graph(m)  # drains the tree changes written with the stack
    kept, new = split_map(stack, 0, {"uav1"}, sim.inverse(), {"undone": 0})
    with store.transaction():  # the server's writes: the kept map by what left it, the new one whole
        store.remove_side(0, list(new.keyframes), list(new.points), kept.agents, {"undone": 0})
        store.sync_graph(kept)
        store.save_map(new)
    loaded = store.load_stack()
    store.close()
    assert map_differences(kept, loaded.maps[0]) == [] and map_differences(new, loaded.maps[new.id]) == []
    assert loaded.maps[0].merge_history == kept.merge_history and loaded.maps[0].agents == {"ugv"}
    assert kept is m and kept.agents == {"ugv"} and new.agents == {"uav1"}
    assert set(kept.keyframes) == set(ref.keyframes) and set(kept.points) == set(ref.points)
    for k in ref.keyframes:
        assert kept.covisibility(k) == ref.covisibility(k), k
        assert kept.keyframes[k].parent is None or kept.keyframes[k].parent[0] == "ugv"
    for pk, mp in ref.points.items():
        assert kept.points[pk].observations == mp.observations, pk
    assert kept.pending_references() == ref.pending_references()
    assert any(pk[0] == "uav1" for pk in kept.pending_references())
    assert_consistent(kept)
    assert_consistent(new)
