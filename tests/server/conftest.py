"""Fixtures shared by the server tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from hivemap.cli.main import app


@pytest.fixture(scope="session")
def tiny_uav(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny scenario's uav1, 6 s, rendered once per test session (EuRoC layout)."""
    out = tmp_path_factory.mktemp("tiny")
    res = CliRunner().invoke(
        app, ["sim", "render", "--scenario", "tiny", "--agents", "uav1", "--duration", "6", "--out", str(out),
              "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return out / "uav1"
