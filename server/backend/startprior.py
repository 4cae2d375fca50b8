"""The nominal start configuration as a prior for merges (paper 2.4: the UAVs take off from the UGV's roof).

``[start_poses]`` gives each agent's cam0 start pose in a common frame, known to ``sigma_m`` / ``sigma_deg``
per axis. It never merges maps by itself: a place-recognition merge between two agents' maps is checked
against it. One that agrees within :data:`GATE_SIGMAS` of the two mountings' combined uncertainty is
taken at once (the prior stands in for the consecutive confirmations); one that contradicts it needs
the confirmations as any other, and then overrides it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from hivemap.maps.geometry import Sim3, rotation_angle_deg
from hivemap.server.backend.fit import fit_pairs
from hivemap.server.backend.surgery import common_from_map
from hivemap.server.placerec import Detection

F64 = NDArray[np.float64]
KfKey = tuple[str, int]

# A measurement agrees with the prior within this many per-axis sigmas of the difference of two
# independent mountings. Position and rotation differences are 3-D norms, so the gate is the 99 % point of
# a chi distribution with 3 degrees of freedom (3 sigmas of a 3-D norm flag 3 % of correct mountings).
GATE_SIGMAS = math.sqrt(float(chi2.ppf(0.99, 3)))


@dataclass(frozen=True)
class PriorCheck:
    """How a merge measurement compares with the prior, at the query keyframe's camera."""

    diff_m: float
    diff_deg: float
    gate_m: float
    gate_deg: float

    @property
    def agrees(self) -> bool:
        return self.diff_m <= self.gate_m and self.diff_deg <= self.gate_deg

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "agrees": self.agrees}


class StartPrior:
    """Per agent with a nominal start pose: its map's ``common_from_map`` once its first keyframe
    arrived, valid while that map keeps its frame (``generation``: the back-end's per-map frame counter,
    read live)."""

    def __init__(
        self, poses: dict[str, F64], sigma_m: float, sigma_deg: float, generation: dict[int, int]
    ) -> None:
        self.poses = poses
        self.sigma_m, self.sigma_deg = sigma_m, sigma_deg
        self._generation = generation
        self._frames: dict[str, tuple[int, int, Sim3]] = {}  # agent -> (map, generation, common_from_map)

    @staticmethod
    def from_settings(starts: Any, generation: dict[int, int]) -> StartPrior:
        """From the server's ``start_poses`` settings (None: no agent has a start pose)."""
        poses = {
            a: np.asarray(T, dtype=np.float64).reshape(4, 4) for a, T in getattr(starts, "poses", {}).items()
        }
        return StartPrior(
            poses, getattr(starts, "sigma_m", 0.2), getattr(starts, "sigma_deg", 5.0), generation
        )

    def wants(self, folded: str) -> bool:
        """The agent has a nominal start pose and its first keyframe was not recorded yet."""
        return folded in self.poses and folded not in self._frames

    def record(self, folded: str, map_id: int, first_world_from_cam: F64) -> None:
        c = common_from_map(self.poses[folded], first_world_from_cam)
        self._frames[folded] = (map_id, self._generation.get(map_id, 0), c)

    def merged(self, target: int, source: int, target_from_source: Sim3) -> None:
        """Maps ``source`` went into ``target`` (whose frame counter the merge has just bumped)."""
        gen = self._generation.get(target, 0)
        source_from_target = target_from_source.inverse()
        for a, (mid, g, c) in list(self._frames.items()):
            if mid == source and g == self._generation.get(source, g):
                self._frames[a] = (target, gen, c @ source_from_target)
            elif mid == target and g == gen - 1:
                self._frames[a] = (target, gen, c)

    def split(self, map_id: int, new_id: int, agents: set[str], target_from_source: Sim3) -> None:
        """A merge was undone: ``agents`` left map ``map_id`` for ``new_id``, moved back by the inverse of
        ``target_from_source`` (both maps' frame counters have just been bumped)."""
        for a, (mid, g, c) in list(self._frames.items()):
            if mid == map_id and g == self._generation.get(map_id, 0) - 1:
                to = new_id if a in agents else map_id
                self._frames[a] = (
                    to,
                    self._generation.get(to, 0),
                    c @ target_from_source if a in agents else c,
                )

    def common_from(self, map_id: int, prefer: str) -> tuple[str, Sim3] | None:
        """(agent, ``common_from_map``) of map ``map_id`` from its agent ``prefer`` if it has a valid one,
        else from another agent of that map."""
        gen = self._generation.get(map_id, 0)
        valid = {a: c for a, (mid, g, c) in self._frames.items() if mid == map_id and g == gen}
        if prefer in valid:
            return prefer, valid[prefer]
        return next(iter(sorted(valid.items())), None)

    def check(self, det: Detection, maps: Any, min_inlier_ratio: float, fix_scale: bool) -> PriorCheck | None:
        """The merge detection against the prior; None if either map has no valid prior or the
        detection's point pairs do not fit one transform."""
        if det.is_loop:
            return None
        q = self.common_from(det.query_map, det.query_key[0])
        c = self.common_from(det.candidate_map, det.candidate_key[0])
        mq, mc = maps.get(det.query_map), maps.get(det.candidate_map)
        if q is None or c is None or mq is None or mc is None or det.query_key not in mq.keyframes:
            return None
        pairs = list(zip(det.candidate_points, det.query_points, strict=True))
        meas, _, _, _ = fit_pairs(mc, mq, pairs, min_inlier_ratio, with_scale=not fix_scale)
        if meas is None:
            return None
        pred = c[1].inverse() @ q[1]  # candidate map from query map, by the two nominal start poses
        p = np.asarray(mq.keyframes[det.query_key].world_from_cam, dtype=np.float64)[:3, 3]
        diff_m = float(np.linalg.norm(pred.apply(p) - meas.apply(p)))
        diff_deg = rotation_angle_deg(meas.R @ pred.R.T)
        # an orientation error turns the query camera about its agent's start: its lever arm counts
        start_q = q[1].inverse().apply(self.poses[q[0]][:3, 3])
        lever = float(np.linalg.norm(p - start_q))
        sig_rad = math.radians(self.sigma_deg)
        gate_m = GATE_SIGMAS * math.sqrt(2.0 * (self.sigma_m**2 + (lever * sig_rad) ** 2))
        gate_deg = GATE_SIGMAS * math.sqrt(2.0) * self.sigma_deg
        return PriorCheck(diff_m, diff_deg, gate_m, gate_deg)
