"""The second stage's fusion: :class:`SecondStage` (see :mod:`hivemap.client.second_stage`)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.second_stage import colocation, imu
from hivemap.client.second_stage.factors import (
    _bkey,
    _gaussian,
    _key,
    _okey,
    _vkey,
    rigid_alignment,
    yaw_translation_alignment,
)
from hivemap.client.second_stage.options import SecondStageOptions
from hivemap.client.second_stage.outputs import StageOutputs
from hivemap.maps.geometry import Sim3, se3, se3_inverse

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


_IDENTITY16 = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass
class _Kf:
    kf_id: int
    timestamp: float
    vio_from_kf: F64
    segment: int
    fixes: list[tuple[F64, F64]] = field(default_factory=list)  # accepted (enu, cov)


@dataclass(frozen=True)
class GnssDecision:
    """Outcome of :meth:`SecondStage.add_gnss`."""

    accepted: bool
    mahalanobis: float
    residual_m: float
    forced: bool = False


class SecondStage(StageOutputs):
    """Incremental VIO + GNSS + co-location fusion over keyframe poses (see module docstring)."""

    def __init__(self, options: SecondStageOptions | None = None) -> None:
        import gtsam

        self.options = options or SecondStageOptions()
        self._gtsam = gtsam
        self._kfs: dict[int, _Kf] = {}
        self._order: list[int] = []  # insertion order
        self._segment_count = 0
        self._factors: dict[int, Any] = {}  # handle -> factor
        self._handle_to_index: dict[int, int] = {}  # handle -> iSAM2 factor index
        self._next_handle = 0
        self._colocation_handle: dict[int, int] = {}  # kf_id -> handle of its co-location prior
        self._colocation_enu = False  # the current co-location priors are absolute ENU poses
        self._offset: F64 | None = None  # estimate of O (colocation_offset_sigma), once it exists
        self._offset_prior: tuple[int, bool] | None = None  # handle of O's prior, and whether the ENU one
        # kf_id -> (handle of its relative-pose factor, previous kf_id, 6x6 covariance)
        self._between: dict[int, tuple[int, int, F64]] = {}
        self._segment_prior: dict[int, tuple[int, int, F64]] = {}  # segment -> (handle, kf_id, mean)
        self._estimate: dict[int, F64] = {}  # kf_id -> local_from_kf
        self._local_from_vio: dict[int, F64] = {}  # segment -> transform
        self._gnss_stage = 0  # 0: no fix, 1: translation aligned, 2: yaw aligned
        self._consecutive_rejections = 0
        self.rejected_fixes: list[dict[str, float]] = []  # kf_id, t, mahalanobis, residual_m
        self.n_gnss_accepted = 0
        self._gnss_handles: dict[int, list[int]] = {}  # kf_id -> handles of its GNSS factors in the graph
        self._gnss_held: dict[int, list[Any]] = {}  # kf_id -> its GNSS factors held out (the server has them)
        # IMU factors (options.imu): samples not yet integrated, the keyframes with a velocity and a bias
        # variable, and the velocity priors that start a segment (kf_id -> (handle, mean))
        self._imu_buf: list[F64] = []
        self._imu_kfs: set[int] = set()
        self._vel_prior: dict[int, tuple[int, F64]] = {}
        self._est: Any = None  # the latest iSAM2 estimate (gtsam Values): velocities and biases are read here
        self.n_imu_factors = 0
        self._imu_params = imu.imu_params(self) if self.options.imu is not None else None
        b = self.options.between_huber
        self._between_loss = self._gtsam.noiseModel.mEstimator.Huber.Create(b) if b > 0 else None
        self._isam = self._new_isam()

    # ------------------------------------------------------------------ construction helpers
    def _new_isam(self) -> Any:
        p = self._gtsam.ISAM2Params()
        # QR: Cholesky declares the system indeterminate when a 100 m prior meets 2 cm odometry.
        p.setFactorization("QR")
        p.setRelinearizeThreshold(self.options.relinearize_threshold)
        p.relinearizeSkip = self.options.relinearize_skip
        return self._gtsam.ISAM2(p)

    def _between_noise(self, cov: F64) -> Any:
        """A relative-pose factor's noise: Gaussian, or Huber-robust (``options.between_huber``)."""
        g = _gaussian(cov)
        if self._between_loss is None:
            return g
        return self._gtsam.noiseModel.Robust.Create(self._between_loss, g)

    def _first_prior_noise(self, vio_from_kf: F64) -> Any:
        o = self.options
        tilt = o.first_prior_sigma_tilt if o.gravity_aligned else o.first_prior_sigma_yaw
        cov_world = np.diag([tilt**2, tilt**2, o.first_prior_sigma_yaw**2])
        R = vio_from_kf[:3, :3]
        cov = np.zeros((6, 6))
        cov[:3, :3] = R.T @ cov_world @ R  # perturbation is in the kf frame: T * Exp(xi)
        cov[3:, 3:] = np.eye(3) * o.first_prior_sigma_pos**2
        return _gaussian(cov)

    def _commit(
        self,
        factors: list[Any],
        values: dict[int, F64],
        remove: list[int] | None = None,
        extra_values: Any = None,
    ) -> list[int]:
        """Add factors (+ new values, kf_id -> pose, and any other new gtsam ``Values``) to iSAM2;
        returns the new factor handles."""
        gtsam = self._gtsam
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f)
        theta = gtsam.Values()
        for kf_id, T in values.items():
            theta.insert(_key(kf_id), gtsam.Pose3(T))
        if extra_values is not None:
            theta.insert(extra_values)
        remove_idx = [self._handle_to_index.pop(h) for h in (remove or [])]
        for h in remove or []:
            self._factors.pop(h, None)
        result = self._isam.update(graph, theta, remove_idx)
        indices = list(result.getNewFactorsIndices())
        handles = []
        for f, idx in zip(factors, indices, strict=True):
            h = self._next_handle
            self._next_handle += 1
            self._factors[h] = f
            self._handle_to_index[h] = int(idx)
            handles.append(h)
        for _ in range(self.options.extra_iterations):
            self._isam.update()
        self._refresh()
        return handles

    def _refresh(self) -> None:
        est = self._isam.calculateEstimate()
        for kf_id in self._order:
            self._estimate[kf_id] = est.atPose3(_key(kf_id)).matrix()
        self._est = est
        if self._offset is not None:
            self._offset = est.atPose3(_okey()).matrix()
        self._update_local_from_vio()

    def _rebuild(self, T: F64) -> None:
        """Restart iSAM2 from all live factors, everything moved by ``T`` (local_new_from_local_old).

        The loose segment priors are gauge only, so they move along (their means are transformed).
        """
        gtsam = self._gtsam
        initial = {k: T @ self._estimate[k] for k in self._order}
        for seg, (h, kf_id, mean) in list(self._segment_prior.items()):
            new_mean = T @ mean
            self._factors[h] = gtsam.PriorFactorPose3(
                _key(kf_id), gtsam.Pose3(new_mean), self._first_prior_noise(new_mean)
            )
            self._segment_prior[seg] = (h, kf_id, new_mean)
        if not self._colocation_enu:
            # map-frame co-location priors were expressed in the old local frame: they move along
            for kf_id, h in self._colocation_handle.items():
                f = self._factors[h]
                if self._offset is not None:  # O ~ identity: the measurement moves like a prior
                    self._factors[h] = gtsam.BetweenFactorPose3(
                        _okey(), _key(kf_id), gtsam.Pose3(T @ f.measured().matrix()), f.noiseModel()
                    )
                    continue
                self._factors[h] = gtsam.PriorFactorPose3(
                    _key(kf_id), gtsam.Pose3(T @ f.prior().matrix()), f.noiseModel()
                )
        # velocities are local-frame vectors: they turn with the frame (biases are in the IMU frame)
        R = T[:3, :3]
        for kf_id, (h, mean) in list(self._vel_prior.items()):
            f = self._factors[h]
            self._factors[h] = gtsam.PriorFactorVector(_vkey(kf_id), R @ mean, f.noiseModel())
            self._vel_prior[kf_id] = (h, R @ mean)
        self._isam = self._new_isam()
        graph = gtsam.NonlinearFactorGraph()
        handles = sorted(self._factors)
        for h in handles:
            graph.add(self._factors[h])
        theta = gtsam.Values()
        for kf_id in self._order:
            theta.insert(_key(kf_id), gtsam.Pose3(initial[kf_id]))
            if kf_id in self._imu_kfs:
                v, b = imu.velocity_bias(self, kf_id)
                theta.insert(_vkey(kf_id), R @ v)
                theta.insert(_bkey(kf_id), b)
        if self._offset is not None:
            theta.insert(_okey(), gtsam.Pose3(self._offset))
        result = self._isam.update(graph, theta)
        self._handle_to_index = {
            h: int(i) for h, i in zip(handles, result.getNewFactorsIndices(), strict=True)
        }
        for _ in range(max(1, self.options.extra_iterations)):
            self._isam.update()
        self._refresh()

    # ------------------------------------------------------------------ public API
    def add_keyframe(
        self,
        kf_id: int,
        timestamp: float,
        vio_from_kf: F64,
        rel_cov: F64 | None = None,
        prev_id: int | None = None,
        prev_from_kf: F64 | None = None,
        new_segment: bool = False,
    ) -> None:
        """Add a keyframe with its VIO-frame pose and the relative-pose factor to ``prev_id``.

        ``prev_id`` defaults to the last added keyframe; ``prev_from_kf`` defaults to the relative
        pose of the two VIO poses; ``rel_cov`` is the 6x6 covariance ([rot, trans]) of that relative
        pose (required unless this keyframe starts a segment). The first keyframe, and any with
        ``new_segment=True``, start a new segment with a loose prior instead.
        """
        if kf_id in self._kfs:
            raise ValueError(f"keyframe {kf_id} already added")
        vio_from_kf = np.asarray(vio_from_kf, dtype=np.float64).reshape(4, 4)
        gtsam = self._gtsam
        starts_segment = new_segment or not self._order
        if starts_segment:
            segment = self._segment_count
            self._segment_count += 1
            # Place the new segment with the best transform known so far (identity at start).
            local_from_vio = self._local_from_vio.get(segment - 1, np.eye(4)) if segment else np.eye(4)
            init = local_from_vio @ vio_from_kf
            factor = gtsam.PriorFactorPose3(_key(kf_id), gtsam.Pose3(init), self._first_prior_noise(init))
        else:
            prev_id = self._order[-1] if prev_id is None else prev_id
            if prev_id not in self._kfs:
                raise KeyError(f"previous keyframe {prev_id} unknown")
            if rel_cov is None:
                raise ValueError("rel_cov (6x6, [rot, trans]) is required for a relative-pose factor")
            prev = self._kfs[prev_id]
            segment = prev.segment
            rel = se3_inverse(prev.vio_from_kf) @ vio_from_kf if prev_from_kf is None else prev_from_kf
            init = self._estimate[prev_id] @ rel
            factor = gtsam.BetweenFactorPose3(
                _key(prev_id),
                _key(kf_id),
                gtsam.Pose3(rel),
                self._between_noise(np.asarray(rel_cov).reshape(6, 6)),
            )
        factors = [factor]
        extra = None
        vel_prior_mean: F64 | None = None
        if self._imu_params is not None:
            imu_factors, extra, vel_prior_mean = imu.imu_factors(self, kf_id, float(timestamp), segment)
            factors += imu_factors
        self._kfs[kf_id] = _Kf(kf_id, float(timestamp), vio_from_kf, segment)
        self._order.append(kf_id)
        handles = self._commit(factors, {kf_id: init}, extra_values=extra)
        h = handles[0]
        if vel_prior_mean is not None:  # factors: [pose factor, velocity prior, bias prior]
            self._vel_prior[kf_id] = (handles[1], vel_prior_mean)
        if starts_segment:
            self._segment_prior[segment] = (h, kf_id, init)
        else:
            assert prev_id is not None and rel_cov is not None
            self._between[kf_id] = (h, prev_id, np.asarray(rel_cov, dtype=np.float64).reshape(6, 6))

    def add_imu(self, samples: F64 | None) -> None:
        """IMU samples (K, 7) ``[t_s, w (3) rad/s, a (3) m/s^2]`` in the IMU frame, in time order.

        Integrated into an IMU factor when the next keyframe arrives (ignored without ``options.imu``).
        """
        if self._imu_params is None or samples is None:
            return
        a = np.asarray(samples, dtype=np.float64).reshape(-1, 7)
        if len(a) and not np.all(np.isfinite(a)):
            raise ValueError("IMU samples must be finite")
        self._imu_buf.extend(a)

    def update_vio_pose(self, kf_id: int, vio_from_kf: F64) -> None:
        """The front-end moved an already added keyframe (local BA): see ``update_vio_poses``."""
        self.update_vio_poses({kf_id: vio_from_kf})

    def update_vio_poses(self, updates: dict[int, F64], min_change_m: float = 1e-3) -> None:
        """The front-end's local BA moved already added keyframes: keep their VIO poses current and
        replace the relative-pose factors that touch them by the refined relative poses (same
        covariance). Keyframes are emitted before the local BA window has settled, so their emission-time
        relative poses can be decimetres off at sharp turns (docs/decisions.md)."""
        touched: set[int] = set()
        for kf_id, T in updates.items():
            if kf_id in self._kfs:
                self._kfs[kf_id].vio_from_kf = np.asarray(T, dtype=np.float64).reshape(4, 4)
                touched.add(kf_id)
        if not touched:
            return
        gtsam = self._gtsam
        factors, remove, owners = [], [], []
        for kf_id, (h, prev_id, cov) in self._between.items():
            if kf_id not in touched and prev_id not in touched:
                continue
            old = self._factors.get(h)
            rel = se3_inverse(self._kfs[prev_id].vio_from_kf) @ self._kfs[kf_id].vio_from_kf
            if old is not None:
                d = se3_inverse(old.measured().matrix()) @ rel
                if np.linalg.norm(d[:3, 3]) < min_change_m and abs(np.trace(d[:3, :3]) - 3.0) < 1e-6:
                    continue
            factors.append(
                gtsam.BetweenFactorPose3(
                    _key(prev_id), _key(kf_id), gtsam.Pose3(rel), self._between_noise(cov)
                )
            )
            remove.append(h)
            owners.append((kf_id, prev_id, cov))
        if not factors:
            return
        handles = self._commit(factors, {}, remove=remove)
        for h, (kf_id, prev_id, cov) in zip(handles, owners, strict=True):
            self._between[kf_id] = (h, prev_id, cov)

    def vio_pose(self, kf_id: int) -> F64:
        """The keyframe's current VIO-frame pose (4x4)."""
        return self._kfs[kf_id].vio_from_kf.copy()

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self._kfs

    @property
    def segment_count(self) -> int:
        return self._segment_count

    def predicted_antenna(self, kf_id: int) -> tuple[F64, F64]:
        """Predicted antenna position (3,) in the local frame and its 3x3 marginal covariance."""
        T = self._estimate[kf_id]
        R = T[:3, :3]
        lever = np.asarray(self.options.kf_from_antenna, dtype=np.float64)
        p = T[:3, 3] + R @ lever
        P = np.asarray(self._isam.marginalCovariance(_key(kf_id)))
        lx = np.array([[0, -lever[2], lever[1]], [lever[2], 0, -lever[0]], [-lever[1], lever[0], 0]])
        J = np.hstack([-R @ lx, R])  # d p / d [rot, trans] for T * Exp(xi)
        return p, J @ P @ J.T

    def add_gnss(self, kf_id: int, enu: F64, cov: F64) -> GnssDecision:
        """Fuse a GNSS fix (ENU position of the antenna, 3x3 covariance) at keyframe ``kf_id``.

        Returns the gate decision; a rejected fix is logged and not fused.
        """
        enu = np.asarray(enu, dtype=np.float64).reshape(3)
        cov = np.asarray(cov, dtype=np.float64).reshape(3, 3)
        if not (np.all(np.isfinite(enu)) and np.all(np.isfinite(cov))):
            raise ValueError("GNSS fix must be finite")
        kf = self._kfs[kf_id]
        pred, pred_cov = self.predicted_antenna(kf_id)
        r = enu - pred
        S = pred_cov + cov
        d = float(math.sqrt(max(0.0, float(r @ np.linalg.solve(S, r)))))
        o = self.options
        forced = False
        # Before the yaw is anchored (by GNSS spread or a co-location) the linearised prediction is
        # meaningless (a 30 degree yaw error is far from linear), so the gate only runs afterwards.
        # Map-frame co-location priors tie the local frame to the VIO frame, not to ENU: only absolute
        # (ENU) ones anchor it (else fixes after map-frame corrections are rejected as outliers).
        anchored = self._gnss_stage >= 2 or (self._colocation_enu and bool(self._colocation_handle))
        if anchored and d > o.gnss_gate_sigma:
            if 0 < o.gnss_max_consecutive_rejections <= self._consecutive_rejections:
                forced = True
                log.warning(
                    "GNSS fix at kf %d accepted after %d rejections in a row (Mahalanobis %.1f, %.2f m)",
                    kf_id, self._consecutive_rejections, d, float(np.linalg.norm(r)),
                )  # fmt: skip
            else:
                self._consecutive_rejections += 1
                res = float(np.linalg.norm(r))
                entry = {"kf_id": kf_id, "t": kf.timestamp, "mahalanobis": d, "residual_m": res}
                self.rejected_fixes.append(entry)
                log.warning(
                    "GNSS fix at kf %d (t=%.3f) rejected: Mahalanobis %.1f > %.1f, residual %.2f m",
                    kf_id, kf.timestamp, d, o.gnss_gate_sigma, float(np.linalg.norm(r)),
                )  # fmt: skip
                return GnssDecision(False, d, float(np.linalg.norm(r)))
        self._consecutive_rejections = 0
        gtsam = self._gtsam
        lever = np.asarray(o.kf_from_antenna, dtype=np.float64)
        if np.any(lever != 0):
            factor = gtsam.GPSFactorArm(_key(kf_id), enu, lever, _gaussian(cov))
        else:
            factor = gtsam.GPSFactor(_key(kf_id), enu, _gaussian(cov))
        kf.fixes.append((enu, cov))
        self.n_gnss_accepted += 1
        (h,) = self._commit([factor], {})
        self._gnss_handles.setdefault(kf_id, []).append(h)
        self._maybe_realign()
        return GnssDecision(True, d, float(np.linalg.norm(r)), forced)

    def add_colocation(self, kf_id: int, local_from_kf: F64, cov: F64) -> None:
        """Co-location factor: a prior on keyframe ``kf_id``'s local-frame pose, 6x6 cov [rot, trans].

        A newer co-location of the same keyframe replaces the older factor.
        """
        gtsam = self._gtsam
        if kf_id not in self._kfs:
            raise KeyError(f"keyframe {kf_id} unknown")
        pose = np.asarray(local_from_kf, dtype=np.float64).reshape(4, 4)
        noise = _gaussian(np.asarray(cov).reshape(6, 6))
        factor = gtsam.PriorFactorPose3(_key(kf_id), gtsam.Pose3(pose), noise)
        old = self._colocation_handle.pop(kf_id, None)
        (h,) = self._commit([factor], {}, remove=[old] if old is not None else None)
        self._colocation_handle[kf_id] = h

    def set_colocations(
        self, priors: dict[int, tuple[F64, F64]], enu: bool = False, scope: set[int] | None = None
    ) -> None:
        """Replace the co-location factors of the keyframes in ``scope`` (None: every keyframe) by
        ``priors`` (kf_id -> (local_from_kf, 6x6 cov)) in one update.

        A server correction is one consistent snapshot of the server's estimate expressed through one
        ``global_from_local``; priors kept from older corrections were expressed through older transforms
        and pulled against the new ones. The server sends one correction per front-end session, so an
        agent that lost tracking gets one for each: ``scope`` is the session's keyframes, and one
        session's snapshot must leave the other's priors alone (docs/decisions.md)."""
        colocation.set_colocations(self, priors, enu, scope)

    def add_correction(self, kf_id: int, global_from_kf: F64, global_from_local: F64, cov: F64) -> None:
        """A server correction: keyframe pose in the global frame + ``global_from_local`` (Sim(3)
        matrix ``[[sR, t], [0, 1]]``) -> co-location prior on ``local_from_kf``.

        ``local`` here is the frame the agent sent its keyframes in; if that was the VIO frame,
        pass ``global_from_local @ inv(local_from_vio)`` (see :meth:`local_from_vio`).
        """
        local_from_global = Sim3.from_matrix(np.asarray(global_from_local, dtype=np.float64)).inverse()
        self.add_colocation(kf_id, local_from_global.transform_pose(np.asarray(global_from_kf)), cov)

    # ------------------------------------------------------------------ re-initialisation on GNSS
    def _fix_pairs(self) -> tuple[F64, F64]:
        lever = np.asarray(self.options.kf_from_antenna, dtype=np.float64)
        est, meas = [], []
        for kf_id in self._order:
            T = self._estimate[kf_id]
            for enu, _ in self._kfs[kf_id].fixes:
                est.append(T[:3, 3] + T[:3, :3] @ lever)
                meas.append(enu)
        return np.asarray(est).reshape(-1, 3), np.asarray(meas).reshape(-1, 3)

    def _maybe_realign(self) -> None:
        if self._gnss_stage >= 2:
            return
        est, meas = self._fix_pairs()
        if len(est) == 0:
            return
        spread = float(np.max(np.linalg.norm(meas[:, :2] - meas[0, :2], axis=1)))
        if spread >= self.options.align_min_spread_m and len(est) >= 2:
            if self.options.gravity_aligned or len(est) < 3:
                T = yaw_translation_alignment(est, meas)
            else:
                T = rigid_alignment(est, meas)
            stage = 2
        elif self._gnss_stage == 0:
            T = se3(np.eye(3), meas.mean(axis=0) - est.mean(axis=0))
            stage = 1
        else:
            return
        log.info("second stage re-initialised on GNSS (stage %d, %d fixes)", stage, len(est))
        self._gnss_stage = stage
        self._rebuild(T)
