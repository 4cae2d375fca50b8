"""The live-input API (`hivemap.client.Agent`): fed sample by sample as a driver would, it tracks the
tiny dataset into ENU with its GNSS fixes, applies a server correction and calls back, and streams to a
real server."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hivemap.client import Agent, CorrectionInfo
from hivemap.client.dataset import load_dataset
from hivemap.protocol import Correction

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))


def _feed(agent: Agent, ds, events: list | None = None) -> list:  # type: ignore[no-untyped-def]
    """Interleave IMU, GNSS and frames in time order, one sample at a time."""
    if events is not None:
        agent.core.on_event = events.append
    g = ds.gnss
    fixes = list(zip(g.timestamps, g.enu, g.sigma, strict=True)) if g is not None else []
    results = []
    imu_i = fix_i = 0
    for t, left, right in ds.frames:
        while imu_i < len(ds.imu) and ds.imu[imu_i, 0] <= t:
            agent.feed_imu(ds.imu[imu_i, 0], ds.imu[imu_i, 1:4], ds.imu[imu_i, 4:7])
            imu_i += 1
        while fix_i < len(fixes) and fixes[fix_i][0] <= t + 0.01:
            ft, enu, (sh, sv) = fixes[fix_i]
            agent.feed_gnss(ft, enu, sh, sv)
            fix_i += 1
        results.append(agent.feed_stereo(t, left, right))
    return results


def _tap_events(agent: Agent) -> list:  # type: ignore[type-arg]
    """Every front-end event of a connected agent, collected after its link has taken it."""
    events: list = []
    on_event = agent.core.on_event
    assert on_event is not None

    def both(ev: object) -> None:
        events.append(ev)
        on_event(ev)

    agent.core.on_event = both
    return events


def test_live_agent_tracks_into_enu_with_its_fixes(tiny_agent: Path) -> None:
    ds = load_dataset(tiny_agent)
    agent = Agent.from_calibration([tiny_agent / "mav0"])
    assert agent.agent_id == "uav1" and agent.pose() is None
    results = _feed(agent, ds)
    assert all(r.tracked for r in results) and any(r.keyframe_id is not None for r in results)
    np.testing.assert_array_equal(agent.pose("vio"), results[-1].world_from_body)
    # the fixes went in at their keyframes (the newest two wait for local BA until close()), so the local
    # frame is ENU: compare to ground truth
    assert agent.core.gnss_used == len(ds.gnss) - 2 == 9
    truth = ds.groundtruth.at(ds.frames.t_ns[-1:])[0]
    local = agent.pose("local")
    assert local is not None and np.linalg.norm(local[:3, 3] - truth[:3, 3]) < 0.15
    vio = agent.pose("vio")
    assert vio is not None and np.linalg.norm(vio[:3, 3] - truth[:3, 3]) > 1.0  # the VIO frame is not ENU
    assert agent.close() == 0
    assert agent.core.gnss_used == len(ds.gnss)


def test_a_correction_is_applied_before_the_next_frame_and_called_back(tiny_agent: Path) -> None:
    ds = load_dataset(tiny_agent)
    agent = Agent.from_dataset(ds)
    seen: list[CorrectionInfo] = []
    agent.on_correction(seen.append)
    events: list = []
    agent.core.on_event = events.append
    frames = list(ds.frames)
    imu = ds.imu
    for k, (t, left, right) in enumerate(frames[:-1]):
        prev = frames[k - 1][0] if k else -np.inf
        agent.feed_imu_batch(imu[(imu[:, 0] > prev) & (imu[:, 0] <= t)])
        agent.feed_stereo(t, left, right)
    kfs = [e for e in events if hasattr(e, "keypoints")]
    assert kfs
    # the server's estimate of these keyframes in a global frame 10 m away: the same poses, moved
    g_from_l = np.eye(4)
    g_from_l[:3, 3] = [10.0, 0.0, 0.0]
    corr = Correction(0, g_from_l, np.array([e.kf_id for e in kfs], np.int64),
                      np.array([g_from_l @ e.world_from_cam for e in kfs]))  # fmt: skip
    agent.submit_correction(corr)
    assert not seen  # applied between frames, on the feeding thread
    before = agent.pose("local")
    t, left, right = frames[-1]
    agent.feed_imu_batch(imu[(imu[:, 0] > frames[-2][0]) & (imu[:, 0] <= t)])
    agent.feed_stereo(t, left, right)
    assert len(seen) == 1 and seen[0].map_id == 0 and seen[0].keyframes == len(kfs)
    np.testing.assert_array_equal(seen[0].global_from_local, g_from_l)
    after = agent.pose("local")
    # consistent with the agent's own estimate: the local pose barely moves
    assert before is not None and after is not None and np.linalg.norm(after[:3, 3] - before[:3, 3]) < 0.05
    agent.close()


def test_connected_agent_streams_its_keyframes(tiny_agent: Path, tmp_path: Path) -> None:
    from srv_helpers import TOKENS, ServerProcess, write_config

    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        agent = Agent.from_calibration([tiny_agent])
        with pytest.raises(ValueError, match="server URL"):
            agent.connect("127.0.0.1:8765", TOKENS["uav1"], tmp_path / "agent")
        agent.connect(server.ws_url, TOKENS["uav1"], tmp_path / "agent")
        events = _tap_events(agent)
        _feed(agent, load_dataset(tiny_agent))
        assert agent.close(timeout=30) == 0
        n_kf = sum(hasattr(e, "keypoints") for e in events)
        info = server.json("/agents/uav1")
        assert n_kf > 3 and info["keyframes"] == n_kf and info["pending_keyframes"] == 0
    finally:
        server.stop()


def test_streaming_replay_is_the_offline_replay_plus_the_link(tiny_agent: Path, tmp_path: Path) -> None:
    """Both replays feed the dataset through ``Agent``: without a back-end (no corrections) the streamed
    run computes the offline run's trajectory exactly, and the server holds every keyframe it made."""
    from srv_helpers import TOKENS, ServerProcess, write_config

    from hivemap.client.runner import RunnerOptions, run_offline
    from hivemap.client.streaming import run_streaming
    from hivemap.eval.trajectory import read_tum

    opts = RunnerOptions(progress=False, corrections_max_wait_s=0.0)
    offline = run_offline(tiny_agent, tmp_path / "offline", opts)
    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        streamed = run_streaming(tiny_agent, tmp_path / "streamed", server.ws_url, None, TOKENS["uav1"], opts)
        info = server.json("/agents/uav1")
    finally:
        server.stop()
    assert streamed.unsent == 0 and streamed.stopped_by == ""
    assert info["keyframes"] == streamed.keyframes == offline.keyframes > 3 and info["pending_keyframes"] == 0
    a, b = read_tum(tmp_path / "offline" / "local.tum"), read_tum(tmp_path / "streamed" / "local.tum")
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_allclose(a.positions_xyz, b.positions_xyz, atol=1e-6)


