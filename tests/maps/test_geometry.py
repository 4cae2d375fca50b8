"""SE(3)/Sim(3) helpers against gtsam and pycolmap conventions; camera projection/undistortion round trips."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pycolmap
import pytest
from evo.core.geometry import umeyama_alignment

from hivemap.maps.camera import PinholeCamera, StereoRig
from hivemap.maps.geometry import (
    Sim3,
    levelled_similarity,
    quat_wxyz_from_rotmat,
    relative_poses,
    rotation_angle_deg,
    rotation_between,
    rotmat_from_quat_wxyz,
    se3,
    se3_inverse,
    so3_exp,
    so3_log,
    transform_points,
)

EUROC = PinholeCamera(
    752, 480, 458.654, 457.296, 367.215, 248.375, (-0.28340811, 0.07395907, 0.00019359, 1.76e-05)
)


def random_sim(rng: np.random.Generator) -> Sim3:
    return Sim3(so3_exp(rng.normal(0, 1.0, 3)), rng.normal(0, 10, 3), float(np.exp(rng.normal(0, 0.7))))


@pytest.mark.parametrize("seed", range(5))
def test_sim3_matches_gtsam_similarity3(seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = random_sim(rng)
    pts = rng.normal(0, 20, (50, 3))
    g = S.to_gtsam()
    # gtsam maps p -> s (R p + t): same points as ours once t is divided by s (to_gtsam does it)
    got = np.array([g.transformFrom(gtsam.Point3(*p)) for p in pts])
    np.testing.assert_allclose(got, S.apply(pts), atol=1e-10)  # double round-off on ~100 m values
    # gtsam's matrix is [[R, t], [0, 1/s]]: the same projective map as our [[sR, t_ours], [0, 1]]
    Mg = np.asarray(g.matrix())
    np.testing.assert_allclose(Mg / Mg[3, 3], S.matrix(), atol=1e-10)
    back = Sim3.from_gtsam(g)
    np.testing.assert_allclose(back.matrix(), S.matrix(), atol=1e-12)
    # composition and inverse agree with gtsam's
    T = random_sim(rng)
    np.testing.assert_allclose(
        Sim3.from_gtsam(g.compose(T.to_gtsam())).matrix(), (S @ T).matrix(), atol=1e-10
    )
    np.testing.assert_allclose(Sim3.from_gtsam(g.inverse()).matrix(), S.inverse().matrix(), atol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_sim3_matches_pycolmap_sim3d(seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = random_sim(rng)
    c = S.to_pycolmap()
    pts = rng.normal(0, 20, (50, 3))
    np.testing.assert_allclose(c * pts, S.apply(pts), atol=1e-10)  # pycolmap: p -> s R p + t, as ours
    assert c.scale == pytest.approx(S.s, abs=1e-15)
    np.testing.assert_allclose(Sim3.from_pycolmap(c).matrix(), S.matrix(), atol=1e-12)
    np.testing.assert_allclose(Sim3.from_pycolmap(c.inverse()).matrix(), S.inverse().matrix(), atol=1e-10)
    # moving a camera: pycolmap's transform_camera_world(cam_from_world) == inverse of our transform_pose
    world_from_cam = se3(so3_exp(rng.normal(size=3)), rng.normal(0, 5, 3))
    cam_from_world = se3_inverse(world_from_cam)
    x, y, z, w = pycolmap.Rotation3d(cam_from_world[:3, :3]).quat
    rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), cam_from_world[:3, 3])
    moved = np.vstack([np.asarray(c.transform_camera_world(rig).matrix()), [0, 0, 0, 1]])
    np.testing.assert_allclose(moved, se3_inverse(S.transform_pose(world_from_cam)), atol=1e-10)


def test_sim3_algebra_and_transform_pose() -> None:
    rng = np.random.default_rng(9)
    A, B = random_sim(rng), random_sim(rng)
    p = rng.normal(0, 5, (20, 3))
    np.testing.assert_allclose((A @ B).apply(p), A.apply(B.apply(p)), atol=1e-10)
    np.testing.assert_allclose(A.inverse().apply(A.apply(p)), p, atol=1e-10)
    np.testing.assert_allclose(Sim3.from_matrix(A.matrix()).matrix(), A.matrix(), atol=1e-12)
    np.testing.assert_allclose(transform_points(A.matrix(), p), A.apply(p), atol=1e-12)
    with pytest.raises(ValueError):
        Sim3(np.eye(3), np.zeros(3), 0.0)
    # a moved camera stays rigid and sees the moved world as the old one scaled by s: same pixels
    T = se3(so3_exp(rng.normal(size=3)), rng.normal(0, 3, 3))
    T2 = A.transform_pose(T)
    np.testing.assert_allclose(T2[:3, :3] @ T2[:3, :3].T, np.eye(3), atol=1e-12)
    pts_cam = np.c_[rng.uniform(-2, 2, (30, 2)), rng.uniform(2, 20, 30)]
    world2 = A.apply(transform_points(T, pts_cam))
    np.testing.assert_allclose(transform_points(se3_inverse(T2), world2), A.s * pts_cam, atol=1e-9)
    uv1, _ = EUROC.project(pts_cam)
    uv2, _ = EUROC.project(transform_points(se3_inverse(T2), world2))
    np.testing.assert_allclose(uv1, uv2, atol=1e-8)


def test_se3_quaternion_and_so3_helpers() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        w = rng.normal(0, 1.0, 3)
        w = w * min(1.0, 3.0 / float(np.linalg.norm(w)))  # angle < pi: log is the inverse of exp
        R = so3_exp(w)
        np.testing.assert_allclose(so3_log(R), w, atol=1e-10)
        assert rotation_angle_deg(R) == pytest.approx(np.degrees(np.linalg.norm(w)), abs=1e-6)
        q = quat_wxyz_from_rotmat(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(rotmat_from_quat_wxyz(q), R, atol=1e-12)
        # (w, x, y, z) is gtsam's Quaternion order too
        gq = gtsam.Rot3(R).toQuaternion()
        g_wxyz = [gq.w(), gq.x(), gq.y(), gq.z()]  # type: ignore[attr-defined]
        np.testing.assert_allclose(np.asarray(g_wxyz) * np.sign(g_wxyz[0]), q, atol=1e-12)
        T = se3(R, rng.normal(size=3))
        np.testing.assert_allclose(T @ se3_inverse(T), np.eye(4), atol=1e-12)


@pytest.mark.parametrize("camera", [EUROC, PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)])
def test_camera_projection_matches_opencv_and_undistortion_round_trips(camera: PinholeCamera) -> None:
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.8, 0.8, (5000, 2)), np.ones(5000)] * rng.uniform(0.5, 50, (5000, 1))
    uv, valid = camera.project(pts)
    assert valid.all()
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist_coeffs)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    inside = camera.in_image(uv)
    # pixel -> normalized -> pixel over the whole image, corners included: 1e-6 px
    grid = np.stack(
        np.meshgrid(np.linspace(0, camera.width - 1, 60), np.linspace(0, camera.height - 1, 40)), -1
    )
    grid = grid.reshape(-1, 2)
    xy = camera.undistort_to_normalized(grid)
    back, _ = camera.project(np.c_[xy, np.ones(len(xy))])
    np.testing.assert_allclose(back, grid, atol=1e-6)
    # 3D point -> pixel -> bearing recovers the direction
    b = camera.bearing(uv[inside])
    np.testing.assert_allclose(b, pts[inside] / np.linalg.norm(pts[inside], axis=1, keepdims=True), atol=1e-9)
    und = camera.undistort_pixels(uv[inside])
    np.testing.assert_allclose(
        und, (pts[inside, :2] / pts[inside, 2:]) * [camera.fx, camera.fy] + [camera.cx, camera.cy], atol=1e-6
    )  # noqa: E501
    # behind the camera: flagged invalid
    _, v2 = camera.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]))
    assert not v2.any()
    assert PinholeCamera.from_dict(camera.to_dict()) == camera


def test_stereo_rig_baseline() -> None:
    b = 0.11
    rig = StereoRig(EUROC, EUROC, np.eye(4), se3(np.eye(3), [b, 0, 0]))
    assert rig.baseline == pytest.approx(b)
    np.testing.assert_allclose(rig.right_from_left[:3, 3], [-b, 0, 0], atol=1e-15)


def test_sim3_keeps_rotations_on_so3() -> None:
    """A rotation block with accumulated rounding error is projected back onto SO(3), so repeated
    compositions cannot amplify it (the server composes poses thousands of times)."""
    from hivemap.maps.geometry import Sim3, nearest_rotation, so3_exp

    R = so3_exp(np.array([0.3, -0.2, 1.0]))
    noisy = R + 1e-4 * np.arange(9.0).reshape(3, 3)
    s = Sim3(noisy, np.zeros(3))
    np.testing.assert_allclose(s.R @ s.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(s.R, R, atol=1e-3)
    assert nearest_rotation(R) is not None and np.array_equal(nearest_rotation(R), R)  # exact ones untouched
    T = np.eye(4)
    T[:3, :3] = noisy
    for _ in range(50):
        T = Sim3(R, np.ones(3)).transform_pose(T)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_rotation_between_takes_one_direction_onto_the_other() -> None:
    rng = np.random.default_rng(3)
    for a, b in [(rng.normal(size=3), rng.normal(size=3)), (np.array([0, 0, 2.0]), np.array([0, 0, -1.0]))]:
        R = rotation_between(a, b)
        np.testing.assert_allclose(R @ a / np.linalg.norm(a), b / np.linalg.norm(b), atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_levelled_similarity_exact_and_robust_to_depth_noise() -> None:
    """Exact data: the 5-DoF fit recovers the similarity. Points seen from 15 m with depth noise (along the
    viewing rays, as a far keyframe triangulates them): a free fit tilts, and with the true up directions
    the levelled fit puts a camera 15 m on the other side of the points nearer the truth."""
    rng = np.random.default_rng(4)
    S = Sim3(so3_exp(np.array([0.02, -0.03, 1.1])), np.array([1.0, -2.0, 0.3]), 1.3)
    up = np.array([0.0, 0.0, 1.0])
    x = rng.uniform([-3, -3, 0], [3, 3, 4], (200, 3))
    np.testing.assert_allclose(
        levelled_similarity(x, S.apply(x), up, S.R @ up).matrix(), S.matrix(), atol=1e-9
    )
    T = Sim3(S.R, S.t)  # rigid, as metric maps
    cam, far = np.array([15.0, 0.0, 1.0]), np.array([-15.0, 0.0, 1.0])
    rays = (x - cam) / np.linalg.norm(x - cam, axis=1)[:, None]
    e_free, e_lev = [], []
    for _ in range(20):
        noisy = x + rays * rng.normal(0, 0.15, (len(x), 1)) + rng.normal(0, 0.005, x.shape)
        R, t, _ = umeyama_alignment(noisy.T, T.apply(x).T, False)
        e_free.append(np.linalg.norm(Sim3(R, t).apply(far) - T.apply(far)))
        lev = levelled_similarity(noisy, T.apply(x), up, T.R @ up, with_scale=False)
        e_lev.append(np.linalg.norm(lev.apply(far) - T.apply(far)))
    assert np.median(e_lev) < 0.7 * np.median(e_free), (np.median(e_lev), np.median(e_free))


def test_levelled_similarity_weights_favour_the_near_points() -> None:
    """Points 2-15 m from the camera that saw them, stereo-like depth noise growing as the square of the
    distance (1 cm at 2 m, 56 cm at 15 m): weighting each pair by 1 / d^4 recovers the yaw and the
    translation several times better than equal weights."""
    rng = np.random.default_rng(8)
    T = Sim3(so3_exp(np.array([0.0, 0.0, 0.7])), np.array([0.5, -1.0, 0.2]))
    up = np.array([0.0, 0.0, 1.0])
    cam = np.zeros(3)
    dirs = rng.normal(size=(300, 3)) * np.array([1.0, 1.0, 0.3])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    d = rng.uniform(2.0, 15.0, 300)
    x = cam + dirs * d[:, None]
    e_eq, e_w = [], []
    probe = np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [-10.0, 0.0, 0.0]])
    for _ in range(20):
        noisy = x + dirs * (rng.normal(0, 0.0025, 300) * d**2)[:, None]
        eq = levelled_similarity(noisy, T.apply(x), up, T.R @ up, with_scale=False)
        w = levelled_similarity(noisy, T.apply(x), up, T.R @ up, with_scale=False, weights=1.0 / d**4)
        e_eq.append(np.abs(eq.apply(probe) - T.apply(probe)).max())
        e_w.append(np.abs(w.apply(probe) - T.apply(probe)).max())
    assert np.median(e_w) < 0.5 * np.median(e_eq), (np.median(e_w), np.median(e_eq))


def test_batched_relative_poses_match_the_per_pair_ones_also_off_so3() -> None:
    """``relative_poses`` is ``Sim3.from_se3(inv(a) @ b)`` per pair in one batch: the same rotations (also
    for matrices a composition left slightly off SO(3), which both project), the same translations to
    rounding, and rotations that are rotations."""
    rng = np.random.default_rng(3)
    a = np.array([se3(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 20) for _ in range(200)])
    b = np.array([se3(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 20) for _ in range(200)])
    a[::2, :3, :3] += rng.normal(size=(100, 3, 3)) * 1e-7  # off SO(3) by more than the 1e-9 tolerance
    batched = relative_poses(a, b)
    for A, B, r in zip(a, b, batched, strict=True):
        one = Sim3.from_se3(se3_inverse(A) @ B)
        np.testing.assert_allclose(r.R, one.R, atol=1e-12)
        np.testing.assert_allclose(r.t, one.t, atol=1e-9)
        assert r.s == 1.0 and np.abs(r.R @ r.R.T - np.eye(3)).max() < 1e-12
    assert relative_poses(np.zeros((0, 4, 4)), np.zeros((0, 4, 4))) == []
