"""The Sim(3) refinement's analytic Jacobian against central differences of its residuals, and the
refinement with it recovering a known similarity."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, se3_inverse, so3_exp
from hivemap.server.placerec import _Obs, refine_sim3
from hivemap.server.placerec.match import _jacobians, _residuals, _so3_left_jacobian

CAM = PinholeCamera(640, 480, 420.0, 415.0, 318.0, 243.0, (-0.28, 0.07, 0.0002, -0.0003))
UP = np.array([0.0, 0.0, 1.0])


def _look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = (target - c) / np.linalg.norm(target - c)
    x = np.cross(z, UP)
    x /= np.linalg.norm(x)
    return se3(np.stack([x, np.cross(z, x), z], 1), c)


def _scene(rng: np.random.Generator, noise_px: float) -> tuple[Sim3, _Obs, np.ndarray]:
    """A query camera and two candidate cameras over 120 points; one point behind the query camera and
    some without a query-map point (direction B and the 3D term only where there is one)."""
    T = Sim3(so3_exp([0.05, -0.02, 0.4]), np.array([3.0, -2.0, 0.5]), 1.1)  # candidate_from_query
    centre = np.array([4.0, 9.0, 0.0])
    x = centre + rng.normal(size=(120, 3)) * np.array([3.0, 2.0, 1.0])
    Wq = _look_at(np.array([0.0, 0.0, 1.0]), centre)
    qcfw = se3_inverse(Wq)
    x[0] = Wq[:3, 3] - 2.0 * Wq[:3, 2]  # behind the query camera: direction A invalid
    xc = T.apply(x)
    cams = []
    for c in (np.array([10.0, 0.0, 6.0]), np.array([8.0, 2.0, 5.0])):
        Wc_q = _look_at(c, centre)
        cams.append(se3_inverse(se3(T.R @ Wc_q[:3, :3], T.apply(Wc_q[:3, 3][None])[0])))
    uv_q, _ = CAM.project(x @ qcfw[:3, :3].T + qcfw[:3, 3])
    uv_b = np.zeros((len(x), 2))
    groups = [(np.arange(1, 60), CAM, cams[0]), (np.arange(60, 100), CAM, cams[1])]
    for idx, cam, cfw in groups:
        uv_b[idx] = cam.project(xc[idx] @ cfw[:3, :3].T + cfw[:3, 3])[0]
    has_b = np.zeros(len(x), bool)
    has_b[1:100] = True
    xq = np.where(has_b[:, None], x, np.nan)
    n = len(x)
    obs = _Obs(xc, uv_q + noise_px * rng.standard_normal(uv_q.shape), np.full(n, 1.2), xq,
               uv_b + noise_px * rng.standard_normal(uv_b.shape), np.full(n, 0.8), has_b, groups,
               np.full(n, 0.05))  # fmt: skip
    return T, obs, qcfw


@pytest.mark.parametrize("yaw,fix_scale", [(False, False), (False, True), (True, True)])
def test_jacobian_matches_central_differences(yaw: bool, fix_scale: bool) -> None:
    """At a point away from the start (the left Jacobian matters there), every column within 1e-6 of
    central differences, relative to the column's size."""
    rng = np.random.default_rng(1)
    T, obs, qcfw = _scene(rng, 0.0)
    sim0 = Sim3(so3_exp([0.02, 0.01, -0.03]) @ T.R, T.t + 0.1, T.s * 0.97)
    n_rot = 1 if yaw else 3
    n_par = n_rot + 3 + (0 if fix_scale else 1)

    def make(x: np.ndarray) -> Sim3:
        R = (so3_exp(UP * x[0]) if yaw else so3_exp(x[:3])) @ sim0.R
        return Sim3(R, sim0.t + x[n_rot : n_rot + 3], sim0.s * (1.0 if fix_scale else np.exp(x[-1])))

    def f(x: np.ndarray) -> np.ndarray:
        sim = make(x)
        ra, rb, _ = _residuals(sim, obs, CAM, qcfw)
        return np.concatenate([ra.ravel(), rb.ravel(), sim.apply(np.nan_to_num(obs.xq)).ravel()])

    x0 = rng.normal(scale=0.05, size=n_par)
    d_rot = UP[:, None] if yaw else _so3_left_jacobian(x0[:3])
    ja, jb, dy = _jacobians(make(x0), d_rot, fix_scale, obs, CAM, qcfw)
    analytic = np.concatenate([ja.reshape(-1, n_par), jb.reshape(-1, n_par), dy.reshape(-1, n_par)])
    h = 1e-6
    numeric = np.stack([(f(x0 + h * e) - f(x0 - h * e)) / (2 * h) for e in np.eye(n_par)], axis=1)
    assert np.all(ja[0] == 0.0)  # the point behind the camera: a constant residual
    for k in range(n_par):
        scale = float(np.abs(numeric[:, k]).max())
        assert scale > 0
        np.testing.assert_allclose(analytic[:, k], numeric[:, k], atol=1e-6 * scale, rtol=0)


def test_refinement_recovers_the_similarity_with_its_scale() -> None:
    """From a start 0.3 m, 2 deg and 4 % of scale off, with 0.5 px keypoint noise, the refinement comes
    back within 2 cm, 0.05 deg and 0.3 % of scale at the query camera."""
    rng = np.random.default_rng(2)
    T, obs, qcfw = _scene(rng, 0.5)
    start = Sim3(
        so3_exp(np.radians(2.0) * np.array([0.3, 0.2, 0.93])) @ T.R, T.t + [0.2, -0.2, 0.1], 1.04 * T.s
    )
    out = refine_sim3(start, obs, CAM, qcfw, False)
    cq = se3_inverse(qcfw)[:3, 3][None]
    assert float(np.linalg.norm(out.apply(cq) - T.apply(cq))) < 0.02
    assert rotation_angle_deg(out.R @ T.R.T) < 0.05
    assert abs(out.s / T.s - 1.0) < 0.003
