"""The report's section setting hivemap beside ORB-SLAM3 (bench/orbslam3.py's summary)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hivemap.eval.peer import peer_section, rewrite_report


def _row(world: str, agent: str, hm: float | None, orb: float | None) -> dict[str, object]:
    path = 100.0
    row: dict[str, object] = {"world": world, "agent": agent, "orbslam3": {"tracking_losses": 1, "maps": 2}}
    if hm is not None:
        row["hm"] = {"ate_rmse": hm, "ate_pct": 100 * hm / path}
    if orb is not None:
        row["orb"] = {"ate_rmse": orb, "ate_pct": 100 * orb / path}
    return row


def test_the_section_compares_the_means_over_agents_with_both_figures(tmp_path: Path) -> None:
    rows = [
        _row("f-s1", "uav1", 0.04, 0.06),
        _row("f-s1", "ugv", 0.06, 3.00),
        _row("f-s3", "uav1", 0.15, 0.08),
        _row("f-s3", "ugv", 0.10, None),  # ORB-SLAM3 gave no trajectory: left out of the means
    ]
    (tmp_path / "orbslam3").mkdir()
    (tmp_path / "orbslam3" / "summary.json").write_text(json.dumps(rows))
    md = "\n".join(peer_section(tmp_path))
    assert "| f-s1 | ugv | 0.060 (0.060 %) | 3.000 (3.000 %) | 1 / 2 |" in md
    assert "| f-s3 | ugv | 0.100 (0.100 %) | - | 1 / 2 |" in md
    # per world: f-s1 hivemap (0.04 + 0.06) / 2, ORB-SLAM3 (0.06 + 3.00) / 2; f-s3 one agent
    assert "| f-s1 | 2 | 0.050 / 0.060 | 1.530 / 3.000 |" in md
    assert "| f-s3 | 1 | 0.150 / 0.150 | 0.080 / 0.080 |" in md
    # all: hivemap (0.04 + 0.06 + 0.15) / 3 = 0.0833, ORB-SLAM3 (0.06 + 3.00 + 0.08) / 3 = 1.0467
    assert "| all | 3 | 0.083 / 0.150 | 1.047 / 3.000 |" in md
    assert "hivemap's mean ATE (0.083 m) is at most ORB-SLAM3's (1.047 m)." in md


def test_a_worse_mean_is_said_and_no_run_gives_no_section(tmp_path: Path) -> None:
    assert peer_section(tmp_path) == []
    (tmp_path / "orbslam3").mkdir()
    (tmp_path / "orbslam3" / "summary.json").write_text(json.dumps([_row("w", "uav1", 0.2, 0.1)]))
    assert "hivemap's mean ATE (0.200 m) is above ORB-SLAM3's (0.100 m)." in "\n".join(peer_section(tmp_path))


def test_rewriting_a_folder_without_results_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no results/"):
        rewrite_report(tmp_path)
