"""Place recognition's geometry (descriptor matching is :mod:`.descmatch`): Sim(3) RANSAC, the bidirectional
reprojection refinement (paper 2.5.1) and the observations it works on."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse, so3_exp
from hivemap.server.placerec.descmatch import match_projected
from hivemap.server.placerec.types import PlaceRecOptions

log = logging.getLogger(__name__)

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ----------------------------------------------------------------------------------------------
# geometry
def estimate_sim3_ransac(
    src: F64,
    tgt: F64,
    max_error: float,
    fix_scale: bool,
    min_trials: int = 200,
    seed: int = 0,
    max_trials: int = 3000,
) -> tuple[Sim3, NDArray[np.bool_]] | None:
    """Robust ``tgt_from_src`` with pycolmap LO-RANSAC (Sim3d, or Rigid3d when ``fix_scale``)."""
    import pycolmap

    if len(src) < 3:
        return None
    opts = pycolmap.RANSACOptions()
    opts.max_error = float(max_error)
    opts.min_num_trials = int(min_trials)
    # bounded: a wrong candidate has ~0 % inliers and would otherwise run to 100k trials
    opts.max_num_trials = max(int(max_trials), int(min_trials))
    opts.random_seed = int(seed)
    src = np.ascontiguousarray(src, dtype=np.float64)
    tgt = np.ascontiguousarray(tgt, dtype=np.float64)
    # both return a dict (tgt_from_src, num_inliers, inlier_mask) or None, despite their docstrings
    res: Any = (
        pycolmap.estimate_rigid3d_robust(src, tgt, opts)
        if fix_scale
        else pycolmap.estimate_sim3d_robust(src, tgt, opts)
    )
    if res is None:
        return None
    M = np.asarray(res["tgt_from_src"].matrix())
    if fix_scale:
        sim = Sim3(M[:3, :3], M[:3, 3], 1.0)
    else:
        sim = Sim3.from_matrix(np.vstack([M[:3, :4], [0, 0, 0, 1]]))
    return sim, np.asarray(res["inlier_mask"]).astype(bool)


@dataclass
class _Obs:
    """Observations for the bidirectional reprojection refinement (paper 2.5.1).

    Direction A: candidate point ``Xc`` -> query map (S^-1) -> query keyframe camera, vs ``uv_q``.
    Direction B (where the query keypoint has a map point): query point ``Xq`` -> candidate map (S) ->
    candidate keyframe camera ``cam_b``, vs ``uv_b``.
    """

    xc: F64  # (N, 3) candidate-map points
    uv_q: F64  # (N, 2)
    sig_q: F64  # (N,)
    xq: F64  # (N, 3) query-map points (nan where none)
    uv_b: F64  # (N, 2)
    sig_b: F64  # (N,)
    has_b: NDArray[np.bool_]  # (N,) direction B available
    groups_b: list[tuple[I64, Any, F64]]  # (indices, camera, cam_from_world) per candidate keyframe
    sig3: F64 | None = None  # (N,) sigma of the optional 3D term (``S Xq - Xc``), None = off

    def subset(self, idx: I64) -> _Obs:
        pos = np.full(len(self.xc), -1, dtype=np.int64)
        pos[idx] = np.arange(len(idx))
        groups = []
        for g, cam, cfw in self.groups_b:
            gi = pos[g]
            gi = gi[gi >= 0]
            if len(gi):
                groups.append((gi, cam, cfw))
        return _Obs(
            self.xc[idx],
            self.uv_q[idx],
            self.sig_q[idx],
            self.xq[idx],
            self.uv_b[idx],
            self.sig_b[idx],
            self.has_b[idx],
            groups,
        )


def _project(camera: Any, cam_from_world: F64, pts: F64) -> tuple[F64, NDArray[np.bool_]]:
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv, valid = camera.project(pc)
    return uv, valid


def _residuals(
    sim: Sim3, obs: _Obs, q_camera: Any, q_cam_from_world: F64
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Whitened residuals (N, 2) of directions A and B (B zero where unavailable) and B availability."""
    inv = sim.inverse()
    uv_a, va = _project(q_camera, q_cam_from_world, inv.apply(obs.xc))
    ra = (uv_a - obs.uv_q) / obs.sig_q[:, None]
    ra[~va] = 1e3
    rb = np.zeros_like(ra)
    if obs.groups_b:
        xs = sim.apply(np.where(np.isfinite(obs.xq), obs.xq, 0.0))
        for idx, cam, cfw in obs.groups_b:
            uv_b, vb = _project(cam, cfw, xs[idx])
            r = (uv_b - obs.uv_b[idx]) / obs.sig_b[idx, None]
            r[~vb] = 1e3
            rb[idx] = r
    return ra, rb, obs.has_b


