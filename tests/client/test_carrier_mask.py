"""Other agents' carriers masked out of tracking (issues 25/28): no ORB feature and no stereo match on a
carrier whose true outline is known, from its pose or, when the pose is refused, from its marker quads;
a carrier the detector misses keeps its mask for ``hold_frames`` frames; between whole-image searches
the masked carriers are followed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from marker_carriers import cube_carrier

from hivemap.client.frontend.carrier_mask import CarrierMask
from hivemap.client.frontend.features import OrbExtractor
from hivemap.client.frontend.markers import MarkerOptions
from hivemap.client.frontend.options import FrontendOptions
from hivemap.client.frontend.synthetic import SyntheticScene, body_from_cam_pitched, make_rig
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, se3_inverse
from hivemap.maps.markers import Carrier

RIG = make_rig(f=430.0, pitch=0.0, dist=(-0.05, 0.01, 0.0002, -0.0001))
UAV_CAM = body_from_cam_pitched(45.0)
CARRIERS = {"uav2": cube_carrier("uav2", 0, 0.3, np.array([0.0, 0.0, -0.25]), UAV_CAM)}
CUBE_AT = se3(np.eye(3), np.array([0.3, 0.2, 2.0]))  # uav2 hovering; its cube's centre 1.75 m up


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return se3(np.stack([x, np.cross(z, x), z], 1), eye)


def _true_hull(carrier: Carrier, cam_from_body: np.ndarray, cam: PinholeCamera) -> np.ndarray:
    """The carrier's printed faces (markers grown by their one-cell quiet zone, 8/6) in ``cam``."""
    pts = []
    for m in carrier.markers:
        c = m.corners_body
        pts.append(c.mean(0) + (8 / 6) * (c - c.mean(0)))
    P = np.concatenate(pts) @ cam_from_body[:3, :3].T + cam_from_body[:3, 3]
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    return cv2.convexHull(uv.reshape(-1, 2).astype(np.float32))


@pytest.fixture(scope="module")
def view() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(left, right, true hull in cam0, true hull in cam1) of the cube seen from 1.6 m."""
    scene = SyntheticScene(seed=3, size=40.0, wall_h=8.0)
    scene.add_marker_carrier(CARRIERS["uav2"], CUBE_AT)
    centre = CUBE_AT[:3, 3] + [0.0, 0.0, -0.25]
    W_l = _look_at(centre + np.array([-1.3, -0.8, 0.5]), centre)
    W_b = W_l @ se3_inverse(RIG.body_from_left)
    W_r = W_b @ RIG.body_from_right
    left, right = scene.render(RIG.left, W_l), scene.render(RIG.right, W_r)
    hl = _true_hull(CARRIERS["uav2"], se3_inverse(W_l) @ CUBE_AT, RIG.left)
    hr = _true_hull(CARRIERS["uav2"], se3_inverse(W_r) @ CUBE_AT, RIG.right)
    return left, right, hl, hr


def _inside(uv: np.ndarray, hull: np.ndarray) -> int:
    return sum(cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in uv)


def _covered(mask: np.ndarray, hull: np.ndarray) -> float:
    """Fraction of the hull's pixels that the mask blocks (0)."""
    region = np.zeros_like(mask)
    cv2.fillConvexPoly(region, np.round(hull).astype(np.int32), 255)
    return float(np.mean(mask[region > 0] == 0))


def test_carrier_from_its_pose_has_no_features_in_either_image(view: tuple) -> None:
    left, right, hl, hr = view
    cm = CarrierMask(RIG, CARRIERS, "uav1")
    ml, mr = cm.update(0.0, left)
    assert [o.agent_id for o in cm.observations] == ["uav2"] and cm.stats.by_pose == 1
    assert ml is not None and mr is not None
    assert _covered(ml, hl) >= 0.999 and _covered(mr, hr) >= 0.999
    orb = OrbExtractor(FrontendOptions())
    uv_free = orb.extract(left, adapt=False)[0]
    uv_masked = orb.extract(left, adapt=False, mask=ml)[0]
    assert _inside(uv_free, hl) >= 100  # the carrier is textured: without a mask ORB fires on it
    assert _inside(uv_masked, hl) == 0
    # the mask is the carrier plus a margin, not the image: the static world keeps its features
    assert len(uv_masked) >= 0.6 * len(uv_free)
    assert float(np.mean(ml == 0)) < 0.25


def test_refused_pose_masks_the_detected_quads(view: tuple) -> None:
    left, right, hl, hr = view
    cm = CarrierMask(RIG, CARRIERS, "uav1", MarkerOptions(max_reproj_rms_px=0.0))  # every pose refused
    ml, mr = cm.update(0.0, left)
    assert cm.observations == [] and cm.stats.by_quads == 1
    assert ml is not None and mr is not None
    # the detected faces are most of what is visible of the cube
    assert _covered(ml, hl) >= 0.8 and _covered(mr, hr) >= 0.8


def test_missed_carrier_stays_masked_for_hold_frames(view: tuple) -> None:
    left = view[0]
    blank = np.full_like(left, 128)
    cm = CarrierMask(RIG, CARRIERS, "uav1", hold_frames=3)
    assert cm.update(0.0, left)[0] is not None
    held = [cm.update(0.05 * (i + 1), blank)[0] is not None for i in range(4)]
    assert held == [True, True, True, False]
    assert cm.stats.held == 3


def test_between_whole_image_searches_only_masked_carriers_are_followed(view: tuple) -> None:
    left = view[0]
    blank = np.full_like(left, 128)
    cm = CarrierMask(RIG, CARRIERS, "uav1", full_every=2)
    assert cm.update(0.0, left)[0] is not None and cm.full_frame
    # frame 1: searched around the mask only, the carrier found there again with its pose
    assert cm.update(0.05, left)[0] is not None and not cm.full_frame
    assert [o.agent_id for o in cm.observations] == ["uav2"] and cm.stats.by_pose == 2
    cm = CarrierMask(RIG, CARRIERS, "uav1", full_every=2)
    assert cm.update(0.0, blank) == (None, None)
    # a carrier appearing between two whole-image searches is masked from the next one on
    assert cm.update(0.05, left) == (None, None) and cm.observations == []
    assert cm.update(0.10, left)[0] is not None and cm.full_frame


def test_own_carrier_is_not_masked(view: tuple) -> None:
    cm = CarrierMask(RIG, CARRIERS, "uav2")
    assert cm.update(0.0, view[0]) == (None, None)
