"""Agent link without the hivemap server: the durable outbox (real SQLite files, a real SIGKILLed process)
and AgentLink against a small in-test WebSocket server that speaks protocol v1 over a real loopback
socket and misbehaves on purpose (drops connections, refuses, reports errors, sends corrections)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import websockets
from websockets.asyncio.server import ServerConnection, serve

from hivemap.client.link import AgentLink, LinkOptions, LinkRefused
from hivemap.client.outbox import Outbox, OutboxError
from hivemap.maps.camera import PinholeCamera
from hivemap.protocol import (
    Ack,
    Bye,
    Correction,
    Error,
    Hello,
    MapPoints,
    Message,
    Welcome,
    decode,
    encode,
)

CAMERA = PinholeCamera(640, 480, 400.0, 400.0, 320.0, 240.0).to_dict()
TOKEN = "secret"
# fast retries: the attempt bound is not what these tests are about (test_link_faults covers it)
FAST = LinkOptions(
    backoff_initial_s=0.01, backoff_max_s=0.05, window=16, open_timeout_s=5.0, max_connect_attempts=1000
)


def _msg(i: int) -> MapPoints:
    """Message number i (1-based), recognisable on arrival by its point id and coordinates."""
    rng = np.random.default_rng(i)
    return MapPoints(
        np.array([i], np.int64), rng.normal(size=(1, 3)), rng.integers(0, 256, (1, 32), dtype=np.uint8)
    )


# --- outbox -----------------------------------------------------------------------------------------


def test_outbox_assigns_increasing_seqs_and_forgets_only_acked(tmp_path: Path) -> None:
    box = Outbox(tmp_path / "a.outbox", "uav1")
    seqs = [box.put(_msg(i)) for i in range(1, 11)]
    assert seqs == list(range(1, 11))
    box.ack(3)
    box.ack(1)
    assert [s for s, _ in box.pending()] == [2, 4, 5, 6, 7, 8, 9, 10]
    assert box.last_acked == 3  # the highest acknowledged seq, not the last ack received
    box.ack_through(6)
    pending = box.pending()
    assert [s for s, _ in pending] == [7, 8, 9, 10]
    assert box.pending(after=8, limit=1)[0][0] == 9
    # frames are stored encoded with their seq: decoding gives back the message
    seq, msg = decode(pending[0][1])
    assert seq == 7 and isinstance(msg, MapPoints) and msg.ids.tolist() == [7]
    box.close()
    box = Outbox(tmp_path / "a.outbox", "uav1")  # reopen: same content, seqs continue, never reused
    assert (box.last_seq, box.last_acked, len(box)) == (10, 6, 4)
    assert box.put(Ack(0)) == 11
    box.ack_through(11)
    assert len(box) == 0 and box.put(Ack(0)) == 12
    box.close()
    with pytest.raises(OutboxError, match="belongs to agent 'uav1'"):
        Outbox(tmp_path / "a.outbox", "uav2")


PUTTER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from hivemap.client.outbox import Outbox
    from hivemap.protocol import MapPoints
    box = Outbox(sys.argv[1], "uav1")
    i = box.last_seq
    while True:
        i += 1
        seq = box.put(MapPoints(np.array([i]), np.zeros((1, 3)), np.zeros((1, 32), np.uint8)))
        if seq % 3 == 0:
            box.ack(seq - 2)
        print(seq, flush=True)
    """
)


@pytest.mark.timeout(60)
def _open_outbox(path: str, barrier: object) -> None:
    barrier.wait()  # type: ignore[attr-defined]
    Outbox(path, "uav1").close()


