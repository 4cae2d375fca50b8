"""Rendezvous geometry without a server: the observed pose at the observation's time, and agreement."""

from __future__ import annotations

import numpy as np

from hivemap.maps.geometry import se3, se3_inverse, so3_exp
from hivemap.server.backend.options import RendezvousOptions
from hivemap.server.backend.rendezvous_fit import Oriented, bracket, consensus, edge_of, interpolate

OPTS = RendezvousOptions()
COV = np.diag([0.003**2] * 3 + [0.02**2] * 3)


def track(t: float) -> np.ndarray:
    """Constant body velocity (1 m/s forward, 0.1 rad/s yaw): the exponential of a fixed twist."""
    from scipy.linalg import expm

    xi = np.zeros((4, 4))
    xi[:3, :3] = np.array([[0, -0.1, 0], [0.1, 0, 0], [0, 0, 0]])
    xi[0, 3] = 1.0
    return np.asarray(expm(xi * t))


def test_interpolated_and_extrapolated_pose_is_the_true_pose_under_constant_rotation_rate() -> None:
    kfs = [(float(t), ("ugv", t), track(float(t))) for t in range(4)]
    observer = se3(so3_exp(np.array([0.2, -0.1, 0.3])), np.array([2.0, -1.0, 3.0]))
    for t in (1.0, 1.5, 2.25, 3.2):  # 3.2: 0.2 s past the last keyframe, extrapolated
        br = bracket(kfs, t, OPTS)
        assert not isinstance(br, str), br
        edge = edge_of(("uav", 0), np.eye(4), se3_inverse(observer) @ track(t), COV, br, OPTS)
        truth = se3_inverse(observer) @ br.world_from_a
        err = se3_inverse(edge.measured.matrix()) @ truth
        # slerp is exact for the rotation; linear translation is off the 10 m radius arc by its sagitta
        assert np.linalg.norm(err[:3, 3]) < 0.015 and np.allclose(err[:3, :3], np.eye(3), atol=1e-9), (t, err)
        assert edge.sigma_trans >= 0.02 and (t != 1.5 or edge.sigma_trans > 0.09)  # mid-interval: 0.1 m
    assert isinstance(bracket(kfs, 3.5, OPTS), str)  # 0.5 s past the last keyframe: held
    assert isinstance(bracket(kfs, -0.1, OPTS), str)


def test_consensus_needs_three_agreeing_observations_and_ignores_a_wrong_one() -> None:
    rng = np.random.default_rng(3)
    true = se3(so3_exp(np.array([0.0, 0.0, 0.7])), np.array([5.0, -2.0, 0.3]))  # target_from_source

    def obs(t: float, wrong: bool = False) -> Oriented:
        wc = se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3))  # observer keyframe, target map
        wq = se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3))  # observed keyframe, source map
        c_from_q = se3_inverse(wc) @ true @ wq
        if wrong:  # another agent 4 m away
            c_from_q = c_from_q @ se3(np.eye(3), np.array([4.0, 0.0, 0.0]))
        br = bracket([(0.0, ("q", 0), np.eye(4)), (1.0, ("q", 1), np.eye(4))], 0.0, OPTS)
        assert not isinstance(br, str)
        noise = se3(so3_exp(rng.normal(0, 0.002, 3)), rng.normal(0, 0.01, 3))
        return Oriented(edge_of(("c", 0), np.eye(4), c_from_q @ noise, COV, br, OPTS), wc, wq, True, t)

    good = [obs(t) for t in (0.0, 1.5, 3.0)]
    res = consensus([obs(0.5, wrong=True), *good], OPTS)
    assert res is not None and res.inliers == [1, 2, 3], res
    assert np.linalg.norm(res.target_from_source[:3, 3] - true[:3, 3]) < 0.03
    assert consensus([obs(0.5, wrong=True), *good[:2]], OPTS) is None  # two agree: not enough
    assert consensus([obs(0.0), obs(0.2), obs(0.4)], OPTS) is None  # three within 0.4 s: not spread enough


def test_edge_covariance_predicts_its_error_and_the_up_directions_take_the_tilt() -> None:
    """A carrier 10 m off seen between two of its agent's keyframes, its PnP error drawn from an
    anisotropic covariance (tilt 1.5 deg, yaw 0.2 deg, 5 cm along the ray): the edge's errors whitened by
    its covariance are chi-square with 6 degrees of freedom (its sigmas alone cannot say that: tilt and
    yaw, ray and across it differ); with both keyframes' exact up directions its tilt error is gravity's."""
    from hivemap.maps.geometry import so3_log

    rng = np.random.default_rng(5)
    o = RendezvousOptions(observer_drift_deg_per_m=0.0, observer_drift_trans=0.0, interp_share=0.0,
                          sigma_rot_floor_deg=0.0, sigma_trans_floor_m=0.0, correlated_edges=1.0)  # fmt: skip
    # the observed agent's motion between its keyframes as the server models it (slerp, linear)
    wa = track(0.0)
    wb = wa @ se3(so3_exp(np.array([0.0, 0.0, 0.1])), np.array([1.0, 0.0, 0.0]))
    kfs = [(0.0, ("ugv", 0), wa), (1.0, ("ugv", 1), wb)]
    observer = se3(so3_exp(np.array([0.9, 0.1, 0.2])), np.array([-6.0, 2.0, 8.0]))
    t = 0.5
    w_t = wa @ interpolate(se3_inverse(wa) @ wb, t)
    truth_cfo = se3_inverse(observer) @ w_t
    up_q = w_t[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    ray = truth_cfo[:3, :3].T @ (truth_cfo[:3, 3] / np.linalg.norm(truth_cfo[:3, 3]))  # in the observed frame
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.radians(1.5) ** 2 * np.eye(3) + (np.radians(0.2) ** 2 - np.radians(1.5) ** 2) * np.outer(
        up_q, up_q
    )
    cov[3:, 3:] = 0.01**2 * np.eye(3) + (0.05**2 - 0.01**2) * np.outer(ray, ray)
    br = bracket(kfs, t, OPTS)
    assert not isinstance(br, str)
    true_edge = se3_inverse(observer) @ track(0.0)
    up_c = observer[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    up_a = track(0.0)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    m2, tilt_before, tilt_after = [], [], []
    L = np.linalg.cholesky(cov)
    for _ in range(300):
        x = L @ rng.normal(size=6)
        cfo = truth_cfo @ se3(so3_exp(x[:3]), x[3:])
        e = edge_of(("uav", 0), np.eye(4), cfo, cov, br, o)
        assert e.covariance is not None
        E = se3_inverse(e.measured.matrix()) @ true_edge
        r = np.concatenate([so3_log(E[:3, :3]), E[:3, 3]])
        m2.append(float(r @ np.linalg.solve(e.covariance, r)))
        lv = edge_of(("uav", 0), np.eye(4), cfo, cov, br, o, (up_c, up_a)).measured.matrix()
        for M, out in ((e.measured.matrix(), tilt_before), (lv, tilt_after)):
            out.append(np.degrees(np.arccos(np.clip((M[:3, :3] @ up_a) @ up_c, -1.0, 1.0))))
    assert 5.0 < np.mean(m2) < 7.0, np.mean(m2)
    assert np.sqrt(np.mean(np.square(tilt_before))) > 1.5
    assert np.sqrt(np.mean(np.square(tilt_after))) < 0.4, np.sqrt(np.mean(np.square(tilt_after)))