def _stream_tapped(tiny_agent: Path, tmp_path: Path, runner: object, tap: object) -> tuple[Agent, list]:  # type: ignore[type-arg]
    """Stream the tiny dataset to a real server with ``runner`` options, calling ``tap(agent, event)``
    after the link took each front-end event; returns the agent and every message of its outbox."""
    import sqlite3

    from srv_helpers import TOKENS, ServerProcess, write_config

    from hivemap.client.agent import AgentOptions
    from hivemap.protocol import decode

    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        agent = Agent.from_calibration([tiny_agent], agent_id="uav1", options=AgentOptions(runner))  # type: ignore[arg-type]
        agent.connect(server.ws_url, TOKENS["uav1"], tmp_path / "agent")
        on_event = agent.core.on_event
        assert on_event is not None

        def both(ev: object) -> None:
            on_event(ev)
            tap(agent, ev)  # type: ignore[operator]

        agent.core.on_event = both
        _feed(agent, load_dataset(tiny_agent))
        assert agent.close(timeout=30) == 0
    finally:
        server.stop()
    db = sqlite3.connect(next((tmp_path / "agent").rglob("outbox*.sqlite")))
    msgs = [decode(bytes(f))[1] for (f,) in db.execute("SELECT frame FROM outbox ORDER BY seq")]
    db.close()
    return agent, msgs


