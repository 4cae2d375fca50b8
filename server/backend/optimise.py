"""Global optimisation of a map after a merge, a loop or new fixes: the pose graph over the essential graph
plus the new edges, and global BA. Each step is built from a snapshot on the event loop, solved in the
optimisation thread (pure functions, no map access) and turned into per-keyframe corrections.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, nearest_rotations, relative_poses, sim3_arrays
from hivemap.maps.odometry import Chains
from hivemap.server.backend.options import OptimiseOptions
from hivemap.server.optim import PoseGraphOptions, PoseGraphResult

KfKey = tuple[str, int]
F64 = NDArray[np.float64]


class NewEdge(NamedTuple):
    """A loop's or merge's pose-graph edge: ``measured`` is cam_candidate_from_cam_query; sigmas in rad
    and m (``FitOptions.loop_sigma_bootstrap``). ``covariance``: (6, 6) in gtsam's Between perturbation
    ([rot, trans], query side), used instead of the sigmas where given (a rendezvous edge's)."""

    candidate: KfKey
    query: KfKey
    measured: Sim3
    sigma_rot: float
    sigma_trans: float
    covariance: F64 | None = None


@dataclass
class Snapshot:
    map_id: int
    generation: int
    keys: list[KfKey]
    poses: F64  # (N, 4, 4) world_from_cam at snapshot time


def snapshot(m: Any, generation: int) -> Snapshot:
    keys = sorted(m.keyframes)
    poses = np.array([m.keyframes[k].world_from_cam for k in keys]).reshape(-1, 4, 4)
    return Snapshot(m.id, generation, keys, poses)


def up_rows(m: Any, keys: list[KfKey]) -> F64:
    """(N, 3): each keyframe's IMU up direction in its camera frame (``Keyframe.up_cam``), NaN where none."""
    nan3 = np.full(3, np.nan)
    return np.array([nan3 if (u := m.keyframes[k].up_cam) is None else u for k in keys], dtype=np.float64)


def anchor(m: Any, keys: list[KfKey], agent_kind: Callable[[str], str], per_agent: int = 2) -> list[int]:
    """Indices of the ``per_agent`` earliest keyframes of the map's reference agent (UGV, else first
    agent): the pose graph's gauge. Start poses never join maps, so every other agent of the map is tied
    to it by edges."""
    agents = sorted(m.agents, key=lambda f: (agent_kind(f) != "ugv", f))
    for a in agents:
        idx = [i for i, k in enumerate(keys) if k[0] == a]
        if idx:
            idx.sort(key=lambda i: (m.keyframes[keys[i]].timestamp, keys[i][1]))
            return idx[:per_agent]
    return [0]


@dataclass
class PoseGraphProblem:
    initial: F64
    graph_edges: list[tuple[int, int]]
    new_edges: list[tuple[int, int, Sim3, float, float]]
    fixed: list[int]
    ups: F64 | None
    # for each of ``new_edges``, its index in the ``edges`` the problem was built from
    new_edge_source: list[int] = field(default_factory=list)
    loose: list[int] = field(default_factory=list)  # per agent joined only by robust edges: one held loosely
    # per graph edge (sigma_rot rad, sigma_trans m, extra yaw sigma rad); None: the options' sigmas
    graph_sigmas: list[tuple[float, float, float]] | None = None
    move_slack_m: float = 0.0  # how much farther than the options' limit weak tracking lets a keyframe move
    new_edge_covs: list[F64 | None] = field(default_factory=list)  # per new edge, its covariance or None
    # per graph edge, the relative pose it holds (i_from_j); None: the snapshot's (the map's shape)
    graph_rel: list[Sim3] | None = None


def pose_graph_problem(
    m: Any,
    snap: Snapshot,
    edges: list[NewEdge],
    pre: tuple[Sim3, list[KfKey]] | None,
    fixed: list[int],
    o: OptimiseOptions,
    measured_only: bool = False,
    metric: bool = True,
) -> PoseGraphProblem:
    """The pose graph of ``m``'s odometry plus ``edges``, from ``snap``; ``pre``: a correction that
    the listed keyframes start from (a loop's query neighbourhood), ``fixed``: the held keyframes.

    ``measured_only``: ``edges`` are all the map's measured loop, merge and rendezvous edges, and only
    they join its agents: the essential edges between two agents (points fused at a loop or merge) are
    left out. Their relative poses are the map's current ones, not a measurement, so a bend the map had
    when the points were fused would be held forever and outvote the loops that could straighten it.
    Each agent without a held keyframe gets a loose prior on its first one (its gauge, should the robust
    solve reject every edge to it). With ``metric`` too, each agent's odometry is its own
    (:func:`odometry_chain`); else it is the map's essential graph, holding the map's relative poses."""
    index = {k: i for i, k in enumerate(snap.keys)}
    own_odometry = measured_only and metric
    new_pairs = {(e.candidate, e.query) for e in edges} | {(e.query, e.candidate) for e in edges}
    graph_edges = [] if own_odometry else [
        (index[a], index[b])
        for a, b in m.essential_edges()
        if a in index and b in index and (a, b) not in new_pairs and not (measured_only and a[0] != b[0])
    ]  # fmt: skip
    kept = [n for n, e in enumerate(edges) if e.candidate in index and e.query in index]
    loose: list[int] = []
    if measured_only:  # each agent's first keyframe, unless the agent is held
        held = {snap.keys[i][0] for i in fixed}
        first: dict[str, int] = {}
        for i, k in enumerate(snap.keys):
            first.setdefault(k[0], i)
        loose = sorted(i for a, i in first.items() if a not in held)
    new_edges = [
        (index[edges[n].candidate], index[edges[n].query], edges[n].measured, edges[n].sigma_rot,
         edges[n].sigma_trans)
        for n in kept
    ]  # fmt: skip
    covs = [edges[n].covariance for n in kept]
    initial = snap.poses.copy()
    if pre is not None:
        for k in pre[1]:
            if k in index and index[k] not in fixed:
                initial[index[k]] = pre[0].transform_pose(snap.poses[index[k]])
    ups = up_rows(m, snap.keys) if o.pose_graph_sigma_yaw > 0 else None
    if own_odometry:
        chains = Chains(m, snap.keys, dict(zip(snap.keys, snap.poses, strict=True)))
        graph_edges, rel, sigmas = odometry_chain(m, index, chains, snap.poses, o)
        slack = max((3.0 * float(chains.weak_total(a)[0]) for a in chains.order), default=0.0)
        return PoseGraphProblem(
            initial, graph_edges, new_edges, fixed, ups, kept, loose, sigmas, slack, covs, graph_rel=rel
        )
    kfs = [m.keyframes[k] for k in snap.keys]
    tracked = o.pose_graph_tracked and any(kf.track_sigma is not None for kf in kfs)
    if not tracked and not any(kf.odom_sigma is not None for kf in kfs):
        return PoseGraphProblem(initial, graph_edges, new_edges, fixed, ups, kept, loose, new_edge_covs=covs)
    chains = Chains(m, snap.keys, dict(zip(snap.keys, snap.poses, strict=True)))
    graph_edges = across_weak_tracking(graph_edges, snap.keys, chains, m)
    sigmas = edge_sigmas(m, chains, snap.keys, graph_edges, o)
    slack = max((3.0 * float(chains.weak_total(a)[0]) for a in {k[0] for k in snap.keys}), default=0.0)
    return PoseGraphProblem(initial, graph_edges, new_edges, fixed, ups, kept, loose, sigmas, slack, covs)


def odometry_chain(
    m: Any, index: dict[KfKey, int], chains: Chains, poses: F64, o: OptimiseOptions
) -> tuple[list[tuple[int, int]], list[Sim3], list[tuple[float, float, float]]]:
    """Each agent's consecutive keyframes in time (``index``: graph index per key), the relative pose its
    own odometry measured between them (``Keyframe.vio_from_cam``, the pose it last sent; the map's where
    either has none, as in a store written before it was kept) and :func:`chain_sigmas`.

    The agent's odometry is a measurement; the map's shape is an estimate. Edges holding the map's shape
    carry every bend an earlier solve put in it into the next, and the covisibility graph's dozens of
    edges per keyframe make an agent as stiff as its scene is textured, not as sure as its tracking."""
    a_keys = [k for ks in chains.order.values() for k in ks[:-1]]
    b_keys = [k for ks in chains.order.values() for k in ks[1:]]
    if not a_keys:
        return [], [], []
    ia = np.array([index[k] for k in a_keys])
    ib = np.array([index[k] for k in b_keys])
    va = [m.keyframes[k].vio_from_cam for k in a_keys]
    vb = [m.keyframes[k].vio_from_cam for k in b_keys]
    own = np.array([x is not None and y is not None for x, y in zip(va, vb, strict=True)])
    A, B = poses[ia].copy(), poses[ib].copy()
    for n in np.flatnonzero(own):
        A[n], B[n] = va[n], vb[n]
    rel = relative_poses(A, B)
    d, _ = chains.between_many(a_keys, b_keys)
    sig = chain_sigmas(d, o)
    edges = [(int(i), int(j)) for i, j in zip(ia, ib, strict=True)]
    return edges, rel, [(float(r), float(t), float(y)) for r, t, y in sig]


def chain_sigmas(d: F64, o: OptimiseOptions) -> F64:
    """(n, 3): (sigma_rot rad, sigma_trans m, extra yaw sigma rad) of odometry edges between consecutive
    keyframes whose ends are ``d`` (:meth:`Chains.between_many`) apart: the odometry's floor and its random
    walk over the path travelled in quadrature (with ``pose_graph_tracked`` at least the tracking's own
    error), plus, in quadrature, what weak or lost tracking added."""
    path, _, weak_m, weak_deg, track_m, track_deg, untracked = d.T
    base_t = np.hypot(o.odometry_sigma_m, o.odometry_walk_m * np.sqrt(path))
    base_r = np.radians(np.hypot(o.odometry_sigma_deg, o.odometry_walk_deg * np.sqrt(path)))
    if o.pose_graph_tracked:
        use = (untracked == 0) & ((track_m > 0) | (track_deg > 0))
        base_t[use] = np.maximum(base_t[use], o.pose_graph_track_scale * track_m[use])
        base_r[use] = np.maximum(base_r[use], o.pose_graph_track_scale * np.radians(track_deg[use]))
    weak_r = np.radians(weak_deg)
    return np.stack([np.hypot(base_r, weak_r), np.hypot(base_t, weak_m), weak_r], axis=1)


def across_weak_tracking(
    graph_edges: list[tuple[int, int]], keys: list[KfKey], chains: Chains, m: Any
) -> list[tuple[int, int]]:
    """Where an agent's tracking was weak or lost before a keyframe (``odom_sigma``), one edge crosses
    that stretch: from its previous keyframe to it. The covisibility and spanning-tree edges across it go:
    their relative poses all carry the same tracking error, and as independent edges they would hold it
    as many times as there are of them, so no loop could correct it. Loop edges stay (measured)."""
    index = {k: i for i, k in enumerate(keys)}
    loops = {frozenset((index[a], index[b])) for a, b in m.loop_edges() if a in index and b in index}
    weak = [k for k in keys if m.keyframes[k].odom_sigma is not None and chains.previous(k) is not None]
    if not weak:
        return graph_edges

    d, same = chains.between_many([keys[i] for i, _ in graph_edges], [keys[j] for _, j in graph_edges])
    crossing = same & np.any(d[:, 2:4] > 0, axis=1)
    kept = [e for e, c in zip(graph_edges, crossing, strict=True) if not c or frozenset(e) in loops]
    odo = {tuple(sorted((index[p], index[k]))) for k in weak if (p := chains.previous(k)) is not None}
    return kept + sorted((int(a), int(b)) for a, b in odo)


def edge_sigmas(
    m: Any, chains: Chains, keys: list[KfKey], edges: list[tuple[int, int]], o: OptimiseOptions
) -> list[tuple[float, float, float]]:
    """:func:`odometry_sigmas` of each essential edge (indices into ``keys``); between two agents (their
    fused points) whose keyframes both say how well they tracked, the two keyframes' own errors in
    quadrature (times the scale), so these edges are weighed on the same footing as the agents' odometry
    around them."""
    a, b = [keys[i] for i, _ in edges], [keys[j] for _, j in edges]
    d, same = chains.between_many(a, b)
    out = odometry_sigmas_many(d, same, o)
    if o.pose_graph_tracked:
        for n in np.flatnonzero(~same):
            ta, tb = m.keyframes[a[n]].track_sigma, m.keyframes[b[n]].track_sigma
            if ta is not None and tb is not None:
                sr, st = tracked_sigmas(float(np.hypot(ta[0], tb[0])), float(np.hypot(ta[1], tb[1])), o)
                out[n] = (sr, st, 0.0)
    return [(float(r), float(t), float(y)) for r, t, y in out]


def tracked_sigmas(track_m: float, track_deg: float, o: OptimiseOptions) -> tuple[float, float]:
    """(sigma_rot rad, sigma_trans m) of an edge whose tracking error is ``track_m`` / ``track_deg``:
    times ``pose_graph_track_scale``, at least the ``pose_graph_track_floor_*``."""
    st = max(o.pose_graph_track_scale * track_m, o.pose_graph_track_floor_m)
    sr = max(
        o.pose_graph_track_scale * float(np.radians(track_deg)),
        float(np.radians(o.pose_graph_track_floor_deg)),
    )
    return sr, st


def odometry_sigmas(chain: F64 | None, o: OptimiseOptions) -> tuple[float, float, float]:
    """(sigma_rot rad, sigma_trans m, extra yaw sigma rad) of an essential edge whose ends are
    ``chain`` (:meth:`Chains.between`) apart; :func:`odometry_sigmas_many` of one edge."""
    if chain is None:
        return o.pose_graph_sigma_rot, o.pose_graph_sigma_trans, 0.0
    sr, st, sy = odometry_sigmas_many(np.asarray(chain, dtype=np.float64)[None], np.ones(1, bool), o)[0]
    return float(sr), float(st), float(sy)


def odometry_sigmas_many(d: F64, same: NDArray[np.bool_], o: OptimiseOptions) -> F64:
    """(n, 3): (sigma_rot rad, sigma_trans m, extra yaw sigma rad) of edges whose ends are ``d``
    (:meth:`Chains.between_many`) apart. The base: with ``pose_graph_tracked``, where every keyframe
    between them says how well it tracked, that error summed along the chain (times
    ``pose_graph_track_scale``, at least the ``pose_graph_track_floor_*``), so an agent that tracked badly
    bends at a loop and one that tracked well does not; else the options' fixed sigmas. Across weak
    tracking, the drift over the path travelled or the base, whichever is larger, plus the weak sigma.
    Across agents (``same`` False): the options' fixed sigmas (:func:`edge_sigmas` weighs those by the
    two keyframes' tracking where both say it)."""
    n = len(d)
    base_r, base_t = np.full(n, o.pose_graph_sigma_rot), np.full(n, o.pose_graph_sigma_trans)
    path, turn, weak_m, weak_deg, track_m, track_deg, untracked = d.T
    if o.pose_graph_tracked:
        use = same & (untracked == 0) & ((track_m > 0) | (track_deg > 0))
        base_t[use] = np.maximum(o.pose_graph_track_scale * track_m[use], o.pose_graph_track_floor_m)
        base_r[use] = np.maximum(o.pose_graph_track_scale * np.radians(track_deg[use]),
                                 np.radians(o.pose_graph_track_floor_deg))  # fmt: skip
    # tracked well: the ends' shared points set their relative pose, which the drift does not bend
    weak = same & ((weak_m > 0) | (weak_deg > 0))
    weak_r = np.radians(weak_deg)
    sr = np.where(weak, np.hypot(np.maximum(base_r, o.pose_graph_drift_rot * turn), weak_r), base_r)
    st = np.where(weak, np.hypot(np.maximum(base_t, o.pose_graph_drift_trans * path), weak_m), base_t)
    return np.stack([sr, st, np.where(weak, weak_r, 0.0)], axis=1)


def pose_graph_corrections(snap: Snapshot, sims: list[Sim3]) -> tuple[dict[KfKey, Sim3], float]:
    """Each keyframe's correction from the solved poses (``sims[i] @ snap.poses[i]^-1``, batched: one
    Sim3 at a time held the event loop on large maps), and the largest move (m)."""
    n = len(snap.keys)
    if n == 0:
        return {}, 0.0
    P = np.asarray(snap.poses, dtype=np.float64).reshape(n, 4, 4)
    Rs, ts, ss = sim3_arrays(sims)
    RsRpt = Rs @ nearest_rotations(P[:, :3, :3]).transpose(0, 2, 1)
    R = nearest_rotations(RsRpt)
    t = ts - ss[:, None] * np.einsum("nij,nj->ni", RsRpt, P[:, :3, 3])
    corr = {k: Sim3._trusted(R[i], t[i], float(ss[i])) for i, k in enumerate(snap.keys)}
    moved = float(np.linalg.norm(ts - P[:, :3, 3], axis=1).max())
    return corr, moved


def solve_pose_graph(p: PoseGraphProblem, poses: F64, metric: bool, o: OptimiseOptions) -> PoseGraphResult:
    """Optimisation thread: :func:`pose_graph` on a :class:`PoseGraphProblem`; the result's
    ``inlier`` and ``chi2`` are those of ``p.new_edges`` (the essential edges are always kept)."""
    t0 = time.process_time()
    res = pose_graph(
        p.initial, poses, p.graph_edges, p.new_edges, p.fixed, metric,
        sigmas=(o.pose_graph_sigma_rot, o.pose_graph_sigma_trans),
        sigma_yaw=o.pose_graph_sigma_yaw if o.pose_graph_sigma_yaw > 0 else None, ups=p.ups,
        options=PoseGraphOptions(gnc=o.gnc, gnc_inlier_probability=o.gnc_inlier_probability), loose=p.loose,
        graph_sigmas=p.graph_sigmas, covariances=p.new_edge_covs, graph_rel=p.graph_rel,
    )  # fmt: skip
    n = len(p.graph_edges)
    return PoseGraphResult(res.poses, res.inlier[n:], res.chi2[n:], (time.process_time() - t0) * 1e3)


def pose_graph(
    initial: F64,
    poses: F64,
    graph_edges: list[tuple[int, int]],
    new_edges: list[tuple[int, int, Sim3, float, float]],
    fixed: list[int],
    metric: bool,
    *,
    sigmas: tuple[float, float],
    sigma_yaw: float | None = None,
    ups: F64 | None = None,
    options: PoseGraphOptions | None = None,
    loose: Sequence[int] = (),
    graph_sigmas: Sequence[tuple[float, float, float]] | None = None,
    covariances: Sequence[F64 | None] = (),
    graph_rel: Sequence[Sim3] | None = None,
) -> PoseGraphResult:
    """Initial values ``initial``; the graph's edges keep the relative poses of ``poses`` (uncorrected),
    with ``sigmas`` (rad, m); ``new_edges`` (i, j, i_from_j, sigma_rot, sigma_trans) are robust (Huber,
    or judged by GNC with ``options.gnc``; the result's ``inlier`` has one flag per edge, graph's first).
    ``sigma_yaw`` with ``ups`` ((N, 3) up directions in the keyframes' camera frames, NaN rows where there
    is none): the graph's edges hold the rotation about the far keyframe's up with this sigma instead.
    ``graph_sigmas``: per graph edge (sigma_rot, sigma_trans, extra yaw sigma), instead of ``sigmas``.
    ``covariances``: per new edge, a (6, 6) covariance instead of its two sigmas, or None.
    ``graph_rel``: per graph edge, the relative pose it holds instead of that of ``poses``.

    ``metric``: the map has metric scale (stereo agents), so the graph is SE(3) (gtsam Pose3). A Sim(3)
    graph let scale creep in at each of the dozens of loop closures of a factory run until poses
    overflowed, and holding its scale with a tiny log-scale sigma made it ill-conditioned (rotations
    came out scaled by ~100)."""
    from hivemap.server.optim import solve_pose_graph_se3, solve_pose_graph_sim3

    edges = pose_graph_edges(
        poses, graph_edges, new_edges, sigmas=sigmas, sigma_yaw=sigma_yaw, ups=ups, graph_sigmas=graph_sigmas,
        covariances=covariances, graph_rel=graph_rel,
    )  # fmt: skip
    opts = options or PoseGraphOptions()
    if metric:
        return solve_pose_graph_se3(initial, edges, set(fixed), opts, loose)
    return solve_pose_graph_sim3(initial, edges, set(fixed), opts, loose)


def pose_graph_edges(
    poses: F64,
    graph_edges: list[tuple[int, int]],
    new_edges: list[tuple[int, int, Sim3, float, float]],
    *,
    sigmas: tuple[float, float],
    sigma_yaw: float | None = None,
    ups: F64 | None = None,
    graph_sigmas: Sequence[tuple[float, float, float]] | None = None,
    covariances: Sequence[F64 | None] = (),
    graph_rel: Sequence[Sim3] | None = None,
) -> list[Any]:
    """The :class:`~hivemap.server.optim.PoseGraphEdge` list of :func:`pose_graph` (its arguments): the
    graph's edges first, holding ``graph_rel`` or else the relative poses of ``poses``, then the robust
    new edges."""
    from hivemap.server.optim import PoseGraphEdge

    def up(j: int) -> tuple[float, float, float] | None:
        if sigma_yaw is None or ups is None or not np.all(np.isfinite(ups[j])):
            return None
        return (float(ups[j][0]), float(ups[j][1]), float(ups[j][2]))

    per_edge = graph_sigmas if graph_sigmas is not None else [(sigmas[0], sigmas[1], 0.0)] * len(graph_edges)
    if graph_rel is not None:
        rel = list(graph_rel)
    else:
        ij = np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2)
        stack = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        rel = relative_poses(stack[ij[:, 0]], stack[ij[:, 1]])
    edges = [
        PoseGraphEdge(
            i,
            j,
            r,
            sigma_rot=sr,
            sigma_trans=st,
            sigma_yaw=None if sigma_yaw is None else float(np.hypot(sigma_yaw, sy)),
            up_j=up(j),
        )  # fmt: skip
        for (i, j), (sr, st, sy), r in zip(graph_edges, per_edge, rel, strict=True)
    ]
    covs = list(covariances) + [None] * (len(new_edges) - len(covariances))
    edges += [PoseGraphEdge(i, j, s, sr, st, robust=True, covariance=c)
              for (i, j, s, sr, st), c in zip(new_edges, covs, strict=True)]  # fmt: skip
    return edges


