"""Pose-graph solve time, Huber vs GNC (``OptimiseOptions.gnc``), on a factory-sized synthetic graph.

A corridor of N keyframes 0.5 m apart, each tied to its 6 predecessors (a spanning tree plus strong
covisibility, as the essential graph of a factory map), drifted by 0.005-0.02 deg of yaw per keyframe, with
true loops every 200 keyframes and as many loops 10 m off. Prints the time of each solve and how many of
the loops it kept. Usage: ``.venv/bin/python bench/pose_graph.py [N ...]``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from hivemap.maps.geometry import Sim3, se3, se3_inverse, so3_exp
from hivemap.server.optim import PoseGraphEdge, PoseGraphOptions, relative_sim3, solve_pose_graph_se3


def graph(
    n: int, rng: np.random.Generator, drift_deg: float
) -> tuple[np.ndarray, list[PoseGraphEdge], int, list]:
    truth = [
        se3(so3_exp(np.array([0.0, 0.0, 0.3 * np.sin(k / 50)])), np.array([0.5 * k, 0.0, 0.0]))
        for k in range(n)
    ]
    drifted, D = [truth[0]], truth[0].copy()
    step = se3(so3_exp(np.array([0, 0, np.radians(drift_deg)])), np.zeros(3))
    for k in range(1, n):
        D = D @ se3_inverse(truth[k - 1]) @ truth[k] @ step
        drifted.append(D.copy())
    poses = np.array(drifted)
    edges = [
        PoseGraphEdge(j, k, relative_sim3(poses[j], poses[k]))
        for k in range(1, n)
        for j in range(max(0, k - 6), k)
    ]
    loops = []
    for k in range(200, n, 200):
        j = int(rng.integers(0, k - 100))
        loops.append(
            PoseGraphEdge(j, k, Sim3.from_se3(se3_inverse(truth[j]) @ truth[k]), 0.005, 0.02, robust=True)
        )
        rel = se3_inverse(truth[j]) @ truth[k]
        rel[:3, 3] += rng.normal(0, 1, 3) / np.sqrt(3) * 10.0
        loops.append(PoseGraphEdge(j, k, Sim3.from_se3(rel), 0.005, 0.02, robust=True))
    return poses, edges + loops, len(edges), truth


def main(sizes: list[int], drifts: tuple[float, ...] = (0.005, 0.01, 0.02)) -> None:
    rng = np.random.default_rng(1)
    for n, drift in ((n, d) for n in sizes for d in drifts):
        poses, all_edges, n_ess, truth = graph(n, rng, drift)
        end = float(np.linalg.norm(poses[-1, :3, 3] - truth[-1][:3, 3]))
        print(f"drift {drift} deg per keyframe ({end:.1f} m at the end)")
        for wrong in (False, True):
            edges = all_edges if wrong else all_edges[:n_ess] + all_edges[n_ess::2]
            for name, opts in (("huber", PoseGraphOptions()), ("gnc", PoseGraphOptions(gnc=True))):
                t0 = time.perf_counter()
                res = solve_pose_graph_se3(poses, edges, {0}, opts)
                ms = (time.perf_counter() - t0) * 1e3
                kept = res.inlier[n_ess:]
                err = max(
                    float(np.linalg.norm(p.t - T[:3, 3])) for p, T in zip(res.poses, truth, strict=True)
                )
                true_kept = kept[0::2] if wrong else kept
                wrong_kept = kept[1::2] if wrong else []
                print(f"  {n} keyframes, {len(edges)} edges, {name}: {ms:.0f} ms; true loops kept "
                      f"{sum(true_kept)}/{len(true_kept)}, wrong loops kept {sum(wrong_kept)}/"
                      f"{len(wrong_kept)}; worst position error {err:.2f} m")  # fmt: skip


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [500, 2000])
