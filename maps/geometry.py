"""SE(3) and Sim(3) helpers over numpy arrays.

Conventions (project-wide):
- Poses are 4x4 float64 matrices named by frames: ``world_from_cam`` maps points in the camera
  frame to the world frame: ``p_world = R @ p_cam + t``.
- Quaternions are (w, x, y, z), Hamilton, unit norm.
- ``Sim3`` follows pycolmap's ``Sim3d``: ``p -> s * R @ p + t``.  gtsam's ``Similarity3(R, t, s)``
  maps ``p -> s * (R @ p + t)``, so ``t_gtsam = t / s`` (see ``Sim3.to_gtsam``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]


def se3(R: F64, t: F64) -> F64:
    """Build a 4x4 SE(3) matrix from a 3x3 rotation and a 3-vector."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def se3_inverse(T: F64) -> F64:
    """Inverse of a 4x4 SE(3) matrix (exact, without a general matrix inverse)."""
    R = T[:3, :3]
    t = T[:3, 3]
    return se3(R.T, -R.T @ t)


def transform_points(T: F64, pts: F64) -> F64:
    """Apply a 4x4 SE(3) (or similarity) matrix to points of shape (N, 3); returns (N, 3)."""
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def quat_wxyz_from_rotmat(R: F64) -> F64:
    """Rotation matrix (3, 3) -> unit quaternion (w, x, y, z) with w >= 0."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def rotmat_from_quat_wxyz(q: F64) -> F64:
    """Unit quaternion (w, x, y, z) -> rotation matrix (3, 3)."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def so3_exp(w: F64) -> F64:
    """Rotation vector (3,) -> rotation matrix (3, 3)."""
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def so3_log(R: F64) -> F64:
    """Rotation matrix (3, 3) -> rotation vector (3,)."""
    return Rotation.from_matrix(R).as_rotvec()


def nearest_rotation(R: F64, tol: float = 1e-9) -> F64:
    """``R`` itself when it is a rotation to ``tol``, else the nearest rotation (SVD projection).

    Poses are composed thousands of times on the server (merges, pose graphs, GNSS stages): without this
    the rounding error of each composition is carried and, once a 3x3 block is off SO(3), gtsam's
    factors amplify it (factory01: x3 per GNSS stage, rotations scaled by 1e4 after 15 stages).
    """
    R = np.asarray(R, dtype=np.float64)
    if np.abs(R @ R.T - np.eye(3)).max() <= tol:
        return R
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return np.asarray(U @ D @ Vt, dtype=np.float64)


def nearest_rotations(R: F64, tol: float = 1e-9) -> F64:
    """:func:`nearest_rotation` of a stack (n, 3, 3): the same result per matrix, in one batched SVD."""
    R = np.array(R, dtype=np.float64).reshape(-1, 3, 3)
    off = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2)) > tol
    if np.any(off):
        U, _, Vt = np.linalg.svd(R[off])
        d = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= d[:, None]  # U @ diag(1, 1, d) @ Vt
        R[off] = U @ Vt
    return R


def relative_poses(world_from_i: F64, world_from_j: F64) -> list[Sim3]:
    """``i_from_j`` of each pair of rigid poses (n, 4, 4) as Sim3s with scale 1: what
    ``Sim3.from_se3(se3_inverse(a) @ b)`` gives per pair, batched (a pose graph has tens of thousands)."""
    a = np.asarray(world_from_i, dtype=np.float64).reshape(-1, 4, 4)
    b = np.asarray(world_from_j, dtype=np.float64).reshape(-1, 4, 4)
    Rt = a[:, :3, :3].transpose(0, 2, 1)
    R = nearest_rotations(Rt @ b[:, :3, :3])
    t = np.einsum("nij,nj->ni", Rt, b[:, :3, 3] - a[:, :3, 3])
    return [Sim3._trusted(R[n], t[n]) for n in range(len(R))]


