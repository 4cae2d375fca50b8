"""Global BA of a metric map with stereo observations (issue 23 item 4): CPU time on one core for maps of
500 / 1000 / 2000 keyframes shaped like factory01's (about 300 map points seen per keyframe, tracks of 3-10
keyframes, about 70% of the observations with a stereo match), and the scale error before and after.

Each keypoint has an ORB pyramid level (octave l with share ~ 1.2^-l, l = 0..7) and noise ``NOISE_PX``
times 1.2^l; consecutive keyframes are joined by odometry between factors at the start poses' relative pose
with the pose graph's default sigmas (the stereo BA in gtsam, :mod:`hivemap.server.ba_gtsam`); as the
start map is scaled, they carry its scale error (``--no-odometry``: without them).

Run: ``python bench/global_ba.py [--sizes 500 1000 2000] [--mono] [--scale-error 0.02] [--solver pycolmap]``
(``--mono``: the same maps without their stereo observations, two held keyframes, for comparison;
``--scale-error``: how far the start map's scale is off; ``--solver``: the stereo BA's solver).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3, so3_exp

CAMERA = PinholeCamera(640, 480, 420.0, 420.0, 320.0, 240.0, (-0.05, 0.01, 0.0005, -0.0003))
BASELINE = 0.11  # m
STEP = 0.3  # m between keyframes
POINTS_SEEN = 300
STEREO_SHARE = 0.7
NOISE_PX = 0.7
OUTLIER_SHARE = 0.01


def synthetic_map(n: int, seed: int, scale_error: float = 0.02) -> dict[str, np.ndarray]:
    """Keyframes every ``STEP`` m along a gently winding path, the camera looking sideways; keyframe ``k``
    starts ``POINTS_SEEN / 6.5`` points (depth 4-25 m) that keyframes ``k .. k + L - 1`` observe, L drawn
    from 3-10, so each keyframe sees ~``POINTS_SEEN``. Returns the truth, the perturbed start (poses off by
    3 cm / 0.3 deg and the whole map ``scale_error`` too large about keyframe 0, points off by 3 cm) and
    observations with ``NOISE_PX`` noise, ``OUTLIER_SHARE`` of them gross outliers."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0, 0.01, n))
    pos = np.cumsum(np.stack([STEP * np.cos(heading), rng.normal(0, 0.01, n), STEP * np.sin(heading)], 1), 0)
    truth = np.array([se3(so3_exp([0.0, -heading[k], 0.0]), pos[k]) for k in range(n)])
    per_kf = POINTS_SEEN / 6.5
    pts, obs_kf, obs_pt = [], [], []
    for k in range(n):
        for _ in range(rng.poisson(per_kf)):
            length = int(rng.integers(3, 11))
            views = list(range(k, min(n, k + length)))
            if len(views) < 2:
                continue
            z = rng.uniform(4, 25)
            # within the field of view of every keyframe of its track (each is STEP further along x)
            half = 0.7 * z * CAMERA.cx / CAMERA.fx
            x = rng.uniform(STEP * (len(views) - 1) - half, half)
            y = rng.uniform(-0.6, 0.6) * z * CAMERA.cy / CAMERA.fy
            pts.append(truth[k, :3, :3] @ np.array([x, y, z]) + truth[k, :3, 3])
            obs_kf += views
            obs_pt += [len(pts) - 1] * len(views)
    P = np.array(pts)
    okf, opt = np.array(obs_kf), np.array(obs_pt)
    uv = np.empty((len(okf), 2))
    ur = np.full(len(okf), np.nan)
    for k in range(n):
        sel = np.flatnonzero(okf == k)
        pc = (P[opt[sel]] - truth[k, :3, 3]) @ truth[k, :3, :3]
        uv[sel], _ = CAMERA.project(pc)
        ur[sel] = CAMERA.fx * (pc[:, 0] - BASELINE) / pc[:, 2] + CAMERA.cx
    levels = np.arange(8)
    octave = rng.choice(levels, len(okf), p=1.2**-levels / (1.2**-levels).sum()).astype(np.uint8)
    sigma = NOISE_PX * 1.2 ** octave.astype(np.float64)
    uv += rng.normal(0, 1, uv.shape) * sigma[:, None]
    ur += rng.normal(0, 1, len(ur)) * sigma
    ur[rng.random(len(ur)) > STEREO_SHARE] = np.nan
    bad = rng.random(len(uv)) < OUTLIER_SHARE
    uv[bad] += rng.uniform(-40, 40, (int(bad.sum()), 2))
    c = truth[0, :3, 3]
    init = truth.copy()
    init[:, :3, 3] = c + (1 + scale_error) * (truth[:, :3, 3] - c)
    for k in range(1, n):
        init[k] = init[k] @ se3(so3_exp(rng.normal(0, 0.005, 3)), rng.normal(0, 0.03, 3))
    P0 = c + (1 + scale_error) * (P - c) + rng.normal(0, 0.03, P.shape)
    return {"truth": truth, "init": init, "points": P0, "obs_kf": okf, "obs_pt": opt, "uv": uv, "ur": ur,
            "octave": octave}  # fmt: skip


