"""Cost of the pose-graph marginals (:mod:`hivemap.server.marginals`) on factory-sized graphs.

The graph of ``bench/pose_graph.py`` (a corridor of N keyframes, each tied to its 6 predecessors, true
loops every 200 keyframes; the wrong loops left out); per N: CPU time of the factorisation with the
latest keyframe's covariance (what a correction waits for), of every keyframe's (the rate-limited solve),
and the position sigma of the last keyframe. Usage: ``.venv/bin/python bench/marginals.py [N ...]``.
"""

from __future__ import annotations

import sys

import numpy as np
from pose_graph import graph

from hivemap.server.marginals import pose_marginals


def main(sizes: list[int]) -> None:
    rng = np.random.default_rng(1)
    for n in sizes:
        poses, edges, n_ess, _ = graph(n, rng, 0.01)
        edges = edges[:n_ess] + edges[n_ess::2]
        latest = min(pose_marginals(poses, edges, {0}, indices=[n - 1]).cpu_s for _ in range(3))
        full = pose_marginals(poses, edges, {0})
        sigma = np.sqrt(np.diag(full.covariances[-1][3:, 3:]))
        print(f"N={n} ({len(edges)} edges): latest only {latest * 1e3:.0f} ms CPU, all keyframes "
              f"{full.cpu_s * 1e3:.0f} ms CPU; last position sigma {np.round(sigma, 3)} m")  # fmt: skip


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [500, 2000])
