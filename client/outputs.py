"""What a finished agent run leaves in its output folder: the VIO, local and keyframe trajectories (TUM),
``frames.csv`` (one row a frame) and ``run.json`` (the run's summary), the same for every way of running
an agent (offline, streaming, live)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hivemap.client.replay_io import write_tum_poses

if TYPE_CHECKING:
    from hivemap.client.runner import OfflineAgent, RunSummary


def write_outputs(agent: OfflineAgent, out: Path, summary: RunSummary, n_frames: int) -> None:
    """Write vio/local/keyframe TUM files, frames.csv and run.json; fill the summary."""
    vio_t, vio_poses = agent.vio_trajectory()
    loc_t, loc_poses = agent.local_trajectory()
    kf_t, kf_poses = agent.stage.keyframe_poses()
    order = np.argsort(kf_t, kind="stable")
    files = {
        "vio": out / "vio.tum",
        "local": out / "local.tum",
        "keyframes_local": out / "keyframes_local.tum",
        "frames": out / "frames.csv",
        "run": out / "run.json",
    }
    write_tum_poses(files["vio"], vio_t, vio_poses)
    write_tum_poses(files["local"], loc_t, loc_poses)
    write_tum_poses(files["keyframes_local"], kf_t[order], kf_poses[order])
    write_frames_csv(files["frames"], agent.frame_log)
    summary.frames = n_frames
    summary.tracked_frames = len(vio_t)
    summary.keyframes = len(agent.stage.keyframe_ids)
    summary.tracking_losses = agent.losses
    st = agent.frontend.stats
    summary.weak_frames, summary.lost_frames = st.weak_frames, st.lost_frames
    summary.relocalized_frames, summary.imu_rejections, summary.sessions = (
        st.relocalizations, st.imu_rejections, st.sessions,
    )  # fmt: skip
    summary.lost_keyframes = st.lost_keyframes
    summary.segments = agent.stage.segment_count
    summary.gnss_used = agent.gnss_used
    summary.gnss_rejected = agent.gnss_rejected
    summary.rejected_fixes = list(agent.stage.rejected_fixes)
    summary.frontend_ms_mean = float(np.mean(agent.fe_ms)) if agent.fe_ms else 0.0
    summary.frontend_ms_max = float(np.max(agent.fe_ms)) if agent.fe_ms else 0.0
    summary.second_stage_ms_mean = float(np.mean(agent.stage_ms)) if agent.stage_ms else 0.0
    summary.second_stage_ms_max = float(np.max(agent.stage_ms)) if agent.stage_ms else 0.0
    summary.fps = summary.frames / summary.wall_s if summary.wall_s > 0 else 0.0
    summary.outputs = {k: str(v) for k, v in files.items()}
    files["run"].write_text(summary.to_json())


def write_frames_csv(path: Path, rows: list[dict[str, float | int | str]]) -> None:
    import csv

    with open(path, "w", newline="") as f:
        if not rows:
            return
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
