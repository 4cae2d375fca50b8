"""Cost of the pose-graph marginals (:mod:`hivemap.server.marginals`) on factory-sized graphs.

The graph of ``bench/pose_graph.py`` (a corridor of N keyframes, each tied to its 6 predecessors, true
loops every 200 keyframes; the wrong loops left out); per N: CPU time of the factorisation with the
latest keyframe's covariance (what a correction waits for), of every keyframe's (the rate-limited solve),
and the position sigma of the last keyframe. Then the same with each keyframe tied to its 24 predecessors,
as a map's covisibility graph ties them: every keyframe's covariance in one pass over the Bayes tree's
cliques (what the server does) against gtsam's per-pose ``marginalCovariance`` (timed on 40 poses and
scaled to N). Usage: ``.venv/bin/python bench/marginals.py [N ...]``.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from pose_graph import graph

from hivemap.maps.geometry import Sim3, se3_inverse
from hivemap.server.marginals import pose_marginals
from hivemap.server.optim import PoseGraphEdge, PoseGraphOptions, se3_graph


def main(sizes: list[int]) -> None:
    import gtsam

    rng = np.random.default_rng(1)
    for n in sizes:
        poses, edges, n_ess, _ = graph(n, rng, 0.01)
        edges = edges[:n_ess] + edges[n_ess::2]
        latest = min(pose_marginals(poses, edges, {0}, indices=[n - 1]).cpu_s for _ in range(3))
        full = pose_marginals(poses, edges, {0})
        sigma = np.sqrt(np.diag(full.covariances[-1][3:, 3:]))
        print(f"N={n} ({len(edges)} edges): latest only {latest * 1e3:.0f} ms CPU, all keyframes "
              f"{full.cpu_s * 1e3:.0f} ms CPU; last position sigma {np.round(sigma, 3)} m")  # fmt: skip
    for n in sizes:
        poses, _, _, _ = graph(n, rng, 0.01)
        dense = [PoseGraphEdge(j, k, Sim3.from_se3(se3_inverse(poses[j]) @ poses[k]))
                 for k in range(1, n) for j in range(max(0, k - 24), k)]  # fmt: skip
        full = pose_marginals(poses, dense, {0})
        g, v = se3_graph(poses, dense, {0}, PoseGraphOptions(), ())
        linear = g.linearize(v)
        tree = linear.eliminateMultifrontal(gtsam.Ordering.ColamdGaussianFactorGraph(linear))
        sample = np.linspace(1, n - 1, 40).astype(int)
        t0 = time.process_time()
        for i in sample:
            tree.marginalCovariance(int(i))
        per_pose = (time.process_time() - t0) / len(sample) * (n - 1)
        print(f"N={n} dense ({len(dense)} edges): all keyframes in one pass {full.cpu_s:.2f} s CPU "
              f"(factorisation included); gtsam per pose ~{per_pose:.1f} s CPU")  # fmt: skip


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [500, 2000])
