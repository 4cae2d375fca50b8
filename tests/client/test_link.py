"""The agent link (durable outbox + resumable WebSocket) against a real `hivemap server` process:
every message arrives exactly once through server SIGKILLs, dropped connections and agent kills."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from srv_helpers import TOKENS, ServerProcess, map_of, write_config  # noqa: E402

from hivemap.client.link import AgentLink, LinkRefused  # noqa: E402
from hivemap.client.outbox import Outbox, OutboxError  # noqa: E402
from hivemap.protocol import Ack  # noqa: E402
from hivemap.server.loadgen import CAMERA, StreamTruth, synthetic_stream  # noqa: E402


@pytest.fixture
def server(tmp_path: Path) -> ServerProcess:
    s = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    yield s
    s.stop()


def _assert_exact(server: ServerProcess, agent_id: str, truth: StreamTruth) -> None:
    m = map_of(server, agent_id)
    assert (m["keyframes"], m["points"]) == (len(truth.kf_poses), len(truth.points))
    kfs = server.json(f"/maps/{m['id']}/keyframes", limit=10000)["keyframes"]
    assert sorted(k["id"] for k in kfs) == sorted(truth.kf_poses)
    for k in kfs:
        np.testing.assert_allclose(np.array(k["world_from_cam"]), truth.kf_poses[k["id"]], atol=1e-12)
    info = server.json(f"/agents/{agent_id}")
    assert info["pending_keyframes"] == 0
    assert info["duplicates"] == 0, "the link resent something the server already had"


def _link(
    server: ServerProcess, tmp_path: Path, agent_id: str = "uav1", token: str | None = None
) -> AgentLink:
    return AgentLink(
        server.ws_url,
        agent_id,
        "uav",
        CAMERA.to_dict(),
        token or TOKENS[agent_id],
        tmp_path / f"{agent_id}.outbox",
    )


def test_outbox_is_durable_and_owned(tmp_path: Path) -> None:
    msgs, _ = synthetic_stream("uav1", 3, seed=1)
    box = Outbox(tmp_path / "o.sqlite", "uav1")
    seqs = [box.put(m) for m in msgs]
    assert seqs == list(range(1, len(msgs) + 1))
    box.ack(1)
    box.close()
    box = Outbox(tmp_path / "o.sqlite", "uav1")  # reopened: same content, seqs continue
    assert [s for s, _ in box.pending()] == seqs[1:]
    assert box.put(Ack(0)) == len(msgs) + 1
    box.ack_through(3)
    assert [s for s, _ in box.pending()][0] == 4
    box.close()
    with pytest.raises(OutboxError, match="belongs to agent 'uav1'"):
        Outbox(tmp_path / "o.sqlite", "uav2")


def test_link_streams_and_survives_server_sigkill(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("uav1", 40, features=200, seed=5, kf_before_points_every=3)

    async def main() -> None:
        link = _link(server, tmp_path)
        task = asyncio.create_task(link.run())
        for i, m in enumerate(msgs):
            await link.submit(m)
            if i == len(msgs) // 2:
                await asyncio.sleep(0.3)
                server.kill()  # SIGKILL mid-stream
                await asyncio.to_thread(server.start)
        await link.flush(timeout=60)
        assert link.stats.connects >= 2
        await link.close()
        await asyncio.wait_for(task, 10)

    asyncio.run(main())
    _assert_exact(server, "uav1", truth)


def test_link_survives_repeated_connection_drops(server: ServerProcess, tmp_path: Path) -> None:
    msgs, truth = synthetic_stream("uav2", 40, features=200, seed=6)

    async def main() -> None:
        link = _link(server, tmp_path, "uav2")
        task = asyncio.create_task(link.run())
        drops = 0
        for i in range(0, len(msgs), 12):
            await asyncio.wait_for(link.connected.wait(), 20)
            for m in msgs[i : i + 12]:
                await link.submit(m)
            await asyncio.sleep(0.02)  # some in flight, some acked
            ws = link._ws
            if ws is not None and i + 12 < len(msgs):
                await ws.close()  # the network drops the link
                drops += 1
                await asyncio.sleep(0.05)
        await link.flush(timeout=60)
        assert drops >= 4 and link.stats.connects >= drops
        await link.close()
        await asyncio.wait_for(task, 10)

    asyncio.run(main())
    _assert_exact(server, "uav2", truth)


AGENT_SCRIPT = textwrap.dedent(
    """
    import asyncio, sys, time
    from hivemap.client.link import AgentLink
    from hivemap.server.loadgen import CAMERA, synthetic_stream
    url, outbox, start = sys.argv[1], sys.argv[2], int(sys.argv[3])
    msgs, _ = synthetic_stream("ugv1", 40, features=200, seed=7)
    async def main():
        link = AgentLink(url, "ugv1", "ugv", CAMERA.to_dict(), "tok-ugv1", outbox)
        task = asyncio.create_task(link.run())
        for m in msgs[start:]:
            await link.submit(m)
            time.sleep(0.01)
        await link.flush(timeout=60)
        await link.close()
        await task
    asyncio.run(main())
    """
)


def test_agent_process_killed_and_restarted(server: ServerProcess, tmp_path: Path) -> None:
    """SIGKILL the agent process mid-stream; a new process on the same outbox finishes the job.
    (The agent resumes producing where its outbox says it stopped.)"""
    msgs, truth = synthetic_stream("ugv1", 40, features=200, seed=7)
    script = tmp_path / "agent.py"
    script.write_text(AGENT_SCRIPT)
    outbox = tmp_path / "ugv1.outbox"
    p = subprocess.Popen([sys.executable, str(script), server.ws_url, str(outbox), "0"])
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if outbox.exists():
            box = Outbox(outbox, "ugv1")
            produced = box.last_seq
            box.close()
            if produced > len(msgs) // 2:
                break
        time.sleep(0.05)
    p.kill()
    p.wait(10)
    box = Outbox(outbox, "ugv1")
    produced = box.last_seq
    box.close()
    assert 0 < produced < len(msgs)
    q = subprocess.run([sys.executable, str(script), server.ws_url, str(outbox), str(produced)], timeout=120)
    assert q.returncode == 0
    _assert_exact(server, "ugv1", truth)


def test_wrong_token_stops_the_link(server: ServerProcess, tmp_path: Path) -> None:
    async def main() -> None:
        link = _link(server, tmp_path, "uav1", token="not-the-token")
        with pytest.raises(LinkRefused, match="uav1"):
            await asyncio.wait_for(link.run(), 20)

    asyncio.run(main())
    assert server.json("/maps")["maps"] == []
