"""ORB features (OpenCV) spread over the image, Hamming distances and matching helpers.

Extraction follows ORB-SLAM's recipe on top of OpenCV's ORB: per pyramid level a number of features
proportional to the level's area; the level is cut into cells of ``cell_size`` pixels; FAST at
``fast_threshold`` everywhere, and at ``min_fast_threshold`` in the cells where the first pass found nothing
(dim or low-contrast regions); then the strongest keypoints are taken cell by cell in round-robin so they
cover the image instead of piling up on the most textured spot. OpenCV computes orientation (intensity
centroid) and the rotated BRIEF descriptors.

Descriptors are u8 (N, 32) (256 bits). Keypoints are (u, v) pixels in the level-0 image (pixel centres
at integers, as OpenCV; unlike OpenCV's ORB the half-pixel offset of upper pyramid levels is corrected),
octaves u8 (pyramid level; scale ``scale_factor ** octave``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class OrbOptions:
    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    min_fast_threshold: int = 7
    cell_size: int = 30  #: grid cell side in pixels of each pyramid level (ORB-SLAM: 30)
    edge_threshold: int = 19  #: no keypoint closer to the border (ORB-SLAM: 19)
    patch_size: int = 31
    oversample: float = 4.0  #: candidates asked from each FAST pass, relative to n_features


def _level_quotas(opts: OrbOptions) -> NDArray[np.int64]:
    """Features per level, proportional to the level's area as in ORB-SLAM (sum == n_features)."""
    inv = 1.0 / opts.scale_factor
    first = opts.n_features * (1 - inv) / (1 - inv**opts.n_levels) if opts.n_levels > 1 else opts.n_features
    q = np.floor(first * inv ** np.arange(opts.n_levels)).astype(np.int64)
    q[-1] = max(opts.n_features - int(q[:-1].sum()), 0)
    return q


def _detect(gray: U8, opts: OrbOptions, threshold: int, mask: U8 | None) -> tuple[list[cv2.KeyPoint], object]:
    orb = cv2.ORB_create(  # type: ignore[attr-defined]
        nfeatures=int(opts.n_features * opts.oversample),
        scaleFactor=opts.scale_factor,
        nlevels=opts.n_levels,
        edgeThreshold=opts.edge_threshold,
        firstLevel=0,
        WTA_K=2,
        scoreType=cv2.ORB_HARRIS_SCORE,  # type: ignore[attr-defined]
        patchSize=opts.patch_size,
        fastThreshold=int(threshold),
    )
    return list(orb.detect(gray, mask)), orb


def _kp_arrays(kps: list[cv2.KeyPoint]) -> tuple[NDArray[np.float64], I64, NDArray[np.float64]]:
    if not kps:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0)
    pts = np.array([k.pt for k in kps], dtype=np.float64)
    octs = np.array([k.octave for k in kps], dtype=np.int64)
    resp = np.array([k.response for k in kps], dtype=np.float64)
    return pts, octs, resp


