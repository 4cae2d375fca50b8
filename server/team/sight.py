"""A map's lines of sight for the frontier extraction (:mod:`.frontiers`): from each keyframe's camera to
a few of the points it observes, in the map's frame now.

Which points a keyframe observes is read once per keyframe and kept in its camera frame: the map's
corrections move a keyframe and its points together, so the camera-frame ends stay valid, and the
snapshot on the event loop is then one batched transform rather than a look-up per point.

The ground under a line of sight counts as seen (:func:`.frontiers.extract`); from a UAV's height that
includes a little ground just behind a building the line passes over, which the camera did not see.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
KfKey = tuple[str, int]


class SightLines:
    """Per keyframe, up to ``per_keyframe`` observed points (evenly over its keypoints with a point) in its
    camera frame; :meth:`rays` gives a map's lines of sight (R, 2, 3) in its frame."""

    def __init__(self, per_keyframe: int) -> None:
        self.per_keyframe = per_keyframe
        self._ends: dict[KfKey, F64] = {}  # camera-frame ends (K, 3), K <= per_keyframe

    def _of(self, m: Any, kf: Any) -> F64:
        idx = np.flatnonzero(np.asarray(kf.point_ids) >= 0)
        if len(idx) > self.per_keyframe:
            idx = idx[np.linspace(0, len(idx) - 1, self.per_keyframe).astype(np.int64)]
        xyz = []
        for i in idx:
            p = m.points.get((kf.point_agents.get(int(i), kf.agent_id), int(kf.point_ids[i])))
            if p is not None:
                xyz.append(p.xyz)
        if not xyz:
            return np.zeros((0, 3))
        T = np.asarray(kf.world_from_cam, dtype=np.float64)
        out: F64 = (np.asarray(xyz, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
        return out

    def rays(self, m: Any) -> F64:
        """Map ``m``'s lines of sight (R, 2, 3): [camera centre, observed point], map frame (on the event
        loop: the map may change afterwards)."""
        if self.per_keyframe <= 0 or not m.keyframes:
            return np.zeros((0, 2, 3))
        poses, ends_all, counts = [], [], []
        for key, kf in m.keyframes.items():
            ends = self._ends.get(key)
            if ends is None or not len(ends):  # (none yet: its points may arrive after it)
                ends = self._ends[key] = self._of(m, kf)
            if len(ends):
                poses.append(kf.world_from_cam)
                ends_all.append(ends)
                counts.append(len(ends))
        if not poses:
            return np.zeros((0, 2, 3))
        T = np.asarray(poses, dtype=np.float64)[np.repeat(np.arange(len(poses)), counts)]
        out = np.empty((len(T), 2, 3))
        out[:, 0] = T[:, :3, 3]
        out[:, 1] = np.einsum("nij,nj->ni", T[:, :3, :3], np.concatenate(ends_all)) + T[:, :3, 3]
        return out

    def prune(self, maps: Any) -> None:
        """Drop the kept ends of keyframes no longer in any of ``maps`` (id -> map), once they are as many as
        the keyframes there (a merge, an undo or a mission's end leaves them)."""
        n = sum(len(m.keyframes) for m in maps.values())
        if len(self._ends) > 2 * n:
            live = {k for m in maps.values() for k in m.keyframes}
            self._ends = {k: v for k, v in self._ends.items() if k in live}
