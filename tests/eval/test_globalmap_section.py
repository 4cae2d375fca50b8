"""The report's global-map table says what the agents streamed (a run's figures depend on it)."""

from __future__ import annotations

from hivemap.eval.globalmap import globalmap_section


def _run(**extra: object) -> dict[str, object]:
    team = [{"map": "map 1", "agents": ["uav1", "ugv"], "team_ate_rmse": 0.05}]
    return {"team": team, "loop_errors": [], "all_merged_s": 11.7, "start_poses": {"mode": "none"}, **extra}


def test_the_table_names_the_streamed_odometry_and_old_runs_streamed_the_tracking() -> None:
    md = globalmap_section({
        ("factory01", "denied"): _run(stream_imu_odometry=True),
        ("factory02", "denied"): _run(stream_imu_odometry=False),
        ("factory04", "denied"): _run(),  # written before the setting existed
    })  # fmt: skip
    rows = {r.split(" | ")[0].lstrip("| "): r.split(" | ") for r in md if r.startswith("| factory")}
    header = next(r for r in md if r.startswith("| scenario")).split(" | ")
    col = header.index("streamed")
    assert rows["factory01"][col] == "IMU fusion"
    assert rows["factory02"][col] == "tracking"
    assert rows["factory04"][col] == "tracking"
    assert all(len(r) == len(header) for r in rows.values())
