"""A tiny self-contained stereo(-inertial) scene for front-end tests and benches.

Ray-casts textured planes (ground + four walls) with OpenCV remapping; textures are multi-octave
value noise (non-repetitive, ORB-friendly).  Independent of ``hivemap.sim`` on purpose, so the
front-end tests have an exact, cheap ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera, StereoRig
from hivemap.maps.geometry import se3, transform_points
from hivemap.maps.markers import Carrier

F64 = NDArray[np.float64]


def _noise_texture(rng: np.random.Generator, h: int, w: int) -> NDArray[np.float32]:
    tex = np.zeros((h, w), np.float32)
    for cell, amp in ((128, 0.6), (32, 1.0), (8, 1.0), (3, 1.0), (1, 0.4)):
        small = rng.random((max(2, h // cell), max(2, w // cell))).astype(np.float32)
        tex += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    tex -= tex.min()
    tex *= 230.0 / max(float(tex.max()), 1e-6)
    return np.asarray(cv2.GaussianBlur(tex + 15.0, (3, 3), 0.7), dtype=np.float32)


@dataclass
class _Plane:
    origin: F64  # world point of texture (0, 0)
    ax_u: F64  # unit world direction of texture u
    ax_v: F64  # unit world direction of texture v
    size: tuple[float, float]  # metres along u, v
    tex: NDArray[np.float32]
    px_per_m: float
    one_sided: bool = False  # seen only from the side u x v points away from (a marker's face)


class SyntheticScene:
    """Ground (z = 0) of ``size`` metres + walls ``wall_h`` high around it, z-up world."""

    def __init__(
        self, seed: int = 0, size: float = 50.0, wall_h: float = 10.0, px_per_m: float = 60.0
    ) -> None:
        rng = np.random.default_rng(seed)
        h = size / 2
        ex, ey, ez = np.eye(3)
        specs = [
            (np.array([-h, -h, 0.0]), ex, ey, (size, size)),
            (np.array([-h, h, 0.0]), ex, ez, (size, wall_h)),
            (np.array([-h, -h, 0.0]), ex, ez, (size, wall_h)),
            (np.array([h, -h, 0.0]), ey, ez, (size, wall_h)),
            (np.array([-h, -h, 0.0]), ey, ez, (size, wall_h)),
        ]
        self._rays: dict[PinholeCamera, F64] = {}
        self.planes = []
        for o, u, v, sz in specs:
            tex = _noise_texture(rng, int(sz[1] * px_per_m), int(sz[0] * px_per_m))
            self.planes.append(_Plane(o, u, v, sz, tex, px_per_m))

    def render(self, camera: PinholeCamera, world_from_cam: F64) -> NDArray[np.uint8]:
        """Gray image (H,W) of the scene (no distortion support needed for tests: dist must be 0)."""
        H, W = camera.height, camera.width
        rays_c = self._rays.get(camera)
        if rays_c is None:  # per camera: undistorting every pixel costs more than the rest of a render
            uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            if camera.has_distortion:  # rays of the distorted pixels
                xy = camera.undistort_to_normalized(np.stack([uu.ravel(), vv.ravel()], 1)).reshape(H, W, 2)
                rays_c = np.concatenate([xy, np.ones((H, W, 1))], -1)
            else:
                xn, yn = (uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy
                rays_c = np.stack([xn, yn, np.ones_like(uu)], -1)
            self._rays[camera] = rays_c
        R, c = world_from_cam[:3, :3], world_from_cam[:3, 3]
        rays_flat = rays_c.reshape(-1, 3)
        rays = rays_flat @ R.T
        best_t = np.full(len(rays), np.inf)
        img = np.zeros(len(rays), np.float32)
        for p in self.planes:
            idx = self._window(p, rays_flat, R, c)
            if idx is not None and not len(idx):
                continue
            r = rays if idx is None else rays[idx]
            n = np.cross(p.ax_u, p.ax_v)
            den = r @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((p.origin - c) @ n) / den
            hit = c + r * t[:, None]
            a = (hit - p.origin) @ p.ax_u
            b = (hit - p.origin) @ p.ax_v
            bt = best_t if idx is None else best_t[idx]
            ok = (t > 0.05) & (t < bt) & (a >= 0) & (a <= p.size[0]) & (b >= 0) & (b <= p.size[1])
            if p.one_sided:
                ok &= den > 0
            if not ok.any():
                continue
            val = _sample(p.tex, a * p.px_per_m, b * p.px_per_m)
            sel = np.flatnonzero(ok) if idx is None else idx[ok]
            img[sel] = val[ok]
            best_t[sel] = t[ok]
        self.last_depth = (best_t * rays_c.reshape(-1, 3)[:, 2]).reshape(H, W)  # z in the camera, metres
        return np.clip(img, 0, 255).astype(np.uint8).reshape(H, W)

    @staticmethod
    def _window(p: _Plane, rays_c: F64, R: F64, c: F64) -> NDArray[np.int64] | None:
        """The pixels whose rays can hit a plane wholly in front of the camera (inside its corners'
        bounding box in normalized coordinates), or None (every pixel) for one that is not."""
        su, sv = p.size
        corners = p.origin + np.array([[0, 0], [su, 0], [su, sv], [0, sv]]) @ np.stack([p.ax_u, p.ax_v])
        cc = (corners - c) @ R
        if (cc[:, 2] <= 0.05).any():
            return None
        xy = cc[:, :2] / cc[:, 2:]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        x, y = rays_c[:, 0], rays_c[:, 1]
        return np.flatnonzero((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]))

    def add_marker_carrier(self, carrier: Carrier, world_from_body: F64, cell_px: int = 12) -> None:
        """Draw ``carrier``'s markers (with a one-cell white quiet zone) at the carrier's body pose."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, carrier.dictionary))
        cells = dictionary.markerSize + 2
        for m in carrier.markers:
            c = transform_points(world_from_body, m.corners_body)
            ax_u = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
            ax_v = (c[3] - c[0]) / np.linalg.norm(c[3] - c[0])
            cell_m = m.size_m / cells
            code = cv2.aruco.generateImageMarker(dictionary, m.marker_id, cells * cell_px, borderBits=1)
            tex = np.full(((cells + 2) * cell_px,) * 2, 255.0, np.float32)
            tex[cell_px:-cell_px, cell_px:-cell_px] = code
            side = m.size_m + 2 * cell_m
            ppm = len(tex) / side
            # remap samples texel centres at integers: the texture's edge is half a texel before texel 0
            origin = c[0] - cell_m * (ax_u + ax_v) + 0.5 / ppm * (ax_u + ax_v)
            self.planes.append(_Plane(origin, ax_u, ax_v, (side, side), tex, ppm, True))


