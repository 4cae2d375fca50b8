"""The pycolmap BA of :func:`hivemap.server.optim.global_bundle_adjustment`: its reconstruction and solve.

Monocular keyframes are one image each (a trivial rig). A stereo keyframe is a rig frame of two
images: the left camera as it is (distorted pixels), and the virtual rectified right camera the agent's
front-end measures ``u_right`` in (``hivemap.client.frontend.optim``): the left camera's pinhole
intrinsics without distortion, ``baseline`` metres along the left x axis. The rig's sensor_from_rig is
held constant, so every stereo observation measures depth in metres and the map cannot change scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, se3_inverse

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class BuiltProblem:
    """``rec``: the reconstruction; ``point_ids`` (M,): each input point's pycolmap id, -1 when it is not
    optimised (seen by fewer than two keyframes); ``right_sensors``: the right cameras' sensor ids (their
    sensor_from_rig is held constant); ``n_stereo``: right-image observations in the problem."""

    rec: Any
    point_ids: I64
    right_sensors: list[Any]
    n_stereo: int


def right_errors(
    cameras: Sequence[PinholeCamera],
    baselines: Sequence[float | None],
    camera_index: I64,
    world_from_cam: F64,
    points: F64,
    obs_kf: I64,
    obs_pt: I64,
    obs_ur: F64,
) -> F64:
    """Per observation: |predicted - measured| ``u_right`` (px); NaN where the observation is mono, its
    camera has no baseline, or the point is behind the camera."""
    err = np.full(len(obs_kf), np.nan)
    for k in np.unique(obs_kf):
        cam = cameras[int(camera_index[k])]
        b = baselines[int(camera_index[k])]
        if b is None:
            continue
        sel = np.flatnonzero(obs_kf == k)
        T = world_from_cam[k]
        pc = (points[obs_pt[sel]] - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ur = cam.fx * (pc[:, 0] - b) / z + cam.cx
        err[sel] = np.where(z > 1e-9, np.abs(ur - obs_ur[sel]), np.nan)
    return err


def build(
    cameras: Sequence[PinholeCamera],
    baselines: Sequence[float | None],
    camera_index: I64,
    world_from_cam: F64,
    points: F64,
    obs_kf: I64,
    obs_pt: I64,
    obs_uv: F64,
    obs_ur: F64,
) -> BuiltProblem:
    """The reconstruction of ``len(world_from_cam)`` keyframes: keyframe ``k`` is frame ``k + 1`` with its
    left image ``k + 1`` (and right image ``n + k + 1`` when it has stereo observations). ``obs_ur`` (K,):
    each observation's ``u_right`` in the virtual right camera, NaN for mono; only used where the
    keyframe's camera has a baseline."""
    import pycolmap

    n, m = len(world_from_cam), len(points)
    rec = pycolmap.Reconstruction()
    right_ids: dict[int, Any] = {}
    for ci, cam in enumerate(cameras):
        left = pycolmap.Camera(
            model="OPENCV", width=cam.width, height=cam.height,
            params=[cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist], camera_id=ci + 1,
        )  # fmt: skip
        rec.add_camera(left)
        rig = pycolmap.Rig(rig_id=ci + 1)
        rig.add_ref_sensor(left.sensor_id)
        b = baselines[ci]
        if b is not None:
            right = pycolmap.Camera(
                model="PINHOLE", width=cam.width, height=cam.height,
                params=[cam.fx, cam.fy, cam.cx, cam.cy], camera_id=len(cameras) + ci + 1,
            )  # fmt: skip
            rec.add_camera(right)
            rig.add_sensor(right.sensor_id, pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-b, 0.0, 0.0])))
            right_ids[ci] = right
        rec.add_rig(rig)
    stereo = np.isfinite(obs_ur) & np.array(
        [baselines[int(camera_index[k])] is not None for k in obs_kf], dtype=bool
    ).reshape(-1)
    order = np.argsort(obs_kf, kind="stable")
    starts = np.searchsorted(obs_kf[order], np.arange(n + 1))
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(m)]
    n_stereo = 0
    for k in range(n):
        ci = int(camera_index[k])
        sel = order[starts[k] : starts[k + 1]]
        frame = pycolmap.Frame(frame_id=k + 1, rig_id=ci + 1)
        frame.rig_from_world = pycolmap.Rigid3d(se3_inverse(world_from_cam[k])[:3, :])
        left_img = pycolmap.Image(
            name=f"kf{k}", keypoints=np.asarray(obs_uv[sel], dtype=np.float64).reshape(-1, 2),
            camera_id=ci + 1, image_id=k + 1,
        )  # fmt: skip
        left_img.frame_id = k + 1
        frame.add_data_id(left_img.data_id)
        images = [left_img]
        for j, o in enumerate(sel.tolist()):
            tracks[int(obs_pt[o])].append((k + 1, j))
        st = sel[stereo[sel]]
        if len(st) and ci in right_ids:
            # the right observation's row is the left keypoint's undistorted row (a rectified pair)
            v = cameras[ci].undistort_pixels(np.asarray(obs_uv[st], dtype=np.float64))[:, 1]
            right_img = pycolmap.Image(
                name=f"kf{k}r", keypoints=np.column_stack([obs_ur[st], v]),
                camera_id=right_ids[ci].camera_id, image_id=n + k + 1,
            )  # fmt: skip
            right_img.frame_id = k + 1
            frame.add_data_id(right_img.data_id)
            images.append(right_img)
            for j, o in enumerate(st.tolist()):
                tracks[int(obs_pt[o])].append((n + k + 1, j))
            n_stereo += len(st)
        rec.add_frame(frame)
        for img in images:
            rec.add_image(img)
        rec.register_frame(k + 1)
    point_ids = np.full(m, -1, dtype=np.int64)
    for p in range(m):
        # a point seen by one keyframe only (even with its stereo pair) ties no two poses together
        if len({(i - 1) % n for i, _ in tracks[p]}) < 2:
            continue
        track = pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in tracks[p]])
        point_ids[p] = rec.add_point3D(points[p], track)
    return BuiltProblem(rec, point_ids, [r.sensor_id for r in right_ids.values()], n_stereo)