def _so3_left_jacobian(w: F64) -> F64:
    """J with ``exp(w + d) = exp(J d) exp(w)`` to first order."""
    th = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-6:
        return np.eye(3) + W / 2.0 + W @ W / 6.0
    return np.eye(3) + (1.0 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * (W @ W)


def _jacobians(
    sim: Sim3, d_rot: F64, fix_scale: bool, obs: _Obs, q_camera: Any, q_cam_from_world: F64
) -> tuple[F64, F64, F64]:
    """d residual / d parameters of :func:`_residuals` (N, 2, P) for directions A and B, and
    d ``S Xq`` / d parameters (N, 3, P); parameters: the rotation's (``d_rot``'s columns: the rotation
    of ``exp(d_rot @ r) R``), ``t``, then ``log s`` unless ``fix_scale``."""
    R, t, s = sim.R, sim.t, sim.s
    n, n_rot = len(obs.xc), d_rot.shape[1]
    n_par = n_rot + 3 + (0 if fix_scale else 1)
    # A: Xa = R^T (Xc - t) / s
    w = obs.xc - t
    xa = (w @ R) / s
    dxa = np.empty((n, 3, n_par))
    for k in range(n_rot):
        dxa[:, :, k] = (np.cross(w, d_rot[:, k]) @ R) / s
    dxa[:, :, n_rot : n_rot + 3] = -R.T / s
    if not fix_scale:
        dxa[:, :, -1] = -xa
    Rq = q_cam_from_world[:3, :3]
    ja = q_camera.project_jacobian(xa @ Rq.T + q_cam_from_world[:3, 3]) @ Rq @ dxa / obs.sig_q[:, None, None]
    # B: Y = s R Xq + t (the 3D term's too)
    rx = np.where(np.isfinite(obs.xq), obs.xq, 0.0) @ R.T
    dy = np.empty((n, 3, n_par))
    for k in range(n_rot):
        dy[:, :, k] = s * np.cross(d_rot[:, k], rx)
    dy[:, :, n_rot : n_rot + 3] = np.eye(3)
    if not fix_scale:
        dy[:, :, -1] = s * rx
    jb = np.zeros((n, 2, n_par))
    y = s * rx + t
    for idx, cam, cfw in obs.groups_b:
        Rc = cfw[:3, :3]
        jb[idx] = cam.project_jacobian(y[idx] @ Rc.T + cfw[:3, 3]) @ Rc @ dy[idx] / obs.sig_b[idx, None, None]
    return ja, jb, dy


def refine_sim3(
    sim0: Sim3,
    obs: _Obs,
    q_camera: Any,
    q_cam_from_world: F64,
    fix_scale: bool,
    huber: float = 2.45,
    max_nfev: int = 50,
    yaw_axis: F64 | None = None,
) -> Sim3:
    """Minimise the bidirectional reprojection error over ``[rotvec, t, log s]`` (Huber loss).

    With ``obs.sig3`` set, a weak 3D term ``(S Xq - Xc) / sigma`` is added: when the query and the
    candidate keyframes see the place from (almost) the same viewpoint, a similarity centred on the
    camera is invisible in the reprojections, and only the maps' 3D structure fixes the scale.
    ``yaw_axis`` (unit up direction in the candidate map's frame): only the rotation about it is refined
    (``sim0``'s roll/pitch kept: a levelled loop, see BackendOptions.level_reprojection).
    """
    n_rot = 3 if yaw_axis is None else 1
    n_par = n_rot + 3 + (0 if fix_scale else 1)
    axis = None if yaw_axis is None else np.asarray(yaw_axis, dtype=np.float64) / np.linalg.norm(yaw_axis)

    def make(x: F64) -> Sim3:
        R = (so3_exp(x[:3]) if axis is None else so3_exp(axis * x[0])) @ sim0.R
        s = sim0.s if fix_scale else sim0.s * float(np.exp(x[n_rot + 3]))
        return Sim3(R, sim0.t + x[n_rot : n_rot + 3], s)

    use3 = obs.sig3 is not None and bool(obs.has_b.any())
    if use3:
        assert obs.sig3 is not None
        i3 = np.flatnonzero(obs.has_b)
        xq3, xc3, s3 = obs.xq[i3], obs.xc[i3], obs.sig3[i3, None]

    def fun(x: F64) -> F64:
        sim = make(x)
        ra, rb, _ = _residuals(sim, obs, q_camera, q_cam_from_world)
        parts = [ra.ravel(), rb.ravel()]
        if use3:
            parts.append(((sim.apply(xq3) - xc3) / s3).ravel())
        return np.concatenate(parts)

    def jac(x: F64) -> F64:
        # the rotation's columns: a left perturbation of exp(x) (its left Jacobian), or the yaw axis
        d_rot = _so3_left_jacobian(x[:3]) if axis is None else axis[:, None]
        ja, jb, dy = _jacobians(make(x), d_rot, fix_scale, obs, q_camera, q_cam_from_world)
        parts = [ja.reshape(-1, n_par), jb.reshape(-1, n_par)]
        if use3:
            parts.append((dy[i3] / s3[:, :, None]).reshape(-1, n_par))
        return np.concatenate(parts)

    # translation steps are scaled to the scene (x_scale), as the rotation's and the scale's are
    depth = float(np.median(np.linalg.norm(obs.xc - np.median(obs.xc, axis=0), axis=1))) + 1e-9
    x_scale = np.array([0.01] * n_rot + [0.01 * depth] * 3 + ([0.01] if not fix_scale else []))
    res = least_squares(
        fun, np.zeros(n_par), jac=jac, loss="huber", f_scale=huber, x_scale=x_scale, max_nfev=max_nfev,
        method="trf",
    )  # fmt: skip
    return make(res.x)


def correction_of(sim: Sim3, world_from_cam: Any) -> tuple[float, float]:
    """How far (m) and how much (deg) the similarity ``sim`` moves and turns a camera pose."""
    c = np.asarray(world_from_cam, dtype=np.float64)[:3, 3]
    return float(np.linalg.norm(sim.apply(c) - c)), rotation_angle_deg(sim.R)


def pair_observations(
    mq: Any,
    mc: Any,
    query_key: KfKey,
    candidate_key: KfKey,
    query_points: Sequence[PointKey],
    candidate_points: Sequence[PointKey],
    n_covisible: int = 5,
) -> _Obs:
    """The reprojection observations of a detection's point pairs (``query_points[i]`` is
    ``candidate_points[i]``): the query keyframe's keypoints of its paired points, and those points'
    keypoints in the candidate keyframe and its ``n_covisible`` best covisible keyframes."""
    q = mq.keyframes[query_key]
    q_pk = _point_keys(q)
    index: dict[PointKey, int] = {}
    for i, k in enumerate(q_pk):
        if k is not None:
            index.setdefault(mq.resolve_point(k), i)
    pairs: dict[int, PointKey] = {}
    for kq, kc in zip(query_points, candidate_points, strict=True):
        iq, pc = index.get(mq.resolve_point(kq)), mc.resolve_point(kc)
        if iq is not None and pc in mc.points:
            pairs.setdefault(iq, pc)
    keys = [candidate_key, *_best_covisible(mc, candidate_key, n_covisible)]
    window = [mc.keyframes[k] for k in dict.fromkeys(keys) if k in mc.keyframes]
    return _observations(pairs, q, q_pk, mq, mc, window)


def _best_covisible(m: Any, key: KfKey, n: int) -> list[KfKey]:
    out = m.best_covisible(key, n)
    res: list[KfKey] = []
    for item in out:
        if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], tuple):
            res.append(item[0])  # (key, weight)
        elif isinstance(item, tuple):
            res.append(item)  # type: ignore[arg-type]
        else:
            res.append(item.key)
    return res


