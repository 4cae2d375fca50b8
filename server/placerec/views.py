"""What one place-recognition query reads of each keyframe, computed once per query.

A query verifies many candidates whose windows (candidate + best covisible keyframes) overlap, and
every verification reads the query keyframe again: their point keys, which of those points are still
in the map, and the windows' points were recomputed per candidate. The cache lives for one query only,
as the event loop changes the maps between queries.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.placerec.match import _has_point, _point_keys

KfKey = tuple[str, int]
PointKey = tuple[str, int]


class KeyframeViews:
    """Per keyframe of one query: point keys and "has a map point" masks."""

    def __init__(self) -> None:
        self._pk: dict[KfKey, list[PointKey | None]] = {}
        self._has: dict[KfKey, NDArray[np.bool_]] = {}

    def point_keys(self, kf: Any) -> list[PointKey | None]:
        pk = self._pk.get(kf.key)
        if pk is None:
            pk = self._pk[kf.key] = _point_keys(kf)
        return pk

    def has(self, m: Any, kf: Any) -> NDArray[np.bool_]:
        """Which keypoints of ``kf`` (a keyframe of map ``m``) reference a point of ``m``."""
        h = self._has.get(kf.key)
        if h is None:
            h = self._has[kf.key] = _has_point(self.point_keys(kf), m.points)
        return h

    def window_points(self, m: Any, window_kfs: list[Any]) -> list[PointKey]:
        """The points of map ``m`` the window's keyframes observe, each once, in window order."""
        seen: dict[PointKey, None] = {}
        for w in window_kfs:
            pk = self.point_keys(w)
            for i in np.flatnonzero(self.has(m, w)).tolist():
                seen.setdefault(pk[i], None)  # type: ignore[arg-type]
        return list(seen)
