"""A small synchronous agent for the server tests (real WebSocket, protocol codec)."""

from __future__ import annotations

from typing import Any

from websockets.sync.client import ClientConnection, connect

from hivemap.protocol import Ack, Message, Welcome, decode, encode
from hivemap.protocol import Error as ErrorMsg
from hivemap.server.loadgen import hello


class SyncAgent:
    def __init__(
        self,
        ws_url: str,
        agent_id: str,
        token: str,
        session: int = 0,
        kind: str = "uav",
        mission: str | None = None,
    ) -> None:
        self.url = ws_url
        self.ws: ClientConnection = connect(
            ws_url, max_size=None, compression=None, open_timeout=10, legacy=True
        )
        self.agent_id, self.token, self.session, self.kind = agent_id, token, session, kind
        self.mission = mission  # None: one fixed mission per agent id, so reconnects resume it
        self.bytes_sent = 0
        self.others: list[Message] = []  # what send_all received besides acks and errors (corrections)

    def send_raw(self, frame: bytes) -> None:
        self.ws.send(frame)
        self.bytes_sent += len(frame)

    def send(self, msg: Message, seq: int) -> None:
        self.send_raw(encode(msg, seq))

    def recv(self, timeout: float = 10.0) -> Message:
        frame = self.ws.recv(timeout=timeout)
        assert isinstance(frame, bytes)
        return decode(frame)[1]

    def hello(self, resume_from: int = 0) -> Message:
        self.send(hello(self.agent_id, self.token, self.kind, self.session, resume_from, self.mission), 0)
        return self.recv()

    def welcome(self) -> Welcome:
        """Hello until welcomed; a server still loading its store says "unavailable" (a real agent
        reconnects with backoff), so this reconnects for up to 20 s."""
        import time

        deadline = time.monotonic() + 20.0
        msg = self.hello()
        while isinstance(msg, ErrorMsg) and msg.code == "unavailable" and time.monotonic() < deadline:
            time.sleep(0.05)
            self.ws.close()
            self.ws = connect(self.url, max_size=None, compression=None, open_timeout=10, legacy=True)
            msg = self.hello()
        assert isinstance(msg, Welcome), msg
        return msg

    def send_all(self, msgs: list[Message], first_seq: int = 1) -> tuple[list[int], list[ErrorMsg]]:
        """Send, then wait for one ack or error per message; returns (acked seqs, errors)."""
        for i, m in enumerate(msgs):
            self.send(m, first_seq + i)
        acks: list[int] = []
        errors: list[ErrorMsg] = []
        while len(acks) + len(errors) < len(msgs):
            r = self.recv()
            if isinstance(r, Ack):
                acks.append(r.seq)
            elif isinstance(r, ErrorMsg):
                errors.append(r)
            else:
                self.others.append(r)
        return acks, errors

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> SyncAgent:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
