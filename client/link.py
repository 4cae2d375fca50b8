"""The agent's link to the server: a resumable WebSocket session over protocol v1.

Every message goes through the durable :class:`~hivemap.client.outbox.Outbox` first. On (re)connect
the link sends ``hello`` naming the outbox's mission; the server's ``welcome(last_seq)`` says what it
already stored of that mission, so the link resends the rest in order: no loss and no duplicates across
agent or server restarts and dropped connections. A server that does not know the mission
(``mission_known`` false) gets the whole outbox again. Reconnects use exponential backoff with jitter.
A refused hello (bad token) stops the link with :class:`LinkRefused` instead of retrying forever.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import websockets
from websockets.exceptions import ConnectionClosed

from hivemap.client.outbox import Outbox
from hivemap.protocol import (
    Ack,
    Correction,
    Hello,
    Message,
    ProtocolError,
    TeamAdvisory,
    Welcome,
    decode,
    encode,
)
from hivemap.protocol import Bye as ByeMsg
from hivemap.protocol import Error as ErrorMsg

log = logging.getLogger(__name__)


class LinkRefused(RuntimeError):
    """The server refused this agent (token, agent id): retrying would not help."""


class LinkFailed(RuntimeError):
    """The server could not be reached (bad address, HTTP refusal, dead port) for
    ``LinkOptions.max_connect_attempts`` consecutive attempts, or the address is not a WebSocket URL."""


def check_server_url(url: str) -> str | None:
    """None if ``url`` can be a server's WebSocket address (``ws://HOST:PORT/ws``), else why not."""
    from urllib.parse import urlsplit

    u = urlsplit(url)
    if u.scheme not in ("ws", "wss"):
        return f"server address {url!r} needs a ws:// or wss:// scheme, e.g. ws://HOST:8765/ws"
    if not u.hostname:
        return f"server address {url!r} has no host, e.g. ws://HOST:8765/ws"
    return None


def _describe(exc: BaseException) -> str:
    """One line for a failed connection attempt (an HTTP status says which, with a hint for 403/404)."""
    status = getattr(getattr(exc, "response", None), "status_code", None)
    if status is not None:
        hint = " (is the path /ws, e.g. ws://HOST:8765/ws?)" if status in (403, 404) else ""
        return f"HTTP {status} on the WebSocket handshake{hint}"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


# Error codes that say "not now" rather than "never": the message stays in the outbox and the link
# reconnects, so the server's welcome decides what is resent. Any other error naming a seq is final
# (the server will never accept that message) and the message is dropped from the outbox.
TRANSIENT_ERROR_CODES = frozenset({"storage", "busy", "overloaded", "unavailable", "internal", "rate"})


class _Reconnect(Exception):
    """Internal: end this connection and resume on a new one."""


@dataclass(frozen=True)
class LinkOptions:
    backoff_initial_s: float = 0.2
    backoff_max_s: float = 10.0
    window: int = 64  # unacknowledged messages in flight per connection
    open_timeout_s: float = 10.0
    max_frame_bytes: int = 8 * 1024 * 1024
    # consecutive connection attempts that fail (no welcome) before run() gives up with LinkFailed; the
    # count restarts at every welcome, so a link that was up and drops gets as many again. With the
    # backoff above, 10 attempts span about a minute: a restarting server comes back within that.
    max_connect_attempts: int = 10


@dataclass
class LinkStats:
    connects: int = 0
    bytes_up: int = 0
    bytes_down: int = 0
    resent: int = 0
    corrections: int = 0
    errors: int = 0
    advisories: int = 0


