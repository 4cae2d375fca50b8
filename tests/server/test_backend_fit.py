"""A loop's point-pair fit and its bootstrap spread (backend._fit_pairs), and how the pose graph weighs a
loop edge by it (backend._pose_graph).

Pairs: points 4-14 m from the query camera (source frame) and from a candidate camera 10 m away
(target frame), each side off along its own viewing rays as stereo depth is (sigma k d^2). The
spread the fit reports for the query camera must match its true error in size, and grow with the
noise.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hivemap.maps.geometry import Sim3, se3, so3_exp
from hivemap.server.backend import _fit_pairs, _pose_graph

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
        out = _pose_graph(poses, poses, chain, loop, [0], True, sigmas=(0.002, 0.02))
        moved[sig] = float(np.linalg.norm(out[-1].t - drift[-1][:3, 3]))
        err = float(np.linalg.norm(out[-1].t - true[-1][:3, 3]))
        if sig == 0.02:
            assert err < 0.05, err
    assert moved[0.3] < 0.25 * 0.3 and moved[0.02] > 0.25, moved
