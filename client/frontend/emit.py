"""The front-end's keyframe events: a keyframe, its new points and its relative pose (with the
covariance in the body frame), once local BA has settled it."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.events import KeyframeEvent
from hivemap.client.frontend.mapdata import KeyframeData
from hivemap.maps.geometry import se3_inverse

if TYPE_CHECKING:
    from hivemap.client.frontend.tracker import Frontend


def emit_ready(fe: Frontend) -> None:
    """Emit the keyframes old enough that local BA has settled them (all but the newest two)."""
    if not fe._gravity_aligned:
        return
    ids = sorted(fe._kfs)
    delay = 2
    for kid in ids[: max(0, len(ids) - delay)]:
        if not fe._kfs[kid].emitted:
            emit_keyframe(fe, fe._kfs[kid])


def emit_keyframe(fe: Frontend, kf: KeyframeData) -> None:
    f = kf.frame
    pids = f.point_ids.copy()
    ok = pids >= 0
    ok[ok] = fe._pts.alive[pids[ok]]
    pids[~ok] = -1
    newp = np.unique(pids[ok])
    newp = newp[~fe._pts.emitted[newp]]
    fe._pts.emitted[newp] = True
    fe._pts.sent_xyz[newp] = fe._pts.xyz[newp]
    T_wc = kf.T_wc
    T_wb = T_wc @ fe.cam_from_body
    rel_body = rel_cov = None
    prev = fe._kfs.get(kf.prev_id) if kf.prev_id is not None else None
    if prev is not None and kf.rel_cov_cam is not None:
        prev_wb = prev.T_wc @ fe.cam_from_body
        rel_body = se3_inverse(prev_wb) @ T_wb
        # right perturbation: xi_body = Ad(body_from_cam) xi_cam
        Tbc = fe.body_from_cam
        Rb, tb = Tbc[:3, :3], Tbc[:3, 3]
        tx = np.array([[0, -tb[2], tb[1]], [tb[2], 0, -tb[0]], [-tb[1], tb[0], 0]])
        Ad = np.zeros((6, 6))
        Ad[:3, :3] = Rb
        Ad[3:, 3:] = Rb
        Ad[3:, :3] = tx @ Rb
        rel_cov = Ad @ kf.rel_cov_cam @ Ad.T
    kf.emitted = True
    fe._events.append(
        KeyframeEvent(
            session=kf.session,
            kf_id=kf.id,
            timestamp=kf.timestamp,
            world_from_cam=T_wc,
            world_from_body=T_wb,
            keypoints=f.uv.copy(),
            octaves=f.octaves.copy(),
            descriptors=f.desc.copy(),
            point_ids=pids,
            prev_kf_id=kf.prev_id if prev is not None else None,
            rel_body=rel_body,
            rel_cov=rel_cov,
            gnss_epoch=kf.gnss_epoch,
            new_point_ids=newp,
            new_point_xyz=fe._pts.xyz[newp].copy(),
            new_point_descriptors=fe._pts.desc[newp].copy(),
            prev_session_from_world=kf.prev_session_from_world,
            prev_session_sigma=kf.prev_session_sigma,
            u_right=f.meas[:, 2].astype(np.float32),
            odom_sigma=kf.odom_sigma,
            track_sigma=track_sigma(kf.rel_cov_cam) if rel_cov is not None else None,
        )
    )


def track_sigma(cov: NDArray[np.float64]) -> tuple[float, float]:
    """[m, deg]: the per-axis sigmas (RMS over the axes) of a 6x6 [rot, trans] pose covariance."""
    c = np.asarray(cov, dtype=np.float64)
    return float(np.sqrt(np.trace(c[3:, 3:]) / 3.0)), float(np.degrees(np.sqrt(np.trace(c[:3, :3]) / 3.0)))
