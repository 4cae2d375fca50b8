"""The gtsam stereo BA (:mod:`hivemap.server.ba_gtsam`) weighs each observation by its keypoint's pyramid
level and keeps the agents' odometry between consecutive keyframes."""

from __future__ import annotations

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.server import ba_gtsam

CAM = PinholeCamera(640, 480, 420.0, 420.0, 320.0, 240.0, (-0.05, 0.01, 0.0005, -0.0003))
BASELINE = 0.11


def _corridor(rng: np.random.Generator, n: int, coarse_px: float) -> tuple[np.ndarray, ...]:
    """``n`` keyframes every 0.5 m along x looking at points 4-10 m away, every observation stereo; half
    the keypoints at octave 0 with 0.3 px noise, half at octave 6 with ``coarse_px`` noise. Returns truth,
    the start (poses off by 3 cm / 0.3 deg, points by 5 cm) and the observations."""
    truth = np.array([se3(so3_exp(rng.normal(0, 0.02, 3)), [0.5 * k, 0.0, 0.0]) for k in range(n)])
    pts = np.column_stack([rng.uniform(-6, 0.5 * n + 6, 30 * n), rng.uniform(-3, 3, 30 * n),
                           rng.uniform(4, 10, 30 * n)])  # fmt: skip
    kf, pt, uvs, urs, octs = [], [], [], [], []
    for k in range(n):
        pc = (pts - truth[k, :3, 3]) @ truth[k, :3, :3]
        uv, valid = CAM.project(pc)
        idx = np.flatnonzero(valid & CAM.in_image(uv) & (pc[:, 2] > 1))
        p = pc[idx]
        oct_ = np.where(rng.random(len(idx)) < 0.5, 0, 6).astype(np.uint8)
        noise = np.where(oct_ == 0, 0.3, coarse_px)
        ur = CAM.fx * (p[:, 0] - BASELINE) / p[:, 2] + CAM.cx + rng.normal(0, 1, len(idx)) * noise
        kf += [k] * len(idx)
        pt += idx.tolist()
        uvs.append(uv[idx] + rng.normal(0, 1, (len(idx), 2)) * noise[:, None])
        urs.append(ur)
        octs.append(oct_)
    init = truth.copy()
    for k in range(1, n):
        init[k] = init[k] @ se3(so3_exp(rng.normal(0, 0.005, 3)), rng.normal(0, 0.03, 3))
    pts0 = pts + rng.normal(0, 0.05, pts.shape)
    return (
        truth,
        init,
        pts0,
        np.array(kf),
        np.array(pt),
        np.vstack(uvs),
        np.concatenate(urs),
        np.concatenate(octs),
    )


def _relative_error(out: np.ndarray, truth: np.ndarray) -> float:
    """RMS error (m) of the translation between consecutive keyframes (the shape, not the gauge's drift)."""
    e = [np.linalg.solve(out[k], out[k + 1])[:3, 3] - np.linalg.solve(truth[k], truth[k + 1])[:3, 3]
         for k in range(len(out) - 1)]  # fmt: skip
    return float(np.sqrt(np.mean(np.square(e)) * 3))


def test_octave_sigmas_weigh_coarse_keypoints_less() -> None:
    """Half the keypoints at octave 6 with 1.2^6 times the noise of octave 0: with per-octave sigmas the
    relative poses of consecutive keyframes come out markedly closer to the truth than with every
    observation weighed alike (about 0.6 of the error)."""
    rng = np.random.default_rng(4)
    n = 30
    truth, init, pts0, kf, pt, uv, ur, octs = _corridor(rng, n, 0.3 * 1.2**6)
    cams = np.zeros(n, dtype=np.int64)
    runs = {}
    for weighted in (True, False):
        g = ba_gtsam.solve([CAM], [BASELINE], cams, init, pts0, kf, pt, uv, ur, octs, {0},
                           octave_weights=weighted)  # fmt: skip
        runs[weighted] = _relative_error(g.world_from_cam, truth)
    assert runs[True] < 0.8 * runs[False], runs
    assert runs[True] < 0.1 * _relative_error(init, truth)
