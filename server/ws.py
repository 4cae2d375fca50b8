"""The agents' WebSocket endpoint (protocol v1): one :class:`AgentConnection` per socket.

Flow: the first frame must be ``hello`` with the agent's token -> ``welcome(last_seq)``; then data messages,
each acknowledged after it is durably stored. Bad frames get an ``error`` naming the field and change nothing.
A refused hello gets an ``error`` and the socket is closed with 1008 (policy violation); so does a socket
that sends no hello within ``hello_timeout_s`` (code ``hello_timeout``). While the server loads its store a
hello waits up to ``hello_loading_wait_s``, then gets a transient ``unavailable`` error and a 1013 close
(the agent retries). Data messages may be
refused with ``quota`` (a per-agent total; final) or ``rate`` (too fast; transient), see
:mod:`hivemap.server.quotas`, and a seq more than ``max_seq_step`` past the agent's last is refused naming
``seq``.

Back-pressure: uvicorn reads one frame at a time (the sans-I/O protocol pauses the socket until the app has
taken the frame), this handler applies one message at a time and waits when too many are uncommitted, and
the outgoing queue is bounded: an agent that does not read its acks is disconnected, not buffered forever.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Any

from starlette.websockets import WebSocket, WebSocketDisconnect

from hivemap.protocol import (
    Bye,
    FieldError,
    FrameTooLarge,
    Hello,
    Limits,
    Message,
    ProtocolError,
    TeamAdvisory,
    UnknownTypeError,
    VersionError,
    carries,
    decode_versioned,
    downgrade,
    encode,
)
from hivemap.protocol import Error as ErrorMsg
from hivemap.protocol.limits import PROTOCOL_VERSION
from hivemap.server.core import AgentState, HiveServer, Rejected

logger = logging.getLogger(__name__)

POLICY_VIOLATION = 1008
TRY_AGAIN_LATER = 1013
# after refusing a message for a quota the reader pauses this long, so an agent over its quota is slowed
# down (TCP back-pressure) instead of keeping the event loop busy with messages that will be refused
QUOTA_PAUSE_S = 0.02


def _error_code(exc: ProtocolError) -> str:
    if isinstance(exc, VersionError):
        return "version"
    if isinstance(exc, UnknownTypeError):
        return "unknown_type"
    if isinstance(exc, FrameTooLarge):
        return "too_large"
    if isinstance(exc, FieldError):
        return "bad_field"
    return "protocol"


class _Close:
    def __init__(self, code: int, reason: str) -> None:
        self.code = code
        self.reason = reason.encode()[:120].decode(errors="ignore")  # a close reason is limited to 123 bytes


class AgentConnection:
    def __init__(self, websocket: WebSocket, server: HiveServer) -> None:
        self.ws = websocket
        self.server = server
        self.agent_id: str | None = None
        self.mission: str | None = None  # set by HiveServer.attach once the hello is accepted
        self.replaced = False
        s = server.settings
        self.limits = Limits(max_frame_bytes=s.max_frame_bytes)
        self._outbox: asyncio.Queue[Any] = asyncio.Queue(maxsize=s.outbox_max)
        self._out_seq = 0
        # the protocol version of the agent's hello: what it is sent in (an older agent gets frames it reads)
        self.peer_version = PROTOCOL_VERSION
        self.peer_team_advisories = False  # the hello asked for team advisories (protocol v4)
        self._closing = False
        self._overflow = False
        self._task: asyncio.Task[Any] | None = None

    @property
    def agent(self) -> AgentState | None:
        return self.server.agents.get(self.agent_id) if self.agent_id is not None else None

    # -- outgoing -----------------------------------------------------------------------------------
    def send(self, msg: Message) -> bool:
        """Queue a message for the agent. False if the connection is closing, or if the agent cannot read
        the message (a type newer than its hello's version, a team advisory it did not ask for: an unknown
        type would be a protocol error to it); a full queue drops the agent."""
        if self._closing:
            return False
        if not carries(self.peer_version, msg.TYPE) or (
            isinstance(msg, TeamAdvisory) and not self.peer_team_advisories
        ):
            logger.debug("not sending %s to %s (protocol v%d)", msg.TYPE, self.agent_id, self.peer_version)
            return False
        try:
            self._outbox.put_nowait(msg)
            return True
        except asyncio.QueueFull:
            self._drop("slow consumer: outgoing queue full")
            return False

    async def close(self, code: int, reason: str) -> None:
        """Close after the messages already queued (non-blocking)."""
        if self._closing:
            return
        self._closing = True
        try:
            self._outbox.put_nowait(_Close(code, reason))
        except asyncio.QueueFull:
            self._drop(reason)

    def _drop(self, reason: str) -> None:
        """Abandon the connection without a close handshake (used when the agent doesn't read)."""
        logger.warning("dropping connection of %s: %s", self.agent_id, reason)
        self._closing = True
        self._overflow = True
        self.server.events.add("error", f"{self.agent_id}: {reason}", agent_id=self.agent_id)
        if self._task is not None and not self._task.done():
            self._task.cancel()

    async def _send_loop(self) -> None:
        try:
            while True:
                item = await self._outbox.get()
                if isinstance(item, _Close):
                    await self.ws.close(item.code, item.reason)
                    return
                self._out_seq += 1
                frame = encode(downgrade(item, self.peer_version), self._out_seq, self.peer_version)
                await self.ws.send_bytes(frame)
                agent = self.agent
                if agent is not None and not self.replaced:
                    agent.bandwidth.sent(len(frame))
        except (WebSocketDisconnect, RuntimeError, OSError) as e:
            # the agent went away mid-send (uvicorn: ClientDisconnected, an OSError; starlette: a
            # RuntimeError after close); on reconnect the welcome's last_seq replaces the lost acks
            logger.debug("send to %s ended: %s", self.agent_id, type(e).__name__)

    def _reply_error(self, code: str, message: str, field: str | None, seq: int | None) -> None:
        self.send(ErrorMsg(code=code, message=message[:1000], field=field, seq=seq))

    # -- incoming -----------------------------------------------------------------------------------
    async def run(self) -> None:
        await self.ws.accept()
        self._task = asyncio.current_task()
        sender = asyncio.create_task(self._send_loop())
        hello_deadline = time.monotonic() + self.server.settings.hello_timeout_s
        try:
            while True:
                if self.agent_id is None and not self._closing:
                    event = await self._receive_before_hello(hello_deadline)
                    if event is None:
                        break
                else:
                    event = await self.ws.receive()
                if event["type"] == "websocket.disconnect":
                    break
                data = event.get("bytes")
                if data is None:
                    self.server.rejected_frames += 1
                    self._reply_error("bad_frame", "frames must be binary (msgpack), not text", None, None)
                    continue
                if self._closing:
                    continue
                await self._on_frame(data)
                # yield to the other connections: with frames already buffered, receive() returns without
                # suspending, and one agent sending as fast as it can starved the others (acks took
                # seconds in bench/flood.py)
                await asyncio.sleep(0)
        except WebSocketDisconnect:
            pass
        except asyncio.CancelledError:
            if not self._overflow:
                raise
            task = asyncio.current_task()
            if task is not None:
                task.uncancel()
        finally:
            self.server.detach(self)
            if not sender.done():
                if self._overflow or not self._closing:
                    sender.cancel()  # nothing left worth delivering (or the agent doesn't read)
                # else give the close frame queued by close() a moment to go out
                with contextlib.suppress(asyncio.CancelledError, TimeoutError, Exception):
                    await asyncio.wait_for(sender, timeout=1.0)

    async def _receive_before_hello(self, deadline: float) -> Any:
        """The next event, or None (after queueing a close) when no hello came within the hello timeout:
        a socket that never says who it is must not stay open forever."""
        try:
            return await asyncio.wait_for(self.ws.receive(), max(deadline - time.monotonic(), 0.0))
        except TimeoutError:
            t = self.server.settings.hello_timeout_s
            reason = f"no hello within hello_timeout_s = {t:g} s"
            self.server.events.add("refused", reason, agent_id=None)
            logger.warning("closing connection: %s", reason)
            self._reply_error("hello_timeout", reason, "type", None)
            await self.close(POLICY_VIOLATION, reason)
            return None

    async def _on_frame(self, data: bytes) -> None:
        received_at = time.monotonic()
        agent = self.agent
        if agent is not None:
            agent.bandwidth.received(len(data))
        try:
            version, seq, msg = decode_versioned(data, self.limits)
        except ProtocolError as exc:
            self.server.rejected_frames += 1
            if agent is not None:
                agent.errors += 1
            self._reply_error(_error_code(exc), str(exc), exc.field, None)
            return
        if self.agent_id is None:
            if isinstance(msg, Hello):
                self.peer_version = version
                self.peer_team_advisories = msg.team_advisories
            await self._on_hello(seq, msg)
            if self.agent is not None:
                self.agent.bandwidth.received(len(data))
            return
        if isinstance(msg, Hello):
            self._reply_error(
                "already_authenticated", "hello was already accepted on this connection", "type", seq
            )
            return
        if isinstance(msg, Bye):  # not stored, not acked: the agent leaves
            # the mission's last optimisation is asked for before the socket closes, so that an agent
            # polling /health after its close sees it running
            try:
                if self.agent_id is not None:
                    await self.server.agent_said_bye(self.agent_id)
            finally:
                await self.close(1000, f"bye: {msg.reason}")
            return
        try:
            await self.server.handle(self, seq, msg, received_at)
        except Rejected as r:
            if agent is not None:
                agent.errors += 1
            if r.code not in ("quota", "rate"):  # those publish their own (rate-limited) "quota" event
                self.server.events.add(
                    "error", f"{self.agent_id} seq {seq}: {r.message}", agent_id=self.agent_id
                )
            self._reply_error(r.code, r.message, r.field, seq)
            if r.code in ("quota", "rate"):
                await asyncio.sleep(QUOTA_PAUSE_S)

    async def _on_hello(self, seq: int, msg: Message) -> None:
        if not isinstance(msg, Hello):
            self._reply_error(
                "hello_required",
                f"the first message must be 'hello', got '{type(msg).__name__}'",
                "type",
                seq,
            )
            return
        reason = self.server.authenticate(msg)
        if reason is None and self.server.loading:  # a short start-up is waited out
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.server.loaded.wait(), self.server.settings.hello_loading_wait_s)
        if reason is None and self.server.loading:
            # transient for the agent ("unavailable"): it reconnects with backoff until the store is loaded
            why = "server is loading its store; retry shortly"
            self._reply_error("unavailable", why, None, seq)
            await self.close(TRY_AGAIN_LATER, why)
            return
        if reason is not None:
            self.server.events.add("refused", reason, agent_id=None)
            logger.warning("refused connection: %s", reason)
            self._reply_error("unauthorized", reason, "body.token", seq)
            await self.close(POLICY_VIOLATION, reason)
            return
        self.agent_id = msg.agent_id
        try:
            await self.server.attach(self, msg)  # sends the welcome
        except Rejected as r:
            self.agent_id = None
            self.mission = None
            self._reply_error(r.code, r.message, r.field, seq)


async def agent_endpoint(websocket: WebSocket) -> None:
    """ASGI WebSocket route: ``/ws``."""
    server: HiveServer = websocket.app.state.hive
    await AgentConnection(websocket, server).run()
