"""Single- and multi-agent trajectory evaluation on evo's API (ATE, RPE, frame changes at merges).

Everything numeric goes through evo: ``evo.core.sync`` associates timestamps, ``PosePath3D.align``
(Umeyama) aligns, ``evo.core.metrics.APE``/``RPE`` compute errors and their statistics.  Nothing here
re-implements alignment.

Alignment is always explicit:

- ``"none"``: the estimate is compared as is (an agent that fused GNSS is in ENU, like the ground truth);
- ``"se3"``: rigid alignment (stereo / visual-inertial, metric scale);
- ``"sim3"``: rigid + scale (monocular).

Multi-agent (seed 004, "Multi-Agent EVO"): an agent's estimate lives in its own frame until its map
is merged, then in the merged (global) frame.  A *frame timeline* lists, per agent, the times at which
its frame changed and the label of the new frame: ``[(t_start, frame_id), ...]``.  Every pose is
evaluated in the frame it had when it was estimated: the estimate is cut into segments at the frame
changes and the segments of *all* agents that share a frame label are aligned together with ONE
transform (they share a frame, so one transform must fit them all; relative errors between agents
then show up as ATE).  Per agent and for the team the ATE statistics are pooled over segments, the
merge time is the first frame change, and the relative pose error between two agents is measured on
their simultaneous poses while they share a frame (it needs no alignment).
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]
Alignment = Literal["none", "se3", "sim3"]
ALIGNMENTS: tuple[str, ...] = ("none", "se3", "sim3")
log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class ErrorStats:
    """Statistics of an error array (metres or degrees)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    @staticmethod
    def of(errors: F64) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64).ravel()
        if e.size == 0:
            nan = math.nan
            return ErrorStats(nan, nan, nan, nan, nan, nan, 0)
        return ErrorStats(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            n=int(e.size),
        )

    @staticmethod
    def from_evo(metric: Any) -> ErrorStats:
        """From an evo metric after ``process_data`` (uses its own statistics)."""
        s = metric.get_all_statistics()
        return ErrorStats(
            rmse=float(s["rmse"]),
            mean=float(s["mean"]),
            median=float(s["median"]),
            std=float(s["std"]),
            min=float(s["min"]),
            max=float(s["max"]),
            n=int(np.asarray(metric.error).size),
        )


@dataclass(frozen=True)
class AteResult:
    """ATE of one trajectory: translation statistics (m), alignment used and its transform."""

    stats: ErrorStats
    alignment: str
    rotation: F64  # (3, 3) of the alignment est -> ref (identity for "none")
    translation: F64  # (3,)
    scale: float
    errors: F64  # per associated pose (m)
    timestamps: F64


@dataclass(frozen=True)
class RpeResult:
    """RPE of one trajectory: translation (m) and rotation (deg) statistics over ``delta`` ``unit``."""

    trans: ErrorStats
    rot_deg: ErrorStats
    delta: float
    unit: str


@dataclass(frozen=True)
class SegmentReport:
    frame_id: str
    t_start: float
    t_end: float
    ate: ErrorStats


@dataclass(frozen=True)
class AgentReport:
    agent_id: str
    ate: ErrorStats
    rpe: RpeResult | None
    segments: list[SegmentReport]
    merge_time: float | None  # time of the first frame change (None: never changed frame)


@dataclass(frozen=True)
class InterAgentError:
    """Relative pose error between two agents at simultaneous times while they share a frame."""

    agent_a: str
    agent_b: str
    frame_id: str
    trans: ErrorStats  # m
    rot_deg: ErrorStats


@dataclass(frozen=True)
class FrameAlignment:
    frame_id: str
    agents: list[str]
    n: int
    rotation: F64
    translation: F64
    scale: float


@dataclass(frozen=True)
class TeamReport:
    alignment: str
    agents: dict[str, AgentReport]
    team: ErrorStats  # ATE pooled over every agent's associated poses
    frames: dict[str, FrameAlignment]
    inter_agent: list[InterAgentError] = field(default_factory=list)


@dataclass(frozen=True)
class AgentRun:
    """One agent's estimate and ground truth (``evo`` trajectories) and its frame timeline.

    ``frames``: ``[(t_start, frame_id), ...]`` sorted by time; empty -> one frame named ``agent_id``.
    Poses before the first ``t_start`` belong to the first frame.
    """

    agent_id: str
    est: Any  # evo PoseTrajectory3D
    gt: Any  # evo PoseTrajectory3D
    frames: Sequence[tuple[float, str]] = ()


