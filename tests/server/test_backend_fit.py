"""A loop's point-pair fit and its bootstrap spread (backend.fit.fit_pairs), and how the pose graph weighs a
loop edge by it (backend.optimise.pose_graph).

Pairs: points 4-14 m from the query camera (source frame) and from a candidate camera 10 m away
(target frame), each side off along its own viewing rays as stereo depth is (sigma k d^2). The
spread the fit reports for the query camera must match its true error in size, and grow with the
noise.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.server.backend.fit import fit_pairs as _fit_pairs
from hivemap.server.backend.optimise import pose_graph as _pose_graph

UP = np.array([0.0, 0.0, 1.0])


def _map(xyz: np.ndarray, tag: str) -> SimpleNamespace:
    pts = {(tag, i): SimpleNamespace(xyz=p) for i, p in enumerate(xyz)}
    return SimpleNamespace(points=pts, resolve_point=lambda k: k)


def _trial(rng: np.random.Generator, k: float) -> tuple[float, float]:
    """(true error of the query camera under the fit, the fit's reported spread), m."""
    T = Sim3(so3_exp(np.radians(30.0) * UP), np.array([3.0, -2.0, 0.5]))  # target_from_source
    cq, cc_world = np.zeros(3), np.array([10.0, 0.0, 2.0])
    dirs = rng.normal(size=(120, 3)) * np.array([0.4, 1.0, 0.2]) + np.array([0.5, 1.0, 0.0])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    x = cq + dirs * rng.uniform(4.0, 14.0, 120)[:, None]  # source frame

    def along_rays(p: np.ndarray, centre: np.ndarray) -> np.ndarray:
        ray = p - centre
        d = np.linalg.norm(ray, axis=1)
        return p + ray / d[:, None] * (k * d**2 * rng.standard_normal(len(p)))[:, None]

    src = along_rays(x, cq)
    cc = T.apply(cc_world[None])[0]
    tgt = along_rays(T.apply(x), cc)
    pairs = [(("c", i), ("q", i)) for i in range(len(x))]
    est, _, _, spread = _fit_pairs(
        _map(tgt, "c"), _map(src, "q"), pairs, 0.5, False, (UP, T.R @ UP), (cq, cc), bootstrap=30
    )
    assert est is not None and spread is not None
    return float(np.linalg.norm(est.apply(cq[None]) - T.apply(cq[None]))), spread[1]


def test_bootstrap_spread_matches_the_fits_true_error_and_grows_with_noise() -> None:
    rng = np.random.default_rng(5)
    rms = {}
    for k in (0.0005, 0.002):
        err, spread = np.array([_trial(rng, k) for _ in range(30)]).T
        ratio = float(np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(spread**2)))
        assert 0.5 < ratio < 2.0, (k, ratio)
        rms[k] = float(np.sqrt(np.mean(spread**2)))
    assert rms[0.002] > 2.5 * rms[0.0005], rms


def test_pose_graph_follows_a_tight_loop_edge_and_resists_a_loose_one() -> None:
    """A chain of 21 keyframes 1 m apart whose last one drifted 0.3 m sideways; a loop edge says where it
    is. Essential edges 0.002 rad / 0.02 m here: with the loop edge at 0.02 m too, the keyframe lands
    within 5 cm of where the loop puts it (the chain of 20 edges bends 0.09 m); at 0.3 m it moves under a
    quarter of the way."""
    n = 21
    true = [se3(np.eye(3), np.array([float(i), 0.0, 0.0])) for i in range(n)]
    drift = [se3(np.eye(3), np.array([float(i), 0.3 * i / (n - 1), 0.0])) for i in range(n)]
    poses = np.array(drift)
    chain = [(i, i + 1) for i in range(n - 1)]
    loop_meas = Sim3.from_se3(true[0]).inverse() @ Sim3.from_se3(true[-1])  # cam_0 from cam_20
    moved = {}
    for sig in (0.02, 0.3):
        loop = [(0, n - 1, loop_meas, 0.002, sig)]
        out = _pose_graph(poses, poses, chain, loop, [0], True, sigmas=(0.002, 0.02)).poses
        moved[sig] = float(np.linalg.norm(out[-1].t - drift[-1][:3, 3]))
        err = float(np.linalg.norm(out[-1].t - true[-1][:3, 3]))
        if sig == 0.02:
            assert err < 0.05, err
    assert moved[0.3] < 0.25 * 0.3 and moved[0.02] > 0.25, moved