def rotation_angle_deg(R: F64) -> float:
    """Angle of a rotation matrix in degrees (0..180)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class Sim3:
    """A similarity transform ``p -> s * R @ p + t`` (pycolmap ``Sim3d`` convention).

    ``R``: (3, 3) rotation, ``t``: (3,) translation, ``s``: positive scale.
    """

    R: F64
    t: F64
    s: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", nearest_rotation(np.asarray(self.R, dtype=np.float64).reshape(3, 3)))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))
        object.__setattr__(self, "s", float(self.s))
        if not self.s > 0 or not np.isfinite(self.s):
            raise ValueError(f"Sim3 scale must be finite and > 0, got {self.s}")

    @staticmethod
    def _trusted(R: F64, t: F64, s: float = 1.0) -> Sim3:
        """A Sim3 of an ``R`` already on SO(3) (float64, 3x3) and ``t`` (3,): :meth:`__post_init__`'s
        checks skipped, for batches that made them already (:func:`relative_poses`)."""
        out = object.__new__(Sim3)
        object.__setattr__(out, "R", R)
        object.__setattr__(out, "t", t)
        object.__setattr__(out, "s", float(s))
        return out

    @staticmethod
    def identity() -> Sim3:
        return Sim3(np.eye(3), np.zeros(3), 1.0)

    @staticmethod
    def from_se3(T: F64) -> Sim3:
        """A rigid 4x4 transform as a Sim3 with scale 1."""
        return Sim3(T[:3, :3], T[:3, 3], 1.0)

    @staticmethod
    def from_matrix(M: F64) -> Sim3:
        """4x4 matrix ``[[sR, t], [0, 1]]`` -> Sim3."""
        A = np.asarray(M, dtype=np.float64)[:3, :3]
        s = float(np.cbrt(np.linalg.det(A)))
        return Sim3(A / s, M[:3, 3], s)

    def matrix(self) -> F64:
        """4x4 matrix ``[[sR, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def apply(self, pts: F64) -> F64:
        """Transform points of shape (N, 3) or (3,)."""
        pts = np.asarray(pts, dtype=np.float64)
        return self.s * (pts @ self.R.T) + self.t

    def inverse(self) -> Sim3:
        Rinv = self.R.T
        return Sim3(Rinv, -(Rinv @ self.t) / self.s, 1.0 / self.s)

    def __matmul__(self, other: Sim3) -> Sim3:
        """Composition: ``(a @ b).apply(p) == a.apply(b.apply(p))``."""
        return Sim3(self.R @ other.R, self.s * (self.R @ other.t) + self.t, self.s * other.s)

    def transform_pose(self, world_from_cam: F64) -> F64:
        """Move a camera pose (4x4 SE(3)) by this similarity: the result stays rigid.

        The camera centre is mapped by the similarity and the orientation rotated by ``R``.
        """
        out = np.eye(4)
        out[:3, :3] = nearest_rotation(self.R @ world_from_cam[:3, :3])
        out[:3, 3] = self.apply(world_from_cam[:3, 3])
        return out

    # --- library conversions -------------------------------------------------------------
    def to_gtsam(self) -> Any:
        """-> ``gtsam.Similarity3`` (which maps ``p -> s (R p + t)``, hence ``t / s``)."""
        import gtsam

        return gtsam.Similarity3(gtsam.Rot3(self.R), gtsam.Point3(*(self.t / self.s)), self.s)

    @staticmethod
    def from_gtsam(sim: Any) -> Sim3:
        s = float(sim.scale())
        return Sim3(sim.rotation().matrix(), np.asarray(sim.translation()) * s, s)

    def to_pycolmap(self) -> Any:
        """-> ``pycolmap.Sim3d`` (same convention)."""
        import pycolmap

        x, y, z, w = Rotation.from_matrix(self.R).as_quat()
        return pycolmap.Sim3d(self.s, pycolmap.Rotation3d(np.array([x, y, z, w])), self.t)

    @staticmethod
    def from_pycolmap(sim: Any) -> Sim3:
        M = np.asarray(sim.matrix())
        return Sim3.from_matrix(np.vstack([M[:3, :4], [0, 0, 0, 1]]))


def rotation_angles(A: F64, B: F64) -> F64:
    """Angle (rad) of each ``A[i]^T @ B[i]`` for stacks of rotations (n, 3, 3): :func:`rotation_angle_deg`
    batched (in radians)."""
    c = (np.trace(np.transpose(A, (0, 2, 1)) @ B, axis1=1, axis2=2) - 1.0) / 2.0
    return np.asarray(np.arccos(np.clip(c, -1.0, 1.0)), dtype=np.float64)


def sim3_arrays(sims: Sequence[Sim3]) -> tuple[F64, F64, F64]:
    """(R (n, 3, 3), t (n, 3), s (n,)) of a list of similarities, for the batched helpers."""
    R = np.array([c.R for c in sims], dtype=np.float64).reshape(-1, 3, 3)
    t = np.array([c.t for c in sims], dtype=np.float64).reshape(-1, 3)
    return R, t, np.array([c.s for c in sims], dtype=np.float64)


def transform_poses(R: F64, t: F64, s: F64, W: F64) -> F64:
    """``Sim3(R[i], t[i], s[i]).transform_pose(W[i])`` for a stack of rigid poses ``W`` (n, 4, 4)."""
    out = np.zeros_like(W)
    out[:, :3, :3] = nearest_rotations(R @ W[:, :3, :3])
    out[:, :3, 3] = s[:, None] * np.einsum("nij,nj->ni", R, W[:, :3, 3]) + t
    out[:, 3, 3] = 1.0
    return out


def rotation_between(a: F64, b: F64) -> F64:
    """The smallest rotation taking direction ``a`` onto direction ``b`` (both (3,), any length)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    R, _ = Rotation.align_vectors(b[None], a[None])  # one pair: scipy gives the shortest arc
    return np.asarray(R.as_matrix(), dtype=np.float64)


def levelled_similarity(
    src: F64,
    dst: F64,
    up_src: F64,
    up_dst: F64,
    with_scale: bool = True,
    weights: F64 | None = None,
    level: F64 | None = None,
) -> Sim3:
    """Least-squares ``dst ~ s R src + t`` with ``R`` constrained to take ``up_src`` onto ``up_dst``.

    The 4-DoF (5 with scale) Umeyama of visual-inertial maps: roll and pitch are known from gravity in
    both frames, so only the rotation about the up axis is fitted to the points (2D Procrustes in the
    plane normal to ``up_dst``). Points (N, 3), N >= 1; s = 1 without ``with_scale``; ``weights`` (N,)
    of the pairs' squared residuals (None: equal); ``level``: ``rotation_between(up_src, up_dst)`` if the
    caller has it (fits repeated with the same up directions).
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    R0 = rotation_between(up_src, up_dst) if level is None else np.asarray(level, dtype=np.float64)
    axis = np.asarray(up_dst, dtype=np.float64) / np.linalg.norm(up_dst)
    a = (src - ms) @ R0.T
    b = dst - md
    # the yaw about ``axis`` maximising sum(w b . Rz a): atan2 of the weighted cross and dot in the plane
    a_perp = a - np.outer(a @ axis, axis)
    b_perp = b - np.outer(b @ axis, axis)
    s_ = float(w @ (np.cross(a_perp, b_perp) @ axis))
    c_ = float(w @ np.sum(a_perp * b_perp, axis=1))
    yaw = float(np.arctan2(s_, c_)) if abs(s_) + abs(c_) > 1e-12 else 0.0
    R = so3_exp(axis * yaw) @ R0
    s = 1.0
    if with_scale:
        ra = a @ so3_exp(axis * yaw).T
        den = float(w @ np.sum(ra * ra, axis=1))
        s = float(w @ np.sum(ra * b, axis=1) / den) if den > 1e-12 else 1.0
    return Sim3(R, md - s * R @ ms, s)
