"""How sure each agent's odometry is between two of its keyframes: the error that weak or lost tracking
added (``Keyframe.odom_sigma``, per keyframe relative to the agent's previous one) and the error its
tracking measured (``Keyframe.track_sigma``), each summed in quadrature along the agent's keyframes in
time, and the path travelled, so the pose graph's odometry edges weigh each agent by how well it tracked
and the loop gates can let a loop correct a tracking jump."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import rotation_angles

KfKey = tuple[str, int]
F64 = NDArray[np.float64]


class Chains:
    """Per agent (each session is an agent key), its keyframes in time with cumulative path length (m),
    rotation (rad) and weak-tracking variances [m^2, deg^2] up to each; ``poses``: world_from_cam per key
    (default: the map's)."""

    def __init__(self, m: Any, keys: Iterable[KfKey] | None = None, poses: dict[KfKey, F64] | None = None):
        by_agent: dict[str, list[KfKey]] = {}
        for k in m.keyframes if keys is None else keys:
            by_agent.setdefault(k[0], []).append(k)
        self.pos: dict[KfKey, tuple[str, int]] = {}
        self.order: dict[str, list[KfKey]] = by_agent
        # (n, 7): path m, rotation rad, weak var m^2, deg^2, tracked var m^2, deg^2, steps without tracked
        self.cum: dict[str, F64] = {}
        for agent, ks in by_agent.items():
            ks.sort(key=lambda k: (m.keyframes[k].timestamp, k[1]))
            # each step from the previous keyframe, all of an agent's at once (a map's optimisation builds
            # the chains twice, and one step at a time held the event loop)
            P = np.array([poses[k] if poses is not None else m.keyframes[k].world_from_cam for k in ks])
            steps = np.zeros((len(ks), 7))
            if len(ks) > 1:
                a, b = P[:-1], P[1:]
                steps[1:, 0] = np.linalg.norm(b[:, :3, 3] - a[:, :3, 3], axis=1)
                steps[1:, 1] = rotation_angles(a[:, :3, :3], b[:, :3, :3])
            for i in range(1, len(ks)):
                kf = m.keyframes[ks[i]]
                if kf.odom_sigma is not None:
                    steps[i, 2:4] = np.asarray(kf.odom_sigma, dtype=np.float64) ** 2
                if kf.track_sigma is not None:
                    steps[i, 4:6] = np.asarray(kf.track_sigma, dtype=np.float64) ** 2
                else:
                    steps[i, 6] = 1.0
            cum = np.cumsum(steps, axis=0)
            for i, k in enumerate(ks):
                self.pos[k] = (agent, i)
            self.cum[agent] = cum
        # every agent's rows stacked, for :meth:`between_many`
        self.row: dict[KfKey, int] = {}
        owners: list[NDArray[np.int64]] = []
        for n, agent in enumerate(self.cum):
            base = len(self.row)
            for i, k in enumerate(self.order[agent]):
                self.row[k] = base + i
            owners.append(np.full(len(self.order[agent]), n, dtype=np.int64))
        self._all = np.concatenate(list(self.cum.values())) if self.cum else np.zeros((0, 7))
        self._owner = np.concatenate(owners) if owners else np.zeros(0, np.int64)

    def between(self, a: KfKey, b: KfKey) -> F64 | None:
        """[path m, rotation rad, weak sigma m, weak sigma deg, tracked sigma m, tracked sigma deg, steps
        without a tracked sigma] between two keyframes of one agent, or None when they are of different
        agents (or unknown)."""
        pa, pb = self.pos.get(a), self.pos.get(b)
        if pa is None or pb is None or pa[0] != pb[0]:
            return None
        c = self.cum[pa[0]]
        d = np.abs(c[pb[1]] - c[pa[1]])
        d[2:6] = np.sqrt(d[2:6])
        return d

    def between_many(self, a: list[KfKey], b: list[KfKey]) -> tuple[F64, NDArray[np.bool_]]:
        """:meth:`between` of each pair ``(a[n], b[n])`` at once: (n, 7) rows, and whether each pair is of
        one agent (where not, its row is meaningless)."""
        ra = np.array([self.row.get(k, -1) for k in a], dtype=np.int64)
        rb = np.array([self.row.get(k, -1) for k in b], dtype=np.int64)
        if not len(self._all):
            return np.zeros((len(a), 7)), np.zeros(len(a), dtype=bool)
        ia, ib = np.maximum(ra, 0), np.maximum(rb, 0)
        same = (ra >= 0) & (rb >= 0) & (self._owner[ia] == self._owner[ib])
        d = np.abs(self._all[ib] - self._all[ia])
        d[:, 2:6] = np.sqrt(d[:, 2:6])
        return d, same

    def previous(self, k: KfKey) -> KfKey | None:
        """The agent's keyframe before ``k`` in time (None for its first, or an unknown key)."""
        p = self.pos.get(k)
        return None if p is None or p[1] == 0 else self.order[p[0]][p[1] - 1]

    def weak_total(self, agent: str) -> F64:
        """[m, deg]: the weak-tracking sigma over all of an agent's keyframes (zero if none)."""
        c = self.cum.get(agent)
        return np.zeros(2) if c is None or not len(c) else np.sqrt(c[-1, 2:4])


def weak_sigma_between(m: Any, a: KfKey, b: KfKey) -> F64:
    """[m, deg]: what weak or lost tracking may have put between keyframes ``a`` and ``b`` of ``m``: along
    the chain for one agent, each agent's whole chain for two (the map joins them elsewhere)."""
    ta, tb = m.keyframes[a].timestamp, m.keyframes[b].timestamp
    lo, hi = ((ta, a[1]), (tb, b[1])) if (ta, a[1]) <= (tb, b[1]) else ((tb, b[1]), (ta, a[1]))
    var = np.zeros(2)
    for k, kf in m.keyframes.items():
        if kf.odom_sigma is None or k[0] not in (a[0], b[0]):
            continue
        if a[0] != b[0] or lo < (kf.timestamp, k[1]) <= hi:
            var += np.asarray(kf.odom_sigma, dtype=np.float64) ** 2
    return np.sqrt(var)


# sqrt of the 99% chi-square quantile of 3 dof: a correction within this many weak sigmas is plausible
SLACK_SIGMAS = 3.37


def correction_slack(m: Any, query: KfKey, candidate: KfKey) -> tuple[float, float]:
    """[m, deg] a loop's fixed correction limits grow by: :data:`SLACK_SIGMAS` times what weak or lost
    tracking may have put between the two keyframes (zero when both agents tracked well), so a loop that
    would correct a tracking jump reaches the robust pose graph, which judges it."""
    if query not in m.keyframes or candidate not in m.keyframes:
        return 0.0, 0.0
    w = weak_sigma_between(m, query, candidate)
    return SLACK_SIGMAS * float(w[0]), SLACK_SIGMAS * float(w[1])
