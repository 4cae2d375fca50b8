"""hivemap's single-agent front-end next to ORB-SLAM3 stereo-inertial on the same rendered worlds.

    .venv/bin/python bench/orbslam3.py WORLD [WORLD ...] --hivemap EXP_OUT [--agents uav1,ugv]
        [--venv DIR] [--out DIR] [--rerun] [--no-pace]

``WORLD`` is a render folder (``hivemap sim render --out``), ``EXP_OUT`` the ``--out`` of a
``hivemap eval experiment --modes single`` run over the same worlds: its ``results/<world>/single.json``
gives hivemap's figures. ORB-SLAM3 (the ``pyorbslam3`` wheel) runs in a venv of its own, created once
under ``--venv`` (default ``$HIVEMAP_ORBSLAM3_VENV`` or ``~/.cache/hivemap/orbslam3-venv``); it is no
dependency of hivemap. Per world and agent it writes, under ``--out`` (default ``EXP_OUT/orbslam3``),
the settings YAML, ORB-SLAM3's log, its trajectory (TUM, body frame) and ``stats.json``; a finished
run is reused unless ``--rerun``. Then one table: agent, hivemap ATE (m, % of path), ORB-SLAM3 ATE
(m, %), the share of frames each trajectory covers, ORB-SLAM3's tracking losses and maps; means over
agents. Both ATEs are evo's, SE(3)-aligned, against the body ground truth, through ``hivemap.eval``.
With the default ``--out`` the experiment's report (``EXP_OUT/report.md``) is re-written with a
section that sets both side by side (:mod:`hivemap.eval.peer`).

The acceptance run (issue 28: full-length factory01, its default world and seed 1)::

    .venv/bin/hivemap eval experiment --scenarios factory01 --modes single --seeds default,1 \\
        --data data --out data/exp-orb
    .venv/bin/python bench/orbslam3.py data/factory01 data/factory01-s1 --hivemap data/exp-orb

Exit status: 0 when every agent has both figures (or when run bare, as ``make bench`` does: nothing
to compare), 1 when an ORB-SLAM3 run crashed or gave no trajectory or hivemap's result is missing
(each named on a ``FAILED:`` line), 2 when the venv or the vocabulary could not be made. A run that
lost tracking or started new maps is not a failure; it is named on a ``note:`` line and in the
table, and its ATE covers its largest map (ORB-SLAM3's own EuRoC output).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

PACKAGES = ("pyorbslam3", "opencv-python-headless")
VENV_ENV = "HIVEMAP_ORBSLAM3_VENV"
# ORB-SLAM3's EuRoC stereo-inertial example settings for the ORB extractor and the stereo depth limit.
ORB_SETTINGS = {
    "ORBextractor.nFeatures": 1200,
    "ORBextractor.scaleFactor": 1.2,
    "ORBextractor.nLevels": 8,
    "ORBextractor.iniThFAST": 20,
    "ORBextractor.minThFAST": 7,
    "ThDepth": 60.0,
}
# ORB-SLAM3's settings reader requires the viewer block even with the viewer off.
VIEWER_SETTINGS = {
    "Viewer.KeyFrameSize": 0.05,
    "Viewer.KeyFrameLineWidth": 1.0,
    "Viewer.GraphLineWidth": 0.9,
    "Viewer.PointSize": 2.0,
    "Viewer.CameraSize": 0.08,
    "Viewer.CameraLineWidth": 3.0,
    "Viewer.ViewpointX": 0.0,
    "Viewer.ViewpointY": -0.7,
    "Viewer.ViewpointZ": -1.8,
    "Viewer.ViewpointF": 500.0,
}


class BenchError(Exception):
    """The comparison cannot run at all (venv, vocabulary)."""


# ------------------------------------------------------------------------------------------ setup
def ensure_venv(venv: Path) -> Path:
    """The venv's python with pyorbslam3 importable; creates the venv and installs into it once."""
    py = venv / "bin" / "python"
    probe = [str(py), "-c", "import pyorbslam3, cv2"]
    if py.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    print(f"creating the ORB-SLAM3 venv {venv} and installing {', '.join(PACKAGES)} ...", flush=True)
    steps = [[sys.executable, "-m", "venv", str(venv)], [str(py), "-m", "pip", "install", "-q", *PACKAGES]]
    for cmd in steps:
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise BenchError(f"install failed: {' '.join(cmd)}\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    r = subprocess.run(probe, capture_output=True, text=True)
    if r.returncode != 0:
        raise BenchError(f"pyorbslam3 installed in {venv} but does not import:\n{r.stderr[-2000:]}")
    return py


def ensure_vocabulary(venv: Path) -> Path:
    """hivemap's shipped vocabulary in DBoW2's text format, re-exported when the vocabulary changes.

    Why hivemap's own tree and not ORB-SLAM3's ORBvoc.txt: that file is a download, which this bench
    may not depend on, and a vocabulary trained here anyway should be the one hivemap uses, so the two
    systems' place recognition starts from the same words. Its structure is DBoW2's (k-ary tree,
    k-majority centres of 256-bit ORB descriptors from OpenCV's pattern, which ORB-SLAM3's extractor
    shares, tf-idf word weights, L1 score), so the export is a change of file format only.
    """
    from hivemap.maps.vocabulary import default_vocabulary

    try:
        vocab = default_vocabulary()
    except (FileNotFoundError, ValueError) as exc:
        raise BenchError(f"vocabulary: {exc}") from exc
    digest = hashlib.sha1(vocab.centers.tobytes() + vocab.idf.tobytes()).hexdigest()[:12]
    path = venv / f"hivemap-vocab-{digest}.txt"
    if not path.exists():
        tmp = path.with_suffix(".part")
        vocab.save_dbow2_text(tmp)
        tmp.rename(path)
    return path


def _cv_matrix(m: np.ndarray) -> str:
    data = ", ".join(f"{float(x):.9f}" for x in np.asarray(m).ravel())
    return f"!!opencv-matrix\n  rows: {m.shape[0]}\n  cols: {m.shape[1]}\n  dt: f\n  data: [{data}]"


def rectification(ds: Any) -> dict[str, np.ndarray]:
    """Stereo rectification of cam0/cam1 as ORB-SLAM3's own settings reader computes it (OpenCV,
    zero disparity, alpha -1): per camera K, D, R (unrectified -> rectified) and P."""
    import cv2

    c0, c1 = ds.cameras["cam0"], ds.cameras["cam1"]
    T_c1_c0 = np.linalg.inv(ds.T_BS["cam1"]) @ ds.T_BS["cam0"]  # OpenCV: first camera -> second
    size = (c0.width, c0.height)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        c0.K, c0.dist_coeffs, c1.K, c1.dist_coeffs, size, T_c1_c0[:3, :3].copy(), T_c1_c0[:3, 3:].copy(),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1, newImageSize=size,
    )  # fmt: skip
    return {
        "K0": c0.K,
        "D0": c0.dist_coeffs,
        "R0": R1,
        "P0": P1,
        "K1": c1.K,
        "D1": c1.dist_coeffs,
        "R1": R2,
        "P1": P2,
    }