def problem_edges(p: PoseGraphProblem, poses: F64, o: OptimiseOptions) -> list[Any]:
    """:func:`pose_graph_edges` of a :class:`PoseGraphProblem` with the options' sigmas (what
    :func:`solve_pose_graph` solves)."""
    return pose_graph_edges(
        poses, p.graph_edges, p.new_edges, sigmas=(o.pose_graph_sigma_rot, o.pose_graph_sigma_trans),
        sigma_yaw=o.pose_graph_sigma_yaw if o.pose_graph_sigma_yaw > 0 else None, ups=p.ups,
        graph_sigmas=p.graph_sigmas, covariances=p.new_edge_covs, graph_rel=p.graph_rel,
    )  # fmt: skip


@dataclass
class BAProblem:
    """``obs_ur``: each observation's ``u_right`` (NaN: mono), ``baselines``: per camera its stereo
    baseline (m) or None (``Keyframe.u_right``, ``Keyframe.stereo_baseline``); ``obs_octave`` and
    ``odometry``: the stereo BA's weights and between factors (:mod:`hivemap.server.ba_gtsam`)."""

    cameras: list[Any]
    camera_index: NDArray[np.int64]
    point_keys: list[Any]
    points: F64
    obs_kf: NDArray[np.int64]
    obs_pt: NDArray[np.int64]
    obs_uv: F64
    obs_ur: F64 = field(default_factory=lambda: np.zeros(0))
    baselines: list[float | None] = field(default_factory=list)
    obs_octave: NDArray[np.uint8] | None = None  # each observation's keypoint pyramid level
    # each agent's consecutive keyframes (i, j, sigma_rot rad, sigma_trans m): the pose graph's odometry
    odometry: list[tuple[int, int, float, float]] = field(default_factory=list)

    @property
    def n_stereo(self) -> int:
        return int(np.isfinite(self.obs_ur).sum())


