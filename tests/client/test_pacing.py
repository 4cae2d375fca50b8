"""Replay pacing (issue 23): frames at the recording's clock, and a live agent that falls behind takes
the newest frame. The pacer's choices against a simulated clock (hand-computed), then `hivemap agent
--pace live` on a rendered dataset, whose wall time must follow the recording's."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from hivemap.cli.main import app
from hivemap.client.dataset import load_dataset
from hivemap.client.pacing import Pacer
from hivemap.eval.trajectory import ate, groundtruth_trajectory, read_tum


class SimClock:
    """Wall time that advances only by the work done and the pacer's sleeps."""

    def __init__(self) -> None:
        self.now = 100.0
        self.slept = 0.0

    def clock(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        assert dt > 0
        self.now += dt
        self.slept += dt


def _replay(pace: str, n: int, period: float, cost: float) -> tuple[list[int], Pacer, SimClock]:
    """Frames every ``period`` s, each costing ``cost`` s of work; returns the indices processed."""
    sim = SimClock()
    pacer = Pacer(np.arange(n) * period, pace, clock=sim.clock, sleep=sim.sleep)
    taken, i = [], 0
    while i < n:
        i = pacer.take(i)
        taken.append(i)
        sim.now += cost
        i += 1
    return taken, pacer, sim


def test_asap_takes_every_frame_without_waiting():
    taken, pacer, sim = _replay("asap", 10, 0.05, 0.2)
    assert taken == list(range(10)) and sim.slept == 0.0 and pacer.dropped == 0


def test_camera_pace_waits_for_each_frame_and_never_drops():
    # 20 ms of work per 50 ms frame: each frame is taken exactly when due, 30 ms of sleep before it
    taken, pacer, sim = _replay("camera", 10, 0.05, 0.02)
    assert taken == list(range(10)) and pacer.dropped == 0 and pacer.late_max_s == 0.0
    assert sim.slept == pytest.approx(9 * 0.03)
    # 120 ms of work per frame: every frame still taken, the last one 9 * 70 ms late
    taken, pacer, _ = _replay("camera", 10, 0.05, 0.12)
    assert taken == list(range(10)) and pacer.dropped == 0
    assert pacer.late_max_s == pytest.approx(9 * 0.07)


def test_live_pace_takes_the_newest_due_frame():
    # 120 ms of work per 50 ms frame: frame 0 at t=0 ends at 0.12, when frames 1-2 are due -> take 2;
    # it ends at 0.24 (due: 3, 4) -> take 4; ends at 0.36 (due up to 7) -> 7; 0.48 -> 9
    taken, pacer, _ = _replay("live", 10, 0.05, 0.12)
    assert taken == [0, 2, 4, 7, 9]
    assert pacer.dropped == 5
    assert pacer.late_max_s < 0.05  # a frame is taken at most one period after it was due


def test_unknown_pace_is_refused():
    with pytest.raises(ValueError, match="unknown pace"):
        Pacer(np.arange(3.0), "fast")


def test_agent_at_live_pace_follows_the_recordings_clock(tiny_uav, tmp_path):
    out = tmp_path / "live"
    res = CliRunner().invoke(
        app, ["agent", "--dataset", str(tiny_uav), "--offline", "--out", str(out), "--pace", "live",
              "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "live pace:" in res.output
    summary = json.loads((out / "run.json").read_text())
    frames = load_dataset(tiny_uav).frames.t_ns
    span = (int(frames[-1]) - int(frames[0])) * 1e-9
    assert summary["pace"] == "live"
    # every frame either processed or dropped, and the replay took at least the recording's duration
    assert summary["frames"] + summary["frames_dropped"] == len(frames)
    assert summary["wall_s"] >= span - 0.05
    gt = groundtruth_trajectory(tiny_uav)
    assert ate(read_tum(out / "local.tum"), gt, "se3").stats.rmse < 0.1


def test_bad_pace_is_one_line(tiny_agent, tmp_path):
    res = CliRunner().invoke(
        app, ["agent", "--dataset", str(tiny_agent), "--offline", "--out", str(tmp_path), "--pace", "x"]
    )
    assert res.exit_code == 2 and "--pace" in res.output
