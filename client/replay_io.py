"""The offline replay's inputs and outputs: GNSS modes (paper Table 8), the dataset adapter (frame
times, stereo pairs, IMU, GNSS fixes) and TUM trajectory files. Split out of ``hivemap.client.runner``,
which re-exports these names.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


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


# ---------------------------------------------------------------------------------------- dataset adapter
@dataclass(frozen=True)
class _Gnss:
    t: F64  # (N,) seconds
    enu: F64  # (N, 3)
    cov: F64  # (N, 3, 3)
    valid: NDArray[np.bool_]


def _seconds(t: F64) -> F64:
    t = np.asarray(t, dtype=np.float64)
    return t * 1e-9 if t.size and np.nanmedian(np.abs(t)) > 1e12 else t


def _gnss_table(ds: object) -> _Gnss:
    """The dataset's GNSS fixes as arrays (t, enu, 3x3 covariance from sigma_h / sigma_v)."""
    g = getattr(ds, "gnss", None)
    if g is None:
        z = np.zeros(0)
        return _Gnss(z, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, bool))
    t = _seconds(np.asarray(g.timestamps if hasattr(g, "timestamps") else g.t))
    enu = np.asarray(g.enu, dtype=np.float64).reshape(-1, 3)
    sig = np.asarray(g.sigma, dtype=np.float64)
    if sig.ndim == 1:
        sig = np.stack([sig, sig], axis=1)
    sh, sv = sig[:, 0], sig[:, -1]
    cov = np.zeros((len(t), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = sh**2
    cov[:, 2, 2] = sv**2
    valid = np.all(np.isfinite(enu), axis=1) & np.isfinite(sh) & np.isfinite(sv) & (sh > 0) & (sv > 0)
    return _Gnss(t, enu, cov, valid)


def _frame_times(ds: object) -> F64:
    fr = ds.frames  # type: ignore[attr-defined]
    for name in ("timestamps", "t", "times"):
        if hasattr(fr, name):
            return _seconds(np.asarray(getattr(fr, name)))
    return _seconds(np.array([f.timestamp for f in fr]))


def _load_pair(ds: object, i: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    fr = ds.frames  # type: ignore[attr-defined]
    for name in ("load", "load_pair", "images", "stereo"):
        fn = getattr(fr, name, None)
        if callable(fn):
            left, right = fn(i)
            return left, right
    item = fr[i]
    if isinstance(item, tuple):
        return item[-2], item[-1]
    for a, b in (("left", "right"), ("cam0", "cam1")):
        if hasattr(item, a):
            la, lb = getattr(item, a), getattr(item, b)
            return (la() if callable(la) else la), (lb() if callable(lb) else lb)
    raise TypeError("cannot load stereo images from the dataset's frames")


def _imu(ds: object) -> F64:
    imu = np.asarray(getattr(ds, "imu", np.zeros((0, 7))), dtype=np.float64).reshape(-1, 7).copy()
    imu[:, 0] = _seconds(imu[:, 0])
    return imu


def _imu_params(ds: object) -> dict[str, float] | None:
    for name in ("imu_params", "imu_noise", "imu_sensor"):
        p = getattr(ds, name, None)
        if isinstance(p, dict):
            return {k: float(v) for k, v in p.items() if isinstance(v, int | float)}
    return {} if len(_imu(ds)) else None


# ---------------------------------------------------------------------------------------- outputs
def write_tum_poses(path: str | Path, times: F64, poses: F64) -> None:
    """TUM file ``t tx ty tz qx qy qz qw`` from (N,) seconds and (N, 4, 4) poses."""
    from hivemap.maps.geometry import quat_wxyz_from_rotmat

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        for t, T in zip(np.asarray(times), np.asarray(poses).reshape(-1, 4, 4), strict=True):
            w, x, y, z = quat_wxyz_from_rotmat(T[:3, :3])
            f.write(f"{t:.9f} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}\n")
