"""Front-end throughput, memory and accuracy on one core.

    .venv/bin/python bench/frontend.py                          # synthetic scene (self-contained)
    .venv/bin/python bench/frontend.py --dataset DATA/factory01/uav1 [--max-frames N] [--no-imu]
        [--option imu_gate_strong_scale=1.0 ...]                # FrontendOptions fields
        [--markers [--markers-every K]]                         # + marker detection (issue 25)

Prints frames/s of ``Frontend.process`` alone (images are pre-loaded / pre-rendered outside the
timed region), peak RSS over the run, and ATE (evo, SE(3) alignment) when ground truth exists.
A dataset with a ``markers.yaml`` has the other agents' carriers masked out of tracking, as the agent
does (``--option carrier_mask=False`` to see tracking without it); the mask's detector runs inside
``process``. ``--markers``: the agent's rendezvous stream (``hivemap.client.rendezvous``) runs in the
timed region after each frame (reusing the mask's detections where there is one), on the carriers
of the dataset's ``markers.yaml`` or, without one, a stand-in team
(a board on another agent): the detector's cost is about the same whether a carrier is in view.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def _ate(est: np.ndarray, gt: np.ndarray, times: np.ndarray) -> tuple[float, float, float]:
    from evo.core import geometry, metrics
    from evo.core.trajectory import PoseTrajectory3D

    te = PoseTrajectory3D(poses_se3=list(est), timestamps=times)
    tg = PoseTrajectory3D(poses_se3=list(gt), timestamps=times)
    te.align(tg)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((tg, te))
    rmse = float(ape.get_statistic(metrics.StatisticsType.rmse))
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    _r, _t, s = geometry.umeyama_alignment(est[:, :3, 3].T, gt[:, :3, 3].T, True)
    return rmse, path, float(s)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dataset", default=None, help="agent folder (EuRoC layout); default: synthetic scene")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--frames", type=int, default=300, help="synthetic sequence length")
    ap.add_argument("--no-imu", action="store_true")
    ap.add_argument("--contrast", default=None, help="stretch | clahe | off (default: the front-end's)")
    ap.add_argument("--tum-out", default=None, help="write the VIO body trajectory (TUM) here")
    ap.add_argument("--option", action="append", default=[], help="FrontendOptions field=value (repeat)")
    ap.add_argument("--markers", action="store_true", help="also run the agent's marker detection")
    ap.add_argument("--markers-every", type=int, default=2, help="detect on every k-th frame")
    args = ap.parse_args()
    cv2.setNumThreads(1)

    from hivemap.client.frontend.tracker import Frontend, TrackingState
    from hivemap.maps.geometry import se3_inverse

    imu = None
    gt = None
    if args.dataset:
        from hivemap.client.dataset import load_dataset

        ds = load_dataset(args.dataset)
        rig = ds.rig
        n = len(ds.frames) if args.max_frames is None else min(args.max_frames, len(ds.frames))
        times = ds.frames.timestamps[:n]
        if not args.no_imu and len(ds.imu):
            imu = ds.imu.copy()
            if imu[0, 0] > 1e12:  # ns
                imu[:, 0] *= 1e-9
        if ds.groundtruth is not None:
            gt = ds.groundtruth_at_frames()[:n]

        def load(i: int) -> tuple[np.ndarray, np.ndarray]:
            a, b = ds.frames.load(i)
            assert b is not None
            return a, b

        imu_params = dict(ds.imu_noise) if imu is not None else None
        name = ds.agent_id
    else:
        from hivemap.client.frontend.synthetic import make_sequence

        seq = make_sequence(args.frames)
        rig = seq.rig
        n = args.frames
        times = seq.times
        imu = None if args.no_imu else seq.imu
        gt = seq.world_from_body
        load = seq.images
        imu_params = None if args.no_imu else {}
        name = "synthetic"
    assert rig is not None
    import ast
    from dataclasses import replace

    from hivemap.client.frontend.options import FrontendOptions

    opts = FrontendOptions() if args.contrast is None else replace(FrontendOptions(), contrast=args.contrast)
    opts = replace(opts, **{k: ast.literal_eval(v) for k, v in (a.split("=", 1) for a in args.option)})
    fe = Frontend(rig, opts, imu_params=imu_params)
    if args.dataset:
        from pathlib import Path

        from hivemap.maps.markers import LAYOUT_FILE, load_layout

        layout = Path(args.dataset) / LAYOUT_FILE
        if layout.is_file():  # as the agent does: other agents' carriers masked out of tracking
            fe.use_carriers(load_layout(layout), name)
    rv = _rendezvous(args, rig.left, name) if args.markers else None
    busy = 0.0
    cpu = 0.0
    refs = []
    states: dict[str, int] = {}
    t_prev = -np.inf
    losses = 0
    was_lost = False
    for i in range(n):
        left, right = load(i)
        t = float(times[i])
        samples = None
        if imu is not None:
            samples = imu[(imu[:, 0] > t_prev) & (imu[:, 0] <= t)]
        t_prev = t
        t0 = time.perf_counter()
        c0 = time.process_time()
        res = fe.process(t, left, right, samples)
        if rv is not None:
            rv.observe(t, left, res, fe)
        busy += time.perf_counter() - t0
        cpu += time.process_time() - c0
        states[res.state.value] = states.get(res.state.value, 0) + 1
        lost = res.state == TrackingState.LOST
        losses += int(lost and not was_lost)
        was_lost = lost
        if fe.keyframes and res.state.tracked:
            k = max(fe.keyframes)
            refs.append((i, res.session, k, se3_inverse(fe.keyframes[k].T_wc) @ res.world_from_cam))
        fe.poll_events()
        if (i + 1) % 200 == 0:
            print(f"  {i + 1}/{n} frames, {(i + 1) / busy:.1f} fps, kfs {len(fe.keyframes)}", flush=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(
        f"agent {name}: {n} frames, {n / busy:.1f} fps wall, {n / cpu:.1f} fps CPU time "
        f"(one thread, process() only), peak RSS {peak_mb:.0f} MB"
    )
    st = fe.stats
    print(f"  states {states}, tracking losses {losses}, sessions {fe.session + 1}, kfs {st.keyframes}")
    print(
        f"  weak {st.weak_frames}, lost {st.lost_frames}, relocalised {st.relocalizations}, "
        f"visual poses refused by the IMU gate {st.imu_rejections}, keyframes while lost {st.lost_keyframes}"
    )
    print("  time per frame (ms): " + ", ".join(f"{k} {1e3 * v / n:.1f}" for k, v in fe.stats.timing.items()))
    if rv is not None:
        per = 1e3 * rv.cpu_s / max(rv.frames_run, 1)
        print(
            f"  markers: detector on {rv.frames_run} frames, {per:.1f} ms CPU each, "
            f"{rv.observations} observations"
        )
    cm = fe.carrier_mask
    if cm is not None:
        st_m = cm.stats
        frac = 100 * float(np.mean(st_m.masked_fraction)) if st_m.masked_fraction else 0.0
        print(
            f"  carrier mask: detector {1e3 * st_m.detect_s / max(st_m.frames, 1):.1f} ms per frame, "
            f"{st_m.frames_masked} frames masked (mean {frac:.1f}% of cam0), by pose {st_m.by_pose}, "
            f"by quads {st_m.by_quads}, held {st_m.held}"
        )
    if gt is not None and refs:
        sess = fe.session
        rows = [r for r in refs if r[1] == sess and r[2] in fe.keyframes]
        idx = np.array([r[0] for r in rows])
        est = np.array([fe.keyframes[k].T_wc @ rel @ fe.cam_from_body for _, _, k, rel in rows])
        rmse, path, scale = _ate(est, gt[idx], np.asarray(times)[idx])
        print(
            f"  ATE RMSE {rmse:.3f} m over {path:.1f} m path = {100 * rmse / path:.3f}% "
            f"(session {sess}, {len(idx)} frames), Sim3 scale {scale:.4f}"
        )
        if args.tum_out:
            from hivemap.maps.geometry import quat_wxyz_from_rotmat

            with open(args.tum_out, "w") as f:
                for j, T in zip(idx, est, strict=True):
                    w, x, y, z = quat_wxyz_from_rotmat(T[:3, :3])
                    f.write(f"{times[j]:.9f} {T[0, 3]} {T[1, 3]} {T[2, 3]} {x} {y} {z} {w}\n")


def _rendezvous(args: argparse.Namespace, camera: Any, own: str) -> Any:
    from pathlib import Path

    from hivemap.client.frontend.markers import MarkerOptions
    from hivemap.client.rendezvous import RendezvousSource
    from hivemap.maps.markers import LAYOUT_FILE, Carrier, Marker, load_layout

    layout = Path(args.dataset or ".") / LAYOUT_FILE
    if args.dataset and layout.is_file():
        carriers = load_layout(layout)
    else:
        sq = 0.25 * np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], dtype=np.float64)
        markers = tuple(Marker(i, 0.5, sq + [0.6 * (i % 2), 0.6 * (i // 2), 1.0]) for i in range(4))
        carriers = {"other": Carrier("other", "DICT_4X4_50", np.eye(4), markers)}
    return RendezvousSource(camera, carriers, own, MarkerOptions(every_k_frames=args.markers_every))


if __name__ == "__main__":
    main()
