"""Place recognition's descriptor matching: ORB descriptors paired by bag-of-words node (paper 2.5.1's
2D-2D step) or by projection into a keyframe, on 64-bit words, best and unique per descriptor."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from hivemap.maps.vocabulary import FeatureVector

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def _u64(d: NDArray[np.uint8]) -> NDArray[np.uint64]:
    return np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, 32).view(np.uint64)


def _hamming(desc_a: NDArray[np.uint8], ia: I64, desc_b: NDArray[np.uint8], ib: I64) -> NDArray[np.int16]:
    """Hamming distances of descriptor pairs ``(desc_a[ia[k]], desc_b[ib[k]])``; the four words' counts
    added column by column (a ``sum(axis=1)`` over four columns took 2.5x as long)."""
    x = _u64(desc_a)[ia]
    x ^= _u64(desc_b)[ib]
    c = np.bitwise_count(x).astype(np.int16)
    return c[:, 0] + c[:, 1] + c[:, 2] + c[:, 3]  # type: ignore[no-any-return]


def match_bow(
    fv_a: FeatureVector,
    desc_a: NDArray[np.uint8],
    fv_b: FeatureVector,
    desc_b: NDArray[np.uint8],
    max_distance: int = 50,
    ratio: float = 0.75,
    mask_a: NDArray[np.bool_] | None = None,
    mask_b: NDArray[np.bool_] | None = None,
) -> I64:
    """Direct-index-accelerated matching (DBoW2 / ORB-SLAM ``SearchByBoW``), fully vectorised.

    Features are compared only when they fall under the same vocabulary node. For every feature of
    ``a`` the best ``b`` must be within ``max_distance`` bits and pass the ratio test against the
    second best; each ``b`` is used once (the closest wins). Returns (K, 2) index pairs (a, b).
    """
    ia = np.arange(len(desc_a)) if mask_a is None else np.flatnonzero(mask_a)
    ib = np.arange(len(desc_b)) if mask_b is None else np.flatnonzero(mask_b)
    if len(ia) == 0 or len(ib) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    na = fv_a.node_of_feature[ia]
    nb = fv_b.node_of_feature[ib]
    order = np.argsort(nb, kind="stable")
    ib_sorted, nb_sorted = ib[order], nb[order]
    start = np.searchsorted(nb_sorted, na, side="left")
    cnt = np.searchsorted(nb_sorted, na, side="right") - start
    total = int(cnt.sum())
    if total == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a_rep = np.repeat(ia, cnt)
    offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    b_rep = ib_sorted[np.repeat(start, cnt) + offs]
    dist = _hamming(desc_a, a_rep, desc_b, b_rep)
    nz = cnt > 0
    return _best_per_block(ia[nz], (np.cumsum(cnt) - cnt)[nz], b_rep, dist, max_distance, ratio)


def _best_per_block(
    a: I64, starts: I64, b: I64, dist: NDArray[Any], max_distance: float, ratio: float
) -> I64:
    """:func:`_best_unique` with a ratio test, for pairs already in blocks of one ``a`` each (``a[i]``'s
    pairs from ``starts[i]``, ``a`` increasing), without sorting them: one minimum per block gives the
    best (the first of equals, as the stable sort did), a second with the best masked the second best."""
    pos = np.arange(len(dist), dtype=np.int64)
    key = (np.asarray(dist, dtype=np.int64) << 32) | pos
    low = np.minimum.reduceat(key, starts)
    best = low & 0xFFFFFFFF
    best_d = low >> 32
    key[best] = np.iinfo(np.int64).max  # a block of one pair keeps it: no second best
    second = np.minimum.reduceat(key, starts)
    second_d = np.where(second == np.iinfo(np.int64).max, np.inf, second >> 32)
    ok = (best_d <= max_distance) & (best_d < ratio * second_d)
    pa, pb, pd = a[ok], b[best[ok]], best_d[ok]
    o = np.argsort((pb.astype(np.int64) << 9) | pd, kind="stable")
    pa, pb = pa[o], pb[o]
    keep = np.ones(len(pb), dtype=bool)
    keep[1:] = pb[1:] != pb[:-1]
    return np.stack([pa[keep], pb[keep]], axis=1).astype(np.int64)


def _best_unique(a: I64, b: I64, dist: NDArray[Any], max_distance: float, ratio: float | None) -> I64:
    """Per ``a``: best ``b`` (ratio test vs the second best if ``ratio``); then one ``a`` per ``b``."""
    if len(a) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dist = np.asarray(dist, dtype=np.int64)  # Hamming distances: 0..256
    # one stable sort on a packed (a, dist) key instead of a two-key lexsort (same order, ~3x faster)
    o = np.argsort((a.astype(np.int64) << 9) | dist, kind="stable")
    a, b, dist = a[o], b[o], dist[o]
    first = np.ones(len(a), dtype=bool)
    first[1:] = a[1:] != a[:-1]
    idx = np.flatnonzero(first)
    best_d = dist[idx]
    ok = best_d <= max_distance
    if ratio is not None:
        has_second = np.zeros(len(idx), dtype=bool)
        nxt = idx + 1
        in_range = nxt < len(a)
        has_second[in_range] = a[nxt[in_range]] == a[idx[in_range]]
        second_d = np.where(has_second, dist[np.minimum(nxt, len(a) - 1)], np.inf)
        ok &= best_d < ratio * second_d
    idx = idx[ok]
    pa, pb, pd = a[idx], b[idx], dist[idx]
    o = np.argsort((pb.astype(np.int64) << 9) | pd, kind="stable")
    pa, pb = pa[o], pb[o]
    keep = np.ones(len(pb), dtype=bool)
    keep[1:] = pb[1:] != pb[:-1]
    return np.stack([pa[keep], pb[keep]], axis=1).astype(np.int64)


def match_projected(
    uv: F64,
    desc_pts: NDArray[np.uint8],
    keypoints: NDArray[np.floating],
    octaves: NDArray[np.integer],
    descriptors: NDArray[np.uint8],
    radius: float,
    max_distance: int,
    kp_mask: NDArray[np.bool_] | None = None,
) -> I64:
    """Guided search: points projected to ``uv`` (M, 2) -> (K, 2) pairs (point index, keypoint index).

    A keypoint is a candidate when within ``radius * 1.2^octave`` pixels; the closest descriptor within
    ``max_distance`` bits wins; each keypoint is used once.
    """
    kidx = np.arange(len(keypoints)) if kp_mask is None else np.flatnonzero(kp_mask)
    if len(uv) == 0 or len(kidx) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    kp = np.asarray(keypoints, dtype=np.float64)[kidx]
    scale = 1.2 ** np.asarray(octaves, dtype=np.float64)[kidx]
    tree_kp = cKDTree(kp)
    tree_uv = cKDTree(np.asarray(uv, dtype=np.float64))
    sdm = tree_uv.sparse_distance_matrix(tree_kp, radius * float(scale.max()), output_type="ndarray")
    if len(sdm) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pi = sdm["i"].astype(np.int64)
    kj = sdm["j"].astype(np.int64)
    near = sdm["v"] <= radius * scale[kj]
    pi, kj = pi[near], kj[near]
    dist = _hamming(desc_pts, pi, descriptors, kidx[kj])
    pairs = _best_unique(pi, kidx[kj], dist, max_distance, None)
    return pairs