# ---------------------------------------------------------------------------------------- I/O
def trajectory_from_poses(timestamps: F64, poses: F64) -> Any:
    """(N,) seconds + (N, 4, 4) poses -> ``evo.core.trajectory.PoseTrajectory3D``."""
    from evo.core.trajectory import PoseTrajectory3D

    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return PoseTrajectory3D(timestamps=np.asarray(timestamps, dtype=np.float64), poses_se3=list(poses))


def read_tum(path: str | Path) -> Any:
    """TUM file (``t tx ty tz qx qy qz qw``) -> PoseTrajectory3D (evo's reader)."""
    from evo.tools import file_interface

    return file_interface.read_tum_trajectory_file(str(path))


def write_tum(path: str | Path, traj: Any) -> None:
    """PoseTrajectory3D -> TUM file (evo's writer)."""
    from evo.tools import file_interface

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    file_interface.write_tum_trajectory_file(str(path), traj)


def groundtruth_trajectory(agent_dir: str | Path, sensor: str | None = None) -> Any:
    """Ground truth of a dataset agent (``hivemap.client.dataset``) as a PoseTrajectory3D.

    ``sensor=None`` gives ``world_from_body`` (body = IMU, as EuRoC); ``sensor="cam0"`` gives
    ``world_from_body @ T_BS(cam0)``.
    """
    from hivemap.client.dataset import load_dataset

    ds = load_dataset(Path(agent_dir))
    gt = ds.groundtruth
    t = np.asarray(_attr(gt, "timestamps", "t", "times"), dtype=np.float64)
    poses = np.asarray(_attr(gt, "world_from_body", "poses"), dtype=np.float64)
    if t.size and np.median(t) > 1e12:  # nanoseconds
        t = t * 1e-9
    if sensor is not None:
        T_BS = np.asarray(ds.T_BS[sensor], dtype=np.float64)
        poses = poses @ T_BS
    return trajectory_from_poses(t, poses)


def _attr(obj: Any, *names: str) -> Any:
    for n in names:
        if isinstance(obj, dict) and n in obj:
            return obj[n]
        if hasattr(obj, n):
            return getattr(obj, n)
    if isinstance(obj, tuple) and len(obj) == 2:  # (timestamps, poses)
        return obj[0] if names[0] in ("timestamps",) else obj[1]
    raise AttributeError(f"ground truth has none of {names}")


def read_frame_timeline(path: str | Path) -> list[tuple[float, str]]:
    """CSV ``t_start,frame_id`` (header optional, ``#`` comments) -> sorted timeline."""
    out: list[tuple[float, str]] = []
    with open(path, newline="") as f:
        for row in csv.reader(f):
            if not row or row[0].lstrip().startswith("#"):
                continue
            try:
                out.append((float(row[0]), row[1].strip()))
            except ValueError:
                continue  # header
    return sorted(out)