def test_outbox_created_by_several_processes_at_once(tmp_path: Path) -> None:
    """Processes that open a new outbox file at the same moment (a restarted agent while something reads
    its outbox) all get it: none fails on SQLite's lock or on the meta rows another one just wrote."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    for trial in range(6):
        path = str(tmp_path / f"race{trial}.sqlite")
        barrier = ctx.Barrier(3)
        procs = [ctx.Process(target=_open_outbox, args=(path, barrier)) for _ in range(3)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(60)
        assert [p.exitcode for p in procs] == [0, 0, 0], f"trial {trial}"
        box = Outbox(path, "uav1")
        assert (box.last_seq, box.last_acked) == (0, 0)
        box.close()


def test_outbox_survives_sigkill_of_the_agent_process(tmp_path: Path) -> None:
    """Every put() that returned before a SIGKILL is on disk afterwards, with its seq and content."""
    path = tmp_path / "k.outbox"
    script = tmp_path / "putter.py"
    script.write_text(PUTTER)
    reported = 0
    kills = []  # the last seq each killed process reported
    for _ in range(2):  # kill twice: the second process continues from the first one's outbox
        p = subprocess.Popen([sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True)
        assert p.stdout is not None
        got = []
        for line in p.stdout:
            got.append(int(line))
            if len(got) >= 40:
                break
        p.kill()
        p.wait(10)
        assert got[0] > reported  # seqs continue across processes, none reused (some were put unreported)
        reported = got[-1]
        kills.append(reported)
    box = Outbox(path, "uav1")
    assert box.last_seq >= reported
    rows = dict(box.pending())
    for seq in range(1, reported + 1):
        if seq % 3 != 1:  # every third put acked the one two before it: gone; all others kept
            _, msg = decode(rows[seq])
            assert isinstance(msg, MapPoints) and msg.ids.tolist() == [seq]
        else:
            # (unless its process was killed before the put that acks it: within two of a kill)
            assert seq not in rows or any(seq <= k < seq + 2 for k in kills)
    box.close()


# --- a tiny protocol v1 server ------------------------------------------------------------------------


@dataclass
class MiniServer:
    """Stores data messages in memory (``stored``: seq -> message), acks each one, and misbehaves on
    request: ``drop_every`` k-th data message on a connection it drops the link (alternately after
    storing but before acking, and before storing; alternately a clean close and a TCP abort)."""

    drop_every: int = 0
    on_data: Callable[[MiniServer, ServerConnection, int, Message], object] | None = None
    stored: dict[int, Message] = field(default_factory=dict)
    order: list[int] = field(default_factory=list)
    hellos: list[Hello] = field(default_factory=list)
    duplicates: int = 0
    drops: int = 0
    byes: int = 0

    @property
    def last_seq(self) -> int:
        return max(self.stored, default=0)

    async def handler(self, ws: ServerConnection) -> None:
        _, hello = decode(await ws.recv())  # type: ignore[arg-type]
        assert isinstance(hello, Hello)
        if hello.token != TOKEN:
            await ws.send(encode(Error("unauthorized", "bad token", "body.token", 0), 0))
            await ws.close(1008, "bad token")
            return
        self.hellos.append(hello)
        last = self.last_seq
        await ws.send(encode(Welcome(last, "mini"), 0))
        n = 0
        async for frame in ws:
            seq, msg = decode(frame)  # type: ignore[arg-type]
            if isinstance(msg, Bye):
                self.byes += 1
                return
            if seq in self.stored:
                self.duplicates += 1
                await ws.send(encode(Ack(seq), 0))
                continue
            if self.on_data is not None and await self.on_data(self, ws, seq, msg):  # type: ignore[misc]
                if ws.close_code is not None:
                    # the hook closed the session: frames the agent had already pipelined behind it
                    # must not be stored (under load they were, before the resent message)
                    return
                continue  # the hook replied itself
            n += 1
            drop = self.drop_every and n % self.drop_every == 0
            if drop and self.drops % 2 == 1:  # drop before storing: the message is lost in transit
                await self._drop(ws)
                return
            self.stored[seq] = msg
            self.order.append(seq)
            if drop:  # stored but the ack never arrives
                await self._drop(ws)
                return
            await ws.send(encode(Ack(seq), 0))

    async def _drop(self, ws: ServerConnection) -> None:
        self.drops += 1
        if self.drops % 4 < 2:
            ws.transport.abort()  # the network vanishes
        else:
            await ws.close()


@contextlib.asynccontextmanager
async def running(server: MiniServer, port: int = 0):  # type: ignore[no-untyped-def]
    async with serve(server.handler, "127.0.0.1", port, compression=None) as s:
        yield f"ws://127.0.0.1:{s.sockets[0].getsockname()[1]}"


def _link(url: str, tmp_path: Path, token: str = TOKEN, **kw: object) -> AgentLink:
    return AgentLink(url, "uav1", "uav", CAMERA, token, tmp_path / "uav1.outbox", options=FAST, **kw)  # type: ignore[arg-type]


def _assert_exactly_once_in_order(server: MiniServer, n: int, missing: frozenset[int] = frozenset()) -> None:
    want = [i for i in range(1, n + 1) if i not in missing]
    assert server.order == want  # stored in seq order, each once
    assert server.duplicates == 0  # the link never resent what the welcome said was stored
    for seq in want:
        msg = server.stored[seq]
        assert isinstance(msg, MapPoints)
        np.testing.assert_array_equal(msg.xyz, _msg(seq).xyz)  # the content of message `seq`


@pytest.mark.timeout(60)
def test_link_delivers_exactly_once_in_order_through_repeated_drops(tmp_path: Path) -> None:
    server = MiniServer(drop_every=7)
    n = 300

    async def main() -> None:
        async with running(server) as url:
            link = _link(url, tmp_path)
            task = asyncio.create_task(link.run())
            for i in range(1, n + 1):
                assert await link.submit(_msg(i)) == i
                if i % 25 == 0:
                    await asyncio.sleep(0.01)  # let some go out while more are produced
            await link.flush(timeout=30)
            assert len(link.outbox) == 0
            await link.close()
            await asyncio.wait_for(task, 10)
            assert link.stats.connects == len(server.hellos) >= server.drops + 1

    asyncio.run(main())
    assert server.drops >= n // 7 - 1
    _assert_exactly_once_in_order(server, n)
    assert server.byes == 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.timeout(60)
def test_link_waits_for_the_server_and_resumes_after_agent_restart(tmp_path: Path) -> None:
    """Messages submitted while no server listens survive the agent's restart and are all delivered
    once the server comes up; the hello carries what the agent knows was acknowledged."""
    server = MiniServer()
    port = _free_port()
    url = f"ws://127.0.0.1:{port}"

    async def main() -> None:
        link = _link(url, tmp_path)
        task = asyncio.create_task(link.run())
        for i in range(1, 21):
            await link.submit(_msg(i))
        await asyncio.sleep(0.3)  # several refused connection attempts (backoff capped at 50 ms)
        assert link.stats.connects == 0 and len(link.outbox) == 20
        await link.close()
        await asyncio.wait_for(task, 10)

        link = _link(url, tmp_path)  # the agent restarts on the same outbox
        for i in range(21, 31):
            assert await link.submit(_msg(i)) == i
        async with running(server, port):
            task = asyncio.create_task(link.run())
            await link.flush(timeout=30)
            await link.close()
            await asyncio.wait_for(task, 10)
        assert server.hellos[0].resume_from == 0

        link = _link(url, tmp_path)  # and once more, now with everything acknowledged
        for i in range(31, 36):
            await link.submit(_msg(i))
        async with running(server, port):
            task = asyncio.create_task(link.run())
            await link.flush(timeout=30)
            await link.close()
            await asyncio.wait_for(task, 10)
        assert server.hellos[-1].resume_from == 30

    asyncio.run(main())
    _assert_exactly_once_in_order(server, 35)


@pytest.mark.timeout(60)
def test_corrections_reach_the_callback_and_errors_are_handled(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A correction goes to on_correction; an error naming the field is logged; a final error drops
    that message; a transient (storage) error keeps it and it is resent on a new connection."""
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    corr = Correction(3, np.diag([2.0, 2.0, 2.0, 1.0]), np.array([4, 5]), np.stack([pose, pose]))
    storage_failed: list[int] = []

    async def on_data(srv: MiniServer, ws: ServerConnection, seq: int, msg: Message) -> bool:
        if seq == 3:
            await ws.send(encode(corr, 0))
        if seq == 5:
            await ws.send(encode(Error("bad_field", "point 5 is bogus", "body.xyz", seq), 0))
            return True
        if seq == 8 and not storage_failed:
            storage_failed.append(seq)
            await ws.send(encode(Error("storage", "disk full", None, seq), 0))
            await ws.close()  # storage is failing: the server stops this session
            return True
        return False

    server = MiniServer(on_data=on_data)
    got: list[Correction] = []

    async def main() -> None:
        async with running(server) as url:
            link = _link(url, tmp_path, on_correction=got.append)
            task = asyncio.create_task(link.run())
            for i in range(1, 13):
                await link.submit(_msg(i))
            await link.flush(timeout=30)
            await link.close()
            await asyncio.wait_for(task, 10)
            assert [(e.code, e.seq) for e in link.server_errors] == [("bad_field", 5), ("storage", 8)]
            assert link.stats.connects == 2  # the storage error made it reconnect once

    with caplog.at_level(logging.ERROR, logger="hivemap.client.link"):
        asyncio.run(main())
    assert len(got) == 1 and got[0].map_id == 3
    np.testing.assert_array_equal(got[0].world_from_cam, corr.world_from_cam)
    np.testing.assert_array_equal(got[0].global_from_local, corr.global_from_local)
    assert any("body.xyz" in r.getMessage() and "point 5 is bogus" in r.getMessage() for r in caplog.records)
    _assert_exactly_once_in_order(server, 12, missing=frozenset({5}))