def odometry_edges(m: Any, keys: list[KfKey], o: OptimiseOptions) -> list[tuple[int, int, float, float]]:
    """Each agent's consecutive keyframes in time with the pose graph's sigmas for that stretch
    (:func:`odometry_sigmas`): (i, j, sigma_rot rad, sigma_trans m), indices into ``keys``."""
    index = {k: i for i, k in enumerate(keys)}
    chains = Chains(m, keys)
    out = []
    for ks in chains.order.values():
        for a, b in zip(ks, ks[1:], strict=False):
            sr, st, _ = odometry_sigmas(chains.between(a, b), o)
            out.append((index[a], index[b], sr, st))
    return out


def ba_problem(m: Any, keys: list[KfKey], o: OptimiseOptions | None = None) -> BAProblem:
    """Copy what the BA needs out of the map (on the loop, quick); with ``o``, the agents' odometry
    between consecutive keyframes too (:func:`odometry_edges`)."""
    cams: dict[Any, int] = {}
    cam_list: list[Any] = []
    baselines: list[float | None] = []
    cam_idx = np.zeros(len(keys), dtype=np.int64)
    pidx: dict[Any, int] = {}
    pkeys: list[Any] = []
    obs_kf: list[Any] = []
    obs_pt: list[Any] = []
    obs_uv: list[Any] = []
    obs_ur: list[Any] = []
    obs_oct: list[Any] = []
    for i, k in enumerate(keys):
        kf = m.keyframes[k]
        ck = (id(kf.camera), kf.stereo_baseline)
        if ck not in cams:
            cams[ck] = len(cam_list)
            cam_list.append(kf.camera)
            baselines.append(kf.stereo_baseline)
        cam_idx[i] = cams[ck]
        idx_kp, idx_pt = [], []
        for idx, pk in kf.referenced_points():
            pk = m.resolve_point(pk)
            if pk not in m.points:
                continue
            j = pidx.get(pk)
            if j is None:
                j = pidx[pk] = len(pkeys)
                pkeys.append(pk)
            idx_kp.append(idx)
            idx_pt.append(j)
        obs_kf.append(np.full(len(idx_kp), i, dtype=np.int64))
        obs_pt.append(np.asarray(idx_pt, dtype=np.int64))
        obs_uv.append(kf.keypoints[idx_kp].reshape(-1, 2))
        ur = kf.u_right[idx_kp] if kf.u_right is not None else np.full(len(idx_kp), np.nan)
        obs_ur.append(np.asarray(ur, dtype=np.float64))
        obs_oct.append(kf.octaves[idx_kp])
    pts = np.array([m.points[pk].xyz for pk in pkeys], dtype=np.float64).reshape(-1, 3)

    def cat(parts: list[Any], dtype: Any, shape: tuple[int, ...]) -> Any:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    return BAProblem(
        cam_list, cam_idx, pkeys, pts, cat(obs_kf, np.int64, (0,)), cat(obs_pt, np.int64, (0,)),
        cat(obs_uv, np.float64, (0, 2)), cat(obs_ur, np.float64, (0,)), baselines,
        cat(obs_oct, np.uint8, (0,)), odometry_edges(m, keys, o) if o is not None else [],
    )  # fmt: skip


