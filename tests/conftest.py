"""Fixtures shared by every test folder."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

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


@pytest.fixture(scope="session")
def bench_module() -> Callable[[str], ModuleType]:
    """``bench/<name>.py`` imported by path (bench/ is not a package); registered in ``sys.modules`` under
    ``bench_<name>``, which its dataclasses need while it executes."""

    def load(name: str) -> ModuleType:
        path = Path(__file__).resolve().parents[1] / "bench" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        return mod

    return load
