"""Synthetic maps for tests and benchmarks (random but realistic observation patterns)."""

from __future__ import annotations

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp
from hivemap.maps.model import Keyframe, Map, MapPoint

DEFAULT_CAMERA = PinholeCamera(640, 480, 458.654, 457.296, 367.215, 248.375, (-0.28, 0.07, 2e-4, 1.8e-5))


def random_keyframes_and_points(
    rng: np.random.Generator,
    agent_id: str,
    n_keyframes: int,
    n_points: int,
    *,
    obs_per_keyframe: int = 120,
    extra_keypoints: int = 30,
    window: float = 3.0,
    camera: PinholeCamera = DEFAULT_CAMERA,
    gnss_every: int = 5,
) -> tuple[list[Keyframe], list[MapPoint]]:
    """Keyframes along a path, each observing ``obs_per_keyframe`` points drawn from a window of
    ``window * n_points / n_keyframes`` consecutive point ids around its position (so neighbours share many
    points, as in a real trajectory), plus ``extra_keypoints`` unmatched keypoints. Random arrays of the
    right dtypes; every ``gnss_every``-th keyframe carries a GNSS fix."""
    pts = [
        MapPoint(agent_id, i, rng.normal(0.0, 20.0, 3), rng.integers(0, 256, 32, dtype=np.uint8))
        for i in range(n_points)
    ]
    per = n_points / max(n_keyframes, 1)
    half = max(int(window * per / 2), obs_per_keyframe // 2 + 1)
    kfs = []
    for k in range(n_keyframes):
        c = int((k + 0.5) * per)
        lo, hi = max(0, c - half), min(n_points, c + half)
        n_obs = min(obs_per_keyframe, hi - lo)
        ids = rng.choice(np.arange(lo, hi), size=n_obs, replace=False)
        n_kp = n_obs + extra_keypoints
        point_ids = np.full(n_kp, -1, np.int64)
        point_ids[rng.choice(n_kp, size=n_obs, replace=False)] = ids
        T = se3(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 30, 3))
        gnss = k % gnss_every == 0 if gnss_every else False
        kfs.append(
            Keyframe(
                agent_id,
                k,
                1e9 + 0.1 * k + rng.uniform(0, 0.01),
                T,
                camera,
                rng.uniform(0, [camera.width, camera.height], (n_kp, 2)).astype(np.float32),
                rng.integers(0, 8, n_kp, dtype=np.uint8),
                rng.integers(0, 256, (n_kp, 32), dtype=np.uint8),
                point_ids,
                gnss_enu=rng.normal(0, 30, 3) if gnss else None,
                gnss_cov=np.diag(rng.uniform(0.01, 0.1, 3)) if gnss else None,
                up_cam=T[2, :3] if k % 3 == 1 else None,  # the pose's own up axis in the camera frame
            )
        )
        if k % 4 == 2:  # a stereo keyframe: every other keypoint matched (no draws: other streams unchanged)
            kp = kfs[-1].keypoints
            kfs[-1].u_right = np.where(np.arange(n_kp) % 2 == 0, kp[:, 0] - 7.5, np.nan).astype(np.float32)
            kfs[-1].stereo_baseline = 0.11
        if k % 5 == 3:  # a keyframe after weak tracking (no draws either)
            kfs[-1].odom_sigma = np.array([0.05 * k, 1.5])
        if k % 5 == 1:  # a keyframe that says how well it tracked (no draws either)
            kfs[-1].track_sigma = np.array([0.004 + 1e-4 * k, 0.05])
    return kfs, pts


def random_map(
    rng: np.random.Generator,
    map_id: int,
    agent_id: str,
    n_keyframes: int,
    n_points: int,
    **kwargs: object,
) -> Map:
    """A ``Map`` filled with ``random_keyframes_and_points`` (points first, then keyframes)."""
    kfs, pts = random_keyframes_and_points(rng, agent_id, n_keyframes, n_points, **kwargs)  # type: ignore[arg-type]
    m = Map(map_id)
    for p in pts:
        m.add_point(p)
    for kf in kfs:
        m.add_keyframe(kf)
    return m