def settings_yaml(ds: Any, rect: dict[str, np.ndarray]) -> str:
    """ORB-SLAM3 stereo-inertial settings (the pre-1.0 format) for rectified images of a dataset.

    The pre-1.0 format because only it reads ``IMU.fastInit``: without it ORB-SLAM3 starts a
    stereo-inertial map only on a frame whose mean acceleration differs by 0.5 m/s^2 from the last
    one's, a jolt that handheld EuRoC recordings have and our smooth simulated flights never do (it
    never initialised on a 40 s factory01 agent). That format takes rectified images, so the worker
    rectifies them (``rectification``, as the 1.0 reader would) and ``Tbc`` is the rectified left
    camera's. IMU noise is the sensor.yaml's continuous-time densities and random walks, which is
    what ORB-SLAM3 expects (it discretises them with the rate).
    """
    P0, P1, R0 = rect["P0"], rect["P1"], rect["R0"]
    T_c0_r0 = np.eye(4)
    T_c0_r0[:3, :3] = R0.T
    T_b_r0 = np.linalg.inv(ds.T_BS["imu0"]) @ ds.T_BS["cam0"] @ T_c0_r0
    c0, noise = ds.cameras["cam0"], ds.imu_noise
    lines = ["%YAML:1.0", 'Camera.type: "PinHole"']
    vals = {
        "fx": P0[0, 0],
        "fy": P0[1, 1],
        "cx": P0[0, 2],
        "cy": P0[1, 2],
        "k1": 0,
        "k2": 0,
        "p1": 0,
        "p2": 0,
    }
    lines += [f"Camera.{k}: {float(v)!r}" for k, v in vals.items()]
    lines += [
        f"Camera.width: {c0.width}",
        f"Camera.height: {c0.height}",
        f"Camera.fps: {float(ds.rates['cam0'])!r}",
        f"Camera.bf: {float(-P1[0, 3])!r}",
        "Camera.RGB: 0",
        f"Tbc: {_cv_matrix(T_b_r0)}",
        "IMU.fastInit: 1",
        f"IMU.NoiseGyro: {noise['gyroscope_noise_density']!r}",
        f"IMU.NoiseAcc: {noise['accelerometer_noise_density']!r}",
        f"IMU.GyroWalk: {noise['gyroscope_random_walk']!r}",
        f"IMU.AccWalk: {noise['accelerometer_random_walk']!r}",
        f"IMU.Frequency: {round(ds.rates['imu0'])}",
    ]
    lines += [f"{k}: {v!r}" for k, v in (ORB_SETTINGS | VIEWER_SETTINGS).items()]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ worker