def extract_orb(
    gray: NDArray[np.uint8], options: OrbOptions | None = None, mask: NDArray[np.uint8] | None = None
) -> tuple[F32, U8, U8]:
    """Grid-distributed ORB features of a grayscale uint8 image (H, W).

    ``mask``: optional uint8 (H, W), non-zero where features may be detected.
    Returns ``keypoints`` f32 (N, 2), ``octaves`` u8 (N,), ``descriptors`` u8 (N, 32), N <= n_features.
    """
    opts = options or OrbOptions()
    gray = np.ascontiguousarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"extract_orb needs a uint8 (H, W) image, got {gray.dtype} {gray.shape}")
    if mask is not None:
        mask = np.ascontiguousarray((np.asarray(mask) > 0).astype(np.uint8) * 255)
    high, orb = _detect(gray, opts, opts.fast_threshold, mask)
    low: list[cv2.KeyPoint] = []
    if opts.min_fast_threshold < opts.fast_threshold:
        low, _ = _detect(gray, opts, opts.min_fast_threshold, mask)
    kps = high + low
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.uint8), np.zeros((0, 32), np.uint8)
    pts, octs, resp = _kp_arrays(kps)
    is_low = np.zeros(len(kps), bool)
    is_low[len(high) :] = True
    scale = opts.scale_factor ** octs.astype(np.float64)
    cell_xy = np.floor(pts / (opts.cell_size * scale)[:, None]).astype(np.int64)
    ncx = int(np.ceil(gray.shape[1] / opts.cell_size)) + 1
    cell = (
        octs * (ncx * (gray.shape[0] // opts.cell_size + 2)) + cell_xy[:, 1] * ncx + cell_xy[:, 0]
    ).astype(np.int64)
    # a low-threshold keypoint only counts in cells where the normal threshold found nothing
    keep = ~is_low | ~np.isin(cell, np.unique(cell[~is_low]))
    pts, octs, resp, cell = pts[keep], octs[keep], resp[keep], cell[keep]
    kps = [k for k, f in zip(kps, keep, strict=True) if f]
    # rank within each cell by response (0 = strongest)
    order = np.lexsort((-resp, cell))
    sorted_cell = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_cell)) + 1]
    group_start = np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - group_start
    # per level: round-robin over cells (all rank-0, then rank-1, ...) up to the level's quota; what a
    # level cannot fill passes to the next one
    quotas = _level_quotas(opts)
    chosen: list[NDArray[np.int64]] = []
    carry = 0
    for lvl in range(opts.n_levels):
        idx = np.flatnonzero(octs == lvl)
        want = int(quotas[lvl]) + carry
        if len(idx) > want:
            idx = idx[np.lexsort((-resp[idx], rank[idx]))[:want]]
        carry = want - len(idx)
        chosen.append(idx)
    sel = np.concatenate(chosen) if chosen else np.zeros(0, np.int64)
    sel_kps = [kps[i] for i in sel.tolist()]
    out_kps, desc = orb.compute(gray, sel_kps)  # type: ignore[attr-defined]
    if desc is None or not out_kps:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.uint8), np.zeros((0, 32), np.uint8)
    oct_arr = np.array([k.octave for k in out_kps], dtype=np.uint8)
    # OpenCV reports a level-l keypoint at x_l * s; the pyramid (pixel-centre resizing) puts level pixel x_l
    # at x_l * s + (s - 1) / 2 in the full image: correct that bias (1.3 px at level 7)
    s = opts.scale_factor ** oct_arr.astype(np.float64)
    kp_pts = np.array([k.pt for k in out_kps], dtype=np.float64).reshape(-1, 2)
    kp_arr = (kp_pts + 0.5 * (s - 1.0)[:, None]).astype(np.float32)
    return kp_arr, oct_arr, np.ascontiguousarray(desc, dtype=np.uint8)


# ---------------------------------------------------------------------------------------------- distances
def hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    """Hamming distance between descriptors, broadcasting over leading axes:
    ``a`` (..., 32), ``b`` (..., 32) -> (...) int64. All pairs: ``hamming(a[:, None], b[None])`` or
    ``hamming_matrix``."""
    x = np.bitwise_xor(np.asarray(a, np.uint8), np.asarray(b, np.uint8))
    return np.bitwise_count(x).sum(axis=-1, dtype=np.int64)


def hamming_matrix(a: NDArray[np.uint8], b: NDArray[np.uint8], chunk: int = 512) -> NDArray[np.int32]:
    """All-pairs Hamming distances ``a`` (N, 32) x ``b`` (M, 32) -> int32 (N, M) (64-bit words, chunked)."""
    a64 = np.ascontiguousarray(a, np.uint8).reshape(-1, 32).view(np.uint64)
    b64 = np.ascontiguousarray(b, np.uint8).reshape(-1, 32).view(np.uint64)
    out = np.empty((len(a64), len(b64)), np.int32)
    for s in range(0, len(a64), chunk):
        x = np.bitwise_xor(a64[s : s + chunk, None, :], b64[None, :, :])
        out[s : s + chunk] = np.bitwise_count(x).sum(axis=-1, dtype=np.int32)
    return out