def _scale_error(est: np.ndarray, ref: np.ndarray) -> float:
    a, b = est - est.mean(0), ref - ref.mean(0)
    u, d, vt = np.linalg.svd(b.T @ a / len(a))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt))
    return float((d * sign).sum() / (a**2).sum(1).mean() - 1.0)


def bench(n: int, mono: bool, scale_error: float, solver: str = "gtsam", odometry_edges: bool = True) -> None:
    from hivemap.server.ba_gtsam import OdometryEdge
    from hivemap.server.backend.options import OptimiseOptions
    from hivemap.server.optim import BundleAdjustmentOptions, global_bundle_adjustment

    o = OptimiseOptions()
    sr, st = o.pose_graph_sigma_rot, o.pose_graph_sigma_trans
    odometry = [OdometryEdge(k, k + 1, sr, st) for k in range(n - 1)] if odometry_edges else []
    d = synthetic_map(n, seed=n, scale_error=scale_error)
    ur = np.full_like(d["ur"], np.nan) if mono else d["ur"]
    track = np.bincount(d["obs_pt"])
    t0, w0 = time.process_time(), time.perf_counter()
    res = global_bundle_adjustment(
        [CAMERA], np.zeros(n, np.int64), d["init"], d["points"], d["obs_kf"], d["obs_pt"], d["uv"],
        {0, 1} if mono else {0},
        BundleAdjustmentOptions(max_iterations=30, num_threads=1, stereo_solver=solver),
        obs_ur=ur, baselines=[BASELINE], obs_octave=d["octave"],
        odometry=odometry,
    )  # fmt: skip
    cpu, wall = time.process_time() - t0, time.perf_counter() - w0
    truth = d["truth"]
    s0 = _scale_error(d["init"][:, :3, 3], truth[:, :3, 3])
    s1 = _scale_error(res.world_from_cam[:, :3, 3], truth[:, :3, 3])
    e0 = np.linalg.norm(d["init"][:, :3, 3] - truth[:, :3, 3], axis=1).mean()
    e1 = np.linalg.norm(res.world_from_cam[:, :3, 3] - truth[:, :3, 3], axis=1).mean()
    n_obs = len(d["obs_kf"])
    print(f"global BA {n} keyframes ({'mono' if mono else 'stereo ' + solver}): {n_obs} observations "
          f"({n_obs / n:.0f} per keyframe, tracks {track.min()}-{track.max()} mean {track.mean():.1f}),"
          f" {int(res.extras.get('n_stereo', 0))} stereo; CPU {cpu:.1f} s (wall {wall:.1f} s, 1 thread), "
          f"{res.iterations} iterations, rmse {res.initial_rmse_px:.2f} -> {res.final_rmse_px:.2f} px, "
          f"scale error {s0 * 100:+.2f} -> {s1 * 100:+.3f} %, mean position error {e0 * 100:.1f} -> "
          f"{e1 * 100:.1f} cm, accepted {res.accepted}", flush=True)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[500, 1000, 2000])
    ap.add_argument("--mono", action="store_true", help="also without the stereo observations")
    ap.add_argument("--scale-error", type=float, default=0.02, help="the start map's scale error (0.02: 2%%)")
    ap.add_argument(
        "--no-odometry", action="store_true", help="no between factors (they carry the start's scale)"
    )
    ap.add_argument("--solver", choices=["gtsam", "pycolmap"], default="gtsam", help="the stereo BA's solver")
    args = ap.parse_args(argv)
    for n in args.sizes:
        bench(
            n,
            mono=False,
            scale_error=args.scale_error,
            solver=args.solver,
            odometry_edges=not args.no_odometry,
        )
        if args.mono:
            bench(n, mono=True, scale_error=args.scale_error)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
