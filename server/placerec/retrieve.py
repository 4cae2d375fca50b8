"""Which keyframes a query verifies: BoW retrieval, then candidates grouped by covisibility.

A look-up retrieves the ``retrieve_max`` best keyframes by BoW score (loops: only those scoring above
the query's worst covisible neighbour, as ORB-SLAM), a number that does not grow with the team: with
``4 x agents`` (the paper's) a query's cost grew with the team and the server's with its square.
Neighbouring keyframes of one place come back together, and verifying each of them repeats the same
work on overlapping windows. As ORB-SLAM2 does (``KeyFrameDatabase::DetectLoopCandidates``), each
retrieved keyframe forms a group with its best covisible keyframes; the group scores the sum of its
members' BoW scores and is represented by its best-scoring member; groups with the same representative
are one, and groups scoring below a fraction of the best group are not verified, nor any beyond the
``max_groups`` best (ORB-SLAM3's ``DetectNBestCandidates`` keeps 3). The representative's window (it
and its best covisible keyframes) is what the verification matches against, so the place is still
covered.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.kfdb import KeyframeDatabase

KfKey = tuple[str, int]


@dataclass(frozen=True)
class Group:
    """One covisibility group of candidates: its representative, that keyframe's score, the group's."""

    key: KfKey
    score: float
    group_score: float
    members: int


def group_candidates(
    kfdb: KeyframeDatabase,
    maps: Mapping[int, Any],
    candidates: list[tuple[KfKey, float]],
    scores: NDArray[np.float64],
    n_covisible: int,
    min_ratio: float,
    allowed: Callable[[KfKey], bool] = lambda k: True,
    max_groups: int = 0,
) -> list[Group]:
    """Groups of ``candidates`` (key, BoW score), best group first, at most ``max_groups`` (0: all);
    ``scores``: the query's score against every slot (:meth:`KeyframeDatabase.scores`); ``allowed``: may
    a keyframe join a group (loops: not the query's covisible keyframes)."""
    best: dict[KfKey, Group] = {}
    for key, _ in candidates:
        if key not in kfdb:
            continue
        m = maps.get(kfdb.map_of(key))
        neigh = m.best_covisible(key, n_covisible) if m is not None and key in m.keyframes else []
        members = [key] + [k for k in neigh if k != key and k in kfdb and allowed(k)]
        s = kfdb.scores_of(members, scores)
        i = int(np.argmax(s))
        g = Group(members[i], float(s[i]), float(s[s > 0].sum()), len(members))
        prev = best.get(g.key)
        if prev is None or g.group_score > prev.group_score:
            best[g.key] = g
    if not best:
        return []
    top = max(g.group_score for g in best.values())
    kept = [g for g in best.values() if g.group_score >= min_ratio * top]
    kept.sort(key=lambda g: (-g.group_score, -g.score, g.key))
    return kept[:max_groups] if max_groups > 0 else kept
