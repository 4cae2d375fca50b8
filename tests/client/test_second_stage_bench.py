"""bench/second_stage.py: a recording of an agent's second stage replays to the run's own keyframes."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from hivemap.eval.trajectory import read_tum


def test_a_recorded_stage_replays_to_the_runs_keyframes(
    tiny_agent: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    bench_module: Callable[[str], ModuleType],
) -> None:
    import pickle

    bench = bench_module("second_stage")
    rec_path, run = tmp_path / "uav1.pkl", tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["second_stage.py", "record", "--dataset", str(tiny_agent), "--out",
                                      str(rec_path), "--run-out", str(run), "--no-progress"])  # fmt: skip
    bench.main()
    with open(rec_path, "rb") as f:
        rec = pickle.load(f)
    names = [c[0] for c in rec["calls"]]
    assert names.count("add_keyframe") >= 3 and "add_imu" in names
    out = bench.replay(rec, rec["options"])
    ts, poses = out["final"]
    kf = read_tum(run / "keyframes_local.tum")
    assert len(ts) == len(kf.timestamps)
    np.testing.assert_allclose(ts, kf.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses[:, :3, 3], kf.positions_xyz, atol=1e-6)
    # a variant really changes the stage: without the IMU it follows the tracking exactly
    plain = bench.replay(rec, bench._variant(rec["options"], ["imu=None"]))
    vt, vio = out["vio"]
    np.testing.assert_allclose(plain["final"][1][:, :3, 3] - plain["final"][1][:1, :3, 3],
                               vio[:, :3, 3] - vio[:1, :3, 3], atol=1e-3)  # fmt: skip