# ---------------------------------------------------------------------------------------------- matching
def match_bf(
    desc_a: NDArray[np.uint8],
    desc_b: NDArray[np.uint8],
    ratio: float = 0.8,
    max_distance: int = 64,
    cross_check: bool = False,
) -> I64:
    """Brute-force Hamming matching (OpenCV ``BFMatcher``) with Lowe's ratio test (best < ratio * second
    best), a maximum distance and optionally a mutual-best check. Returns i64 (K, 2) index pairs
    ``(i_a, i_b)`` sorted by ``i_a``; each ``i_b`` appears at most once (the closer match wins)."""
    da = np.ascontiguousarray(desc_a, np.uint8).reshape(-1, 32)
    db = np.ascontiguousarray(desc_b, np.uint8).reshape(-1, 32)
    if len(da) == 0 or len(db) == 0:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(da, db, k=2)
    n = len(knn)
    best = np.full(n, -1, np.int64)
    d1 = np.full(n, np.inf)
    d2 = np.full(n, np.inf)
    for i, ms in enumerate(knn):
        if ms:
            best[i] = ms[0].trainIdx
            d1[i] = ms[0].distance
            if len(ms) > 1:
                d2[i] = ms[1].distance
    ok = (best >= 0) & (d1 <= max_distance) & (d1 < ratio * d2)
    if cross_check:
        back = bf.match(db, da)
        back_best = np.full(len(db), -1, np.int64)
        for m in back:
            back_best[m.queryIdx] = m.trainIdx
        ok &= back_best[np.where(best >= 0, best, 0)] == np.arange(n)
    ia = np.flatnonzero(ok)
    if len(ia) == 0:
        return np.zeros((0, 2), np.int64)
    ib = best[ia]
    # one match per b: keep the smallest distance
    order = np.lexsort((d1[ia], ib))
    first = np.r_[True, np.diff(ib[order]) != 0]
    keep = np.sort(ia[order][first])
    return np.stack([keep, best[keep]], axis=1).astype(np.int64)


def match_by_projection(
    uv_pred: NDArray[np.floating],
    desc_pts: NDArray[np.uint8],
    keypoints: NDArray[np.floating],
    octaves: NDArray[np.integer],
    descriptors: NDArray[np.uint8],
    radius: float,
    max_distance: int = 50,
    *,
    ratio: float = 0.9,
    scale_factor: float = 1.2,
    pred_octaves: NDArray[np.integer] | None = None,
    octave_tolerance: int = 1,
    unique: bool = True,
) -> I64:
    """Guided search: for each projected point find the best keypoint in a window around its prediction.

    ``uv_pred`` (M, 2) predicted pixels, ``desc_pts`` (M, 32) the points' descriptors; ``keypoints`` (N, 2),
    ``octaves`` (N,), ``descriptors`` (N, 32) of the image searched. A keypoint j is a candidate for point
    i if it lies within ``radius * scale_factor ** o`` pixels of ``uv_pred[i]``, where ``o`` is the
    point's predicted octave (``pred_octaves``; then only keypoints within ``octave_tolerance`` levels
    count, as in ORB-SLAM) or else the keypoint's own octave. The best candidate is accepted if its
    distance is <= ``max_distance`` and < ``ratio`` x the second best's (when there is one). With
    ``unique`` a keypoint goes to at most one point (the one with the smallest distance).
    Returns i64 (M,): keypoint index per point, or -1.
    """
    uv = np.asarray(uv_pred, np.float64).reshape(-1, 2)
    dp = np.ascontiguousarray(desc_pts, np.uint8).reshape(-1, 32)
    kp = np.asarray(keypoints, np.float64).reshape(-1, 2)
    ko = np.asarray(octaves, np.int64).reshape(-1)
    dk = np.ascontiguousarray(descriptors, np.uint8).reshape(-1, 32)
    m = len(uv)
    out = np.full(m, -1, np.int64)
    if m == 0 or len(kp) == 0:
        return out
    po = None if pred_octaves is None else np.asarray(pred_octaves, np.int64).reshape(-1)
    ok_pt: NDArray[np.bool_] = np.asarray(np.isfinite(uv).all(axis=1), dtype=bool)
    pi, kj = _window_candidates(uv, ok_pt, kp, ko, po, radius, scale_factor, octave_tolerance)
    if len(pi) == 0:
        return out
    dist = hamming(dp[pi], dk[kj])
    order = np.lexsort((dist, pi))
    pi, kj, dist = pi[order], kj[order], dist[order]
    starts = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    counts = np.diff(np.r_[starts, len(pi)])
    b_pt, b_kp, b_d = pi[starts], kj[starts], dist[starts]
    second = np.full(len(starts), np.inf)
    has2 = counts > 1
    second[has2] = dist[starts[has2] + 1]
    ok = (b_d <= max_distance) & (b_d < ratio * second)
    b_pt, b_kp, b_d = b_pt[ok], b_kp[ok], b_d[ok]
    if unique and len(b_pt):
        order = np.lexsort((b_d, b_kp))
        b_pt, b_kp = b_pt[order], b_kp[order]
        first = np.r_[True, b_kp[1:] != b_kp[:-1]]
        b_pt, b_kp = b_pt[first], b_kp[first]
    out[b_pt] = b_kp
    return out


