"""What the second stage gives out: keyframe poses in the local frame, each segment's ``local_from_vio``,
and any frame's local pose (the per-keyframe correction interpolated in time)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.second_stage.factors import frame_fit, interpolate_se3
from hivemap.client.second_stage.options import SecondStageOptions
from hivemap.maps.geometry import se3_inverse

F64 = NDArray[np.float64]


class StageOutputs:
    """Mixed into :class:`~.stage.SecondStage`, which holds this state."""

    options: SecondStageOptions
    _kfs: dict[int, Any]
    _order: list[int]
    _segment_count: int
    _estimate: dict[int, F64]
    _local_from_vio: dict[int, F64]

    def _update_local_from_vio(self) -> None:
        by_seg: dict[int, list[int]] = {}
        for kf_id in self._order:
            by_seg.setdefault(self._kfs[kf_id].segment, []).append(kf_id)
        for seg, ids in by_seg.items():
            src = np.array([self._kfs[k].vio_from_kf[:3, 3] for k in ids])
            dst = np.array([self._estimate[k][:3, 3] for k in ids])
            k = ids[-1]  # the last keyframe's correction, where there is no geometry for a point fit
            last = self._estimate[k] @ se3_inverse(self._kfs[k].vio_from_kf)
            self._local_from_vio[seg] = frame_fit(src, dst, self.options.gravity_aligned, last)

    def local_from_vio(self, segment: int | None = None) -> F64:
        """Current ``local_from_vio`` (4x4) of a segment (default: the newest one)."""
        if not self._local_from_vio:
            return np.eye(4)
        seg = self._segment_count - 1 if segment is None else segment
        return self._local_from_vio[seg].copy()

    @property
    def keyframe_ids(self) -> list[int]:
        return list(self._order)

    def keyframe_pose(self, kf_id: int) -> F64:
        """Current estimate of ``local_from_kf`` (4x4)."""
        return self._estimate[kf_id].copy()

    def keyframe_segment(self, kf_id: int) -> int:
        return self._kfs[kf_id].segment

    def keyframe_poses(self) -> tuple[F64, F64]:
        """(timestamps (K,), local_from_kf (K, 4, 4)) in insertion order."""
        ts = np.array([self._kfs[k].timestamp for k in self._order])
        poses = np.array([self._estimate[k] for k in self._order]).reshape(-1, 4, 4)
        return ts, poses

    def local_from_frame(
        self, timestamp: float, vio_from_frame: F64, segment: int | None = None, interpolate: bool = True
    ) -> F64:
        """Pose of any frame in the local frame.

        With ``interpolate`` the per-keyframe correction ``local_from_kf @ inv(vio_from_kf)`` is
        interpolated in time between the two neighbouring keyframes of the segment (the nearest one
        outside the keyframes' time span); otherwise ``local_from_vio @ vio_from_frame``.
        """
        vio_from_frame = np.asarray(vio_from_frame, dtype=np.float64).reshape(4, 4)
        seg = self._segment_count - 1 if segment is None else segment
        if not interpolate or not self._order:
            return self.local_from_vio(seg) @ vio_from_frame
        ids = [k for k in self._order if self._kfs[k].segment == seg]
        if not ids:
            return self.local_from_vio(seg) @ vio_from_frame
        ts = np.array([self._kfs[k].timestamp for k in ids])
        order = np.argsort(ts, kind="stable")
        ts = ts[order]
        ids = [ids[i] for i in order]

        def corr(k: int) -> F64:
            return self._estimate[k] @ se3_inverse(self._kfs[k].vio_from_kf)

        j = int(np.searchsorted(ts, timestamp))
        if j <= 0:
            C = corr(ids[0])
        elif j >= len(ids):
            C = corr(ids[-1])
        else:
            t0, t1 = ts[j - 1], ts[j]
            alpha = 0.0 if t1 <= t0 else (timestamp - t0) / (t1 - t0)
            C = interpolate_se3(corr(ids[j - 1]), corr(ids[j]), alpha)
        return C @ vio_from_frame
