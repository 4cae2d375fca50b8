"""The global BA of metric (stereo) maps in gtsam, a factor graph solved by Levenberg-Marquardt.

- A stereo observation is one ``GenericStereoFactor3D`` (u_left, u_right, v in undistorted pixels,
  ``Cal3_S2Stereo`` with the keyframe's baseline), so each of u_left, u_right and v is weighted once and
  the baseline holds the metric scale; a mono observation is a ``GenericProjectionFactorCal3_S2``.
- Each observation's sigma is that of its keypoint's pyramid level, ``scale_factor ** octave`` px (the
  ORB pyramid the agents' front-ends detect in), under a Huber loss whose thresholds are ORB-SLAM's
  chi-square 95% gates (2 and 3 dof).
- Between factors join each agent's consecutive keyframes with the relative pose they have (what the
  agent's VIO measured, as moved rigidly by the pose graph) and the pose graph's odometry sigmas
  (``optimise.odometry_sigmas``), so the BA cannot bend a trajectory the IMU holds straight.
- One held keyframe per map is the gauge (a strong prior); the stereo observations hold the scale.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

# sqrt of the 95% chi-square quantiles of 2 and 3 dof (ORB-SLAM's gates): Huber thresholds, whitened
HUBER_MONO = float(np.sqrt(5.991))
HUBER_STEREO = float(np.sqrt(7.815))
HELD_SIGMA = 1e-6  # the held keyframe's prior (rad, m): the gauge


@dataclass(frozen=True)
class OdometryEdge:
    """A between factor ``cam_i_from_cam_j`` at the input poses' relative pose, sigmas rad and m."""

    i: int
    j: int
    sigma_rot: float
    sigma_trans: float


@dataclass
class GtsamBAOutput:
    """Solved poses and points (points not in the problem keep their input), which points were in the
    problem, LM iterations, stereo factors, and the factor graph's error before and after."""

    world_from_cam: F64
    points: F64
    in_problem: NDArray[np.bool_]
    iterations: int
    n_stereo: int
    error_before: float
    error_after: float


def undistorted(cameras: Sequence[PinholeCamera], camera_index: I64, obs_kf: I64, obs_uv: F64) -> F64:
    """(K, 2): every observation in its camera's undistorted pinhole pixels."""
    out = np.asarray(obs_uv, dtype=np.float64).reshape(-1, 2).copy()
    cam_of_obs = camera_index[obs_kf] if len(obs_kf) else np.zeros(0, dtype=np.int64)
    for ci in np.unique(cam_of_obs):
        sel = np.flatnonzero(cam_of_obs == ci)
        out[sel] = cameras[int(ci)].undistort_pixels(out[sel])
    return out


def _pose3(T: F64) -> Any:
    import gtsam

    T = np.asarray(T, dtype=np.float64)
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3].copy())


