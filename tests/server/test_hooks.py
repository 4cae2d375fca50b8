"""The hooks the collaboration back-end uses, on a real server (uvicorn in a thread) with real sockets."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn
from agent_client import SyncAgent
from srv_helpers import TOKENS, free_port

from hivemap.maps.geometry import Sim3, so3_exp
from hivemap.protocol import Correction, Welcome
from hivemap.server.app import create_app, uvicorn_config_kwargs
from hivemap.server.core import HiveServer
from hivemap.server.loadgen import synthetic_stream
from hivemap.server.settings import ServerSettings


class InProcessServer:
    def __init__(self, data_dir: Path, extensions: list[Callable[[HiveServer], None]] | None = None) -> None:
        self.port = free_port()
        settings = ServerSettings(port=self.port, data_dir=data_dir, tokens=TOKENS, log_level="warning")
        self.app = create_app(settings, extensions=extensions or [])
        self.server = uvicorn.Server(uvicorn.Config(self.app, **uvicorn_config_kwargs(settings)))  # type: ignore[arg-type]
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 20
        while not (self.server.started and self.app.state.hive.loaded.is_set()):  # the store loads after
            assert time.monotonic() < deadline and self.thread.is_alive(), "server did not start"
            time.sleep(0.05)
        self.hive: HiveServer = self.app.state.hive
        self.ws_url = f"ws://127.0.0.1:{self.port}/ws"
        self.url = f"http://127.0.0.1:{self.port}"

    def run(self, coro: Coroutine[Any, Any, Any]) -> Any:
        """Run a coroutine on the server's event loop (as the back-end would from a worker thread)."""
        assert self.hive.loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self.hive.loop).result(10)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


@pytest.fixture
def srv(tmp_path: Path) -> Iterator[InProcessServer]:
    s = InProcessServer(tmp_path / "data")
    yield s
    s.stop()


def _correction(map_id: int, n: int) -> Correction:
    return Correction(
        map_id=map_id,
        global_from_local=Sim3(so3_exp(np.array([0, 0, 0.3])), np.array([1.0, 2.0, 3.0]), 1.5).matrix(),
        kf_ids=np.arange(n, dtype=np.int64),
        world_from_cam=np.tile(np.eye(4), (n, 1, 1)),
    )


def test_observers_see_every_inserted_keyframe_and_corrections_reach_the_agent(srv: InProcessServer) -> None:
    seen: list[tuple[int, tuple[str, int]]] = []

    async def observer(map_id: int, key: tuple[str, int]) -> None:
        seen.append((map_id, key))

    srv.hive.keyframe_observers.append(observer)
    msgs, truth = synthetic_stream("uav1", 6, seed=4, kf_before_points_every=2)
    with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as ag:
        ag.welcome()
        acks, errors = ag.send_all(msgs)
        assert not errors
        map_id = srv.hive.stack.map_of_agent("uav1").id  # type: ignore[union-attr]
        assert sorted(k for _, k in seen) == [("uav1", i) for i in range(6)]
        assert {m for m, _ in seen} == {map_id}
        corr = _correction(map_id, 3)
        assert srv.run(srv.hive.send_correction("uav1", corr)) is True
        got = ag.recv()
        assert isinstance(got, Correction)
        np.testing.assert_array_equal(got.global_from_local, corr.global_from_local)
        np.testing.assert_array_equal(got.kf_ids, corr.kf_ids)
    # Offline: queued, delivered right after the next welcome.
    time.sleep(0.2)
    assert srv.run(srv.hive.send_correction("uav1", _correction(map_id, 2))) is False
    with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as ag:
        assert isinstance(ag.hello(), Welcome)
        got = ag.recv()
        assert isinstance(got, Correction) and len(got.kf_ids) == 2
    events = httpx.get(srv.url + "/events", params={"kind": "correction"}).json()["events"]
    assert len(events) == 2


def test_agent_transform_moves_incoming_data_into_the_map_frame(srv: InProcessServer) -> None:
    msgs, truth = synthetic_stream("uav2", 10, seed=6)
    g = Sim3(so3_exp(np.array([0.1, -0.2, 0.7])), np.array([5.0, -3.0, 1.0]), 2.0)
    with SyncAgent(srv.ws_url, "uav2", TOKENS["uav2"]) as ag:
        ag.welcome()
        half = len(msgs) // 2
        assert not ag.send_all(msgs[:half])[1]
        # The back-end merged uav2's map: move what is there and set the transform for what comes next.
        srv.run(_transform(srv.hive, "uav2", g))
        assert not ag.send_all(msgs[half:], half + 1)[1]
    m = srv.hive.stack.map_of_agent("uav2")
    assert m is not None and len(m.keyframes) == len(truth.kf_poses)
    for k, T in truth.kf_poses.items():
        np.testing.assert_allclose(m.keyframes[("uav2", k)].world_from_cam, g.transform_pose(T), atol=1e-9)
    for p, x in truth.points.items():
        np.testing.assert_allclose(m.points[("uav2", p)].xyz, g.apply(x), atol=1e-9)
    # The local frame undoes the transform: the agent's own poses.
    traj = httpx.get(srv.url + "/agents/uav2/trajectory", params={"frame": "local"}).json()["poses"]
    for p in traj:
        np.testing.assert_allclose(p["position"], truth.kf_poses[p["kf_id"]][:3, 3], atol=1e-9)


