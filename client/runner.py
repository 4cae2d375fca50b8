"""Offline agent runner: dataset -> front-end -> second stage -> TUM trajectories + run log.

``run_offline(agent_dir, out_dir, options)`` replays one EuRoC-layout agent dataset through the
front-end (``hivemap.client.frontend``) and the second stage (``hivemap.client.second_stage``) with the
GNSS fixes a *GNSS mode* allows (paper Table 8):

- ``denied``: no fix is used;
- ``every:20s``: one valid fix every 20 s (the first valid fix, then the first valid fix at least
  20 s after the previously used one);
- ``random:4``: 4 valid fixes drawn at random (seeded) over the whole run;
- ``all``: every valid fix.

Outputs in ``out_dir``: ``vio.tum`` (every tracked frame, body pose in the VIO frame), ``local.tum``
(every tracked frame in the local frame, final smoothed estimate: the per-keyframe correction
interpolated between neighbouring keyframes), ``keyframes_local.tum``, ``run.json`` (summary: keyframe
count, tracking losses, GNSS used/rejected, timing) and ``frames.csv`` (per-frame timing and state).
TUM lines are ``t tx ty tz qx qy qz qw`` (seconds; quaternion x, y, z, w as TUM requires) of
``world_from_body`` (body = IMU frame, like the EuRoC ground truth).
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------- GNSS modes
@dataclass(frozen=True)
class GnssMode:
    """Which GNSS fixes an agent may use (paper Table 8)."""

    kind: Literal["denied", "every", "random", "all"]
    period_s: float = 0.0  # for "every"
    count: int = 0  # for "random"

    def __str__(self) -> str:
        if self.kind == "every":
            return f"every:{self.period_s:g}s"
        if self.kind == "random":
            return f"random:{self.count}"
        return self.kind


def parse_gnss_mode(text: str) -> GnssMode:
    """``denied`` | ``all`` | ``every:<seconds>[s]`` | ``random:<count>`` -> :class:`GnssMode`."""
    s = text.strip().lower()
    if s in ("denied", "none", "off"):
        return GnssMode("denied")
    if s == "all":
        return GnssMode("all")
    m = re.fullmatch(r"every:(\d+(?:\.\d*)?)s?", s)
    if m and float(m.group(1)) > 0:
        return GnssMode("every", period_s=float(m.group(1)))
    m = re.fullmatch(r"random:(\d+)", s)
    if m:
        return GnssMode("random", count=int(m.group(1)))
    raise ValueError(f"bad GNSS mode {text!r}: use denied, all, every:<seconds>s or random:<count>")


def select_gnss(times: F64, valid: NDArray[np.bool_], mode: GnssMode, seed: int = 0) -> NDArray[np.bool_]:
    """Boolean mask (N,) of the fixes the mode lets the agent use; ``times`` sorted, seconds."""
    times = np.asarray(times, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    out = np.zeros(times.shape, dtype=bool)
    idx = np.nonzero(valid)[0]
    if mode.kind == "all":
        out[idx] = True
    elif mode.kind == "every":
        last = -math.inf
        for i in idx:
            if times[i] - last >= mode.period_s - 1e-9:
                out[i] = True
                last = times[i]
    elif mode.kind == "random":
        rng = np.random.default_rng(seed)
        k = min(mode.count, idx.size)
        out[rng.choice(idx, size=k, replace=False)] = True
    return out


# ---------------------------------------------------------------------------------------- run
@dataclass(frozen=True)
class RunnerOptions:
    """Options of an offline run."""

    gnss: GnssMode = field(default_factory=lambda: GnssMode("denied"))
    seed: int = 0  # for random GNSS modes
    max_frames: int | None = None  # stop after this many frames (tests, quick looks)
    gnss_max_dt_s: float = 0.03  # a fix is attached to the frame closest in time within this
    progress: bool = True


@dataclass
class RunSummary:
    """What ``run.json`` holds."""

    agent_id: str
    gnss_mode: str
    frames: int = 0
    tracked_frames: int = 0
    keyframes: int = 0
    tracking_losses: int = 0
    segments: int = 0
    gnss_available: int = 0
    gnss_selected: int = 0
    gnss_used: int = 0
    gnss_rejected: int = 0
    frontend_ms_mean: float = 0.0
    frontend_ms_max: float = 0.0
    second_stage_ms_mean: float = 0.0
    second_stage_ms_max: float = 0.0
    wall_s: float = 0.0
    fps: float = 0.0
    outputs: dict[str, str] = field(default_factory=dict)
    rejected_fixes: list[dict[str, float]] = field(default_factory=list)

    def to_json(self) -> str:
        from dataclasses import asdict

        return json.dumps(asdict(self), indent=2)