def solve(
    cameras: Sequence[PinholeCamera],
    baselines: Sequence[float | None],
    camera_index: I64,
    world_from_cam: F64,
    points: F64,
    obs_kf: I64,
    obs_pt: I64,
    obs_uv: F64,
    obs_ur: F64,
    obs_octave: NDArray[np.integer] | None,
    fixed_kfs: set[int] | frozenset[int],
    odometry: Sequence[OdometryEdge] = (),
    *,
    max_iterations: int = 30,
    relative_error_tol: float = 1e-6,
    scale_factor: float = 1.2,
    octave_weights: bool = True,
    cpu_budget_s: float = float("inf"),
) -> GtsamBAOutput:
    """Refine ``world_from_cam`` (N, 4, 4) and ``points`` (M, 3) from observations ``obs_kf``, ``obs_pt``,
    ``obs_uv`` (K, 2; distorted pixels), ``obs_ur`` (K,; the virtual right camera's u, NaN: mono) and
    ``obs_octave`` (K,; None or ``octave_weights`` False: every sigma 1 px). Observations must already be
    gated (the caller drops outliers). A point seen by fewer than two keyframes is left out (it ties no
    two poses together). ``fixed_kfs``: held keyframes (at least one). LM stops after ``max_iterations``,
    when the error falls by less than ``relative_error_tol``, or once ``cpu_budget_s`` of CPU is spent."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    poses = np.asarray(world_from_cam, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    n, m = len(poses), len(pts)
    if not fixed_kfs:
        raise ValueError("the BA needs a held keyframe (gauge)")
    uv = undistorted(cameras, camera_index, obs_kf, obs_uv)
    cam_of_obs = camera_index[obs_kf] if len(obs_kf) else np.zeros(0, dtype=np.int64)
    has_b = np.array([b is not None for b in baselines], dtype=bool)
    stereo = np.isfinite(obs_ur) & (has_b[cam_of_obs] if len(obs_kf) else np.zeros(0, dtype=bool))
    # points seen by at least two keyframes
    pairs = np.unique(np.column_stack([obs_pt, obs_kf]), axis=0) if len(obs_kf) else np.zeros((0, 2), int)
    n_kf_of_pt = np.bincount(pairs[:, 0], minlength=m) if len(pairs) else np.zeros(m, dtype=np.int64)
    in_problem = n_kf_of_pt >= 2
    use = in_problem[obs_pt]
    octs = np.zeros(len(obs_kf), dtype=np.int64)
    if obs_octave is not None and octave_weights:
        octs = np.clip(np.asarray(obs_octave, dtype=np.int64), 0, 31)

    noise_cache: dict[tuple[int, int], Any] = {}

    def noise(dim: int, octave: int) -> Any:
        key = (dim, octave)
        if key not in noise_cache:
            base = gtsam.noiseModel.Isotropic.Sigma(dim, float(scale_factor**octave))
            huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_STEREO if dim == 3 else HUBER_MONO)
            noise_cache[key] = gtsam.noiseModel.Robust.Create(huber, base)
        return noise_cache[key]

    k_mono = [gtsam.Cal3_S2(c.fx, c.fy, 0.0, c.cx, c.cy) for c in cameras]
    k_stereo = [
        None if b is None else gtsam.Cal3_S2Stereo(c.fx, c.fy, 0.0, c.cx, c.cy, float(b))
        for c, b in zip(cameras, baselines, strict=True)
    ]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(n):
        values.insert(X(k), _pose3(poses[k]))
    for pi in np.flatnonzero(in_problem):
        values.insert(L(int(pi)), np.asarray(pts[pi], dtype=np.float64))
    n_stereo = 0
    for o in np.flatnonzero(use):
        k, p, ci = int(obs_kf[o]), int(obs_pt[o]), int(cam_of_obs[o])
        ks = k_stereo[ci]
        octave = int(octs[o]) if octave_weights else 0
        if stereo[o] and ks is not None:
            meas = gtsam.StereoPoint2(float(uv[o, 0]), float(obs_ur[o]), float(uv[o, 1]))
            graph.add(gtsam.GenericStereoFactor3D(meas, noise(3, octave), X(k), L(p), ks))
            n_stereo += 1
        else:
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    np.array([uv[o, 0], uv[o, 1]]), noise(2, octave), X(k), L(p), k_mono[ci]
                )
            )
    for e in odometry:
        rel = np.linalg.solve(poses[e.i], poses[e.j])
        sig = gtsam.noiseModel.Diagonal.Sigmas(np.array([e.sigma_rot] * 3 + [e.sigma_trans] * 3))
        graph.add(gtsam.BetweenFactorPose3(X(e.i), X(e.j), _pose3(rel), sig))
    held = gtsam.noiseModel.Isotropic.Sigma(6, HELD_SIGMA)
    for k in sorted(fixed_kfs):
        graph.add(gtsam.PriorFactorPose3(X(int(k)), _pose3(poses[int(k)]), held))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setVerbosityLM("SILENT")
    error_before = float(graph.error(values))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    # LM step by step, so that a large map stops within its CPU budget (one BA process, one core)
    t0 = time.process_time()
    for _ in range(int(max_iterations)):
        before = opt.error()
        opt.iterate()
        after = opt.error()
        if not after < before * (1.0 - relative_error_tol) or opt.lambda_() > params.getlambdaUpperBound():
            break
        if time.process_time() - t0 > cpu_budget_s:
            break
    result = opt.values()
    out_poses = poses.copy()
    for k in range(n):
        out_poses[k] = result.atPose3(X(k)).matrix()
    for k in fixed_kfs:
        out_poses[int(k)] = poses[int(k)]  # exactly as given
    out_pts = pts.copy()
    for pi in np.flatnonzero(in_problem):
        out_pts[pi] = result.atPoint3(L(int(pi)))
    error_after = float(graph.error(result))
    iters = int(opt.iterations())
    return GtsamBAOutput(out_poses, out_pts, in_problem, iters, n_stereo, error_before, error_after)
