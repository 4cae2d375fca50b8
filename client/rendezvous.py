"""Rendezvous observations of a live agent: the marker carriers of other agents in its cam0 images
(``hivemap.client.frontend.markers``), each tied to the agent's own tracking as a protocol ``Rendezvous``.

The observation is anchored to the newest keyframe of the current session that the front-end has
already emitted: its ``Keyframe`` message went into the outbox before this frame's messages, so the
server always knows the reference keyframe when the rendezvous arrives (the newest keyframes wait for
local BA before they are emitted). ``ref_from_cam`` is the frame's cam0 in that keyframe's cam0, both
as the front-end estimates them now. Only frames tracked well (state ``ok``) are used: a weak or
relocalised pose would carry its error into the team's graph. So is the reference: a keyframe made while
tracking was weak or lost (at the IMU's pose) is centimetres and tenths of a degree off its successor
frames, which the server would weigh with the marker pose's millimetre covariance.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.markers import MarkerDetector, MarkerOptions
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3_inverse
from hivemap.maps.markers import Carrier
from hivemap.protocol import Rendezvous

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


class RendezvousSource:
    """Runs the detector on every ``options.every_k_frames``-th frame, or takes the detections of the
    front-end's carrier mask (one detector per frame); counts what it saw."""

    def __init__(
        self,
        camera: PinholeCamera,
        carriers: Mapping[str, Carrier],
        own_agent_id: str,
        options: MarkerOptions,
    ) -> None:
        self.options = options
        self.detector = MarkerDetector(camera, carriers, own_agent_id, options)
        self.frames_seen = 0
        self.frames_run = 0  # frames the detector ran on
        self.observations = 0  # rendezvous messages made
        self.cpu_s = 0.0  # process CPU time the detector took

    def observe(self, t: float, gray: NDArray[np.uint8], res: Any, frontend: Any) -> list[Rendezvous]:
        """The frame's rendezvous (front-end session numbering; the caller offsets it for the link)."""
        from hivemap.client.frontend.events import TrackingState

        self.frames_seen += 1
        mask = getattr(frontend, "carrier_mask", None)
        if mask is not None and mask.frame_t == float(t):
            # the front-end's carrier mask ran the detector on this frame: its whole-image searches
            # (every ``carrier_mask_full_every``-th frame) set the rate instead of ``every_k_frames``
            due = bool(mask.full_frame)
        else:
            mask = None
            due = (self.frames_seen - 1) % max(self.options.every_k_frames, 1) == 0
        if res.state != TrackingState.OK or not due:
            return []
        ref = _reference(frontend, res)
        if ref is None:
            return []
        if mask is not None:
            seen = mask.observations
        else:
            c0 = time.process_time()
            seen = self.detector.detect(gray)
            self.cpu_s += time.process_time() - c0
        self.frames_run += 1
        kf_id, ref_from_cam = ref
        out = [
            Rendezvous(
                timestamp=float(t),
                observed_agent=o.agent_id,
                marker_ids=np.asarray(o.marker_ids, dtype=np.int64),
                ref_kf_id=kf_id,
                ref_from_cam=ref_from_cam,
                cam_from_observed=np.asarray(o.cam_from_observed, dtype=np.float64),
                covariance=np.asarray(o.covariance, dtype=np.float64),
                reproj_rms_px=float(o.reproj_rms_px),
                session=int(res.session),
            )
            for o in seen
        ]
        for r in out:
            log.debug("t %.3f: %s at %.2f m (markers %s)", t, r.observed_agent,
                      float(np.linalg.norm(r.cam_from_observed[:3, 3])), r.marker_ids.tolist())  # fmt: skip
        self.observations += len(out)
        return out


def _reference(frontend: Any, res: Any) -> tuple[int, F64] | None:
    """(newest emitted keyframe of the frame's session, the frame's cam0 in that keyframe's cam0)."""
    if int(res.session) != int(frontend.session):
        return None
    emitted = [k for k, kf in frontend.keyframes.items() if kf.emitted]
    if not emitted:
        return None
    kf = frontend.keyframes[max(emitted)]
    if kf.odom_sigma is not None:  # not tracked well since its predecessor
        return None
    return int(kf.id), se3_inverse(kf.T_wc) @ np.asarray(res.world_from_cam, dtype=np.float64)
