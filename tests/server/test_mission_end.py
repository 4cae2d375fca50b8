"""An agent's end of mission (issue 27): its last pose updates carry its final, smoothed odometry, and its
bye makes the server solve the robust pose graph once more on them, so the map the agent then reads holds
both that odometry and the loops (real server, real WebSocket).

One agent passes a place twice; the loop puts the second pass back onto the first. Then the agent's
smoothing says the junction between the passes (untracked) was 0.35 m shorter: it resends the second
pass's keyframes moved rigidly by that much. A pose update alone moves each keyframe by its own change,
which takes the second pass off the place the loop holds; the solve after the bye brings it back."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_backend import FAST, Server, stream

from hivemap.maps.geometry import se3
from hivemap.protocol import Bye, PoseUpdates
from hivemap.server.backend import preset
from hivemap.server.backend_synth import loop_passes

SECOND = list(range(1000, 1010))


@pytest.fixture
def srv(tmp_path: Path) -> Iterator[Server]:
    # no global BA: the map's points would pull the keyframes back by themselves
    s = Server(tmp_path / "data", preset("default", scheduler=FAST))
    yield s
    s.stop()


def _errors(srv: Server, true2: np.ndarray) -> np.ndarray:
    poses = srv.call(
        lambda: {
            k[1]: kf.world_from_cam.copy()
            for m in srv.hive.stack.maps.values()
            for k, kf in m.keyframes.items()
        }
    )
    return np.linalg.norm(np.array([poses[i][:3, 3] for i in SECOND]) - true2[:, :3, 3], axis=1)


def _pose_graphs(srv: Server) -> int:
    return int(srv.call(lambda: srv.hive.events.counts.get("pose_graph", 0)))


def test_a_bye_solves_the_pose_graph_on_the_agents_last_odometry(srv: Server) -> None:
    first, second, true2, sent2 = loop_passes()
    shift = se3(np.eye(3), np.array([0.35, 0.0, 0.0]))
    resent = np.array([shift @ T for T in sent2])
    update = PoseUpdates(np.array(SECOND, np.int64), resent, np.zeros(0, np.int64), np.zeros((0, 3)), 0,
                         points_follow=True)  # fmt: skip
    with stream(srv, "ugv1", "ugv", first + second) as agent:
        srv.wait_idle()
        assert srv.call(lambda: len(srv.backend.loops)) >= 1
        assert _errors(srv, true2).max() < 0.1
        acks, errors = agent.send_all([update], first_seq=len(first) + len(second) + 1)
        assert acks and not errors
        srv.wait_idle()
        held = _errors(srv, true2)
        solves = _pose_graphs(srv)
        agent.send(Bye("mission complete"), 0)
        with pytest.raises(Exception):  # noqa: B017 (the server closes the socket: the bye was handled)
            agent.recv(timeout=10.0)
    srv.wait_idle()
    after = _errors(srv, true2)
    # the update alone took the second pass off the loop's place by about the shift
    assert held.min() > 0.25, held
    # the bye's solve: one more pose graph, and the second pass back where the loop holds it
    assert _pose_graphs(srv) == solves + 1
    assert after.max() < 0.1, after
    # the odometry the pose graph held is the resent one
    vio = srv.call(lambda: {k[1]: kf.vio_from_cam.copy() for m in srv.hive.stack.maps.values()
                            for k, kf in m.keyframes.items()})  # fmt: skip
    for n, k in enumerate(SECOND):
        np.testing.assert_allclose(vio[k], resent[n], atol=1e-9)