def _sample(tex: NDArray[np.float32], x: F64, y: F64) -> NDArray[np.float32]:
    """Bilinear texture values at (x, y) (any count: cv2.remap takes maps below 32767 columns)."""
    n, w = len(x), 512
    pad = -n % w
    mx = np.pad(x.astype(np.float32), (0, pad)).reshape(-1, w)
    my = np.pad(y.astype(np.float32), (0, pad)).reshape(-1, w)
    out = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).reshape(-1)[:n]
    return np.asarray(out, dtype=np.float32)


def body_from_cam_pitched(pitch_down_deg: float) -> F64:
    """Body FLU (x forward, y left, z up) from an OpenCV camera looking forward, pitched down."""
    th = np.radians(pitch_down_deg)
    z = np.array([np.cos(th), 0.0, -np.sin(th)])
    x = np.array([0.0, -1.0, 0.0])
    y = np.cross(z, x)
    return se3(np.stack([x, y, z], 1), np.zeros(3))


def make_rig(
    width: int = 640,
    height: int = 480,
    f: float = 420.0,
    baseline: float = 0.12,
    pitch: float = 30.0,
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> StereoRig:
    cam = PinholeCamera(width, height, f, f, width / 2 - 0.5, height / 2 - 0.5, dist)
    b_l = body_from_cam_pitched(pitch)
    b_r = b_l @ se3(np.eye(3), np.array([baseline, 0.0, 0.0]))
    return StereoRig(cam, cam, b_l, b_r)


@dataclass
class SyntheticSequence:
    times: F64
    world_from_body: F64  # (N,4,4)
    imu: F64  # (M,7) t, gyro, acc (body)
    rig: StereoRig
    scene: SyntheticScene
    velocity_w: F64  # (N,3) of the body, world frame

    def images(self, i: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        T_wb = self.world_from_body[i]
        left = self.scene.render(self.rig.left, T_wb @ self.rig.body_from_left)
        right = self.scene.render(self.rig.right, T_wb @ self.rig.body_from_right)
        return left, right

    def imu_between(self, t0: float | None, t1: float) -> F64:
        lo = -np.inf if t0 is None else t0
        m = (self.imu[:, 0] > lo) & (self.imu[:, 0] <= t1)
        return self.imu[m]


def make_sequence(
    n_frames: int = 60,
    rate: float = 20.0,
    seed: int = 0,
    radius: float = 12.0,
    speed: float = 2.0,
    height: float = 3.0,
    pitch: float = 30.0,
    baseline: float = 0.12,
    imu_rate: float = 200.0,
    scene_size: float = 50.0,
    focal: float = 420.0,
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    surge_m: float = 0.0,
) -> SyntheticSequence:
    """Body on a circle of ``radius`` at ``height`` (with a gentle bobbing), yaw along the path.

    ``surge_m``: amplitude of a speed oscillation (arc length ``speed t + surge_m sin(t)``), so that a
    constant-velocity prediction is wrong where the IMU's is not.
    """
    rig = make_rig(baseline=baseline, pitch=pitch, f=focal, dist=dist)

    def pose(t: F64) -> tuple[F64, F64]:
        ang = (speed * t + surge_m * np.sin(t)) / radius
        p = np.stack(
            [radius * np.cos(ang) - radius, radius * np.sin(ang), height + 0.3 * np.sin(0.8 * t)], -1
        )
        yaw = ang + np.pi / 2
        return p, yaw

    times = np.arange(n_frames) / rate
    p, yaw = pose(times)
    Ts = np.stack([se3(_rz(y), q) for q, y in zip(p, yaw, strict=True)])
    ti = np.arange(0.0, times[-1] + 1e-9, 1.0 / imu_rate)
    dt = 1e-4
    pm, _ = pose(ti - dt)
    p0, y0 = pose(ti)
    pp, _ = pose(ti + dt)
    acc_w = (pp - 2 * p0 + pm) / dt**2 + np.array([0.0, 0.0, 9.81])
    acc_b = np.stack([_rz(y).T @ a for a, y in zip(acc_w, y0, strict=True)])
    gyro = np.zeros((len(ti), 3))
    gyro[:, 2] = (speed + surge_m * np.cos(ti)) / radius
    imu = np.concatenate([ti[:, None], gyro, acc_b], 1)
    vel = (pose(times + dt)[0] - pose(times - dt)[0]) / (2 * dt)
    scene = SyntheticScene(seed, size=scene_size, px_per_m=40.0 if scene_size > 60 else 60.0)
    return SyntheticSequence(times, Ts, imu, rig, scene, vel)


def _rz(a: float) -> F64:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


__all__ = [
    "SyntheticScene",
    "SyntheticSequence",
    "make_rig",
    "make_sequence",
    "body_from_cam_pitched",
]