def _point_keys(kf: Any) -> list[PointKey | None]:
    """``kf.point_keys`` from the keyframe's id array in one pass (a verification reads it for the
    query and every window keyframe; the per-keypoint property call was a third of its time)."""
    agent = kf.agent_id
    ids = kf.point_ids.tolist()
    out: list[PointKey | None] = [None if p < 0 else (agent, p) for p in ids]
    for i, a in kf.point_agents.items():  # points of other agents (fused after a merge)
        if ids[i] >= 0:
            out[i] = (a, ids[i])
    return out


def _has_point(pk: Sequence[PointKey | None], points: Any) -> NDArray[np.bool_]:
    """Per keypoint: does it reference a point that is (still) in ``points``."""
    return np.array([k is not None and k in points for k in pk], dtype=bool).reshape(len(pk))


@dataclass
class PointSet:
    """Map points read once for a verification: keys, positions, descriptors and key -> row."""

    keys: list[PointKey]
    xyz: F64  # (N, 3)
    desc: NDArray[np.uint8]  # (N, 32)
    index: dict[PointKey, int]

    @staticmethod
    def of(m: Any, keys: list[PointKey]) -> PointSet:
        pts = [m.points[k] for k in keys]
        xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        desc = np.array([p.descriptor for p in pts], dtype=np.uint8).reshape(-1, 32)
        return PointSet(keys, xyz, desc, {k: i for i, k in enumerate(keys)})


