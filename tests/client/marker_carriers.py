"""Carrier layouts for the marker tests: a cube of markers and a flat board, built in the body frame."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.markers import Carrier, Marker

F64 = NDArray[np.float64]


def face_corners(centre: F64, normal: F64, up_hint: F64, size: float) -> F64:
    """OpenCV corner order (TL, TR, BR, BL) of a square facing ``normal``: u x v points away from a
    viewer on the ``normal`` side (u to the viewer's right, v down)."""
    n = normal / np.linalg.norm(normal)
    v = -(up_hint - (up_hint @ n) * n)
    v /= np.linalg.norm(v)
    u = np.cross(v, -n)  # u x v = -n
    h = size / 2
    return np.stack(
        [centre + h * (-u - v), centre + h * (u - v), centre + h * (u + v), centre + h * (-u + v)]
    )


def cube_carrier(
    agent_id: str,
    first_id: int,
    side: float,
    centre: F64,
    body_from_cam: F64,
    dictionary: str = "DICT_4X4_50",
) -> Carrier:
    """Markers of ``0.7 * side`` on the cube's four sides and its bottom (body z up)."""
    ex, ey, ez = np.eye(3)
    faces = [(ex, ez), (-ex, ez), (ey, ez), (-ey, ez), (-ez, ex)]
    markers = tuple(
        Marker(first_id + i, 0.7 * side, face_corners(centre + n * side / 2, n, up, 0.7 * side))
        for i, (n, up) in enumerate(faces)
    )
    return Carrier(agent_id, dictionary, body_from_cam, markers)


def board_carrier(
    agent_id: str, first_id: int, size: float, gap: float, body_from_cam: F64, dictionary: str = "DICT_4X4_50"
) -> Carrier:
    """A 2 x 2 board of markers on the body's z = 0 plane facing up (a roof board)."""
    ex, _, ez = np.eye(3)
    step = size + gap
    centres = [np.array([x, y, 0.0]) for y in (step / 2, -step / 2) for x in (step / 2, -step / 2)]
    markers = tuple(Marker(first_id + i, size, face_corners(c, ez, ex, size)) for i, c in enumerate(centres))
    return Carrier(agent_id, dictionary, body_from_cam, markers)
