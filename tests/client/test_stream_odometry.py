"""What an agent streams (client/odometry.py): keyframes moved to their IMU-aided odometry, with their
points, pose updates and session guesses moved consistently (the odometry itself:
``test_second_stage_imu.test_streamed_poses_hold_the_tilt_the_vio_loses``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from hivemap.client.odometry import StreamedPoses
from hivemap.maps.geometry import se3, se3_inverse


def _moved(table: dict[tuple[int, int], np.ndarray]):
    return lambda s, k: table.get((s, k), np.eye(4)) if k is not None else np.eye(4)


def _rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3(Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix(), rng.normal(0, 0.5, 3))


def test_points_stay_where_their_keyframe_sees_them():
    C = {(0, 7): _rigid(1), (0, 8): _rigid(2), (1, 20): _rigid(3)}
    sp = StreamedPoses(_moved(C))
    W = _rigid(4)
    xyz = np.array([[1.0, 2.0, 5.0], [-1.0, 0.5, 3.0]])
    ev = SimpleNamespace(session=0, kf_id=7, world_from_cam=W, new_point_ids=np.array([100, 101]),
                         new_point_xyz=xyz, prev_session_from_world=None)  # fmt: skip
    W2, xyz2, guess = sp.keyframe(ev)
    assert guess is None
    cam = (se3_inverse(W)[:3, :3] @ xyz.T).T + se3_inverse(W)[:3, 3]
    cam2 = (se3_inverse(W2)[:3, :3] @ xyz2.T).T + se3_inverse(W2)[:3, 3]
    np.testing.assert_allclose(cam2, cam, atol=1e-12)
    # a later pose update: keyframe 8 by its own transform, point 101 by its creator's (keyframe 7)
    sp.keyframe(SimpleNamespace(session=0, kf_id=8, world_from_cam=W, new_point_ids=np.zeros(0, np.int64),
                                new_point_xyz=np.zeros((0, 3)), prev_session_from_world=None))  # fmt: skip
    upd = SimpleNamespace(session=0, kf_ids=np.array([8]), world_from_cam=W[None], point_ids=np.array([101]),
                          xyz=xyz[1:])  # fmt: skip
    T, p = sp.update(upd)
    np.testing.assert_allclose(T[0], C[(0, 8)] @ W, atol=1e-12)
    np.testing.assert_allclose(p[0], C[(0, 7)][:3, :3] @ xyz[1] + C[(0, 7)][:3, 3], atol=1e-12)


def test_a_new_sessions_guess_joins_the_two_streamed_frames():
    C = {(0, 8): _rigid(5), (1, 20): _rigid(6)}
    sp = StreamedPoses(_moved(C))
    none = np.zeros(0, np.int64)
    sp.keyframe(SimpleNamespace(session=0, kf_id=8, world_from_cam=np.eye(4), new_point_ids=none,
                                new_point_xyz=np.zeros((0, 3)), prev_session_from_world=None))  # fmt: skip
    G = _rigid(7)  # session 1's VIO frame in session 0's
    x_new = np.array([2.0, -1.0, 4.0, 1.0])  # a point in session 1's VIO frame
    first = SimpleNamespace(session=1, kf_id=20, world_from_cam=np.eye(4), new_point_ids=none,
                            new_point_xyz=np.zeros((0, 3)), prev_session_from_world=G)  # fmt: skip
    _, _, guess = sp.keyframe(first)
    # the same point through either path: session 1 streamed -> session 0 streamed
    np.testing.assert_allclose(guess @ (C[(1, 20)] @ x_new), C[(0, 8)] @ (G @ x_new), atol=1e-12)


def test_keyframes_the_smoothing_moved_are_sent_again():
    """``refresh``: a keyframe whose streamed pose moved 1 cm or more (or turned 0.2 deg) since it was
    sent comes back at its new streamed pose; one that moved less does not, and once resent it is not sent
    again until it moves again."""
    from hivemap.maps.geometry import so3_exp

    C = {(0, 1): np.eye(4), (0, 2): np.eye(4), (0, 3): np.eye(4), (1, 9): np.eye(4)}
    sp = StreamedPoses(_moved(C))
    W = {k: _rigid(10 + k) for k in (1, 2, 3, 9)}
    none = np.zeros(0, np.int64)
    for s, k in C:
        ev = SimpleNamespace(session=s, kf_id=k, world_from_cam=W[k], new_point_ids=none,
                             new_point_xyz=np.zeros((0, 3)), prev_session_from_world=None)  # fmt: skip
        sp.keyframe(ev)
    assert sp.refresh(0.01, 0.2) == []
    C[(0, 1)] = se3(np.eye(3), np.array([0.0, 0.004, 0.0]))  # 4 mm: below the threshold
    C[(0, 2)] = se3(np.eye(3), np.array([0.03, 0.0, 0.0]))  # 3 cm
    C[(0, 3)] = se3(so3_exp(np.array([0.0, 0.0, np.radians(0.3)])), np.zeros(3))  # 0.3 deg
    C[(1, 9)] = se3(np.eye(3), np.array([0.0, 0.0, -0.02]))  # another session: its own update
    (s0, ids0, T0), (s1, ids1, T1) = sp.refresh(0.01, 0.2)
    assert (s0, ids0.tolist(), s1, ids1.tolist()) == (0, [2, 3], 1, [9])
    np.testing.assert_allclose(T0[0], C[(0, 2)] @ W[2], atol=1e-12)
    np.testing.assert_allclose(T0[1], C[(0, 3)] @ W[3], atol=1e-12)
    np.testing.assert_allclose(T1[0], C[(1, 9)] @ W[9], atol=1e-12)
    np.testing.assert_allclose(sp.sent_pose(0, 2), C[(0, 2)] @ W[2], atol=1e-12)
    assert sp.refresh(0.01, 0.2) == []
    # keyframe 1 drifts on, to 12 mm from what the server has: over the threshold
    C[(0, 1)] = se3(np.eye(3), np.array([0.0, 0.012, 0.0]))
    ((_, ids, _),) = sp.refresh(0.01, 0.2)
    assert ids.tolist() == [1]