async def _transform(hive: HiveServer, folded: str, g: Sim3) -> None:
    m = hive.stack.map_of_agent(folded)
    assert m is not None
    m.transform(g)
    hive.set_agent_transform(folded, g)


def test_apply_merge_reframes_later_data_and_survives_a_restart(tmp_path: Path) -> None:
    s1, t1 = synthetic_stream("uav1", 12, seed=31)
    s2, t2 = synthetic_stream("ugv1", 12, seed=32, offset=(3.0, 1.0, 0.0))
    g = Sim3(so3_exp(np.array([0.0, 0.0, 0.4])), np.array([-2.0, 4.0, 0.5]), 1.0)  # ugv1 -> uav1 frame
    srv = InProcessServer(tmp_path / "data")
    try:
        a1 = SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"])
        a2 = SyncAgent(srv.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv")
        a1.welcome()
        a2.welcome()
        assert not a1.send_all(s1)[1]
        half = len(s2) // 2
        assert not a2.send_all(s2[:half])[1]
        target = srv.hive.stack.map_of_agent("uav1")
        source = srv.hive.stack.map_of_agent("ugv1")
        assert target is not None and source is not None and target.id != source.id
        merged = srv.run(srv.hive.apply_merge(target.id, source.id, g))
        assert merged.id == target.id and source.id not in srv.hive.stack.maps
        # ugv1 goes on streaming in its own VIO frame; the server files it in the merged (uav1) frame.
        assert not a2.send_all(s2[half:], half + 1)[1]
        a1.close()
        a2.close()
        maps = httpx.get(srv.url + "/maps").json()["maps"]
        assert len(maps) == 1 and maps[0]["agents"] == ["uav1", "ugv1"]
        assert (maps[0]["keyframes"], maps[0]["points"]) == (24, len(t1.points) + len(t2.points))
        assert maps[0]["merges"] == 1
        assert any(e["kind"] == "merge" for e in httpx.get(srv.url + "/events").json()["events"])
    finally:
        srv.stop()
    srv = InProcessServer(tmp_path / "data")  # restart: everything reloads from SQLite
    try:
        m = srv.hive.stack.map_of_agent("ugv1")
        assert m is not None and m is srv.hive.stack.map_of_agent("uav1")
        assert len(m.keyframes) == 24 and len(m.merge_history) == 1
        for k, T in t2.kf_poses.items():
            np.testing.assert_allclose(
                m.keyframes[("ugv1", k)].world_from_cam, g.transform_pose(T), atol=1e-9
            )
        for k, T in t1.kf_poses.items():
            np.testing.assert_allclose(m.keyframes[("uav1", k)].world_from_cam, T, atol=1e-12)
        local = httpx.get(srv.url + "/agents/ugv1/trajectory", params={"frame": "local"}).json()["poses"]
        for p in local:
            np.testing.assert_allclose(p["position"], t2.kf_poses[p["kf_id"]][:3, 3], atol=1e-9)
    finally:
        srv.stop()


def test_extensions_install_and_lifecycle_hooks_run_around_the_reload(tmp_path: Path) -> None:
    calls: list[str] = []

    def install(server: HiveServer) -> None:
        calls.append("install")

        async def started(s: HiveServer) -> None:
            calls.append(f"start maps={len(s.stack.maps)} agents={sorted(s.agents)}")

        async def stopping(s: HiveServer) -> None:
            calls.append("stop")

        server.startup_hooks.append(started)
        server.shutdown_hooks.append(stopping)

    msgs, _ = synthetic_stream("uav1", 2, seed=51)
    srv = InProcessServer(tmp_path / "data", extensions=[install])
    with SyncAgent(srv.ws_url, "uav1", TOKENS["uav1"]) as ag:
        ag.welcome()
        assert not ag.send_all(msgs)[1]
    srv.stop()
    srv = InProcessServer(tmp_path / "data", extensions=[install])
    srv.stop()
    # The second start sees the reloaded stack: start hooks run after the reload.
    assert calls == [
        "install",
        "start maps=0 agents=[]",
        "stop",
        "install",
        "start maps=1 agents=['uav1']",
        "stop",
    ]
    from hivemap.server.app import default_extensions

    assert default_extensions(ServerSettings(backend=False)) == []