def run_ba(poses: F64, p: BAProblem, fixed: list[int], max_iterations: int, solver: str = "gtsam") -> Any:
    """BA process: :func:`hivemap.server.optim.global_bundle_adjustment` of ``p`` from ``poses``."""
    from hivemap.server.ba_gtsam import OdometryEdge
    from hivemap.server.optim import BundleAdjustmentOptions, global_bundle_adjustment

    return global_bundle_adjustment(
        p.cameras, p.camera_index, poses, p.points, p.obs_kf, p.obs_pt, p.obs_uv, set(fixed),
        BundleAdjustmentOptions(max_iterations=max_iterations, stereo_solver=solver), obs_ur=p.obs_ur,
        baselines=p.baselines, obs_octave=p.obs_octave, odometry=[OdometryEdge(*e) for e in p.odometry],
    )  # fmt: skip


def ba_corrections(snap: Snapshot, res: Any, problem: BAProblem) -> tuple[dict[KfKey, Sim3], dict[Any, F64]]:
    """Each keyframe's correction and each point's new position from a BA result."""
    corr = {k: Sim3.from_se3(res.world_from_cam[i]) @ Sim3.from_se3(snap.poses[i]).inverse()
            for i, k in enumerate(snap.keys)}  # fmt: skip
    new_xyz = {pk: res.points[j] for j, pk in enumerate(problem.point_keys)}
    return corr, new_xyz