def _window_candidates(
    uv: NDArray[np.float64],
    ok_pt: NDArray[np.bool_],
    kp: NDArray[np.float64],
    ko: I64,
    po: I64 | None,
    radius: float,
    scale_factor: float,
    octave_tolerance: int,
) -> tuple[I64, I64]:
    """(point index, keypoint index) pairs within each pair's window, via a grid of keypoints whose cell is
    the largest window radius (each point looks at its 3 x 3 neighbouring cells)."""
    if po is None:
        r_max = radius * scale_factor ** float(ko.max())
    else:
        r_max = radius * scale_factor ** float(po[ok_pt].max()) if ok_pt.any() else radius
    cell = max(float(r_max), 1e-6)
    kc = np.floor(kp / cell).astype(np.int64)
    lo = kc.min(axis=0)
    kc -= lo
    ncol, nrow = int(kc[:, 0].max()) + 1, int(kc[:, 1].max()) + 1
    if ncol * nrow > 4_000_000:  # degenerate spread (tiny radius, huge coordinates): coarser cells
        return _window_candidates(uv, ok_pt, kp, ko, po, radius * 8, scale_factor, octave_tolerance)
    kid = kc[:, 1] * ncol + kc[:, 0]
    korder = np.argsort(kid, kind="stable")
    cell_start = np.searchsorted(kid[korder], np.arange(ncol * nrow + 1))
    pidx = np.flatnonzero(ok_pt)
    uvc = uv[pidx]
    inside = np.all(np.abs(uvc) < 1e12, axis=1)  # far-off predictions cannot overflow the grid maths
    pidx, uvc = pidx[inside], uvc[inside]
    pc = np.floor(uvc / cell).astype(np.int64) - lo
    all_pi, all_kj = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            cx, cy = pc[:, 0] + dx, pc[:, 1] + dy
            valid = (cx >= 0) & (cx < ncol) & (cy >= 0) & (cy < nrow)
            cid = cy[valid] * ncol + cx[valid]
            st, en = cell_start[cid], cell_start[cid + 1]
            cnt = en - st
            tot = int(cnt.sum())
            if tot == 0:
                continue
            rep_pt = np.repeat(pidx[valid], cnt)
            offs = np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(st, cnt)
            all_pi.append(rep_pt)
            all_kj.append(korder[offs])
    if not all_pi:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pi = np.concatenate(all_pi)
    kj = np.concatenate(all_kj)
    d2 = ((uv[pi] - kp[kj]) ** 2).sum(axis=1)
    if po is None:
        r = radius * scale_factor ** ko[kj].astype(np.float64)
        keep = d2 <= r * r
    else:
        r = radius * scale_factor ** po[pi].astype(np.float64)
        keep = (d2 <= r * r) & (np.abs(ko[kj] - po[pi]) <= octave_tolerance)
    return pi[keep], kj[keep]
