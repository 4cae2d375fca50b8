"""`hivemap eval ate` prints the ATE of a file against ground truth (real CLI, real files)."""

from __future__ import annotations

import re

import numpy as np
from typer.testing import CliRunner

from hivemap.cli.main import app
from hivemap.eval.trajectory import trajectory_from_poses, write_tum
from hivemap.maps.geometry import se3


def _value(out: str, key: str) -> float:
    m = re.search(rf"^{re.escape(key)}\s+([-0-9.]+)", out, re.M)
    assert m, out
    return float(m.group(1))


def test_eval_ate_table(tmp_path):
    t = 0.05 * np.arange(300)
    P = np.stack([se3(np.eye(3), np.array([np.cos(0.1 * x) * 10, np.sin(0.13 * x) * 8, 0.1 * x])) for x in t])
    Q = P.copy()
    Q[:, :3, 3] += np.array([0.0, 0.0, 0.25])  # a known 0.25 m constant offset
    write_tum(tmp_path / "gt.tum", trajectory_from_poses(t, P))
    write_tum(tmp_path / "est.tum", trajectory_from_poses(t, Q))
    runner = CliRunner()
    base = ["eval", "ate", "--est", str(tmp_path / "est.tum"), "--gt", str(tmp_path / "gt.tum")]
    none = runner.invoke(app, [*base, "--align", "none"])
    assert none.exit_code == 0, none.output
    assert _value(none.output, "ATE RMSE [m]") == 0.25  # printed with 4 decimals
    assert _value(none.output, "poses matched") == 300
    se3_run = runner.invoke(app, base)
    assert se3_run.exit_code == 0, se3_run.output
    assert _value(se3_run.output, "ATE RMSE [m]") == 0.0
    bad = runner.invoke(app, [*base, "--align", "affine"])
    assert bad.exit_code != 0


def test_eval_team_table(tmp_path):
    """Two agents, B changes frame at t=10 s and is 0.5 m off after the merge: the table shows
    the merge time and the 0.5 m inter-agent relative error."""
    from test_trajectory import _two_agents  # same directory (pytest's default prepend import mode)

    from hivemap.eval.trajectory import write_frame_timeline

    args = []
    for run in _two_agents(extra_offset_b=0.5):
        write_tum(tmp_path / f"{run.agent_id}_est.tum", run.est)
        write_tum(tmp_path / f"{run.agent_id}_gt.tum", run.gt)
        write_frame_timeline(tmp_path / f"{run.agent_id}_frames.csv", run.frames)
        p = f"{tmp_path}/{run.agent_id}"
        args += ["--agent", f"{run.agent_id}={p}_est.tum,{p}_gt.tum,{p}_frames.csv"]
    res = CliRunner().invoke(app, ["eval", "team", *args])
    assert res.exit_code == 0, res.output
    row_b = next(line.split() for line in res.output.splitlines() if line.startswith("b "))
    assert float(row_b[-1]) == 10.0  # merge time
    m = re.search(r"a-b \[global\] n=\d+ trans rmse ([0-9.]+) m", res.output)
    assert m and float(m.group(1)) == 0.5