def test_levelled_reprojection_refinement_fixes_yaw_and_translation_only() -> None:
    """refine_sim3 with ``yaw_axis`` (FitOptions.level_reprojection): a levelled loop 0.3 m and 1 deg
    of yaw off, over 150 exact points seen 4-16 m away by a query camera and a candidate camera 10 m
    apart (0.5 px keypoint noise), comes back within 2 cm / 0.05 deg; its roll/pitch stay those of the
    start (the up directions') to 1e-9, even when the start leans 0.5 deg."""
    from hivemap.maps.camera import PinholeCamera
    from hivemap.maps.geometry import rotation_angle_deg, se3_inverse
    from hivemap.server.placerec import _Obs, refine_sim3

    rng = np.random.default_rng(3)
    cam = PinholeCamera(640, 480, 300.0, 300.0, 320.0, 240.0)

    def look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
        z = (target - c) / np.linalg.norm(target - c)
        x = np.cross(z, UP)
        x /= np.linalg.norm(x)
        return se3(np.stack([x, np.cross(z, x), z], 1), c)

    T = Sim3(so3_exp(np.radians(30.0) * UP), np.array([3.0, -2.0, 0.5]))  # candidate_from_query
    centre = np.array([4.0, 9.0, 0.0])
    x = centre + rng.normal(size=(150, 3)) * np.array([4.0, 3.0, 1.5])  # query-map frame
    Wq = look_at(np.array([0.0, 0.0, 1.0]), centre)
    Wc_q = look_at(np.array([10.0, 0.0, 9.0]), centre)
    Wc = se3(T.R @ Wc_q[:3, :3], T.apply(Wc_q[:3, 3][None])[0])
    qcfw, ccfw = se3_inverse(Wq), se3_inverse(Wc)

    def observe(cfw: np.ndarray, p: np.ndarray) -> np.ndarray:
        uv, valid = cam.project(p @ cfw[:3, :3].T + cfw[:3, 3])
        assert valid.all()
        return uv + 0.5 * rng.standard_normal(uv.shape)

    xc = T.apply(x)
    n = len(x)
    obs = _Obs(xc, observe(qcfw, x), np.ones(n), x, observe(ccfw, xc), np.ones(n), np.ones(n, bool),
               [(np.arange(n), cam, ccfw)])  # fmt: skip
    cq = Wq[:3, 3][None]
    for lean_deg in (0.0, 0.5):
        lean = so3_exp(np.radians(lean_deg) * np.array([1.0, 0.0, 0.0]))
        start = Sim3(so3_exp(np.radians(1.0) * UP) @ lean @ T.R, T.t + np.array([0.2, -0.2, 0.1]))
        out = refine_sim3(start, obs, cam, qcfw, True, yaw_axis=UP)
        # the refinement only turned about up: the start's tilt is kept
        turn = out.R @ start.R.T
        np.testing.assert_allclose(turn @ UP, UP, atol=1e-9)
        if lean_deg == 0.0:
            assert float(np.linalg.norm(out.apply(cq) - T.apply(cq))) < 0.02
            assert rotation_angle_deg(out.R @ T.R.T) < 0.05
        else:  # a leaning start stays leaning: what is left is the lean
            assert abs(rotation_angle_deg(out.R @ T.R.T) - lean_deg) < 0.05