def test_an_agent_streaming_its_imu_odometry_sends_each_keyframe_moved_to_it(
    tiny_agent: Path, tmp_path: Path
) -> None:
    """``stream_imu_odometry``: every keyframe reaches the outbox at its IMU-only fusion's pose
    (``stream_from_vio`` at emission time times the tracking's pose), which is not the tracking's."""
    from hivemap.client.runner import RunnerOptions
    from hivemap.protocol import Keyframe

    expected: dict[int, np.ndarray] = {}

    def tap(agent: Agent, ev: object) -> None:
        if hasattr(ev, "keypoints"):
            expected[ev.kf_id] = agent.core.stream_from_vio(ev.session, ev.kf_id) @ ev.world_from_cam  # type: ignore[attr-defined]

    runner = RunnerOptions(progress=False, stream_imu_odometry=True)
    agent, msgs = _stream_tapped(tiny_agent, tmp_path, runner, tap)
    sent = {m.kf_id: m.world_from_cam for m in msgs if isinstance(m, Keyframe)}
    assert len(sent) > 3 and set(sent) == set(expected)
    for k, T in sent.items():
        np.testing.assert_allclose(T, expected[k], atol=1e-9)
    # the fusion moved them: not the identity on every keyframe
    moved = [np.linalg.norm(agent.core.stream_from_vio(0, k)[:3, 3]) for k in sent]
    assert max(moved) > 1e-4, moved


def _latest_vio(vio: dict[int, np.ndarray]) -> object:
    """A tap keeping each keyframe's latest tracking pose in ``vio``: its keyframe event, then the local
    BA's updates."""
    from hivemap.client.frontend.tracker import KeyframeEvent, PoseUpdateEvent

    def tap(agent: Agent, ev: object) -> None:
        if isinstance(ev, KeyframeEvent):
            vio[ev.kf_id] = ev.world_from_cam
        elif isinstance(ev, PoseUpdateEvent):
            vio.update(zip(np.asarray(ev.kf_ids).tolist(), ev.world_from_cam, strict=True))

    return tap


def test_keyframes_the_odometry_moved_later_are_sent_again(tiny_agent: Path, tmp_path: Path) -> None:
    """``stream_resend``: the IMU-only fusion is a smoother, and the last pose the outbox holds for each
    keyframe (its keyframe message, then the pose updates that moved it) is within the resend threshold of
    where the fusion puts it at the end; the resends are pose updates whose points follow their keyframes,
    and the server takes them all."""
    from hivemap.client.runner import RunnerOptions
    from hivemap.protocol import Keyframe, PoseUpdates

    vio: dict[int, np.ndarray] = {}
    tap = _latest_vio(vio)
    runner = RunnerOptions(progress=False, stream_imu_odometry=True, stream_resend=(0.002, 0.1),
                           stream_final_resend=None)  # fmt: skip
    agent, msgs = _stream_tapped(tiny_agent, tmp_path, runner, tap)
    last: dict[int, np.ndarray] = {}
    resends = 0
    for m in msgs:
        if isinstance(m, Keyframe):
            last[m.kf_id] = m.world_from_cam
        elif isinstance(m, PoseUpdates):
            resends += len(m.kf_ids) if m.points_follow else 0
            assert not m.points_follow or len(m.point_ids) == 0
            last.update(zip(m.kf_ids.tolist(), m.world_from_cam, strict=True))
    assert resends > 0 and len(last) > 3
    for k, T in last.items():
        final = agent.core.stream_from_vio(0, k) @ vio[k]
        assert np.linalg.norm(final[:3, 3] - T[:3, 3]) < 0.002 + 1e-9, k


