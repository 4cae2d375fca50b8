"""Known start configuration (paper 2.4: UAVs take off from the UGV's roof): agents with declared start
poses end up in one map right after their first keyframes, with the transform the start poses imply."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import uvicorn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from agent_client import SyncAgent  # noqa: E402
from srv_helpers import TOKENS, free_port  # noqa: E402

from hivemap.maps.geometry import se3, se3_inverse, so3_exp  # noqa: E402
from hivemap.server.app import create_app, uvicorn_config_kwargs  # noqa: E402
from hivemap.server.loadgen import synthetic_stream  # noqa: E402
from hivemap.server.settings import ServerSettings  # noqa: E402


def test_start_poses_merge_at_first_keyframe(tmp_path: Path) -> None:
    # Two agents' streams, each in its own VIO frame; their true start poses in a common frame.
    msgs_a, truth_a = synthetic_stream("ugv1", 6, features=150, seed=3)
    msgs_b, truth_b = synthetic_stream("uav1", 6, features=150, seed=4, offset=(2.0, -1.0, 0.5))
    start_a = se3(so3_exp([0.0, 0.0, 0.3]), [10.0, 5.0, 1.2])  # common_from_cam of ugv1's first keyframe
    start_b = se3(so3_exp([0.1, -0.2, 1.0]), [10.5, 5.2, 2.0])
    settings = ServerSettings(
        port=free_port(), data_dir=tmp_path / "d", tokens=TOKENS, log_level="warning",
        start_poses={"ugv1": start_a.tolist(), "uav1": start_b.tolist()},
    )  # fmt: skip
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, **uvicorn_config_kwargs(settings)))  # type: ignore[arg-type]
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    while not (server.started and app.state.hive.loaded.is_set()):  # the store loads after start-up
        time.sleep(0.05)
    try:
        url = f"ws://127.0.0.1:{settings.port}/ws"
        for agent_id, msgs in (("ugv1", msgs_a), ("uav1", msgs_b)):
            with SyncAgent(
                url, agent_id, TOKENS[agent_id], kind="ugv" if agent_id == "ugv1" else "uav"
            ) as ag:
                ag.welcome()
                _, errors = ag.send_all(msgs)
                assert not errors
        hive = app.state.hive
        deadline = time.monotonic() + 20
        while (len(hive.stack.maps) > 1 or not hive.backend.merges) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(hive.stack.maps) == 1, "the two agents were not merged from their start poses"
        (m,) = hive.stack.maps.values()
        # The UGV's map keeps its frame; uav1's first keyframe sits where the start poses say.
        a0 = m.keyframes[("ugv1", 0)].world_from_cam
        b0 = m.keyframes[("uav1", 0)].world_from_cam
        np.testing.assert_allclose(a0, truth_a.kf_poses[0], atol=1e-9)
        expected_b0 = se3_inverse(start_a @ se3_inverse(truth_a.kf_poses[0])) @ start_b
        np.testing.assert_allclose(b0, expected_b0, atol=1e-6)
        assert any(r.get("by") == "start_pose" for r in hive.backend.merges)
    finally:
        server.should_exit = True
        th.join(10)


def test_start_poses_must_be_rigid() -> None:
    with pytest.raises(ValueError, match="start_poses.uav1"):
        ServerSettings(start_poses={"uav1": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
