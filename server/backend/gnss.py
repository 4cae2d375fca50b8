"""The server's GNSS stage around :func:`hivemap.server.gnss_stage.fuse_gnss`: its inputs from a map (fixes,
lever arms, the map's shape as its pose graph holds it, IMU up directions), whether its result is applied,
and the bend it gives the map (kept so the next optimisation can take it out and work on the visual
shape).

Pure functions; the scheduler runs the solve in its optimisation thread and applies the result.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, se3, se3_inverse
from hivemap.server.backend import optimise
from hivemap.server.backend.optimise import NewEdge, Snapshot
from hivemap.server.backend.options import GnssOptions, OptimiseOptions
from hivemap.server.gnss_stage import GnssFix, GnssStageResult, ShapeEdge

if TYPE_CHECKING:
    from hivemap.server.optim import PoseGraphEdge

KfKey = tuple[str, int]
F64 = NDArray[np.float64]


@dataclass
class StageInput:
    """What one GNSS stage solves over, copied out of the map on the event loop."""

    keys: list[KfKey]  # by agent, then time
    poses: F64  # (N, 4, 4) world_from_cam (visual: the last stage's bend already taken out)
    cam_from_ant: F64  # (N, 4, 4) each keyframe's lever arm
    world_from_ant: F64
    fixes: list[GnssFix]


def stage_input(
    m: Any,
    lever_of: Callable[[str], F64],
) -> StageInput | None:
    """The stage's input for map ``m`` (``lever_of``: an agent's cam_from_antenna); None with fewer than
    3 fixes."""
    keys = sorted(m.keyframes, key=lambda k: (k[0], m.keyframes[k].timestamp))
    fixes = []
    for i, k in enumerate(keys):
        kf = m.keyframes[k]
        if kf.gnss_enu is not None:
            cov = kf.gnss_cov if kf.gnss_cov is not None else np.eye(3)
            fixes.append(GnssFix(i, np.asarray(kf.gnss_enu), np.asarray(cov)))
    if len(fixes) < 3:
        return None
    poses = np.array([m.keyframes[k].world_from_cam for k in keys])
    levers = {a: lever_of(a) for a in {k[0] for k in keys}}
    cam_from_ant = np.array([se3(np.eye(3), levers[k[0]]) for k in keys])
    return StageInput(keys, poses, cam_from_ant, poses @ cam_from_ant, fixes)


def shape_edges(
    m: Any, snap: Snapshot, kept: list[NewEdge], o: OptimiseOptions, metric: bool
) -> list[PoseGraphEdge]:
    """The map's shape as its pose-graph step holds it: the edges of :func:`.optimise.pose_graph_problem`
    over the map's kept loop, merge and rendezvous edges ``kept`` (read from the map: the event loop's
    part; :func:`on_antennas` makes them the stage's factors)."""
    problem = optimise.pose_graph_problem(m, snap, kept, None, [], o, measured_only=o.gnc, metric=metric)
    return optimise.problem_edges(problem, snap.poses, o)


def on_antennas(edges: list[PoseGraphEdge], cam_from_ant: F64) -> list[ShapeEdge]:
    """The GNSS stage's factors of :func:`shape_edges`: each edge's covariance moved from the keyframes'
    cameras onto their antennas (``cam_from_ant``, per keyframe); robust edges are measurements, the
    others an agent's odometry."""
    import gtsam

    out = []
    for e in edges:
        # the antenna's perturbation is the camera's seen through the lever arm (j side of the Between)
        ad = gtsam.Pose3(se3_inverse(cam_from_ant[e.j])).AdjointMap()
        out.append(ShapeEdge(e.i, e.j, ad @ e.se3_covariance() @ ad.T, odometry=not e.robust))
    return out


def fuse(inp: StageInput, edges: list[PoseGraphEdge], **kwargs: Any) -> GnssStageResult:
    """:func:`hivemap.server.gnss_stage.fuse_gnss` of a stage input and its :func:`shape_edges` (in the
    optimisation thread; ``kwargs`` go to ``fuse_gnss``)."""
    from hivemap.server.gnss_stage import fuse_gnss

    return fuse_gnss(inp.world_from_ant, on_antennas(edges, inp.cam_from_ant), inp.fixes, **kwargs)