def guided_search(
    o: PlaceRecOptions,
    q: Any,
    q_cfw: F64,
    q_pk: Sequence[PointKey | None],
    c: Any,
    c_cfw: F64,
    c_pk: Sequence[PointKey | None],
    c_has: NDArray[np.bool_],
    cand: PointSet,
    qpts: PointSet,
    sim: Sim3,
    pairs: dict[int, PointKey],
) -> dict[int, PointKey]:
    """Add matches by projection both ways; returns query keypoint -> candidate point.

    ``cand``: the candidate window's points; ``qpts``: the query keyframe's points; ``c_pk`` / ``c_has``:
    the candidate keyframe's point keys and which of them are in its map."""
    out = dict(pairs)
    used = np.zeros(len(cand.keys), dtype=bool)
    for v in out.values():
        i = cand.index.get(v)
        if i is not None:
            used[i] = True
    # A: candidate-window points -> query keyframe
    free = np.flatnonzero(~used)
    if len(free):
        uv, valid = _project(q.camera, q_cfw, sim.inverse().apply(cand.xyz[free]))
        valid &= q.camera.in_image(uv)
        vi = free[valid]
        mask = np.ones(len(q.keypoints), dtype=bool)
        mask[list(out.keys())] = False
        m = match_projected(
            uv[valid], cand.desc[vi], q.keypoints, q.octaves, q.descriptors,
            o.search_radius_px, o.search_max_distance, mask,
        )  # fmt: skip
        for pi, kq in m.tolist():
            out[int(kq)] = cand.keys[vi[pi]]
    # B: query points -> candidate keyframe
    used_q = {q_pk[i] for i in out if q_pk[i] is not None}
    free_q = np.array([i for i, k in enumerate(qpts.keys) if k not in used_q], dtype=np.int64)
    if len(free_q):
        uv, valid = _project(c.camera, c_cfw, sim.apply(qpts.xyz[free_q]))
        valid &= c.camera.in_image(uv)
        vi = free_q[valid]
        used_c = set(out.values())
        cmask = c_has & np.fromiter((k not in used_c for k in c_pk), dtype=bool, count=len(c_pk))
        m = match_projected(
            uv[valid], qpts.desc[vi], c.keypoints, c.octaves, c.descriptors,
            o.search_radius_px, o.search_max_distance, cmask,
        )  # fmt: skip
        q_index = {k: i for i, k in enumerate(q_pk) if k is not None}
        for pi, kc in m.tolist():
            iq = q_index[qpts.keys[vi[pi]]]
            pc = c_pk[kc]
            if iq not in out and pc is not None:
                out[iq] = pc
    return out


def _observations(
    pairs: dict[int, PointKey],
    q: Any,
    q_pk: Sequence[PointKey | None],
    mq: Any,
    mc: Any,
    window_kfs: list[Any],
) -> _Obs:
    n = len(pairs)
    iqs = np.fromiter(pairs.keys(), dtype=np.int64, count=n)
    mps = [mc.points[pc] for pc in pairs.values()]
    xc = np.array([mp.xyz for mp in mps], dtype=np.float64).reshape(n, 3)
    uv_q = np.asarray(q.keypoints, dtype=np.float64)[iqs].reshape(n, 2)
    sig_q = 1.2 ** np.asarray(q.octaves, dtype=np.float64)[iqs]
    xq = np.full((n, 3), np.nan)
    uv_b = np.zeros((n, 2))
    sig_b = np.ones(n)
    # direction B: the candidate point's keypoint in the first window keyframe (candidate first) observing it
    by_kf: dict[KfKey, list[int]] = {w.key: [] for w in window_kfs}
    kp_of: dict[KfKey, list[int]] = {w.key: [] for w in window_kfs}
    q_points = mq.points
    for i, (iq, mp) in enumerate(zip(iqs.tolist(), mps, strict=True)):
        qk = q_pk[iq]
        if qk is None or qk not in q_points:
            continue
        for wk, idx in mp.observations.items():
            rows = by_kf.get(wk)
            if rows is not None:
                xq[i] = q_points[qk].xyz
                rows.append(i)
                kp_of[wk].append(idx)
                break
    groups: list[tuple[I64, Any, F64]] = []
    has_b = np.zeros(n, dtype=bool)
    for w in window_kfs:
        rows = by_kf[w.key]
        if not rows:
            continue
        ri, ki = np.asarray(rows, dtype=np.int64), np.asarray(kp_of[w.key], dtype=np.int64)
        uv_b[ri] = np.asarray(w.keypoints, dtype=np.float64)[ki]
        sig_b[ri] = 1.2 ** np.asarray(w.octaves, dtype=np.float64)[ki]
        has_b[ri] = True
        groups.append((ri, w.camera, se3_inverse(np.asarray(w.world_from_cam, dtype=np.float64))))
    return _Obs(xc, uv_q, sig_q, xq, uv_b, sig_b, has_b, groups)
