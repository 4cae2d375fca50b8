"""Rendezvous observations on the server (protocol v3 ``rendezvous``): one agent saw another's marker
carrier. Each is kept (in memory and in the map store's ``map_rendezvous`` table) with its state, which
the back-end (:mod:`hivemap.server.backend.rendezvous`) moves on:

* ``held``: waiting for the observer's reference keyframe, for the observed agent to appear, or for a
  keyframe of the observed agent after the observation's time (as keyframes wait for their points);
* ``pending``: resolved into an edge between two maps, waiting for enough consistent observations to merge;
* ``judging``: an edge of a map's robust pose graph, not judged yet;
* ``kept`` / ``rejected``: judged by the map's robust pose graph (or refused at a merge as inconsistent
  with the observations that made it), ``reason`` says why;
* ``redundant``: too close in time to another observation of the same agent by the same observer (kept,
  not used).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.protocol import Rendezvous

F64 = NDArray[np.float64]
KfKey = tuple[str, int]

# how many observations may be held at once (each is a few hundred bytes; an agent sending observations
# of an agent that never appears must not fill the server)
MAX_HELD = 20000


@dataclass
class RendezvousObs:
    """One observation: ``observer`` is the folded id of the observer's agent map (its session)."""

    id: int
    observer: str
    observed_agent: str
    timestamp: float
    marker_ids: list[int]
    ref_kf_id: int
    ref_from_cam: F64
    cam_from_observed: F64
    covariance: F64
    reproj_rms_px: float
    received: float = field(default_factory=time.time)
    state: str = "held"
    reason: str = ""
    # once resolved: the edge (candidate = the observer's reference keyframe, query = the observed agent's
    # keyframe before the observation), its measured cam_candidate_from_cam_query and sigmas
    edge: dict[str, Any] | None = None
    chi2: float | None = None
    map_id: int | None = None

    @staticmethod
    def from_msg(rid: int, observer: str, msg: Rendezvous) -> RendezvousObs:
        return RendezvousObs(
            rid, observer, msg.observed_agent, float(msg.timestamp), [int(i) for i in msg.marker_ids],
            int(msg.ref_kf_id), np.array(msg.ref_from_cam, dtype=np.float64),
            np.array(msg.cam_from_observed, dtype=np.float64), np.array(msg.covariance, dtype=np.float64),
            float(msg.reproj_rms_px),
        )  # fmt: skip

    @property
    def ref_key(self) -> KfKey:
        return (self.observer, self.ref_kf_id)

    def record(self) -> dict[str, Any]:
        """JSON-serialisable (the store's row, the REST listing)."""
        return {"id": self.id, "observer": self.observer, "observed_agent": self.observed_agent,
                "timestamp": self.timestamp, "marker_ids": list(self.marker_ids), "ref_kf_id": self.ref_kf_id,
                "ref_from_cam": self.ref_from_cam.tolist(),
                "cam_from_observed": self.cam_from_observed.tolist(),
                "covariance": self.covariance.tolist(), "reproj_rms_px": self.reproj_rms_px,
                "received": self.received, "state": self.state, "reason": self.reason, "edge": self.edge,
                "chi2": self.chi2, "map_id": self.map_id}  # fmt: skip

    @staticmethod
    def from_record(d: dict[str, Any]) -> RendezvousObs:
        def arr(x: Any) -> F64:
            return np.asarray(x, dtype=np.float64)

        return RendezvousObs(
            int(d["id"]), str(d["observer"]), str(d["observed_agent"]), float(d["timestamp"]),
            [int(i) for i in d["marker_ids"]], int(d["ref_kf_id"]), arr(d["ref_from_cam"]),
            arr(d["cam_from_observed"]), arr(d["covariance"]), float(d["reproj_rms_px"]),
            float(d.get("received", 0.0)), str(d.get("state", "held")), str(d.get("reason", "")),
            d.get("edge"), d.get("chi2"), d.get("map_id"),
        )  # fmt: skip
