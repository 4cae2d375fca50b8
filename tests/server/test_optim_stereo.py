"""Global BA with stereo observations (a rig of the left camera and its virtual rectified right camera)
keeps a metric map's scale: the baseline holds it."""

from __future__ import annotations

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp, so3_log
from hivemap.server.optim import global_bundle_adjustment

CAM = PinholeCamera(640, 480, 420.0, 420.0, 320.0, 240.0, (-0.05, 0.01, 0.0005, -0.0003))
BASELINE = 0.11  # m, EuRoC's


def _stereo_corridor(rng: np.random.Generator, n: int, noise_px: float) -> tuple[np.ndarray, ...]:
    """n keyframes every 0.5 m along x looking at facades 6-12 m away; each keyframe sees up to 150 of
    the points within 12 m along x; ``u_right`` (the virtual right camera's u, undistorted) for the
    points closer than 10 m, NaN beyond (the front-end's depth cap), all with ``noise_px`` noise."""
    truth = np.array(
        [se3(so3_exp(rng.normal(0, 0.03, 3)), [0.5 * k, rng.normal(0, 0.2), 0.0]) for k in range(n)]
    )
    n_pts = 40 * n
    pts = np.column_stack(
        [rng.uniform(-10, 0.5 * n + 10, n_pts), rng.uniform(-4, 4, n_pts), rng.uniform(6, 12, n_pts)]
    )
    kf, pt, uvs, urs = [], [], [], []
    for k in range(n):
        pc = (pts - truth[k, :3, 3]) @ truth[k, :3, :3]
        uv, valid = CAM.project(pc)
        idx = np.flatnonzero(valid & CAM.in_image(uv) & (pc[:, 2] > 1) & (np.abs(pc[:, 0]) < 12))
        if len(idx) > 150:
            idx = rng.choice(idx, 150, replace=False)
        p = pc[idx]
        ur = CAM.fx * (p[:, 0] - BASELINE) / p[:, 2] + CAM.cx + rng.normal(0, noise_px, len(idx))
        kf += [k] * len(idx)
        pt += idx.tolist()
        uvs.append(uv[idx] + rng.normal(0, noise_px, (len(idx), 2)))
        urs.append(np.where(p[:, 2] < 10, ur, np.nan))
    return truth, pts, np.array(kf), np.array(pt), np.vstack(uvs), np.concatenate(urs)


def _scale(est: np.ndarray, ref: np.ndarray) -> float:
    """Scale of the least-squares similarity taking ``est`` onto ``ref`` (Umeyama)."""
    a, b = est - est.mean(0), ref - ref.mean(0)
    u, d, vt = np.linalg.svd(b.T @ a / len(a))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt))
    return float((d * sign).sum() / (a**2).sum(1).mean())


def _perturbed(rng: np.random.Generator, truth: np.ndarray, pts: np.ndarray, scale: float) -> tuple:
    """The map scaled by ``scale`` about keyframe 0 (held), then poses off by 3 cm / 0.3 deg, points
    by 5 cm."""
    c = truth[0, :3, 3]
    init = truth.copy()
    init[:, :3, 3] = c + scale * (truth[:, :3, 3] - c)
    for k in range(1, len(init)):
        init[k] = init[k] @ se3(so3_exp(rng.normal(0, 0.005, 3)), rng.normal(0, 0.03, 3))
    return init, c + scale * (pts - c) + rng.normal(0, 0.05, pts.shape)


