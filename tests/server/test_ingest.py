"""Ingest and REST against a real `hivemap server` subprocess on a loopback port, real WebSocket clients."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, map_of, parse_ply, write_config

from hivemap.maps.geometry import rotmat_from_quat_wxyz
from hivemap.protocol import Ack, Keyframe, MapPoints, PoseUpdates, encode
from hivemap.protocol import Error as ErrorMsg
from hivemap.server.loadgen import StreamTruth, synthetic_stream

# Poses and points travel as float64 and the server stores what it gets (identity global_from_vio before a
# merge): the only error is the SE(3) round trip through quaternions for TUM/JSON output.
POSE_TOL = 1e-9


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> ServerProcess:
    d: Path = tmp_path_factory.mktemp("ingest")
    s = ServerProcess(d / "data", write_config(d / "server.toml")).start()
    yield s
    s.stop()


def _check_map(server: ServerProcess, agent_id: str, truth: StreamTruth) -> dict:
    m = map_of(server, agent_id)
    assert m["agents"] == [agent_id]
    assert m["keyframes"] == len(truth.kf_poses)
    assert m["points"] == len(truth.points)
    kfs = server.json(f"/maps/{m['id']}/keyframes", limit=10000)["keyframes"]
    assert sorted(k["id"] for k in kfs) == sorted(truth.kf_poses)
    for k in kfs:
        np.testing.assert_allclose(np.array(k["world_from_cam"]), truth.kf_poses[k["id"]], atol=POSE_TOL)
    return m


def test_two_agents_stream_and_rest_shows_exact_maps(server: ServerProcess) -> None:
    streams = {
        "uav1": synthetic_stream("uav1", 25, seed=1),
        "ugv1": synthetic_stream("ugv1", 18, seed=2, offset=(0.0, 30.0, 0.0)),
    }
    agents = {
        a: SyncAgent(server.ws_url, a, TOKENS[a], kind="uav" if a.startswith("uav") else "ugv")
        for a in streams
    }
    for ag in agents.values():
        assert ag.welcome().last_seq == 0
    # Interleave the two agents message by message.
    sent = {a: 0 for a in streams}
    for i in range(max(len(m) for m, _ in streams.values())):
        for a, (msgs, _) in streams.items():
            if i < len(msgs):
                agents[a].send(msgs[i], i + 1)
                sent[a] += 1
    for a, (msgs, _) in streams.items():
        acks: list[int] = []
        while len(acks) < len(msgs):
            r = agents[a].recv()
            assert isinstance(r, Ack), r
            acks.append(r.seq)
        assert acks == list(range(1, len(msgs) + 1)), "acks come back in order, one per message"
    maps = {a: _check_map(server, a, truth) for a, (_, truth) in streams.items()}
    assert maps["uav1"]["id"] != maps["ugv1"]["id"]
    assert len(server.json("/maps")["maps"]) >= 2

    # PLY: vertex count and coordinates equal the truth (sorted by point id; doubles, so exact).
    truth = streams["uav1"][1]
    r = server.get(f"/maps/{maps['uav1']['id']}/points", format="ply")
    assert r.status_code == 200
    props, verts = parse_ply(r.content)
    assert [p[1] for p in props[:3]] == ["x", "y", "z"]
    assert len(verts) == len(truth.points)
    expected = np.stack([truth.points[i] for i in sorted(truth.points)])
    got = np.stack([verts["x"], verts["y"], verts["z"]], axis=1)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    assert (verts["observations"] >= 1).all(), "every point is observed by at least one keyframe"

    pts = server.json(f"/maps/{maps['uav1']['id']}/points", format="json")
    assert pts["count"] == len(truth.points) == len(pts["points"])

    # Trajectories: TUM text and JSON, ordered by time, equal to the truth.
    tum = server.get("/agents/uav1/trajectory", format="tum", frame="global").text.strip().splitlines()
    assert len(tum) == len(truth.kf_poses)
    for line, k in zip(tum, sorted(truth.kf_poses), strict=True):
        t, x, y, z, qx, qy, qz, qw = map(float, line.split())
        assert t == pytest.approx(truth.kf_timestamps[k], abs=1e-9)
        np.testing.assert_allclose([x, y, z], truth.kf_poses[k][:3, 3], atol=1e-8)
        np.testing.assert_allclose(
            rotmat_from_quat_wxyz([qw, qx, qy, qz]), truth.kf_poses[k][:3, :3], atol=1e-8
        )
    traj = server.json("/agents/uav1/trajectory", format="json", frame="local")
    assert [p["kf_id"] for p in traj["poses"]] == sorted(truth.kf_poses)

    info = {a["agent_id"]: a for a in server.json("/agents")["agents"]}
    for a, ag in agents.items():
        assert info[a]["state"] == "connected"
        assert info[a]["keyframes"] == len(streams[a][1].kf_poses)
        assert info[a]["pending_keyframes"] == 0
        assert info[a]["last_seq"] == len(streams[a][0])
        bw = info[a]["bandwidth"]
        assert bw["up_total"] == ag.bytes_sent, "every byte the agent sent is counted"
        assert bw["down_total"] > 0 and bw["up_peak"] >= bw["up_avg"] > 0
    metrics = server.get("/metrics").text
    assert f'hivemap_map_keyframes{{map="{maps["uav1"]["id"]}"}} 25' in metrics
    for ag in agents.values():
        ag.close()


def test_keyframe_waits_for_its_points_and_duplicates_are_ignored(server: ServerProcess) -> None:
    msgs, truth = synthetic_stream("uav2", 3, seed=3, pose_update_every=0)
    points0, kf0 = msgs[0], msgs[1]
    assert isinstance(points0, MapPoints) and isinstance(kf0, Keyframe)
    with SyncAgent(server.ws_url, "uav2", TOKENS["uav2"]) as ag:
        ag.welcome()
        # The keyframe first: stored (acked) but not inserted until its points arrive (paper 2.3.2).
        assert ag.send_all([kf0], 1) == ([1], [])
        m = map_of(server, "uav2")
        assert m["keyframes"] == 0
        assert server.json("/agents/uav2")["pending_keyframes"] == 1
        assert ag.send_all([points0], 2) == ([2], [])
        m = map_of(server, "uav2")
        assert (m["keyframes"], m["points"]) == (1, len(points0.ids))
        assert server.json("/agents/uav2")["pending_keyframes"] == 0
        # Re-sent keyframe / points under new seqs: acked, ignored by id.
        assert ag.send_all([kf0, points0], 3) == ([3, 4], [])
        # An old seq: a duplicate, acked without reapplying.
        assert ag.send_all([msgs[2]], 2) == ([2], [])
        m = map_of(server, "uav2")
        assert (m["keyframes"], m["points"]) == (1, len(points0.ids))
        assert server.json("/agents/uav2")["duplicates"] >= 3
        # The rest of the stream.
        acks, errors = ag.send_all(msgs[2:], 5)
        assert not errors
    m = map_of(server, "uav2")
    assert (m["keyframes"], m["points"]) == (len(truth.kf_poses), len(truth.points))


def test_bad_messages_get_an_error_naming_the_field_and_change_nothing(server: ServerProcess) -> None:
    msgs, _ = synthetic_stream("uav1", 2, seed=9, session=5, pose_update_every=0)
    with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], session=5) as ag:
        # Before hello: refused, connection kept.
        ag.send(msgs[0], 1)
        err = ag.recv()
        assert isinstance(err, ErrorMsg) and err.field == "type", err
        welcome = ag.welcome()
        base = welcome.last_seq
        before = server.json("/maps")
        # Unknown keyframe id in a pose update.
        bad = PoseUpdates(
            kf_ids=np.array([999], dtype=np.int64),
            world_from_cam=np.eye(4)[None],
            point_ids=np.zeros(0, dtype=np.int64),
            xyz=np.zeros((0, 3)),
            session=5,
        )
        acks, errors = ag.send_all([bad], base + 1)
        assert acks == [] and errors[0].field == "body.kf_ids[0]" and errors[0].seq == base + 1
        # Garbage frame: a protocol error, no seq.
        ag.send_raw(b"\x81\xa1v\x07")
        err = ag.recv()
        assert isinstance(err, ErrorMsg) and err.code != "unauthorized"
        # A truncated valid frame.
        ag.send_raw(encode(msgs[1], base + 2)[:-7])
        assert isinstance(ag.recv(), ErrorMsg)
        assert server.json("/maps") == before
        # The connection still works.
        acks, errors = ag.send_all(msgs, base + 2)
        assert (acks, errors) == ([base + 2, base + 3, base + 4, base + 5][: len(msgs)], [])
    info = server.json("/agents/uav1")
    assert info["errors"] >= 3
    kinds = {e["kind"] for e in server.json("/events")["events"]}
    assert {"connect", "error"} <= kinds


def test_rest_404_and_422_have_clear_bodies(server: ServerProcess) -> None:
    r = server.get("/maps/987654")
    assert r.status_code == 404 and "987654" in r.json()["detail"]
    r = server.get("/agents/nobody/trajectory")
    assert r.status_code == 404 and "nobody" in r.json()["detail"]
    r = server.get("/maps/abc")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["path", "map_id"]
    r = server.get("/maps/0/points", format="obj")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "format"]
    r = server.get("/agents/uav1/trajectory", frame="moon")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "frame"]
    assert server.get("/docs").status_code == 200
    viewer = httpx.get(server.url + "/", follow_redirects=True, timeout=10)
    assert viewer.status_code == 200 and "<canvas" in viewer.text
    assert server.get("/viewer/viewer.js").status_code == 200
    spec = server.json("/openapi.json")
    assert "/maps/{map_id}/points" in spec["paths"]
    h = server.json("/health")
    assert h["status"] == "ok" and h["store"]["commits"] > 0
    assert h["backend_idle"] is None and h["backend_queue"] == 0  # this server runs without a back-end


def test_reconnect_of_the_same_agent_replaces_the_old_connection(server: ServerProcess) -> None:
    from websockets.exceptions import ConnectionClosed

    msgs, truth = synthetic_stream("ugv1", 4, seed=12, session=3, pose_update_every=0)
    old = SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], session=3, kind="ugv")
    base = old.welcome().last_seq
    half = len(msgs) // 2
    assert old.send_all(msgs[:half], base + 1)[1] == []
    new = SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], session=3, kind="ugv")
    assert new.welcome().last_seq == base + half
    with pytest.raises(ConnectionClosed) as info:
        old.recv(timeout=5)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1000
    assert "replaced" in info.value.rcvd.reason
    assert new.send_all(msgs[half:], base + half + 1) == (
        list(range(base + half + 1, base + len(msgs) + 1)),
        [],
    )
    new.close()
    agents = server.json("/agents")["agents"]
    assert [a["agent_id"] for a in agents].count("ugv1") == 1
    m = map_of(server, "ugv1")
    assert m["agents"] == ["ugv1#3"] and m["keyframes"] == len(truth.kf_poses)


def test_rest_reads_during_ingest_never_fail(server: ServerProcess) -> None:
    """REST views run on the loop thread, so reading while agents stream never sees a map mid-update."""
    import threading

    msgs, truth = synthetic_stream("uav2", 40, seed=13, session=2, kf_before_points_every=3)
    statuses: list[int] = []
    stop = threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=server.url, timeout=10) as client:
            while not stop.is_set():
                for m in client.get("/maps").json()["maps"]:
                    for path in (f"/maps/{m['id']}/points", f"/maps/{m['id']}/keyframes", f"/maps/{m['id']}"):
                        statuses.append(client.get(path).status_code)
                statuses.append(client.get("/agents/uav2/trajectory", params={"format": "tum"}).status_code)
                statuses.append(client.get("/metrics").status_code)

    th = threading.Thread(target=poll)
    th.start()
    try:
        with SyncAgent(server.ws_url, "uav2", TOKENS["uav2"], session=2) as ag:
            base = ag.welcome().last_seq
            assert not ag.send_all(msgs, base + 1)[1]
    finally:
        stop.set()
        th.join(20)
    assert len(statuses) >= 5 and set(statuses) == {200}
    m = map_of(server, "uav2")
    assert (m["keyframes"], m["points"]) == (len(truth.kf_poses), len(truth.points))
