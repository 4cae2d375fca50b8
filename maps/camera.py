"""Camera models: pinhole with radial-tangential (k1, k2, p1, p2) distortion, and a stereo rig.

Pixel convention: (u, v) with the centre of the top-left pixel at (0, 0) (OpenCV, EuRoC).
Camera frame: x right, y down, z forward (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera with radial-tangential distortion (OpenCV ``k1, k2, p1, p2``)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> F64:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> F64:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def distort_normalized(self, xy: F64) -> F64:
        """Apply distortion to normalized coordinates (N, 2) -> distorted normalized (N, 2)."""
        k1, k2, p1, p2 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, pts_in_cam: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Project (N, 3) camera-frame points -> pixels (N, 2) (distorted) and a mask z > 0."""
        pts = np.asarray(pts_in_cam, dtype=np.float64).reshape(-1, 3)
        z = pts[:, 2]
        valid = z > 1e-9
        zs = np.where(valid, z, 1.0)
        xy = pts[:, :2] / zs[:, None]
        if self.has_distortion:
            xy = self.distort_normalized(xy)
        uv = np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)
        return uv, valid

    def project_jacobian(self, pts_in_cam: F64) -> NDArray[np.float64]:
        """d pixel / d point of :meth:`project` at (N, 3) camera-frame points -> (N, 2, 3); zero where
        ``project`` reports the point invalid (its pixel then does not depend on the point)."""
        pts = np.asarray(pts_in_cam, dtype=np.float64).reshape(-1, 3)
        z = pts[:, 2]
        valid = z > 1e-9
        iz = np.where(valid, 1.0 / np.where(valid, z, 1.0), 0.0)
        x, y = pts[:, 0] * iz, pts[:, 1] * iz
        dn = np.zeros((len(pts), 2, 3))  # d normalized / d point
        dn[:, 0, 0] = dn[:, 1, 1] = iz
        dn[:, 0, 2], dn[:, 1, 2] = -x * iz, -y * iz
        if self.has_distortion:
            k1, k2, p1, p2 = self.dist
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            dr = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d x = dr * x
            dd = np.empty((len(pts), 2, 2))  # d distorted / d normalized
            dd[:, 0, 0] = radial + dr * x * x + 2 * p1 * y + 6 * p2 * x
            dd[:, 0, 1] = dr * x * y + 2 * p1 * x + 2 * p2 * y
            dd[:, 1, 0] = dr * x * y + 2 * p1 * x + 2 * p2 * y
            dd[:, 1, 1] = radial + dr * y * y + 6 * p1 * y + 2 * p2 * x
            dn = dd @ dn
        dn[:, 0, :] *= self.fx
        dn[:, 1, :] *= self.fy
        return dn

    def in_image(self, uv: F64, margin: float = 0.0) -> NDArray[np.bool_]:
        """Mask of pixels (N, 2) inside the image (with an optional margin)."""
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 0] <= self.width - 1 - margin)
            & (uv[:, 1] <= self.height - 1 - margin)
        )

    def undistort_to_normalized(self, uv: F64) -> F64:
        """Distorted pixels (N, 2) -> undistorted normalized coordinates (N, 2) (cv2, iterative)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if len(uv) == 0:
            return np.zeros((0, 2))
        if not self.has_distortion:
            xy = (uv.reshape(-1, 2) - [self.cx, self.cy]) / [self.fx, self.fy]
            return np.asarray(xy, dtype=np.float64)
        # OpenCV's default (5 fixed-point iterations) leaves up to 0.3 px in the corners of a EuRoC-like
        # lens; 30 iterations converge to ~1e-12 px (measured, 20k points in 8 ms)
        eye = np.eye(3)
        out = cv2.undistortPoints(uv, self.K, self.dist_coeffs, None, eye, eye, _UNDISTORT_CRITERIA)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def undistort_pixels(self, uv: F64) -> F64:
        """Distorted pixels (N, 2) -> undistorted pixels (N, 2) under the same K."""
        xy = self.undistort_to_normalized(uv)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)

    def bearing(self, uv: F64) -> F64:
        """Distorted pixels (N, 2) -> unit bearing vectors (N, 3) in the camera frame."""
        xy = self.undistort_to_normalized(uv)
        b = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def to_dict(self) -> dict[str, object]:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "dist": list(self.dist),
        }

    @staticmethod
    def from_dict(d: dict[str, object]) -> PinholeCamera:
        dist = tuple(float(x) for x in d.get("dist", (0.0, 0.0, 0.0, 0.0)))  # type: ignore[attr-defined]
        if len(dist) != 4:
            raise ValueError(f"camera 'dist' must have 4 coefficients (k1, k2, p1, p2), got {len(dist)}")
        return PinholeCamera(
            width=int(d["width"]),  # type: ignore[call-overload]
            height=int(d["height"]),  # type: ignore[call-overload]
            fx=float(d["fx"]),  # type: ignore[arg-type]
            fy=float(d["fy"]),  # type: ignore[arg-type]
            cx=float(d["cx"]),  # type: ignore[arg-type]
            cy=float(d["cy"]),  # type: ignore[arg-type]
            dist=dist,  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class StereoRig:
    """Two cameras and their extrinsics.

    ``body_from_left`` / ``body_from_right``: 4x4 SE(3) (EuRoC's ``T_BS`` per sensor).
    For a rectified horizontal rig ``right_from_left`` is a pure translation ``[-b, 0, 0]``.
    """

    left: PinholeCamera
    right: PinholeCamera
    body_from_left: F64 = field(default_factory=lambda: np.eye(4))
    body_from_right: F64 = field(default_factory=lambda: np.eye(4))

    @property
    def right_from_left(self) -> F64:
        from hivemap.maps.geometry import se3_inverse

        return se3_inverse(self.body_from_right) @ self.body_from_left

    @property
    def baseline(self) -> float:
        """Distance between the two optical centres, metres."""
        return float(np.linalg.norm(self.right_from_left[:3, 3]))
