"""Renderers of the simulated site: grayscale + metric depth from a pinhole camera with distortion.

- ``GLRenderer``: moderngl on a headless EGL context (Mesa llvmpipe, no GPU needed). Renders an
  undistorted view slightly wider than the camera, then applies the lens distortion with a
  precomputed ``cv2.remap``. Depth is the camera-frame z in metres (inf for sky), written by the
  fragment shader to a float32 attachment (exact, not the non-linear z-buffer).
- ``NumpyRenderer``: the same scene ray-cast in numpy (ground plane + box faces). Slow, but needs
  nothing; it is the fallback when EGL is missing and the depth reference in tests.

``make_renderer(world, camera, backend="auto", extra_layers=None)`` picks one. Both return
``render(world_from_cam, quads=None) -> (gray uint8 (H, W), depth float32 (H, W))`` with the camera's
distortion; ``quads`` are per-frame objects (the other agents' marker carriers) textured from
``extra_layers``, texture layers appended after the world's.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3_inverse
from hivemap.sim.world import GROUND_SHADE, TEXTURE_M, World, box_quads

log = logging.getLogger(__name__)
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]
SKY_TOP, SKY_HORIZON = 150.0, 215.0


@dataclass(frozen=True)
class Quads:
    """Textured planar quads drawn on top of the static scene in one frame (the agents' marker carriers):
    corners (Q, 4, 3) in the world, uv (Q, 4, 2), texture layer (Q,) and shade (Q,), as ``box_quads``.
    Each is one-sided: seen from its front only (corners p0, p1, p2 clockwise in the image), because the
    agents' bodies, which would hide a panel's back, are not drawn."""

    corners: F64
    uv: F64
    layer: NDArray[np.int32]
    shade: F64


class Renderer(Protocol):
    camera: PinholeCamera

    def render(self, world_from_cam: F64, quads: Quads | None = None) -> tuple[U8, F32]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class _UndistortPlan:
    """Render an undistorted image with ``K_render`` of size ``size``; remap maps give the distortion."""

    K_render: F64
    size: tuple[int, int]  # (width, height)
    map_x: F32
    map_y: F32


def _plan(camera: PinholeCamera) -> _UndistortPlan:
    h, w = camera.height, camera.width
    if not camera.has_distortion:
        K = camera.K
        mx, my = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        return _UndistortPlan(K, (w, h), mx, my)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xy = camera.undistort_to_normalized(np.stack([u.ravel(), v.ravel()], 1))
    px = camera.fx * xy[:, 0] + camera.cx
    py = camera.fy * xy[:, 1] + camera.cy
    pad = 2.0
    x0, x1 = np.floor(px.min() - pad), np.ceil(px.max() + pad)
    y0, y1 = np.floor(py.min() - pad), np.ceil(py.max() + pad)
    K = camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    size = (int(x1 - x0) + 1, int(y1 - y0) + 1)
    return _UndistortPlan(
        K, size, (px - x0).reshape(h, w).astype(np.float32), (py - y0).reshape(h, w).astype(np.float32)
    )


def _remap_inverse_depth(inv: F32, map_x: F32, map_y: F32) -> F32:
    """Resample inverse depth (0 = sky) and return depth (inf = sky). For a plane 1/z is affine in the
    undistorted image, so bilinear interpolation of 1/z is exact on smooth surfaces; across depth edges
    and at the sky the nearest sample is kept (never a blend of a foreground and a background surface)."""
    near = cv2.remap(inv, map_x, map_y, cv2.INTER_NEAREST)
    lin = cv2.remap(inv, map_x, map_y, cv2.INTER_LINEAR)
    smooth = np.abs(lin - near) < 0.05 * near
    inv_out = np.where(smooth, lin, near)
    depth = np.full(inv_out.shape, np.inf, np.float32)
    np.divide(1.0, inv_out, out=depth, where=inv_out > 0)
    return depth


def _sky(depth: F32, gray: F32, camera_rows: int) -> F32:
    rows = np.linspace(0, 1, camera_rows, dtype=np.float32)[:, None]
    sky = SKY_TOP + (SKY_HORIZON - SKY_TOP) * rows
    return np.where(np.isfinite(depth), gray, np.broadcast_to(sky, gray.shape)).astype(np.float32)


VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
uniform mat4 view;
in vec3 in_pos;
in vec2 in_uv;
in float in_layer;
in float in_shade;
out vec2 v_uv;
flat out float v_layer;
out float v_shade;
out float v_depth;
void main() {
    gl_Position = mvp * vec4(in_pos, 1.0);
    v_uv = in_uv;
    v_layer = in_layer;
    v_shade = in_shade;
    v_depth = (view * vec4(in_pos, 1.0)).z;
}
"""
FRAGMENT_SHADER = """
#version 330
uniform sampler2DArray tex;
in vec2 v_uv;
flat in float v_layer;
in float v_shade;
in float v_depth;
layout(location = 0) out float out_gray;
layout(location = 1) out float out_inv_depth;
void main() {
    out_gray = texture(tex, vec3(v_uv, v_layer)).r * v_shade;
    out_inv_depth = -1.0 / v_depth;  // camera looks along -z in GL: 1 / (depth in metres); 0 = sky
}
"""


def _scene_vertices(world: World) -> NDArray[np.float32]:
    """Interleaved triangles: x y z u v layer shade (float32)."""
    verts: list[F64] = []
    n, t = world.tiles_n, world.tile_m
    ox, oy = world.tiles_origin
    for iy in range(n):
        for ix in range(n):
            x0, y0 = ox + ix * t, oy + iy * t
            c = np.array([[x0, y0, 0], [x0 + t, y0, 0], [x0 + t, y0 + t, 0], [x0, y0 + t, 0]], float)
            uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
            verts.append(_quad_tris(c, uv, world.tile_layer(ix, iy), GROUND_SHADE))
    # Far-field ground: four quads around the tiled site out to world.apron_m.
    h, A = n * t / 2, world.apron_m
    for x0, y0, x1, y1 in ((-A, -A, A, -h), (-A, h, A, A), (-A, -h, -h, h), (h, -h, A, h)):
        c = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
        uv = c[:, :2] / TEXTURE_M
        verts.append(_quad_tris(c, uv, world.apron_layer, GROUND_SHADE))
    corners, uvs, layers, shades = box_quads(world)
    for c, uv, lay, sh in zip(corners, uvs, layers, shades, strict=True):
        verts.append(_quad_tris(c, uv, int(lay), float(sh)))
    return np.concatenate(verts).astype(np.float32)


def _quad_tris(c: F64, uv: F64, layer: int, shade: float) -> F64:
    idx = [0, 1, 2, 0, 2, 3]
    out = np.zeros((6, 7))
    out[:, :3] = c[idx]
    out[:, 3:5] = uv[idx]
    out[:, 5] = layer
    out[:, 6] = shade
    return out


def _all_layers(world: World, extra: NDArray[np.uint8] | None) -> NDArray[np.uint8]:
    if extra is None or len(extra) == 0:
        return world.layers
    if extra.shape[1:] != world.layers.shape[1:]:
        raise ValueError(
            f"extra texture layers {extra.shape[1:]} do not match the world's {world.layers.shape[1:]}"
        )
    return np.concatenate([world.layers, np.asarray(extra, dtype=np.uint8)])


def _quad_arrays(q: Quads) -> tuple[F64, F64, NDArray[np.int32], F64]:
    return q.corners, q.uv, q.layer, q.shade


class GLRenderer:
    """moderngl + headless EGL renderer (see module docstring)."""

    def __init__(
        self,
        world: World,
        camera: PinholeCamera,
        near: float = 0.05,
        far: float = 3000.0,
        extra_layers: NDArray[np.uint8] | None = None,
    ) -> None:
        import moderngl

        self.camera = camera
        self.near, self.far = near, far
        self.plan = _plan(camera)
        self.ctx = moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]
        layers = np.ascontiguousarray(_all_layers(world, extra_layers), dtype=np.uint8)
        L, s, _ = layers.shape
        self.tex = self.ctx.texture_array((s, s, L), 1, layers.tobytes())
        self.tex.build_mipmaps()
        self.tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        # No anisotropic filtering: on Mesa llvmpipe it costs ~400x at grazing angles (a UGV frame took
        # 3.6 s with anisotropy 16 vs 8.6 ms without); trilinear mipmapping keeps distant ground alias-free.
        self.tex.anisotropy = 1.0
        self.tex.repeat_x = self.tex.repeat_y = True
        self.prog = self.ctx.program(vertex_shader=VERTEX_SHADER, fragment_shader=FRAGMENT_SHADER)
        vbo = self.ctx.buffer(_scene_vertices(world).tobytes())
        self.vao = self.ctx.vertex_array(
            self.prog, [(vbo, "3f 2f 1f 1f", "in_pos", "in_uv", "in_layer", "in_shade")]
        )
        w, h = self.plan.size
        self.color = self.ctx.renderbuffer((w, h), 1, dtype="f4")
        self.depth_out = self.ctx.renderbuffer((w, h), 1, dtype="f4")
        self.zbuf = self.ctx.depth_renderbuffer((w, h))
        self.fbo = self.ctx.framebuffer([self.color, self.depth_out], self.zbuf)
        self.proj = self._projection(self.plan.K_render, w, h)
        self._map_y_gl = np.ascontiguousarray((h - 1) - self.plan.map_y, dtype=np.float32)

    def _projection(self, K: F64, w: int, h: int) -> F64:
        """OpenCV intrinsics -> GL projection for the GL camera (x right, y up, z backwards)."""
        n, f = self.near, self.far
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
        return np.array(
            [
                [2 * fx / w, 0, 1 - 2 * cx / w, 0],
                [0, 2 * fy / h, 2 * cy / h - 1, 0],
                [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
                [0, 0, -1, 0],
            ]
        )

    def render(self, world_from_cam: F64, quads: Quads | None = None) -> tuple[U8, F32]:
        import moderngl

        cv_from_world = se3_inverse(np.asarray(world_from_cam, dtype=np.float64))
        gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
        view = gl_from_cv @ cv_from_world
        mvp = self.proj @ view
        self.prog["mvp"].write(mvp.T.astype("f4").tobytes())  # type: ignore[union-attr]
        self.prog["view"].write(view.T.astype("f4").tobytes())  # type: ignore[union-attr]
        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE * 0)
        self.tex.use(0)
        self.vao.render(moderngl.TRIANGLES)
        if quads is not None and len(quads.corners):
            tris = np.concatenate(
                [
                    _quad_tris(c, uv, int(la), float(sh))
                    for c, uv, la, sh in zip(*_quad_arrays(quads), strict=True)
                ]
            )
            vbo = self.ctx.buffer(tris.astype(np.float32).tobytes())
            vao = self.ctx.vertex_array(
                self.prog, [(vbo, "3f 2f 1f 1f", "in_pos", "in_uv", "in_layer", "in_shade")]
            )
            # carriers are seen from the front only (see Quads): clockwise in the image is clockwise in
            # GL's window too (the image rows are read bottom-up, and so is its y axis)
            self.ctx.front_face = "cw"
            self.ctx.enable(moderngl.CULL_FACE)
            vao.render(moderngl.TRIANGLES)
            self.ctx.disable(moderngl.CULL_FACE)
            self.ctx.front_face = "ccw"
            vao.release()
            vbo.release()
        w, h = self.plan.size
        gray = np.frombuffer(self.fbo.read(components=1, attachment=0, dtype="f4"), np.float32).reshape(h, w)
        inv = np.frombuffer(self.fbo.read(components=1, attachment=1, dtype="f4"), np.float32).reshape(h, w)
        p = self.plan
        if self.camera.has_distortion or p.size != (self.camera.width, self.camera.height):
            # GL rows start at the bottom: the maps sample the flipped image directly (no copy).
            gray = np.asarray(cv2.remap(gray, p.map_x, self._map_y_gl, cv2.INTER_LINEAR), np.float32)
            depth = _remap_inverse_depth(inv, p.map_x, self._map_y_gl)
        else:
            gray = gray[::-1]
            inv = inv[::-1]
            depth = np.full(inv.shape, np.inf, np.float32)
            np.divide(1.0, inv, out=depth, where=inv > 0)
        gray = _sky(depth, gray * np.float32(255.0), self.camera.height)
        return np.clip(gray + 0.5, 0, 255).astype(np.uint8), depth

    def close(self) -> None:
        self.ctx.release()


