"""Protocol v4 to older and to non-opted agents, over real WebSockets to a real server: each connection
is written in the version of its hello, and a ``team_advisory`` reaches only a v4 agent that asked for it
(a v3 agent would reject the unknown type; one that did not ask gets none). A correction to the v3 agent
still goes, as a v3 frame without the v4 covariance."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from srv_helpers import TOKENS
from test_backend import Server
from test_uncertainty import VersionedAgent

from hivemap.protocol import Correction, Message, TeamAdvisory, Welcome
from hivemap.server.loadgen import hello as make_hello


@pytest.fixture
def srv(tmp_path: Path) -> Iterator[Server]:
    s = Server(tmp_path / "data")
    yield s
    s.stop()


def _next(agent: VersionedAgent, cls: type, timeout: float = 5.0) -> Message:
    """The agent's next message of type ``cls`` (skipping anything else the server sends meanwhile)."""
    while True:
        msg = agent.recv(timeout=timeout)
        if isinstance(msg, cls):
            return msg


def test_each_connection_gets_only_what_its_hello_can_read(srv: Server) -> None:
    old = VersionedAgent(srv.ws_url, "uav1", TOKENS["uav1"], kind="uav", version=3)
    plain = VersionedAgent(srv.ws_url, "ugv1", TOKENS["ugv1"], kind="ugv", version=4)
    asking = VersionedAgent(srv.ws_url, "uav2", TOKENS["uav2"], kind="uav", version=4)
    try:
        old.welcome()
        plain.welcome()
        asking.send(replace(make_hello("uav2", TOKENS["uav2"], "uav"), team_advisories=True), 0)
        assert isinstance(asking.recv(), Welcome)
        adv = TeamAdvisory(
            map_id=7, computed_at=1.5e9, goals=np.array([[1.0, 2.0, 3.0]]),
            desired_velocity=np.array([1.0, 0.0, 0.0]), safe_velocity=np.array([0.5, 0.5, 0.0]), radius_m=0.7,
        )  # fmt: skip
        ids = ("uav1", "ugv1", "uav2")
        sent = srv.call(lambda: {a: srv.hive.agents[a].connection.send(adv) for a in ids})
        assert sent == {"uav1": False, "ugv1": False, "uav2": True}
        got = _next(asking, TeamAdvisory)
        assert isinstance(got, TeamAdvisory) and (got.map_id, got.computed_at) == (7, 1.5e9)
        np.testing.assert_array_equal(got.safe_velocity, adv.safe_velocity)
        for a in (old, plain):  # nothing was queued for them
            with pytest.raises(TimeoutError):
                a.recv(timeout=1.0)
        corr = Correction(
            map_id=7, global_from_local=np.eye(4), kf_ids=np.zeros(0, np.int64),
            world_from_cam=np.zeros((0, 4, 4)), pose_covariance=np.eye(6) * 1e-4, covariance_kf_id=3,
        )  # fmt: skip
        assert srv.call(lambda: {a: srv.hive.agents[a].connection.send(corr) for a in ids[:2]}) == {
            "uav1": True,
            "ugv1": True,
        }
        c3, c4 = _next(old, Correction), _next(plain, Correction)
        assert isinstance(c3, Correction) and c3.pose_covariance is None and c3.covariance_kf_id is None
        assert isinstance(c4, Correction) and c4.covariance_kf_id == 3 and c4.pose_covariance is not None
        np.testing.assert_array_equal(c4.pose_covariance, corr.pose_covariance)
        assert set(old.versions) == {3} and set(plain.versions) == set(asking.versions) == {4}
    finally:
        for a in (old, plain, asking):
            a.close()
