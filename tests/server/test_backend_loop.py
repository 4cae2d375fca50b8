"""Intra-map loop closure through the back-end: one agent passes a place, drifts, and passes it again.

The second pass is sent under a known drift (rigid, 2.3 deg + ~0.5 m, as odometry would accumulate) with
its own keyframe and point ids; place recognition inside the agent's own map must find the loop, and the
loop edge + Sim(3) pose graph + global BA must bring the second pass back onto the first.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_backend import (
    FAST,
    UAV_FROM_WORLD,
    UGV_FROM_WORLD,
    Server,
    agent_transform,
    check_transform,
    stream,
)

from hivemap.maps.geometry import Sim3, rotation_angle_deg, so3_exp
from hivemap.server.backend import preset
from hivemap.server.backend.options import FitOptions
from hivemap.server.backend_synth import agent_stream, loop_passes, make_world


@pytest.fixture
def srv(tmp_path: Path) -> Iterator[Server]:
    s = Server(tmp_path / "data")
    yield s
    s.stop()


def test_second_pass_closes_a_loop_and_removes_the_drift(srv: Server) -> None:
    first, second, true2, sent2 = loop_passes()
    with stream(srv, "ugv1", "ugv", first + second):
        srv.wait_idle()
    loops = srv.call(lambda: list(srv.backend.loops))
    assert len(loops) >= 1, srv.call(lambda: dict(srv.hive.events.counts))
    poses = srv.call(
        lambda: {
            k[1]: kf.world_from_cam.copy()
            for m in srv.hive.stack.maps.values()
            for k, kf in m.keyframes.items()
        }
    )
    ids = list(range(1000, 1010))
    before = np.linalg.norm(sent2[:, :3, 3] - true2[:, :3, 3], axis=1)
    after = np.linalg.norm(np.array([poses[i][:3, 3] for i in ids]) - true2[:, :3, 3], axis=1)
    # the drift moved the second pass by ~0.5-0.9 m; after the loop it is back within 10 cm (point noise
    # 2 cm, pixel noise 0.5 px: the BA solution is good to a few cm)
    assert before.mean() > 0.4
    assert after.max() < 0.1, (before, after)
    # each loop record says what it asked of its query keyframe: the drift there, to 5 cm / 0.2 deg
    for rec in loops:
        q = rec["query"][1] - 1000
        assert abs(rec["move_m"] - before[q]) < 0.05 and abs(rec["turn_deg"] - 2.29) < 0.2, (rec, before[q])


def test_keyframes_reloaded_after_restart_are_indexed_and_merge(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    pts, desc = make_world(rng, 2500, (-20, 30))
    ugv_msgs, _, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    uav_msgs, _, _ = agent_stream(rng, pts, desc, np.linspace(-2, 12, 10), UAV_FROM_WORLD)
    first = Server(tmp_path / "data")
    try:
        with stream(first, "ugv1", "ugv", ugv_msgs):
            first.wait_idle()
    finally:
        first.stop()
    second = Server(tmp_path / "data")  # the UGV's map comes back from SQLite; the UAV arrives now
    try:
        with stream(second, "uav1", "uav", uav_msgs):
            second.wait_idle()
        assert second.call(lambda: len(second.backend.merges)) == 1
        assert second.call(lambda: len(second.hive.stack.maps)) == 1
    finally:
        second.stop()


def test_single_agent_with_gnss_moves_into_enu_without_a_merge(srv: Server) -> None:
    rng = np.random.default_rng(7)
    pts, desc = make_world(rng, 2500, (-20, 30))
    # 20 keyframes with fixes (sigma 5 cm, world frame taken as ENU): the GNSS stage runs after the 20th
    msgs, true, _ = agent_stream(rng, pts, desc, np.linspace(-6, 12, 20), UGV_FROM_WORLD, gnss_sigma=0.05)
    with stream(srv, "ugv1", "ugv", msgs):
        srv.wait_idle()
    assert srv.call(lambda: srv.hive.events.counts.get("gnss_stage", 0)) >= 1
    check_transform(agent_transform(srv, "ugv1"), UGV_FROM_WORLD.inverse(), true[:, :3, 3])


def test_keyframes_missing_from_an_optimisation_follow_their_parent(srv: Server) -> None:
    """ORB-SLAM's propagation: keyframes that arrived after the snapshot of a global BA (not in its result)
    move with their spanning-tree ancestor's correction; so do the points and the agent's frame."""
    rng = np.random.default_rng(8)
    pts, desc = make_world(rng, 2000, (-20, 30))
    msgs, _, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    with stream(srv, "ugv1", "ugv", msgs):
        srv.wait_idle()
    C = Sim3(so3_exp(np.array([0.01, -0.02, 0.03])), np.array([0.3, -0.1, 0.2]), 1.0)

    def run() -> tuple[dict, dict, dict, dict, Sim3, Sim3]:
        m = next(iter(srv.hive.stack.maps.values()))
        keys = sorted(m.keyframes)
        old = {k: m.keyframes[k].world_from_cam.copy() for k in keys}
        old_pts = {k: p.xyz.copy() for k, p in m.points.items()}
        g0 = srv.hive.agents["ugv1"].maps[0].global_from_vio
        # "the optimisation saw only the first half": the second half was not in its snapshot
        srv.backend._apply_corrections(m, {k: C for k in keys[:5]}, {})
        new = {k: m.keyframes[k].world_from_cam.copy() for k in keys}
        new_pts = {k: p.xyz.copy() for k, p in m.points.items()}
        return old, new, old_pts, new_pts, g0, srv.hive.agents["ugv1"].maps[0].global_from_vio

    old, new, old_pts, new_pts, g0, g1 = srv.call(run)
    for k in old:  # every keyframe's ancestor chain reaches the corrected half (the root is keyframe 0)
        np.testing.assert_allclose(new[k], C.transform_pose(old[k]), atol=1e-9)
    for k in old_pts:
        np.testing.assert_allclose(new_pts[k], C.apply(old_pts[k][None])[0], atol=1e-9)
    np.testing.assert_allclose((C @ g0).matrix(), g1.matrix(), atol=1e-6)


@pytest.mark.parametrize("tilt_deg", [0.0, 0.5, 2.0])
def test_loop_against_the_agents_up_directions_is_refused(srv: Server, tilt_deg: float) -> None:
    """The same loop with IMU up directions on every keyframe: exact ones agree with the loop's measured
    rotation, and it closes; on a second pass whose up directions lean 2 degrees (what a loop with a 2
    degree tilt error looks like), it is refused (limit AcceptOptions.loop_max_gravity_deg = 1 degree).
    Under the limit (0.5 degree) the loop closes levelled: its rotation follows the up directions
    (FitOptions.level_gravity), so it differs from the points' own by the lean."""
    rng = np.random.default_rng(5)
    pts, desc = make_world(rng, 2500, (-20, 30))
    drift = Sim3(so3_exp(np.array([0.0, 0.04, 0.0])), np.array([0.4, -0.2, 0.3]), 1.0)
    first, true1, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD, up_tilt_deg=0.0)
    second, true2, _ = agent_stream(rng, pts, desc, np.linspace(-4, 10, 10), UGV_FROM_WORLD, id0=1000,
                                    point_id0=100000, drift=drift, up_tilt_deg=tilt_deg)  # fmt: skip
    with stream(srv, "ugv1", "ugv", first + second):
        srv.wait_idle()
    events = srv.call(lambda: srv.hive.events.since(0, kind="loop"))
    refused = [e for e in events if (e.data or {}).get("refused")]
    if tilt_deg > 1.0:
        assert srv.call(lambda: len(srv.backend.loops)) == 0, [e.message for e in events]
        assert refused and all(abs(e.data["gravity_deg"] - tilt_deg) < 0.5 for e in refused)
        return
    loops = srv.call(lambda: list(srv.backend.loops))
    assert loops and not refused, [e.message for e in events]
    true = {k: T for k, T in enumerate(true1)} | {1000 + k: T for k, T in enumerate(true2)}
    for rec in loops:
        assert rec["levelled"] and abs(rec["gravity_deg"] - tilt_deg) < 0.3, rec
        gt = np.linalg.inv(true[rec["candidate"][1]]) @ true[rec["query"][1]]
        measured = Sim3.from_matrix(np.asarray(rec["candidate_from_query"]))  # these test maps are Sim(3)
        err = rotation_angle_deg(measured.R.T @ gt[:3, :3])
        # levelled to the (leaning) up directions: the loop's rotation error is the lean, to 0.2 deg
        assert abs(err - tilt_deg) < 0.2, (rec["query"], rec["candidate"], err)


