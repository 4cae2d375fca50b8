"""Procedural + photographic textures for the simulated factory site (grayscale, float32 in [0, 1]).

Photographs ship inside scikit-image (``skimage.data``; no download); they are mixed with
procedural noise, windows, lettering and road markings so that every wall and every patch of ground
is distinguishable (place recognition needs unique places) and rich in corners (ORB needs them).
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
TEX = 512  # texture side in pixels
PHOTOS = (
    "brick", "grass", "gravel", "camera", "coffee", "rocket", "astronaut", "chelsea", "coins", "moon",
    "text", "page", "clock", "hubble_deep_field", "retina",
)  # fmt: skip


@cache
def photo(name: str, size: int = TEX) -> F32:
    """A scikit-image photograph as grayscale float32 (size x size), contrast-normalised."""
    from skimage import data

    img = getattr(data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
    img = img.astype(np.float32)
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)


def fractal_noise(rng: np.random.Generator, size: int, octaves: int = 5, base: int = 4) -> F32:
    """Multi-octave value noise in [0, 1], (size, size)."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = base * 2**o
        grid = rng.random((n + 1, n + 1)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.55
    out /= total
    lo, hi = out.min(), out.max()
    return ((out - lo) / max(hi - lo, 1e-6)).astype(np.float32)


def _put_text(img: F32, text: str, org: tuple[int, int], scale: float, value: float, thick: int) -> None:
    """Draw anti-aliased text of intensity ``value`` into a float image (cv2 draws text on uint8 only)."""
    mask = np.zeros(img.shape, np.uint8)
    cv2.putText(mask, text, org, cv2.FONT_HERSHEY_DUPLEX, scale, 255, thick, cv2.LINE_AA)
    a = mask.astype(np.float32) / 255.0
    img *= 1.0 - a
    img += a * value


def wall_texture(rng: np.random.Generator, label: str) -> F32:
    """A facade covering 8 m x 8 m: material, windows, a poster and a unique painted label."""
    s = TEX
    kind = rng.integers(0, 3)
    if kind == 0:  # brick
        base = np.tile(photo("brick", s // 2), (2, 2))
    elif kind == 1:  # concrete panels
        base = 0.35 + 0.4 * fractal_noise(rng, s, 6, 8)
        for x in range(0, s, s // 4):
            base[:, x : x + 3] *= 0.55
        for y in range(0, s, s // 3):
            base[y : y + 3, :] *= 0.55
    else:  # corrugated metal cladding
        xr = np.arange(s, dtype=np.float32)
        base = 0.45 + 0.25 * np.sin(xr / 5.0)[None, :].repeat(s, 0) + 0.2 * fractal_noise(rng, s, 5, 6)
    base = np.clip(base * (0.6 + 0.5 * rng.random()) + 0.15 * (fractal_noise(rng, s, 6, 16) - 0.5), 0, 1)
    img = base.astype(np.float32)
    # Windows: a grid of dark glass with frames and sills; some lit, some with blinds.
    rows, cols = int(rng.integers(1, 3)), int(rng.integers(2, 4))
    for r in range(rows):
        for c in range(cols):
            if rng.random() < 0.2:
                continue
            w, h = s // (cols + 1), s // (rows + 2)
            x0 = int((c + 0.5) * s / cols - w / 2)
            y0 = int(s * 0.12 + r * s * 0.4)
            glass = 0.08 + 0.25 * fractal_noise(rng, max(w, h), 3, 2)[:h, :w]
            if rng.random() < 0.3:
                glass[:: max(3, h // 12)] += 0.5  # blinds
            img[y0 : y0 + h, x0 : x0 + w] = np.clip(glass, 0, 1)
            cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), 0.85, 4)
            cv2.line(img, (x0 + w // 2, y0), (x0 + w // 2, y0 + h), 0.8, 3)
    # A poster: a photograph with a frame, at a random place.
    name = str(
        rng.choice(["astronaut", "chelsea", "coffee", "rocket", "camera", "clock", "coins", "moon", "page"])
    )
    ps = int(rng.integers(s // 5, s // 3))
    poster = cv2.resize(photo(name), (ps, ps))
    px, py = int(rng.integers(10, s - ps - 10)), int(rng.integers(s // 2, s - ps - 10))
    img[py : py + ps, px : px + ps] = poster
    cv2.rectangle(img, (px - 4, py - 4), (px + ps + 4, py + ps + 4), 0.05, 5)
    # A unique label: building number + wall letter, big and high contrast.
    sign_y = int(rng.integers(s // 2 + 40, s - 20))
    cv2.rectangle(img, (20, sign_y - 70), (20 + 60 * len(label), sign_y + 15), 0.95, -1)
    _put_text(img, label, (28, sign_y), 2.4, 0.05, 5)
    # Dirt and stains near the ground (the bottom of the texture is at ground level).
    grime = fractal_noise(rng, s, 5, 8)
    ramp = np.linspace(0, 1, s, dtype=np.float32)[:, None] ** 4
    img *= 1.0 - 0.35 * ramp * grime
    return np.clip(img, 0, 1).astype(np.float32)


def roof_texture(rng: np.random.Generator) -> F32:
    s = TEX
    img = 0.3 + 0.35 * fractal_noise(rng, s, 6, 8)
    for _ in range(int(rng.integers(3, 8))):  # vents, AC units, hatches
        w, h = (int(v) for v in rng.integers(20, 90, 2))
        x, y = (int(v) for v in rng.integers(0, s - 100, 2))
        val = float(rng.uniform(0.1, 0.9))
        img[y : y + h, x : x + w] = val
        cv2.rectangle(img, (x, y), (x + w, y + h), 1.0 - val, 3)
    img += 0.25 * (photo("gravel") - 0.5)
    return np.clip(img, 0, 1).astype(np.float32)


def container_texture(rng: np.random.Generator, label: str) -> F32:
    s = TEX
    x = np.arange(s, dtype=np.float32)
    tone = float(rng.uniform(0.25, 0.75))
    img = tone + 0.12 * np.sign(np.sin(x / 9.0))[None, :].repeat(s, 0)
    img += 0.15 * (fractal_noise(rng, s, 6, 12) - 0.5)
    _put_text(img, label, (30, s // 3), 2.2, 1.0 - tone, 5)
    rust = fractal_noise(rng, s, 6, 10) > 0.8
    img[rust] *= 0.5
    return np.clip(img, 0, 1).astype(np.float32)


def ground_tile(
    rng: np.random.Generator,
    x0: float,
    y0: float,
    tile_m: float,
    road_dist: F32,
    road_along: F32,
    road_width: float,
    terrain: F32,
) -> F32:
    """Ground texture for the tile [x0, x0 + tile_m] x [y0, y0 + tile_m] (texture row 0 at y0).

    road_dist: (TEX, TEX) distance of each texel to the nearest road centre line (m); road_along:
    arc length along that road (m, for dashes); terrain: (TEX, TEX) in [0, 1] (grass <-> gravel).
    """
    s = TEX
    m_per_px = tile_m / s
    xs = x0 + (np.arange(s, dtype=np.float32) + 0.5) * m_per_px
    ys = y0 + (np.arange(s, dtype=np.float32) + 0.5) * m_per_px
    X, Y = np.meshgrid(xs, ys)

    def sample(img: F32, period_m: float, ox: float = 0.0, oy: float = 0.0) -> F32:
        mx = ((X + ox) / period_m * img.shape[1]).astype(np.float32)
        my = ((Y + oy) / period_m * img.shape[0]).astype(np.float32)
        out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return np.asarray(out, dtype=np.float32)

    grass = 0.15 + 0.7 * sample(photo("grass"), 3.0)
    gravel = 0.2 + 0.7 * sample(photo("gravel"), 2.5, 1.3, 0.7)
    img = grass * (1 - terrain) + gravel * terrain
    asphalt = 0.22 + 0.2 * sample(photo("gravel"), 1.7, 3.1, 2.2) + 0.08 * (fractal_noise(rng, s, 6, 8) - 0.5)
    half = road_width / 2
    on_road = road_dist < half
    img = np.where(on_road, asphalt, img)
    # Curb: a light strip along the road edge.
    curb = (road_dist >= half) & (road_dist < half + 0.25)
    img = np.where(curb, 0.75 + 0.1 * (gravel - 0.5), img)
    # Markings: dashed centre line (3 m dash, 3 m gap) and solid edge lines.
    centre = (road_dist < 0.08) & (np.mod(road_along, 6.0) < 3.0)
    edge = on_road & (np.abs(road_dist - (half - 0.3)) < 0.07)
    img = np.where(centre | edge, 0.92, img)
    # Unique clutter: manhole covers, oil stains, cracks.
    for _ in range(int(rng.integers(0, 3))):
        cx, cy, r = int(rng.integers(0, s)), int(rng.integers(0, s)), int(rng.integers(15, 40))
        cv2.circle(img, (cx, cy), r, 0.12, -1)
        cv2.circle(img, (cx, cy), r, 0.6, 3)
        for k in range(-r + 6, r - 5, 8):
            cv2.line(img, (cx - r + 5, cy + k), (cx + r - 5, cy + k), 0.35, 1)
    for _ in range(int(rng.integers(1, 4))):
        p = [(int(rng.integers(0, s)), int(rng.integers(0, s)))]
        for _ in range(6):
            p.append((p[-1][0] + int(rng.integers(-40, 41)), p[-1][1] + int(rng.integers(-40, 41))))
        cv2.polylines(img, [np.array(p, np.int32)], False, 0.08, 2)
    return np.clip(img, 0, 1).astype(np.float32)
