"""Fault injection on the tiny scenario with real processes: `hivemap server` (no back-end, so nothing but
the agent may move a stored keyframe) and `hivemap agent` replaying one UAV, over a real WebSocket.

After each fault the stored maps are compared with the agents' own records (their outboxes): 0 keyframes
lost, 0 stored twice, 0 changed, nothing foreign; and the map stack is the same after one more restart.
The suite's other rows live beside it: two missions of one agent id with one and with two ``--out``
folders, an unknown resumed mission, and the restart of a server that has fused points
(``test_missions.py``).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mission_records import Comparison, agent_record, compare
from srv_helpers import TOKENS, ServerProcess, write_config


def _agent(dataset: Path, server: ServerProcess, out: Path) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "hivemap.cli.main", "agent", "--dataset", str(dataset),
           "--server", server.ws_url, "--agent-id", "uav1", "--token", TOKENS["uav1"], "--out", str(out),
           "--no-progress", "--wait-corrections", "0", "--max-connect-attempts", "50"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _stored_seq(server: ServerProcess) -> int:
    try:
        return int(server.json("/agents/uav1")["last_seq"])
    except Exception:
        return 0


def _wait_seq(server: ServerProcess, seq: int, proc: subprocess.Popen[str], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while _stored_seq(server) < seq:
        assert proc.poll() is None, f"the agent ended before seq {seq}: {proc.communicate()[1][-2000:]}"
        assert time.monotonic() < deadline, f"seq {seq} never stored"
        time.sleep(0.05)


def _finish(proc: subprocess.Popen[str], timeout: float = 300.0) -> tuple[str, str]:
    """Wait for the agent; its exit code must be 0. Returns (stdout, stderr)."""
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return out, err


def _restart_and_compare(server: ServerProcess, outbox: Path) -> tuple[Comparison, bool, int]:
    """Compare the store with the agent's record, restart once more: (comparison, the same map stack
    after the restart, messages the agent still has unacknowledged)."""
    digest = server.json("/maps/digest")["digests"]
    server.stop()
    c = compare([agent_record(outbox, "uav1")], server.data_dir / "hivemap.sqlite", "uav1")
    server.start()
    return c, server.json("/maps/digest")["digests"] == digest, agent_record(outbox, "uav1").unacked


@pytest.fixture
def server(tmp_path: Path):  # type: ignore[no-untyped-def]
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def test_server_killed_at_three_points_of_a_stream(
    tiny_uav: Path, server: ServerProcess, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    proc = _agent(tiny_uav, server, out)
    survived = []
    try:
        for seq in (3, 12, 25):  # early, mid-stream, late (this run sends ~40 messages)
            _wait_seq(server, seq, proc)
            acked = _stored_seq(server)
            server.kill()
            time.sleep(0.5)
            server.start()
            survived.append(_stored_seq(server) >= acked)  # what was acknowledged outlives the kill
        _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert survived == [True, True, True]
    c, same_after_restart, unacked = _restart_and_compare(server, out / "outbox.sqlite")
    assert c.clean, c
    assert same_after_restart and unacked == 0
    assert agent_record(out / "outbox.sqlite", "uav1").keyframe_messages > 5


def test_agent_killed_then_restarted_resumes_its_mission(
    tiny_uav: Path, server: ServerProcess, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    proc = _agent(tiny_uav, server, out)
    _wait_seq(server, 20, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    mission = agent_record(out / "outbox.sqlite", "uav1").mission
    _, err = _finish(_agent(tiny_uav, server, out))  # resumes the mission: delivers the rest, new session
    assert "resumes mission" in err
    rec = agent_record(out / "outbox.sqlite", "uav1")
    assert rec.mission == mission and {k[1] for k in rec.poses} == {0, 1}
    c, same_after_restart, unacked = _restart_and_compare(server, out / "outbox.sqlite")
    assert c.clean, c
    assert same_after_restart and unacked == 0


def test_sigterm_of_the_agent_and_of_the_server(
    tiny_uav: Path, server: ServerProcess, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    proc = _agent(tiny_uav, server, out)
    _wait_seq(server, 20, proc)
    proc.send_signal(signal.SIGTERM)
    last, _ = _finish(proc, timeout=60)  # exit 0; the last line says what stays unsent
    assert "stopped by SIGTERM" in last.splitlines()[-1] and "unsent" in last.splitlines()[-1]
    assert server.proc is not None
    server.proc.send_signal(signal.SIGTERM)
    assert server.proc.wait(30) == 0
    server.start()
    _finish(_agent(tiny_uav, server, out))
    c, same_after_restart, unacked = _restart_and_compare(server, out / "outbox.sqlite")
    assert c.clean, c
    assert same_after_restart and unacked == 0
