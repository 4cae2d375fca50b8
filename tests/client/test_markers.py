"""Marker detection: carrier poses from rendered (distorted) images against ground truth, refusals, and
the covariance against a Monte-Carlo spread."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from marker_carriers import board_carrier, cube_carrier

from hivemap.client.frontend.markers import MarkerDetector, MarkerOptions, solve_carrier_pose
from hivemap.client.frontend.synthetic import SyntheticScene, body_from_cam_pitched
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import rotation_angle_deg, rotation_between, se3, se3_inverse, transform_points

CAM = PinholeCamera(640, 480, 430.0, 430.0, 319.5, 239.5, (-0.05, 0.01, 0.0002, -0.0001))
UAV_CAM = body_from_cam_pitched(45.0)
UGV_CAM = body_from_cam_pitched(0.0)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_from_cam of an OpenCV camera at ``eye`` looking at ``target`` (world z up)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return se3(np.stack([x, np.cross(z, x), z], 1), eye)


def truth(world_from_cam: np.ndarray, world_from_body: np.ndarray, carrier_cam: np.ndarray) -> np.ndarray:
    return se3_inverse(world_from_cam) @ world_from_body @ carrier_cam


def carriers() -> dict:
    return {
        "uav1": cube_carrier("uav1", 0, 0.3, np.array([0.0, 0.0, -0.25]), UAV_CAM),
        "ugv": board_carrier("ugv", 10, 0.25, 0.05, UGV_CAM),
        "me": cube_carrier("me", 20, 0.3, np.array([0.0, 0.0, -0.25]), UAV_CAM),
    }


def render(cs: dict, placed: dict[str, np.ndarray], world_from_cam: np.ndarray) -> np.ndarray:
    scene = SyntheticScene(seed=3, size=40.0, wall_h=8.0)
    for aid, T in placed.items():
        scene.add_marker_carrier(cs[aid], T)
    return scene.render(CAM, world_from_cam)


UAV_AT = se3(np.eye(3), np.array([0.0, 0.0, 3.0]))  # a UAV hovering 3 m up, yawed 0
UGV_AT = se3(np.eye(3), np.array([2.0, 1.0, 1.0]))  # a UGV whose roof board is 1 m above the ground


@pytest.mark.parametrize(
    ("eye", "dist_tol_rel"),
    [((1.5, -1.2, 2.0), 0.02), ((3.0, 1.0, 2.0), 0.02), ((4.0, -3.0, 1.5), 0.04)],
)
def test_cube_pose_matches_truth(eye: tuple[float, float, float], dist_tol_rel: float) -> None:
    cs = carriers()
    W_c = look_at(np.array(eye), UAV_AT[:3, 3] + [0.0, 0.0, -0.25])
    img = render(cs, {"uav1": UAV_AT}, W_c)
    obs = MarkerDetector(CAM, cs, "ugv").detect(img)
    assert [o.agent_id for o in obs] == ["uav1"]
    o = obs[0]
    gt = truth(W_c, UAV_AT, UAV_CAM)
    d = float(np.linalg.norm(gt[:3, 3]))
    assert o.n_corners >= 8 and o.reproj_rms_px < 1.5
    assert np.linalg.norm(o.cam_from_observed[:3, 3] - gt[:3, 3]) <= dist_tol_rel * d
    assert rotation_angle_deg(gt[:3, :3].T @ o.cam_from_observed[:3, :3]) <= 2.0
    assert o.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(o.covariance) > 0)


def test_roof_board_seen_from_above() -> None:
    cs = carriers()
    W_c = look_at(np.array([0.5, 0.3, 4.0]), UGV_AT[:3, 3] + [0.3, 0.0, 0.0])
    img = render(cs, {"ugv": UGV_AT}, W_c)
    obs = MarkerDetector(CAM, cs, "uav1").detect(img)
    assert [o.agent_id for o in obs] == ["ugv"]
    gt = truth(W_c, UGV_AT, UGV_CAM)
    d = float(np.linalg.norm(gt[:3, 3]))
    assert sorted(obs[0].marker_ids.tolist()) == [10, 11, 12, 13]
    assert np.linalg.norm(obs[0].cam_from_observed[:3, 3] - gt[:3, 3]) <= 0.02 * d
    assert rotation_angle_deg(gt[:3, :3].T @ obs[0].cam_from_observed[:3, :3]) <= 1.0


def test_own_unknown_and_wrong_dictionary_not_reported() -> None:
    cs = carriers()
    W_c = look_at(np.array([1.5, -0.4, 2.6]), UAV_AT[:3, 3] + [0.0, 0.0, -0.25])
    own = render(cs, {"me": UAV_AT}, W_c)
    assert MarkerDetector(CAM, cs, "me").detect(own) == []
    # the same image for an observer whose layout does not list those ids
    assert MarkerDetector(CAM, {"uav1": cs["uav1"]}, "ugv").detect(own) == []
    # markers printed from another dictionary than the layout says
    other = {"uav1": cube_carrier("uav1", 0, 0.3, np.array([0.0, 0.0, -0.25]), UAV_CAM, "DICT_6X6_50")}
    img6 = render(other, {"uav1": UAV_AT}, W_c)
    assert MarkerDetector(CAM, cs, "ugv").detect(img6) == []


def _corners_px(obj: np.ndarray, T: np.ndarray) -> np.ndarray:
    uv, ok = CAM.project(transform_points(T, obj))
    assert ok.all()
    return uv


def facing(obj: np.ndarray, dist: float, tilt_deg: float) -> np.ndarray:
    """cam_from_observed with the planar corners ``obj`` (one marker's first) facing the camera at
    ``dist``, tilted by ``tilt_deg`` about the camera's x axis."""
    c0, c1, c3 = obj[0], obj[1], obj[3]
    toward_viewer = -np.cross(c1 - c0, c3 - c0)
    R = gtsam.Rot3.Rx(np.radians(tilt_deg)).matrix() @ rotation_between(toward_viewer, np.array([0, 0, -1.0]))
    return se3(R, np.array([0.0, 0.0, dist]) - R @ obj.mean(0))


def test_single_marker_ambiguity_refused() -> None:
    board = carriers()["ugv"]
    rng = np.random.default_rng(0)
    opts = MarkerOptions()
    # one small marker seen nearly face-on from 8 m: both IPPE solutions fit its corners about equally well
    obj = board.corners_cam([10])
    T = facing(obj, 8.0, 5.0)
    refused = sum(
        solve_carrier_pose(obj, _corners_px(obj, T) + rng.normal(0, 0.5, (4, 2)), CAM, opts) is None
        for _ in range(20)
    )
    assert refused == 20
    # the whole board from 2 m at 40 deg: unambiguous, and right
    all_obj = board.corners_cam([10, 11, 12, 13])
    T = facing(all_obj, 2.0, 40.0)
    sol = solve_carrier_pose(all_obj, _corners_px(all_obj, T) + rng.normal(0, 0.3, (16, 2)), CAM, opts)
    assert sol is not None
    assert np.linalg.norm(sol[0][:3, 3] - T[:3, 3]) < 0.02 * 2.0
    assert rotation_angle_deg(T[:3, :3].T @ sol[0][:3, :3]) < 1.0


def test_covariance_matches_monte_carlo_spread() -> None:
    """The reported covariance is gtsam's Pose3 right perturbation: Logmap(truth.between(estimate))."""
    cube = carriers()["uav1"]
    ids = [0, 2, 4]  # two sides and the bottom, as a camera below and aside sees them
    obj = cube.corners_cam(ids)
    W_c = look_at(np.array([1.5, -1.0, 1.2]), UAV_AT[:3, 3] + [0.0, 0.0, -0.25])
    gt = truth(W_c, UAV_AT, UAV_CAM)
    clean = _corners_px(obj, gt)
    sigma = 0.5
    opts = MarkerOptions(pixel_sigma_px=1e-3)  # the covariance then scales with the residual alone
    rng = np.random.default_rng(1)
    T_gt = gtsam.Pose3(gt)
    xs, covs = [], []
    for _ in range(600):
        sol = solve_carrier_pose(obj, clean + rng.normal(0, sigma, clean.shape), CAM, opts)
        assert sol is not None
        xs.append(gtsam.Pose3.Logmap(T_gt.between(gtsam.Pose3(sol[0]))))
        covs.append(sol[1])
    x = np.asarray(xs)
    sample = np.cov(x.T)
    pred = np.mean(covs, axis=0)
    L = np.linalg.cholesky(pred)
    white = np.linalg.solve(L, np.linalg.solve(L, sample).T)  # L^-1 S L^-T: identity when they agree
    ev = np.linalg.eigvalsh(0.5 * (white + white.T))
    assert ev.min() > 0.75 and ev.max() < 1.3, ev
    # the left perturbation (the observer's frame) is a different covariance: the test can tell them apart
    Ad = T_gt.AdjointMap()
    white_left = np.linalg.solve(L, np.linalg.solve(L, Ad @ sample @ Ad.T).T)
    ev_left = np.linalg.eigvalsh(0.5 * (white_left + white_left.T))
    assert ev_left.max() > 2.0 or ev_left.min() < 0.5


def test_options_from_table() -> None:
    o = MarkerOptions.from_table({"every_k_frames": 2, "pixel_sigma_px": 1})
    assert o.every_k_frames == 2 and o.pixel_sigma_px == 1.0 and o.enabled
    with pytest.raises(ValueError, match="markers.nope"):
        MarkerOptions.from_table({"nope": 1})
    with pytest.raises(ValueError, match="markers.enabled"):
        MarkerOptions.from_table({"enabled": "yes"})
