"""One query's verification as a self-contained job: what it reads of the maps, as arrays.

A query's candidates are verified in a worker process (or a Ray task) while the event loop keeps
changing the maps, so the job cannot read the maps: it carries a slice of each map it touches, taken on
the place-recognition thread: the query keyframe, every candidate's window (the candidate and its best
covisible keyframes), the map points those keyframes reference (positions, descriptors, and their
observations in the slice's keyframes, in their keyframes' order of arrival) and the direct-index feature
vectors. On the worker the slices become small map-like objects the verification reads as it reads a
map. What differs: a point's observations come in its keyframes' order of arrival rather than its own
(they differ only for points fused after a merge or loop), which picks the keyframe of the refinement's
second direction.
"""

from __future__ import annotations

import copy
import operator
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.elements import Keyframe
from hivemap.maps.vocabulary import FeatureVector
from hivemap.server.placerec.types import PlaceRecOptions, Thresholds
from hivemap.server.placerec.views import HasCache

KfKey = tuple[str, int]
PointKey = tuple[str, int]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class Candidate:
    """One candidate to verify: its keyframe, map, kind, BoW score, scale mode and window."""

    key: KfKey
    map_id: int
    kind: str
    bow_score: float
    fix_scale: bool
    window: list[KfKey]  # the candidate's best covisible keyframes (without itself), best first
    # [m, deg] the correction limit grows by: what weak tracking between query and candidate may have added
    # (infinite across a loose edge, see ``loose_pairs``)
    correction_slack: tuple[float, float] = (0.0, 0.0)


@dataclass
class MapSlice:
    """The keyframes of one map a job reads and the points they reference, as arrays.

    Point ``i`` is ``(agents[agent_idx[i]], ids[i])``; its observations in the slice's keyframes are rows
    ``obs_point == i`` of ``obs_kf`` (index into ``keyframes``) and ``obs_kp`` (keypoint index), in the
    order its keyframes arrived in the map."""

    map_id: int
    keyframes: list[Keyframe]
    agents: list[str]
    agent_idx: NDArray[np.int32]
    ids: I64
    xyz: F64
    desc: NDArray[np.uint8]
    obs_point: NDArray[np.int32]
    obs_kf: NDArray[np.int32]
    obs_kp: NDArray[np.int32]
    # positions only: no descriptors (``desc`` empty), the observations in no particular order
    light: bool = False

    @property
    def nbytes(self) -> int:
        arrays: list[NDArray[Any]] = [
            self.agent_idx,
            self.ids,
            self.xyz,
            self.desc,
            self.obs_point,
            self.obs_kf,
            self.obs_kp,
        ]
        kfs = sum(k.keypoints.nbytes + k.descriptors.nbytes + k.point_ids.nbytes + k.octaves.nbytes
                  for k in self.keyframes)  # fmt: skip
        return int(sum(a.nbytes for a in arrays) + kfs)


@dataclass
class QueryJob:
    """What verifying one query's candidates needs (:func:`..verify.run_job` runs it)."""

    options: PlaceRecOptions
    thresholds: Thresholds
    query_key: KfKey
    query_map: int
    candidates: list[Candidate]
    slices: list[MapSlice]
    features: dict[KfKey, FeatureVector]
    best_covisible: dict[KfKey, list[KfKey]] = field(default_factory=dict)
    skip_covered: bool = True  # candidates inside an accepted candidate's window are not verified
    # 0: the full verification of every candidate; 1: phase 1 of a two-phase verification (light slices,
    # BoW matching and RANSAC only); 2: the full verification of phase 1's survivors (:mod:`.phases`)
    phase: int = 0

    @property
    def nbytes(self) -> int:
        fv = sum(f.node_of_feature.nbytes + f.word_of_feature.nbytes for f in self.features.values())
        return sum(s.nbytes for s in self.slices) + fv


# ------------------------------------------------------------------------------------------ building
_XYZ, _DESC, _OBS = (
    operator.attrgetter("xyz"),
    operator.attrgetter("descriptor"),
    operator.attrgetter("observations"),
)


def _copy_keyframe(kf: Keyframe) -> Keyframe:
    """A copy whose pose and point references the event loop cannot change while the job is shipped
    (features and camera are never changed in place: shared)."""
    c = copy.copy(kf)
    c.world_from_cam = kf.world_from_cam.copy()
    c.point_ids = kf.point_ids.copy()
    c.point_agents = dict(kf.point_agents)
    return c


