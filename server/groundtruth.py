"""Ground-truth trajectories for the viewer, read from files the server is pointed at.

Agents know nothing of ground truth (a real robot has none), so the server is given it by the person
running an evaluation: ``groundtruth = "DIR"`` (``--groundtruth DIR``), a folder with one entry per agent
id, either a EuRoC-layout agent folder ``DIR/<agent>/mav0/state_groundtruth_estimate0/data.csv`` (as
``hivemap sim render`` writes a scenario; its ``cam0/sensor.yaml`` gives the camera's pose on the body)
or a TUM file ``DIR/<agent>.tum`` (``t tx ty tz qx qy qz qw`` of the camera). Files are read when first
asked for and again when they change.

Ground truth lives in its own world frame, the server's maps in theirs: :func:`aligned_groundtruth`
fits one rigid transform per map (evo's Umeyama, no scale: stereo maps are metric) from the ground-truth
camera positions at the map's keyframe times to the keyframes' camera centres, over all agents of the
map at once, so a wrong merge shows as ground truth that disagrees with the estimate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
MAX_DRAWN = 2000  # ground-truth positions returned per agent (the viewer draws a line through them)


@dataclass(frozen=True)
class Track:
    """An agent's ground-truth camera positions: ``t`` (N,) seconds, ``xyz`` (N, 3) metres."""

    t: F64
    xyz: F64


class GroundTruthError(ValueError):
    """A ground-truth file that cannot be read (the message names it)."""


def _euroc(agent_dir: Path) -> Track:
    mav0 = agent_dir / "mav0"
    csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    try:
        rows = np.loadtxt(csv, delimiter=",", comments="#", ndmin=2, usecols=range(8))
    except (OSError, ValueError) as exc:
        raise GroundTruthError(f"{csv}: {exc}") from exc
    cam = np.zeros(3)
    sensor = mav0 / "cam0" / "sensor.yaml"
    if sensor.exists():
        import yaml

        try:
            T_BS = np.asarray(yaml.safe_load(sensor.read_text())["T_BS"]["data"], np.float64).reshape(4, 4)
        except (KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
            raise GroundTruthError(f"{sensor}: no 4x4 T_BS ({exc})") from exc
        cam = T_BS[:3, 3]
    from scipy.spatial.transform import Rotation

    # EuRoC: position, then quaternion w, x, y, z of world_from_body; the camera centre is body + R @ t_BS
    R = Rotation.from_quat(rows[:, [5, 6, 7, 4]]).as_matrix()
    return Track(rows[:, 0] * 1e-9, rows[:, 1:4] + R @ cam)


def _tum(path: Path) -> Track:
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2, usecols=range(4))
    except (OSError, ValueError) as exc:
        raise GroundTruthError(f"{path}: {exc}") from exc
    return Track(rows[:, 0], rows[:, 1:4])


class GroundTruthSource:
    """The ground truth folder of the server's ``groundtruth`` setting; per agent id, cached by mtime."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._cache: dict[str, tuple[float, Track | None]] = {}

    def _file(self, agent_id: str) -> tuple[Path, bool] | None:
        d = self.root / agent_id
        if (d / "mav0" / "state_groundtruth_estimate0" / "data.csv").is_file():
            return d / "mav0" / "state_groundtruth_estimate0" / "data.csv", True
        if (self.root / f"{agent_id}.tum").is_file():
            return self.root / f"{agent_id}.tum", False
        return None

    def track(self, agent_id: str) -> Track | None:
        """The agent's ground truth (session suffix ``#n`` ignored), None when the folder has none.
        A file that cannot be read is logged once (per change) and treated as absent."""
        base = agent_id.split("#")[0]
        found = self._file(base)
        if found is None:
            return None
        path, euroc = found
        mtime = path.stat().st_mtime
        cached = self._cache.get(base)
        if cached is not None and cached[0] == mtime:
            return cached[1]
        try:
            tr: Track | None = _euroc(self.root / base) if euroc else _tum(path)
        except GroundTruthError as exc:
            log.warning("ground truth of %s unreadable: %s", base, exc)
            tr = None
        if tr is not None and (len(tr.t) == 0 or np.any(np.diff(tr.t) <= 0)):
            log.warning("ground truth of %s: timestamps empty or not increasing: ignored", base)
            tr = None
        self._cache[base] = (mtime, tr)
        return tr


@dataclass(frozen=True)
class AlignedTrack:
    agent_id: str
    xyz: F64  # (M, 3) in the map's frame, over the time span of the agent's keyframes
    matched: int  # keyframes paired with a ground-truth time
    rmse_m: float  # keyframe camera centres against the aligned ground truth


def _at(tr: Track, t: F64) -> tuple[F64, NDArray[np.bool_]]:
    ok = (t >= tr.t[0]) & (t <= tr.t[-1])
    xyz = np.stack([np.interp(t, tr.t, tr.xyz[:, d]) for d in range(3)], axis=1)
    return xyz, ok


def aligned_groundtruth(
    source: GroundTruthSource, keyframes: dict[str, list[tuple[float, F64]]]
) -> tuple[list[AlignedTrack], bool]:
    """Ground truth of each agent of one map in the map's frame. ``keyframes``: agent id -> [(timestamp,
    camera centre)]. Returns the tracks and whether an alignment was possible (at least 3 keyframes
    matched, not all on a line); without one the tracks are empty."""
    from evo.core.geometry import GeometryException, umeyama_alignment

    tracks: dict[str, Track] = {}
    src, dst, owner = [], [], []
    for aid, kfs in keyframes.items():
        tr = source.track(aid)
        if tr is None or not kfs:
            continue
        tracks[aid] = tr
        t = np.array([k[0] for k in kfs], np.float64)
        c = np.array([k[1] for k in kfs], np.float64).reshape(-1, 3)
        gt, ok = _at(tr, t)
        src.append(gt[ok])
        dst.append(c[ok])
        owner += [aid] * int(ok.sum())
    if not src or sum(len(s) for s in src) < 3:
        return [], False
    S, D = np.concatenate(src), np.concatenate(dst)
    try:
        R, tvec, _ = umeyama_alignment(S.T, D.T, with_scale=False)
    except GeometryException:  # degenerate (all on a line)
        return [], False
    R, tvec = np.asarray(R), np.asarray(tvec).reshape(3)
    if not np.isfinite(R).all():
        return [], False
    res = D - (S @ R.T + tvec)
    who = np.array(owner)
    out = []
    for aid, tr in tracks.items():
        times = [k[0] for k in keyframes[aid]]
        sel = (tr.t >= min(times)) & (tr.t <= max(times))
        xyz = tr.xyz[sel]
        if len(xyz) > MAX_DRAWN:
            xyz = xyz[np.linspace(0, len(xyz) - 1, MAX_DRAWN).round().astype(int)]
        mine = res[who == aid]
        rmse = float(np.sqrt(np.mean(np.sum(mine**2, axis=1)))) if len(mine) else float("nan")
        out.append(AlignedTrack(aid, xyz @ R.T + tvec, int(len(mine)), rmse))
    return out, True


def source_of(settings: Any) -> GroundTruthSource | None:
    root = getattr(settings, "groundtruth", None)
    return None if root is None else GroundTruthSource(Path(root))