def antenna_fixes(
    m: Any, lever_of: Callable[[str], F64], agents: Collection[str] | None = None
) -> list[tuple[KfKey, F64, Any]]:
    """(key, antenna position in the map's frame, keyframe) of every keyframe of map ``m`` with a fix
    (of ``agents`` only, if given); ``lever_of``: an agent's cam_from_antenna."""
    out = []
    for k, kf in m.keyframes.items():
        if kf.gnss_enu is None or (agents is not None and k[0] not in agents):
            continue
        T = kf.world_from_cam
        out.append((k, T[:3, :3] @ np.asarray(lever_of(k[0]), dtype=np.float64) + T[:3, 3], kf))
    return out


def cv_due(n_fixes: int, n_at_last_cv: int, o: GnssOptions) -> bool:
    """Whether the GNSS stage's chain stiffness is cross-validated again (``cv_new_fixes`` more fixes
    and ``cv_growth`` more than at the last round): a round is 20 more solves."""
    return n_fixes >= max(n_at_last_cv + o.cv_new_fixes, n_at_last_cv * (1.0 + o.cv_growth))


def refusal(res: GnssStageResult, n_fixes: int, o: GnssOptions) -> str | None:
    """Why a stage result is not applied (most fixes must agree with the map: else a wrong loop or merge
    is the likelier cause than bad fixes), or None."""
    used = int(np.sum(res.used))
    med = float(np.median(res.residuals_m))
    if used < (1.0 - o.max_rejected_ratio) * n_fixes or med > o.max_median_residual_m:
        return (
            f"GNSS stage result refused ({used}/{n_fixes} fixes agree, median residual "
            f"{med:.2f} m): the map and the fixes disagree"
        )
    return None


def corrected_cameras(res: GnssStageResult, inp: StageInput) -> tuple[F64, dict[KfKey, Sim3]]:
    """The stage's new camera poses and each keyframe's correction to them."""
    new_cam = np.asarray(res.world_from_body) @ np.array([se3_inverse(T) for T in inp.cam_from_ant])
    corr = {
        k: Sim3.from_se3(new_cam[i]) @ Sim3.from_se3(inp.poses[i]).inverse() for i, k in enumerate(inp.keys)
    }
    return new_cam, corr


def unbend_of(res: GnssStageResult, inp: StageInput, new_cam: F64) -> dict[KfKey, Sim3]:
    """Per keyframe, what undoes the bend the stage gave it (visual = U @ bent): the bend alone, without
    the rigid move into ENU, so the unbent poses are in the map's new frame like the keyframes of agents
    that join the map later."""
    rigid = Sim3.from_se3(np.asarray(res.enu_from_map))
    return {
        k: rigid @ Sim3.from_se3(inp.poses[i]) @ Sim3.from_se3(new_cam[i]).inverse()
        for i, k in enumerate(inp.keys)
    }


def bend_corrections(m: Any, unbend: dict[KfKey, Sim3], invert: bool) -> dict[KfKey, Sim3]:
    """Per keyframe of ``m``, what undoes the GNSS stage's bend (``unbend``), or with ``invert`` what
    gives it again: each keyframe's own, or for a keyframe that came later its agent's latest
    keyframe's before it (new keyframes follow their agent's frame, which followed that correction)."""
    latest: dict[str, Sim3] = {}
    out: dict[KfKey, Sim3] = {}
    for k in sorted(m.keyframes, key=lambda k: (k[0], m.keyframes[k].timestamp, k[1])):
        u = unbend.get(k, latest.get(k[0]))
        if u is None:
            out[k] = Sim3.identity()
            continue
        latest[k[0]] = u
        out[k] = u.inverse() if invert else u
    return out


def retry_queries(m: Any, other: Any, o: GnssOptions) -> Iterator[tuple[KfKey, list[KfKey]]]:
    """GNSS-guided retry (paper 2.5.3): per agent of ``m``, its latest keyframe and the keyframes of
    ``other`` (both maps in ENU) within ``retry_radius_m`` of it, nearest first (lazily: each agent's
    latest keyframe is taken when the caller asks for it)."""
    okeys = list(other.keyframes)
    if not okeys:
        return
    opos = np.array([other.keyframes[k].world_from_cam[:3, 3] for k in okeys])
    for folded in sorted(m.agents):
        own = [k for k in m.keyframes if k[0] == folded]
        if not own:
            continue
        q = max(own, key=lambda k: (m.keyframes[k].timestamp, k[1]))
        d = np.linalg.norm(opos - m.keyframes[q].world_from_cam[:3, 3], axis=1)
        order = np.argsort(d)[: o.retry_candidates]
        near = [okeys[i] for i in order if d[i] <= o.retry_radius_m]
        if near:
            yield q, near
