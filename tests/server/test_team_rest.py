"""The team routes on a real server (subprocess, real WebSocket agents): ``/maps/{id}/frontiers`` gives
the frontiers of the stored points, ``/team/assignments`` the auction and advisories, in the documented
schemas. And the service's assignment of two agents in one map, on real frontiers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, map_of, write_config

from hivemap.protocol import Keyframe, MapPoints, TeamAdvisory, Welcome
from hivemap.server import schemas
from hivemap.server.loadgen import hello as make_hello
from hivemap.server.team.frontiers import extract
from hivemap.server.team.options import FrontierOptions, TeamOptions
from hivemap.server.team.orca import preferred_velocity
from hivemap.server.team.service import TeamService, _AgentSnap

sys.path.insert(0, str(Path(__file__).parent))
from test_team import FOPT, _half_explored  # noqa: E402

TEAM_TOML = """
[team]
min_interval_s = 0.0
[team.frontiers]
voxel_m = 0.5
cluster_m = 2.5
[team.auction]
max_goals_per_agent = 3
"""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> ServerProcess:
    d: Path = tmp_path_factory.mktemp("team")
    cfg = write_config(d / "server.toml", {**TOKENS, "uav3": "tok-uav3"})
    cfg.write_text(cfg.read_text() + TEAM_TOML)
    s = ServerProcess(d / "data", cfg).start()
    yield s
    s.stop()


def _stream(points: np.ndarray, path: np.ndarray) -> list[MapPoints | Keyframe]:
    """The points, then one keyframe per path position (camera looking along x; no keypoints linked)."""
    rng = np.random.default_rng(0)
    msgs: list[MapPoints | Keyframe] = [
        MapPoints(ids=np.arange(len(points), dtype=np.int64), xyz=points,
                  descriptors=rng.integers(0, 256, (len(points), 32), dtype=np.uint8))
    ]  # fmt: skip
    for k, p in enumerate(path):
        T = np.eye(4)
        T[:3, 3] = p
        n = 50
        msgs.append(
            Keyframe(kf_id=k, timestamp=100.0 + k, world_from_cam=T,
                     keypoints=rng.uniform(0, [640, 480], (n, 2)).astype(np.float32),
                     octaves=np.zeros(n, np.uint8), descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
                     point_ids=np.full(n, -1, np.int64))
        )  # fmt: skip
    return msgs


def test_frontiers_and_assignments_over_rest(server: ServerProcess) -> None:
    pts = _half_explored()
    floor = pts[pts[:, 2] < 1.0]  # the UGV's map: the floor half only
    uav_path = np.array([[1.0, 7.0, 3.5], [5.0, 7.0, 3.5], [9.0, 7.5, 3.5]])
    ugv_path = np.array([[1.0, 2.0, 0.3], [5.0, 2.0, 0.3], [9.0, 2.5, 0.3]])
    with (
        SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], kind="uav") as uav,
        SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as ugv,
    ):
        for ag, p, path in ((uav, pts, uav_path), (ugv, floor, ugv_path)):
            ag.welcome()
            msgs = _stream(p, path)
            acks, errors = ag.send_all(msgs)
            assert not errors and len(acks) == len(msgs)

        # frontiers of the stored map equal the module's on the same points and path (float64 kept)
        m_uav = map_of(server, "uav1")["id"]
        body = server.json(f"/maps/{m_uav}/frontiers")
        got = schemas.FrontierList.model_validate(body)
        opts = FrontierOptions(voxel_m=0.5, cluster_m=2.5)
        assert opts == FOPT
        want = extract(pts, opts, [uav_path])
        assert len(got.frontiers) == len(want.frontiers) > 0
        for g, w in zip(got.frontiers, want.frontiers, strict=True):
            np.testing.assert_allclose(g.goal, w.goal, atol=1e-9)
            assert tuple(g.reachable) == w.reachable
        assert got.voxel_m == 0.5 and got.known_cells == want.known_cells
        assert server.get("/maps/999999/frontiers").status_code == 404

        team = schemas.TeamAssignments.model_validate(server.json("/team/assignments"))
        by_agent = {a.agent_id: (m, a) for m in team.maps for a in m.agents}
        assert set(by_agent) == {"uav1", "ugv1"}
        for agent_id, kind in (("uav1", "uav"), ("ugv1", "ugv")):
            m, a = by_agent[agent_id]
            fr = {f.id: f for f in schemas.FrontierList.model_validate(
                server.json(f"/maps/{m.map_id}/frontiers")).frontiers}  # fmt: skip
            assert a.kind == kind and 1 <= len(a.goals) <= 3
            assert all(kind in fr[g].reachable for g in a.goals)
            np.testing.assert_allclose(a.position, (uav_path if kind == "uav" else ugv_path)[-1])
            # alone in its map: the advisory is the desired velocity, what the agent flies now (moving)
            assert a.advisory.neighbours == [] and a.advisory.safe_velocity == a.advisory.desired_velocity
            orca = TeamOptions().orca
            speed = orca.max_speed_uav if kind == "uav" else orca.max_speed_ugv
            want = preferred_velocity(np.array(a.velocity), np.array(a.position),
                                      np.array(a.goal_positions[0]), speed, orca)  # fmt: skip
            assert np.linalg.norm(np.array(a.velocity)[:2]) > orca.moving_mps  # moving: its own velocity
            np.testing.assert_allclose(a.advisory.desired_velocity, want, atol=1e-12)
            assert a.advisory.covariance == "default"
            assert a.advisory.inflated_radius_m == pytest.approx(a.advisory.radius_m + 2.0 * (0.1 + 0.05))
            assert [r.frontier_id for r in m.rounds if r.agent_id == agent_id] == sorted(
                a.goals, key=lambda g: [r.frontier_id for r in m.rounds].index(g)
            )
        spec = server.json("/openapi.json")
        assert "/maps/{map_id}/frontiers" in spec["paths"] and "/team/assignments" in spec["paths"]


def test_advisories_pushed_only_to_agents_that_ask(server: ServerProcess) -> None:
    """uav2's hello asks for team advisories (protocol v4): it gets its goals and safe velocity, the same as
    /team/assignments says; ugv1, connected alongside without asking, gets none."""
    import dataclasses
    import time

    pts = _half_explored()
    path = np.array([[2.0, 8.0, 3.5], [6.0, 8.0, 3.5]])
    with (
        SyncAgent(server.ws_url, "uav2", TOKENS["uav2"], kind="uav") as uav,
        SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as ugv,
    ):
        asking = dataclasses.replace(make_hello("uav2", TOKENS["uav2"], "uav"), team_advisories=True)
        uav.send(asking, 0)
        assert isinstance(uav.recv(), Welcome)
        ugv.welcome()
        uav.send_all(_stream(pts, path))
        deadline, got = time.monotonic() + 10.0, None
        while got is None and time.monotonic() < deadline:
            got = next((m for m in uav.others if isinstance(m, TeamAdvisory)), None)
            if got is None:
                msg = uav.recv(timeout=10.0)
                got = msg if isinstance(msg, TeamAdvisory) else None
        assert got is not None, "no team advisory within 10 s"
        team = schemas.TeamAssignments.model_validate(server.json("/team/assignments"))
        (mine,) = [a for m in team.maps for a in m.agents if a.agent_id == "uav2"]
        assert got.map_id == map_of(server, "uav2")["id"] and got.session == 0
        np.testing.assert_allclose(got.goals, np.array(mine.goal_positions).reshape(-1, 3), atol=1e-9)
        assert len(got.goals) >= 1 and got.radius_m == pytest.approx(mine.advisory.inflated_radius_m)
        np.testing.assert_allclose(got.safe_velocity, mine.advisory.safe_velocity, atol=1e-9)
        # the cylinder's half height: a UAV's own 0.3 m, no vertical sigma (default covariance)
        assert got.half_height_m == pytest.approx(mine.advisory.half_height_m) == pytest.approx(0.3)
        # ugv1 did not ask: nothing but what it asked for arrives (its queue stays empty for 2 push periods)
        with pytest.raises(TimeoutError):
            ugv.recv(timeout=2.5)


def test_the_intent_of_a_keyframe_is_the_desired_velocity_in_the_map_frame(server: ServerProcess) -> None:
    """Keyframes that carry the agent's intent (protocol v7, in the keyframe's camera frame): the server
    turns the latest one into the map frame by that keyframe's rotation and makes it the advisory's
    desired velocity (cut to the top speed), whatever the agent flies now; a keyframe without one brings
    back the current velocity."""
    import dataclasses

    pts = _half_explored()
    path = np.array([[2.0, 8.0, 3.5], [3.0, 8.0, 3.5], [4.0, 8.0, 3.5]])
    msgs = _stream(pts, path)
    # the camera looks along +y (its z), its x along -x: world = R cam
    R = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    intent_cam = np.array([0.5, 0.25, 3.0])  # 3 m/s forward: 2 m/s at the UAV's top speed
    for i, m in enumerate(msgs):
        if isinstance(m, Keyframe):
            T = np.array(m.world_from_cam)
            T[:3, :3] = R
            msgs[i] = dataclasses.replace(m, world_from_cam=T, intent_velocity=intent_cam)
    with SyncAgent(server.ws_url, "uav3", "tok-uav3", kind="uav") as uav:
        uav.welcome()
        acks, errors = uav.send_all(msgs)
        assert not errors and len(acks) == len(msgs)
        team = schemas.TeamAssignments.model_validate(server.json("/team/assignments"))
        (a,) = [a for m in team.maps for a in m.agents if a.agent_id == "uav3"]
        want = R @ intent_cam
        assert a.advisory.intent is not None
        np.testing.assert_allclose(a.advisory.intent, want, atol=1e-12)
        assert np.linalg.norm(want[:2]) > 2.0 and np.linalg.norm(a.velocity) == pytest.approx(1.0)
        cut = np.array([*(want[:2] * 2.0 / np.linalg.norm(want[:2])), want[2]])
        np.testing.assert_allclose(a.advisory.desired_velocity, cut, atol=1e-12)
        T = np.array(msgs[-1].world_from_cam)  # type: ignore[union-attr]
        T[:3, 3] = [6.0, 8.0, 3.5]  # 2 m on in 2 s: 1 m/s along x
        plain = dataclasses.replace(
            msgs[-1], kf_id=99, timestamp=104.0, world_from_cam=T, intent_velocity=None
        )
        acks, errors = uav.send_all([plain], first_seq=len(msgs) + 1)
        assert not errors
        team = schemas.TeamAssignments.model_validate(server.json("/team/assignments"))
        (a,) = [a for m in team.maps for a in m.agents if a.agent_id == "uav3"]
        assert a.advisory.intent is None
        np.testing.assert_allclose(a.velocity, [1.0, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(a.advisory.desired_velocity, a.velocity, atol=1e-12)


def test_service_assigns_two_agents_in_one_map_and_separates_them() -> None:
    """Two UAVs heading at each other in one map: the auction splits the deck's frontiers between them and the
    advisories, if followed for the time horizon, keep them apart by their inflated radii."""
    fr = extract(_half_explored(), FOPT)
    svc = TeamService(server=None, options=TeamOptions())
    team = [
        _AgentSnap("uav1", "uav", 0, np.array([3.0, 7.0, 3.0]), np.array([1.0, 0.0, 0.0])),
        _AgentSnap("uav2", "uav", 0, np.array([7.0, 7.0, 3.0]), np.array([-1.0, 0.0, 0.0])),
    ]
    covs = [svc._covariance(a.agent_id) for a in team]
    out = svc._assign(0, fr, team, covs)
    a1, a2 = out.agents
    assert a1.goals and a2.goals and not set(a1.goals) & set(a2.goals)
    uav_frontiers = {f.id for f in fr.frontiers if "uav" in f.reachable}
    # 8 deck frontiers, 5 a UAV at most: all taken; the floor's stay with nobody (no UGV here)
    assert len(uav_frontiers) == 8 and set(a1.goals) | set(a2.goals) == uav_frontiers
    assert set(out.unassigned) == {f.id for f in fr.frontiers} - uav_frontiers
    assert a1.advisory.neighbours == ["uav2"]
    p1, p2 = np.array(a1.position[:2]), np.array(a2.position[:2])
    v1, v2 = np.array(a1.advisory.safe_velocity[:2]), np.array(a2.advisory.safe_velocity[:2])
    r_sum = a1.advisory.inflated_radius_m + a2.advisory.inflated_radius_m
    horizon = TeamOptions().orca.time_horizon_s
    t = np.linspace(0.0, horizon, 501)[:, None]
    closest = np.linalg.norm((p2 + t * v2) - (p1 + t * v1), axis=1).min()
    assert closest >= r_sum - 1e-3
