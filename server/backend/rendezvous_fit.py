"""Rendezvous geometry (pure functions): an observation as a pose-graph edge, with the observed agent's pose
at the observation's time interpolated between its keyframes, and the map-to-map transform a set of
observations agrees on (chi-square gate, least squares)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp, so3_log
from hivemap.server.backend.optimise import NewEdge
from hivemap.server.backend.options import RendezvousOptions

F64 = NDArray[np.float64]
KfKey = tuple[str, int]


def interpolate(a_from_b: F64, alpha: float) -> F64:
    """The pose a share ``alpha`` along the relative motion ``a_from_b`` (in a's frame): rotation by
    slerp, translation linearly; ``alpha`` > 1 extrapolates at the same velocity."""
    R = so3_exp(alpha * so3_log(a_from_b[:3, :3]))
    return se3(R, alpha * a_from_b[:3, 3])


@dataclass(frozen=True)
class Bracket:
    """The observed agent's keyframes around the observation's time: ``a`` (at or before it) and ``b``
    (after it, or before ``a`` when extrapolating), their poses in their map, and the share ``alpha`` of
    the motion a -> b at the observation's time (> 1 when extrapolating)."""

    a: KfKey
    b: KfKey
    world_from_a: F64
    world_from_b: F64
    alpha: float


def bracket(keyframes: Sequence[tuple[float, KfKey, F64]], t: float, o: RendezvousOptions) -> Bracket | str:
    """The keyframes around time ``t`` among one agent map's ``(timestamp, key, world_from_cam)``, sorted
    by time; a string says why there is none yet."""
    if len(keyframes) < 2:
        return "the observed agent has fewer than two keyframes"
    times = np.array([k[0] for k in keyframes])
    if t < times[0]:
        return "the observation is older than the observed agent's first keyframe"
    i = int(np.searchsorted(times, t, side="right"))
    if i < len(keyframes):
        (ta, ka, wa), (tb, kb, wb) = keyframes[i - 1], keyframes[i]
        return Bracket(ka, kb, wa, wb, (t - ta) / (tb - ta) if tb > ta else 0.0)
    (tp, kp, wp), (tl, kl, wl) = keyframes[-2], keyframes[-1]
    if t - tl > o.extrapolate_max_s or tl <= tp:
        return f"no keyframe of the observed agent after the observation yet ({t - tl:.2f} s past its last)"
    # extrapolate from the last keyframe at the velocity of the last two: a = last, motion a -> b reversed
    return Bracket(kl, kp, wl, wp, -(t - tl) / (tl - tp))


def edge_of(
    ref_key: KfKey,
    ref_from_cam: F64,
    cam_from_observed: F64,
    covariance: F64,
    br: Bracket,
    o: RendezvousOptions,
) -> NewEdge:
    """The observation as an edge from the observer's reference keyframe (candidate) to the observed
    agent's keyframe ``br.a`` (query): the observed pose at the observation's time is ``a`` moved by the
    interpolated share of its motion a -> b. Sigmas: the PnP covariance's largest (its rotation acting over
    the lever back to ``a``), plus the interpolation's uncertainty, floored."""
    a_from_b = se3_inverse(br.world_from_a) @ br.world_from_b
    a_from_t = interpolate(a_from_b, br.alpha)
    measured = ref_from_cam @ cam_from_observed @ se3_inverse(a_from_t)
    cov = np.asarray(covariance, dtype=np.float64)
    sr = math.sqrt(max(float(np.linalg.eigvalsh(cov[:3, :3]).max()), 0.0))
    st = math.sqrt(max(float(np.linalg.eigvalsh(cov[3:, 3:]).max()), 0.0))
    lever = float(np.linalg.norm(a_from_t[:3, 3]))
    # interpolation: none at a keyframe, most in the middle; extrapolation: grows with the distance past a
    u = abs(br.alpha) if br.alpha < 0 else min(br.alpha, 1.0 - br.alpha)
    it = o.interp_share * u * float(np.linalg.norm(a_from_b[:3, 3]))
    ir = o.interp_share * u * float(np.linalg.norm(so3_log(a_from_b[:3, :3])))
    sigma_rot = max(math.hypot(sr, ir), math.radians(o.sigma_rot_floor_deg))
    sigma_trans = max(math.sqrt(st**2 + (sr * lever) ** 2 + it**2), o.sigma_trans_floor_m)
    return NewEdge(ref_key, br.a, Sim3.from_se3(measured), sigma_rot, sigma_trans)


@dataclass(frozen=True)
class Oriented:
    """One observation between a target and a source map: its edge's keyframes' poses in their maps and
    whether its candidate (the observer's keyframe) is in the target map."""

    edge: NewEdge
    world_from_candidate: F64
    world_from_query: F64
    candidate_in_target: bool
    timestamp: float


def implied(x: Oriented) -> F64:
    """target_from_source (4x4) that this observation alone implies."""
    c_from_q = x.world_from_candidate @ x.edge.measured.matrix() @ se3_inverse(x.world_from_query)
    return c_from_q if x.candidate_in_target else se3_inverse(c_from_q)


def whitened(T: F64, x: Oriented, floors: tuple[float, float] = (0.0, 0.0)) -> F64:
    """(6,) the observation's whitened residual under target_from_source ``T``, its sigmas at least
    ``floors`` (rad, m)."""
    c_from_q = T if x.candidate_in_target else se3_inverse(T)
    predicted = se3_inverse(x.world_from_candidate) @ c_from_q @ x.world_from_query
    E = se3_inverse(x.edge.measured.matrix()) @ predicted
    sr, st = max(x.edge.sigma_rot, floors[0]), max(x.edge.sigma_trans, floors[1])
    return np.concatenate([so3_log(E[:3, :3]) / sr, E[:3, 3] / st])


def chi2(T: F64, x: Oriented, floors: tuple[float, float] = (0.0, 0.0)) -> float:
    return float(np.sum(whitened(T, x, floors) ** 2))


def least_squares(
    T0: F64, obs: Sequence[Oriented], floors: tuple[float, float] = (0.0, 0.0), iterations: int = 10
) -> F64:
    """target_from_source minimising the observations' whitened residuals (Gauss-Newton, left
    perturbation, numerical Jacobian: a handful of observations, six unknowns)."""
    T = T0.copy()

    def moved(d: F64) -> F64:
        return se3(so3_exp(d[:3]), d[3:]) @ T

    for _ in range(iterations):
        r0 = np.concatenate([whitened(T, x, floors) for x in obs])
        J = np.zeros((len(r0), 6))
        h = 1e-6
        for j in range(6):
            d = np.zeros(6)
            d[j] = h
            J[:, j] = (np.concatenate([whitened(moved(d), x, floors) for x in obs]) - r0) / h
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        T = moved(step)
        if float(np.linalg.norm(step)) < 1e-10:
            break
    return T


@dataclass(frozen=True)
class Consensus:
    target_from_source: F64
    inliers: list[int]  # indices into the observations
    chi2: list[float]  # every observation's under the transform


def consensus(obs: Sequence[Oriented], o: RendezvousOptions) -> Consensus | None:
    """The largest set of observations whose residuals under their least-squares transform all pass the
    chi-square gate, if it has ``min_observations`` spread over ``min_span_s``; else None. Each
    observation seeds one hypothesis (its own implied transform), so one wrong observation, however far
    off, cannot pull the others' transform: it only fails the gate."""
    f = (math.radians(o.agree_sigma_rot_deg), o.agree_sigma_trans_m)
    best: Consensus | None = None
    tried: set[tuple[int, ...]] = set()
    for seed in obs:
        T = implied(seed)
        inl = [i for i, x in enumerate(obs) if chi2(T, x, f) < o.gate_chi2]
        if tuple(inl) in tried:  # the seeds of one agreeing set all lead to its least squares
            continue
        tried.add(tuple(inl))
        for _ in range(3):
            if len(inl) < 2:
                break
            T = least_squares(T, [obs[i] for i in inl], f)
            again = [i for i, x in enumerate(obs) if chi2(T, x, f) < o.gate_chi2]
            if again == inl:
                break
            inl = again
        c2 = [chi2(T, x, f) for x in obs]
        score = (len(inl), -sum(c2[i] for i in inl))
        if best is None or score > (len(best.inliers), -sum(best.chi2[i] for i in best.inliers)):
            best = Consensus(T, inl, c2)
    if best is None or len(best.inliers) < o.min_observations:
        return None
    times = [obs[i].timestamp for i in best.inliers]
    if max(times) - min(times) < o.min_span_s:
        return None
    return best
