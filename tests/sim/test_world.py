"""The generated factory site: determinism, layout, unique facades, baked shadows."""

from __future__ import annotations

import cv2
import numpy as np

from hivemap.sim import textures
from hivemap.sim.world import generate_world, road_distance


def test_same_seed_same_world_other_seed_other_world() -> None:
    a = generate_world.__wrapped__(7, 48.0)  # uncached: two independent generations
    b = generate_world.__wrapped__(7, 48.0)
    c = generate_world.__wrapped__(8, 48.0)
    assert a.layers.tobytes() == b.layers.tobytes()
    assert [(x.center.tolist(), x.size.tolist(), x.yaw) for x in a.boxes] == [
        (x.center.tolist(), x.size.tolist(), x.yaw) for x in b.boxes
    ]
    assert not np.array_equal(a.layers, c.layers)


def test_site_layout() -> None:
    w = generate_world(1)
    assert len(w.buildings) >= 10
    assert {"C", "P", "F", "W"} <= {o.name[0] for o in w.obstacles}  # containers, posts, fences, walls
    half = w.size_m / 2
    for i, b in enumerate(w.buildings):
        corners = b.corners_xy()
        assert np.abs(corners).max() < half  # inside the site
        # no building on a road: its footprint (sampled densely) stays off the asphalt
        g = np.linspace(0, 1, 20)
        pts = (
            corners[0]
            + g[:, None, None] * (corners[1] - corners[0])
            + g[None, :, None] * (corners[3] - corners[0])
        )
        dist, _ = road_distance(pts.reshape(-1, 2), w.roads)
        assert dist.min() > w.road_width / 2, b.name
        for other in w.buildings[i + 1 :]:
            assert not other.contains_xy(pts.reshape(-1, 2), -0.01).any(), (b.name, other.name)


def test_facades_are_distinct() -> None:
    """Place recognition needs unique places: every building wall texture differs from every other
    (mean absolute difference of 64x64 thumbnails > 0.04 of full scale; a repeated texture gives 0)."""
    w = generate_world(1)
    walls = [
        ids[k] for b, ids in zip(w.boxes, w.box_layers, strict=True) if b.name[0] == "B" for k in range(4)
    ]
    thumbs = np.stack([cv2.resize(w.layers[i], (64, 64), interpolation=cv2.INTER_AREA) for i in walls])
    thumbs = thumbs.astype(np.float32) / 255.0
    diff = np.abs(thumbs[:, None] - thumbs[None, :]).mean(axis=(2, 3))
    np.fill_diagonal(diff, 1.0)
    assert diff.min() > 0.04, diff.min()
    # and the texture is rich in corners everywhere (ORB needs them): > 500 ORB corners per 8 m x 8 m wall
    orb = cv2.ORB_create(2000)  # type: ignore[attr-defined]
    assert min(len(orb.detect(w.layers[i], None)) for i in walls) > 500


def test_baked_shadow_geometry() -> None:
    """A 2 m x 2 m x 10 m box with the sun at (0.6, 0, 0.8): the shadow reaches 10 * 0.6 / 0.8 = 7.5 m
    towards -x (penumbra blur 6 cm, so test 0.3 m inside / outside that edge)."""
    res = 0.05
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32)
    light = textures.shading_map(
        [(corners, 10.0)], np.array([0.6, 0.0, 0.8], np.float32), (-20.0, -20.0), 800, res
    )

    def at(x: float, y: float) -> float:
        return float(light[int((y + 20) / res), int((x + 20) / res)])

    assert at(-1.0 - 7.5 + 0.3, 0.0) < 0.65  # in the shadow, > 0.3 m from the wall (little occlusion)
    assert at(-1.0 - 7.5 - 0.3, 0.0) > 0.95  # beyond the shadow's tip: sunlit
    assert at(3.0, 0.0) > 0.95  # sunny side, 2 m from the wall
    assert at(1.05, 0.0) < 0.8  # at the foot of the sunlit wall: ambient occlusion


def test_facades_of_interest_face_outwards() -> None:
    w = generate_world(1)
    facades = w.facades_of_interest
    assert len(facades) == 4 * len(w.buildings)
    assert len({f.label for f in facades}) == len(facades)  # labels are unique
    for f in facades:
        b = next(b for b in w.buildings if f.label[:-1] == b.name)
        # 0.5 m in front of the wall is outside the building, 0.5 m behind it inside
        assert not b.contains_xy((f.centre[:2] + 0.5 * f.normal[:2])[None])[0], f.label
        assert b.contains_xy((f.centre[:2] - 0.5 * f.normal[:2])[None])[0], f.label