def solve_pycolmap(
    cameras: Sequence[PinholeCamera],
    cam_baselines: Sequence[float | None],
    camera_index: I64,
    poses: F64,
    pts: F64,
    obs_kf: I64,
    obs_pt: I64,
    obs_uv: F64,
    obs_ur_kept: F64,
    fixed_kfs: set[int] | frozenset[int],
    options: Any,
) -> tuple[F64, F64, NDArray[np.bool_], int, int, bool]:
    """The gated problem of :func:`hivemap.server.optim.global_bundle_adjustment` (``options``: its
    ``BundleAdjustmentOptions``) solved by pycolmap: (poses, points, which points were in the problem,
    iterations, stereo observations, whether position priors held the gauge)."""
    import pycolmap

    n, m = len(poses), len(pts)
    built = build(cameras, cam_baselines, camera_index, poses, pts, obs_kf, obs_pt, obs_uv, obs_ur_kept)
    rec, point_ids = built.rec, built.point_ids
    stereo = built.n_stereo > 0

    ba_opts = pycolmap.BundleAdjustmentOptions()
    ba_opts.print_summary = False
    ba_opts.refine_focal_length = False
    ba_opts.refine_principal_point = False
    ba_opts.refine_extra_params = False
    ba_opts.ceres.solver_options.max_num_iterations = options.max_iterations
    ba_opts.ceres.solver_options.num_threads = options.num_threads
    ba_opts.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
    ba_opts.ceres.loss_function_scale = options.huber_px
    ba_opts.ceres.solver_options.function_tolerance = options.function_tolerance
    # Beyond 1000 images COLMAP switches to ITERATIVE_SCHUR, ~5x slower here than the direct sparse
    # Schur solver (2000 keyframes: 176 s before this change).
    ba_opts.ceres.max_num_images_direct_sparse_cpu_solver = 100000
    ba_opts.refine_sensor_from_rig = False  # the stereo baseline is calibrated: it holds the scale
    config = pycolmap.BundleAdjustmentConfig()
    for k in range(n):
        config.add_image(k + 1)
        if k in fixed_kfs:
            config.set_constant_rig_from_world_pose(k + 1)
        if rec.exists_image(n + k + 1):
            config.add_image(n + k + 1)
    for sensor in built.right_sensors:
        config.set_constant_sensor_from_rig_pose(sensor)
    # pycolmap's pose-prior BA needs >= 3 priors (DESIGN.md); the priors then fix the gauge. Stereo
    # observations hold the scale themselves: one held keyframe fixes the remaining 6 DoF.
    use_priors = options.position_prior_m is not None and n >= 3 and not stereo
    if len(fixed_kfs) < 2 and not use_priors and not stereo:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    for cam_id in rec.cameras:
        config.set_constant_cam_intrinsics(cam_id)
    if use_priors:
        assert options.position_prior_m is not None
        sigma2 = float(options.position_prior_m) ** 2
        priors = []
        for k in range(n):
            prior = pycolmap.PosePrior(
                position=poses[k, :3, 3].copy(),
                position_covariance=np.eye(3) * sigma2,
                coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
            )
            prior.corr_data_id = rec.image(k + 1).data_id
            priors.append(prior)
        prior_opts = pycolmap.PosePriorBundleAdjustmentOptions()
        prior_opts.prior_position_fallback_stddev = float(options.position_prior_m)
        adjuster = pycolmap.create_pose_prior_bundle_adjuster(ba_opts, prior_opts, config, priors, rec)
    else:
        adjuster = pycolmap.create_default_bundle_adjuster(ba_opts, config, rec)
    summary = adjuster.solve()
    out_poses = poses.copy()
    for k in range(n):
        cw = np.asarray(rec.image(k + 1).cam_from_world().matrix())
        out_poses[k] = se3_inverse(se3(cw[:3, :3], cw[:3, 3]))
    out_pts = pts.copy()
    for p in range(m):
        if point_ids[p] >= 0:
            out_pts[p] = rec.point3D(int(point_ids[p])).xyz
    iters = int(getattr(getattr(summary, "ceres_summary", summary), "num_successful_steps", 0) or 0)
    return out_poses, out_pts, point_ids >= 0, iters, built.n_stereo, use_priors
