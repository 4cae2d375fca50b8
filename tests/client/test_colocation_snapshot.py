"""A server correction is a whole snapshot: it replaces the agent's previous co-location priors."""

from __future__ import annotations

import numpy as np

from hivemap.client.second_stage import SecondStage, SecondStageOptions
from hivemap.maps.geometry import se3, se3_inverse


def _straight(n: int) -> tuple[list[np.ndarray], SecondStage]:
    """``n`` keyframes 1 m apart along x, chained by 1 cm relative-pose factors."""
    poses = [se3(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(n)]
    stage = SecondStage(SecondStageOptions(gravity_aligned=True))
    odo = np.diag([1e-4] * 3 + [1e-4] * 3)
    for k, T in enumerate(poses):
        if k == 0:
            stage.add_keyframe(k, 0.5 * k, T)
        else:
            stage.add_keyframe(k, 0.5 * k, T, odo, prev_id=k - 1, prev_from_kf=se3_inverse(poses[k - 1]) @ T)
    return poses, stage


def test_new_snapshot_replaces_older_priors() -> None:
    """20 keyframes along x; a first correction says the whole trajectory is 0.5 m further north, a
    second (newer) one says it is where the VIO put it. With replacement the estimate follows the
    second one (within 1 cm: 5 cm priors on every keyframe against 1 cm odometry); if the first
    snapshot's priors were kept the estimate would sit ~0.25 m north (halfway)."""
    poses, stage = _straight(20)
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    north = se3(np.eye(3), np.array([0.0, 0.5, 0.0]))
    stage.set_colocations({k: (north @ T, cov) for k, T in enumerate(poses)})
    _, first = stage.keyframe_poses()
    assert abs(float(np.mean(first[:, 1, 3])) - 0.5) < 0.05  # the first snapshot is followed
    stage.set_colocations({k: (T, cov) for k, T in enumerate(poses) if k % 2 == 0})
    _, second = stage.keyframe_poses()
    assert float(np.max(np.abs(second[:, 1, 3]))) < 0.01, second[:, 1, 3]


def test_first_fix_after_map_frame_priors_is_not_an_outlier() -> None:
    """Map-frame co-location priors tie the local frame to the VIO frame, not to ENU: the first GNSS fix,
    14 m away in ENU, must be accepted (factory01 challenged2 rejected all four random fixes before)."""
    poses, stage = _straight(10)
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    stage.set_colocations({k: (T, cov) for k, T in enumerate(poses)})  # map frame (enu=False)
    fix = poses[9][:3, 3] + np.array([13.0, 6.0, 0.5])
    d = stage.add_gnss(9, fix, np.diag([0.05**2, 0.05**2, 0.15**2]))
    assert d.accepted, d


def test_a_session_snapshot_leaves_the_other_sessions_priors() -> None:
    """Two segments (the front-end lost tracking: a second session), 10 keyframes each, 20 m apart along
    x. The server corrects each session separately: session 0's snapshot puts it 0.5 m north, then
    session 1's snapshot (one keyframe) arrives. Replacing only session 1's priors keeps session 0 north
    (within 5 cm); replacing every prior, as before, let it fall back to its VIO pose (factory06
    challenged2: uav1 ended 14 m from ENU)."""
    stage = SecondStage(SecondStageOptions(gravity_aligned=True))
    odo = np.diag([1e-4] * 3 + [1e-4] * 3)
    poses = {}
    for seg in (0, 1):
        for i in range(10):
            k = 10 * seg + i
            poses[k] = se3(np.eye(3), np.array([float(i) + 20.0 * seg, 0.0, 0.0]))
            if i == 0:
                stage.add_keyframe(k, 0.5 * k, poses[k], new_segment=seg > 0)
            else:
                rel = se3_inverse(poses[k - 1]) @ poses[k]
                stage.add_keyframe(k, 0.5 * k, poses[k], odo, prev_id=k - 1, prev_from_kf=rel)
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    north = se3(np.eye(3), np.array([0.0, 0.5, 0.0]))
    sessions = {0: set(range(10)), 1: set(range(10, 20))}
    stage.set_colocations({k: (north @ poses[k], cov) for k in sessions[0]}, scope=sessions[0])
    stage.set_colocations({15: (north @ poses[15], cov)}, scope=sessions[1])
    ts, est = stage.keyframe_poses()  # keyframe k was added at t = 0.5 k
    y = dict(zip(np.round(ts / 0.5).astype(int).tolist(), est[:, 1, 3].tolist(), strict=True))
    assert all(abs(y[k] - 0.5) < 0.05 for k in sessions[0]), y
    assert abs(y[15] - 0.5) < 0.05, y
