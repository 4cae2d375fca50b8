"""Marker carriers in the renders (issue 25): cv2.aruco finds the carriers' ids where their true corners
project, with both renderers; markers off draws none; each dataset gets the team's layout."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.maps.markers import LAYOUT_FILE, load_layout
from hivemap.sim.carriers import (
    DICTIONARY,
    SMALL_ROOF_ROWS_X,
    CarrierDesign,
    CarrierScene,
    team_carriers,
    team_geometry,
)
from hivemap.sim.dataset import render_scenario, stereo_extrinsics
from hivemap.sim.render import GLRenderer, NumpyRenderer, make_renderer
from hivemap.sim.scenarios import get_scenario
from hivemap.sim.world import generate_world

CAM = PinholeCamera(320, 240, 215.0, 215.0, 159.5, 119.5, (-0.05, 0.01, 0.0002, -0.0001))
R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera looks along +x, level
SC = replace(get_scenario("tiny"), markers=True)


@pytest.fixture(scope="module")
def world():  # type: ignore[no-untyped-def]
    return generate_world(1, 48.0)


DEFAULT = CarrierDesign()
SMALL = CarrierDesign(ugv_small_rows_x=SMALL_ROOF_ROWS_X)  # the opt-in small roof markers


def _scene(world, d: CarrierDesign = DEFAULT):  # type: ignore[no-untyped-def]
    return CarrierScene(team_geometry(SC, d), len(world.layers), world.layers.shape[1], DICTIONARY)


def _detect(gray: np.ndarray) -> dict[int, np.ndarray]:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY)), params)
    corners, ids, _ = det.detectMarkers(gray)
    return {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


def _view(world):  # type: ignore[no-untyped-def]
    """uav1's cube 2.5 m in front of a level camera 1 m above the road, seen from below."""
    x, y = float(world.roads[0][0, 0]), float(world.roads[1][0, 1])
    world_from_cam = se3(so3_exp([0, 0, 0.3]) @ R_LEVEL, [x, y, 1.0])
    carrier = se3(
        so3_exp([0, 0, np.pi + 0.5]), world_from_cam[:3, :3] @ [0.2, -0.9, 2.5] + world_from_cam[:3, 3]
    )
    return world_from_cam, carrier


@pytest.mark.parametrize("backend", ["gl", "numpy"])
def test_rendered_carrier_is_detected_at_its_projected_corners(world, backend: str) -> None:
    scene = _scene(world)
    r = make_renderer(world, CAM, backend, extra_layers=scene.layers)
    assert isinstance(r, GLRenderer if backend == "gl" else NumpyRenderer)
    world_from_cam, carrier = _view(world)
    gray, depth = r.render(world_from_cam, scene.quads({"uav1": carrier}, "ugv"))
    r.close()
    carriers = team_carriers(SC, {a.agent_id: stereo_extrinsics(a)[0] for a in SC.agents})
    found = _detect(gray)
    assert found and set(found) <= carriers["uav1"].ids(), found
    cam_from_body = np.linalg.inv(world_from_cam) @ carrier
    by_id = {m.marker_id: m for m in carriers["uav1"].markers}
    for i, uv in found.items():
        pts = by_id[i].corners_body @ cam_from_body[:3, :3].T + cam_from_body[:3, 3]
        proj, ok = CAM.project(pts)
        assert ok.all()
        err = np.linalg.norm(proj - uv, axis=1).max()
        assert err < 1.0, (i, err, proj, uv)
        # the depth image holds the marker's own depth at its centre
        c = np.round(proj.mean(0)).astype(int)
        assert abs(float(depth[c[1], c[0]]) - pts[:, 2].mean()) < 0.05


@pytest.mark.parametrize("backend", ["gl", "numpy"])
def test_ugv_close_up_shows_its_small_roof_markers_whole(world, backend: str) -> None:
    """A camera 0.3 m over the UGV's roof, 1 m from its centre, 45 deg down (a UAV at take-off): the roof
    board's markers do not fit the image, the small ones in front of it are found at their corners."""
    scene = _scene(world, SMALL)
    x, y = float(world.roads[0][0, 0]), float(world.roads[1][0, 1])
    body = se3(so3_exp([0, 0, 0.3]), [x, y, 0.9])
    R = body[:3, :3] @ R_LEVEL @ so3_exp([-np.radians(45.0), 0, 0])
    world_from_cam = se3(R, body[:3, :3] @ [-0.7, 0.0, 0.8] + body[:3, 3])
    r = make_renderer(world, CAM, backend, extra_layers=scene.layers)
    gray, _ = r.render(world_from_cam, scene.quads({"ugv": body}, "uav1"))
    r.close()
    ugv = team_carriers(SC, {a.agent_id: stereo_extrinsics(a)[0] for a in SC.agents}, SMALL)["ugv"]
    by_id = {m.marker_id: m for m in ugv.markers}
    found = _detect(gray)
    small = {i for i in found if by_id[i].size_m < 0.2}
    assert len(small) >= 2 and set(found) <= ugv.ids(), found
    cam_from_body = np.linalg.inv(world_from_cam) @ body
    for i, uv in found.items():
        proj, ok = CAM.project(by_id[i].corners_body @ cam_from_body[:3, :3].T + cam_from_body[:3, 3])
        assert ok.all() and np.linalg.norm(proj - uv, axis=1).max() < 2.0, (i, proj, uv)


