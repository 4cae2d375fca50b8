"""Coverage metric of the explore mode (issue 26) against hand-computed cases: a camera looking straight
down from 10 m over a 1 m grid."""

from __future__ import annotations

import numpy as np

from hivemap.eval.coverage import CoverageOptions, Grid, coverage_curve, seen_cells, time_to
from hivemap.maps.camera import PinholeCamera

# 100 x 100 pixels, f = 100 px: from 10 m the image spans |x|, |y| <= 4.95 m on the ground
CAM = PinholeCamera(100, 100, 100.0, 100.0, 49.5, 49.5)


def _down(x: float, y: float, h: float = 10.0) -> np.ndarray:
    """world_from_cam of a camera at (x, y, h) looking straight down (image x = east, image y = south)."""
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    T[:3, 3] = [x, y, h]
    return T


def _grid() -> Grid:
    # cells of 1 m centred at -9.5 .. 9.5 on both axes: 400 cells; a UGV reaches the row band |y| < 2
    g = np.arange(-9.5, 10.0, 1.0)
    c = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
    return Grid(c, {"uav": np.ones(len(c), bool), "ugv": np.abs(c[:, 1]) < 2.0})


def test_footprint_range_and_occlusion() -> None:
    c = _grid().centres
    # centres within 4.95 m on both axes: -4.5 .. 4.5, 10 x 10 cells
    assert seen_cells(c, _down(0, 0), CAM, 30.0).sum() == 100
    # a range of 10.5 m from 10 m up leaves x^2 + y^2 <= 10.25: 8 cells per quadrant
    assert seen_cells(c, _down(0, 0), CAM, 10.5).sum() == 32
    # something 5 m from the camera over the image's left half (u < 50, i.e. x < 0.05) hides those cells
    depth = np.full((100, 100), 10.0)
    depth[:, :50] = 5.0
    seen = seen_cells(c, _down(0, 0), CAM, 30.0, depth)
    assert seen.sum() == 50 and (c[seen, 0] > 0).all()
    # a camera looking up sees no ground
    up = _down(0, 0)
    up[:3, :3] = np.diag([1.0, 1.0, 1.0])
    assert seen_cells(c, up, CAM, 30.0).sum() == 0


def test_coverage_over_time_and_time_to_target() -> None:
    grid = _grid()
    # uav1 over the origin at t = 0..1 s; uav2 over x = 10 from t = 1 s: its footprint adds x = 5.5 .. 9.5
    # (5 columns of 10 cells)
    poses = {
        "uav1": (np.array([0.0, 1.0]), np.stack([_down(0, 0)] * 2)),
        "uav2": (np.array([1.0, 2.0]), np.stack([_down(10, 0)] * 2)),
    }
    t, f = coverage_curve(grid, ["uav"], poses, CAM, CoverageOptions(sample_s=1.0))
    assert np.allclose(t, [0, 1, 2]) and np.allclose(f, [100 / 400, 150 / 400, 150 / 400])
    assert time_to(t, f, 0.3) == 1.0 and time_to(t, f, 0.5) is None
    # the team's area is the union of its kinds': a UGV-only team counts the 4 rows |y| < 2 (80 cells),
    # of which the cameras saw x = -4.5 .. 9.5 (15 columns)
    t, f = coverage_curve(grid, ["ugv"], poses, CAM, CoverageOptions(sample_s=1.0))
    assert np.allclose(f, [40 / 80, 60 / 80, 60 / 80])
    assert grid.area(["ugv", "uav"]).sum() == 400
