"""Rendezvous geometry without a server: the observed pose at the observation's time, and agreement."""

from __future__ import annotations

import numpy as np

from hivemap.maps.geometry import se3, se3_inverse, so3_exp
from hivemap.server.backend.options import RendezvousOptions
from hivemap.server.backend.rendezvous_fit import Oriented, bracket, consensus, edge_of

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