@pytest.mark.parametrize("window", [0, 6])
def test_loop_levelled_by_neighbouring_up_directions(tmp_path: Path, window: int) -> None:
    """The second pass's up directions jump +-1.5 degrees from keyframe to keyframe (an agent's filter can
    be off for a while). Each keyframe's own (FitOptions.level_up_window = 0) make every loop look
    1.5 degrees off gravity, and the loops are refused; the mean over +-6 neighbours, carried by the map's
    relative rotations, is within 0.2 degree, so the loops close and their rotation is right to 0.3 deg."""
    rng = np.random.default_rng(5)
    pts, desc = make_world(rng, 2500, (-20, 30))
    drift = Sim3(so3_exp(np.array([0.0, 0.04, 0.0])), np.array([0.4, -0.2, 0.3]), 1.0)
    jumpy = np.where(np.arange(10) % 2 == 0, 1.5, -1.5)
    first, true1, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD, up_tilt_deg=0.0)
    second, true2, _ = agent_stream(rng, pts, desc, np.linspace(-4, 10, 10), UGV_FROM_WORLD, id0=1000,
                                    point_id0=100000, drift=drift, up_tilt_deg=jumpy)  # fmt: skip
    srv = Server(
        tmp_path / "data", preset("monocular", scheduler=FAST, fit=FitOptions(level_up_window=window))
    )
    try:
        with stream(srv, "ugv1", "ugv", first + second):
            srv.wait_idle()
        events = srv.call(lambda: srv.hive.events.since(0, kind="loop"))
        loops = srv.call(lambda: list(srv.backend.loops))
    finally:
        srv.stop()
    refused = [e for e in events if (e.data or {}).get("refused")]
    if window == 0:
        assert not loops and refused, [e.message for e in events]
        assert all(abs(e.data["gravity_deg"] - 1.5) < 0.3 for e in refused), [e.message for e in refused]
        return
    assert loops and not refused, [e.message for e in events]
    true = {k: T for k, T in enumerate(true1)} | {1000 + k: T for k, T in enumerate(true2)}
    for rec in loops:
        assert rec["levelled"] and rec["gravity_deg"] < 0.3, rec
        gt = np.linalg.inv(true[rec["candidate"][1]]) @ true[rec["query"][1]]
        measured = Sim3.from_matrix(np.asarray(rec["candidate_from_query"]))
        assert rotation_angle_deg(measured.R.T @ gt[:3, :3]) < 0.3, rec