def test_ugv_layout_has_each_markers_own_size() -> None:
    """Board, panels and small roof markers: each marker's size is its own black border's side."""
    ugv = team_carriers(SC, {a.agent_id: stereo_extrinsics(a)[0] for a in SC.agents}, SMALL)["ugv"]
    for m in ugv.markers:
        assert np.allclose(
            np.linalg.norm(np.diff(m.corners_body, axis=0, append=m.corners_body[:1]), axis=1), m.size_m
        )
    assert sorted({round(m.size_m, 4) for m in ugv.markers}) == [0.1875, 0.4125, 0.525]
    assert [m.marker_id for m in ugv.markers][:8] == list(range(15, 23))  # the board and panels as before


def test_docked_uav_carrier_is_not_drawn(world) -> None:
    """On the UGV's roof a UAV's cube sits in the landing well: the same view with the UAV 1.5 m up (its
    take-off height on the roof) shows no marker."""
    scene = _scene(world)
    world_from_cam, carrier = _view(world)
    docked = carrier.copy()
    docked[2, 3] = 1.5
    assert len(scene.quads({"uav1": carrier}, "ugv").corners) == 6
    assert len(scene.quads({"uav1": docked}, "ugv").corners) == 0


@pytest.mark.parametrize("backend", ["gl", "numpy"])
def test_carrier_faces_are_one_sided(world, backend: str) -> None:
    """A face seen from behind is not drawn (the agent's body that would hide it is not rendered)."""
    scene = _scene(world)
    world_from_cam, carrier = _view(world)
    geo = team_geometry(SC)["uav1"]
    faces_w = geo.faces @ carrier[:3, :3].T + carrier[:3, 3]
    to_cam = world_from_cam[:3, 3] - faces_w.mean(1)
    nrm = np.cross(faces_w[:, 1] - faces_w[:, 0], faces_w[:, 3] - faces_w[:, 0])
    face_w = faces_w[int(np.argmin(np.einsum("ij,ij->i", nrm, to_cam)))]  # the face that looks at the camera
    q = scene.quads({"uav1": carrier}, "ugv")
    k = next(i for i, c in enumerate(q.corners) if np.allclose(c, face_w))
    keep = [i for i in range(len(q.corners)) if i != k]
    front = type(q)(q.corners[[k]], q.uv[[k]], q.layer[[k]], q.shade[[k]])
    back = type(q)(q.corners[[k]][:, ::-1], q.uv[[k]][:, ::-1], q.layer[[k]], q.shade[[k]])
    assert keep  # the other faces are not needed for this view
    r = make_renderer(world, CAM, backend, extra_layers=scene.layers)
    centre, _ = CAM.project((face_w.mean(0) - world_from_cam[:3, 3]) @ world_from_cam[:3, :3])
    u, v = np.round(centre[0]).astype(int)
    z_face = float(((face_w.mean(0) - world_from_cam[:3, 3]) @ world_from_cam[:3, :3])[2])
    _, d_front = r.render(world_from_cam, front)
    _, d_back = r.render(world_from_cam, back)
    r.close()
    assert abs(float(d_front[v, u]) - z_face) < 0.05
    assert float(d_back[v, u]) > z_face + 1.0


def test_markers_off_renders_no_marker(world) -> None:
    r = make_renderer(world, CAM, "gl")
    world_from_cam, _ = _view(world)
    gray, _ = r.render(world_from_cam)
    r.close()
    assert _detect(gray) == {}


def test_layout_written_only_with_markers(tmp_path: Path) -> None:
    sc = replace(SC, duration_s=0.3)
    w = generate_world(SC.seed, SC.world_size_m)
    render_scenario(sc, tmp_path / "on", agents=["ugv"], progress=False, world=w)
    lay = load_layout(tmp_path / "on" / "ugv" / LAYOUT_FILE)
    assert set(lay) == {a.agent_id for a in SC.agents}
    for a in SC.agents:
        assert np.allclose(lay[a.agent_id].body_from_cam, stereo_extrinsics(a)[0])
    render_scenario(replace(sc, markers=False), tmp_path / "off", agents=["ugv"], progress=False, world=w)
    assert not (tmp_path / "off" / "ugv" / LAYOUT_FILE).exists()