def write_frame_timeline(path: str | Path, frames: Sequence[tuple[float, str]]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_start", "frame_id"])
        for t, fid in frames:
            w.writerow([f"{t:.9f}", fid])


# ---------------------------------------------------------------------------------------- single trajectory
def _copy(traj: Any) -> Any:
    import copy

    return copy.deepcopy(traj)


def associate(est: Any, gt: Any, max_diff: float = 0.01) -> tuple[Any, Any]:
    """Pairs of poses with matching timestamps (evo ``associate_trajectories``): (gt, est)."""
    from evo.core import sync

    return sync.associate_trajectories(gt, est, max_diff=max_diff)


def _align(est: Any, ref: Any, alignment: str) -> tuple[F64, F64, float]:
    """Align ``est`` (modified in place) to ``ref`` with evo; returns (R, t, s)."""
    if alignment == "none":
        return np.eye(3), np.zeros(3), 1.0
    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment must be one of {ALIGNMENTS}, got {alignment!r}")
    R, t, s = est.align(ref, correct_scale=alignment == "sim3")
    return np.asarray(R), np.asarray(t), float(s)


def _ape(ref: Any, est: Any) -> Any:
    from evo.core import metrics

    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    return m


def ate(est: Any, gt: Any, alignment: Alignment = "se3", max_diff: float = 0.01) -> AteResult:
    """Absolute trajectory error (translation) of ``est`` against ``gt`` with an explicit alignment."""
    ref, e = associate(est, gt, max_diff)
    e = _copy(e)
    R, t, s = _align(e, ref, alignment)
    m = _ape(ref, e)
    errors, times = np.asarray(m.error), np.asarray(ref.timestamps)
    return AteResult(ErrorStats.from_evo(m), alignment, R, t, s, errors, times)


def rpe(
    est: Any,
    gt: Any,
    delta: float = 1.0,
    unit: str = "m",
    alignment: Alignment = "se3",
    max_diff: float = 0.01,
) -> RpeResult:
    """Relative pose error over ``delta`` metres (``unit="m"``) or frames (``unit="frames"``).

    The alignment only matters for ``sim3`` (scale); rigid alignment does not change relative poses.
    """
    from evo.core import metrics
    from evo.core.units import Unit

    ref, e = associate(est, gt, max_diff)
    e = _copy(e)
    _align(e, ref, alignment)
    u = Unit.meters if unit == "m" else Unit.frames
    out = []
    for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
        m = metrics.RPE(rel, delta=delta, delta_unit=u, all_pairs=False)
        m.process_data((ref, e))
        out.append(ErrorStats.from_evo(m))
    return RpeResult(out[0], out[1], delta, unit)


# ---------------------------------------------------------------------------------------- multi-agent
def _segments(
    t: F64, frames: Sequence[tuple[float, str]], default: str
) -> list[tuple[str, float, float, NDArray[np.int64]]]:
    """Split sorted times at the frame changes: [(frame_id, t_start, t_end, indices)]."""
    tl = sorted(frames) if frames else [(-math.inf, default)]
    out = []
    for i, (t0, fid) in enumerate(tl):
        lo = -math.inf if i == 0 else t0
        hi = tl[i + 1][0] if i + 1 < len(tl) else math.inf
        idx = np.nonzero((t >= lo) & (t < hi))[0]
        if idx.size:
            out.append((fid, float(t[idx[0]]), float(t[idx[-1]]), idx))
    return out


def _sub(traj: Any, idx: NDArray[np.int64]) -> Any:
    from evo.core.trajectory import PoseTrajectory3D

    poses = np.asarray(traj.poses_se3)[idx]
    return PoseTrajectory3D(timestamps=np.asarray(traj.timestamps)[idx], poses_se3=list(poses))


def evaluate_team(
    runs: Sequence[AgentRun],
    alignment: Alignment = "se3",
    max_diff: float = 0.01,
    rpe_delta: float | None = 10.0,
    rpe_unit: str = "m",
) -> TeamReport:
    """Per-agent and team ATE/RPE with frame changes, merge times and inter-agent relative errors."""
    from evo.core.trajectory import PosePath3D

    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment must be one of {ALIGNMENTS}, got {alignment!r}")
    # 1. associate each agent with its ground truth and cut it into frame segments
    pieces: dict[str, list[tuple[str, Any, Any]]] = {}  # frame_id -> [(agent, ref_seg, est_seg)]
    assoc: dict[str, tuple[Any, Any]] = {}
    for run in runs:
        ref, est = associate(run.est, run.gt, max_diff)
        assoc[run.agent_id] = (ref, est)
        for fid, _, _, idx in _segments(np.asarray(est.timestamps), run.frames, run.agent_id):
            pieces.setdefault(fid, []).append((run.agent_id, _sub(ref, idx), _sub(est, idx)))

    # 2. one alignment per frame, fitted on every agent's poses in that frame together
    frames: dict[str, FrameAlignment] = {}
    aligned: dict[str, list[tuple[str, Any, Any]]] = {}
    for fid, segs in pieces.items():
        ref_all = PosePath3D(poses_se3=[p for _, r, _ in segs for p in r.poses_se3])
        est_all = PosePath3D(poses_se3=[p for _, _, e in segs for p in e.poses_se3])
        R, t, s = _align(est_all, ref_all, alignment)
        frames[fid] = FrameAlignment(fid, sorted({a for a, _, _ in segs}), est_all.num_poses, R, t, s)
        out = []
        for agent, r, e in segs:
            e = _copy(e)
            if alignment != "none":
                if alignment == "sim3":
                    e.scale(s)
                e.transform(_se3(R, t))
            out.append((agent, r, e))
        aligned[fid] = out

    # 3. per-agent reports
    agents: dict[str, AgentReport] = {}
    all_errors = []
    for run in runs:
        seg_reports, errs, rpe_t, rpe_r = [], [], [], []
        for fid, segs in aligned.items():
            for agent, r, e in segs:
                if agent != run.agent_id:
                    continue
                m = _ape(r, e)
                errs.append(np.asarray(m.error))
                ts = np.asarray(r.timestamps)
                seg_reports.append(SegmentReport(fid, float(ts[0]), float(ts[-1]), ErrorStats.from_evo(m)))
                if rpe_delta is not None:
                    te, re = _rpe_errors(r, e, rpe_delta, rpe_unit)
                    rpe_t.append(te)
                    rpe_r.append(re)
        seg_reports.sort(key=lambda s: s.t_start)
        e_all = np.concatenate(errs) if errs else np.zeros(0)
        all_errors.append(e_all)
        rpe_res = None
        if rpe_delta is not None:
            rpe_res = RpeResult(
                ErrorStats.of(np.concatenate(rpe_t) if rpe_t else np.zeros(0)),
                ErrorStats.of(np.concatenate(rpe_r) if rpe_r else np.zeros(0)),
                rpe_delta,
                rpe_unit,
            )
        merge_time = sorted(run.frames)[1][0] if len(run.frames) > 1 else None
        agents[run.agent_id] = AgentReport(
            run.agent_id, ErrorStats.of(e_all), rpe_res, seg_reports, merge_time
        )

    # 4. inter-agent relative pose error while two agents share a frame
    inter = []
    ids = [r.agent_id for r in runs]
    for fid, segs in pieces.items():
        by_agent: dict[str, list[Any]] = {}
        for agent, r, e in segs:
            by_agent.setdefault(agent, []).append((r, e))
        names = [a for a in ids if a in by_agent]
        for i in range(len(names)):
            for j in range(i + 1, len(names)):
                res = _inter_agent(by_agent[names[i]], by_agent[names[j]], max_diff, frames[fid].scale)
                if res is not None:
                    inter.append(InterAgentError(names[i], names[j], fid, res[0], res[1]))
    team = ErrorStats.of(np.concatenate(all_errors) if all_errors else np.zeros(0))
    return TeamReport(alignment, agents, team, frames, inter)


def _se3(R: F64, t: F64) -> F64:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _rpe_errors(ref: Any, est: Any, delta: float, unit: str) -> tuple[F64, F64]:
    from evo.core import metrics
    from evo.core.units import Unit

    out = []
    for rel in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg):
        m = metrics.RPE(rel, delta=delta, delta_unit=Unit.meters if unit == "m" else Unit.frames)
        try:
            m.process_data((ref, est))
        except Exception as exc:  # evo raises when a segment is shorter than delta
            log.debug("RPE skipped on a short segment: %s", exc)
            return np.zeros(0), np.zeros(0)
        out.append(np.asarray(m.error))
    return out[0], out[1]


