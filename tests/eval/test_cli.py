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