def test_optimisations_requested_together_run_one_after_another(srv: Server) -> None:
    """Several optimisations requested in one stretch of the event loop (a batch of rendezvous
    observations, each adding an edge) run one after another: run side by side, each would apply its
    correction, computed from the same snapshot, on top of the others' and turn the map by a multiple."""
    first, second, true2, _ = loop_passes()
    with stream(srv, "ugv1", "ugv", first + second):
        srv.wait_idle()
    ids = list(range(1000, 1010))
    drift = Sim3(so3_exp(np.radians([0.0, 0.0, 3.0])), np.array([0.4, -0.3, 0.1]))

    def drift_and_request() -> None:
        m = next(iter(srv.hive.stack.maps.values()))
        edge = srv.backend.evidence.kept_edges(m.id, m.keyframes)[0].edge
        # the second pass drifts off again (as if the loop had not been closed yet), then three requests
        srv.backend._apply_corrections(m, {k: drift for k in m.keyframes if k[1] >= 1000}, {})
        for _ in range(3):
            srv.backend._schedule_optimisation(m.id, [edge], 0.0)

    srv.call(drift_and_request)
    srv.wait_idle()
    poses = srv.call(
        lambda: {
            k[1]: kf.world_from_cam.copy()
            for m in srv.hive.stack.maps.values()
            for k, kf in m.keyframes.items()
        }
    )
    after = np.linalg.norm(np.array([poses[i][:3, 3] for i in ids]) - true2[:, :3, 3], axis=1)
    assert after.max() < 0.1, after
