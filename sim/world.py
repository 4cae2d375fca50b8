"""A seeded generator of the simulated factory site (~120 m x 120 m, z up, ground at z = 0).

The site is a grid of roads (asphalt with markings) between blocks of buildings with unique facades,
containers, pillars and fences, on grass and gravel. Geometry is a ground plane cut into textured
tiles plus textured boxes; both renderers (:mod:`hivemap.sim.render`) draw exactly this.
Same seed -> identical world (geometry and textures).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.sim import textures

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """A box turned by ``yaw`` (rad) about z: ``center`` (x, y, z) of its volume, ``size`` (dx, dy, dz)."""

    center: F64
    size: F64
    yaw: float = 0.0
    name: str = ""

    def corners_xy(self) -> F64:
        """(4, 2) footprint corners, counter-clockwise."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        R = np.array([[c, -s], [s, c]])
        h = np.asarray(self.size[:2]) / 2
        local = np.array([[-h[0], -h[1]], [h[0], -h[1]], [h[0], h[1]], [-h[0], h[1]]])
        return local @ R.T + np.asarray(self.center[:2])

    def contains_xy(self, pts: F64, margin: float = 0.0) -> NDArray[np.bool_]:
        """Which (N, 2) points lie inside the footprint grown by ``margin``."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        d = np.asarray(pts, dtype=np.float64).reshape(-1, 2) - np.asarray(self.center[:2])
        lx = d[:, 0] * c + d[:, 1] * s
        ly = -d[:, 0] * s + d[:, 1] * c
        return (np.abs(lx) <= self.size[0] / 2 + margin) & (np.abs(ly) <= self.size[1] / 2 + margin)


@dataclass(frozen=True)
class Facade:
    """A building wall: ``label`` as painted on it, ``centre`` (x, y, z), outward unit ``normal``."""

    label: str
    centre: F64
    normal: F64
    width: float
    height: float


@dataclass
class World:
    """Everything the renderers and the trajectory planner need."""

    seed: int
    size_m: float
    roads: list[F64]  # road centre polylines (K, 2)
    road_width: float
    buildings: list[Box]
    obstacles: list[Box]
    tile_m: float
    tiles_origin: F64  # (x, y) of the ground grid corner
    tiles_n: int  # tiles per side
    layers: NDArray[np.uint8]  # (L, TEX, TEX) texture array (0..255), ground tiles first
    box_layers: list[list[int]] = field(default_factory=list)  # per box: [+x, +y, -x, -y, top] layer
    apron_layer: int = 0  # ground texture outside the tiled site (repeats every TEXTURE_M)
    apron_m: float = 1500.0  # half-size of the far-field ground
    sun_dir: F64 = field(default_factory=lambda: np.array([0.45, 0.3, 0.84]))

    @property
    def boxes(self) -> list[Box]:
        return self.buildings + self.obstacles

    @property
    def facades_of_interest(self) -> list[Facade]:
        """Every building wall (uniquely labelled, e.g. "B3N"): centre, outward normal, size."""
        out = []
        for b in self.buildings:
            fp = b.corners_xy()
            # CCW footprint edges 0->1, 1->2, 2->3, 3->0 face S, E, N, W for yaw 0 (see box_quads).
            for e, letter in enumerate("SENW"):
                a, c = fp[e], fp[(e + 1) % 4]
                d = c - a
                width = float(np.linalg.norm(d))
                normal = np.array([d[1], -d[0], 0.0]) / width
                centre = np.array([(a[0] + c[0]) / 2, (a[1] + c[1]) / 2, float(b.size[2]) / 2])
                out.append(Facade(f"{b.name}{letter}", centre, normal, width, float(b.size[2])))
        return out

    def tile_layer(self, ix: int, iy: int) -> int:
        return iy * self.tiles_n + ix


def _to_u8(img: NDArray[np.floating]) -> NDArray[np.uint8]:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _segments(roads: list[F64]) -> tuple[F64, F64, F64]:
    a = np.concatenate([r[:-1] for r in roads])
    b = np.concatenate([r[1:] for r in roads])
    start = np.concatenate(
        [np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(r, axis=0), axis=1))[:-1]]) for r in roads]
    )
    return a, b, start


def road_distance(
    xy: F64, roads: list[F64], cutoff: float = np.inf
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Distance of (..., 2) points to the nearest road centre line, and arc length along it.

    Segments farther than ``cutoff`` from all points are skipped (their distance reads as inf).
    """
    X = np.asarray(xy[..., 0], dtype=np.float32)
    Y = np.asarray(xy[..., 1], dtype=np.float32)
    a, b, start = _segments(roads)
    best = np.full(X.shape, np.inf, dtype=np.float32)
    along = np.zeros(X.shape, dtype=np.float32)
    lo = np.array([X.min(), Y.min()]) - cutoff
    hi = np.array([X.max(), Y.max()]) + cutoff
    for k in range(len(a)):
        if (np.minimum(a[k], b[k]) > hi).any() or (np.maximum(a[k], b[k]) < lo).any():
            continue  # segment farther than ``cutoff`` from every point
        d = (b[k] - a[k]).astype(np.float32)
        L2 = float(d @ d)
        dx, dy = X - np.float32(a[k][0]), Y - np.float32(a[k][1])
        t = np.clip((dx * d[0] + dy * d[1]) / np.float32(L2), 0, 1)
        dist = np.hypot(dx - t * d[0], dy - t * d[1])
        closer = dist < best
        best = np.where(closer, dist, best)
        along = np.where(closer, np.float32(start[k]) + t * np.float32(np.sqrt(L2)), along)
    return best, along


