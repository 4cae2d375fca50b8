"""Marker corners from its four border edges: sub-pixel edge points along each side, one line per side
fitted in the undistorted image, corners where the lines meet.

``cv2.aruco``'s own refinement (``CORNER_REFINE_SUBPIX``) looks at a window around each corner that its
``relativeCornerRefinmentWinSize`` shrinks to a fraction of a code cell, so a small marker's corners come
from a few pixels each. A side of the black border is a straight dark-to-bright step along its whole
length: dozens of edge samples per side fix its line, and the corners with it, far better (measured in
docs/decisions.md, issue 25). The lines are fitted after undistortion, where the border's sides are
straight.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera

F64 = NDArray[np.float64]
CODE_CELLS = 6  # a 4x4 code with its one-cell black border: the border is a sixth of the side
_STEP_PX = 0.25  # profile sampling step across an edge
_END_FRACTION = 0.15  # each side's ends are left out: the corners round them off and the next side starts
_MAX_SAMPLES = 32  # edge samples per side: a long side is fixed well before this many
_MIN_RISE = 2.0  # grey levels per pixel: a flatter profile shows no edge (sensor noise, or hidden)


def refine_quad(
    gray: NDArray[np.uint8], quad: F64, camera: PinholeCamera, offset: tuple[int, int] = (0, 0)
) -> F64 | None:
    """The corners (4, 2) of one marker whose cv2.aruco corners are ``quad`` (4, 2, full-image pixels),
    or None when an edge does not show (then keep cv2's). ``gray`` may be a crop whose top-left pixel is
    at ``offset`` in the image; the camera's distortion is that of the full image."""
    quad = np.asarray(quad, np.float64).reshape(4, 2)
    a, b = quad, quad[[1, 2, 3, 0]]  # side i runs from corner i to corner i + 1
    length = np.linalg.norm(b - a, axis=1)
    if float(length.min()) < 4.0:
        return None
    along = (b - a) / length[:, None]
    normal = np.stack([along[:, 1], -along[:, 0]], axis=1)
    outward = np.einsum("ij,ij->i", normal, (a + b) / 2 - quad.mean(axis=0))
    normal *= np.where(outward < 0, -1.0, 1.0)[:, None]
    cell_px = float(length.mean()) / CODE_CELLS
    # the profile spans most of the black border inside and the white quiet zone outside, never the code
    half = float(np.clip(0.8 * cell_px, 1.0, 3.0))
    offs = np.arange(-half, half + 1e-9, _STEP_PX)
    m = int(np.clip(length.mean() * (1 - 2 * _END_FRACTION), 4, _MAX_SAMPLES))
    t = np.linspace(_END_FRACTION, 1 - _END_FRACTION, m)
    pts = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]  # (4, m, 2)
    samp = pts[:, :, None, :] + offs[None, None, :, None] * normal[:, None, None, :] - np.asarray(offset)
    prof = cv2.remap(
        np.asarray(gray),
        samp[..., 0].reshape(4 * m, -1).astype(np.float32),
        samp[..., 1].reshape(4 * m, -1).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    # the edge is where the profile rises from the border's black to the quiet zone's white: the centroid
    # of the rising gradient (a falling one belongs to something else)
    grad = np.clip(np.diff(prof, axis=1), 0.0, None)
    weight = grad.sum(axis=1).reshape(4, m)
    shift = (grad @ ((offs[:-1] + offs[1:]) / 2)).reshape(4, m) / np.maximum(weight, 1e-9)
    edge = pts + shift[..., None] * normal[:, None, :]
    und = cv2.undistortPoints(edge.reshape(-1, 1, 2), camera.K, camera.dist_coeffs).reshape(4, m, 2)
    weight = np.where(weight > _MIN_RISE * (offs[-1] - offs[0]), weight, 0.0)
    if int((weight > 0).sum(axis=1).min()) < 3:
        return None
    # one weighted total-least-squares line per side: through the centroid, along the principal axis
    w = weight / weight.sum(axis=1, keepdims=True)
    mu = np.einsum("sm,smk->sk", w, und)
    dev = und - mu[:, None, :]
    sxx = np.einsum("sm,sm->s", w, dev[..., 0] ** 2)
    syy = np.einsum("sm,sm->s", w, dev[..., 1] ** 2)
    sxy = np.einsum("sm,sm->s", w, dev[..., 0] * dev[..., 1])
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    n = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    lines = np.concatenate([n, -np.einsum("sk,sk->s", n, mu)[:, None]], axis=1)
    x = np.cross(lines[[3, 0, 1, 2]], lines)  # corner i joins side i - 1 (into it) and side i
    if float(np.abs(x[:, 2]).min()) < 1e-12:
        return None
    norm = np.hstack([x[:, :2] / x[:, 2:], np.ones((4, 1))])
    proj, _ = cv2.projectPoints(norm, np.zeros(3), np.zeros(3), camera.K, camera.dist_coeffs)
    out = np.asarray(proj, np.float64).reshape(4, 2)
    # a corner that moved further than a border's width found another edge than the marker's
    if not np.isfinite(out).all() or float(np.abs(out - quad).max()) > max(1.0, cell_px):
        return None
    return out