def test_a_finishing_agent_sends_its_final_odometry(tiny_agent: Path, tmp_path: Path) -> None:
    """``stream_final_resend``: during the mission a keyframe is resent only once the smoothing moved it
    3 cm, so the server's odometry lags the agent's by up to that; at the end of the mission every keyframe
    that moved 1 mm is sent again, and the outbox's last pose of each is within 1 mm of where the fusion
    ends (the smoothing had moved some by more than that after their keyframe message)."""
    from hivemap.client.runner import RunnerOptions
    from hivemap.protocol import Keyframe, PoseUpdates

    vio: dict[int, np.ndarray] = {}
    tap = _latest_vio(vio)
    runner = RunnerOptions(progress=False)
    assert runner.stream_final_resend == (0.001, 0.01) and runner.stream_resend == (0.03, 0.5)
    agent, msgs = _stream_tapped(tiny_agent, tmp_path, runner, tap)
    first = {m.kf_id: m.world_from_cam for m in msgs if isinstance(m, Keyframe)}
    last = dict(first)
    for m in msgs:
        if isinstance(m, PoseUpdates):
            last.update(zip(m.kf_ids.tolist(), m.world_from_cam, strict=True))
    final = {k: agent.core.stream_from_vio(0, k) @ vio[k] for k in first}
    moved = max(float(np.linalg.norm(final[k][:3, 3] - T[:3, 3])) for k, T in first.items())
    assert len(first) > 3 and moved > 0.001, moved
    for k, T in last.items():
        assert np.linalg.norm(final[k][:3, 3] - T[:3, 3]) < 0.001 + 1e-9, k


def _shape_error(a: np.ndarray, b: np.ndarray) -> float:
    """RMS distance (m) between two sets of positions after the rigid motion that best aligns them."""
    from hivemap.server.backend.fit import umeyama

    return float(np.sqrt(np.mean(np.sum((umeyama(a, b, with_scale=False).apply(a) - b) ** 2, axis=1))))


def test_a_finished_agent_takes_the_servers_estimate_of_all(tiny_agent: Path, tmp_path: Path) -> None:
    """A correction carries only some keyframes (every stride-th and the moved ones), and an agent used
    to end with whatever priors its last one left. Here a stale correction holds the first half of the
    keyframes 0.5 m off the rest, bending the agent's trajectory; at the end the agent reads the
    server's estimate of all its keyframes and fuses it in place of those priors: every keyframe gets
    one, and the agent's keyframes take the server's shape again (within 2 mm after a rigid alignment;
    the stale correction had bent them by over 1 cm)."""
    from srv_helpers import TOKENS, ServerProcess, write_config

    from hivemap.client.health import fetch_trajectory

    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        agent = Agent.from_calibration([tiny_agent], agent_id="uav1")
        agent.connect(server.ws_url, TOKENS["uav1"], tmp_path / "agent")
        events = _tap_events(agent)
        _feed(agent, load_dataset(tiny_agent))
        kfs = [e for e in events if hasattr(e, "keypoints")]
        assert len(kfs) > 3
        session = agent.mission_session
        assert session is not None
        off = np.eye(4)
        off[:3, 3] = [0.5, 0.0, 0.0]
        half = len(kfs) // 2
        held_off = np.array([(off if n < half else np.eye(4)) @ e.world_from_cam for n, e in enumerate(kfs)])
        ids = np.array([e.kf_id for e in kfs], np.int64)
        stale = Correction(0, np.eye(4), ids, held_off, session=session)
        agent.submit_correction(stale)
        agent.apply_corrections()
        assert agent.core.corrections_applied == len(kfs)
        _, bent = agent.core.stage.keyframe_poses()
        assert agent.close(timeout=30) == 0
        all_ids, held = fetch_trajectory(server.ws_url, "uav1", session, "local")
        assert agent.core.corrections_applied == len(kfs) + len(all_ids) and len(all_ids) >= len(kfs)
        _, final = agent.core.stage.keyframe_poses()
        n = len(bent)
        assert _shape_error(bent[:, :3, 3], held[:n, :3, 3]) > 0.01
        assert _shape_error(final[:n, :3, 3], held[:n, :3, 3]) < 0.002
    finally:
        server.stop()
