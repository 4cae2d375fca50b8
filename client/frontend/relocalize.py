"""The front-end's relocalisation against the agent's own map."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from hivemap.client.frontend.mapdata import Frame
from hivemap.maps.geometry import se3

if TYPE_CHECKING:
    from hivemap.client.frontend.tracker import Frontend


def relocalize(fe: Frontend, frame: Frame) -> tuple[bool, int]:
    """Global relocalisation: the frame's descriptors against the points of the last keyframes, P3P
    RANSAC, then the same refinement as tracking."""
    o = fe.options
    if frame.n == 0 or not fe._kfs:
        return False, 0
    kf_ids = sorted(fe._kfs)[-o.reloc_keyframes :]
    pids = np.unique(np.concatenate([fe._kfs[k].frame.point_ids for k in kf_ids]))
    pids = pids[pids >= 0]
    pids = pids[fe._pts.alive[pids]]
    if len(pids) < o.reloc_min_inliers:
        return False, 0
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(frame.desc, fe._pts.desc[pids], k=2)
    qi, ti = [], []
    for m in knn:
        if len(m) == 2 and m[0].distance < 0.8 * m[1].distance and m[0].distance <= 64:
            qi.append(m[0].queryIdx)
            ti.append(m[0].trainIdx)
    if len(qi) < o.reloc_min_inliers:
        return False, len(qi)
    kps = np.array(qi)
    mp = pids[np.array(ti)]
    _, u = np.unique(kps, return_index=True)
    kps, mp = kps[u], mp[u]
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        fe._pts.xyz[mp],
        frame.kpu[kps],
        fe.cam.K,
        None,
        iterationsCount=500,
        reprojectionError=o.pnp_reprojection_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or inl is None or len(inl) < o.reloc_min_inliers:
        return False, 0 if inl is None else len(inl)
    T = se3(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    inl = inl.reshape(-1)
    return fe._finish_tracking(frame, T, mp[inl], kps[inl])
