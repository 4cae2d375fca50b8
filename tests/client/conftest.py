"""Fixtures shared by the client tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from hivemap.cli.main import app


@pytest.fixture(scope="session")
def tiny_agent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny scenario's uav1, 2 s (21 stereo frames, IMU, GNSS), rendered once per session. Read-only:
    tests that damage a dataset copy it first."""
    out = tmp_path_factory.mktemp("tiny2s")
    res = CliRunner().invoke(
        app, ["sim", "render", "--scenario", "tiny", "--agents", "uav1", "--duration", "2", "--out", str(out),
              "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return out / "uav1"


@pytest.fixture(scope="session")
def tiny_agent_6s(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny scenario's uav1 for 6 s: the 2-s one is mostly the standstill before take-off. Read-only."""
    out = tmp_path_factory.mktemp("tiny6s")
    res = CliRunner().invoke(
        app, ["sim", "render", "--scenario", "tiny", "--agents", "uav1", "--duration", "6", "--out", str(out),
              "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return out / "uav1"
