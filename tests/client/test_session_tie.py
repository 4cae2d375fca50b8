"""A server correction ties a new front-end session to the earlier one (issue 26: the live UGV's final
trajectory stayed metres off after a loss although the server had placed its new session right).

Session 0 maps 10 keyframes; tracking is lost and session 1 starts where the IMU guessed, which is
3 m north and 2 deg of yaw from the truth; it maps 10 more keyframes. The server's map is the truth. Its
correction of session 1, in the same map as session 0's, must bring session 1's keyframes to the truth in
the agent's local frame (session 0's), within 5 cm. A pose that breaks the session's shape is still
refused, and a correction from a map session 0 is not in ties nothing."""

from __future__ import annotations

import numpy as np

from hivemap.client import Agent
from hivemap.client.frontend.events import KeyframeEvent
from hivemap.client.frontend.synthetic import make_sequence
from hivemap.maps.geometry import se3, so3_exp
from hivemap.protocol import Correction

N = 10
GUESS_ERROR = se3(so3_exp(np.array([0.0, 0.0, np.radians(2.0)])), np.array([0.0, 3.0, 0.0]))


def _truth(k: int) -> np.ndarray:
    """Body pose of keyframe k (sessions 0 and 1 in turn), about 1 m apart on a gentle curve (a line
    leaves the frame fits without geometry)."""
    x = float(k) + (2.0 if k >= N else 0.0)
    return se3(so3_exp(np.array([0.0, 0.0, 0.05 * x])), np.array([x, 0.5 * np.sin(0.5 * x), 0.1 * x]))


def _agent() -> tuple[Agent, np.ndarray]:
    """The agent after both sessions' keyframes, and body_from_cam."""
    agent = Agent(make_sequence(3, rate=10.0, seed=1).rig, use_imu=False)
    body_from_cam = agent.core.frontend.body_from_cam
    odo = np.diag([1e-6] * 3 + [1e-4] * 3)
    events = []
    for k in range(2 * N):
        session, kf = divmod(k, N)
        # session 1's frame is the IMU's guess: its poses are the truth moved by the guess's error
        T = _truth(k) if session == 0 else GUESS_ERROR @ _truth(k)
        prev = None if kf == 0 else kf - 1
        rel = None if prev is None else np.linalg.inv(_truth(k - 1)) @ _truth(k)
        events.append(KeyframeEvent(
            session, kf, 0.1 * k, T @ body_from_cam, T, np.zeros((0, 2), np.float32), np.zeros(0, np.uint8),
            np.zeros((0, 32), np.uint8), np.zeros(0, np.int64), prev, rel, None if prev is None else odo,
            False, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 32), np.uint8),
        ))  # fmt: skip
    agent.core._consume(events)
    return agent, body_from_cam


def _correction(
    session: int, map_id: int, body_from_cam: np.ndarray, moved: dict[int, np.ndarray] | None = None
) -> Correction:
    """The server's correction of ``session``: its keyframes at the truth (``moved``: some elsewhere),
    the session's frame as the server placed it."""
    ids = np.arange(N, dtype=np.int64)
    poses = np.array([(moved or {}).get(int(i), _truth(session * N + int(i))) @ body_from_cam for i in ids])
    frame = np.eye(4) if session == 0 else np.linalg.inv(GUESS_ERROR)
    return Correction(map_id, frame, ids, poses, session=session)


def _session_positions(agent: Agent, session: int) -> np.ndarray:
    core = agent.core
    return np.array([core.stage.keyframe_pose(core._node_of[(session, i)])[:3, 3] for i in range(N)])


def _truth_positions(session: int) -> np.ndarray:
    return np.array([_truth(session * N + i)[:3, 3] for i in range(N)])


def test_a_new_session_is_placed_where_the_servers_map_puts_it() -> None:
    agent, bfc = _agent()
    before = np.linalg.norm(_session_positions(agent, 1) - _truth_positions(1), axis=1)
    assert before.min() > 2.9  # the guess's error: 3 m north (and 2 deg)
    agent.submit_correction(_correction(0, 3, bfc))
    agent.submit_correction(_correction(1, 3, bfc))
    applied = agent.apply_corrections()
    assert [a.keyframes for a in applied] == [N, N]
    err0 = np.linalg.norm(_session_positions(agent, 0) - _truth_positions(0), axis=1)
    err1 = np.linalg.norm(_session_positions(agent, 1) - _truth_positions(1), axis=1)
    assert err0.max() < 0.05 and err1.max() < 0.05, (err0, err1)


def test_a_tie_still_refuses_a_pose_that_breaks_the_sessions_shape() -> None:
    agent, bfc = _agent()
    off = _truth(N + 4).copy()
    off[:3, 3] += [0.0, 2.0, 0.0]
    agent.submit_correction(_correction(0, 3, bfc))
    agent.submit_correction(_correction(1, 3, bfc, moved={4: off}))
    refused = agent.core.corrections_refused
    applied = agent.apply_corrections()
    assert [a.keyframes for a in applied] == [N, N - 1] and agent.core.corrections_refused == refused + 1
    err1 = np.linalg.norm(_session_positions(agent, 1) - _truth_positions(1), axis=1)
    assert err1.max() < 0.05, err1


def test_a_session_in_another_map_is_not_tied() -> None:
    """Session 1 merged into no map of session 0's: its correction keeps it in its own frame (where the
    guess put it, within 5 cm), as before."""
    agent, bfc = _agent()
    guess = _session_positions(agent, 1)
    agent.submit_correction(_correction(0, 3, bfc))
    agent.submit_correction(_correction(1, 4, bfc))
    agent.apply_corrections()
    err = np.linalg.norm(_session_positions(agent, 1) - guess, axis=1)
    assert err.max() < 0.05, err
