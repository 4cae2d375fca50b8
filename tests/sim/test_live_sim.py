"""LiveSim (issue 26): the same advisories at the same frames give the same run, bit for bit; a UGV sent
to a goal off the road drives along the road, on drivable ground."""

from __future__ import annotations

import numpy as np

from hivemap.sim.live import LiveOptions, LiveSim
from hivemap.sim.live_control import WorldAdvisory
from hivemap.sim.world import road_distance


def _run(n: int) -> tuple[LiveSim, list[object]]:
    sim = LiveSim(LiveOptions("tiny", "ugv", hold_s=0.2, replan_period_s=0.2))
    frames = []
    for i in range(n):
        fr = sim.step()
        if i == 2:  # a goal 15 m north of the start and 4 m off the road's centre line
            p = fr.world_from_body[:3, 3]
            goal = np.array([[p[0] + 4.0, p[1] + 15.0, 0.0]])
            v = np.zeros(3)
            sim.advise(WorldAdvisory(fr.t, goal, v, v, 0.8))
        sim.steer()
        frames.append(fr)
    sim.close()
    return sim, frames


def test_live_sim_is_deterministic_and_keeps_the_ugv_on_the_road() -> None:
    a, fa = _run(60)
    b, fb = _run(60)
    for x, y in zip(fa, fb, strict=True):
        assert np.array_equal(x.left, y.left) and np.array_equal(x.right, y.right)  # type: ignore[attr-defined]
        assert np.array_equal(x.imu, y.imu) and np.array_equal(x.world_from_body, y.world_from_body)  # type: ignore[attr-defined]
    # 60 frames at 10 Hz span 5.9 s: IMU at 200 Hz and GNSS at 5 Hz, both from t = 0
    assert sum(len(f.imu) for f in fa) == 1181 and sum(len(f.fixes) for f in fa) == 30  # type: ignore[attr-defined]
    xy = np.array([T[:3, 3] for T in a.gt_poses])
    assert np.linalg.norm(xy[-1, :2] - xy[0, :2]) > 3.0  # it left the start
    dist, _ = road_distance(xy[:, :2], list(a.world.roads))
    assert float(dist.max()) < a.world.road_width / 2  # on the road all along