def slice_of(
    m: Any, map_id: int, keys: Iterable[KfKey], has: HasCache | None = None, light: bool = False
) -> MapSlice:
    """The slice of map ``m`` (``map_id`` in the stack) holding keyframes ``keys`` (those still in it) and
    their points (``has``: which keypoints reference a point of the map, kept across queries). ``light``:
    the points' positions only, without descriptors, and the observations unordered (what phase 1 of a
    two-phase verification reads, :mod:`.phases`)."""
    has = has if has is not None else HasCache()
    kfs = [_copy_keyframe(m.keyframes[k]) for k in dict.fromkeys(keys) if k in m.keyframes]
    per_kf = [has.refs(m, kf) for kf in kfs]
    # the references of all keyframes end to end; each point once, in first-seen order, found by its code
    # (array work: a slice's keyframes hold ~10-20k references to ~2-5k points)
    kp_all = np.concatenate([r[0] for r in per_kf]) if per_kf else np.zeros(0, np.intp)
    codes = np.concatenate([r[1] for r in per_kf]) if per_kf else np.zeros(0, np.int64)
    kf_all = np.repeat(np.arange(len(kfs), dtype=np.int64), [len(r[0]) for r in per_kf])
    _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
    seen = np.argsort(first, kind="stable")
    names, agent_num, pid = has.decode(codes[first[seen]])
    cand = list(zip(map(names.__getitem__, agent_num.tolist()), pid.tolist(), strict=True))
    found = list(map(m.points.get, cand))
    if None in found:  # a point left the map without its keyframes' references being rewritten
        ok = np.fromiter((p is not None for p in found), bool, len(found))
        pts = [p for p in found if p is not None]
    else:
        ok = np.ones(len(found), bool)
        pts = found
    # the agents in order of their first point, each point's agent as an index into them
    anum = agent_num[ok]
    uniq, first_a, inv_a = np.unique(anum, return_index=True, return_inverse=True)
    order_a = np.argsort(first_a, kind="stable")
    rank_a = np.empty(len(uniq), np.int32)
    rank_a[order_a] = np.arange(len(uniq), dtype=np.int32)
    agents = [names[int(a)] for a in uniq[order_a]]
    agent_idx = rank_a[inv_a.reshape(-1)] if len(anum) else np.zeros(0, np.int32)
    ids = pid[ok]
    xyz = np.array(list(map(_XYZ, pts)), dtype=np.float64).reshape(-1, 3)
    # the observations in the slice's keyframes, from the keyframes' side (a point's full observation list
    # is ~8x larger), ordered per point as the map adds them: by its keyframes' order of arrival
    rank = np.empty(len(seen), np.int64)
    rank[seen] = np.arange(len(seen))
    row_by_seen = np.where(ok, np.cumsum(ok) - 1, -1)
    rows = row_by_seen[rank[inverse.reshape(-1)]] if len(codes) else np.zeros(0, np.int64)
    keep = rows >= 0
    obs_pt, obs_kf, obs_kp = rows[keep], kf_all[keep], kp_all[keep]
    if light:  # the references as they come (phase 1 reads them per keyframe, not per point)
        return MapSlice(map_id, kfs, agents, agent_idx, ids, xyz, np.zeros((0, 32), np.uint8),
                        obs_pt.astype(np.int32), obs_kf.astype(np.int32), obs_kp.astype(np.int32),
                        light=True)  # fmt: skip
    desc = np.array(list(map(_DESC, pts)), dtype=np.uint8).reshape(-1, 32)
    arrival = has.arrival(m)
    kf_arrival = np.array([arrival.get(kf.key, len(arrival)) for kf in kfs], dtype=np.int64)
    order = np.lexsort((kf_arrival[obs_kf] if len(obs_kf) else obs_kf, obs_pt))
    return MapSlice(
        map_id, kfs, list(agents), agent_idx, ids, xyz, desc, obs_pt[order].astype(np.int32),
        obs_kf[order].astype(np.int32), obs_kp[order].astype(np.int32),
    )  # fmt: skip


# ------------------------------------------------------------------------------------------ on the worker
class _Point:
    __slots__ = ("xyz", "descriptor", "observations")

    def __init__(self, xyz: F64, descriptor: NDArray[np.uint8] | None) -> None:
        self.xyz = xyz
        self.descriptor = descriptor
        self.observations: dict[KfKey, int] = {}


class SliceMap:
    """A map slice read as a map (``keyframes``, ``points``, ``best_covisible``) by the verification."""

    def __init__(self, s: MapSlice, best_covisible: dict[KfKey, list[KfKey]]) -> None:
        self.id = s.map_id
        self.keyframes: dict[KfKey, Keyframe] = {kf.key: kf for kf in s.keyframes}
        keys = [(s.agents[a], p) for a, p in zip(s.agent_idx.tolist(), s.ids.tolist(), strict=True)]
        pts = [_Point(s.xyz[i], None if s.light else s.desc[i]) for i in range(len(keys))]
        kf_keys = [kf.key for kf in s.keyframes]
        for i, j, kp in zip(s.obs_point.tolist(), s.obs_kf.tolist(), s.obs_kp.tolist(), strict=True):
            pts[i].observations[kf_keys[j]] = kp
        self.points: dict[PointKey, _Point] = dict(zip(keys, pts, strict=True))
        self._best = best_covisible

    def best_covisible(self, key: KfKey, n: int) -> list[KfKey]:
        return self._best.get(key, [])[: max(int(n), 0)]


def maps_of(job: QueryJob) -> dict[int, SliceMap]:
    return {s.map_id: SliceMap(s, job.best_covisible) for s in job.slices}
