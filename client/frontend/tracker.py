"""The front-end: stereo ORB tracking, keyframes, local mapping, local BA, relocalisation, IMU."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.features import OrbExtractor
from hivemap.client.frontend.mapdata import Frame, KeyframeData, PointStore, hamming
from hivemap.client.frontend.optim import (
    BAProblem,
    Intrinsics,
    bundle_adjust,
    chi2_of,
    chi2_thresholds,
    optimize_pose,
    pose_hessian,
    project,
)
from hivemap.client.frontend.options import FrontendOptions
from hivemap.client.frontend.stereo import StereoMatcher
from hivemap.maps.camera import StereoRig
from hivemap.maps.geometry import se3, se3_inverse, so3_exp

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class TrackingState(StrEnum):
    INITIALIZING = "initializing"
    OK = "ok"
    RELOCALIZED = "relocalized"
    LOST = "lost"
    NEW_MAP = "new_map"


@dataclass(frozen=True)
class FrameResult:
    """Result of one ``Frontend.process`` call.  Poses are in the VIO frame of ``session``."""

    t: float
    state: TrackingState
    world_from_cam: F64
    world_from_body: F64
    n_tracked: int
    session: int
    new_keyframe_id: int | None = None


@dataclass(frozen=True)
class KeyframeEvent:
    """A new keyframe ready for the link / second stage (emitted once, after ``emit_delay_keyframes``).

    ``rel_body`` = prev_body_from_body (4x4) with ``rel_cov`` (6x6, gtsam order [rot, trans], right
    perturbation of ``rel_body``), both None for the first keyframe of a session.
    New points: those its keypoints reference that were not emitted before.
    """

    session: int
    kf_id: int
    timestamp: float
    world_from_cam: F64
    world_from_body: F64
    keypoints: NDArray[np.float32]
    octaves: NDArray[np.uint8]
    descriptors: NDArray[np.uint8]
    point_ids: I64
    prev_kf_id: int | None
    rel_body: F64 | None
    rel_cov: F64 | None
    gnss_epoch: bool
    new_point_ids: I64
    new_point_xyz: F64
    new_point_descriptors: NDArray[np.uint8]


@dataclass(frozen=True)
class PoseUpdateEvent:
    """Poses/points (already emitted) changed by local BA or gravity alignment."""

    session: int
    kf_ids: I64
    world_from_cam: F64  # (K,4,4)
    point_ids: I64
    xyz: F64


@dataclass(frozen=True)
class NewSessionEvent:
    """Tracking was lost and relocalisation failed: a new map (session) starts."""

    old_session: int
    session: int
    t: float


Event = KeyframeEvent | PoseUpdateEvent | NewSessionEvent


@dataclass
class FrontendStats:
    frames: int = 0
    keyframes: int = 0
    lost_frames: int = 0
    relocalizations: int = 0
    sessions: int = 1
    timing: dict[str, float] = field(default_factory=dict)


class _ImuState:
    """Gyro preintegration (gtsam) between frames + accelerometer buffer for gravity alignment."""

    def __init__(self, params: dict[str, float] | None) -> None:
        import gtsam

        p = params or {}
        self.gtsam = gtsam
        self.pp = gtsam.PreintegrationParams.MakeSharedU(9.81)
        self.pp.setGyroscopeCovariance(np.eye(3) * float(p.get("gyroscope_noise_density", 1.7e-4)) ** 2)
        self.pp.setAccelerometerCovariance(np.eye(3) * float(p.get("accelerometer_noise_density", 2e-3)) ** 2)
        self.pp.setIntegrationCovariance(np.eye(3) * 1e-8)
        self.bias = gtsam.imuBias.ConstantBias()
        self.last_t: float | None = None
        self.acc_log: list[tuple[float, F64]] = []

    def preintegrate(self, samples: F64) -> Any:
        """samples (K,7) [t_s, wx, wy, wz, ax, ay, az] -> gtsam PreintegratedImuMeasurements or None."""
        pim = self.gtsam.PreintegratedImuMeasurements(self.pp, self.bias)
        n = 0
        for row in samples:
            t = float(row[0])
            if self.last_t is not None and t > self.last_t:
                dt = t - self.last_t
                if dt < 0.5:
                    pim.integrateMeasurement(row[4:7], row[1:4], dt)
                    n += 1
            self.last_t = t
        return pim if n else None


class Frontend:
    """Stereo(-inertial) ORB visual odometry producing keyframes and map points.

    ``process`` each stereo pair in time order; read ``poll_events()`` for the link/second stage.
    ``imu_params``: dict with optional ``gyroscope_noise_density``/``accelerometer_noise_density``;
    when given, pass ``imu_samples_since_last`` (K,7) [t_s, w(3) rad/s, a(3) m/s^2] in the body frame.
    """

    def __init__(
        self,
        rig: StereoRig,
        options: FrontendOptions | None = None,
        imu_params: dict[str, float] | None = None,
    ) -> None:
        self.rig = rig
        o = options or FrontendOptions()
        area = rig.left.width * rig.left.height
        if o.scale_features_with_resolution and area < 640 * 480:
            o = replace(o, n_features=max(300, int(o.n_features * area / (640 * 480) * 1.5)))
        self.options = o
        self.cam = rig.left
        self.body_from_cam = rig.body_from_left
        self.cam_from_body = se3_inverse(rig.body_from_left)
        self.stereo = StereoMatcher(
            rig, o.stereo_max_row_error_px, o.stereo_fb_error_px, o.stereo_min_depth_m
        )
        self.k = Intrinsics(self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy, rig.baseline)
        self.orb = OrbExtractor(o)
        self.imu = _ImuState(imu_params) if imu_params is not None else None
        self.session = 0
        self.stats = FrontendStats()
        self._events: list[Event] = []
        self._reset_map()
        self._kf_counter = 0
        self._last: Frame | None = None
        self._motion = np.eye(4)  # cam_last_from_cam_cur of the last step
        self._lost_count = 0
        self._median_disp = 0.0
        self._state = TrackingState.INITIALIZING
        self._gravity_aligned = self.imu is None
        self._velocity_w = np.zeros(3)
        self._align_buffer: list[tuple[float, F64, F64]] = []  # t, T_wb, accel (mean since last)
        self._last_T_wb: F64 | None = None
        self._last_tracked = False
        self._pending_new_map = False
        self._align_failures = 0

    # ------------------------------------------------------------------ public API
    @property
    def keyframes(self) -> dict[int, KeyframeData]:
        """Keyframes of the current session, by id."""
        return self._kfs

    @property
    def points(self) -> PointStore:
        return self._pts

    def poll_events(self) -> list[Event]:
        ev, self._events = self._events, []
        return ev

    def flush(self) -> None:
        """Emit every keyframe still held back (end of a run)."""
        for kid in sorted(self._kfs):
            if not self._kfs[kid].emitted:
                self._emit_keyframe(self._kfs[kid])

    def process(
        self,
        t: float,
        left_gray: NDArray[np.uint8],
        right_gray: NDArray[np.uint8],
        imu_samples_since_last: F64 | None = None,
        gnss_epoch: bool = False,
    ) -> FrameResult:
        import time

        o = self.options
        t0 = time.perf_counter()
        self.stats.frames += 1
        pim = None
        acc_mean = None
        if self.imu is not None and imu_samples_since_last is not None and len(imu_samples_since_last):
            pim = self.imu.preintegrate(np.asarray(imu_samples_since_last, dtype=np.float64))
            acc_mean = np.asarray(imu_samples_since_last)[:, 4:7].mean(0)
        frame = self._make_frame(t, left_gray, right_gray)
        t1 = time.perf_counter()
        new_kf: int | None = None
        if self._state == TrackingState.INITIALIZING or self._last is None:
            state0 = TrackingState.INITIALIZING
            if self._initialize(frame, np.eye(4) if self._last is None else self._last.T_cw):
                self._state = TrackingState.OK
                new_kf = self._kf_last_id
                state0 = TrackingState.NEW_MAP if self._pending_new_map else TrackingState.OK
                self._pending_new_map = False
            self._finish(frame, acc_mean, tracked=new_kf is not None)
            return self._result(frame, len(frame.point_ids[frame.point_ids >= 0]), new_kf, state0)

        T_pred = self._predict(pim)
        state = TrackingState.OK
        was_lost = self._state == TrackingState.LOST
        if was_lost:
            # lost: global relocalisation against the map first, then the (IMU) prediction bridge
            ok, n_tracked = self._relocalize(frame, T_pred)
            if not ok:
                ok, n_tracked = self._track(frame, T_pred)
        else:
            ok, n_tracked = self._track(frame, T_pred)
            if not ok:
                ok, n_tracked = self._relocalize(frame, T_pred)
                was_lost = ok
        if ok and was_lost:
            state = TrackingState.RELOCALIZED
            self.stats.relocalizations += 1
            log.info("relocalised at t=%.3f with %d matches", t, n_tracked)
        t2 = time.perf_counter()
        if ok:
            self._lost_count = 0
            if self._need_keyframe(frame, n_tracked, gnss_epoch, state):
                new_kf = self._create_keyframe(frame, gnss_epoch)
        else:
            self._lost_count += 1
            self.stats.lost_frames += 1
            frame.T_cw = T_pred
            frame.point_ids[:] = -1
            state = TrackingState.LOST
            if self._lost_count > o.max_lost_frames:
                old = self.session
                self.flush()
                self.session += 1
                self.stats.sessions += 1
                self._reset_map()
                self._events.append(NewSessionEvent(old, self.session, t))
                log.warning("tracking lost for %d frames: new map session %d", self._lost_count, self.session)
                self._lost_count = 0
                if self._initialize(frame, T_pred):
                    new_kf = self._kf_last_id
                    state = TrackingState.NEW_MAP
                else:
                    self._pending_new_map = True
                    state = TrackingState.INITIALIZING
        t3 = time.perf_counter()
        self._finish(frame, acc_mean, tracked=state != TrackingState.LOST)
        tm = self.stats.timing
        for name, dt in (("features", t1 - t0), ("track", t2 - t1), ("mapping", t3 - t2)):
            tm[name] = tm.get(name, 0.0) + dt
        self._state = state if state != TrackingState.NEW_MAP else TrackingState.OK
        if state == TrackingState.INITIALIZING:
            frame.T_cw = T_pred
        return self._result(frame, n_tracked, new_kf, state)

    # ------------------------------------------------------------------ frames
    def _enhance(
        self, left: NDArray[np.uint8], right: NDArray[np.uint8]
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """Dim / foggy images: the same linear stretch on both images + a light blur (sensor noise).

        The same mapping on left and right keeps LK stereo consistent; the blur keeps FAST at a low
        threshold from firing on noise.
        """
        o = self.options
        if o.low_contrast_std <= 0:
            return left, right
        sub = left[::4, ::4]
        if float(sub.std()) >= o.low_contrast_std:
            return left, right
        lo, hi = np.percentile(sub, (1.0, 99.0))
        gain = min(o.max_contrast_gain, 200.0 / max(float(hi - lo), 1.0))
        out: list[NDArray[np.uint8]] = []
        for img in (left, right):
            f = cv2.convertScaleAbs(img, alpha=gain, beta=-gain * float(lo) + 20.0)
            out.append(np.asarray(cv2.GaussianBlur(f, (5, 5), 1.0), dtype=np.uint8))
        return out[0], out[1]

    def _make_frame(self, t: float, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> Frame:
        left, right = self._enhance(left, right)
        uv, octv, desc, _ang = self.orb.extract(left)
        kpu = self.cam.undistort_pixels(uv.astype(np.float64)) if len(uv) else np.zeros((0, 2))
        init_d = np.full(len(uv), self._median_disp)
        pts_cam = self.stereo.match(left, right, uv, init_d)
        z = pts_cam[:, 2]
        has = np.isfinite(z)
        if has.sum() > 10:
            d = self.stereo.f_rect * self.stereo.baseline / z[has]
            self._median_disp = float(np.median(d))
        max_z = self.options.stereo_residual_max_depth_baselines * self.rig.baseline
        meas = np.full((len(uv), 3), np.nan)
        meas[:, :2] = kpu
        use = has & (z < max_z)
        # virtual right observation of the left-frame 3D point (exact for a rectified rig)
        meas[use, 2] = kpu[use, 0] - self.k.fx * self.k.baseline / z[use]
        scale = self.options.scale_factor ** octv.astype(np.float64)
        return Frame(
            t=t,
            uv=uv,
            octaves=octv,
            desc=desc,
            kpu=kpu,
            pts_cam=pts_cam,
            meas=meas,
            inv_sigma2=1.0 / (scale * scale),
            point_ids=-np.ones(len(uv), np.int64),
        )

    def _result(
        self, frame: Frame, n_tracked: int, new_kf: int | None, state: TrackingState | None = None
    ) -> FrameResult:
        T_wc = frame.T_wc
        return FrameResult(
            t=frame.t,
            state=state or self._state,
            world_from_cam=T_wc,
            world_from_body=T_wc @ self.cam_from_body,
            n_tracked=int(n_tracked),
            session=self.session,
            new_keyframe_id=new_kf,
        )

    def _finish(self, frame: Frame, acc_mean: F64 | None, tracked: bool = True) -> None:
        if (
            tracked
            and self._last_tracked
            and self._last is not None
            and self._state != TrackingState.INITIALIZING
        ):
            self._motion = self._last.T_cw @ frame.T_wc
            dt = frame.t - self._last.t
            if dt > 0:
                p_new = (frame.T_wc @ self.cam_from_body)[:3, 3]
                p_old = (self._last.T_wc @ self.cam_from_body)[:3, 3]
                self._velocity_w = (p_new - p_old) / dt
        self._last = frame
        self._last_tracked = tracked
        if not self._gravity_aligned and acc_mean is not None and self._kfs:
            self._align_buffer.append((frame.t, frame.T_wc @ self.cam_from_body, acc_mean))
            self._try_gravity_alignment()

    # ------------------------------------------------------------------ map lifecycle
    def _reset_map(self) -> None:
        self._kfs: dict[int, KeyframeData] = {}
        self._pts = PointStore()
        self._local_kf_ids: list[int] = []
        self._local_pids = np.zeros(0, np.int64)
        self._kf_last_id = -1
        self._ref_tracked = 0

    def _initialize(self, frame: Frame, T_cw: F64) -> bool:
        has = np.isfinite(frame.pts_cam[:, 2])
        if has.sum() < 50:
            return False
        frame.T_cw = T_cw.copy()
        self._create_keyframe(frame, False, first=True)
        log.info("map session %d initialised at t=%.3f with %d points", self.session, frame.t, has.sum())
        return True

    # ------------------------------------------------------------------ prediction / IMU
    def _predict(self, pim: Any) -> F64:
        assert self._last is not None
        motion = self._motion.copy()
        if pim is not None:
            dR_body = pim.deltaRij().matrix()
            R_cb = self.cam_from_body[:3, :3]
            motion[:3, :3] = R_cb @ dR_body @ R_cb.T
            if self._gravity_aligned and self.imu is not None:
                import gtsam

                T_wb = self._last.T_wc @ self.cam_from_body
                nav = gtsam.NavState(gtsam.Pose3(T_wb), self._velocity_w)
                pred = pim.predict(nav, self.imu.bias)
                T_wb_pred = pred.pose().matrix()
                return se3_inverse(T_wb_pred @ self.body_from_cam)
        return se3_inverse(self._last.T_wc @ motion)

    def _try_gravity_alignment(self) -> None:
        buf = self._align_buffer
        if len(buf) < 3 or buf[-1][0] - buf[0][0] < self.options.gravity_init_s:
            return
        # specific force in the world: R_wb a = acc_w + g_up  ->  g_up = mean(R_wb a) - (v1 - v0) / T
        ts = np.array([b[0] for b in buf])
        ps = np.array([b[1][:3, 3] for b in buf])
        f_w = np.array([b[1][:3, :3] @ b[2] for b in buf])
        k = max(1, len(buf) // 5)
        v0 = (ps[k] - ps[0]) / (ts[k] - ts[0])
        v1 = (ps[-1] - ps[-1 - k]) / (ts[-1] - ts[-1 - k])
        g_up = f_w.mean(0) - (v1 - v0) / ((ts[-1] + ts[-1 - k]) / 2 - (ts[k] + ts[0]) / 2)
        if not 8.0 < np.linalg.norm(g_up) < 11.6:
            self._align_failures += 1
            if self._align_failures < 5:
                log.warning("gravity estimate %.2f m/s^2 implausible; retrying", np.linalg.norm(g_up))
                self._align_buffer = buf[len(buf) // 2 :]
                return
            g_up = f_w.mean(0)  # give up on the motion correction: assume a small mean acceleration
            log.warning("gravity from the mean specific force only (%.2f m/s^2)", np.linalg.norm(g_up))
        a = g_up / np.linalg.norm(g_up)
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(a, z)
        s = np.linalg.norm(axis)
        ang = np.arctan2(s, float(a @ z))
        R = so3_exp(axis / s * ang) if s > 1e-9 else np.eye(3)
        A = se3(R, np.zeros(3))
        self._apply_world_transform(A)
        self._gravity_aligned = True
        self._align_buffer = []
        log.info("VIO frame gravity-aligned (%.2f deg correction)", np.degrees(ang))

    def _apply_world_transform(self, A: F64) -> None:
        Ainv = se3_inverse(A)
        for kf in self._kfs.values():
            kf.T_cw = kf.T_cw @ Ainv
            kf.frame.T_cw = kf.T_cw
        n = self._pts.n
        self._pts.xyz[:n] = self._pts.xyz[:n] @ A[:3, :3].T + A[:3, 3]
        if self._last is not None and not any(kf.frame is self._last for kf in self._kfs.values()):
            self._last.T_cw = self._last.T_cw @ Ainv
        self._velocity_w = A[:3, :3] @ self._velocity_w

    # ------------------------------------------------------------------ matching
    def _match_projection(
        self, frame: Frame, T_cw: F64, pids: I64, radius: float, taken: NDArray[np.bool_]
    ) -> tuple[I64, NDArray[np.bool_]]:
        """Project points ``pids`` into ``frame``: -> (kp index per point or -1, visible mask)."""
        o = self.options
        m = len(pids)
        res = -np.ones(m, np.int64)
        if m == 0 or frame.n == 0:
            return res, np.zeros(m, bool)
        X = self._pts.xyz[pids]
        pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        uvr = project(self.k, pc)
        vis = (pc[:, 2] > 0.1) & (uvr[:, 0] >= -5) & (uvr[:, 1] >= -5)
        vis &= (uvr[:, 0] <= self.cam.width + 5) & (uvr[:, 1] <= self.cam.height + 5)
        idx_vis = np.flatnonzero(vis)
        if len(idx_vis) == 0:
            return res, vis
        kmax = 8
        max_r = radius * o.scale_factor ** (o.n_levels - 1)
        dist, nn = frame.tree.query(uvr[idx_vis, :2], k=kmax, distance_upper_bound=max_r)
        valid = nn < frame.n
        nn_c = np.where(valid, nn, 0)
        kscale = o.scale_factor ** frame.octaves[nn_c].astype(np.float64)
        valid &= dist <= radius * kscale
        valid &= ~taken[nn_c]
        hd = hamming(self._pts.desc[pids[idx_vis]][:, None, :], frame.desc[nn_c])
        hd = np.where(valid, hd, 999)
        order = np.argsort(hd, axis=1)
        best = np.take_along_axis(hd, order[:, :1], 1)[:, 0]
        second = np.take_along_axis(hd, order[:, 1:2], 1)[:, 0]
        ok = (best <= o.max_descriptor_distance) & ((second >= 999) | (best < o.ratio * second))
        kp = np.take_along_axis(nn_c, order[:, :1], 1)[:, 0]
        sel = np.flatnonzero(ok)
        if len(sel) == 0:
            return res, vis
        # one point per keypoint: keep the best descriptor distance
        srt = sel[np.argsort(best[sel], kind="stable")]
        _, first = np.unique(kp[srt], return_index=True)
        keep = srt[first]
        res[idx_vis[keep]] = kp[keep]
        return res, vis

    def _update_local_map(self) -> None:
        o = self.options
        if not self._kfs:
            self._local_pids = np.zeros(0, np.int64)
            return
        recent = sorted(self._kfs)[-o.local_map_keyframes :]
        cov = self._covisibility(self._kf_last_id)
        best = [k for k, _ in sorted(cov.items(), key=lambda kv: -kv[1])[: o.local_map_keyframes]]
        kf_ids = list(dict.fromkeys(recent[::-1] + best))
        pids = [self._kfs[k].frame.point_ids for k in kf_ids]
        allp = np.unique(np.concatenate(pids)) if pids else np.zeros(0, np.int64)
        allp = allp[allp >= 0]
        self._local_kf_ids = kf_ids
        self._local_pids = allp[self._pts.alive[allp]]

    def _covisibility(self, kf_id: int) -> dict[int, int]:
        kf = self._kfs.get(kf_id)
        if kf is None:
            return {}
        cov: dict[int, int] = {}
        for pid in kf.frame.point_ids[kf.frame.point_ids >= 0]:
            for other in self._pts.obs[pid]:
                if other != kf_id:
                    cov[other] = cov.get(other, 0) + 1
        return cov

    # ------------------------------------------------------------------ tracking
    def _pose_from_matches(self, frame: Frame, T_init: F64, pids: I64, kps: I64) -> tuple[F64, I64, I64]:
        """PnP RANSAC + motion-only refinement -> (T_cw, inlier point ids, inlier keypoints)."""
        o = self.options
        T = T_init
        if len(pids) >= 6:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                self._pts.xyz[pids],
                frame.kpu[kps],
                self.cam.K,
                None,
                iterationsCount=200,
                reprojectionError=o.pnp_reprojection_px,
                confidence=0.999,
                flags=cv2.SOLVEPNP_P3P,
            )
            if ok and inl is not None and len(inl) >= max(10, o.min_tracked // 2):
                T = se3(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
                inl = inl.reshape(-1)
                pids, kps = pids[inl], kps[inl]
        T, good = optimize_pose(self.k, T, self._pts.xyz[pids], frame.meas[kps], frame.inv_sigma2[kps])
        return T, pids[good], kps[good]

    def _track(self, frame: Frame, T_pred: F64) -> tuple[bool, int]:
        o = self.options
        pids = self._local_pids
        taken = np.zeros(frame.n, bool)
        match, _ = self._match_projection(frame, T_pred, pids, o.search_radius_px, taken)
        sel = match >= 0
        if sel.sum() < o.min_tracked:
            match, _ = self._match_projection(frame, T_pred, pids, 2.5 * o.search_radius_px, taken)
            sel = match >= 0
            if sel.sum() < o.min_tracked:
                return False, int(sel.sum())
        return self._finish_tracking(frame, T_pred, pids[sel], match[sel])

    def _finish_tracking(self, frame: Frame, T_init: F64, pids: I64, kps: I64) -> tuple[bool, int]:
        o = self.options
        T, p_in, k_in = self._pose_from_matches(frame, T_init, pids, kps)
        if len(p_in) < o.min_tracked:
            return False, len(p_in)
        # track local map: all local points again, tight radius, around the refined pose
        local = self._local_pids
        taken = np.zeros(frame.n, bool)
        match, vis = self._match_projection(frame, T, local, o.local_search_radius_px, taken)
        sel = match >= 0
        p2, k2 = local[sel], match[sel]
        if len(p2) < len(p_in):
            p2, k2 = p_in, k_in
        T, inl = optimize_pose(self.k, T, self._pts.xyz[p2], frame.meas[k2], frame.inv_sigma2[k2])
        n_in = int(inl.sum())
        if n_in < o.min_tracked:
            return False, n_in
        frame.T_cw = T
        frame.point_ids[:] = -1
        frame.point_ids[k2[inl]] = p2[inl]
        self._pts.visible[local[vis]] += 1
        self._pts.found[p2[inl]] += 1
        return True, n_in

    # ------------------------------------------------------------------ relocalisation
    def _relocalize(self, frame: Frame, T_pred: F64) -> tuple[bool, int]:
        o = self.options
        if frame.n == 0 or not self._kfs:
            return False, 0
        kf_ids = sorted(self._kfs)[-o.reloc_keyframes :]
        pids = np.unique(np.concatenate([self._kfs[k].frame.point_ids for k in kf_ids]))
        pids = pids[pids >= 0]
        pids = pids[self._pts.alive[pids]]
        if len(pids) < o.reloc_min_inliers:
            return False, 0
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        knn = bf.knnMatch(frame.desc, self._pts.desc[pids], k=2)
        qi, ti = [], []
        for m in knn:
            if len(m) == 2 and m[0].distance < 0.8 * m[1].distance and m[0].distance <= 64:
                qi.append(m[0].queryIdx)
                ti.append(m[0].trainIdx)
        if len(qi) < o.reloc_min_inliers:
            return False, len(qi)
        kps = np.array(qi)
        mp = pids[np.array(ti)]
        _, u = np.unique(kps, return_index=True)
        kps, mp = kps[u], mp[u]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            self._pts.xyz[mp],
            frame.kpu[kps],
            self.cam.K,
            None,
            iterationsCount=500,
            reprojectionError=o.pnp_reprojection_px,
            confidence=0.999,
            flags=cv2.SOLVEPNP_P3P,
        )
        if not ok or inl is None or len(inl) < o.reloc_min_inliers:
            return False, 0 if inl is None else len(inl)
        T = se3(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        inl = inl.reshape(-1)
        return self._finish_tracking(frame, T, mp[inl], kps[inl])

    # ------------------------------------------------------------------ keyframes
    def _need_keyframe(self, frame: Frame, n_tracked: int, gnss_epoch: bool, state: TrackingState) -> bool:
        o = self.options
        if gnss_epoch or state == TrackingState.RELOCALIZED:
            return True
        last = self._kfs.get(self._kf_last_id)
        if last is None:
            return True
        if frame.t - last.timestamp >= o.kf_max_interval_s:
            return True
        tracked = frame.point_ids >= 0
        close_th = o.close_depth_baselines * self.rig.baseline
        z = frame.pts_cam[:, 2]
        close = np.isfinite(z) & (z < close_th)
        n_close_tracked = int((tracked & close).sum())
        n_close_untracked = int((~tracked & close).sum())
        weak_close = n_close_tracked < o.kf_min_close_tracked and n_close_untracked > o.kf_min_close_tracked
        return n_tracked < o.kf_min_tracked_ratio * self._ref_tracked or weak_close

    def _create_keyframe(self, frame: Frame, gnss_epoch: bool, first: bool = False) -> int:
        import time

        o = self.options
        kid = self._kf_counter
        self._kf_counter += 1
        prev = self._kfs.get(self._kf_last_id)
        kf = KeyframeData(
            kid, self.session, frame, frame.T_cw.copy(), gnss_epoch, prev_id=prev.id if prev else None
        )
        self._kfs[kid] = kf
        self.stats.keyframes += 1
        pts = self._pts
        tracked_before = int((frame.point_ids >= 0).sum())
        for i in np.flatnonzero(frame.point_ids >= 0):
            pid = int(frame.point_ids[i])
            pts.obs[pid][kid] = int(i)
            pts.desc[pid] = frame.desc[i]
        # stereo points: all close ones, at least 100 (closest first) as ORB-SLAM
        z = frame.pts_cam[:, 2]
        cand = np.flatnonzero(np.isfinite(z) & (frame.point_ids < 0))
        cand = cand[np.argsort(z[cand])]
        close_th = o.close_depth_baselines * self.rig.baseline
        n_close = int((z[cand] < close_th).sum())
        n_take = max(n_close, min(len(cand), 100 if not first else len(cand)))
        new = cand[:n_take]
        if len(new):
            Xw = frame.pts_cam[new] @ kf.T_wc[:3, :3].T + kf.T_wc[:3, 3]
            ids = pts.add(Xw, frame.desc[new], kid)
            frame.point_ids[new] = ids
            for pid, i in zip(ids, new, strict=True):
                pts.obs[int(pid)][kid] = int(i)
        t0 = time.perf_counter()
        if not first:
            self._triangulate(kf)
        t1 = time.perf_counter()
        if not first:
            self._local_ba(kf)
            self._cull_points(kid)
        t2 = time.perf_counter()
        self.stats.timing["triangulate"] = self.stats.timing.get("triangulate", 0.0) + t1 - t0
        self.stats.timing["local_ba"] = self.stats.timing.get("local_ba", 0.0) + t2 - t1
        frame.T_cw = kf.T_cw
        # relative pose covariance from the keyframe's own observations (motion-only information)
        if prev is not None:
            tr = frame.point_ids >= 0
            idx = np.flatnonzero(tr)
            H = pose_hessian(
                self.k, kf.T_cw, pts.xyz[frame.point_ids[idx]], frame.meas[idx], frame.inv_sigma2[idx]
            )
            try:
                cov = np.linalg.inv(H + 1e-6 * np.eye(6))
            except np.linalg.LinAlgError:
                cov = np.eye(6)
            # left perturbation of cam_from_world == (minus) right perturbation of world_from_cam
            dist = float(np.linalg.norm(kf.T_wc[:3, 3] - prev.T_wc[:3, 3]))
            floor = np.array([1e-3 + 2e-3 * np.radians(1.0)] * 3 + [1e-3 + 4e-3 * dist] * 3) ** 2
            kf.rel_cov_cam = cov + np.diag(floor)
        self._kf_last_id = kid
        self._ref_tracked = tracked_before if not first else int((frame.point_ids >= 0).sum())
        self._update_local_map()
        self._emit_ready()
        return kid

    def _triangulate(self, kf: KeyframeData) -> None:
        """Multi-view triangulation of unmatched keypoints with the previous keyframes."""
        o = self.options
        f1 = kf.frame
        un1 = np.flatnonzero(f1.point_ids < 0)
        if len(un1) < 10:
            return
        nbrs = sorted((k for k in self._kfs if k != kf.id), reverse=True)[: o.triangulation_neighbours]
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        K = self.cam.K
        Kinv = np.linalg.inv(K)
        C1 = kf.T_wc[:3, 3]
        for nid in nbrs:
            nk = self._kfs[nid]
            f2 = nk.frame
            un2 = np.flatnonzero(f2.point_ids < 0)
            un1 = np.flatnonzero(f1.point_ids < 0)
            if len(un2) < 10 or len(un1) < 10:
                continue
            C2 = nk.T_wc[:3, 3]
            if np.linalg.norm(C2 - C1) < 0.5 * self.rig.baseline:
                continue
            knn = bf.knnMatch(f1.desc[un1], f2.desc[un2], k=2)
            a, b = [], []
            for m in knn:
                if len(m) == 2 and m[0].distance <= 50 and m[0].distance < 0.7 * m[1].distance:
                    a.append(un1[m[0].queryIdx])
                    b.append(un2[m[0].trainIdx])
            if len(a) < 5:
                continue
            ia, ib = np.array(a), np.array(b)
            _, u = np.unique(ib, return_index=True)
            ia, ib = ia[u], ib[u]
            x1 = np.c_[f1.kpu[ia], np.ones(len(ia))] @ Kinv.T
            x2 = np.c_[f2.kpu[ib], np.ones(len(ib))] @ Kinv.T
            r1 = x1 @ kf.T_wc[:3, :3].T
            r2 = x2 @ nk.T_wc[:3, :3].T
            cosp = (r1 * r2).sum(1) / np.linalg.norm(r1, axis=1) / np.linalg.norm(r2, axis=1)
            ok = cosp < o.min_parallax_cos
            if not ok.any():
                continue
            ia, ib, x1, x2 = ia[ok], ib[ok], x1[ok], x2[ok]
            Xh = cv2.triangulatePoints(kf.T_cw[:3], nk.T_cw[:3], x1[:, :2].T, x2[:, :2].T)
            Xw = (Xh[:3] / np.where(np.abs(Xh[3]) > 1e-12, Xh[3], 1e-12)).T
            good = np.isfinite(Xw).all(1)
            # Each view's reprojection, with the right-image coordinate where the keypoint has one (as
            # local BA will weigh it): two views alone only check the epipolar line, so a wrong match
            # along it (repeated posters on a wall, factory01's UGV at t=24-26 s) triangulates at a
            # wrong depth that its stereo measurement contradicts. Such points entered local BA with
            # chi2 in the thousands and pulled keyframes seeing mostly far points by 0.4-2.3 m.
            for T, f, idx in ((kf.T_cw, f1, ia), (nk.T_cw, f2, ib)):
                pc = Xw @ T[:3, :3].T + T[:3, 3]
                meas = f.meas[idx]
                chi2 = chi2_of(self.k, pc, meas, f.inv_sigma2[idx])
                good &= (pc[:, 2] > 0.1) & (chi2 < chi2_thresholds(meas))
            if not good.any():
                continue
            ia, ib, Xw = ia[good], ib[good], Xw[good]
            ids = self._pts.add(Xw, f1.desc[ia], kf.id)
            f1.point_ids[ia] = ids
            f2.point_ids[ib] = ids
            for pid, i, j in zip(ids, ia, ib, strict=True):
                self._pts.obs[int(pid)][kf.id] = int(i)
                self._pts.obs[int(pid)][nid] = int(j)

    def _local_ba(self, kf: KeyframeData) -> None:
        o = self.options
        cov = self._covisibility(kf.id)
        window = [kf.id] + [k for k, _ in sorted(cov.items(), key=lambda kv: -kv[1])[: o.ba_window - 1]]
        wset = set(window)
        pids_l = [self._kfs[k].frame.point_ids for k in window]
        pids = np.unique(np.concatenate(pids_l))
        pids = pids[pids >= 0]
        pids = pids[self._pts.alive[pids]]
        if len(pids) < 10:
            return
        fixed_count: dict[int, int] = {}
        cams: list[int] = []
        pts_i: list[int] = []
        kp_i: list[int] = []
        for j, pid in enumerate(pids):
            for k_id, i in self._pts.obs[int(pid)].items():
                if k_id not in wset:
                    fixed_count[k_id] = fixed_count.get(k_id, 0) + 1
                cams.append(k_id)
                pts_i.append(j)
                kp_i.append(i)
        fixed = [k for k, _ in sorted(fixed_count.items(), key=lambda kv: -kv[1])[: o.ba_fixed_max]]
        if not fixed:
            # gauge: hold the oldest keyframe of the window
            oldest = min(window)
            window.remove(oldest)
            fixed = [oldest]
        all_k = window + fixed
        kidx = {k: n for n, k in enumerate(all_k)}
        cam_arr = np.array(cams)
        use = np.array([c in kidx for c in cams])
        cam_idx = np.array([kidx.get(c, -1) for c in cams])[use]
        pt_idx = np.array(pts_i)[use]
        kp_arr = np.array(kp_i)[use]
        cam_ids = cam_arr[use]
        meas = np.empty((len(cam_idx), 3))
        inv_s2 = np.empty(len(cam_idx))
        for k_id in all_k:
            m = cam_ids == k_id
            f = self._kfs[k_id].frame
            meas[m] = f.meas[kp_arr[m]]
            inv_s2[m] = f.inv_sigma2[kp_arr[m]]
        poses = np.stack([self._kfs[k].T_cw for k in all_k])
        is_fixed = np.array([k not in wset or k in fixed for k in all_k])
        prob = BAProblem(poses, is_fixed, self._pts.xyz[pids].copy(), cam_idx, pt_idx, meas, inv_s2)
        n1 = max(2, o.ba_iterations // 2)
        poses2, X2, inl = bundle_adjust(self.k, prob, n1)
        prob2 = BAProblem(poses2, is_fixed, X2, cam_idx, pt_idx, meas, inv_s2)
        poses2, X2, inl2 = bundle_adjust(self.k, prob2, o.ba_iterations - n1, active=inl)
        # drop outlier observations
        for n in np.flatnonzero(~inl2):
            k_id = int(cam_ids[n])
            pid = int(pids[pt_idx[n]])
            self._pts.obs[pid].pop(k_id, None)
            f = self._kfs[k_id].frame
            if f.point_ids[kp_arr[n]] == pid:
                f.point_ids[kp_arr[n]] = -1
        for k_id, T in zip(all_k, poses2, strict=True):
            if k_id in wset and k_id not in fixed:
                self._kfs[k_id].T_cw = T
                self._kfs[k_id].frame.T_cw = T
        self._pts.xyz[pids] = X2
        upd = [k for k in window if k not in fixed and self._kfs[k].emitted]
        if upd:
            pp = pids[self._pts.emitted[pids]]
            self._events.append(
                PoseUpdateEvent(
                    self.session,
                    np.array(upd, np.int64),
                    np.stack([self._kfs[k].T_wc for k in upd]),
                    pp,
                    self._pts.xyz[pp].copy(),
                )
            )

    def _cull_points(self, kid: int) -> None:
        o = self.options
        pts = self._pts
        ids = pts.alive_ids()
        ids = ids[pts.first_kf[ids] >= kid - 6]  # recently created points only (ORB-SLAM's recent list)
        if len(ids) == 0:
            return
        nobs = np.array([len(pts.obs[i]) for i in ids])
        ratio = pts.found[ids] / np.maximum(pts.visible[ids], 1)
        age = kid - pts.first_kf[ids]
        bad = (nobs == 0) | ((ratio < o.culling_min_found_ratio) & (age >= 2)) | ((age >= 3) & (nobs <= 1))
        bad &= ~pts.emitted[ids] | (nobs == 0)
        for pid in ids[bad]:
            for k_id, i in pts.obs[pid].items():
                f = self._kfs[k_id].frame
                if f.point_ids[i] == pid:
                    f.point_ids[i] = -1
            pts.obs[pid] = {}
            pts.alive[pid] = False

    # ------------------------------------------------------------------ events
    def _emit_ready(self) -> None:
        if not self._gravity_aligned:
            return
        ids = sorted(self._kfs)
        delay = 2
        for kid in ids[: max(0, len(ids) - delay)]:
            if not self._kfs[kid].emitted:
                self._emit_keyframe(self._kfs[kid])

    def _emit_keyframe(self, kf: KeyframeData) -> None:
        f = kf.frame
        pids = f.point_ids.copy()
        ok = pids >= 0
        ok[ok] = self._pts.alive[pids[ok]]
        pids[~ok] = -1
        newp = np.unique(pids[ok])
        newp = newp[~self._pts.emitted[newp]]
        self._pts.emitted[newp] = True
        T_wc = kf.T_wc
        T_wb = T_wc @ self.cam_from_body
        rel_body = rel_cov = None
        prev = self._kfs.get(kf.prev_id) if kf.prev_id is not None else None
        if prev is not None and kf.rel_cov_cam is not None:
            prev_wb = prev.T_wc @ self.cam_from_body
            rel_body = se3_inverse(prev_wb) @ T_wb
            # right perturbation: xi_body = Ad(body_from_cam) xi_cam
            Tbc = self.body_from_cam
            Rb, tb = Tbc[:3, :3], Tbc[:3, 3]
            tx = np.array([[0, -tb[2], tb[1]], [tb[2], 0, -tb[0]], [-tb[1], tb[0], 0]])
            Ad = np.zeros((6, 6))
            Ad[:3, :3] = Rb
            Ad[3:, 3:] = Rb
            Ad[3:, :3] = tx @ Rb
            rel_cov = Ad @ kf.rel_cov_cam @ Ad.T
        kf.emitted = True
        self._events.append(
            KeyframeEvent(
                session=kf.session,
                kf_id=kf.id,
                timestamp=kf.timestamp,
                world_from_cam=T_wc,
                world_from_body=T_wb,
                keypoints=f.uv.copy(),
                octaves=f.octaves.copy(),
                descriptors=f.desc.copy(),
                point_ids=pids,
                prev_kf_id=kf.prev_id if prev is not None else None,
                rel_body=rel_body,
                rel_cov=rel_cov,
                gnss_epoch=kf.gnss_epoch,
                new_point_ids=newp,
                new_point_xyz=self._pts.xyz[newp].copy(),
                new_point_descriptors=self._pts.desc[newp].copy(),
            )
        )
