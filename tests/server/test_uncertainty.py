"""Pose covariances end to end: two synthetic agents stream to a real server over real WebSockets and
merge; the agents' latest keyframes' marginal covariances come back on ``/agents/{id}``, every keyframe's
on ``/maps/{id}/uncertainty``, and on the corrections (protocol v4). The UAV says hello in protocol v3:
it is sent v3 frames, its corrections without the covariance (an older agent keeps working)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
from agent_client import SyncAgent
from srv_helpers import TOKENS
from test_backend import UAV_FROM_WORLD, Server

from hivemap.eval.uncertainty import covariance_coverage
from hivemap.protocol import Correction, Message, decode_versioned, encode
from hivemap.server.backend_synth import UGV_FROM_WORLD, agent_stream, make_world


class VersionedAgent(SyncAgent):
    """A :class:`SyncAgent` that writes protocol ``version`` and records each received frame's version."""

    def __init__(self, *args: object, version: int, **kw: object) -> None:
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.version = version
        self.versions: list[int] = []

    def send(self, msg: Message, seq: int) -> None:
        self.send_raw(encode(msg, seq, version=self.version))

    def recv(self, timeout: float = 10.0) -> Message:
        frame = self.ws.recv(timeout=timeout)
        assert isinstance(frame, bytes)
        v, _, msg = decode_versioned(frame)
        self.versions.append(v)
        return msg

    def drain(self, seconds: float) -> list[Correction]:
        out = [m for m in self.others if isinstance(m, Correction)]
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                msg = self.recv(timeout=0.5)
            except TimeoutError:
                continue
            if isinstance(msg, Correction):
                out.append(msg)
        return out


@pytest.fixture
def srv(tmp_path: Path) -> Iterator[Server]:
    s = Server(tmp_path / "data")
    yield s
    s.stop()


def spd(c: np.ndarray) -> bool:
    finite = np.all(np.isfinite(c)) and np.allclose(c, c.T, atol=1e-12)
    return bool(finite and np.linalg.eigvalsh(c).min() > 0)


def test_agents_and_corrections_carry_their_latest_pose_covariance(srv: Server) -> None:
    rng = np.random.default_rng(1)
    pts, desc = make_world(rng, 2500, (-20, 30))
    ugv_msgs, ugv_true, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    uav_msgs, uav_true, _ = agent_stream(rng, pts, desc, np.linspace(-2, 12, 10), UAV_FROM_WORLD)
    ugv = VersionedAgent(srv.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv", version=4)
    uav = VersionedAgent(srv.ws_url, "uav1", TOKENS["uav1"], kind="uav", version=3)
    try:
        for a, msgs in ((ugv, ugv_msgs), (uav, uav_msgs)):
            a.welcome()
            acks, errors = a.send_all(msgs)
            assert not errors and len(acks) == len(msgs)
        srv.wait_idle()
        got_ugv, got_uav = ugv.drain(3.0), uav.drain(1.0)
    finally:
        ugv.close()
        uav.close()
    maps = srv.call(lambda: {mid: sorted(m.agents) for mid, m in srv.hive.stack.maps.items()})
    assert list(maps.values()) == [["uav1", "ugv1"]], maps
    map_id = next(iter(maps))
    base = f"http://127.0.0.1:{srv.port}"
    info = {a: httpx.get(f"{base}/agents/{a}").json()["uncertainty"] for a in ("ugv1", "uav1")}
    for a, u in info.items():
        assert u is not None and u["map_id"] == map_id, (a, u)
        P, C = np.array(u["position_cov"]), np.array(u["pose_cov"])
        assert P.shape == (3, 3) and C.shape == (6, 6) and spd(P) and spd(C), (a, u)
        np.testing.assert_array_equal(P, C[3:, 3:])
        assert u["kf_id"] == 9 and "map frame" in u["convention"]
        # the map's gauge is the UGV's first keyframe: a few keyframes (and a merge) away, the latest is
        # known to centimetres to metres, not exactly and not wildly
        assert 1e-3 < np.sqrt(np.trace(P)) < 5.0, (a, np.sqrt(np.trace(P)))
    # the UAV hangs on the UGV by the merge: its latest pose is the less certain
    assert np.trace(np.array(info["uav1"]["position_cov"])) > np.trace(np.array(info["ugv1"]["position_cov"]))
    # the v4 agent's last correction carries the same covariance as REST (both at the final poses)
    with_cov = [c for c in got_ugv if c.pose_covariance is not None]
    assert with_cov, f"{len(got_ugv)} corrections, none with a covariance"
    last = with_cov[-1]
    assert last.covariance_kf_id == info["ugv1"]["kf_id"] and last.map_id == map_id
    assert last.pose_covariance is not None
    np.testing.assert_allclose(last.pose_covariance, info["ugv1"]["pose_cov"], rtol=1e-6, atol=1e-15)
    # the v3 agent got corrections, all as v3 frames without the v4 fields
    assert got_uav and all(c.pose_covariance is None and c.covariance_kf_id is None for c in got_uav)
    assert set(uav.versions) == {3} and set(ugv.versions) == {4}
    # every keyframe's covariance on /maps/{id}/uncertainty; the gauge keyframe is exact
    r = httpx.get(f"{base}/maps/{map_id}/uncertainty", params={"limit": 100}).json()
    assert r["total"] == 20 and len(r["keyframes"]) == 20 and r["computed_at"] is not None
    rows = {(k["agent_id"], k["kf_id"]): k for k in r["keyframes"]}
    assert np.all(np.array(rows[("ugv1", 0)]["pose_cov"]) == 0.0)
    for key, k in rows.items():
        if key != ("ugv1", 0):
            assert spd(np.array(k["pose_cov"])), key
    np.testing.assert_allclose(rows[("uav1", 9)]["pose_cov"], info["uav1"]["pose_cov"], rtol=1e-6, atol=1e-15)
    page = httpx.get(f"{base}/maps/{map_id}/uncertainty", params={"offset": 15, "limit": 100}).json()
    assert len(page["keyframes"]) == 5 and page["total"] == 20
    assert httpx.get(f"{base}/maps/999/uncertainty").status_code == 404
    # the eval's calibration figure over the same REST (true poses in the world frame; the agents sent
    # exact poses, so every keyframe is well inside its ellipsoid)
    agents = (("ugv1", UGV_FROM_WORLD, ugv_true), ("uav1", UAV_FROM_WORLD, uav_true))
    gt = {a: SimpleNamespace(timestamps=np.arange(10.0), poses_se3=[F.inverse().transform_pose(T) for T in t])
          for a, F, t in agents}  # fmt: skip
    cover = covariance_coverage(base, [{"id": map_id}], gt)[str(map_id)]
    assert cover is not None and cover["n"] == 19 and cover["inside"] == 1.0, cover
