"""Issue 21, cases 4-6: signals, quotas, hello timeout, seq steps, persisted counters, explicit link
failures and start-up progress. Real `hivemap server` / `hivemap agent` processes, real WebSockets, real
SQLite files, real signals."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, free_port
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from hivemap.client.outbox import Outbox
from hivemap.maps.model import MapPoint
from hivemap.maps.store import MapStore
from hivemap.protocol import Error as ErrorMsg
from hivemap.protocol import Keyframe, MapPoints, decode
from hivemap.server.loadgen import synthetic_stream
from hivemap.sim.dataset import render_scenario
from hivemap.sim.scenarios import get_scenario

HIVEMAP = str(Path(sys.executable).parent / "hivemap")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny scenario's uav1, 4 s (41 stereo frames, ~9 keyframes)."""
    out = tmp_path_factory.mktemp("tiny")
    render_scenario(get_scenario("tiny"), out, agents=["uav1"], duration=4.0, progress=False)
    return out / "uav1"


def _config(path: Path, quotas: dict[str, Any] | None = None, **top: Any) -> Path:
    top.setdefault("backend", False)
    lines = [f"{k} = {json.dumps(v)}" for k, v in top.items()]
    if quotas:
        lines += ["[quotas]"] + [f"{k} = {v!r}" for k, v in quotas.items()]
    lines += ["[tokens]"] + [f'{a} = "{t}"' for a, t in TOKENS.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def _server(tmp_path: Path, quotas: dict[str, Any] | None = None, **top: Any) -> ServerProcess:
    return ServerProcess(tmp_path / "data", _config(tmp_path / "server.toml", quotas, **top))


def _agent(tiny: Path, url: str, out: Path, *extra: str) -> subprocess.Popen[str]:
    cmd = [HIVEMAP, "agent", "--dataset", str(tiny), "--server", url, "--agent-id", "uav1"]
    cmd += ["--token", TOKENS["uav1"], "--out", str(out), "--no-progress", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _agent_info(srv: ServerProcess, agent_id: str) -> dict[str, Any]:
    info: dict[str, Any] = srv.json(f"/agents/{agent_id}")
    return info


# ------------------------------------------------------------------------------------- case 4: signals
def test_server_sigterm_after_streaming_exits_0_with_the_store_closed(tmp_path: Path, tiny: Path) -> None:
    srv = _server(tmp_path, backend=True).start(timeout=60)
    try:
        agent = _agent(tiny, srv.ws_url, tmp_path / "out")
        out, err = agent.communicate(timeout=180)
        assert agent.returncode == 0, err[-3000:]
        keyframes = _agent_info(srv, "uav1")["keyframes"]
        assert keyframes > 0
        assert srv.proc is not None
        srv.proc.send_signal(signal.SIGTERM)
        rc = srv.proc.wait(30)
    finally:
        srv.kill()
    log = srv.log.read_text()
    assert rc == 0, log[-3000:]
    assert "SIGTERM received" not in log and "Aborted" not in log, log[-3000:]  # no glog stack dump
    assert "store closed" in log
    db = sqlite3.connect(srv.data_dir / "hivemap.sqlite")
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert db.execute("SELECT COUNT(*) FROM map_keyframes").fetchone()[0] == keyframes


def test_server_sigint_exits_0(tmp_path: Path) -> None:
    """(Also clean on main: uvicorn re-raises SIGINT as a KeyboardInterrupt that click turns into 0.)"""
    srv = _server(tmp_path).start()
    assert srv.proc is not None
    srv.proc.send_signal(signal.SIGINT)
    rc = srv.proc.wait(30)
    assert rc == 0, srv.log.read_text()[-3000:]
    assert "store closed" in srv.log.read_text()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_agent_signal_keeps_unsent_messages_and_exits_0(tmp_path: Path, tiny: Path, sig: int) -> None:
    srv = _server(tmp_path).start()
    out = tmp_path / "out"
    agent = _agent(tiny, srv.ws_url, out)
    try:
        deadline = time.monotonic() + 60
        while srv.get("/agents/uav1").json().get("last_seq", 0) == 0:  # the stream is flowing
            assert time.monotonic() < deadline and agent.poll() is None
            time.sleep(0.05)
        assert srv.proc is not None
        srv.proc.send_signal(signal.SIGSTOP)  # the server stops acknowledging: messages pile up unsent
        time.sleep(1.5)
        agent.send_signal(sig)
        stdout, stderr = agent.communicate(timeout=30)
    finally:
        if srv.proc is not None:
            srv.proc.send_signal(signal.SIGCONT)
        if agent.poll() is None:
            agent.kill()
    assert agent.returncode == 0, stderr[-3000:]
    last = stdout.strip().splitlines()[-1]
    assert f"stopped by {signal.Signals(sig).name}" in last, last
    unsent = int(last.split(" messages unsent")[0].rsplit(" ", 1)[1])
    assert unsent > 0, last
    box = Outbox(out / "outbox.sqlite", "uav1")  # the agent closed it: it opens again, nothing lost
    try:
        assert len(box) == unsent == box.last_seq - box.last_acked
        assert [s for s, _ in box.pending(limit=10**6)] == list(range(box.last_acked + 1, box.last_seq + 1))
    finally:
        box.close()
    srv.stop()
    stored = ServerProcess(srv.data_dir, srv.config, srv.port).start()
    try:
        # acked => stored; what the server stored after the agent left is skipped by the next welcome
        assert box.last_acked <= _agent_info(stored, "uav1")["last_seq"] <= box.last_seq
    finally:
        stored.stop()


# ------------------------------------------------------------------------------------- case 5: quotas
def test_points_quota_refuses_one_agent_and_serves_the_other(tmp_path: Path) -> None:
    srv = _server(tmp_path, quotas={"max_points": 300}).start()
    try:
        msgs, _ = synthetic_stream("uav1", 10, new_points_per_kf=40, pose_update_every=0)
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            a.welcome()
            acks, errors = a.send_all(msgs)
        quota = [e for e in errors if e.code == "quota"]
        assert quota and all("quotas.max_points" in e.message for e in quota), errors
        assert _agent_info(srv, "uav1")["points"] <= 300
        # the next agent is served in full
        msgs2, truth2 = synthetic_stream("uav2", 5, new_points_per_kf=40, pose_update_every=0, seed=1)
        with SyncAgent(srv.ws_url, "uav2", TOKENS["uav2"]) as b:
            b.welcome()
            acks2, errors2 = b.send_all(msgs2)
        assert errors2 == [] and len(acks2) == len(msgs2)
        assert _agent_info(srv, "uav2")["points"] == len(truth2.points)
        events = srv.json("/events", kind="quota")["events"]
        assert any(e["agent_id"] == "uav1" and "quotas.max_points" in e["message"] for e in events), events
    finally:
        srv.stop()


def test_keyframe_rate_quota_is_transient(tmp_path: Path) -> None:
    srv = _server(tmp_path, quotas={"keyframes_per_s": 2.0, "keyframes_burst": 3}).start()
    try:
        msgs, _ = synthetic_stream("uav1", 6, new_points_per_kf=10, pose_update_every=0)
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            a.welcome()
            acks, errors = a.send_all(msgs)
            rate = [e for e in errors if e.code == "rate"]
            assert rate and all("quotas.keyframes_per_s" in e.message for e in rate), errors
            # "rate" is "not now": the same keyframe is stored once the bucket has refilled
            refused = msgs[int(rate[0].seq) - 1]
            assert isinstance(refused, Keyframe)
            time.sleep(1.0)
            acks2, errors2 = a.send_all([refused], first_seq=len(msgs) + 1)
            assert errors2 == [] and acks2 == [len(msgs) + 1]
    finally:
        srv.stop()


# ------------------------------------------------------------- case 6: hello, seq, counters, link, loading
def test_a_hello_that_never_comes_closes_the_socket(tmp_path: Path) -> None:
    srv = _server(tmp_path, hello_timeout_s=0.5).start()
    try:
        ws = connect(srv.ws_url, open_timeout=10, legacy=True)
        t0 = time.monotonic()
        err = decode(ws.recv(timeout=5))[1]
        assert isinstance(err, ErrorMsg) and err.code == "hello_timeout"
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=5)
        assert time.monotonic() - t0 < 3.0
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
        assert "hello" in closed.value.rcvd.reason
    finally:
        srv.stop()


def test_a_seq_jump_is_refused_and_does_not_lock_the_agent_out(tmp_path: Path) -> None:
    srv = _server(tmp_path).start()
    try:
        msgs, _ = synthetic_stream("uav1", 2, new_points_per_kf=10, pose_update_every=0)
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            a.welcome()
            a.send(msgs[0], 2**62)
            err = a.recv()
            assert isinstance(err, ErrorMsg) and err.field == "seq" and err.seq == 2**62, err
            assert "max_seq_step" in err.message
            a.send(msgs[0], 10_002)  # more than 10000 past the last seq (0): refused too
            assert isinstance(a.recv(), ErrorMsg)
            acks, errors = a.send_all(msgs, first_seq=1)
            assert errors == [] and acks == list(range(1, len(msgs) + 1))
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            assert a.welcome().last_seq == len(msgs)
        assert _agent_info(srv, "uav1")["points"] == 20
    finally:
        srv.stop()


def test_message_and_bandwidth_counters_survive_a_restart(tmp_path: Path) -> None:
    srv = _server(tmp_path).start()
    msgs, _ = synthetic_stream("uav1", 4, new_points_per_kf=10, pose_update_every=0)
    with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
        a.welcome()
        a.send_all(msgs)
        a.send_all(msgs[:1], first_seq=1)  # a duplicate
        a.send_all([MapPoints(np.array([-1]), np.zeros((1, 3)), np.zeros((1, 32), np.uint8))], 100)
    time.sleep(0.5)  # the server sees the disconnect
    before = _agent_info(srv, "uav1")
    srv.stop()
    srv.start()
    try:
        after = _agent_info(srv, "uav1")
    finally:
        srv.stop()
    assert before["messages"]["MapPoints"] >= 5 and before["messages"]["Keyframe"] == 4, before
    assert before["duplicates"] >= 1 and before["errors"] >= 1, before
    for key in ("messages", "duplicates", "errors"):
        assert after[key] == before[key], key
    assert before["bandwidth"]["up_total"] > 0
    for key in ("up_total", "down_total", "up_peak", "down_peak"):
        assert after["bandwidth"][key] == before["bandwidth"][key], key


@pytest.mark.parametrize("kind", ["no_ws_path", "dead_port", "no_scheme"])
def test_agent_link_failures_end_with_one_line_and_a_nonzero_exit(
    tmp_path: Path, tiny: Path, kind: str
) -> None:
    srv = _server(tmp_path).start() if kind == "no_ws_path" else None
    try:
        url = {
            "no_ws_path": f"ws://127.0.0.1:{srv.port if srv else 0}",  # HTTP 403 on the handshake
            "dead_port": f"ws://127.0.0.1:{free_port()}/ws",
            "no_scheme": "127.0.0.1:8765/ws",
        }[kind]
        agent = _agent(tiny, url, tmp_path / "out", "--max-connect-attempts", "2")
        try:
            _, stderr = agent.communicate(timeout=90)
        finally:
            if agent.poll() is None:
                agent.kill()
    finally:
        if srv is not None:
            srv.stop()
    assert agent.returncode not in (0, None)
    assert "Traceback" not in stderr, stderr[-3000:]
    ours = [line for line in stderr.splitlines() if line.startswith("hivemap agent:")]
    assert len(ours) == 1 and stderr.strip().splitlines()[-1] == ours[0], stderr[-3000:]
    if kind == "no_scheme":
        assert "ws://" in ours[0]
    else:
        assert "after 2 attempts" in ours[0] and "messages unsent" in ours[0], ours[0]
        assert ("HTTP 403" in ours[0]) == (kind == "no_ws_path"), ours[0]
        box = Outbox(tmp_path / "out" / "outbox.sqlite", "uav1")
        try:
            assert f"{len(box)} messages unsent" in ours[0]
        finally:
            box.close()


def test_health_says_loading_while_a_large_store_loads(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    n = 150_000
    xyz, desc = rng.normal(0, 20, (n, 3)), rng.integers(0, 256, (n, 32), dtype=np.uint8)
    store = MapStore(data / "hivemap.sqlite")
    store.put_points(0, [MapPoint("uav1", i, xyz[i], desc[i]) for i in range(n)])
    store.close()
    srv = _server(tmp_path, hello_loading_wait_s=0.0).start(wait_loaded=False)  # at the first /health
    try:
        assert srv.json("/health")["status"] == "loading"
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            reply = a.hello()
            assert isinstance(reply, ErrorMsg) and reply.code == "unavailable", reply
        deadline = time.monotonic() + 60
        while srv.json("/health")["status"] == "loading":
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert srv.json("/health")["status"] == "ok"
        assert srv.json("/maps")["maps"][0]["points"] == n
        with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as a:
            assert not isinstance(a.hello(), ErrorMsg)
            acks, _ = a.send_all([MapPoints(np.array([n]), np.zeros((1, 3)), np.zeros((1, 32), np.uint8))])
            assert acks == [1]
    finally:
        srv.stop()
    log = srv.log.read_text()
    assert "store loaded in" in log and f"{n} map points" in log


def test_token_bucket_passes_one_oversized_message_when_full_then_refills_at_its_rate() -> None:
    from hivemap.server.quotas import TokenBucket

    b = TokenBucket(rate=2.0, burst=3.0)
    assert b.take(4, 0.0)  # larger than the burst: passes only on a full bucket, leaving a debt
    assert not b.take(1, 0.1) and not b.take(1, 0.5)  # the debt is not forgiven
    assert b.take(1, 1.0)  # -1 + 2 tokens/s x 1 s = 1