@pytest.mark.timeout(30)
def test_refused_token_stops_the_link(tmp_path: Path) -> None:
    server = MiniServer()

    async def main() -> None:
        async with running(server) as url:
            link = _link(url, tmp_path, token="wrong")
            await link.submit(_msg(1))
            with pytest.raises(LinkRefused, match="bad token"):
                await asyncio.wait_for(link.run(), 10)
            assert len(link.outbox) == 1  # kept for when the agent is configured right
            await link.close()

    asyncio.run(main())
    assert server.stored == {} and server.hellos == []


@pytest.mark.timeout(30)
def test_backoff_grows_and_is_jittered(tmp_path: Path) -> None:
    """Connection attempts against a closed port back off exponentially (with jitter) up to the cap."""
    port = _free_port()
    attempts: list[float] = []
    real_connect = websockets.connect

    def counting_connect(*a: object, **kw: object) -> object:
        attempts.append(time.monotonic())
        return real_connect(*a, **kw)  # type: ignore[arg-type]

    async def main() -> None:
        opts = LinkOptions(
            backoff_initial_s=0.02, backoff_max_s=0.16, open_timeout_s=1.0, max_connect_attempts=1000
        )
        link = AgentLink(
            f"ws://127.0.0.1:{port}", "uav1", "uav", CAMERA, TOKEN, tmp_path / "b.outbox", options=opts
        )
        task = asyncio.create_task(link.run())
        await asyncio.sleep(1.5)
        await link.close()
        await asyncio.wait_for(task, 5)

    mp = pytest.MonkeyPatch()
    mp.setattr("hivemap.client.link.websockets.connect", counting_connect)
    try:
        asyncio.run(main())
    finally:
        mp.undo()
    gaps = np.diff(attempts)
    # delay_k = min(0.02 * 2^k, 0.16) x jitter in [0.5, 1.5): early gaps short, later ones near the cap
    assert 5 <= len(attempts) <= 30, len(attempts)
    assert gaps[0] < 0.05
    late = gaps[4:]
    assert late.min() >= 0.16 * 0.5 - 0.01 and late.max() < 0.16 * 1.5 + 0.1
    assert late.std() > 0.005  # jittered, not lockstep
