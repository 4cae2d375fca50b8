"""Calibration of the server's pose covariances (issue 26): the share of keyframes whose true camera
centre lies inside the 2-sigma ellipsoid of their marginal (``/maps/{id}/uncertainty``).

The marginals are relative to the map's gauge (its reference keyframe, exact: an all-zero covariance), so
the ground truth is put into the map frame by that keyframe alone: ``map_from_gt = T_anchor_est @
T_anchor_gt^-1``. A fit of all keyframes (Umeyama) would absorb part of the errors the covariances are
about and flatter them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.server.marginals import inside_ellipsoid

F64 = NDArray[np.float64]


def _gt_pose(gt: Any, t: float, max_diff: float) -> F64 | None:
    ts = np.asarray(gt.timestamps)
    j = int(np.argmin(np.abs(ts - t)))
    return None if abs(ts[j] - t) > max_diff else np.asarray(gt.poses_se3[j], dtype=np.float64)


def ellipsoid_coverage(
    keyframes: Sequence[dict[str, Any]],
    uncertainty: Sequence[dict[str, Any]],
    gt_cam: dict[str, Any],
    n_sigma: float = 2.0,
    max_diff: float = 0.02,
) -> dict[str, Any] | None:
    """One map: ``keyframes`` as ``/maps/{id}/keyframes`` lists them (agent_id, id, timestamp,
    world_from_cam), ``uncertainty`` as ``/maps/{id}/uncertainty`` does (agent_id, kf_id, pose_cov),
    ``gt_cam``: agent -> ground truth of its cam0 (``sensor="cam0"``; a session ``agent#n`` uses its
    agent's). Returns n (keyframes with a covariance and ground truth within ``max_diff`` s, the anchor
    left out), ``inside`` (the share within the ``n_sigma`` ellipsoid; a calibrated Gaussian: 73.9 % for
    2 sigma in 3-D), ``mean_nees`` (mean squared Mahalanobis distance / 3; 1 when calibrated, > 1:
    overconfident) and the anchor; None without an anchor with ground truth."""
    kfs = {(str(k["agent_id"]), int(k["id"])): k for k in keyframes}
    rows = [
        (str(u["agent_id"]), int(u["kf_id"]), np.asarray(u["pose_cov"], dtype=np.float64))
        for u in uncertainty
    ]
    truth: dict[tuple[str, int], F64] = {}
    for a, i, _ in rows:
        gt = gt_cam.get(a.split("#")[0])
        k = kfs.get((a, i))
        if (
            gt is not None
            and k is not None
            and (T := _gt_pose(gt, float(k["timestamp"]), max_diff)) is not None
        ):
            truth[(a, i)] = T
    anchors = [(a, i) for a, i, c in rows if not np.any(c) and (a, i) in truth]
    if not anchors:
        return None
    anchor = min(anchors)
    map_from_gt = np.asarray(kfs[anchor]["world_from_cam"], dtype=np.float64) @ np.linalg.inv(truth[anchor])
    inside, nees = [], []
    for a, i, c in rows:
        if (a, i) == anchor or (a, i) not in truth or not np.any(c):
            continue
        err = (
            np.asarray(kfs[(a, i)]["world_from_cam"], dtype=np.float64)[:3, 3]
            - (map_from_gt @ truth[(a, i)])[:3, 3]
        )
        P = c[3:, 3:]
        inside.append(inside_ellipsoid(err, P, n_sigma))
        nees.append(float(err @ np.linalg.pinv(P) @ err) / 3.0)
    if not inside:
        return None
    return {"n": len(inside), "inside": float(np.mean(inside)), "n_sigma": n_sigma,
            "mean_nees": float(np.mean(nees)), "median_nees": float(np.median(nees)),
            "anchor": list(anchor)}  # fmt: skip


def covariance_coverage(url: str, maps: list[dict[str, Any]], gt_cam: dict[str, Any]) -> dict[str, Any]:
    """Per map id: :func:`hivemap.eval.uncertainty.ellipsoid_coverage` of the server's keyframe
    covariances (issue 26: the share of keyframes inside their 2-sigma ellipsoid), or None."""
    import httpx

    out: dict[str, Any] = {}
    for m in maps:
        q = {"limit": 10_000}
        kfs: list[dict[str, Any]] = []
        unc: list[dict[str, Any]] = []
        for path, rows, key in (("keyframes", kfs, "keyframes"), ("uncertainty", unc, "keyframes")):
            offset, total = 0, 1
            while offset < total:
                r = httpx.get(f"{url}/maps/{m['id']}/{path}", params={**q, "offset": offset}, timeout=60)
                if r.status_code != 200:
                    break
                page = r.json()
                rows += page[key]
                total, offset = int(page["total"]), offset + len(page[key])
                if not page[key]:
                    break
        out[str(m["id"])] = ellipsoid_coverage(kfs, unc, gt_cam)
    return out
