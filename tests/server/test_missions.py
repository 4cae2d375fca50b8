"""Missions and sessions as identities (issue: mission data is never lost or corrupted).

Real `hivemap server` and `hivemap agent` processes on the tiny scenario (one UAV, 6 s), over a real
WebSocket, with real SQLite files; the server runs without a back-end, so every stored keyframe pose must
equal the last pose its agent sent, bit for bit (mission_records).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from agent_client import SyncAgent
from mission_records import agent_record, compare, stored_keyframes
from srv_helpers import TOKENS, ServerProcess, write_config

from hivemap.client.link import AgentLink, LinkOptions
from hivemap.protocol import MapPoints
from hivemap.server.loadgen import CAMERA, synthetic_stream


@pytest.fixture
def server(tmp_path: Path):  # type: ignore[no-untyped-def]
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def run_agent(
    dataset: Path, server: ServerProcess, out: Path, *extra: str
) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "hivemap.cli.main", "agent", "--dataset", str(dataset),
           "--server", server.ws_url, "--agent-id", "uav1", "--token", TOKENS["uav1"], "--out", str(out),
           "--no-progress", "--wait-corrections", "0", *extra]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def db_of(server: ServerProcess) -> Path:
    return server.data_dir / "hivemap.sqlite"


def test_second_mission_with_the_same_out_is_a_new_session_and_leaves_the_first_untouched(
    tiny_uav: Path, server: ServerProcess, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    a = run_agent(tiny_uav, server, out)
    assert a.returncode == 0, a.stderr[-2000:]
    server.stop()
    rec_a = agent_record(out / "outbox.sqlite", "uav1")
    stored_a, _ = stored_keyframes(db_of(server), "uav1")
    assert rec_a.keyframe_messages > 5 and rec_a.unacked == 0
    server.start()
    b = run_agent(tiny_uav, server, out)  # the same --out: the finished mission is archived, B is new
    assert b.returncode == 0, b.stderr[-2000:]
    info = server.json("/agents/uav1")
    server.stop()
    archived = out / f"outbox-{rec_a.mission}.sqlite"
    assert archived.exists()
    rec_b = agent_record(out / "outbox.sqlite", "uav1")
    assert rec_b.mission != rec_a.mission and rec_b.keyframe_messages > 5
    # both missions are stored whole, each keyframe once, none moved; A exactly as it was before B
    assert compare([agent_record(archived, "uav1"), rec_b], db_of(server), "uav1").clean
    stored, _ = stored_keyframes(db_of(server), "uav1")
    for k, T in stored_a.items():
        assert np.array_equal(stored[k], T), k
    # REST shows both missions and their sessions in separate maps
    assert {m["mission"] for m in info["missions"]} == {rec_a.mission, rec_b.mission}
    sessions = {(s["mission"], s["client_session"]): s for s in info["sessions"]}
    sa, sb = sessions[(rec_a.mission, 0)], sessions[(rec_b.mission, 0)]
    assert sa["session"] != sb["session"] and sa["map_id"] != sb["map_id"]
    assert sb["keyframes"] == rec_b.keyframe_messages


def test_a_fresh_outbox_for_a_known_agent_is_a_new_mission_not_a_resume(
    tiny_uav: Path, server: ServerProcess, tmp_path: Path
) -> None:
    a = run_agent(tiny_uav, server, tmp_path / "a")
    assert a.returncode == 0, a.stderr[-2000:]
    b = run_agent(tiny_uav, server, tmp_path / "b")  # the server knows uav1 with a high last seq
    assert b.returncode == 0, b.stderr[-2000:]
    assert "outbox only assigned" not in b.stderr  # never told to skip ahead
    server.stop()
    recs = [agent_record(tmp_path / d / "outbox.sqlite", "uav1") for d in ("a", "b")]
    assert all(r.unacked == 0 for r in recs)
    c = compare(recs, db_of(server), "uav1")
    assert c.clean, c


def test_a_resumed_mission_the_server_does_not_know_is_sent_again_whole(tmp_path: Path) -> None:
    """The server lost its data (a new data dir): the resumed outbox's welcome says the mission is
    unknown and the agent sends everything again, acknowledged messages included."""
    import asyncio

    msgs, truth = synthetic_stream("uav1", 6, seed=3, pose_update_every=2)
    box = tmp_path / "outbox.sqlite"

    async def deliver(url: str) -> None:
        link = AgentLink(url, "uav1", "uav", CAMERA.to_dict(), TOKENS["uav1"], box, options=LinkOptions())
        task = asyncio.create_task(link.run())
        if link.outbox.last_seq == 0:
            for m in msgs:
                link.submit_nowait(m)
        await asyncio.wait_for(link.connected.wait(), 30)  # the welcome has been handled
        await link.flush(timeout=30)
        await link.close()
        task.cancel()

    first = ServerProcess(tmp_path / "d1", write_config(tmp_path / "s1.toml")).start()
    try:
        asyncio.run(deliver(first.ws_url))
    finally:
        first.stop()
    second = ServerProcess(tmp_path / "d2", write_config(tmp_path / "s2.toml")).start()
    try:
        asyncio.run(deliver(second.ws_url))  # every message was acked by the first server already
        assert second.json("/agents/uav1")["last_seq"] == len(msgs)
    finally:
        second.stop()
    c = compare([agent_record(box, "uav1")], second.data_dir / "hivemap.sqlite", "uav1")
    assert c.clean and len(stored_keyframes(second.data_dir / "hivemap.sqlite", "uav1")[0]) == 6, c


def test_a_new_mission_reusing_ids_and_seqs_is_stored_beside_the_old_one(server: ServerProcess) -> None:
    """Two missions of one agent id send the same keyframe ids and seqs: both are stored, in their own
    sessions, and each mission resumes at its own last seq."""
    a = SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], mission="mission-a")
    assert a.welcome().mission_known is False
    msgs, _ = synthetic_stream("uav1", 3, seed=1, pose_update_every=0)
    assert a.send_all(msgs)[1] == []
    a.close()
    b = SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], mission="mission-b")
    w = b.welcome()
    assert w.mission_known is False and w.last_seq == 0  # a new mission starts at seq 0, not at A's 6
    assert b.send_all(msgs)[1] == []  # the same ids and seqs again: stored as B's, not duplicates of A's
    b.close()
    info = server.json("/agents/uav1")
    by = {(s["mission"], s["client_session"]): s for s in info["sessions"]}
    assert by[("mission-a", 0)]["session"] == 0 and by[("mission-b", 0)]["session"] == 1
    assert by[("mission-a", 0)]["keyframes"] == by[("mission-b", 0)]["keyframes"] == 3
    # back on mission A: resumed at its own last seq
    a2 = SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], mission="mission-a")
    w2 = a2.welcome()
    assert w2.mission_known is True and w2.last_seq == len(msgs)
    a2.close()


def test_points_fused_at_a_loop_closure_survive_kill_and_restart(tmp_path: Path) -> None:
    """A loop closure fuses the two passes' duplicate points; after a SIGKILL and after a clean restart
    the reloaded map stack is the one the server had (same digest: keyframes, points, observations,
    graphs, poses bit for bit), not one with the fused-away points back."""
    from hivemap.server.backend_synth import loop_passes

    first, second, _, _ = loop_passes()
    cfg = write_config(tmp_path / "server.toml", backend=True)
    server = ServerProcess(tmp_path / "data", cfg).start()
    try:
        with SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as agent:
            agent.welcome()
            assert agent.send_all(first + second)[1] == []
        server.wait_backend_idle()
        loops = [e for e in server.json("/events", limit=1000)["events"] if e["kind"] == "loop"]
        assert loops, "the second pass closed no loop"
        (m,) = server.json("/maps")["maps"]
        n_points = m["points"]
        before = server.json("/maps/digest")["digests"]
        sent_points = sum(len(msg.ids) for msg in first + second if isinstance(msg, MapPoints))
        assert n_points < sent_points  # points were fused away
        server.kill()
        server.start()
        assert server.json("/maps/digest")["digests"] == before
        assert server.json("/maps")["maps"][0]["points"] == n_points
        server.stop()  # a clean stop and start give the same again
        server.start()
        assert server.json("/maps/digest")["digests"] == before
    finally:
        server.stop()


def test_corrections_reach_only_the_mission_whose_map_they_correct(tmp_path: Path) -> None:
    """Mission B of an agent id re-visits mission A's place: the back-end merges the two missions' maps
    and corrects both. B's connection gets only corrections of B's keyframes, under B's own session
    number; A's corrections wait for A (applied to B's front-end they would move the wrong map)."""
    import time

    from test_backend import Server

    from hivemap.protocol import Correction
    from hivemap.server.backend_synth import loop_passes

    first, second, _, _ = loop_passes()
    srv = Server(tmp_path / "data")
    try:
        with SyncAgent(srv.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv", mission="mission-a") as a:
            a.welcome()
            assert a.send_all(first)[1] == []
        srv.wait_idle()
        b = SyncAgent(srv.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv", mission="mission-b")
        b.welcome()
        assert b.send_all(second)[1] == []
        srv.wait_idle()
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:  # what is still on the wire
            try:
                b.others.append(b.recv(timeout=0.5))
            except TimeoutError:
                break
        b.close()
        assert srv.call(lambda: len(srv.hive.stack.maps)) == 1, "the two missions' maps did not merge"
        got = [m for m in b.others if isinstance(m, Correction)]
        assert got, "mission B received no correction"
        for c in got:
            assert c.session == 0  # B's own number for its only session (the server's is 1)
            assert set(c.kf_ids.tolist()) <= set(range(1000, 1010)), c.kf_ids
        waiting = srv.call(lambda: len(srv.hive.agents["ugv1"].missions["mission-a"].undelivered))
        assert waiting > 0  # A's corrections are kept for A
    finally:
        srv.stop()


def test_a_store_from_before_missions_files_its_data_under_the_legacy_mission(
    server: ServerProcess,
) -> None:
    """A store written before missions (agent maps without a mission, one seq per agent) is upgraded on
    load: its data belongs to mission ``legacy``, which an upgraded v1 outbox resumes as."""
    import sqlite3

    with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], mission="legacy") as a:
        a.welcome()
        msgs, _ = synthetic_stream("uav1", 3, seed=2, pose_update_every=0)
        assert a.send_all(msgs)[1] == []
    digest = server.json("/maps/digest")["digests"]
    server.stop()
    db = sqlite3.connect(db_of(server))  # back to the old layout: what the previous version wrote
    db.executescript(
        f"""
        UPDATE server_agents SET last_seq = {len(msgs)};
        DELETE FROM server_missions;
        CREATE TABLE old_maps (folded TEXT PRIMARY KEY, agent_id TEXT NOT NULL, session INTEGER NOT NULL,
                               global_from_vio BLOB NOT NULL);
        INSERT INTO old_maps SELECT folded, agent_id, session, global_from_vio FROM server_agent_maps;
        DROP TABLE server_agent_maps;
        ALTER TABLE old_maps RENAME TO server_agent_maps;
        """
    )
    db.commit()
    db.close()
    server.start()
    assert server.json("/maps/digest")["digests"] == digest
    info = server.json("/agents/uav1")
    assert [(s["mission"], s["client_session"]) for s in info["sessions"]] == [("legacy", 0)]
    with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"], mission="legacy") as a:
        w = a.welcome()
        assert w.mission_known and w.last_seq == len(msgs)
