"""Marginal covariances of keyframe poses from the server's pose graph (gtsam: the linearised graph's
Bayes tree, what ``gtsam.Marginals`` builds, with the wanted poses eliminated last when they are few).

Convention of every covariance this module returns (and the server reports, REST and protocol): a pose
``world_from_cam`` = (R, p) in the map frame is perturbed as ``R = Exp(dtheta) R_hat``, ``p = p_hat + dp``
with ``dtheta`` (rad) and ``dp`` (m) both in the map frame; the (6, 6) covariance is that of
``[dtheta, dp]`` and its lower-right (3, 3) block is the camera centre's position covariance in the map
frame. gtsam's own marginal of a Pose3 is in its right perturbation ``T = T_hat Exp([w, v])`` (rotation
first, both in the camera frame); to first order ``dtheta = R_hat w`` and ``dp = R_hat v``, so the map
frame's covariance is ``B Sigma B^T`` with ``B = diag(R_hat, R_hat)`` (:func:`to_map_frame`).

The covariance is relative to the graph's gauge: the held keyframes (the reference agent's first) have
zero covariance and define the map frame. The pose graph is the SE(3) one for every map (a Sim(3) map's
scale uncertainty is not represented), linearised at the poses given.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.optim import PoseGraphEdge, PoseGraphOptions, se3_graph

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]

# up to this many wanted poses are ordered last in the elimination (the latest keyframes of a map's agents)
FEW = 64

CONVENTION = (
    "[dtheta (rad), dp (m)] in the map frame: R = Exp(dtheta) R_hat, p = p_hat + dp (camera centre); "
    "gtsam's right perturbation [w, v] maps to it by diag(R_hat, R_hat)"
)


@dataclass
class MarginalsResult:
    """``covariances`` (len(indices), 6, 6) in the map frame (module docstring), in the order of
    ``indices``; ``relative``: per asked pair (a, b) the (3, 3) map-frame covariance of the difference of
    their camera centres ``p_a - p_b`` (pairs with a pose no edge reaches are left out); ``cpu_s``: the
    CPU time the factorisation and recovery took."""

    indices: list[int]
    covariances: F64
    cpu_s: float
    relative: dict[tuple[int, int], F64] = field(default_factory=dict)


def to_map_frame(cov_right: F64, R: F64) -> F64:
    """gtsam's right-perturbation (6, 6) Pose3 covariance of a pose with rotation ``R`` -> the map frame's
    ``[dtheta, dp]`` covariance (module docstring)."""
    B = np.zeros((6, 6))
    B[:3, :3] = R
    B[3:, 3:] = R
    out = B @ cov_right @ B.T
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)


def pose_marginals(
    world_from_cam: F64,
    edges: list[PoseGraphEdge],
    fixed: set[int] | frozenset[int],
    options: PoseGraphOptions | None = None,
    loose: Sequence[int] = (),
    indices: Sequence[int] | None = None,
    pairs: Sequence[tuple[int, int]] = (),
) -> MarginalsResult:
    """Marginal covariances of the poses ``indices`` (default: all) of the SE(3) pose graph that
    :func:`hivemap.server.optim.solve_pose_graph_se3` solves, linearised at ``world_from_cam`` (N, 4, 4),
    in the map frame. Robust edges are weighted as the solve weights them at these poses (Huber), or
    taken whole with ``options.gnc`` (pass only the edges the GNC kept). Raises ``RuntimeError`` when the
    graph is singular (a part without gauge, or, for all poses, a pose no edge reaches); with ``indices``
    such a pose is left out of the result. ``pairs``: also the covariance of the difference of two poses'
    positions (:class:`MarginalsResult`), from their joint marginal, so the drift they share from the
    gauge cancels as it does in the difference itself."""
    import gtsam

    t0 = time.process_time()
    poses = np.asarray(world_from_cam, dtype=np.float64)
    want = list(range(len(poses))) if indices is None else [int(i) for i in indices]
    if not want and not pairs:
        return MarginalsResult([], np.zeros((0, 6, 6)), 0.0)
    graph, values = se3_graph(poses, edges, fixed, options or PoseGraphOptions(), loose)
    held = set(fixed)
    in_graph = set(graph.keyVector())
    free = [i for i in want if i not in held and i not in in_graph]
    if free and indices is None:  # a keyframe no edge reaches has no gauge, as a singular part has none
        raise RuntimeError(f"pose graph marginals: {len(free)} pose(s) without an edge (first {free[0]})")
    if free:  # asked for by index (an agent's latest keyframe, before its first edge): left out
        want = [i for i in want if i not in free]
    reach = held | in_graph
    pairs = [(int(a), int(b)) for a, b in pairs if a in reach and b in reach]
    if not want and not pairs:
        return MarginalsResult([], np.zeros((0, 6, 6)), 0.0)
    last = sorted({*want, *(i for ab in pairs for i in ab)} - held)
    try:
        linear = graph.linearize(values)
        if len(last) <= FEW:
            # the wanted poses eliminated last sit in the Bayes tree's root clique: their covariances need
            # no walk down the tree (the latest keyframe's cost 0.13 s more at 2000 keyframes otherwise)
            ordering = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(linear, last)
        else:
            ordering = gtsam.Ordering.ColamdGaussianFactorGraph(linear)
        tree = linear.eliminateMultifrontal(ordering)
    except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException
        raise RuntimeError(f"pose graph marginals: singular system ({exc})") from exc
    out = np.zeros((len(want), 6, 6))  # a held keyframe is the gauge: exact by definition
    free_want = [i for i in want if i not in held]
    # one pass over the cliques for the wanted poses and the pairs' ends: gtsam's marginalCovariance and
    # jointMarginalCovariance each recompute their clique's whole joint, and the few poses ordered last
    # share the root clique, which holds hundreds of poses in a dense covisibility graph
    home, joint = clique_joints(tree, sorted({*free_want, *(i for ab in pairs for i in ab if i not in held)}))
    for n, i in enumerate(want):
        if i in home:
            out[n] = to_map_frame(_block(joint, home, i, i), poses[i][:3, :3])
    rel = {(a, b): _difference_covariance(tree, poses, held, a, b, home, joint) for a, b in pairs}
    return MarginalsResult(want, out, time.process_time() - t0, rel)


def _block(joint: dict[int, tuple[dict[int, int], F64]], home: dict[int, int], a: int, b: int,
           dim: int = 6) -> F64:  # fmt: skip
    """The (dim, dim) covariance block of keys ``a`` and ``b`` from their clique's joint (both in it;
    symmetrised for ``a == b``)."""
    off, C = joint[home[a]]
    block = C[off[a] : off[a] + dim, off[b] : off[b] + dim]
    return np.asarray(0.5 * (block + block.T) if a == b else block, dtype=np.float64)


def clique_marginals(tree: Any, keys: Sequence[int], dim: int = 6) -> dict[int, F64]:
    """gtsam's (right-perturbation) marginal covariance of every key in ``keys`` from the Bayes tree, in
    one pass from the root down over the cliques that hold them and their ancestors
    (:func:`clique_joints`)."""
    home, joint = clique_joints(tree, keys, dim)
    return {k: _block(joint, home, k, k, dim) for k in home}


def clique_joints(
    tree: Any, keys: Sequence[int], dim: int = 6
) -> tuple[dict[int, int], dict[int, tuple[dict[int, int], F64]]]:
    """For every key in ``keys`` its clique (by first frontal key), and for each clique visited the joint
    covariance of its variables (frontal and separator) with each key's offset in it, in one pass from the
    root down over the cliques that hold the keys and their ancestors.

    ``GaussianBayesTree.marginalCovariance`` recomputes its clique's whole joint marginal for each key it
    is asked for, so a clique of k poses costs k times its joint; with a map's dense covisibility graph
    the root clique holds hundreds of poses and every keyframe's covariance took minutes. A clique's
    conditional ``R x_F + S x_S = d + n`` (noise sigmas ``s``) and its separator's joint covariance
    ``C_SS`` (a sub-block of its parent's joint) give ``C_FF = G diag(s^2) G^T + A C_SS A^T`` and
    ``C_FS = -A C_SS`` with ``G = R^-1``, ``A = G S``: each clique's joint once (covariance recovery from
    the square-root information matrix, Kaess and Dellaert 2009). Every variable has ``dim`` dimensions."""
    cliques: dict[int, Any] = {}  # by first frontal key
    parent_of: dict[int, int | None] = {}
    home: dict[int, int] = {}  # wanted key -> its clique
    for k in keys:
        c = tree[int(k)]
        home[int(k)] = int(c.conditional().firstFrontalKey())
        while True:
            f = int(c.conditional().firstFrontalKey())
            if f in cliques:
                break
            cliques[f] = c
            p = None if c.isRoot() else c.parent()
            parent_of[f] = None if p is None else int(p.conditional().firstFrontalKey())
            if p is None:
                break
            c = p
    depth: dict[int, int] = {}
    for start in cliques:  # iteratively: a long chain's tree is thousands of cliques deep
        path, at = [], start
        while at not in depth:
            up = parent_of[at]
            if up is None:
                depth[at] = 0
                break
            path.append(at)
            at = up
        for g in reversed(path):
            depth[g] = depth[parent_of[g]] + 1  # type: ignore[index]

    joint: dict[int, tuple[dict[int, int], F64]] = {}  # clique -> (key -> offset, joint covariance)
    for f in sorted(cliques, key=depth.__getitem__):
        cond = cliques[f].conditional()
        R, S = np.asarray(cond.R()), np.asarray(cond.S())
        model = cond.get_model()  # None: unit noise; a held pose's is constrained (sigmas 0)
        sigmas = np.ones(R.shape[0]) if model is None else np.asarray(model.sigmas(), dtype=np.float64)
        ks = [int(k) for k in cond.keys()]  # noqa: SIM118 (a gtsam KeyVector, not a dict)
        n_f = R.shape[0] // dim
        if R.shape[0] != n_f * dim or S.shape[1] != (len(ks) - n_f) * dim:
            raise RuntimeError(f"clique marginals: variables of {dim} dimensions only")
        G = np.linalg.inv(R)  # one small inverse per clique (R: upper triangular, full rank)
        C_ff = (G * sigmas**2) @ G.T
        order = {k: i * dim for i, k in enumerate(ks)}
        if len(ks) > n_f:
            p_off, p_cov = joint[parent_of[f]]  # type: ignore[index]
            idx = np.concatenate([np.arange(p_off[k], p_off[k] + dim) for k in ks[n_f:]])
            C_ss = p_cov[np.ix_(idx, idx)]
            A = G @ S
            C_fs = -A @ C_ss
            C_ff = C_ff - C_fs @ A.T
            C = np.block([[C_ff, C_fs], [C_fs.T, C_ss]])
        else:
            C = C_ff
        joint[f] = (order, C)
    return home, joint


def _difference_covariance(
    tree: Any,
    poses: F64,
    held: set[int],
    a: int,
    b: int,
    home: dict[int, int],
    joint: dict[int, tuple[dict[int, int], F64]],
) -> F64:
    """Map-frame (3, 3) covariance of ``p_a - p_b`` from the Bayes tree: ``C_aa + C_bb - C_ab - C_ba`` of
    the position blocks (a held pose contributes nothing); from the cliques' joints (:func:`clique_joints`
    of both keys) when both keys are in one clique, else from gtsam's joint marginal."""
    free = [i for i in (a, b) if i not in held]
    if not free:
        return np.zeros((3, 3))
    if len(free) == 1:
        f = free[0]
        return position_covariance(to_map_frame(_block(joint, home, f, f), poses[f][:3, :3]))
    if home[a] == home[b]:
        Jaa, Jbb, Jab = _block(joint, home, a, a), _block(joint, home, b, b), _block(joint, home, a, b)
    else:
        J = tree.jointMarginalCovariance([a, b])  # blocks by key: gtsam's [w, v] of each pose
        Jaa, Jbb, Jab = (np.asarray(J.at(x, y)) for x, y in ((a, a), (b, b), (a, b)))
    Ra, Rb = poses[a][:3, :3], poses[b][:3, :3]
    # only the translation parts enter: dp = R_hat v (module docstring)
    Caa = Ra @ Jaa[3:, 3:] @ Ra.T
    Cbb = Rb @ Jbb[3:, 3:] @ Rb.T
    Cab = Ra @ Jab[3:, 3:] @ Rb.T
    out = Caa + Cbb - Cab - Cab.T
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)


def position_covariance(cov6: F64) -> F64:
    """The camera centre's (3, 3) position covariance in the map frame from a map-frame (6, 6)."""
    return np.asarray(cov6[3:, 3:], dtype=np.float64)


def inside_ellipsoid(error: F64, cov3: F64, n_sigma: float = 2.0) -> bool:
    """Whether a position error (3,) lies inside the ``n_sigma`` ellipsoid of ``cov3`` (Mahalanobis
    distance <= n_sigma). A singular covariance holds only a zero error along its null directions."""
    w, V = np.linalg.eigh(0.5 * (cov3 + cov3.T))
    e = V.T @ np.asarray(error, dtype=np.float64)
    tiny = w <= 1e-12 * max(float(w.max()), 1e-300)
    if np.any(np.abs(e[tiny]) > 1e-9):
        return False
    return bool(np.sum(e[~tiny] ** 2 / w[~tiny]) <= n_sigma**2)
