"""Fault tolerance: SIGKILL the server mid-stream, drop the agent link repeatedly, kill and restart the agent.

In every case the final map must hold every keyframe and point sent exactly once, with the final poses, and no
message the server acknowledged may be lost (welcome.last_seq >= every acked seq).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS, ServerProcess, map_of, write_config
from websockets.exceptions import ConnectionClosed

from hivemap.protocol import Ack
from hivemap.server.loadgen import StreamTruth, synthetic_stream


def _assert_exact(server: ServerProcess, agent_id: str, truth: StreamTruth) -> None:
    m = map_of(server, agent_id)
    assert (m["keyframes"], m["points"]) == (len(truth.kf_poses), len(truth.points))
    kfs = server.json(f"/maps/{m['id']}/keyframes", limit=10000)["keyframes"]
    assert sorted(k["id"] for k in kfs) == sorted(truth.kf_poses), "each keyframe exactly once"
    for k in kfs:  # float64 end to end: exact up to nothing
        np.testing.assert_allclose(np.array(k["world_from_cam"]), truth.kf_poses[k["id"]], atol=1e-12)
    info = server.json(f"/agents/{agent_id}")
    assert info["pending_keyframes"] == 0


def _resume(server: ServerProcess, agent_id: str, msgs: list, acked_before: int) -> tuple[SyncAgent, int]:
    ag = SyncAgent(server.ws_url, agent_id, TOKENS[agent_id])
    last = ag.welcome().last_seq
    assert last >= acked_before, f"server lost acknowledged messages: last_seq {last} < acked {acked_before}"
    assert last <= len(msgs)
    return ag, last


def _send_rest(ag: SyncAgent, msgs: list, last: int) -> None:
    acks, errors = ag.send_all(msgs[last:], last + 1)
    assert not errors, errors
    assert acks == list(range(last + 1, len(msgs) + 1))


@pytest.fixture
def server(tmp_path: Path) -> ServerProcess:
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def test_server_sigkill_mid_stream_then_restart(server: ServerProcess) -> None:
    msgs, truth = synthetic_stream("uav1", 60, features=300, seed=21, kf_before_points_every=4)
    ag = SyncAgent(server.ws_url, "uav1", TOKENS["uav1"])
    ag.welcome()
    acked = 0
    for i, m in enumerate(msgs[: len(msgs) // 2]):
        ag.send(m, i + 1)
    # Read some acks, then kill the server while messages are still in flight.
    while acked < len(msgs) // 4:
        r = ag.recv()
        assert isinstance(r, Ack)
        acked = max(acked, r.seq)
    server.kill()
    try:
        while True:
            r = ag.recv(timeout=2)
            if isinstance(r, Ack):
                acked = max(acked, r.seq)
    except (ConnectionClosed, TimeoutError):
        pass
    ag.close()
    server.start()
    ag, last = _resume(server, "uav1", msgs, acked)
    _send_rest(ag, msgs, last)
    ag.close()
    _assert_exact(server, "uav1", truth)
    # And once more after a clean restart: everything reloads.
    server.stop()
    server.start()
    _assert_exact(server, "uav1", truth)
    assert server.json("/agents/uav1")["last_seq"] == len(msgs)


def test_agent_link_dropped_repeatedly(server: ServerProcess) -> None:
    msgs, truth = synthetic_stream("uav2", 40, features=200, seed=22, kf_before_points_every=3)
    rng = np.random.default_rng(0)
    acked = 0
    drops = 0
    while True:
        ag, last = _resume(server, "uav2", msgs, acked)
        if last == len(msgs):
            ag.close()
            break
        # Send a random chunk without waiting for all acks, then drop the TCP connection abruptly.
        chunk = msgs[last : last + int(rng.integers(3, 15))]
        for i, m in enumerate(chunk):
            ag.send(m, last + 1 + i)
        try:
            r = ag.recv(timeout=0.05)
            if isinstance(r, Ack):
                acked = max(acked, r.seq)
        except TimeoutError:
            pass
        ag.ws.socket.close()  # no close handshake
        drops += 1
        assert drops < 200
    assert drops >= 5
    _assert_exact(server, "uav2", truth)


AGENT_SCRIPT = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    from agent_client import SyncAgent
    from hivemap.server.loadgen import synthetic_stream
    msgs, _ = synthetic_stream("ugv1", 50, features=200, seed=23, kf_before_points_every=5)
    ag = SyncAgent({url!r}, "ugv1", {token!r}, kind="ugv")
    last = ag.welcome().last_seq
    print("resume", last, flush=True)
    for i in range(last, len(msgs)):
        ag.send(msgs[i], i + 1)
        time.sleep(0.02)
    acks, errors = 0, 0
    while acks < len(msgs) - last:
        ag.recv(); acks += 1
    print("done", flush=True)
    """
)


def test_agent_process_killed_and_restarted(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("ugv1", 50, features=200, seed=23, kf_before_points_every=5)
    script = tmp_path / "agent.py"
    script.write_text(
        AGENT_SCRIPT.format(tests=str(Path(__file__).parent), url=server.ws_url, token=TOKENS["ugv1"])
    )
    resumed = []
    for _ in range(3):
        p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE)
        assert p.stdout is not None
        line = p.stdout.readline().split()
        resumed.append(int(line[1]))
        time.sleep(0.4)  # mid-stream: the script sends one message every 20 ms, ~2.3 s in all
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        p.stdout.close()
    final = subprocess.run([sys.executable, str(script)], capture_output=True, timeout=120, check=True)
    assert b"done" in final.stdout
    resumed.append(int(final.stdout.split()[1]))
    # Each restart resumed where the server's durable state ended, further each time, never past the end.
    assert resumed[0] == 0 and all(a < b for a, b in zip(resumed, resumed[1:], strict=False)), resumed
    assert resumed[-1] < len(msgs)
    _assert_exact(server, "ugv1", truth)
