"""Front-end map state: frames, keyframes and a growable map-point store (VIO frame)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from hivemap.maps.geometry import se3_inverse

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def hamming(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.int64]:
    """Hamming distance of 256-bit descriptors along the last axis (broadcasting)."""
    # on four 64-bit words per descriptor: an eighth of the popcounts and sums of bytes
    a64 = np.ascontiguousarray(a, np.uint8).view(np.uint64)
    b64 = np.ascontiguousarray(b, np.uint8).view(np.uint64)
    return np.bitwise_count(np.bitwise_xor(a64, b64)).sum(axis=-1, dtype=np.int64)


@dataclass
class Frame:
    """One stereo frame's features.  ``meas`` (N,3) = undistorted left pixels + virtual right u (NaN)."""

    t: float
    uv: NDArray[np.float32]  # raw (distorted) left pixels
    octaves: NDArray[np.uint8]
    desc: NDArray[np.uint8]
    kpu: F64  # undistorted pixels (N,2)
    pts_cam: F64  # stereo points in the left camera (N,3), NaN if none
    meas: F64
    inv_sigma2: F64
    point_ids: I64
    T_cw: F64 = field(default_factory=lambda: np.eye(4))
    _tree: cKDTree | None = None

    @property
    def n(self) -> int:
        return len(self.uv)

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.kpu if self.n else np.zeros((1, 2)) + 1e9)
        return self._tree

    @property
    def T_wc(self) -> F64:
        return se3_inverse(self.T_cw)


@dataclass
class KeyframeData:
    id: int
    session: int
    frame: Frame
    T_cw: F64
    gnss_epoch: bool = False
    emitted: bool = False
    prev_id: int | None = None
    rel_cov_cam: F64 | None = None  # 6x6 [rot, trans], right perturbation of world_from_cam
    # first keyframe of a session after a loss: this session's frame in the previous one's + [m, deg]
    prev_session_from_world: F64 | None = None
    prev_session_sigma: tuple[float, float] | None = None
    # [m, deg]: error weak or lost tracking since the previous keyframe added (None: tracked well)
    odom_sigma: tuple[float, float] | None = None
    bow: Any = None  # bag-of-words vector, computed when relocalisation first needs it
    # inertial state (with an IMU): preintegration from the previous keyframe, world velocity of the
    # body and the biases [gyro, accel], refined by the visual-inertial local BA
    preint: Any = None
    v_w: F64 | None = None
    bias: F64 | None = None
    vi_refined: bool = False  # v_w / bias estimated by a visual-inertial local BA

    @property
    def T_wc(self) -> F64:
        return se3_inverse(self.T_cw)

    @property
    def timestamp(self) -> float:
        return self.frame.t


class PointStore:
    """Map points in growable arrays (ids are indices) + per-point observation dicts."""

    def __init__(self, capacity: int = 4096) -> None:
        self.n = 0
        self.xyz = np.zeros((capacity, 3))
        self.desc = np.zeros((capacity, 32), np.uint8)
        self.alive = np.zeros(capacity, bool)
        self.visible = np.zeros(capacity, np.int64)
        self.found = np.zeros(capacity, np.int64)
        self.first_kf = np.zeros(capacity, np.int64)
        self.emitted = np.zeros(capacity, bool)
        self.sent_xyz = np.zeros((capacity, 3))  # the position last streamed (emitted points)
        self.obs: list[dict[int, int]] = []

    def _grow(self, need: int) -> None:
        cap = len(self.alive)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("xyz", "desc", "alive", "visible", "found", "first_kf", "emitted", "sent_xyz"):
            a = getattr(self, name)
            b = np.zeros((new, *a.shape[1:]), a.dtype)
            b[:cap] = a
            setattr(self, name, b)

    def add(self, xyz: F64, desc: NDArray[np.uint8], kf_id: int) -> I64:
        m = len(xyz)
        self._grow(self.n + m)
        ids = np.arange(self.n, self.n + m)
        self.xyz[ids] = xyz
        self.desc[ids] = desc
        self.alive[ids] = True
        self.visible[ids] = 1
        self.found[ids] = 1
        self.first_kf[ids] = kf_id
        self.obs.extend({} for _ in range(m))
        self.n += m
        return ids

    def alive_ids(self) -> I64:
        return np.flatnonzero(self.alive[: self.n])
