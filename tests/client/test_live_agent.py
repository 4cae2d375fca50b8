"""A live simulated agent (issue 26) against a real `hivemap server` with its team services: it gets goals
from the server's auction over the WebSocket, drives towards the first one, and the keyframes it streamed
track its ground truth."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from srv_helpers import ServerProcess, write_config  # noqa: E402

from hivemap.client.live import run_live  # noqa: E402
from hivemap.client.runner import RunnerOptions  # noqa: E402
from hivemap.eval.trajectory import ate, read_tum  # noqa: E402
from hivemap.server.team.options import TeamOptions  # noqa: E402
from hivemap.sim.live import LiveOptions  # noqa: E402

# SE(3)-aligned RMSE over the ~8 m a test run drives: the keyframes as streamed (no back-end here) and the
# agent's own final trajectory
TOL_STREAMED_M = 0.10
TOL_OWN_M = 0.05


def test_live_ugv_drives_to_its_goal_and_tracks(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "server.toml", {"ugv": "tok-ugv"})
    cfg.write_text(cfg.read_text() + "[team]\nmin_interval_s = 0.2\npush_interval_s = 0.3\n")
    server = ServerProcess(tmp_path / "data", cfg).start()
    out = tmp_path / "ugv"
    seen: list[dict[str, object]] = []  # the UGV's advisories on /team/assignments during the run
    done = threading.Event()

    def poll() -> None:
        while not done.wait(0.5):
            r = server.get("/team/assignments")
            if r.status_code == 200:
                seen.extend(
                    a["advisory"] for m in r.json()["maps"] for a in m["agents"] if a["agent_id"] == "ugv"
                )

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    try:
        # the "tiny" preset (320x240 at 10 Hz): 120 frames, half a second standing still
        summary, ls = run_live(
            LiveOptions("tiny", "ugv", duration_s=12.0, hold_s=0.5), out, server.ws_url, "ugv", "tok-ugv",
            RunnerOptions(progress=False, corrections_max_wait_s=5.0),
        )  # fmt: skip
        r = server.get("/agents/ugv/trajectory", frame="global", format="tum")
        assert r.status_code == 200
        (out / "server_global.tum").write_text(r.text)
    finally:
        done.set()
        poller.join(timeout=10.0)
        server.stop()
    assert ls.stopped_by == "duration" and ls.frames == 121 and summary.unsent == 0
    assert json.loads((out / "live.json").read_text())["frames"] == 121
    # the first advisory with goals: the agent ends at least 3 m closer to its first goal (world frame)
    first = next(a for a in ls.advisory_log if a["goals"])
    goal = np.array(first["goals"][0])
    gt = read_tum(out / "groundtruth.tum")
    t = np.asarray(gt.timestamps) - gt.timestamps[0]
    xy = np.asarray(gt.positions_xyz)[:, :2]
    k = int(np.searchsorted(t, first["t"]))
    d = np.linalg.norm(xy - goal, axis=1)
    assert d[k:].min() < d[k] - 3.0, (d[k], d[k:].min())
    assert ls.path_length_m > 4.0
    # its keyframes told the server where it is going (the controller's intent): the desired velocity is it
    told = [a for a in seen if a["intent"] is not None]
    assert len(told) >= 5, len(seen)
    top = TeamOptions().orca.max_speed_ugv
    for a in told:  # cut to the server's top speed for a UGV
        i = np.asarray(a["intent"])
        want = np.array([*(i[:2] * min(1.0, top / max(np.linalg.norm(i[:2]), 1e-12))), i[2]])
        np.testing.assert_allclose(a["desired_velocity"], want, atol=1e-9)
    assert max(np.linalg.norm(np.asarray(a["intent"])[:2]) for a in told) > 0.5
    # on the ground: the body stays at the UGV's height, upright
    assert np.allclose(np.asarray(gt.positions_xyz)[:, 2], 0.9, atol=1e-6)
    # what it streamed tracks the truth: the server's keyframes (cam0) and the agent's own trajectory
    srv = ate(
        read_tum(out / "server_global.tum"), read_tum(out / "groundtruth_cam0.tum"), "se3", max_diff=0.01
    )
    assert srv.stats.n >= 10 and srv.stats.rmse < TOL_STREAMED_M, srv.stats
    own = ate(read_tum(out / "local.tum"), gt, "se3", max_diff=0.01)
    assert own.stats.n >= 100 and own.stats.rmse < TOL_OWN_M, own.stats