def worker(vocab: str, settings: str, inputs: str, out: str, pace: bool) -> None:
    """Runs inside the ORB-SLAM3 venv (numpy, cv2, pyorbslam3 only): track every frame, save.

    ``pace`` feeds frames no faster than their timestamps, as ORB-SLAM3's EuRoC example does, so its
    local mapping gets the time it would have live.
    """
    import cv2
    import pyorbslam3 as pos

    z = np.load(inputs)
    t_ns, left, right, imu = z["t_ns"], z["left"], z["right"], z["imu"]
    w, h = (int(x) for x in z["size"])
    maps = [
        cv2.initUndistortRectifyMap(z[f"K{c}"], z[f"D{c}"], z[f"R{c}"], z[f"P{c}"], (w, h), cv2.CV_32FC1)
        for c in (0, 1)
    ]
    t = t_ns.astype(np.float64) * 1e-9
    imu_t = imu[:, 0]
    slam = pos.Slam(vocab, settings, pos.Sensor.IMU_STEREO, use_viewer=False)
    states: dict[str, int] = {}
    losses, was_ok, first_ok, imu_init = 0, False, None, None
    cpu0, wall0 = time.process_time(), time.perf_counter()
    lo = int(np.searchsorted(imu_t, t[0] - 0.05, side="right"))
    for i in range(len(t)):
        start = time.perf_counter()
        hi = int(np.searchsorted(imu_t, t[i], side="right"))
        im = []
        for paths, (mx, my) in zip((left, right), maps, strict=True):
            g = cv2.imread(str(paths[i]), cv2.IMREAD_GRAYSCALE)
            if g is None:
                raise FileNotFoundError(f"cannot read frame {i}: {paths[i]}")
            im.append(cv2.remap(g, mx, my, cv2.INTER_LINEAR))
        res = slam.track_stereo(im[0], im[1], float(t[i]), imu=imu[lo:hi])
        lo = hi
        name = str(res.state).split(".")[-1]
        states[name] = states.get(name, 0) + 1
        if res.ok:
            first_ok = float(t[i] - t[0]) if first_ok is None else first_ok
            if imu_init is None and slam.imu_initialized():
                imu_init = float(t[i] - t[0])
        elif was_ok and name in ("RECENTLY_LOST", "LOST"):
            losses += 1
        was_ok = bool(res.ok)
        if i % 200 == 0:
            print(f"[bench] frame {i}/{len(t)} {name}", flush=True)
        if pace and i + 1 < len(t):
            time.sleep(max(0.0, float(t[i + 1] - t[i]) - (time.perf_counter() - start)))
    slam.shutdown()
    # EuRoC output: body (IMU) poses of the frames whose map is the largest, in ns (ORB-SLAM3's own
    # evaluation format); the TUM writer would mix maps and gives the camera, not the body. ORB-SLAM3
    # crashes saving a map without keyframes, so a run that never tracked saves nothing.
    if first_ok is not None:
        slam.save_trajectory_euroc(out + ".euroc")
    stats = {
        "frames": len(t),
        "states": states,
        "tracking_losses": losses,
        "first_ok_s": first_ok,
        "imu_initialised_s": imu_init,
        "track_cpu_s": time.process_time() - cpu0,
        "track_wall_s": time.perf_counter() - wall0,
    }
    Path(out + ".stats.json").write_text(json.dumps(stats, indent=1))


