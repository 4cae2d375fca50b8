"""A new front-end session merged back by its agent's guess (issue 28, recovery instead of loss).

When tracking stays lost beyond the IMU hold, the agent starts a new session whose first keyframe carries
``prev_session_from_world``: the new VIO frame in the previous session's, from the IMU propagation that
bridged the loss, with its sigmas. ORB-SLAM3 starts a new Atlas map there and waits for place recognition
to merge it; a session that never looks back at the old map's places stays apart. Here the guess puts the
new session into its previous session's map at once, as a merge on trial held by one loose edge (the
previous session's last keyframe to the new session's first, with the guess's sigmas): the agent is in the
shared frame from its first new keyframe, its return to mapped ground is a loop (found inside one map)
that confirms and corrects the guess, and the robust pose graph can reject the edge and undo the merge if
the loops contradict it.

Pure planning here; :class:`~.scheduler.Backend` applies it on the event loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, se3_inverse
from hivemap.server.backend.optimise import NewEdge
from hivemap.server.backend.surgery import target_of

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

BY = "session_guess"  # the merge records' and events' ``by``


@dataclass(frozen=True)
class GuessMerge:
    """What the guess asks for: map ``source`` into map ``target`` by ``target_from_source``, held by
    ``edge`` (candidate: the previous session's last keyframe, query: the new session's first)."""

    target: int
    source: int
    target_from_source: Sim3
    edge: NewEdge
    candidate_t: float
    query_t: float
    sigma_m: float
    sigma_deg: float


def previous_session(agent: Any, am: Any, stack: Any) -> Any | None:
    """The agent map of ``am``'s mission with the highest front-end session below ``am``'s that has
    keyframes on the server (a session that never made one was bridged in the same VIO frame)."""
    earlier = [
        a for a in agent.maps.values() if a.mission == am.mission and a.client_session < am.client_session
    ]
    for a in sorted(earlier, key=lambda a: a.client_session, reverse=True):
        m = stack.map_of_agent(a.folded)
        if m is not None and any(k[0] == a.folded for k in m.keyframes):
            return a
    return None


def frame_at(map_pose: F64, vio_pose: F64, scale: float) -> Sim3:
    """The Sim(3) with scale ``scale`` taking the VIO pose ``vio_pose`` of a keyframe to its map pose
    ``map_pose``: the agent's VIO frame in the map as the back-end's corrections left it there."""
    R = map_pose[:3, :3] @ vio_pose[:3, :3].T
    return Sim3(R, map_pose[:3, 3] - scale * (R @ vio_pose[:3, 3]), scale)


def plan(
    stack: Any,
    prev: Any,
    new: Any,
    first: KfKey,
    prev_from_new: F64,
    sigma: F64,
    agent_kind: Any,
) -> GuessMerge | str:
    """The merge the guess asks for, or why there is none. ``prev``/``new``: the two sessions' agent
    maps; ``first``: the new session's keyframe with the guess ``prev_from_new`` (VIO frames, 4x4) and
    ``sigma`` [m, deg]. If the previous session's map has merged into another, the guess goes through
    that map's frame: the previous session's VIO frame is taken where its last keyframe now is."""
    mp, mn = stack.map_of_agent(prev.folded), stack.map_of_agent(new.folded)
    if mp is None or mn is None or first not in mn.keyframes:
        return "a session's map is gone"
    if mp.id == mn.id:
        return "both sessions are in one map already"
    own = [k for k in mp.keyframes if k[0] == prev.folded]
    last = max(own, key=lambda k: (mp.keyframes[k].timestamp, k[1]))
    Mp = np.asarray(mp.keyframes[last].world_from_cam, dtype=np.float64)
    Mn = np.asarray(mn.keyframes[first].world_from_cam, dtype=np.float64)
    Vp = mp.keyframes[last].vio_from_cam
    Vn = mn.keyframes[first].vio_from_cam
    # without the VIO poses (a store from before they were kept): the sessions' transforms alone
    map_from_prev = prev.global_from_vio if Vp is None else frame_at(Mp, Vp, prev.global_from_vio.s)
    map_from_new = new.global_from_vio if Vn is None else frame_at(Mn, Vn, new.global_from_vio.s)
    mp_from_mn = (
        map_from_prev @ Sim3.from_se3(np.asarray(prev_from_new, dtype=np.float64)) @ map_from_new.inverse()
    )
    sigma_m = float(sigma[0]) * map_from_prev.s
    sigma_deg = float(sigma[1])
    # the edge: the new session's start where the guess puts it, relative to where the old one ended
    predicted = mp_from_mn.transform_pose(Mn)
    measured = Sim3.from_se3(se3_inverse(Mp) @ predicted)
    edge = NewEdge(last, first, measured, math.radians(sigma_deg), sigma_m)
    target = target_of(stack.maps, mp.id, mn.id, agent_kind)
    sim = mp_from_mn if target == mp.id else mp_from_mn.inverse()
    source = mn.id if target == mp.id else mp.id
    return GuessMerge(target, source, sim, edge, float(mp.keyframes[last].timestamp),
                      float(mn.keyframes[first].timestamp), sigma_m, sigma_deg)  # fmt: skip


def record(g: GuessMerge, merge_ms: float) -> dict[str, Any]:
    """The merge record (``Backend.merges``, the ``merge_detail`` event), with the fields a visual merge's
    has that the experiment compares with ground truth (``candidate_from_query`` at query/candidate)."""
    return {
        "by": BY,
        "target": g.target,
        "source": g.source,
        "query": list(g.edge.query),
        "candidate": list(g.edge.candidate),
        "query_t": g.query_t,
        "candidate_t": g.candidate_t,
        "candidate_from_query": g.edge.measured.matrix().tolist(),
        "scale": g.target_from_source.s,
        "n_fused": 0,
        "n_inliers": 0,
        "merge_ms": merge_ms,
        "target_from_source": g.target_from_source.matrix().tolist(),
        "levelled": False,
        "sigma_rot_deg": g.sigma_deg,
        "sigma_trans_m": g.sigma_m,
    }


def is_guess(hyp: Any) -> bool:
    """Whether a merge hypothesis came from a session guess (no visual evidence of its own)."""
    return bool(hyp.record.get("by") == BY)


def loose_pairs(evidence: Any) -> tuple[tuple[frozenset[str], frozenset[str]], ...]:
    """The agent groups joined only by a session guess still on trial, over all maps."""
    return tuple(
        (h.source_agents, h.target_agents)
        for mid in list(evidence.merges)
        for h in evidence.on_trial(mid)
        if is_guess(h)
    )


def across(pairs: Any, a: KfKey, b: KfKey) -> bool:
    """Whether keyframes ``a`` and ``b`` lie on the two sides of one of ``pairs``."""
    return any((a[0] in s and b[0] in t) or (a[0] in t and b[0] in s) for s, t in pairs)
