"""The offline agent (client/runner.py) with the real front-end and second stage on a rendered
synthetic stereo + IMU sequence (the front-end's own synthetic scene), GNSS from ground truth + noise."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hivemap.client.frontend.synthetic import make_sequence
from hivemap.client.runner import (
    OfflineAgent,
    RunnerOptions,
    _Gnss,
    health_url,
    parse_gnss_mode,
    write_tum_poses,
)
from hivemap.eval.trajectory import ate, read_tum, trajectory_from_poses

SIGMA_H, SIGMA_V = 0.05, 0.15  # paper Table 3


@pytest.fixture(scope="module")
def run_all():
    seq = make_sequence(n_frames=40)  # 2 s, 20 Hz, ~4 m of a circle, 3 m above the origin
    rng = np.random.default_rng(0)
    tg = seq.times[::4]  # 5 Hz GNSS
    enu = seq.world_from_body[::4, :3, 3] + rng.normal(0, 1, (len(tg), 3)) * [SIGMA_H, SIGMA_H, SIGMA_V]
    cov = np.tile(np.diag([SIGMA_H**2, SIGMA_H**2, SIGMA_V**2]), (len(tg), 1, 1))
    gnss = _Gnss(tg, enu, cov, np.ones(len(tg), bool))
    agent = OfflineAgent(seq.rig, {}, gnss, RunnerOptions(gnss=parse_gnss_mode("all"), progress=False))
    agent.select(seq.times)
    prev = None
    for i, t in enumerate(seq.times):
        left, right = seq.images(i)
        agent.step(float(t), left, right, seq.imu_between(prev, float(t)))
        prev = float(t)
    agent.finish()
    return seq, agent


def test_offline_agent_fuses_gnss(run_all):
    seq, agent = run_all
    gt = trajectory_from_poses(seq.times, seq.world_from_body)
    tv, vio = agent.vio_trajectory()
    tl, local = agent.local_trajectory()
    assert len(tv) == len(seq.times) and agent.losses == 0
    assert len(agent.stage.keyframe_ids) >= 5
    assert agent.gnss_used == int(agent.selected.sum()) > 5 and agent.gnss_rejected == 0
    vio_none = ate(trajectory_from_poses(tv, vio), gt, "none").stats.rmse
    local_none = ate(trajectory_from_poses(tl, local), gt, "none").stats.rmse
    # The VIO frame starts at the first body pose (3 m below the truth's): unaligned it is metres off.
    assert vio_none > 2.0
    # Fused with 5 Hz GNSS (5 cm horizontal, 15 cm vertical): every frame in ENU within 0.15 m RMS
    # (measured 0.04 m) without any alignment.
    assert local_none < 0.15, local_none


def test_tum_output_round_trip(run_all, tmp_path):
    _, agent = run_all
    tl, local = agent.local_trajectory()
    write_tum_poses(tmp_path / "local.tum", tl, local)
    back = read_tum(tmp_path / "local.tum")
    assert np.allclose(back.timestamps, tl)
    assert np.abs(np.asarray(back.positions_xyz) - local[:, :3, 3]).max() < 1e-5  # 6 decimals written


def test_health_url_from_the_websocket_address() -> None:
    assert health_url("ws://10.0.0.2:8765/ws") == "http://10.0.0.2:8765/health"
    assert health_url("wss://hive.example.org/hivemap/ws") == "https://hive.example.org/hivemap/health"
    assert health_url("ws://host:1/") == "http://host:1/health"
    with pytest.raises(ValueError, match="ftp://x/ws"):
        health_url("ftp://x/ws")


class _FlakyHealth:
    """A real HTTP /health endpoint whose first ``drop`` requests get no answer (connection closed);
    ``body(n)``, if given, is the n-th answer's JSON (1-based), else ``backend_idle`` = ``idle``."""

    def __init__(self, drop: int, idle: bool | None, body: Any = None) -> None:
        import http.server
        import json
        import threading

        outer = self
        self.requests = 0

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                outer.requests += 1
                if outer.requests <= drop:
                    self.close_connection = True
                    self.connection.close()
                    return
                answer = body(outer.requests - drop) if body is not None else (
                    {"status": "ok"} if idle is None else {"backend_idle": idle})  # fmt: skip
                data = json.dumps(answer).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *args: object) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"ws://127.0.0.1:{self.httpd.server_address[1]}/ws"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def _timed_wait(srv: _FlakyHealth, **options: float) -> float:
    """Seconds ``wait_for_server`` took against ``srv`` (grace 0, the given ``RunnerOptions``)."""
    import time

    from hivemap.client.health import wait_for_server

    try:
        t0 = time.monotonic()
        wait_for_server(srv.url, RunnerOptions(corrections_grace_s=0.0, **options), lambda: 0.0, lambda: None)
        return time.monotonic() - t0
    finally:
        srv.close()


@pytest.mark.parametrize(
    ("drop", "idle", "expect_health"),
    [
        (3, True, True),  # a few unanswered polls are retried: the back-end's idle state ends the wait
        (100, True, False),  # never answered: after health_max_failures the quiet timer ends it
        (0, None, False),  # an older server without backend_idle: the quiet timer
    ],
)
def test_wait_for_server_retries_unanswered_health_polls(drop: int, idle: bool | None, expect_health: bool):
    srv = _FlakyHealth(drop, idle)
    took = _timed_wait(srv, corrections_quiet_s=6.0, corrections_max_wait_s=30.0)
    if expect_health:
        # 3 dropped + 2 idle polls at 0.5 s: well before the 6 s quiet timer
        assert took < 5.0 and srv.requests == drop + 2, (took, srv.requests)
    else:
        assert took >= 6.0, took
        assert srv.requests == (5 if drop else 1), srv.requests  # health_max_failures, or one answer


def _team_server(n: int, done_from: int | None) -> dict[str, Any]:
    """A back-end never idle (the team still streams: 10 new keyframes a poll) that is through with the
    first 100 arrivals from poll ``done_from`` on (None: never gets past 90); its optimisation runs on
    poll ``done_from + 1`` only."""
    arrived = 100 + 10 * (n - 1)
    done = 90 if done_from is None or n < done_from else arrived - 5
    return {"backend_idle": False, "backend_arrived": arrived, "backend_done": done,
            "backend_optimising": done_from is not None and n == done_from + 1}  # fmt: skip


def test_a_finishing_agent_waits_until_the_server_caught_up_with_its_end_not_until_it_is_idle():
    srv = _FlakyHealth(0, None, lambda n: _team_server(n, done_from=6))
    took = _timed_wait(srv, corrections_stall_s=20.0, corrections_max_wait_s=30.0)
    # the first answer sets the mark (100 arrivals); done reaches it at poll 6, poll 7 still optimises, so
    # polls 8 and 9 end the wait, though the server is never idle
    assert srv.requests == 9, srv.requests
    assert took < 10.0, took


def test_a_server_that_makes_no_progress_ends_the_wait_early():
    srv = _FlakyHealth(0, None, lambda n: _team_server(n, done_from=None))
    took = _timed_wait(srv, corrections_stall_s=3.0, corrections_max_wait_s=30.0)
    # "done" stays at 90 < 100: the stall timer (3 s from the first answer), not the 30 s cap
    assert 3.0 <= took < 6.0, took
