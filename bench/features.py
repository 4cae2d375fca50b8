"""Feature counts per condition: what the front-end's extraction gives on rendered frames.

    .venv/bin/python bench/features.py DATA/f01-s1 DATA/f02-s1 ... [--every 4] [--agents uav1,ugv]
        [--contrast stretch|clahe|off]

Each argument is a render folder (``hivemap sim render --out``); its manifest names the scenario and
so the condition. Per folder and agent the table gives, averaged over every ``--every``-th frame:
keypoints kept, the share of the 8x6 image cells holding at least 5 of them, keypoints with a
stereo depth, and the extraction time (contrast step + ORB + stereo, one thread).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

CELLS = (8, 6)


def _coverage(uv: np.ndarray, w: int, h: int, min_per_cell: int = 5) -> float:
    if len(uv) == 0:
        return 0.0
    cx = np.minimum((uv[:, 0] * CELLS[0] / w).astype(int), CELLS[0] - 1)
    cy = np.minimum((uv[:, 1] * CELLS[1] / h).astype(int), CELLS[1] - 1)
    counts = np.bincount(cy * CELLS[0] + cx, minlength=CELLS[0] * CELLS[1])
    return float((counts >= min_per_cell).mean())


def _condition(folder: Path) -> str:
    man = yaml.safe_load((folder / "manifest.yaml").read_text())
    return f"{man.get('scenario')} {man.get('lighting')}/{man.get('weather')}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("folders", nargs="*", type=Path, help="render folders (hivemap sim render --out)")
    ap.add_argument("--every", type=int, default=4, help="use every N-th frame")
    ap.add_argument("--agents", default=None, help="comma-separated agent ids (default: all)")
    ap.add_argument("--contrast", default=None, help="stretch | clahe | off (default: the front-end's)")
    args = ap.parse_args()
    if not args.folders:  # as `make bench` runs it: nothing rendered to measure
        print("bench/features.py: give render folders (see --help); nothing measured")
        return
    cv2.setNumThreads(1)

    from hivemap.client.dataset import load_dataset
    from hivemap.client.frontend.options import FrontendOptions
    from hivemap.client.frontend.tracker import Frontend

    opts = FrontendOptions()
    if args.contrast:
        opts = replace(opts, contrast=args.contrast)

    print(f"{'render':<10} {'condition':<28} {'agent':<5} {'kept':>5} {'cells':>6} {'stereo':>6} {'ms':>5}")
    for folder in args.folders:
        cond = _condition(folder)
        agents = sorted(p.name for p in folder.iterdir() if (p / "mav0").is_dir())
        if args.agents:
            agents = [a for a in agents if a in args.agents.split(",")]
        for agent in agents:
            ds = load_dataset(folder / agent)
            assert ds.rig is not None
            fe = Frontend(ds.rig, opts)
            kept, cells, stereo, ms = [], [], [], []
            for i in range(0, len(ds.frames), args.every):
                left, right = ds.frames.load(i)
                assert right is not None
                t0 = time.process_time()
                fr = fe._make_frame(float(ds.frames.timestamps[i]), left, right)
                ms.append(1e3 * (time.process_time() - t0))
                kept.append(len(fr.uv))
                cells.append(_coverage(np.asarray(fr.uv), left.shape[1], left.shape[0]))
                stereo.append(int(np.isfinite(fr.pts_cam[:, 2]).sum()))
            print(
                f"{folder.name:<10} {cond:<28} {agent:<5} {np.mean(kept):5.0f} {np.mean(cells):6.2f} "
                f"{np.mean(stereo):6.0f} {np.mean(ms):5.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
