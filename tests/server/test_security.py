"""Security: token checks, fuzzed frames over a live socket, oversized frames, schemathesis on REST."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, snapshot, write_config
from websockets.exceptions import ConnectionClosed

from hivemap.protocol import Error as ErrorMsg
from hivemap.protocol import Welcome
from hivemap.server.loadgen import synthetic_stream


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> ServerProcess:
    d: Path = tmp_path_factory.mktemp("security")
    # A small frame limit so the oversized-frame test stays cheap.
    tokens = {**TOKENS, "fz": "tok-fz"}
    s = ServerProcess(d / "data", write_config(d / "server.toml", tokens, max_frame_bytes=512 * 1024)).start()
    yield s
    s.stop()


@pytest.mark.parametrize(
    ("agent_id", "token", "why"),
    [
        ("uav1", "", "missing token"),
        ("uav1", "not-the-token", "wrong token"),
        ("uav1", TOKENS["uav2"], "wrong token"),  # another agent's token
        ("intruder", "whatever", "unknown agent"),
    ],
)
def test_refused_hello_gets_a_reason_and_a_policy_close(
    server: ServerProcess, agent_id: str, token: str, why: str
) -> None:
    before = snapshot(server)
    msgs, _ = synthetic_stream(agent_id, 2, seed=5)
    with SyncAgent(server.ws_url, agent_id, token) as ag:
        reply = ag.hello()
        assert isinstance(reply, ErrorMsg) and reply.code == "unauthorized"
        assert why in reply.message
        # Whatever comes next is not stored; the socket is closed with 1008 (policy violation).
        try:
            for i, m in enumerate(msgs):
                ag.send(m, i + 1)
        except ConnectionClosed:
            pass
        with pytest.raises(ConnectionClosed) as info:
            while True:
                ag.recv(timeout=5)
        assert info.value.rcvd is not None and info.value.rcvd.code == 1008
    assert snapshot(server) == before
    agents = {a["agent_id"]: a for a in server.json("/agents")["agents"]}
    assert agents.get(agent_id, {"state": "never_connected"})["state"] == "never_connected"
    assert any(why in e["message"] for e in server.json("/events", kind="refused")["events"])


def test_fuzzed_frames_leave_server_up_and_maps_unchanged(server: ServerProcess) -> None:
    from hivemap.protocol.fuzz import fuzz_frames

    msgs, _ = synthetic_stream("ugv1", 6, seed=11)
    with SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as ag:
        base = ag.welcome().last_seq
        acks, errors = ag.send_all(msgs, base + 1)
        assert not errors
    before = snapshot(server)
    frames = list(fuzz_frames(10_000, seed=1234))
    assert len(frames) == 10_000
    sent = 0
    t0 = time.monotonic()
    # Fuzzed frames from an unauthenticated socket: nothing can reach a map. Reconnect whenever refused.
    ag = SyncAgent(server.ws_url, "fuzz", "x")
    while sent < len(frames):
        try:
            ag.send_raw(frames[sent])
            sent += 1
            if sent % 200 == 0:  # drain replies now and then so the outgoing queue never fills
                while True:
                    try:
                        ag.recv(timeout=0.001)
                    except TimeoutError:
                        break
        except ConnectionClosed:
            ag = SyncAgent(server.ws_url, "fuzz", "x")
    ag.close()
    assert server.alive()
    assert server.json("/health")["status"] == "ok"
    assert snapshot(server) == before
    # The same frames from an authenticated agent ("fz"): rejected, or they touch only fz's own maps.
    ag = SyncAgent(server.ws_url, "fz", "tok-fz")
    ag.welcome()
    for i, frame in enumerate(frames[:1000]):
        try:
            ag.send_raw(frame)
        except ConnectionClosed:
            ag = SyncAgent(server.ws_url, "fz", "tok-fz")
            ag.welcome()
        if i % 200 == 0:
            while True:
                try:
                    ag.recv(timeout=0.001)
                except (TimeoutError, ConnectionClosed):
                    break
    ag.close()
    assert server.alive()
    after = snapshot(server)
    others = [m for m in after["maps"] if not any(a.startswith("fz") for a in m["agents"])]
    assert others == before["maps"]
    for m in before["maps"]:
        assert after[f"kf{m['id']}"] == before[f"kf{m['id']}"]
        assert after[f"ply{m['id']}"] == before[f"ply{m['id']}"]
    assert time.monotonic() - t0 < 120
    # The server still ingests normally afterwards.
    with SyncAgent(server.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv") as ag:
        assert isinstance(ag.hello(), Welcome)


def test_oversized_frame_closes_with_1009_and_server_stays_up(server: ServerProcess) -> None:
    with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"]) as ag:
        ag.welcome()
        with pytest.raises(ConnectionClosed) as info:
            ag.send_raw(b"\x00" * (600 * 1024))
            ag.recv(timeout=10)
        assert info.value.rcvd is not None and info.value.rcvd.code == 1009
    assert server.json("/health")["status"] == "ok"


def test_schemathesis_finds_no_server_errors(server: ServerProcess) -> None:
    import schemathesis
    from hypothesis import HealthCheck, Phase, given, settings

    schema = schemathesis.openapi.from_url(server.url + "/openapi.json")
    failures: list[str] = []
    n_cases = 0
    t0 = time.monotonic()
    for result in schema.get_all_operations():
        operation = result.ok()  # type: ignore[union-attr]

        @given(case=operation.as_strategy())
        @settings(
            max_examples=30,
            deadline=None,
            phases=[Phase.explicit, Phase.generate],
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def check(case: schemathesis.Case) -> None:
            nonlocal n_cases
            n_cases += 1
            response = case.call(base_url=server.url, timeout=10)
            if response.status_code >= 500:
                failures.append(f"{case.method} {case.formatted_path} {case.query}: {response.status_code}")

        check()
    assert n_cases >= 100, "every operation was exercised"
    assert not failures, failures
    assert time.monotonic() - t0 < 60


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def test_agent_that_never_reads_is_dropped_with_bounded_memory(tmp_path: Path) -> None:
    """Acks pile up when the agent doesn't read: the bounded outgoing queue fills and the server drops the
    connection instead of buffering without end."""
    import socket
    import threading

    from websockets.sync.client import connect

    from hivemap.protocol import MapPoints, encode
    from hivemap.server.loadgen import hello

    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "s.toml", outbox_max=16)).start()
    try:
        assert s.proc is not None
        rss0 = _rss_kb(s.proc.pid)
        sock = socket.create_connection(("127.0.0.1", s.port))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a tiny window: the server blocks soon
        ws = connect(s.ws_url, sock=sock, max_size=None, compression=None, legacy=True)
        ws.send(encode(hello("uav1", TOKENS["uav1"]), 0))
        tiny = [
            encode(
                MapPoints(
                    ids=np.array([i], np.int64), xyz=np.zeros((1, 3)), descriptors=np.zeros((1, 32), np.uint8)
                ),
                i + 1,
            )
            for i in range(30_000)
        ]
        sent = [0]

        def blast() -> None:
            try:
                for frame in tiny:
                    ws.send(frame)
                    sent[0] += 1
            except Exception:  # the server dropped us / we closed the socket
                pass

        th = threading.Thread(target=blast, daemon=True)
        th.start()
        deadline = time.monotonic() + 60
        dropped = False
        while time.monotonic() < deadline and not dropped:
            time.sleep(0.2)
            dropped = any("slow consumer" in e["message"] for e in s.json("/events", kind="error")["events"])
        assert dropped, f"not dropped after {sent[0]} messages"
        sock.close()
        th.join(10)
        assert s.json("/health")["status"] == "ok"
        assert _rss_kb(s.proc.pid) - rss0 < 100_000, "memory stayed bounded"
        # The agent reconnects and resumes: everything acked before the drop is stored exactly once.
        with SyncAgent(s.ws_url, "uav1", TOKENS["uav1"]) as ag:
            last = ag.welcome().last_seq
        assert 0 < last <= sent[0]
        assert s.json("/agents/uav1")["points"] == last
    finally:
        s.stop()
