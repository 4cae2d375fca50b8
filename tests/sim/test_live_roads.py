"""A live UGV's roads stop short of obstacles (issue 26, closed loop): the world's fences cross the roads'
ends, and a UGV following the centre line drove through them (its camera saw a wall come to zero range and
its tracking failed). Paths end at the connected road nearest a goal behind an obstacle."""

from __future__ import annotations

import numpy as np

from hivemap.sim.live import LiveOptions, LiveSim
from hivemap.sim.live_control import ControlOptions, RoadPaths
from hivemap.sim.roads import inside_box_footprint
from hivemap.sim.world import Box

# a road along x through a fence (0.15 m thick, 8 m wide) at x = 10
ROAD = [np.array([[-20.0, 0.0], [30.0, 0.0]])]
FENCE = Box(np.array([10.0, 0.0, 0.9]), np.array([0.15, 8.0, 1.8]), 0.0, "F")


def test_a_path_stops_at_the_margin_before_a_fence_across_the_road() -> None:
    free = RoadPaths(ROAD)
    through = free.path(np.array([0.0, 0.0]), np.array([25.0, 0.0]))
    assert through[-1][0] > 24.0  # without obstacles the centre line runs through the fence
    paths = RoadPaths(ROAD, blocked=[FENCE], margin=2.0)
    p = paths.path(np.array([0.0, 0.0]), np.array([25.0, 0.0]))
    # ends at the connected node nearest the goal: the fence's near side, 2 m (one node spacing) short
    assert 7.0 <= p[-1][0] <= 8.0 + 1e-9, p[-1]
    assert not inside_box_footprint(FENCE, p, 2.0 - 1e-9).any()
    # from behind the fence, the far side's road is the way, not through it
    q = paths.path(np.array([20.0, 0.0]), np.array([0.0, 0.0]))
    assert 12.0 - 1e-9 <= q[-1][0] <= 13.0 and q[:, 0].min() >= 12.0 - 1e-9, q[[0, -1]]
    # no node of the graph lies within the margin, and none of its edges crosses the fence
    assert not inside_box_footprint(FENCE, paths.nodes, 2.0 - 1e-9).any()
    ends = paths.graph.tocoo()
    a, b = paths.nodes[ends.row], paths.nodes[ends.col]
    assert not ((a[:, 0] < 10.0) & (b[:, 0] > 10.0) | (a[:, 0] > 10.0) & (b[:, 0] < 10.0)).any()


def test_the_live_ugv_roads_keep_clear_of_every_obstacle_on_factory01() -> None:
    sim = LiveSim(LiveOptions(scenario="factory01", seed=1, agent="ugv"))
    try:
        paths = sim.controller.paths
        margin = ControlOptions().obstacle_margin_m
        near = [b.name for b in sim.world.boxes if inside_box_footprint(b, paths.nodes, margin - 1e-9).any()]
        assert near == [], near
        # the fences cut only the roads' ends: the UGV's start reaches almost all of its road network
        start = paths.nearest(sim.motion.trajectory.position(0.0)[0][:2])
        from scipy.sparse.csgraph import dijkstra

        reach = np.isfinite(dijkstra(paths.graph, directed=False, indices=start))
        print(f"{reach.mean():.1%} of {len(paths.nodes)} road nodes reachable from the UGV's start")
        assert reach.mean() > 0.85
        # a UAV's roads are not cut: it flies over the fences
        uav = LiveSim(LiveOptions(scenario="factory01", seed=1, agent="uav1"))
        try:
            fences = [b for b in uav.world.boxes if b.name.startswith("F")]
            assert any(inside_box_footprint(f, uav.controller.paths.nodes, 0.6).any() for f in fences)
        finally:
            uav.close()
    finally:
        sim.close()


def test_a_pillar_in_the_road_is_passed_beside_it() -> None:
    pillar = Box(np.array([10.0, 0.8, 2.0]), np.array([0.5, 0.5, 4.0]), 0.0, "P")
    paths = RoadPaths(ROAD, blocked=[pillar], margin=2.0, lateral=2.5)
    p = paths.path(np.array([0.0, 0.0]), np.array([25.0, 0.0]))
    assert p[-1][0] > 24.0  # the road goes on past it
    # every point of the path keeps the margin from the pillar, moving aside by no more than ``lateral``
    t = np.linspace(0, 1, 11)[:, None]
    dense = np.concatenate([a + t * (b - a) for a, b in zip(p[:-1], p[1:], strict=True)])
    assert not inside_box_footprint(pillar, dense, 1.0).any()
    assert not inside_box_footprint(pillar, p, 2.0 - 1e-9).any()
    assert np.abs(p[:, 1]).max() <= 2.5 + 1e-9 and p[:, 1].min() < -1.0
    # a fence across the whole road cannot be passed aside: the road ends before it (first test)
    fence = RoadPaths(ROAD, blocked=[FENCE], margin=2.0, lateral=2.5)
    assert fence.path(np.array([0.0, 0.0]), np.array([25.0, 0.0]))[-1][0] < 8.0 + 1e-9
