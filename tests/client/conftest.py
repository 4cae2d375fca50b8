"""Fixtures shared by the client tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_agent(render_tiny_uav: Callable[[float], Path]) -> Path:
    """The tiny scenario's uav1, 2 s (21 stereo frames, IMU, GNSS): mostly the standstill before take-off."""
    return render_tiny_uav(2.0)
