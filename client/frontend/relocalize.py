"""The front-end's relocalisation against the agent's own map."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import cv2
import numpy as np

from hivemap.client.frontend.mapdata import Frame
from hivemap.maps.geometry import se3

if TYPE_CHECKING:
    from hivemap.client.frontend.tracker import Frontend

log = logging.getLogger(__name__)


def bow_candidates(fe: Frontend, frame: Frame, skip: set[int]) -> list[int]:
    """The session's older keyframes most similar to the frame by bag of words (ORB-SLAM's
    relocalisation candidates): where the agent returns to ground it mapped long ago."""
    n = fe.options.reloc_bow_candidates
    older = [k for k in fe._kfs if k not in skip]
    if n <= 0 or not older or frame.n == 0:
        return []
    try:
        from hivemap.maps.vocabulary import default_vocabulary

        vocab = default_vocabulary()
    except FileNotFoundError:
        log.warning("no ORB vocabulary: relocalisation against the recent keyframes only")
        return []
    q, _ = vocab.transform(frame.desc)
    scores = []
    for k in older:
        kf = fe._kfs[k]
        if kf.bow is None:
            kf.bow = vocab.transform(kf.frame.desc)[0]
        scores.append(vocab.score(q, kf.bow))
    order = np.argsort(scores)[::-1][:n]
    return [older[i] for i in order if scores[i] > 0]


def relocalize(fe: Frontend, frame: Frame) -> tuple[bool, int]:
    """Global relocalisation: the frame's descriptors against the points of the last keyframes and of
    the bag-of-words candidates, P3P RANSAC, then the same refinement as tracking."""
    o = fe.options
    if frame.n == 0 or not fe._kfs:
        return False, 0
    recent = sorted(fe._kfs)[-o.reloc_keyframes :]
    kf_ids = recent + bow_candidates(fe, frame, set(recent))
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
