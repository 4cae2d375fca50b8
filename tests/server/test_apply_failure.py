"""A message the server fails to apply (a bug, not bad input) is refused alone: the connection, the
back-pressure and every later message go on, and the agent is told not to resend it."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from hivemap.protocol import Ack, Keyframe, Message
from hivemap.protocol import Error as ErrorMsg
from hivemap.server.agents import Rejected
from hivemap.server.core import HiveServer
from hivemap.server.loadgen import hello, synthetic_stream
from hivemap.server.settings import ServerSettings


class _Conn:
    """The two things the core does with a connection: send to it and close it."""

    def __init__(self) -> None:
        self.agent_id: str | None = None
        self.mission: str | None = None
        self.replaced = False
        self.sent: list[Message] = []
        self.closed: list[str] = []

    def send(self, msg: Message) -> bool:
        self.sent.append(msg)
        return True

    async def close(self, code: int, reason: str) -> None:
        self.closed.append(f"{code} {reason}")


async def _run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[_Conn, list[Rejected], HiveServer]:
    # two back-pressure slots: leaking one per failure would block the third message after two failures
    settings = ServerSettings(data_dir=tmp_path, tokens={"uav1": "tok"}, max_uncommitted=2)
    srv = HiveServer(settings)
    await srv.start()
    conn = _Conn()
    h = hello("uav1", "tok", "uav", 0, 0, "mission-1")
    assert srv.authenticate(h) is None
    conn.agent_id = "uav1"
    await srv.attach(conn, h)
    msgs, _ = synthetic_stream("uav1", 6, seed=3)
    real_apply = srv._apply
    n_kf = 0

    def failing_apply(agent: Any, mission: str, msg: Message) -> Any:
        nonlocal n_kf
        if isinstance(msg, Keyframe):
            n_kf += 1
            if n_kf in (2, 3):  # two keyframes meet a bug
                raise RuntimeError("cycle in the spanning tree")
        return real_apply(agent, mission, msg)

    monkeypatch.setattr(srv, "_apply", failing_apply)
    refused: list[Rejected] = []
    for seq, m in enumerate(msgs, start=1):
        try:
            await asyncio.wait_for(srv.handle(conn, seq, m, 0.0), 10.0)
        except Rejected as r:
            refused.append(r)
    for _ in range(200):  # acks follow the commits of the writer thread
        if sum(isinstance(s, Ack) for s in conn.sent) == len(msgs) - len(refused):
            break
        await asyncio.sleep(0.05)
    assert conn.closed == []  # open throughout
    await srv.stop()
    return conn, refused, srv


def test_a_message_the_server_fails_to_apply_is_refused_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    conn, refused, srv = asyncio.run(_run(tmp_path, monkeypatch))
    failed = [r for r in refused if r.code == "apply_failed"]
    assert len(failed) == 2
    assert all("cycle in the spanning tree" in r.message and "Keyframe" in r.message for r in failed)
    # a later pose update naming a refused keyframe is refused as for any unknown keyframe
    assert {r.code for r in refused} <= {"apply_failed", "unknown_id"}
    acks = [s.seq for s in conn.sent if isinstance(s, Ack)]
    n_msgs = len(synthetic_stream("uav1", 6, seed=3)[0])
    assert len(acks) == n_msgs - len(refused) >= n_msgs - 3  # the others applied and acknowledged, in order
    assert acks == sorted(acks)
    # the agent drops a refused message instead of reconnecting: the code is not a transient one
    from hivemap.client.link import TRANSIENT_ERROR_CODES

    assert "apply_failed" not in TRANSIENT_ERROR_CODES
    assert not [s for s in conn.sent if isinstance(s, ErrorMsg)]  # the reply is the ws layer's job
    kfs = sum(len(m.keyframes) for m in srv.stack.maps.values())
    assert kfs == 4