@lru_cache(maxsize=2)
def generate_world(seed: int, size_m: float = 120.0, tile_m: float = 8.0) -> World:
    """Generate the factory site for ``seed`` (deterministic; cached: treat the result as read-only)."""
    rng = np.random.default_rng(seed)
    half = size_m / 2
    # Road grid: 4 north-south and 4 east-west roads with a little jitter.
    base = np.array([-0.75, -0.25, 0.2, 0.67]) * half
    xs = base + rng.uniform(-2, 2, 4)
    ys = base + rng.uniform(-2, 2, 4)
    ext = half - 5.0
    roads = [np.array([[x, -ext], [x, ext]]) for x in xs] + [np.array([[-ext, y], [ext, y]]) for y in ys]
    road_width = 7.0
    buildings: list[Box] = []
    obstacles: list[Box] = []
    clear = road_width / 2 + 3.0
    number = 1
    for i in range(3):
        for j in range(3):
            x0, x1 = xs[i] + clear, xs[i + 1] - clear
            y0, y1 = ys[j] + clear, ys[j + 1] - clear
            w, d = x1 - x0, y1 - y0
            if w < 4.0 or d < 4.0:
                continue  # a small world leaves no room for a block here
            if (i, j) == (1, 1):  # the central block: a yard with containers, no building
                for k in range(4):
                    cx = x0 + w * (0.25 + 0.5 * (k % 2))
                    cy = y0 + d * (0.3 + 0.4 * (k // 2))
                    size = np.array([6.1, 2.44, 2.59])
                    obstacles.append(
                        Box(np.array([cx, cy, size[2] / 2]), size, float(rng.uniform(-0.3, 0.3)), f"C{k + 1}")
                    )
                continue
            split = w > 18 and rng.random() < 0.5
            parts = [(x0, x0 + w * 0.45), (x0 + w * 0.55, x1)] if split else [(x0 + 1, x1 - 1)]
            for a, b in parts:
                h = float(rng.uniform(6.0, 11.0))
                dd = d * float(rng.uniform(0.6, 0.9))
                cy = y0 + dd / 2 + float(rng.uniform(0, d - dd))
                buildings.append(
                    Box(np.array([(a + b) / 2, cy, h / 2]), np.array([b - a, dd, h]), 0.0, f"B{number}")
                )
                number += 1
    # Pillars and fence segments along the outer roads; a few lamp posts at intersections.
    for k in range(10):
        x = float(rng.uniform(-ext + 5, ext - 5))
        y = float(rng.choice(ys)) + float(rng.choice([-1, 1])) * (road_width / 2 + 1.2)
        if not any(bb.contains_xy(np.array([[x, y]]), 1.0)[0] for bb in buildings):
            obstacles.append(Box(np.array([x, y, 2.0]), np.array([0.5, 0.5, 4.0]), 0.0, f"P{k}"))
    for k, yv in enumerate((ys[0] - road_width / 2 - 2.0, ys[-1] + road_width / 2 + 2.0)):
        obstacles.append(Box(np.array([0.0, yv, 0.9]), np.array([60.0, 0.15, 1.8]), 0.0, f"F{k}"))
    # The site's perimeter wall (4 m), so views along the roads end on texture rather than sky.
    wall = half + 1.0
    for k, (cx, cy, sx, sy) in enumerate(
        (
            (wall, 0.0, 0.4, 2 * wall),
            (-wall, 0.0, 0.4, 2 * wall),
            (0.0, wall, 2 * wall, 0.4),
            (0.0, -wall, 2 * wall, 0.4),
        )
    ):
        obstacles.append(Box(np.array([cx, cy, 2.0]), np.array([sx, sy, 4.0]), 0.0, f"W{k + 1}"))
    # Textures: ground tiles first (with roads painted in, shadows baked), then 5 per box.
    n_tiles = int(np.ceil(size_m / tile_m))
    origin = np.array([-n_tiles * tile_m / 2, -n_tiles * tile_m / 2])
    layers: list[NDArray[np.uint8]] = []
    s = textures.TEX
    coarse = textures.fractal_noise(rng, 256, 5, 4)  # terrain mix over the whole site
    m_per_px = tile_m / s
    src = textures.GroundSources(rng, m_per_px)
    shade_px = 160  # sunlight map texels per tile (5 cm for 8 m tiles)
    sun = np.array([0.45, 0.3, 0.84])
    all_boxes = buildings + obstacles
    light = textures.shading_map(
        [(b.corners_xy().astype(np.float32), float(b.center[2] + b.size[2] / 2)) for b in all_boxes],
        sun.astype(np.float32),
        (float(origin[0]), float(origin[1])),
        n_tiles * shade_px,
        tile_m / shade_px,
    )
    px = (np.arange(s) + 0.5) / s * tile_m
    ox0 = round(float(origin[0]) / m_per_px)
    oy0 = round(float(origin[1]) / m_per_px)
    for iy in range(n_tiles):
        for ix in range(n_tiles):
            gx0 = origin[0] + ix * tile_m
            gy0 = origin[1] + iy * tile_m
            X, Y = np.meshgrid(gx0 + px, gy0 + px)
            dist, along = road_distance(np.stack([X, Y], -1), roads, cutoff=road_width)
            dist = np.minimum(dist, 1e3)
            u = ((X - origin[0]) / (n_tiles * tile_m) * 255).astype(np.float32)
            v = ((Y - origin[1]) / (n_tiles * tile_m) * 255).astype(np.float32)
            terrain = cv2.remap(coarse, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            terrain = np.clip((terrain - 0.35) * 3, 0, 1)
            window = light[iy * shade_px : (iy + 1) * shade_px, ix * shade_px : (ix + 1) * shade_px]
            tile = textures.ground_tile(
                rng,
                src,
                ox0 + ix * s,
                oy0 + iy * s,
                dist.astype(np.float32),
                along.astype(np.float32),
                road_width,
                terrain,
                cv2.resize(window, (s, s), interpolation=cv2.INTER_LINEAR),
            )
            layers.append(_to_u8(tile))
    apron_layer = len(layers)
    layers.append(
        _to_u8(0.25 + 0.5 * textures.photo("gravel") * (0.7 + 0.3 * textures.fractal_noise(rng, s, 5, 4)))
    )
    box_layers: list[list[int]] = []
    for bx in buildings + obstacles:
        ids = []
        for face in ("E", "N", "W", "S"):
            label = f"{bx.name}{face}"
            if bx.name.startswith("C"):
                tex = textures.container_texture(rng, label)
            elif bx.name.startswith("P"):
                tex = textures.pillar_texture(rng, label)
            elif bx.name.startswith("F"):
                tex = textures.fence_texture(rng, label)
            else:
                tex = textures.wall_texture(rng, label)
            ids.append(len(layers))
            layers.append(_to_u8(tex))
        ids.append(len(layers))
        layers.append(_to_u8(textures.roof_texture(rng)))
        box_layers.append(ids)
    log.debug(
        "world %d: %d buildings, %d obstacles, %d texture layers",
        seed,
        len(buildings),
        len(obstacles),
        len(layers),
    )
    return World(
        seed=seed,
        size_m=size_m,
        roads=roads,
        road_width=road_width,
        buildings=buildings,
        obstacles=obstacles,
        tile_m=tile_m,
        tiles_origin=origin,
        tiles_n=n_tiles,
        layers=np.stack(layers),
        box_layers=box_layers,
        apron_layer=apron_layer,
    )


TEXTURE_M = 8.0  # metres covered by one wall/roof texture repeat


def box_quads(world: World) -> tuple[F64, F64, NDArray[np.int32], F64]:
    """All box faces as quads: corners (Q, 4, 3), uv (Q, 4, 2), layer (Q,), shade (Q,).

    Corner order p0, p1, p2, p3 with p1 - p0 along u and p3 - p0 along v (v grows downwards on walls,
    so texture row 0 is the top of a wall and the grimy bottom rows touch the ground).
    """
    corners, uvs, layer, shade = [], [], [], []
    sun = world.sun_dir / np.linalg.norm(world.sun_dir)
    for bx, ids in zip(world.boxes, world.box_layers, strict=True):
        fp = bx.corners_xy()  # counter-clockwise: faces E(0->1?) computed from edges
        z0, z1 = float(bx.center[2] - bx.size[2] / 2), float(bx.center[2] + bx.size[2] / 2)
        h = z1 - z0
        # Edges of the CCW footprint: 0->1 faces -y(S), 1->2 +x(E), 2->3 +y(N), 3->0 -x(W) (for yaw 0).
        edge_layer = [ids[3], ids[0], ids[1], ids[2]]
        for e in range(4):
            a, b = fp[e], fp[(e + 1) % 4]
            w = float(np.linalg.norm(b - a))
            p0 = [a[0], a[1], z1]
            p1 = [b[0], b[1], z1]
            p2 = [b[0], b[1], z0]
            p3 = [a[0], a[1], z0]
            corners.append([p0, p1, p2, p3])
            # v = 1 at the ground (texture bottom) and grows upwards in metres / TEXTURE_M.
            top = 1.0 - h / TEXTURE_M
            uvs.append([[0, top], [w / TEXTURE_M, top], [w / TEXTURE_M, 1.0], [0, 1.0]])
            layer.append(edge_layer[e])
            d = b - a
            normal = np.array([d[1], -d[0], 0.0]) / max(w, 1e-9)
            shade.append(0.55 + 0.45 * max(0.0, float(normal @ sun)))
        wx = float(np.linalg.norm(fp[1] - fp[0]))
        wy = float(np.linalg.norm(fp[3] - fp[0]))
        corners.append([[*fp[3], z1], [*fp[2], z1], [*fp[1], z1], [*fp[0], z1]])
        uvs.append([[0, 0], [wx / TEXTURE_M, 0], [wx / TEXTURE_M, wy / TEXTURE_M], [0, wy / TEXTURE_M]])
        layer.append(ids[4])
        shade.append(0.55 + 0.45 * float(sun[2]))
    return (
        np.array(corners, dtype=np.float64),
        np.array(uvs, dtype=np.float64),
        np.array(layer, dtype=np.int32),
        np.array(shade, dtype=np.float64),
    )


GROUND_SHADE = 0.5 + 0.45 * 0.84