def test_stereo_ba_brings_a_scaled_map_back_to_metric_scale() -> None:
    """60 keyframes (30 m), 0.5 px noise, the map 3% too large and perturbed, keyframe 0 held: BA brings
    the scale within 0.2% of the truth, each position within 3 cm + 0.3% of its distance from the held
    keyframe and
    every rotation within 0.2 deg; the reprojection error drops to the noise level."""
    rng = np.random.default_rng(5)
    n = 60
    truth, pts, kf, pt, uv, ur = _stereo_corridor(rng, n, 0.5)
    init, pts0 = _perturbed(rng, truth, pts, 1.03)
    cams = np.zeros(n, dtype=np.int64)
    res = global_bundle_adjustment([CAM], cams, init, pts0, kf, pt, uv, {0}, obs_ur=ur, baselines=[BASELINE])
    assert res.accepted
    assert res.extras["n_stereo"] > 0.5 * np.isfinite(ur).sum()
    out = res.world_from_cam
    s = _scale(out[:, :3, 3], truth[:, :3, 3])
    assert abs(s - 1) < 0.002, s
    # drift grows with the distance from the held keyframe: within 3 cm + 0.3% of it (input: 3% + 3 cm)
    dist = np.linalg.norm(truth[:, :3, 3] - truth[0, :3, 3], axis=1)
    err = np.linalg.norm(out[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert (err < 0.03 + 0.003 * dist).all(), np.max(err - 0.003 * dist)
    rot = [np.degrees(np.linalg.norm(so3_log(out[k, :3, :3].T @ truth[k, :3, :3]))) for k in range(n)]
    assert max(rot) < 0.2, max(rot)
    assert res.final_rmse_px < 0.8 < res.initial_rmse_px  # 0.5 px per axis -> ~0.7 px rms
    np.testing.assert_allclose(out[0], truth[0], atol=1e-9)  # the held keyframe


def test_without_stereo_observations_the_scale_stays_where_it_was() -> None:
    """The same map with every ``u_right`` NaN is a monocular BA (two held keyframes, today's gauge): it
    cannot see that the map is 3% too large, so the scale stays off (what the stereo residuals add)."""
    rng = np.random.default_rng(5)
    n = 60
    truth, pts, kf, pt, uv, ur = _stereo_corridor(rng, n, 0.5)
    init, pts0 = _perturbed(rng, truth, pts, 1.03)
    cams = np.zeros(n, dtype=np.int64)
    mono = np.full_like(ur, np.nan)
    res = global_bundle_adjustment(
        [CAM], cams, init, pts0, kf, pt, uv, {0, 1}, obs_ur=mono, baselines=[BASELINE]
    )
    assert res.accepted and res.extras["n_stereo"] == 0
    assert abs(_scale(res.world_from_cam[:, :3, 3], truth[:, :3, 3]) - 1) > 0.01


def test_the_back_ends_ba_problem_carries_the_keyframes_stereo_observations() -> None:
    """A map of stereo keyframes (``Keyframe.u_right``, ``stereo_baseline``) 3% too large: the back-end's
    BA problem (:func:`optimise.ba_problem`) holds their stereo observations and its BA
    (:func:`optimise.run_ba`) brings the scale within 0.2%; the same map's mono keyframes give none."""
    from hivemap.maps import Keyframe, Map, MapPoint
    from hivemap.server.backend import optimise

    rng = np.random.default_rng(7)
    n = 60
    truth, pts, kf, pt, uv, ur = _stereo_corridor(rng, n, 0.5)
    init, pts0 = _perturbed(rng, truth, pts, 1.03)

    def build(stereo: bool) -> Map:
        m = Map(0)
        for j in np.unique(pt):
            m.add_point(MapPoint("ugv", int(j), pts0[j]))
        for k in range(n):
            sel = kf == k
            m.add_keyframe(
                Keyframe("ugv", k, float(k), init[k], CAM, uv[sel], point_ids=pt[sel],
                         u_right=ur[sel] if stereo else None, stereo_baseline=BASELINE if stereo else None)
            )  # fmt: skip
        return m

    m = build(True)
    keys = sorted(m.keyframes)
    problem = optimise.ba_problem(m, keys)
    assert problem.n_stereo == np.isfinite(ur).sum() and problem.baselines == [BASELINE]
    poses = np.array([m.keyframes[k].world_from_cam for k in keys])
    res = optimise.run_ba(poses, problem, [0], 30)
    assert res.accepted
    assert abs(_scale(res.world_from_cam[:, :3, 3], truth[:, :3, 3]) - 1) < 0.002
    assert optimise.ba_problem(build(False), keys).n_stereo == 0
