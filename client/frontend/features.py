"""ORB extraction with a spatial grid and an adaptive FAST threshold; contrast normalisation of dim images."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.options import FrontendOptions

log = logging.getLogger(__name__)
U8 = NDArray[np.uint8]
CONTRAST_MODES = ("stretch", "clahe", "off")
# Immerkaer's noise operator: the difference of two Laplacians, blind to planes and ramps; on white noise
# of sigma s its output has sigma 6 s
_NOISE_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], np.float32)


class ContrastNormaliser:
    """Low-contrast (somber, foggy) stereo pairs made fit for FAST before extraction.

    Only pairs whose grey-level spread is below ``low_contrast_std`` are touched. ``stretch`` (the
    default) maps both images by the same linear gain, so LK stereo sees the same brightness on both
    sides; ``clahe`` equalises each image cell's histogram on its own, which restores texture in
    crushed shadows but tracked worse in the worst case over worlds (docs/decisions.md). Both end with
    a light blur so that FAST at a low threshold does not fire on the amplified sensor noise.
    """

    def __init__(self, options: FrontendOptions) -> None:
        if options.contrast not in CONTRAST_MODES:
            raise ValueError(f"contrast must be one of {CONTRAST_MODES}, not {options.contrast!r}")
        self.options = options
        self._clahe = cv2.createCLAHE(
            clipLimit=options.clahe_clip_limit, tileGridSize=(options.grid_cols, options.grid_rows)
        )

    def __call__(self, left: U8, right: U8) -> tuple[U8, U8]:
        o = self.options
        if o.contrast == "off" or o.low_contrast_std <= 0:
            return left, right
        sub = left[::4, ::4]
        if float(sub.std()) >= o.low_contrast_std:
            return left, right
        if o.contrast == "clahe":
            pair = [self._clahe.apply(img) for img in (left, right)]
        else:
            lo, hi = np.percentile(sub, (1.0, 99.0))
            gain = min(o.max_contrast_gain, 200.0 / max(float(hi - lo), 1.0))
            # the same mapping on both images keeps LK stereo consistent
            pair = [
                cv2.convertScaleAbs(img, alpha=gain, beta=-gain * float(lo) + 20.0) for img in (left, right)
            ]
        out = [np.asarray(cv2.GaussianBlur(img, (5, 5), 1.0), dtype=np.uint8) for img in pair]
        return out[0], out[1]


class OrbExtractor:
    """cv2 ORB, over-detected then thinned on a grid so features spread over the image.

    The FAST threshold drops (down to ``min_fast_threshold``) when too few corners are found and
    recovers slowly when there are plenty, so somber/misty images still give enough features; with
    ``fast_cell_refill``, cells the image-wide threshold leaves nearly empty are detected again at a
    noise-derived threshold.
    """

    def __init__(self, options: FrontendOptions) -> None:
        self.options = options
        self.threshold = options.fast_threshold
        self._orb = cv2.ORB_create(  # type: ignore[attr-defined]
            nfeatures=int(options.n_features * 2),
            scaleFactor=options.scale_factor,
            nlevels=options.n_levels,
            edgeThreshold=19,
            patchSize=31,
            fastThreshold=self.threshold,
        )

    def extract(
        self, gray: NDArray[np.uint8], adapt: bool = True, mask: NDArray[np.uint8] | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.uint8], NDArray[np.uint8], NDArray[np.float32]]:
        """-> keypoints (N,2) f32 pixels, octaves (N,) u8, descriptors (N,32) u8, angles (N,) f32;
        ``mask`` (0 = no keypoints there, e.g. another agent's carrier)."""
        o = self.options
        for _attempt in range(3):
            self._orb.setFastThreshold(int(self.threshold))
            # descriptors with the corners: one image pyramid instead of a second one in compute()
            kps, desc = self._orb.detectAndCompute(gray, mask)
            n_raw = len(kps)
            if not adapt:
                break
            if n_raw < o.n_features and self.threshold > o.min_fast_threshold:
                self.threshold = max(o.min_fast_threshold, int(self.threshold * 0.6))
                log.debug("FAST threshold lowered to %d (%d corners)", self.threshold, n_raw)
                if n_raw < o.n_features // 2:
                    continue  # far too few: detect again at once with the lower threshold
            elif n_raw >= 2 * o.n_features and self.threshold < o.fast_threshold:
                self.threshold = min(o.fast_threshold, self.threshold + 1)
            break
        if n_raw == 0:
            return (
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.uint8),
                np.zeros((0, 32), np.uint8),
                np.zeros(0, np.float32),
            )
        if adapt and o.fast_cell_refill:
            kps, desc = self._refill_sparse_cells(gray, kps, desc, mask)
        chosen = self._grid_select(kps, gray.shape)
        kps, desc = self._as_computed(gray, [kps[i] for i in chosen], desc[chosen])
        if len(kps) == 0:
            return (
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.uint8),
                np.zeros((0, 32), np.uint8),
                np.zeros(0, np.float32),
            )
        octv = np.array([k.octave for k in kps], dtype=np.uint8)
        # OpenCV reports a level-l keypoint at x_l * s, but level pixel x_l sits at x_l * s + (s - 1) / 2
        # in the full image (pixel-centre resizing): remove that bias (1.3 px at level 7)
        s = self.options.scale_factor ** octv.astype(np.float64)
        uv = (_points(kps) + 0.5 * (s - 1.0)[:, None]).astype(np.float32)
        ang = np.array([k.angle for k in kps], dtype=np.float32)
        return uv, octv, desc, ang

    def _cells(self, pts: NDArray[np.float64], shape: tuple[int, ...]) -> NDArray[np.int64]:
        o = self.options
        h, w = shape[:2]
        cx = np.minimum((pts[:, 0] * o.grid_cols / w).astype(int), o.grid_cols - 1)
        cy = np.minimum((pts[:, 1] * o.grid_rows / h).astype(int), o.grid_rows - 1)
        return np.asarray(cy * o.grid_cols + cx, dtype=np.int64)

    def _as_computed(self, gray: U8, kps: list[cv2.KeyPoint], desc: U8) -> tuple[list[cv2.KeyPoint], U8]:
        """The keypoints and descriptors as ``compute(gray, kps)`` returns them: without those within
        ``edgeThreshold`` of the image border, ordered by pyramid level (stably). A descriptor depends on
        its keypoint and the image only, so the rows ``detectAndCompute`` gave are the same."""
        if not kps:
            return kps, desc
        h, w = gray.shape[:2]
        b = self._orb.getEdgeThreshold()
        pts = np.asarray(cv2.KeyPoint.convert(kps), dtype=np.float32).reshape(-1, 2)
        inside = (pts[:, 0] >= b) & (pts[:, 0] < w - b) & (pts[:, 1] >= b) & (pts[:, 1] < h - b)
        octaves = np.array([k.octave for k in kps])
        order = [i for i in np.argsort(octaves, kind="stable") if inside[i]]
        return [kps[i] for i in order], desc[order]

    def _refill_sparse_cells(
        self, gray: U8, kps: tuple[cv2.KeyPoint, ...], desc: U8, mask: U8 | None
    ) -> tuple[tuple[cv2.KeyPoint, ...], U8]:
        """Cells the image-wide threshold starves (a faint, foggy background beside one close, sharp
        object) are detected again at a threshold just above the sensor noise, as ORB-SLAM's
        extractor retries each cell at its minimum threshold."""
        o = self.options
        n_cells = o.grid_cols * o.grid_rows
        cells = self._cells(_points(kps), gray.shape)
        count = np.bincount(cells, minlength=n_cells)
        sparse = count < max(1, o.n_features // n_cells) / 4.0
        if not sparse.any():
            return kps, desc
        th = self._refill_threshold(gray)
        if th >= self.threshold:
            return kps, desc
        h, w = gray.shape[:2]
        cell_mask = np.zeros((o.grid_rows, o.grid_cols), np.uint8)
        cell_mask.flat[np.flatnonzero(sparse)] = 255
        cell_mask = cv2.resize(cell_mask, (w, h), interpolation=cv2.INTER_NEAREST)
        if mask is not None:
            cell_mask = np.minimum(cell_mask, mask)
        self._orb.setFastThreshold(th)
        extra, extra_desc = self._orb.detectAndCompute(gray, cell_mask)
        if not extra:
            return kps, desc
        keep = np.flatnonzero(~sparse[cells])
        new = np.flatnonzero(sparse[self._cells(_points(extra), gray.shape)])
        log.debug("FAST refill at threshold %d: %d corners in %d sparse cells", th, len(new), sparse.sum())
        out = tuple(kps[i] for i in keep) + tuple(extra[i] for i in new)
        return out, np.concatenate([desc[keep], extra_desc[new]])

    def _refill_threshold(self, gray: U8) -> int:
        """A FAST threshold three sigmas of a pixel difference above the image's noise (Immerkaer's
        estimate, with the median so that texture and edges do not count as noise)."""
        o = self.options
        resp = cv2.filter2D(gray[::2, ::2].astype(np.float32), -1, _NOISE_MASK)[1:-1, 1:-1]
        # median |N(0, 6s)| = 0.6745 * 6 s
        sigma = float(np.median(np.abs(resp))) / (6.0 * 0.6745)
        return int(np.clip(round(3.0 * np.sqrt(2.0) * sigma), o.min_fast_threshold, self.threshold))

    def _grid_select(self, kps: tuple[cv2.KeyPoint, ...], shape: tuple[int, ...]) -> NDArray[np.int64]:
        """Indices of the keypoints kept: the best per grid cell, then the best of the rest."""
        o = self.options
        n = len(kps)
        if n <= o.n_features:
            return np.arange(n)
        resp = np.array([k.response for k in kps])
        cell = self._cells(_points(kps), shape)
        order = np.lexsort((-resp, cell))  # by cell, best response first
        cell_sorted = cell[order]
        first = np.searchsorted(cell_sorted, cell_sorted, side="left")
        rank = np.arange(n) - first
        per_cell = max(1, o.n_features // (o.grid_cols * o.grid_rows))
        chosen = order[rank < per_cell]
        if len(chosen) < o.n_features:
            unchosen = np.ones(n, bool)
            unchosen[chosen] = False
            rest = np.flatnonzero(unchosen)
            rest = rest[np.argsort(-resp[rest])][: o.n_features - len(chosen)]
            chosen = np.concatenate([chosen, rest])
        return chosen


def _points(kps: Sequence[cv2.KeyPoint]) -> NDArray[np.float64]:
    """The keypoints' (x, y) (N, 2): OpenCV's float32 values converted in C, not attribute by attribute."""
    return np.asarray(cv2.KeyPoint.convert(kps), dtype=np.float64).reshape(-1, 2)