class NumpyRenderer:
    """Pure numpy ray caster of the same scene (nearest-texel shading, exact depth)."""

    def __init__(
        self, world: World, camera: PinholeCamera, extra_layers: NDArray[np.uint8] | None = None
    ) -> None:
        self.world = world
        self.camera = camera
        self.layers = _all_layers(world, extra_layers)
        u, v = np.meshgrid(
            np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64)
        )
        xy = camera.undistort_to_normalized(np.stack([u.ravel(), v.ravel()], 1))
        self.rays_cam = np.concatenate([xy, np.ones((len(xy), 1))], 1)  # z = 1: t is the depth
        self.corners, self.uvs, self.box_layers, self.shades = box_quads(world)
        grid = xy.reshape(camera.height, camera.width, 2)
        # Normalised-coordinate extent of each pixel row / column, to cull rays per quad.
        self._row_lo, self._row_hi = grid[..., 1].min(1), grid[..., 1].max(1)
        self._col_lo, self._col_hi = grid[..., 0].min(0), grid[..., 0].max(0)

    def _candidate_rays(self, corners_cam: F64) -> NDArray[np.intp] | None:
        """Indices of the rays that may hit a planar quad (camera-frame corners); None = no ray."""
        z = corners_cam[:, 2]
        if (z <= 1e-6).all():
            return None  # behind the camera
        w = self.camera.width
        if (z <= 1e-6).any():
            return np.arange(self.camera.height * w)  # straddles the camera plane: test every ray
        nxy = corners_cam[:, :2] / z[:, None]  # a convex quad projects inside its corners' hull
        (x0, y0), (x1, y1) = nxy.min(0), nxy.max(0)
        rows = np.flatnonzero((self._row_hi >= y0) & (self._row_lo <= y1))
        cols = np.flatnonzero((self._col_hi >= x0) & (self._col_lo <= x1))
        if len(rows) == 0 or len(cols) == 0:
            return None
        r = np.arange(rows[0], rows[-1] + 1)
        c = np.arange(cols[0], cols[-1] + 1)
        return (r[:, None] * w + c[None, :]).ravel()

    def render(self, world_from_cam: F64, quads: Quads | None = None) -> tuple[U8, F32]:
        T = np.asarray(world_from_cam, dtype=np.float64)
        d = self.rays_cam @ T[:3, :3].T
        o = T[:3, 3]
        n = len(d)
        best = np.full(n, np.inf)
        val = np.zeros(n)
        # Ground plane z = 0.
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = -o[2] / d[:, 2]
        ok = np.isfinite(tg) & (tg > 1e-6)
        hit = o + tg[:, None] * d
        w = self.world
        half = w.tiles_n * w.tile_m / 2
        ok &= (np.abs(hit[:, 0]) < w.apron_m) & (np.abs(hit[:, 1]) < w.apron_m)
        best[ok] = tg[ok]
        apron = ok & ((np.abs(hit[:, 0]) >= half) | (np.abs(hit[:, 1]) >= half))
        val[apron] = (
            self._sample(
                np.full(int(apron.sum()), w.apron_layer), hit[apron, 0] / TEXTURE_M, hit[apron, 1] / TEXTURE_M
            )
            * GROUND_SHADE
        )
        ok &= ~apron
        gx = (hit[ok, 0] - w.tiles_origin[0]) / w.tile_m
        gy = (hit[ok, 1] - w.tiles_origin[1]) / w.tile_m
        ix, iy = np.clip(gx.astype(int), 0, w.tiles_n - 1), np.clip(gy.astype(int), 0, w.tiles_n - 1)
        val[ok] = self._sample(iy * w.tiles_n + ix, gx - ix, gy - iy) * GROUND_SHADE
        # Box faces and the frame's extra quads (planar quads).
        faces = [zip(self.corners, self.uvs, self.box_layers, self.shades, strict=True)]
        if quads is not None:
            faces.append(zip(*_quad_arrays(quads), strict=True))
        n_static = len(self.corners)
        for q, (c, uv, lay, sh) in enumerate(itertools.chain(*faces)):
            rays = self._candidate_rays((c - o) @ T[:3, :3])
            if rays is None:
                continue
            e1, e2 = c[1] - c[0], c[3] - c[0]
            nrm = np.cross(e1, e2)
            if q >= n_static and (c[0] - o) @ nrm <= 0:
                continue  # a carrier quad seen from its back (one-sided, as in the GL renderer)
            den = d[rays] @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                t_r = ((c[0] - o) @ nrm) / den
            cand = np.isfinite(t_r) & (t_r > 1e-6) & (t_r < best[rays])
            if not cand.any():
                continue
            idx, tc = rays[cand], t_r[cand]
            p = o + tc[:, None] * d[idx] - c[0]
            a = (p @ e1) / (e1 @ e1)
            b = (p @ e2) / (e2 @ e2)
            inside = (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
            idx, a, b = idx[inside], a[inside], b[inside]
            best[idx] = tc[inside]
            tu = uv[0, 0] + a * (uv[1, 0] - uv[0, 0])
            tv = uv[0, 1] + b * (uv[3, 1] - uv[0, 1])
            val[idx] = self._sample(np.full(len(idx), lay), tu, tv) * sh
        h, wd = self.camera.height, self.camera.width
        depth = best.reshape(h, wd).astype(np.float32)
        gray = _sky(depth, (val * 255.0).reshape(h, wd).astype(np.float32), h)
        return np.clip(gray + 0.5, 0, 255).astype(np.uint8), depth

    def _sample(self, layer: NDArray[np.int64], u: F64, v: F64) -> F64:
        s = self.layers.shape[1]
        x = (np.floor(np.mod(u, 1.0) * s).astype(int)) % s
        y = (np.floor(np.mod(v, 1.0) * s).astype(int)) % s
        return self.layers[layer, y, x].astype(np.float64) / 255.0

    def close(self) -> None:
        pass


def egl_available() -> tuple[bool, str]:
    """Whether a headless EGL context can be created here (and why not)."""
    try:
        import moderngl

        ctx = moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]
        ctx.release()
        return True, ""
    except Exception as e:  # moderngl raises plain Exceptions for missing libEGL / drivers
        return False, f"{type(e).__name__}: {e}"


def make_renderer(
    world: World, camera: PinholeCamera, backend: str = "auto", extra_layers: NDArray[np.uint8] | None = None
) -> Renderer:
    """``backend``: "gl", "numpy", or "auto" (gl when EGL works, else numpy with a warning)."""
    if backend not in ("auto", "gl", "numpy"):
        raise ValueError(f"unknown renderer backend {backend!r}: use auto, gl or numpy")
    if backend == "numpy":
        return NumpyRenderer(world, camera, extra_layers)
    if backend == "gl":
        return GLRenderer(world, camera, extra_layers=extra_layers)
    ok, why = egl_available()
    if ok:
        return GLRenderer(world, camera, extra_layers=extra_layers)
    log.warning(
        "headless EGL unavailable (%s); using the slow numpy renderer. Install libegl1 libegl-mesa0 "
        "libgl1-mesa-dri for the fast one.",
        why,
    )
    return NumpyRenderer(world, camera, extra_layers)