# ------------------------------------------------------------------------------------------ driver
def run_agent(py: Path, vocab: Path, agent_dir: Path, work: Path, pace: bool) -> dict[str, Any]:
    """One ORB-SLAM3 run in its venv; returns stats (+ "error" when it failed)."""
    from hivemap.client.dataset import FrameList, load_dataset

    work.mkdir(parents=True, exist_ok=True)
    ds = load_dataset(agent_dir)
    frames = ds.frames
    if not isinstance(frames, FrameList) or frames.cam1_paths is None or len(ds.imu) == 0:
        return {"error": "needs a EuRoC folder with cam0, cam1 and imu0"}
    rect = rectification(ds)
    (work / "settings.yaml").write_text(settings_yaml(ds, rect))
    arrays: dict[str, Any] = dict(rect)
    arrays |= {
        "size": np.array([ds.camera.width, ds.camera.height]),
        "t_ns": np.asarray(frames.t_ns),
        "left": np.array([str(p) for p in frames.cam0_paths]),
        "right": np.array([str(p) for p in frames.cam1_paths]),
        "imu": np.asarray(ds.imu, dtype=np.float64),
    }
    np.savez(work / "inputs.npz", **arrays)
    cmd = [str(py), str(Path(__file__).resolve()), "_worker", str(vocab), str(work / "settings.yaml")]
    cmd += [str(work / "inputs.npz"), str(work / "orbslam3")] + ([] if pace else ["--no-pace"])
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.perf_counter()
    with open(work / "orbslam3.log", "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    (work / "inputs.npz").unlink()
    stats_path, euroc = work / "orbslam3.stats.json", work / "orbslam3.euroc"
    if rc != 0 or not stats_path.exists():
        return {"error": f"ORB-SLAM3 exited {rc} (log {work / 'orbslam3.log'})"}
    stats: dict[str, Any] = json.loads(stats_path.read_text())
    text = (work / "orbslam3.log").read_text(errors="replace")
    stats["maps"] = len(re.findall(r"Creation of new map with id:", text))
    stats["merges"] = len(re.findall(r"Merge finished!", text))
    stats["cpu_s"] = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    stats["wall_s"] = time.perf_counter() - wall
    rows = np.loadtxt(euroc, ndmin=2) if euroc.exists() and euroc.stat().st_size else np.zeros((0, 8))
    if len(rows) == 0:
        stats["error"] = "no trajectory (never initialised, or every map was lost)"
    else:
        rows[:, 0] *= 1e-9
        np.savetxt(work / "orbslam3.tum", rows, fmt="%.9f")
    stats_path.write_text(json.dumps(stats, indent=1))
    return stats


def evaluate(agent_dir: Path, est_tum: Path) -> dict[str, float]:
    """ATE as hivemap's single-mode evaluation computes it: evo, SE(3), body ground truth."""
    from hivemap.eval.experiment import MAX_DIFF
    from hivemap.eval.trajectory import ate, groundtruth_trajectory, read_tum

    gt = groundtruth_trajectory(agent_dir)
    a = ate(read_tum(est_tum), gt, "se3", max_diff=MAX_DIFF)
    length = float(gt.path_length)
    return {"ate_rmse": a.stats.rmse, "ate_pct": 100 * a.stats.rmse / length, "n": a.stats.n}


def hivemap_results(exp: Path, world: str) -> dict[str, dict[str, Any]]:
    """Per agent, hivemap's single-mode result for ``world`` (empty when that run is missing)."""
    p = exp / "results" / world / "single.json"
    if not p.exists():
        return {}
    return {a["agent_id"]: a for a in json.loads(p.read_text()).get("agents", [])}


def _f(x: float | None, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


COLUMNS = (
    ("hm ATE m", "hm", "ate_rmse", "9.3f"),
    ("hm %", "hm", "ate_pct", "6.2f"),
    ("hm cov", "hm", "coverage", "6.2f"),
    ("orb ATE m", "orb", "ate_rmse", "9.3f"),
    ("orb %", "orb", "ate_pct", "6.2f"),
    ("orb cov", "orb", "coverage", "7.2f"),
    ("losses", "orbslam3", "tracking_losses", "6d"),
    ("maps", "orbslam3", "maps", "4d"),
    ("cpu s", "orbslam3", "cpu_s", "6.0f"),
)


def print_table(rows: list[dict[str, Any]]) -> None:
    """One line per agent, then the mean and the worst over the agents that have both ATEs."""

    def width(fmt: str) -> int:
        return int(fmt.rstrip("fd").split(".")[0])

    header = f"{'world':<14} {'agent':<5} " + " ".join(f"{c[0]:>{width(c[3])}}" for c in COLUMNS)
    print(header)
    print("-" * len(header))
    for r in rows:
        cells = [_f(r.get(part, {}).get(key), fmt).rjust(width(fmt)) for _, part, key, fmt in COLUMNS]
        print(f"{r['world']:<14} {r['agent']:<5} " + " ".join(cells))
    both = [r for r in rows if "hm" in r and "orb" in r]
    worlds = sorted({r["world"] for r in both})
    groups = [(f"mean {w}", [r for r in both if r["world"] == w]) for w in worlds if len(worlds) > 1]
    for label, group in [*groups, ("mean", both), ("worst", both)]:
        fn: Callable[[list[float]], float] = max if label == "worst" else statistics.fmean
        if not group:
            continue
        cells = []
        for _, part, key, fmt in COLUMNS:
            vals = [r[part].get(key) for r in group if part in ("hm", "orb")]
            ok = [float(v) for v in vals if v is not None]
            cells.append((format(fn(ok), fmt) if ok and key != "coverage" else "").rjust(width(fmt)))
        print(f"{label:<20} " + " ".join(cells))
    if both:
        print(f"({len(both)} agents with both figures; mean and worst of the ATEs over them)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("worlds", nargs="*", type=Path, help="render folders (hivemap sim render --out)")
    ap.add_argument("--hivemap", type=Path, help="--out of a `hivemap eval experiment --modes single` run")
    ap.add_argument("--agents", default=None, help="comma-separated agent ids (default: all)")
    ap.add_argument("--venv", type=Path, default=None, help=f"ORB-SLAM3 venv (${VENV_ENV})")
    ap.add_argument("--out", type=Path, default=None, help="run folder (default: HIVEMAP/orbslam3)")
    ap.add_argument("--rerun", action="store_true", help="run ORB-SLAM3 again even when a run exists")
    ap.add_argument("--no-pace", dest="pace", action="store_false", help="feed frames as fast as it tracks")
    args = ap.parse_args()
    if not args.worlds or args.hivemap is None:  # as `make bench` runs it: nothing to compare
        print("bench/orbslam3.py: give render folders and --hivemap EXP_OUT (see --help); nothing measured")
        return 0
    default_venv = os.environ.get(VENV_ENV) or str(Path.home() / ".cache" / "hivemap" / "orbslam3-venv")
    venv = (args.venv or Path(default_venv)).expanduser().resolve()
    try:
        py = ensure_venv(venv)
        vocab = ensure_vocabulary(venv)
    except BenchError as exc:
        print(f"bench/orbslam3.py: {exc}", file=sys.stderr)
        return 2
    out = args.out or args.hivemap / "orbslam3"
    rows: list[dict[str, Any]] = []
    failures: list[str] = []
    for world in args.worlds:
        hm = hivemap_results(args.hivemap, world.name)
        if not hm:
            failures.append(f"{world.name}: no hivemap results in {args.hivemap / 'results' / world.name}")
        agents = sorted(p.name for p in world.iterdir() if (p / "mav0").is_dir())
        if args.agents:
            agents = [a for a in agents if a in args.agents.split(",")]
        for agent in agents:
            work = out / world.name / agent
            stats_path = work / "orbslam3.stats.json"
            if args.rerun or not stats_path.exists():
                print(f"ORB-SLAM3 on {world.name}/{agent} ...", flush=True)
                stats = run_agent(py, vocab, world / agent, work, args.pace)
            else:
                stats = json.loads(stats_path.read_text())
            row: dict[str, Any] = {"world": world.name, "agent": agent, "orbslam3": stats}
            if "error" in stats:
                failures.append(f"{world.name}/{agent}: ORB-SLAM3 {stats['error']}")
            else:
                row["orb"] = evaluate(world / agent, work / "orbslam3.tum")
                row["orb"]["coverage"] = row["orb"]["n"] / stats["frames"]
                if stats.get("tracking_losses") or stats.get("maps", 1) > 1:
                    print(
                        f"note: {world.name}/{agent}: ORB-SLAM3 lost tracking {stats['tracking_losses']}x, "
                        f"{stats['maps']} maps; its ATE covers the largest map only",
                        flush=True,
                    )
            h = hm.get(agent)
            if h is not None and h.get("ate_rmse") is not None and h.get("path_length"):
                frames = stats.get("frames") or 0
                row["hm"] = {
                    "ate_rmse": h["ate_rmse"],
                    "ate_pct": 100 * h["ate_rmse"] / h["path_length"],
                    "coverage": h["n"] / frames if frames else None,
                }
            elif hm:
                failures.append(f"{world.name}/{agent}: hivemap {h.get('status') if h else 'no result'}")
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(rows, indent=1))
    print_table(rows)
    if args.out is None:  # the summary sits in the experiment's folder, so its report gets the section
        from hivemap.eval.peer import rewrite_report

        try:
            print(f"report: {rewrite_report(args.hivemap)} (with the ORB-SLAM3 section)")
        except (FileNotFoundError, ValueError) as exc:
            failures.append(f"report: {exc}")
    for msg in failures:
        print(f"FAILED: {msg}")
    return 1 if failures else 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_worker":
        wp = argparse.ArgumentParser(prog="orbslam3.py _worker")
        for a in ("vocab", "settings", "inputs", "out"):
            wp.add_argument(a)
        wp.add_argument("--no-pace", dest="pace", action="store_false")
        w = wp.parse_args(sys.argv[2:])
        worker(w.vocab, w.settings, w.inputs, w.out, w.pace)
    else:
        sys.exit(main())