class AgentLink:
    """Resumable agent -> server link. Use ``submit`` from the agent, ``run`` as a task."""

    def __init__(
        self,
        url: str,
        agent_id: str,
        kind: str,
        camera: dict[str, object],
        token: str,
        outbox_path: str | Path | Outbox,
        on_correction: Callable[[Correction], None] | None = None,
        session: int = 0,
        options: LinkOptions | None = None,
        cam_from_antenna: np.ndarray | None = None,
        stereo_baseline: float | None = None,
        on_team_advisory: Callable[[TeamAdvisory], None] | None = None,
    ) -> None:
        self.url = url
        # with a callback the hello asks the server for team advisories (goals, safe velocity)
        self.on_team_advisory = on_team_advisory
        self.last_advisory: TeamAdvisory | None = None
        self.stereo_baseline = stereo_baseline  # m, sent in the hello: the server's BA holds scale with it
        self.cam_from_antenna = cam_from_antenna  # (3,) GNSS lever arm in cam0, sent in the hello
        self.agent_id = agent_id
        self.kind = kind
        self.camera = camera
        self.token = token
        self.session = session
        self.on_correction = on_correction
        self.options = options or LinkOptions()
        self.outbox = outbox_path if isinstance(outbox_path, Outbox) else Outbox(outbox_path, agent_id)
        self.stats = LinkStats()
        self.connected = asyncio.Event()
        self._new = asyncio.Event()
        self._acked = asyncio.Event()
        self._stop = False
        self._stopped = asyncio.Event()
        self._ws: websockets.ClientConnection | None = None
        self._run_task: asyncio.Task[None] | None = None
        self.server_errors: list[ErrorMsg] = []
        self.unsent = 0  # messages left in the outbox at close() (unacknowledged; sent at the next start)
        self._closed = False

    # -- agent side ---------------------------------------------------------------------------------
    def submit_nowait(self, msg: Message) -> int:
        """Store ``msg`` durably and schedule it; returns its seq."""
        seq = self.outbox.put(msg)
        self._new.set()
        return seq

    async def submit(self, msg: Message) -> int:
        return await asyncio.to_thread(self.submit_nowait, msg)

    async def flush(self, timeout: float | None = None) -> None:
        """Wait until the server acknowledged everything submitted so far."""

        async def wait() -> None:
            while len(self.outbox):
                self._acked.clear()
                if not len(self.outbox):
                    break
                await self._acked.wait()

        await asyncio.wait_for(wait(), timeout)

    async def close(self, reason: str = "done") -> None:
        """Say bye and stop ``run``. Unacknowledged messages stay in the outbox for the next start."""
        if self._closed:
            return
        self._stop = True
        self._stopped.set()
        self._new.set()
        ws = self._ws
        if ws is not None:
            with contextlib.suppress(Exception):
                await ws.send(encode(ByeMsg(reason), 0))
                # bounded: a stalled server must not hold up a SIGTERM'd agent past its grace period
                await asyncio.wait_for(ws.close(), 2.0)
        task = self._run_task
        if task is not None and task is not asyncio.current_task() and not task.done():
            # Let run() leave (it may be between reconnect attempts) before the outbox goes away.
            with contextlib.suppress(BaseException):
                await asyncio.wait_for(asyncio.shield(task), 5.0)
        self.unsent = len(self.outbox)
        self._closed = True
        self.outbox.close()

    # -- connection loop ----------------------------------------------------------------------------
    async def run(self) -> None:
        """Connect, resume, stream; reconnect with backoff until ``close``. Raises LinkRefused, and
        LinkFailed after ``max_connect_attempts`` consecutive attempts that got no welcome."""
        self._run_task = asyncio.current_task()  # type: ignore[assignment]
        delay = self.options.backoff_initial_s
        failures = 0
        if (bad := check_server_url(self.url)) is not None:
            raise LinkFailed(bad)
        while not self._stop:
            try:
                await self._session()
                delay = self.options.backoff_initial_s
                failures = 0
            except LinkRefused:
                raise
            except websockets.InvalidURI as e:
                raise LinkFailed(f"server address {self.url!r} is not a WebSocket URL: {e}") from e
            except (
                OSError,
                ConnectionClosed,
                TimeoutError,
                ProtocolError,
                websockets.InvalidHandshake,
                _Reconnect,
            ) as e:
                if self._stop:
                    break
                failures = 0 if self.connected.is_set() else failures + 1  # connected: it was up
                if failures >= self.options.max_connect_attempts:
                    raise LinkFailed(
                        f"cannot connect to {self.url} after {failures} attempts: {_describe(e)}"
                    ) from e
                log.warning("link to %s lost (%s); reconnecting in %.1f s", self.url, _describe(e), delay)
            finally:
                self.connected.clear()
                self._ws = None
            if self._stop:
                break
            # Jittered exponential backoff: agents cut off together do not reconnect in lockstep.
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stopped.wait(), delay * (0.5 + random.random()))
            delay = min(delay * 2, self.options.backoff_max_s)

    async def _session(self) -> None:
        async with websockets.connect(
            self.url,
            max_size=self.options.max_frame_bytes,
            open_timeout=self.options.open_timeout_s,
            compression=None,
        ) as ws:
            self._ws = ws
            hello = Hello(
                self.agent_id, self.kind, self.camera, self.token, self.outbox.last_acked, self.session,
                self.cam_from_antenna, self.outbox.mission, self.stereo_baseline,
                self.on_team_advisory is not None,
            )  # fmt: skip
            await ws.send(encode(hello, 0))
            first = await asyncio.wait_for(ws.recv(), self.options.open_timeout_s)
            if not isinstance(first, bytes):
                raise ProtocolError("text frame from the server", "frame")
            _, reply = decode(first)
            if isinstance(reply, ErrorMsg) and reply.code in TRANSIENT_ERROR_CODES:
                raise _Reconnect(f"server not ready: {reply.message}")  # e.g. still loading its store
            if isinstance(reply, ErrorMsg):
                raise LinkRefused(f"server refused agent {self.agent_id!r}: {reply.message} ({reply.field})")
            if not isinstance(reply, Welcome):
                raise ProtocolError(f"expected welcome, got {type(reply).__name__}", "type")
            if not reply.mission_known or reply.last_seq < self.outbox.last_acked:
                # the server lacks (part of) this mission: what it acknowledged before is sent again
                n = await asyncio.to_thread(
                    self.outbox.reopen_after, reply.last_seq if reply.mission_known else 0
                )
                if n:
                    log.warning(
                        "server %s has %s of mission %s; re-sending %d acknowledged messages",
                        self.url,
                        f"seq <= {reply.last_seq}" if reply.mission_known else "no record",
                        self.outbox.mission,
                        n,
                    )
            await asyncio.to_thread(self.outbox.ack_through, reply.last_seq)
            self._acked.set()
            self.stats.connects += 1
            self.connected.set()
            log.info(
                "agent %s connected to %s; server has seq <= %d", self.agent_id, self.url, reply.last_seq
            )
            sender = asyncio.create_task(self._send_loop(ws, reply.last_seq))
            try:
                await self._recv_loop(ws)
            finally:
                sender.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                    await sender

    async def _send_loop(self, ws: websockets.ClientConnection, after: int) -> None:
        sent = after
        first_pass_end = self.outbox.last_seq
        while not self._stop:
            in_flight = sent - self.outbox.last_acked
            room = self.options.window - in_flight
            batch = await asyncio.to_thread(self.outbox.pending, sent, max(room, 0)) if room > 0 else []
            if not batch:
                self._new.clear()
                # Wake on new messages or acks (which open the window).
                waiters = [asyncio.create_task(self._new.wait()), asyncio.create_task(self._acked.wait())]
                self._acked.clear()
                _, pend = await asyncio.wait(waiters, timeout=1.0, return_when=asyncio.FIRST_COMPLETED)
                for p in pend:
                    p.cancel()
                continue
            for seq, frame in batch:
                await ws.send(frame)
                self.stats.bytes_up += len(frame)
                if seq <= first_pass_end:
                    self.stats.resent += 1
                sent = seq

    async def _recv_loop(self, ws: websockets.ClientConnection) -> None:
        async for frame in ws:
            if not isinstance(frame, bytes):
                raise ProtocolError("text frame from the server", "frame")
            self.stats.bytes_down += len(frame)
            _, msg = decode(frame)
            if isinstance(msg, Ack):
                await asyncio.to_thread(self.outbox.ack, msg.seq)
                self._acked.set()
            elif isinstance(msg, Correction):
                self.stats.corrections += 1
                if self.on_correction is not None:
                    try:
                        self.on_correction(msg)
                    except Exception:
                        log.exception("on_correction callback failed (map %d)", msg.map_id)
            elif isinstance(msg, TeamAdvisory):
                self.stats.advisories += 1
                self.last_advisory = msg
                if self.on_team_advisory is not None:
                    try:
                        self.on_team_advisory(msg)
                    except Exception:
                        log.exception("on_team_advisory callback failed (map %d)", msg.map_id)
            elif isinstance(msg, ErrorMsg):
                self.stats.errors += 1
                self.server_errors.append(msg)
                log.error(
                    "server error %s on seq %s, field %s: %s", msg.code, msg.seq, msg.field, msg.message
                )
                if msg.code in TRANSIENT_ERROR_CODES:
                    raise _Reconnect(f"transient server error {msg.code} on seq {msg.seq}")
                if msg.seq is not None and msg.seq > 0:
                    # The server will never accept this message: drop it so it is not resent forever.
                    await asyncio.to_thread(self.outbox.ack, msg.seq)
                    self._acked.set()
            elif isinstance(msg, ByeMsg):
                log.info("server said bye: %s", msg.reason)
                return
