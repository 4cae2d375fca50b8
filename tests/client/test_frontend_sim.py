"""Front-end on the project's renderer: the sim "tiny" preset (UAV take-off from the UGV roof)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D

from hivemap.client.frontend import Frontend
from hivemap.maps.geometry import se3_inverse


@pytest.fixture(scope="module")
def tiny_uav(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from hivemap.sim.dataset import render_scenario
    from hivemap.sim.scenarios import get_scenario

    out = tmp_path_factory.mktemp("tiny")
    render_scenario(get_scenario("tiny"), out, agents=["uav1"], progress=False)
    return out / "uav1"


def test_tiny_preset_trajectory_within_ate_bound(tiny_uav: Path) -> None:
    from hivemap.client.dataset import load_dataset

    ds = load_dataset(tiny_uav)
    assert ds.rig is not None and ds.groundtruth is not None
    fe = Frontend(ds.rig, imu_params=dict(ds.imu_noise))
    imu = ds.imu
    times = ds.frames.timestamps
    refs = []
    t_prev = -np.inf
    for i, t in enumerate(times):
        left, right = ds.frames.load(i)
        assert right is not None
        res = fe.process(float(t), left, right, imu[(imu[:, 0] > t_prev) & (imu[:, 0] <= t)])
        t_prev = t
        assert res.state.tracked  # no tracking loss
        k = max(fe.keyframes)
        refs.append((k, se3_inverse(fe.keyframes[k].T_wc) @ res.world_from_cam))
    est = np.array([fe.keyframes[k].T_wc @ rel @ fe.cam_from_body for k, rel in refs])
    gt = ds.groundtruth_at_frames()
    te = PoseTrajectory3D(poses_se3=list(est), timestamps=times)
    tg = PoseTrajectory3D(poses_se3=list(gt), timestamps=times)
    te.align(tg)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((tg, te))
    rmse = float(ape.get_statistic(metrics.StatisticsType.rmse))
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    # 320x240 at 10 Hz, 12 s take-off (2 s at rest, then climb): measured ~0.3% of the ~16 m path;
    # 1% leaves room for renderer changes while still catching a scale or drift regression.
    assert rmse <= 0.01 * path
    # gravity-aligned VIO frame: aligned at rest (first second) to < 0.5 deg; afterwards the attitude is
    # visual only (the IMU is not fused in BA) and drifts ~3 deg over this low-res 12 s climb: bound 5 deg
    aligned = int(np.searchsorted(times, times[0] + 1.5))
    for j, bound in ((aligned, 0.5), (len(times) - 1, 5.0)):
        up = est[j][:3, :3] @ gt[j][:3, :3].T @ np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))) < bound
