"""gtsam keys and noise models of the second stage, and the alignments and interpolation it uses."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from hivemap.maps.geometry import levelled_similarity, se3

F64 = NDArray[np.float64]


def _key(kf_id: int) -> int:
    import gtsam

    return int(gtsam.symbol("k", int(kf_id)))


def _vkey(kf_id: int) -> int:
    import gtsam

    return int(gtsam.symbol("v", int(kf_id)))


def _okey() -> int:
    import gtsam

    return int(gtsam.symbol("o", 0))


def _bkey(kf_id: int) -> int:
    import gtsam

    return int(gtsam.symbol("b", int(kf_id)))


def _diag(sigmas: F64) -> Any:
    import gtsam

    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))


def _gaussian(cov: F64) -> Any:
    import gtsam

    cov = np.asarray(cov, dtype=np.float64)
    cov = 0.5 * (cov + cov.T)
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def yaw_translation_alignment(src: F64, dst: F64) -> F64:
    """Least-squares ``dst ~ Rz(yaw) src + t`` for points (N, 3); returns the 4x4 transform.

    The gravity-aligned case of Umeyama/Kabsch: rotation about z only, no scale. N >= 1
    (with one point, or points on a vertical line, the yaw is 0).
    """
    z = np.array([0.0, 0.0, 1.0])
    sim = levelled_similarity(src, dst, z, z, with_scale=False)
    return se3(sim.R, sim.t)


def rigid_alignment(src: F64, dst: F64) -> F64:
    """Least-squares SE(3) ``dst ~ R src + t`` (Umeyama without scale, evo's implementation)."""
    from evo.core.geometry import umeyama_alignment

    R, t, _ = umeyama_alignment(np.asarray(src, float).T, np.asarray(dst, float).T, False)
    return se3(R, t)


def interpolate_se3(a: F64, b: F64, alpha: float) -> F64:
    """Interpolate two 4x4 rigid transforms: slerp on rotation, linear on translation."""
    alpha = float(np.clip(alpha, 0.0, 1.0))
    rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
    R = Slerp([0.0, 1.0], rots)([alpha]).as_matrix()[0]
    return se3(R, (1.0 - alpha) * a[:3, 3] + alpha * b[:3, 3])


def frame_fit(src: F64, dst: F64, gravity_aligned: bool, fallback: F64) -> F64:
    """The transform taking positions ``src`` (K, 3) onto ``dst``: yaw and translation when gravity-aligned
    (or with fewer than 3), else rigid; ``fallback`` (e.g. the last keyframe's own) when ``src`` spreads
    less than a millimetre, which leaves no geometry for a point fit."""
    spread = float(np.max(np.linalg.norm(src - src[0], axis=1))) if len(src) > 1 else 0.0
    if spread < 1e-3:
        return fallback
    if gravity_aligned or len(src) < 3:
        return yaw_translation_alignment(src, dst)
    return rigid_alignment(src, dst)
