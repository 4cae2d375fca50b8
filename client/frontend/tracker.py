"""The front-end: stereo ORB tracking, keyframes, local mapping, local BA, relocalisation, IMU."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend import imu, mapping
from hivemap.client.frontend.carrier_mask import CarrierMask
from hivemap.client.frontend.emit import emit_keyframe
from hivemap.client.frontend.events import (
    Event,
    FrameResult,
    FrontendStats,
    KeyframeEvent,
    NewSessionEvent,
    PoseUpdateEvent,
    TrackingState,
)
from hivemap.client.frontend.features import ContrastNormaliser, OrbExtractor
from hivemap.client.frontend.imu import _ImuState
from hivemap.client.frontend.inertial import MotionFilter
from hivemap.client.frontend.mapdata import Frame, KeyframeData, PointStore
from hivemap.client.frontend.markers import MarkerOptions
from hivemap.client.frontend.optim import (
    Intrinsics,
    PosePrior,
    optimize_pose,
    pose_hessian,
)
from hivemap.client.frontend.options import FrontendOptions
from hivemap.client.frontend.preint import KeyframeImu
from hivemap.client.frontend.projection_match import match_by_projection
from hivemap.client.frontend.relocalize import relocalize
from hivemap.client.frontend.stereo import StereoMatcher
from hivemap.maps.camera import StereoRig
from hivemap.maps.geometry import se3, se3_inverse
from hivemap.maps.markers import Carrier

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


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
        self.contrast = ContrastNormaliser(o)
        self.imu = _ImuState(imu_params) if imu_params is not None else None
        self.kf_imu = KeyframeImu(imu_params) if imu_params is not None else None
        self._vi_ba_ran = False  # the visual-inertial local BA has estimated the biases
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
        self._filter: MotionFilter | None = None  # from gravity alignment on
        self._prior: PosePrior | None = None  # the IMU's prior of the frame being tracked
        self._vis_info = np.eye(6)  # information of the last visual pose solved
        self._lost_since: float | None = None
        self._bridged = False  # the IMU bridged the loss that started the current session
        self._odom_var = np.zeros(2)  # [m^2, deg^2] weak or lost tracking added since the last keyframe
        self.carrier_mask: CarrierMask | None = None  # see ``use_carriers``

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
                emit_keyframe(self, self._kfs[kid])

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
            if self.kf_imu is not None:
                self.kf_imu.add(np.asarray(imu_samples_since_last, dtype=np.float64))
        frame = self._make_frame(t, left_gray, right_gray)
        t1 = time.perf_counter()
        new_kf: int | None = None
        if self._state == TrackingState.INITIALIZING or self._last is None:
            state0 = TrackingState.INITIALIZING
            if self._last is None:
                T_init = np.eye(4)
            elif self._filter is not None and pim is not None:
                # a new session waiting for images: the IMU keeps propagating into the old frame
                T_init = imu.predict(self, pim, frame.t - self._last.t).T_cw
            else:
                T_init = self._last.T_cw
            frame.T_cw = T_init
            if self._initialize(frame, T_init):
                self._state = TrackingState.OK
                new_kf = self._kf_last_id
                state0 = TrackingState.NEW_MAP if self._pending_new_map else TrackingState.OK
                self._pending_new_map = False
            self._finish(frame, acc_mean, tracked=new_kf is not None)
            return self._result(frame, len(frame.point_ids[frame.point_ids >= 0]), new_kf, state0)

        pred = imu.predict(self, pim, frame.t - self._last.t)
        T_pred = pred.T_cw
        self._prior = pred.prior
        state = TrackingState.OK
        was_lost = self._state == TrackingState.LOST
        if was_lost and self._filter is None:
            # lost without an IMU: global relocalisation against the map first, then the prediction
            ok, n_tracked = relocalize(self, frame)
            if not ok:
                ok, n_tracked = self._track(frame, T_pred)
        else:
            # the (IMU) prediction first; relocalisation against the agent's own map if it fails
            ok, n_tracked = self._track(frame, T_pred)
            if not ok:
                ok, n_tracked = relocalize(self, frame)
                was_lost = was_lost or ok
        rejected = ok and imu.gate_refuses(self, pred, frame, n_tracked)
        if rejected:
            log.debug("t=%.3f: visual pose (%d inliers) rejected by the IMU gate", t, n_tracked)
            self.stats.imu_rejections += 1
            ok = False
        self._prior = None
        if ok and was_lost:
            state = TrackingState.RELOCALIZED
            self.stats.relocalizations += 1
            log.info("relocalised at t=%.3f with %d matches", t, n_tracked)
        elif ok and n_tracked < o.good_min_inliers:
            state = TrackingState.WEAK
            self.stats.weak_frames += 1
        t2 = time.perf_counter()
        if ok:
            self._add_odom_error(state, self._lost_count)
            self._lost_count = 0
            self._lost_since = None
            imu.visual_update(self, frame, pim, state)
            if mapping.need_keyframe(self, frame, n_tracked, gnss_epoch, state):
                new_kf = mapping.create_keyframe(self, frame, gnss_epoch)
        else:
            self._lost_count += 1
            if self._lost_since is None:
                self._lost_since = self._last.t
            self.stats.lost_frames += 1
            frame.T_cw = T_pred
            frame.point_ids[:] = -1
            state = TrackingState.LOST
            if self._filter is not None:
                give_up = frame.t - self._lost_since > o.imu_hold_s
            else:
                give_up = self._lost_count > o.max_lost_frames
            if give_up:
                new_kf, state = self._new_session(frame, T_pred)
            elif not rejected and mapping.keyframe_while_lost(self, frame):
                # ORB-SLAM3's keyframes in RECENTLY_LOST: a view the map has no points for gets them
                # at the IMU's pose, so the next frame tracks again instead of waiting for a new session
                self._add_odom_error(state, self._lost_count)
                self._lost_count = 0
                new_kf = mapping.create_keyframe(self, frame, gnss_epoch, first=True)
                self.stats.lost_keyframes += 1
                log.info("t=%.3f: lost (%d matches), keyframe %d at the IMU pose", t, n_tracked, new_kf)
        t3 = time.perf_counter()
        self._finish(frame, acc_mean, tracked=state != TrackingState.LOST)
        tm = self.stats.timing
        for name, dt in (("features", t1 - t0), ("track", t2 - t1), ("mapping", t3 - t2)):
            tm[name] = tm.get(name, 0.0) + dt
        self._state = state if state != TrackingState.NEW_MAP else TrackingState.OK
        if state == TrackingState.INITIALIZING:
            frame.T_cw = T_pred
        return self._result(frame, n_tracked, new_kf, state)

    def _add_odom_error(self, state: TrackingState, n_lost: int) -> None:
        """A tracked frame: what the stretch before it adds to the next keyframe's relative pose error.
        After lost frames (or a relocalisation) that is what the IMU propagation added since the last
        visual pose, which the visual pose now replaces; a weak frame's pose passed the IMU gate with few
        inliers."""
        o = self.options
        if n_lost or state == TrackingState.RELOCALIZED:
            if self._filter is not None:
                m, deg = self._filter.growth_sigmas()
            else:
                n = math.sqrt(max(n_lost, 1))
                m, deg = n * o.odom_lost_sigma_m, n * o.odom_lost_sigma_deg
            self._odom_var += (m * m, deg * deg)
        if state == TrackingState.WEAK:
            self._odom_var += (o.odom_weak_sigma_m**2, o.odom_weak_sigma_deg**2)

    def take_odom_sigma(self) -> tuple[float, float] | None:
        """The error weak or lost tracking added since the last keyframe [m, deg] (None: none), reset."""
        var, self._odom_var = self._odom_var, np.zeros(2)
        if not np.any(var > 0):
            return None
        return float(math.sqrt(var[0])), float(math.sqrt(var[1]))

    def use_carriers(
        self, carriers: Mapping[str, Carrier], own_agent_id: str, marker_options: MarkerOptions | None = None
    ) -> None:
        """Mask the other agents' marker carriers out of tracking from now on (``carrier_mask``)."""
        if not self.options.carrier_mask or not any(a != own_agent_id for a in carriers):
            self.carrier_mask = None
            return
        o = self.options
        self.carrier_mask = CarrierMask(
            self.rig,
            carriers,
            own_agent_id,
            marker_options or MarkerOptions(),
            o.carrier_mask_margin_px,
            o.carrier_mask_hold_frames,
            o.carrier_mask_full_every,
        )

    # ------------------------------------------------------------------ frames
    def _make_frame(self, t: float, left: NDArray[np.uint8], right: NDArray[np.uint8]) -> Frame:
        # carriers are found in the raw image, as the rendezvous detector sees them
        masks = (None, None) if self.carrier_mask is None else self.carrier_mask.update(t, left)
        left, right = self.contrast(left, right)
        uv, octv, desc, _ang = self.orb.extract(left, mask=masks[0])
        kpu = self.cam.undistort_pixels(uv.astype(np.float64)) if len(uv) else np.zeros((0, 2))
        init_d = np.full(len(uv), self._median_disp)
        pts_cam = self.stereo.match(left, right, uv, init_d, right_mask=masks[1])
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
            imu.try_gravity_alignment(self)

    def _new_session(self, frame: Frame, T_pred: F64) -> tuple[int | None, TrackingState]:
        """Tracking stayed lost: a new map session, started at the propagated pose (so its VIO frame is
        the old one's, as well as the propagation could keep it)."""
        old = self.session
        self.flush()
        self.session += 1
        self.stats.sessions += 1
        self._reset_map()
        filt = self._filter
        self._bridged = filt is not None
        if filt is not None:
            self._events.append(NewSessionEvent(old, self.session, frame.t, np.eye(4), *filt.sigmas()))
        else:
            self._events.append(NewSessionEvent(old, self.session, frame.t))
        log.warning("tracking lost for %d frames: new map session %d", self._lost_count, self.session)
        self._lost_count = 0
        self._lost_since = None
        if self._initialize(frame, T_pred):
            return self._kf_last_id, TrackingState.NEW_MAP
        self._pending_new_map = True
        return None, TrackingState.INITIALIZING

    # ------------------------------------------------------------------ map lifecycle
    def _reset_map(self) -> None:
        self._kfs: dict[int, KeyframeData] = {}
        self._pts = PointStore()
        self._local_kf_ids: list[int] = []
        self._local_pids = np.zeros(0, np.int64)
        self._kf_last_id = -1
        self._ref_tracked = 0
        self._odom_var = np.zeros(2)
        if self.kf_imu is not None:
            self.kf_imu.reset()

    def _initialize(self, frame: Frame, T_cw: F64) -> bool:
        has = np.isfinite(frame.pts_cam[:, 2])
        if has.sum() < 50:
            return False
        frame.T_cw = T_cw.copy()
        kid = mapping.create_keyframe(self, frame, False, first=True)
        if self._bridged and self._filter is not None:
            # the map starts at the IMU-propagated pose: the same frame as the old session's, within
            # the propagation's uncertainty now
            kf = self._kfs[kid]
            kf.prev_session_from_world = np.eye(4)
            kf.prev_session_sigma = self._filter.sigmas()
        self._bridged = False
        log.info("map session %d initialised at t=%.3f with %d points", self.session, frame.t, has.sum())
        return True

    # ------------------------------------------------------------------ matching
    def _by_projection(
        self, frame: Frame, T_cw: F64, pids: I64, radius: float, taken: NDArray[np.bool_]
    ) -> tuple[I64, NDArray[np.bool_]]:
        o = self.options
        return match_by_projection(self._pts, frame, self.k, self.cam, o, T_cw, pids, radius, taken)

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
        match, _ = self._by_projection(frame, T_pred, pids, o.search_radius_px, taken)
        sel = match >= 0
        if sel.sum() < o.min_tracked:
            match, _ = self._by_projection(frame, T_pred, pids, 2.5 * o.search_radius_px, taken)
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
        match, vis = self._by_projection(frame, T, local, o.local_search_radius_px, taken)
        sel = match >= 0
        p2, k2 = local[sel], match[sel]
        if len(p2) < len(p_in):
            p2, k2 = p_in, k_in
        T, inl = optimize_pose(self.k, T, self._pts.xyz[p2], frame.meas[k2], frame.inv_sigma2[k2])
        n_in = int(inl.sum())
        if self._prior is not None and n_in < o.good_min_inliers:
            # weak vision: the IMU prediction joins the refinement (a well-tracked frame does without it:
            # the prediction carries the map's tilt and the filter's lag, measured worse on the tiny UAV)
            T, inl = optimize_pose(
                self.k, T, self._pts.xyz[p2], frame.meas[k2], frame.inv_sigma2[k2], prior=self._prior
            )
            n_in = int(inl.sum())
        if n_in < o.min_tracked:
            return False, n_in
        frame.T_cw = T
        # the visual pose's own uncertainty, for the IMU gate (the difference of two estimates)
        ki = k2[inl]
        self._vis_info = pose_hessian(self.k, T, self._pts.xyz[p2[inl]], frame.meas[ki], frame.inv_sigma2[ki])
        frame.point_ids[:] = -1
        frame.point_ids[k2[inl]] = p2[inl]
        self._pts.visible[local[vis]] += 1
        self._pts.found[p2[inl]] += 1
        return True, n_in

    def _triangulate(self, kf: KeyframeData) -> None:
        mapping.triangulate(self, kf)


__all__ = [
    "Event",
    "FrameResult",
    "Frontend",
    "FrontendStats",
    "KeyframeEvent",
    "NewSessionEvent",
    "PoseUpdateEvent",
    "TrackingState",
]
