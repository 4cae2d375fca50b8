"""Fixtures shared by every test folder."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hivemap.cli.main import app


@pytest.fixture(scope="session")
def render_tiny_uav(tmp_path_factory: pytest.TempPathFactory) -> Callable[[float], Path]:
    """The tiny scenario's uav1 for its first ``duration_s`` seconds (EuRoC layout), rendered by `hivemap
    sim render` once per duration and test session. Read-only: tests that damage a dataset copy it."""
    done: dict[float, Path] = {}

    def render(duration_s: float) -> Path:
        if duration_s not in done:
            out = tmp_path_factory.mktemp(f"tiny{duration_s:g}s")
            what = ["--scenario", "tiny", "--agents", "uav1", "--duration", f"{duration_s:g}"]
            res = CliRunner().invoke(app, ["sim", "render", *what, "--out", str(out), "--no-progress"])
            assert res.exit_code == 0, res.output
            done[duration_s] = out / "uav1"
        return done[duration_s]

    return render


@pytest.fixture(scope="session")
def tiny_uav(render_tiny_uav: Callable[[float], Path]) -> Path:
    """The tiny scenario's uav1, 6 s: take-off and the first metres of flight."""
    return render_tiny_uav(6.0)
