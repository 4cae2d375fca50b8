"""Fault tests with the real agent side (hivemap.client.link.AgentLink, durable outbox):
connections dropped repeatedly (through a TCP proxy that cuts them), the server SIGKILLed mid-stream and
restarted, the agent process SIGKILLed and restarted. The final map must hold every keyframe and point
exactly once with the final poses."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from srv_helpers import TOKENS, ServerProcess, free_port, map_of, write_config

from hivemap.server.loadgen import CAMERA, StreamTruth, synthetic_stream

link_mod = pytest.importorskip("hivemap.client.link")
AgentLink = link_mod.AgentLink
LinkOptions = link_mod.LinkOptions

FAST = LinkOptions(backoff_initial_s=0.05, backoff_max_s=0.5)


def _assert_exact(server: ServerProcess, agent_id: str, truth: StreamTruth) -> None:
    m = map_of(server, agent_id)
    assert (m["keyframes"], m["points"]) == (len(truth.kf_poses), len(truth.points))
    kfs = server.json(f"/maps/{m['id']}/keyframes", limit=10000)["keyframes"]
    assert sorted(k["id"] for k in kfs) == sorted(truth.kf_poses)
    for k in kfs:  # float64 end to end
        np.testing.assert_allclose(np.array(k["world_from_cam"]), truth.kf_poses[k["id"]], atol=1e-12)
    assert server.json(f"/agents/{agent_id}")["pending_keyframes"] == 0


class CuttingProxy:
    """A TCP proxy to the server whose connections can all be cut at once (an unreliable radio link)."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = free_port()
        self.writers: list[asyncio.StreamWriter] = []
        self.cuts = 0

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", self.port)

    async def _pipe(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        with contextlib.suppress(Exception):
            while data := await r.read(65536):
                w.write(data)
                await w.drain()
        with contextlib.suppress(Exception):
            w.close()

    async def _handle(self, cr: asyncio.StreamReader, cw: asyncio.StreamWriter) -> None:
        try:
            sr, sw = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            cw.close()
            return
        self.writers += [cw, sw]
        await asyncio.gather(self._pipe(cr, sw), self._pipe(sr, cw))

    def cut(self) -> None:
        for w in self.writers:
            w.transport.abort()
        self.writers.clear()
        self.cuts += 1

    async def stop(self) -> None:
        self.cut()
        self.server.close()


@pytest.fixture
def server(tmp_path: Path) -> ServerProcess:
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def test_link_through_a_connection_cut_every_150ms(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("uav1", 60, features=300, seed=41, kf_before_points_every=4)

    async def main() -> tuple[int, int]:
        proxy = CuttingProxy(server.port)
        await proxy.start()
        link = AgentLink(
            f"ws://127.0.0.1:{proxy.port}/ws", "uav1", "uav", CAMERA.to_dict(), TOKENS["uav1"],
            tmp_path / "outbox.sqlite", options=FAST,
        )  # fmt: skip
        runner = asyncio.create_task(link.run())

        async def cutter() -> None:
            while True:
                await asyncio.sleep(0.15)
                proxy.cut()

        cuts = asyncio.create_task(cutter())
        for m in msgs:
            await link.submit(m)
            await asyncio.sleep(0.005)
        await link.flush(timeout=60)
        cuts.cancel()
        await link.close()
        runner.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await runner
        await proxy.stop()
        return proxy.cuts, link.stats.connects

    cuts, connects = asyncio.run(main())
    assert cuts >= 5 and connects >= 3, (cuts, connects)
    _assert_exact(server, "uav1", truth)


def test_link_survives_server_sigkill_and_restart(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("uav2", 60, features=300, seed=42, kf_before_points_every=5)
    # FAST's attempts span ~4 s: on a loaded machine the restarted server took longer to listen, and the
    # link gave up; as many attempts as span a minute, as the default options do
    patient = replace(FAST, max_connect_attempts=120)

    async def main() -> None:
        link = AgentLink(
            server.ws_url, "uav2", "uav", CAMERA.to_dict(), TOKENS["uav2"], tmp_path / "outbox.sqlite",
            options=patient,
        )  # fmt: skip
        runner = asyncio.create_task(link.run())
        half = len(msgs) // 2
        for m in msgs[:half]:
            await link.submit(m)
        await asyncio.sleep(0.05)  # some acked, some in flight
        server.kill()
        for m in msgs[half:]:  # the agent goes on producing while the server is down
            await link.submit(m)
        await asyncio.to_thread(server.start)
        await link.flush(timeout=60)
        await link.close()
        runner.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await runner

    asyncio.run(main())
    _assert_exact(server, "uav2", truth)


AGENT_SCRIPT = textwrap.dedent(
    """
    import asyncio, sys
    from hivemap.client.link import AgentLink, LinkOptions
    from hivemap.server.loadgen import CAMERA, synthetic_stream

    async def main():
        msgs, _ = synthetic_stream("ugv1", 50, features=200, seed=43, kf_before_points_every=3)
        link = AgentLink({url!r}, "ugv1", "ugv", CAMERA.to_dict(), {token!r}, {outbox!r},
                         options=LinkOptions(backoff_initial_s=0.05, backoff_max_s=0.5))
        runner = asyncio.create_task(link.run())
        start = link.outbox.last_seq  # what an earlier run already produced (seq = index + 1)
        print("start", start, flush=True)
        for m in msgs[start:]:
            await link.submit(m)
            await asyncio.sleep(0.02)
        await link.flush(timeout=60)
        print("done", flush=True)
        await link.close()
        runner.cancel()

    asyncio.run(main())
    """
)


def test_agent_process_with_outbox_killed_and_restarted(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("ugv1", 50, features=200, seed=43, kf_before_points_every=3)
    script = tmp_path / "agent.py"
    script.write_text(
        AGENT_SCRIPT.format(url=server.ws_url, token=TOKENS["ugv1"], outbox=str(tmp_path / "outbox.sqlite"))
    )
    starts = []
    for _ in range(3):
        p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE)
        assert p.stdout is not None
        starts.append(int(p.stdout.readline().split()[1]))
        time.sleep(0.5)  # mid-stream: one message every 20 ms, ~2.3 s in all
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        p.stdout.close()
    final = subprocess.run([sys.executable, str(script)], capture_output=True, timeout=120, check=True)
    assert b"done" in final.stdout
    starts.append(int(final.stdout.split()[1]))
    assert starts[0] == 0 and all(a < b for a, b in zip(starts, starts[1:], strict=False)), starts
    assert starts[-1] < len(msgs)
    _assert_exact(server, "ugv1", truth)
