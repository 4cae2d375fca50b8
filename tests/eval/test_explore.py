"""The explore mode's bookkeeping (issue 26): pair distances against inflated radii, take-off left out, and
the report section with its coverage plot, on hand-made runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hivemap.client.replay_io import write_tum_poses
from hivemap.eval.explore import explore_agents, explore_section, goal_changes, pair_distances
from hivemap.sim.scenarios import get_scenario


def _agent(work: Path, aid: str, xyz: np.ndarray, radius: float, half: float | None = 0.3) -> None:
    out = work / aid
    out.mkdir(parents=True)
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    T[:, :3, 3] = xyz
    write_tum_poses(out / "groundtruth.tum", 1.7e9 + 0.05 * np.arange(len(xyz)), T)
    log: list[dict[str, float]] = [{"t": 0.0, "radius": radius}, {"t": 0.9, "radius": radius + 0.2}]
    if half is not None:
        for e in log:
            e["half_height"] = half
    (out / "live.json").write_text(json.dumps({"advisory_log": log}))


def test_pair_distances(tmp_path: Path) -> None:
    n = 41
    # a starts at the origin next to b (0.35 m apart: the take-off) and flies east at 0.5 m per frame
    # (10 m/s, frames 0.05 s apart); b moves to (10, 1) and stays: once a has left the start zone (3 m) they
    # come 1 m close at frame 20 (t = 1 s), when the latest advisories (t = 0.9 s) gave radii 0.7 + 0.5
    a = np.stack([0.5 * np.arange(n), np.zeros(n), np.zeros(n)], 1)
    b = np.tile([10.0, 1.0, 0.0], (n, 1))
    b[:5] = [0.0, 0.35, 0.0]
    b[5:10] = np.linspace([0.0, 0.35, 0.0], [10.0, 1.0, 0.0], 5)
    # c hovers 1 m over b's spot: horizontally as close, but vertically clear of a (the gap is more than
    # the two half heights, 0.3 m each, though less than the radii)
    c = b + [0.0, 0.0, 1.0]
    _agent(tmp_path, "uav1", a, 0.5)
    _agent(tmp_path, "uav2", b, 0.3)
    _agent(tmp_path, "uav3", c, 0.3)
    ab, ac, _ = pair_distances([("uav1", "uav"), ("uav2", "uav"), ("uav3", "uav")], tmp_path)
    assert np.isclose(ab["min_all_m"], 0.35) and np.isclose(ab["min_m"], 1.0)
    assert np.isclose(ab["radii_m"], 1.2) and np.isclose(ab["margin_m"], -0.2) and ab["clear"] is False
    assert ac["clear"] is True and ac["margin_m"] is None and np.isclose(ac["min_m"], np.hypot(1.0, 1.0))
    # a run logged before half heights (a server whose cylinders were as high as their radii): near
    _agent(tmp_path / "old", "uav1", a, 0.5, None)
    _agent(tmp_path / "old", "uav3", c, 0.3, None)
    (old,) = pair_distances([("uav1", "uav"), ("uav3", "uav")], tmp_path / "old")
    assert old["clear"] is False and np.isclose(old["margin_m"], -0.2)


def test_agents_of_the_modes_and_the_report(tmp_path: Path) -> None:
    sc = get_scenario("factory01")
    assert explore_agents(sc, "explore", None) == [
        ("uav1", "uav"),
        ("uav2", "uav"),
        ("uav3", "uav"),
        ("ugv", "ugv"),
    ]
    assert explore_agents(sc, "explore1", None) == [("uav1", "uav")]
    assert explore_agents(sc, "explore", ["uav2", "ugv"]) == [("uav2", "uav"), ("ugv", "ugv")]
    cov = {"times": [0.0, 1.0, 2.0], "fraction": [0.1, 0.5, 0.85], "final": 0.85, "t_target": 2.0, "cells": 9}
    log = [{"goals": [[0.0, 0.0, 1.0]]}, {"goals": [[5.0, 0.0, 1.0]]}]
    live = {"path_length_m": 12.0, "advisories": 2, "goals_reached": 1, "advisory_log": log}
    agent = {"agent_id": "uav1", "ate_rmse": 0.1, "run": {"live": live}}
    run = {
        "coverage": {"team": cov, "target": 0.8},
        "agents": [agent],
        "pairs": [],
        "explore_duration_s": 2.0,
    }
    md = explore_section(tmp_path, {("w", "explore1"): run, ("w", "denied"): {"agents": []}}, tmp_path)
    row = next(line for line in md if line.startswith("| w | explore1"))
    assert "85.0%" in row and "2.0 (target 80%)" in row and "uav1 12" in row
    goals = next(line for line in md if line.startswith("| w | explore1 | uav1 |"))
    assert goals == "| w | explore1 | uav1 | 2 | 1 | 1 | 0 | 0.833 % |"
    assert (tmp_path / "img" / "coverage.png").stat().st_size > 1000


def test_goal_changes_by_hand() -> None:
    # first goals A, A + 0.5 m (kept), B, A (back to a recent one), C, no goals (skipped), C
    a, b, c = [0.0, 0.0, 2.0], [10.0, 0.0, 2.0], [0.0, 10.0, 2.0]
    log = [{"goals": [g]} for g in (a, [0.5, 0.0, 2.0], b, a, c)] + [{"goals": []}, {"goals": [c, a]}]
    assert goal_changes(log) == (3, 1)
    assert goal_changes(log, jump_m=20.0) == (0, 0)
    assert goal_changes([]) == (0, 0)


def test_explore_server_quota_grows_with_the_run() -> None:
    """A short run keeps the server's default point cap; a 20-minute one gets 1000 points a second, so a
    live agent's later map is not refused (the lone UAV hit the 300k cap after ~12 minutes)."""
    import tomllib

    from hivemap.eval.explore import explore_server_toml
    from hivemap.server.settings import QuotaSettings

    short, long = (tomllib.loads(explore_server_toml(d)) for d in (120.0, 1200.0))
    assert short["quotas"]["max_points"] == QuotaSettings().max_points == 300_000
    assert long["quotas"]["max_points"] == 1_200_000 and long["team"]["push_interval_s"] == 0.5