def _inter_agent(
    segs_a: list[tuple[Any, Any]], segs_b: list[tuple[Any, Any]], max_diff: float, scale: float
) -> tuple[ErrorStats, ErrorStats] | None:
    """Relative pose ``inv(T_a) T_b`` estimated vs true at simultaneous times (evo association)."""
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    def cat(segs: list[tuple[Any, Any]], k: int) -> Any:
        ts = np.concatenate([np.asarray(s[k].timestamps) for s in segs])
        poses = [p for s in segs for p in s[k].poses_se3]
        order = np.argsort(ts, kind="stable")
        return PoseTrajectory3D(timestamps=ts[order], poses_se3=[poses[i] for i in order])

    gt_a, est_a, gt_b, est_b = cat(segs_a, 0), cat(segs_a, 1), cat(segs_b, 0), cat(segs_b, 1)
    try:
        ea, eb = sync.associate_trajectories(est_a, est_b, max_diff=max_diff)
    except sync.SyncException:
        return None
    try:
        ga, _ = sync.associate_trajectories(gt_a, ea, max_diff=max_diff)
        gb, _ = sync.associate_trajectories(gt_b, eb, max_diff=max_diff)
    except sync.SyncException:
        return None
    if ga.num_poses != ea.num_poses or gb.num_poses != eb.num_poses:
        return None
    te, re = [], []
    for Ta, Tb, Ga, Gb in zip(ea.poses_se3, eb.poses_se3, ga.poses_se3, gb.poses_se3, strict=True):
        rel_e = np.linalg.inv(Ta) @ Tb
        rel_g = np.linalg.inv(Ga) @ Gb
        rel_e[:3, 3] *= scale  # a sim3 frame: bring the estimate's distances to metres
        d = np.linalg.inv(rel_g) @ rel_e
        te.append(np.linalg.norm(rel_e[:3, 3] - rel_g[:3, 3]))
        re.append(math.degrees(Rotation.from_matrix(d[:3, :3]).magnitude()))  # exact near 0, unlike acos
    return ErrorStats.of(np.array(te)), ErrorStats.of(np.array(re))
