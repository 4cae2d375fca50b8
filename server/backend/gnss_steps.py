"""The GNSS steps of the back-end's pipeline (paper 2.5.3): bending a map onto the agents' fixes, taking
that bend out before the visual optimisations, and the GNSS-guided place-recognition retry between two maps
in ENU. The solves are :mod:`.gnss` and :mod:`hivemap.server.gnss_stage`, run in the optimisation thread."""

from __future__ import annotations

import asyncio
import concurrent.futures
import time
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3
from hivemap.server.backend import detect, gnss, optimise
from hivemap.server.backend.evidence import EvidenceBook
from hivemap.server.backend.optimise import Snapshot
from hivemap.server.backend.options import BackendOptions
from hivemap.server.placerec import Detection, PlaceRecognizer

KfKey = tuple[str, int]
F64 = NDArray[np.float64]


class GnssSteps:
    """Mixed into :class:`~.pipeline.Pipeline`, which holds this state."""

    server: Any
    options: BackendOptions
    recognizer: PlaceRecognizer | None
    _generation: dict[int, int]
    _opt_exec: concurrent.futures.ThreadPoolExecutor
    _pr_exec: concurrent.futures.ThreadPoolExecutor
    _enu_maps: set[int]
    _gnss_unbend: dict[int, dict[KfKey, Sim3]]
    _retry_at: dict[tuple[int, int], float]
    _gnss_scale: dict[int, tuple[int, float]]
    evidence: EvidenceBook

    def _apply_corrections(self, m: Any, corr: dict[KfKey, Sim3], new_xyz: dict[Any, F64]) -> None:
        raise NotImplementedError

    def _cam_from_antenna(self, folded: str) -> F64:
        raise NotImplementedError

    def _current(self, snap: Snapshot) -> Any:
        raise NotImplementedError

    async def _merge(self, det: Detection, t_det: float) -> None:
        raise NotImplementedError

    def _unbend_map(self, m: Any) -> dict[KfKey, Sim3] | None:
        """Take the last GNSS stage's bend out of the map before the pose graph and global BA: they work on
        the visual shape (moved rigidly into ENU), and the next GNSS stage bends that afresh. Returns the
        bend removed (to restore it if no new stage result replaces it), or None if there was none."""
        unbend = self._gnss_unbend.pop(m.id, None)
        if not unbend:
            return None
        self._apply_corrections(m, gnss.bend_corrections(m, unbend, invert=False), {})
        self._generation[m.id] = self._generation.get(m.id, 0) + 1
        return unbend

    def _rebend_map(self, m: Any, unbend: dict[KfKey, Sim3]) -> None:
        """Give the map back the bend :meth:`_unbend_map` took out (no new GNSS stage result)."""
        self._apply_corrections(m, gnss.bend_corrections(m, unbend, invert=True), {})
        self._gnss_unbend[m.id] = unbend
        self._generation[m.id] = self._generation.get(m.id, 0) + 1

    async def _gnss_stage(self, m: Any) -> None:
        """Paper 2.5.3: bend the whole map onto every agent's GNSS fixes (antenna positions, through each
        agent's lever arm) with the agents tied together, and move it into ENU."""
        from hivemap.server.gnss_stage import NotEnoughFixes

        o = self.options.gnss
        inp = gnss.stage_input(m, self._cam_from_antenna)
        if inp is None:
            return
        fixes = inp.fixes
        # the agents' IMU up directions (camera frame = antenna frame's rotation): the attitude factors hold
        # those keyframes to gravity, the others to the map's own roll/pitch
        up = optimise.up_rows(m, inp.keys)
        snap = Snapshot(m.id, self._generation.get(m.id, 0), inp.keys, inp.poses)
        # the map's shape as the robust pose graph knows it: odometry and the loops and merges it kept
        opt, metric = self.options.optimise, self.options.fix_scale
        kept = self.evidence.held_edges(m.id, m.keyframes) if opt.gnc else []
        shape = gnss.shape_edges(m, snap, kept, opt, metric)
        # the odometry's stiffness is cross-validated on the fixes, again only once enough more have arrived
        cached = self._gnss_scale.get(m.id)
        scale = None if cached is None or gnss.cv_due(len(fixes), cached[0], o) else cached[1]
        try:
            res = await asyncio.get_running_loop().run_in_executor(
                self._opt_exec,
                partial(gnss.fuse, inp, shape, options=o.stage, up_in_body=up, stiffness_scale=scale),
            )
        except NotEnoughFixes as exc:
            self.server.events.add("gnss_stage", f"map {m.id}: {exc}", map_id=m.id)
            return
        cv = res.cv_scores
        used = int(np.sum(res.used))
        refused = gnss.refusal(res, len(fixes), o)
        if refused is not None:
            self.server.events.add(
                "gnss_stage", f"map {m.id}: {refused}", map_id=m.id,
                data={"refused": True, "used": used, "n_fixes": len(fixes),
                      "median_residual_m": float(np.median(res.residuals_m))},
            )  # fmt: skip
            return
        cur = self._current(snap)
        if cur is None:
            return
        new_cam, corr = gnss.corrected_cameras(res, inp)
        self._apply_corrections(cur, corr, {})
        if cv is not None:
            # kept only with a result that is applied: a stage refused, or dropped because the map changed
            # meanwhile (a merge during the solve), leaves the next stage to cross-validate the map it sees
            self._gnss_scale[cur.id] = (len(fixes), res.stiffness_scale)
        self._gnss_unbend[m.id] = gnss.unbend_of(res, inp, new_cam)
        self._generation[m.id] = self._generation.get(m.id, 0) + 1
        self._enu_maps.add(m.id)
        n_odo = sum(not e.robust for e in shape)
        self.server.events.add(
            "gnss_stage",
            f"map {m.id} bent onto {used}/{len(fixes)} fixes in ENU (held by {n_odo} odometry and "
            f"{len(shape) - n_odo} loop, merge and rendezvous edges, "
            f"median residual {float(np.median(res.residuals_m)):.2f} m, chain stiffness "
            f"x{res.stiffness_scale:g}{'' if cv is None else ' by cross-validation'})",
            map_id=m.id,
            data={"used": used, "n_fixes": len(fixes), "n_odometry": n_odo, "n_measured": len(shape) - n_odo,
                  "enu_from_map": res.enu_from_map.tolist(), "stiffness_scale": res.stiffness_scale,
                  "cv_scores": None if cv is None else {str(k): v for k, v in cv.items()}},
        )  # fmt: skip

    async def _gnss_retry(self, map_id: int) -> None:
        """Paper 2.5.3: when GNSS has put two maps into ENU and brings an agent of one next to keyframes of
        the other without a visual merge, verify that place with lowered thresholds
        (``PlaceRecOptions.gnss_retry_thresholds``) and merge on success."""
        o = self.options
        maps = self.server.stack.maps
        m = maps.get(map_id)
        if m is None or self.recognizer is None or o.gnss.retry_radius_m <= 0:
            return
        now = time.monotonic()
        for other_id in sorted(x for x in self._enu_maps if x != map_id and x in maps):
            pair = (min(map_id, other_id), max(map_id, other_id))
            if now - self._retry_at.get(pair, -np.inf) < o.gnss.retry_interval_s:
                continue
            self._retry_at[pair] = now
            for q, near in gnss.retry_queries(m, maps[other_id], o.gnss):
                recognizer = self.recognizer
                res = await asyncio.get_running_loop().run_in_executor(
                    self._pr_exec,
                    partial(recognizer.verify_pair, maps, map_id, q, other_id, near, fix_scale=o.fix_scale),
                )
                detect.publish(self.server.events, res)
                det = res.confirmed
                if det is not None:
                    self.server.events.add(
                        "gnss_retry",
                        f"GNSS-guided retry: {q} (map {map_id}) matched {det.candidate_key} (map {other_id}),"
                        f" {det.n_inliers} inliers: merging",
                        map_id=map_id,
                        data={"query_key": list(q), "candidate_key": list(det.candidate_key),
                              "n_inliers": det.n_inliers},
                    )  # fmt: skip
                    await self._merge(det, time.monotonic())
                    return
