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
        for y in range(s // 12, s, s // 6):  # formwork tie holes, 3 x 2 per panel
            for x in range(s // 16, s, s // 8):
                cv2.circle(base, (x, y), 3, 0.12, -1)
                cv2.circle(base, (x, y), 5, 0.55, 1)
        base *= np.where(fractal_noise(rng, s, 6, 12) > 0.7, 0.8, 1.0).astype(np.float32)  # water stains
    else:  # corrugated metal cladding in riveted sheets, weathered in patches
        xr = np.arange(s, dtype=np.float32)
        base = 0.45 + 0.25 * np.sin(xr / 5.0)[None, :].repeat(s, 0) + 0.2 * fractal_noise(rng, s, 5, 6)
        _riveted_sheets(rng, base)
    base = np.clip(base * (0.6 + 0.5 * rng.random()) + 0.15 * (fractal_noise(rng, s, 6, 16) - 0.5), 0, 1)
    img = base.astype(np.float32)
    # A door at ground level (texture bottom): a roller shutter (2.5-4 m wide, 3-4 m high) or a steel
    # man door (1 m x 2.2 m); windows and the poster keep clear of it.
    shutter = bool(rng.random() < 0.5)
    dw, dh = (int(rng.integers(160, 260)), int(rng.integers(200, 260))) if shutter else (64, 140)
    dx = int(rng.integers(0, s - dw))
    # Windows: a grid of dark glass with frames; some with blinds.
    rows, cols = int(rng.integers(1, 3)), int(rng.integers(2, 4))
    for r in range(rows):
        for c in range(cols):
            if rng.random() < 0.2:
                continue
            w, h = s // (cols + 1), s // (rows + 2)
            x0 = int((c + 0.5) * s / cols - w / 2)
            y0 = int(s * 0.12 + r * s * 0.4)
            if y0 + h > s - dh - 16 and x0 < dx + dw + 16 and x0 + w > dx - 16:
                continue  # the door is here
            glass = 0.08 + 0.25 * fractal_noise(rng, max(w, h), 3, 2)[:h, :w]
            if rng.random() < 0.3:
                glass[:: max(3, h // 12)] += 0.5  # blinds
            img[y0 : y0 + h, x0 : x0 + w] = np.clip(glass, 0, 1)
            cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), 0.85, 4)
            cv2.line(img, (x0 + w // 2, y0), (x0 + w // 2, y0 + h), 0.8, 3)
    # A poster: a photograph with a frame, beside the door.
    name = str(
        rng.choice(["astronaut", "chelsea", "coffee", "rocket", "camera", "clock", "coins", "moon", "page"])
    )
    ps = int(rng.integers(s // 5, s // 3))
    poster = cv2.resize(photo(name), (ps, ps))
    px = min(max(_free_x(rng, s, ps, dx, dw), 10), s - ps - 10)
    py = int(rng.integers(s // 2, s - ps - 10))
    if px < dx + dw + 8 and px + ps > dx - 8:  # no room beside the door: hang it above
        py = max(10, s - dh - ps - 24)
    img[py : py + ps, px : px + ps] = poster
    cv2.rectangle(img, (px - 4, py - 4), (px + ps + 4, py + ps + 4), 0.05, 5)
    if shutter:
        slats = 0.5 + 0.1 * np.sin(np.arange(dh, dtype=np.float32) * 1.3)[:, None]
        img[s - dh :, dx : dx + dw] = slats * (0.8 + 0.4 * rng.random())
        cv2.rectangle(img, (dx - 6, s - dh - 6), (dx + dw + 6, s), 0.1, 6)
    else:
        img[s - dh :, dx : dx + dw] = 0.25 + 0.5 * rng.random()
        cv2.rectangle(img, (dx - 4, s - dh - 4), (dx + dw + 4, s), 0.9, 4)
        cv2.circle(img, (dx + dw - 12, s - dh // 2), 4, 0.95, -1)
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
    """A flat roof (8 m x 8 m): fine ballast gravel on a membrane, seams, vents, AC units and hatches."""
    s = TEX
    gravel = np.tile(photo("gravel", s // 4), (4, 4))  # ~6 cm stones
    img = 0.3 + 0.25 * fractal_noise(rng, s, 6, 8) + 0.3 * (gravel - 0.5)
    for y in range(int(rng.integers(0, 64)), s, 96):  # membrane seams
        img[y : y + 2, :] *= 0.7
    for _ in range(int(rng.integers(3, 8))):
        w, h = (int(v) for v in rng.integers(20, 90, 2))
        x, y = (int(v) for v in rng.integers(0, s - 100, 2))
        val = float(rng.uniform(0.15, 0.9))
        unit = float(val + 0.12 * (rng.random() - 0.5))
        img[y : y + h, x : x + w] = unit
        for k in range(x + 4, x + w - 3, 6):  # grille
            cv2.line(img, (k, y + 3), (k, y + h - 3), unit * 0.6, 1)
        cv2.rectangle(img, (x, y), (x + w, y + h), 1.0 - val, 2)
        cv2.line(img, (x + w + 1, y + 2), (x + w + 1, y + h + 1), 0.1, 3)  # its shadow
        cv2.line(img, (x + 2, y + h + 1), (x + w + 1, y + h + 1), 0.1, 3)
    return np.clip(img, 0, 1).astype(np.float32)


def fence_texture(rng: np.random.Generator, label: str) -> F32:
    """A steel palisade fence: the bottom ~2 m of the texture (rows near the bottom touch the ground)
    holds pales with gaps showing a dark, noisy background, two rails and a unique site sign."""
    s = TEX
    img = 0.12 + 0.2 * fractal_noise(rng, s, 6, 24)  # what is seen through the gaps
    tone = float(rng.uniform(0.55, 0.8))
    pale = 7 + int(rng.integers(0, 3))
    for x in range(0, s, pale + 4):
        img[:, x : x + pale] = tone + 0.1 * (fractal_noise(rng, 32, 3, 2)[:1, :1].item() - 0.5)
        img[:, x + pale - 1 : x + pale] *= 0.7
    img += 0.08 * (fractal_noise(rng, s, 6, 32) - 0.5)
    for y in (s - 110, s - 30):
        img[y : y + 6, :] = tone * 0.8
    sign_x = int(rng.integers(20, s - 200))
    cv2.rectangle(img, (sign_x, s - 100), (sign_x + 170, s - 50), 0.95, -1)
    _put_text(img, label, (sign_x + 10, s - 62), 1.2, 0.05, 3)
    grime = np.linspace(0, 1, s, dtype=np.float32)[:, None] ** 6
    img *= 1.0 - 0.3 * grime * fractal_noise(rng, s, 5, 8)
    return np.clip(img, 0, 1).astype(np.float32)


def pillar_texture(rng: np.random.Generator, label: str) -> F32:
    """A concrete post: noisy concrete, a yellow/black hazard band at the foot and a painted number."""
    s = TEX
    img = 0.45 + 0.3 * fractal_noise(rng, s, 6, 16) + 0.15 * (photo("gravel") - 0.5)
    band = np.arange(s)[None, :] + np.arange(s)[:, None]
    stripes = np.where((band // 24) % 2 == 0, 0.85, 0.1).astype(np.float32)
    img[s - 64 :, :] = stripes[s - 64 :, :]
    _put_text(img, label, (2, s - 150), 0.45, 0.08, 1)  # a post is 0.5 m = 32 texels wide
    return np.clip(img, 0, 1).astype(np.float32)


def _free_x(rng: np.random.Generator, s: int, width: int, avoid_x: int, avoid_w: int) -> int:
    """Random x for an item ``width`` wide clear of [avoid_x, avoid_x + avoid_w] (if one is found)."""
    for _ in range(20):
        x = int(rng.integers(0, s - width))
        if x + width + 8 < avoid_x or x > avoid_x + avoid_w + 8:
            return x
    return x


def _riveted_sheets(rng: np.random.Generator, img: F32) -> None:
    """Horizontal sheet seams with rivet rows and weathered patches (corners for ORB), in place."""
    s = img.shape[0]
    pitch = int(rng.integers(96, 160))
    for y in range(int(rng.integers(20, pitch)), s, pitch):
        img[y : y + 3, :] *= 0.6
        for x in range(int(rng.integers(0, 12)), s, 16):
            cv2.circle(img, (x, y - 6), 2, 0.9, -1)
            cv2.circle(img, (x, y + 9), 2, 0.15, -1)
    patches = fractal_noise(rng, s, 6, 12)
    img *= np.where(patches > 0.72, 0.75, 1.0).astype(np.float32)


def container_texture(rng: np.random.Generator, label: str) -> F32:
    """A shipping container side: corrugation, an owner code and numbers, rust streaks, stickers."""
    s = TEX
    x = np.arange(s, dtype=np.float32)
    tone = float(rng.uniform(0.25, 0.75))
    img = tone + 0.12 * np.sign(np.sin(x / 9.0))[None, :].repeat(s, 0)
    img += 0.15 * (fractal_noise(rng, s, 6, 12) - 0.5)
    ink = 1.0 - tone
    _put_text(img, label, (30, s // 3), 2.2, ink, 5)
    letters = "".join(chr(ord("A") + int(v)) for v in rng.integers(0, 26, 4))
    digits = "".join(str(int(v)) for v in rng.integers(0, 10, 7))
    _put_text(img, f"{letters} {digits[:6]} {digits[6]}", (30, s // 3 + 60), 1.0, ink, 2)
    _put_text(
        img,
        f"MAX GROSS {int(rng.integers(24, 34))},{int(rng.integers(0, 999)):03d} KG",
        (30, s // 3 + 100),
        0.7,
        ink,
        1,
    )
    _put_text(
        img,
        f"TARE {int(rng.integers(2, 4))},{int(rng.integers(0, 999)):03d} KG",
        (30, s // 3 + 130),
        0.7,
        ink,
        1,
    )
    for _ in range(int(rng.integers(2, 5))):  # hazard / handling stickers
        cx, cy, r = (
            int(rng.integers(40, s - 40)),
            int(rng.integers(s // 2, s - 40)),
            int(rng.integers(14, 30)),
        )
        diamond = np.array([[cx, cy - r], [cx + r, cy], [cx, cy + r], [cx - r, cy]], np.int32)
        cv2.fillConvexPoly(img, diamond, float(rng.uniform(0.7, 1.0)))
        cv2.polylines(img, [diamond], True, 0.1, 2)
        _put_text(img, str(int(rng.integers(1, 10))), (cx - 9, cy + 9), 0.7, 0.1, 2)
    for x0 in rng.integers(0, s, int(rng.integers(6, 14))):  # rust streaks running down
        y0 = int(rng.integers(0, s // 2))
        length = int(rng.integers(40, 250))
        cv2.line(img, (int(x0), y0), (int(x0) + int(rng.integers(-3, 4)), y0 + length), tone * 0.55, 2)
    rust = fractal_noise(rng, s, 6, 10) > 0.8
    img[rust] *= 0.5
    return np.clip(img, 0, 1).astype(np.float32)


class GroundSources:
    """Periodic ground materials pre-scaled to the ground texel size, cropped per tile (no resampling)."""

    def __init__(self, rng: np.random.Generator, m_per_px: float) -> None:
        def periodic(img: F32, period_m: float) -> F32:
            n = max(8, round(period_m / m_per_px))
            return np.asarray(cv2.resize(img, (n, n), interpolation=cv2.INTER_AREA), dtype=np.float32)

        self.m_per_px = m_per_px
        # Large-scale patches break up the visible repetition of the photographs.
        self.grass = periodic(photo("grass"), 3.0)
        self.grass2 = periodic(np.ascontiguousarray(photo("grass")[::-1, ::-1].T), 2.3)
        self.gravel = periodic(photo("gravel"), 2.5)
        self.asphalt = periodic(photo("gravel"), 1.7)
        self.fine = periodic(fractal_noise(rng, TEX, 4, 32), 1.1)  # asphalt grain, 2 cm features
        self.patches = periodic(fractal_noise(rng, TEX, 5, 4), 37.0)

    @staticmethod
    def crop(src: F32, ox: int, oy: int, n: int = TEX) -> F32:
        """``n`` x ``n`` window of the periodic ``src`` starting at global texel (ox, oy)."""
        h, w = src.shape
        rows = (oy + np.arange(n)) % h
        cols = (ox + np.arange(n)) % w
        return src[rows][:, cols]


def shading_map(
    footprints: list[tuple[F32, float]], sun: F32, origin: tuple[float, float], n: int, m_per_px: float
) -> F32:
    """Sunlight factor on the ground (n x n texels from ``origin``): baked shadows of the boxes and
    ambient occlusion at their feet. ``footprints``: (corners (4, 2) in metres, height) per box."""
    lit = np.full((n, n), 255, np.uint8)
    feet = np.full((n, n), 255, np.uint8)
    shift = -np.asarray(sun[:2]) / max(float(sun[2]), 1e-3)  # ground offset of a point 1 m up
    for corners, height in footprints:
        pts = np.concatenate([corners, corners + height * shift[None, :]])
        px = ((pts - np.asarray(origin)[None, :]) / m_per_px).astype(np.float32)
        hull = cv2.convexHull(px).astype(np.int32)
        cv2.fillConvexPoly(lit, hull, 0, cv2.LINE_AA)
        foot = ((corners - np.asarray(origin)[None, :]) / m_per_px).astype(np.int32)
        cv2.fillConvexPoly(feet, foot, 0)
    shadow = cv2.GaussianBlur(lit.astype(np.float32) / 255.0, (0, 0), 0.06 / m_per_px)
    dist = cv2.distanceTransform(feet, cv2.DIST_L2, 5) * m_per_px
    occlusion = 1.0 - 0.3 * np.exp(-dist / 0.7)
    return ((0.62 + 0.38 * shadow) * occlusion).astype(np.float32)


def ground_tile(
    rng: np.random.Generator,
    src: GroundSources,
    ox: int,
    oy: int,
    road_dist: F32,
    road_along: F32,
    road_width: float,
    terrain: F32,
    light: F32,
) -> F32:
    """Ground texture for the tile whose first texel is global texel (ox, oy) (texture row 0 at low y).

    road_dist: (TEX, TEX) distance of each texel to the nearest road centre line (m); road_along:
    arc length along that road (m, for dashes); terrain: (TEX, TEX) in [0, 1] (grass <-> gravel);
    light: (TEX, TEX) baked sunlight factor (shadows, occlusion).
    """
    s = TEX
    crop = src.crop
    mix = crop(src.patches, ox, oy)
    grass = 0.12 + 0.72 * (mix * crop(src.grass, ox, oy) + (1 - mix) * crop(src.grass2, ox, oy))
    gravel = 0.2 + 0.7 * crop(src.gravel, ox + 83, oy + 45)
    img = grass * (1 - terrain) + gravel * terrain
    wear = crop(src.patches, ox + 1000, oy + 700)
    asphalt = (
        0.2
        + 0.16 * crop(src.asphalt, ox + 198, oy + 141)
        + 0.1 * (crop(src.fine, ox, oy) - 0.5)
        + 0.08 * wear
    )
    half = road_width / 2
    on_road = road_dist < half
    img = np.where(on_road, asphalt, img)
    # Curb: a light concrete strip along the road edge.
    curb = (road_dist >= half) & (road_dist < half + 0.25)
    img = np.where(curb, 0.72 + 0.15 * (gravel - 0.5), img)
    # Markings: dashed centre line (3 m dash, 3 m gap) and solid edge lines, worn by the traffic.
    centre = (road_dist < 0.08) & (np.mod(road_along, 6.0) < 3.0)
    edge = on_road & (np.abs(road_dist - (half - 0.3)) < 0.07)
    paint = 0.7 + 0.25 * crop(src.fine, ox + 311, oy + 97)
    img = np.where(centre | edge, paint, img)
    # Unique clutter: manhole covers, oil stains, tar-sealed cracks.
    for _ in range(int(rng.integers(0, 3))):
        r = int(rng.integers(15, 40))  # whole covers: a tile edge must not cut one in half
        cx, cy = int(rng.integers(r + 4, s - r - 4)), int(rng.integers(r + 4, s - r - 4))
        cv2.circle(img, (cx, cy), r, 0.12, -1)
        cv2.circle(img, (cx, cy), r, 0.6, 3)
        for k in range(-r + 6, r - 5, 8):
            cv2.line(img, (cx - r + 5, cy + k), (cx + r - 5, cy + k), 0.35, 1)
    for _ in range(int(rng.integers(0, 3))):
        cx, cy = int(rng.integers(80, s - 80)), int(rng.integers(80, s - 80))
        ax = (int(rng.integers(10, 60)), int(rng.integers(8, 40)))
        stain = np.zeros((s, s), np.float32)
        cv2.ellipse(stain, (cx, cy), ax, float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
        img *= 1.0 - 0.35 * cv2.GaussianBlur(stain, (0, 0), 6)
    for _ in range(int(rng.integers(1, 4))):
        p = [(int(rng.integers(0, s)), int(rng.integers(0, s)))]
        for _ in range(6):
            step = rng.integers(-40, 41, 2)
            p.append((int(np.clip(p[-1][0] + step[0], 3, s - 4)), int(np.clip(p[-1][1] + step[1], 3, s - 4))))
        crack = np.zeros((s, s), np.float32)
        cv2.polylines(crack, [np.array(p, np.int32)], False, 1.0, 2, cv2.LINE_AA)
        img *= 1.0 - 0.45 * crack  # tar-sealed: darker than the surface, not black
    return np.clip(img * light, 0, 1).astype(np.float32)
