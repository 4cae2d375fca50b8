"""Corrections: moving a map by per-keyframe corrections (on the event loop, with the keyframes that arrived
after the snapshot following their parent), re-framing its agents, and the ``correction`` messages that
tell each agent where the server now puts its keyframes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from itertools import compress, repeat
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.elements import first_observers, positions, set_positions
from hivemap.maps.geometry import Sim3, rotation_angles, sim3_arrays, transform_poses
from hivemap.protocol import Correction, encode
from hivemap.server.backend.fit import frame_correction
from hivemap.server.backend.options import CorrectionOptions

logger = logging.getLogger(__name__)

KfKey = tuple[str, int]
F64 = NDArray[np.float64]

# A correction whose log-scale exceeds this is "wild" (a failed solve) and none of the batch is applied.
MAX_ABS_LOG_SCALE = 1.0
# Keyframes are ranked for a correction by move (m) + this x turn (deg).
TURN_WEIGHT_M_PER_DEG = 0.05


def local_poses(server: Any, m: Any) -> dict[KfKey, F64]:
    """Each keyframe's pose in its agent's local (VIO) frame, as the agent sees it now."""
    by_agent: dict[str, list[KfKey]] = {}
    for k in m.keyframes:
        by_agent.setdefault(k[0], []).append(k)
    out: dict[KfKey, F64] = {}
    for folded, keys in by_agent.items():
        am = server._agent_map_by_folded(folded)
        g = (am.global_from_vio if am is not None else Sim3.identity()).inverse()
        W = np.array([m.keyframes[k].world_from_cam for k in keys], dtype=np.float64)
        n = len(keys)
        T = transform_poses(np.broadcast_to(g.R, (n, 3, 3)), np.broadcast_to(g.t, (n, 3)), np.full(n, g.s), W)
        out.update(zip(keys, T, strict=True))
    return out


def apply_corrections(
    server: Any,
    m: Any,
    corr: dict[KfKey, Sim3],
    new_xyz: dict[Any, F64],
    o: CorrectionOptions,
    fix_scale: bool,
) -> None:
    """On the loop: move keyframes by their correction; keyframes that are not in ``corr`` (arrived
    after the snapshot) by their nearest corrected ancestor's; points by ``new_xyz`` or by the correction
    of a keyframe observing them; agents' ``global_from_vio`` by their latest keyframe's correction."""
    bad = [
        k
        for k, c in corr.items()
        if not (np.isfinite(c.matrix()).all() and abs(np.log(c.s)) < MAX_ABS_LOG_SCALE)
    ]
    if bad:
        logger.error(
            "map %d: %d non-finite or wild corrections (e.g. %s) not applied", m.id, len(bad), bad[0]
        )
        server.events.add("error", f"map {m.id}: {len(bad)} wild corrections not applied", map_id=m.id)
        return
    full: dict[KfKey, Sim3] = dict(corr)

    def correction_of(k: KfKey) -> Sim3:
        chain: list[KfKey] = []
        cur: KfKey | None = k
        while cur is not None and cur not in full and len(chain) < 10000:
            chain.append(cur)
            cur = m.parent(cur) if cur in m.keyframes else None
        c = full.get(cur, Sim3.identity()) if cur is not None else Sim3.identity()
        for x in chain:
            full[x] = c
        return c

    keys = list(m.keyframes)
    for k in keys:
        correction_of(k)
    _move_keyframes(m, keys, [full[k] for k in keys])
    _move_points(m, full, new_xyz)
    for folded in list(m.agents):
        am = server._agent_map_by_folded(folded)
        recent = sorted((k for k in full if k[0] == folded and k in m.keyframes), key=lambda k: k[1])
        if am is None or not recent:
            continue
        recent = recent[-o.transform_window :]
        c = full[recent[-1]]
        if len(recent) >= 3:
            # the agent's frame follows the mean of its recent keyframes' corrections (one keyframe's
            # correction carries that keyframe's own noise)
            old = [full[k].inverse().apply(m.keyframes[k].world_from_cam[:3, 3]) for k in recent]
            centres = np.array(old)
            c = frame_correction([full[k] for k in recent], centres, with_scale=not fix_scale)
        server.set_agent_transform(folded, c @ am.global_from_vio)


def _move_keyframes(m: Any, keys: list[KfKey], sims: list[Sim3]) -> None:
    """``Sim3.transform_pose`` of every keyframe of ``keys`` by its similarity, batched."""
    if not keys:
        return
    W = np.array([m.keyframes[k].world_from_cam for k in keys], dtype=np.float64)
    for k, T in zip(keys, transform_poses(*sim3_arrays(sims), W), strict=True):
        m.keyframes[k].world_from_cam = T


def _move_points(m: Any, full: dict[KfKey, Sim3], new_xyz: dict[Any, F64]) -> None:
    """Points to ``new_xyz``, the others by their first observer's correction in ``full`` (those without
    a corrected observer stay), batched: a Python loop per point held the event loop on large maps."""
    mps = list(m.points.values())
    if new_xyz:
        for mp in mps:
            x = new_xyz.get(mp.key)
            if x is not None:
                mp.xyz = np.array(x, dtype=np.float64)
        mps = [mp for mp in mps if mp.key not in new_xyz]
    if not mps or not full:
        return
    index = {k: i for i, k in enumerate(full)}
    R, t, s = sim3_arrays(list(full.values()))
    slot = cast(Callable[[Any, int], int], index.get)
    idx = np.fromiter(map(slot, first_observers(mps), repeat(-1)), dtype=np.int64, count=len(mps))
    moved = idx >= 0
    if not moved.all():
        mps = list(compress(mps, moved.tolist()))
        idx = idx[moved]
    if not mps:
        return
    X = positions(mps)
    set_positions(mps, s[idx, None] * np.einsum("nij,nj->ni", R[idx], X) + t[idx])


def chosen_keyframes(
    m: Any, folded: str, before: dict[KfKey, F64], after: dict[KfKey, F64], o: CorrectionOptions, enu: bool
) -> list[KfKey]:
    """The keyframes of agent ``folded`` that a correction carries: the moved ones (largest first), and,
    whenever there are any or the map is in ENU, a whole snapshot of the server's estimate for the agent:
    every ``stride``-th keyframe (the agent replaces this session's co-location priors with it)."""
    keys = [k for k in after if k[0] == folded and k in before]
    moves = []
    if keys:
        T1 = np.array([after[k] for k in keys], dtype=np.float64)
        T0 = np.array([before[k] for k in keys], dtype=np.float64)
        dt = np.linalg.norm(T1[:, :3, 3] - T0[:, :3, 3], axis=1)
        dr = np.degrees(rotation_angles(T0[:, :3, :3], T1[:, :3, :3]))  # the turn of T1 T0^T
        for i in np.flatnonzero((dt >= o.min_move_m) | (dr >= o.min_rot_deg)).tolist():
            moves.append((float(dt[i]) + TURN_WEIGHT_M_PER_DEG * float(dr[i]), keys[i]))
    moves.sort(reverse=True)
    chosen = sorted(k for _, k in moves[: o.max_kfs])
    if chosen or enu:
        own = sorted(k for k in m.keyframes if k[0] == folded)
        sample = own[:: o.stride][-o.max_kfs :]
        in_sample = set(sample)
        extra = [k for k in chosen if k not in in_sample]
        chosen = sorted(set(sample) | set(extra[: max(0, o.max_kfs - len(sample))]))
    return chosen


async def send_corrections(
    server: Any,
    map_id: int,
    before: dict[KfKey, F64],
    t_det: float,
    o: CorrectionOptions,
    enu: bool,
    correction_bytes: dict[str, int],
    latencies: list[float],
    covariance_of: Callable[[str], Any] | None = None,
) -> None:
    """Send every agent of map ``map_id`` its correction (``before``: the local poses before the change,
    empty when no keyframe moved locally); counts bytes and latencies from ``t_det``. ``covariance_of``:
    an agent's latest keyframe's :class:`~.uncertainty.PoseCovariance` (or None), which its correction
    carries when it is of this map."""
    m = server.stack.maps.get(map_id)
    if m is None:
        return
    after = local_poses(server, m) if before else {}
    for folded in sorted(m.agents):
        am = server._agent_map_by_folded(folded)
        if am is None:
            continue
        chosen = chosen_keyframes(m, folded, before, after, o, enu)
        ids = np.array([k[1] for k in chosen], dtype=np.int64)
        poses = np.array([m.keyframes[k].world_from_cam for k in chosen], dtype=np.float64).reshape(-1, 4, 4)
        cov = covariance_of(folded) if covariance_of is not None else None
        if cov is not None and (cov.map_id != map_id or cov.key not in m.keyframes):
            cov = None
        corr = Correction(map_id=map_id, global_from_local=am.global_from_vio.matrix(), kf_ids=ids,
                          world_from_cam=poses, session=am.session,
                          global_frame="enu" if enu else "map",
                          pose_covariance=None if cov is None else cov.covariance,
                          covariance_kf_id=None if cov is None else cov.key[1])  # fmt: skip
        nbytes = len(encode(corr, 0))
        correction_bytes[am.agent_id] = correction_bytes.get(am.agent_id, 0) + nbytes
        try:
            await server.send_correction(am.agent_id, corr)
        except KeyError:
            continue
        latencies.append(time.monotonic() - t_det)
        server.events.add(
            "correction_detail",
            f"{folded}: {len(ids)} keyframes changed, {nbytes} bytes",
            agent_id=am.agent_id,
            map_id=map_id,
            data={"bytes": nbytes, "n_keyframes": len(ids), "total_bytes": correction_bytes[am.agent_id]},
        )
