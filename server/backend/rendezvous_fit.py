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


def skew(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(T: F64) -> F64:
    """(6, 6) adjoint of SE(3) ``T`` in gtsam's tangent order [rot, trans]: ``T Exp(x) T^-1 = Exp(Ad x)``."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def edge_covariance(
    cam_from_observed: F64, covariance: F64, a_from_t: F64, path_m: float, interp: tuple[float, float],
    o: RendezvousOptions,
) -> F64:  # fmt: skip
    """(6, 6) covariance of the edge ``ref_from_cam cam_from_observed a_from_t^-1`` in gtsam's Between
    perturbation (right, on the query side; [rot, trans]): the PnP's (right perturbation of
    ``cam_from_observed``) carried to the query keyframe; the observer's own error of ``ref_from_cam``
    (its front-end's drift over the ``path_m`` between the reference keyframe and the frame), whose
    rotation acts over the whole distance to the observed agent; the interpolation's ``interp`` (rad, m)."""
    A_pnp = adjoint(a_from_t)
    cov = A_pnp @ np.asarray(covariance, dtype=np.float64) @ A_pnp.T
    A_obs = adjoint(a_from_t @ se3_inverse(cam_from_observed))
    s_r, s_t = math.radians(o.observer_drift_deg_per_m) * path_m, o.observer_drift_trans * path_m
    cov += A_obs @ np.diag([s_r**2] * 3 + [s_t**2] * 3) @ A_obs.T
    cov += A_pnp @ np.diag([interp[0] ** 2] * 3 + [interp[1] ** 2] * 3) @ A_pnp.T
    return 0.5 * (cov + cov.T)


def level(measured: F64, cov: F64, up_c: F64, up_q: F64, sigma_rad: float) -> tuple[F64, F64]:
    """The edge ``measured`` (candidate_from_query, covariance ``cov`` as :func:`edge_covariance`) updated
    with the relative tilt the two keyframes' IMU up directions give (``up_c``, ``up_q``, in their camera
    frames; ``sigma_rad`` the error of their relative tilt): ``measured`` should carry ``up_q`` onto
    ``up_c``. An iterated Kalman update in the edge's tangent: the tilt, which a PnP of a carrier seen
    from afar knows worst, comes from gravity, and whatever the PnP's translation shares with its tilt
    error moves with it."""
    up_c = up_c / np.linalg.norm(up_c)
    up_q = up_q / np.linalg.norm(up_q)
    a = np.cross(up_c, [1.0, 0.0, 0.0] if abs(up_c[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    B = np.stack([a, np.cross(up_c, a)])  # (2, 3) across up_c
    R0 = measured[:3, :3]

    def r(w: F64) -> F64:
        return B @ (R0 @ so3_exp(w) @ up_q)

    noise = sigma_rad**2 * np.eye(2)
    x = np.zeros(6)
    J = np.zeros((2, 6))
    K = np.zeros((6, 2))
    for _ in range(5):
        r0 = r(x[:3])
        J[:, :3] = -B @ R0 @ so3_exp(x[:3]) @ skew(up_q)  # d/dw of R Exp(w) u ~ R (u + w x u)
        K = cov @ J.T @ np.linalg.inv(J @ cov @ J.T + noise)
        x_new = K @ (J @ x - r0)
        done = float(np.linalg.norm(x_new - x)) < 1e-12
        x = x_new
        if done:
            break
    IKJ = np.eye(6) - K @ J
    out = IKJ @ cov @ IKJ.T + K @ noise @ K.T
    return measured @ se3(so3_exp(x[:3]), x[3:]), 0.5 * (out + out.T)


def _floored(cov: F64, floor_rot: float, floor_trans: float) -> F64:
    """``cov`` with the eigenvalues of its rotation and translation blocks raised to at least the floors'
    squares (the cross terms kept)."""
    out = cov.copy()
    for sl, f in ((slice(0, 3), floor_rot), (slice(3, 6), floor_trans)):
        lam, U = np.linalg.eigh(out[sl, sl])
        out[sl, sl] += U @ np.diag(np.maximum(f**2 - lam, 0.0)) @ U.T
    return out


def edge_of(
    ref_key: KfKey,
    ref_from_cam: F64,
    cam_from_observed: F64,
    covariance: F64,
    br: Bracket,
    o: RendezvousOptions,
    ups: tuple[F64 | None, F64 | None] | None = None,
) -> NewEdge:
    """The observation as an edge from the observer's reference keyframe (candidate) to the observed
    agent's keyframe ``br.a`` (query): the observed pose at the observation's time is ``a`` moved by the
    interpolated share of its motion a -> b. Its covariance (:func:`edge_covariance`), levelled by the
    keyframes' up directions ``ups`` (candidate, query) when both have one (:func:`level`), floored,
    then multiplied by ``o.correlated_edges``; the sigmas are the largest of its blocks before that."""
    a_from_b = se3_inverse(br.world_from_a) @ br.world_from_b
    a_from_t = interpolate(a_from_b, br.alpha)
    measured = ref_from_cam @ cam_from_observed @ se3_inverse(a_from_t)
    # interpolation: none at a keyframe, most in the middle; extrapolation: grows with the distance past a
    u = abs(br.alpha) if br.alpha < 0 else min(br.alpha, 1.0 - br.alpha)
    it = o.interp_share * u * float(np.linalg.norm(a_from_b[:3, 3]))
    ir = o.interp_share * u * float(np.linalg.norm(so3_log(a_from_b[:3, :3])))
    path = float(np.linalg.norm(ref_from_cam[:3, 3]))
    cov = edge_covariance(cam_from_observed, covariance, a_from_t, path, (ir, it), o)
    if ups is not None and ups[0] is not None and ups[1] is not None and o.level_sigma_deg > 0:
        measured, cov = level(measured, cov, ups[0], ups[1], math.radians(o.level_sigma_deg))
    cov = _floored(cov, math.radians(o.sigma_rot_floor_deg), o.sigma_trans_floor_m)
    # the sigmas are the one observation's (the agreement gate judges each alone)
    sigma_rot = math.sqrt(float(np.linalg.eigvalsh(cov[:3, :3]).max()))
    sigma_trans = math.sqrt(float(np.linalg.eigvalsh(cov[3:, 3:]).max()))
    return NewEdge(ref_key, br.a, Sim3.from_se3(measured), sigma_rot, sigma_trans,
                   cov * max(o.correlated_edges, 1.0))  # fmt: skip


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


def _error(edge: NewEdge, candidate_from_query: F64) -> F64:
    """(6,) ``[rot, trans]`` error of the edge at this relative pose of its keyframes (query side, as the
    pose graph's Between factor)."""
    E = se3_inverse(edge.measured.matrix()) @ candidate_from_query
    return np.concatenate([so3_log(E[:3, :3]), E[:3, 3]])


def whitened(T: F64, x: Oriented, floors: tuple[float, float] = (0.0, 0.0)) -> F64:
    """(6,) the observation's whitened residual under target_from_source ``T``, its sigmas at least
    ``floors`` (rad, m)."""
    c_from_q = T if x.candidate_in_target else se3_inverse(T)
    r = _error(x.edge, se3_inverse(x.world_from_candidate) @ c_from_q @ x.world_from_query)
    sr, st = max(x.edge.sigma_rot, floors[0]), max(x.edge.sigma_trans, floors[1])
    return np.concatenate([r[:3] / sr, r[3:] / st])


def chi2(T: F64, x: Oriented, floors: tuple[float, float] = (0.0, 0.0)) -> float:
    return float(np.sum(whitened(T, x, floors) ** 2))


def edge_chi2(edge: NewEdge, world_from_candidate: F64, world_from_query: F64) -> float:
    """Chi-square of a rendezvous edge (:func:`edge_of`: it always carries its covariance) within one
    map at the keyframes' current poses."""
    assert edge.covariance is not None
    r = _error(edge, se3_inverse(world_from_candidate) @ world_from_query)
    return float(r @ np.linalg.solve(np.asarray(edge.covariance, dtype=np.float64), r))


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
