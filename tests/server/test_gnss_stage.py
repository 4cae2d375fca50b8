"""The global GNSS stage moves a map into ENU, removes drift, and rejects outlier fixes."""

from __future__ import annotations

import numpy as np
import pytest

from hivemap.maps.geometry import se3, so3_exp
from hivemap.server.backend.optimise import chain_sigmas
from hivemap.server.backend.options import OptimiseOptions
from hivemap.server.gnss_stage import GnssFix, GnssStageResult, NotEnoughFixes, ShapeEdge, fuse_gnss


def _truth(n: int = 120) -> np.ndarray:
    """A lawn-mower UAV path in ENU: 60 m legs, 10 m high."""
    poses = []
    for k in range(n):
        s = k / (n - 1) * 180.0
        leg = int(s // 60)
        u = s - 60 * leg
        x = u if leg % 2 == 0 else 60 - u
        yaw = 0.0 if leg % 2 == 0 else np.pi
        poses.append(se3(so3_exp([0, 0, yaw]), [x, 15.0 * leg + 0.05 * u, 10.0]))
    return np.array(poses)


def _map_frame(truth: np.ndarray, drift_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The same path seen in an arbitrary map frame with a yaw drift; returns (poses, map_from_enu)."""
    map_from_enu = se3(so3_exp([0, 0, 0.7]), [12.0, -40.0, 3.0])
    poses = []
    for k, p in enumerate(truth):
        drift = se3(so3_exp([0, 0, drift_scale * k]), [0, 0, 0])
        poses.append(map_from_enu @ drift @ p)
    return np.array(poses), map_from_enu


def _odometry(truth: np.ndarray, first: int = 0) -> list[ShapeEdge]:
    """An agent's odometry edges between consecutive keyframes (indices from ``first``), with the pose
    graph's own sigmas for the path travelled between them (``optimise.chain_sigmas``, default options)."""
    path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    d = np.zeros((len(path), 7))
    d[:, 0] = path
    sig = chain_sigmas(d, OptimiseOptions())
    return [
        ShapeEdge(first + k, first + k + 1, np.diag([sr**2] * 3 + [st**2] * 3), True)
        for k, (sr, st, _) in enumerate(sig)
    ]


def test_gnss_stage_aligns_and_removes_drift() -> None:
    """Fixes every 10th keyframe with 5 cm / 15 cm noise (paper Table 3): the fused positions are
    within 0.12 m RMSE (0.25 m worst, at the ends of the path; 0.096 / 0.228 measured) of truth although
    the map drifted ~1 m and sat in another frame. That drift, 2e-4 rad a keyframe, is about 3 sigmas of
    the pose graph's odometry model, which the stage holds the map by; the fixes still take most of it."""
    rng = np.random.default_rng(3)
    truth = _truth()
    poses, _ = _map_frame(truth, 2e-4)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [
        GnssFix(k, truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, len(truth), 10)
    ]
    res = fuse_gnss(poses, _odometry(truth), fixes)
    err = np.linalg.norm(res.world_from_body[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert res.used.all()
    before = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert before.max() > 10.0  # the map really started in another frame
    assert np.sqrt(np.mean(err**2)) < 0.12 and err.max() < 0.25, (np.sqrt(np.mean(err**2)), err.max())


def test_gnss_stage_rejects_outlier_fix() -> None:
    """A fix 5 m off (100 sigma) is rejected; the result stays within 0.1 m RMSE of truth."""
    rng = np.random.default_rng(4)
    truth = _truth()
    poses, _ = _map_frame(truth, 0.0)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [
        GnssFix(k, truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, len(truth), 10)
    ]
    fixes[5] = GnssFix(fixes[5].index, fixes[5].enu + np.array([5.0, 0, 0]), cov)
    res = fuse_gnss(poses, _odometry(truth), fixes)
    assert not res.used[5] and res.used.sum() == len(fixes) - 1
    err = np.linalg.norm(res.world_from_body[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1 and err.max() < 0.2, (np.sqrt(np.mean(err**2)), err.max())


def test_gnss_stage_refuses_too_few_or_clustered_fixes() -> None:
    truth = _truth()
    cov = np.eye(3) * 0.01
    with pytest.raises(NotEnoughFixes):
        fuse_gnss(truth, _odometry(truth), [GnssFix(0, truth[0, :3, 3], cov)] * 2)
    with pytest.raises(NotEnoughFixes):
        fuse_gnss(truth, _odometry(truth), [GnssFix(k, truth[k, :3, 3], cov) for k in range(3)])


def test_links_carry_one_agents_fixes_to_another() -> None:
    """Two agents flying side by side in one drifted map (the same 2e-4 rad/keyframe yaw drift, ~1 m
    at the end); only A has fixes. B's chain alone has no GNSS: without links the rigid alignment
    leaves its drift (0.286 m RMSE, asserted > 0.25). Inter-agent links (shared views at three
    places) carry A's correction to B: within 0.2 m RMSE of truth (0.169 measured)."""
    rng = np.random.default_rng(5)
    truth_a = _truth()
    truth_b = np.array([p @ se3(np.eye(3), [0.0, 2.0, 0.0]) for p in truth_a])  # 2 m to A's left
    a, _ = _map_frame(truth_a, 2e-4)
    b, _ = _map_frame(truth_b, 2e-4)
    poses = np.concatenate([a, b])
    n = len(truth_a)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [GnssFix(k, truth_a[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, n, 10)]
    chains = _odometry(truth_a) + _odometry(truth_b, n)
    link_cov = np.diag([0.003**2] * 3 + [0.02**2] * 3)

    def rmse_b(links: list[tuple[int, int]]) -> float:
        shape = chains + [ShapeEdge(i, j, link_cov, False) for i, j in links]
        res = fuse_gnss(poses, shape, fixes)
        err = np.linalg.norm(res.world_from_body[n:, :3, 3] - truth_b[:, :3, 3], axis=1)
        return float(np.sqrt(np.mean(err**2)))

    without, with_links = rmse_b([]), rmse_b([(0, n), (n // 2, n + n // 2), (n - 1, 2 * n - 1)])
    assert without > 0.25
    assert with_links < 0.2


def test_map_transform_of_a_gravity_aligned_map_keeps_it_level() -> None:
    """A short stretch with few fixes of 15 cm vertical noise: a 6-DoF fit would tilt the map by the
    noise; the gravity-aligned stage's ``enu_from_map`` is yaw + translation and recovers the true yaw."""
    rng = np.random.default_rng(8)
    truth = _truth()[:40]  # 40 m of one leg
    poses, map_from_enu = _map_frame(truth, 0.0)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [GnssFix(k, truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, 40, 8)]
    res = fuse_gnss(poses, _odometry(truth), fixes)
    R = res.enu_from_map[:3, :3]
    assert np.allclose(R[2], [0.0, 0.0, 1.0], atol=1e-9) and np.allclose(R[:, 2], [0.0, 0.0, 1.0], atol=1e-9)
    true_R = np.linalg.inv(map_from_enu)[:3, :3]
    yaw_err = np.degrees(np.arccos(np.clip((np.trace(R @ true_R.T) - 1) / 2, -1, 1)))
    assert yaw_err < 0.5, yaw_err
    # the same fit without the gravity assumption tilts by the fixes' vertical noise
    from hivemap.server.gnss_stage import GnssStageOptions

    free = fuse_gnss(poses, _odometry(truth), fixes, GnssStageOptions(gravity_aligned=False))
    assert not np.allclose(free.enu_from_map[2, :3], [0.0, 0.0, 1.0], atol=1e-3)


def test_agents_up_directions_remove_the_maps_tilt_drift() -> None:
    """The map's keyframes pitch-drift by 0.3 mrad each (visual tilt drift: 2 degrees after 120
    keyframes; with the legs' turns the path's end sinks 0.3 m), 4 fixes. Held at the map's own
    roll/pitch, the stage keeps part of that bend; held at the agents' IMU up directions (truth + 0.2
    degree noise, what the agents' second stage measures on factory01) it removes most of it; the rest
    is the 4 fixes' vertical noise (0.15 m) bending the map."""
    rng = np.random.default_rng(9)
    truth = _truth()
    poses = [truth[0]]
    for k in range(1, len(truth)):
        rel = np.linalg.inv(truth[k - 1]) @ truth[k]
        poses.append(poses[-1] @ rel @ se3(so3_exp([0.0, 3e-4, 0.0]), [0.0, 0.0, 0.0]))
    poses = np.array(poses)
    assert np.abs(poses[:, 2, 3] - truth[:, 2, 3]).max() > 0.2  # the drift really bent the map
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [
        GnssFix(k, truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, len(truth), 30)
    ]
    up = np.array([T[2, :3] for T in truth]) + rng.normal(0, np.radians(0.2), (len(truth), 3))
    up /= np.linalg.norm(up, axis=1, keepdims=True)

    def height_rmse(res: object) -> float:
        z = res.world_from_body[:, 2, 3] - truth[:, 2, 3]  # type: ignore[attr-defined]
        return float(np.sqrt(np.mean(z**2)))

    def bend(res: object) -> float:  # height error without its mean (the fixes' common offset)
        z = res.world_from_body[:, 2, 3] - truth[:, 2, 3]  # type: ignore[attr-defined]
        return float(np.std(z))

    chain = _odometry(truth)
    res_own = fuse_gnss(poses, chain, fixes)
    res_imu = fuse_gnss(poses, chain, fixes, up_in_body=up)
    half = up.copy()
    half[::2] = np.nan  # keyframes without an up direction keep the map's own
    res_mixed = fuse_gnss(poses, chain, fixes, up_in_body=half)
    own, imu, mixed = height_rmse(res_own), height_rmse(res_imu), height_rmse(res_mixed)
    # measured: height RMSE 0.122 / 0.052 / 0.082 m (own attitude / IMU up / half of the keyframes)
    assert imu < 0.1 and imu < 0.7 * own, (imu, own)
    assert imu <= mixed < own, (imu, mixed, own)
    assert bend(res_imu) < 0.7 * bend(res_own), (bend(res_imu), bend(res_own))  # 0.046 vs 0.108 m


@pytest.mark.parametrize(("drift", "stiff"), [(2e-4, False), (0.0, True)])
def test_cross_validation_picks_how_stiff_the_chain_is(drift: float, stiff: bool) -> None:
    """GnssStageOptions.stiffness_scales: the lawn-mower path with fixes every 10th keyframe. Drifting 2e-4
    rad per keyframe (~1 m), the held-out fixes are predicted best by the loosest odometry (scale 1,
    0.083 m RMSE measured; at 0.1 the drift stays: 0.305 m); not drifting, by a stiff one (0.03
    measured), which lets the fixes' noise bend the map less: 0.031 m RMSE measured against 0.064 at
    scale 1."""
    rng = np.random.default_rng(3)
    truth = _truth()
    poses, _ = _map_frame(truth, drift)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    fixes = [
        GnssFix(k, truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in range(0, len(truth), 10)
    ]
    chains = _odometry(truth)

    def rmse(res: GnssStageResult) -> float:
        return float(np.sqrt(np.mean(np.sum((res.world_from_body[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))

    cv = fuse_gnss(poses, chains, fixes)
    scores = cv.cv_scores
    assert scores is not None and set(scores) == {1.0, 0.3, 0.1, 0.03}
    assert cv.stiffness_scale == min(scores, key=scores.__getitem__)
    others = {k: rmse(fuse_gnss(poses, chains, fixes, stiffness_scale=k)) for k in scores}
    if stiff:
        assert cv.stiffness_scale <= 0.1
        assert rmse(cv) < 0.6 * others[1.0], (rmse(cv), others)
    else:
        assert cv.stiffness_scale == 1.0
        assert rmse(cv) < 0.1 and others[0.1] > 0.12, others
    # a given scale skips the cross-validation
    assert fuse_gnss(poses, chains, fixes, stiffness_scale=0.3).cv_scores is None


def _shape_rmse(est: np.ndarray, truth: np.ndarray) -> float:
    """Position RMSE after one SE(3) alignment (evo's Umeyama): the map's shape, whatever its frame."""
    from evo.core.geometry import umeyama_alignment

    R, t, _ = umeyama_alignment(est[:, :3, 3].T, truth[:, :3, 3].T, with_scale=False)
    err = est[:, :3, 3] @ np.asarray(R).T + np.asarray(t).reshape(3) - truth[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def test_the_maps_loops_hold_its_shape_against_few_noisy_fixes() -> None:
    """A map whose loops closed it (right in shape, in another frame) with 4 fixes of 5 cm / 15 cm noise
    (the challenged2 mode): held by its pose graph's own edges, the odometry and the loops between the
    lawn-mower's legs, the stage moves it into ENU and leaves its shape within 2 cm (measured 0.006 m mean,
    0.012 worst over 20 draws). The odometry alone lets the fixes' noise bend it (0.028 m mean, 0.056
    worst); the stage's earlier chain of per-metre sigmas, without the loops, more (0.059 m, 0.139)."""
    truth = _truth()
    poses, _ = _map_frame(truth, 0.0)
    n = len(truth)
    cov = np.diag([0.05**2, 0.05**2, 0.15**2])
    odometry = _odometry(truth)
    loop_cov = np.diag([np.radians(0.3) ** 2] * 3 + [0.02**2] * 3)
    # keyframes k and 79 - k, 79 - k and 80 + k are at the same x on neighbouring legs, 15 m apart
    loops = [ShapeEdge(k, 79 - k, loop_cov, False) for k in range(0, 40, 5)]
    loops += [ShapeEdge(79 - k, 80 + k, loop_cov, False) for k in range(0, 40, 5)]
    held, odometry_only = [], []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        picks = sorted(rng.choice(n, 4, replace=False))
        fixes = [GnssFix(int(k), truth[k, :3, 3] + rng.normal(0, [0.05, 0.05, 0.15]), cov) for k in picks]
        res = fuse_gnss(poses, odometry + loops, fixes)
        assert np.linalg.norm(res.world_from_body[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.5
        held.append(_shape_rmse(res.world_from_body, truth))
        odometry_only.append(_shape_rmse(fuse_gnss(poses, odometry, fixes).world_from_body, truth))
    assert max(held) < 0.02, held
    assert np.mean(odometry_only) > 2 * np.mean(held), (odometry_only, held)
