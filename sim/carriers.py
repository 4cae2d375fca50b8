"""Marker carriers of a scenario's agents: geometry (``maps.markers`` layouts) and what the renderer draws.

Design (issue 25, chosen from the visibility table in docs/decisions.md): each UAV carries a cube of
markers hanging under its body (four side faces and the bottom face, one marker each), the UGV a flat
board of markers on its roof, beside and behind the UAVs' take-off spots, panels on its back and sides,
and small roof markers beside the take-off spots for cameras too close for the others. Every marker of a
``cv2.aruco`` 4x4 dictionary is printed with a one-cell white quiet zone, so a face of side ``s`` holds a
marker of ``s * 6 / 8`` (6 cells of code and black border out of 8).

``team_carriers(scenario)`` gives every agent's :class:`~hivemap.maps.markers.Carrier` (ids assigned in
the scenario's agent order); ``carrier_quads`` gives the textured quads (body frame) the renderer draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.maps.markers import Carrier, Marker
from hivemap.sim.render import Quads
from hivemap.sim.scenarios import UGV_ROOF_HEIGHT, AgentSpec, Scenario

F64 = NDArray[np.float64]
DICTIONARY = "DICT_4X4_50"
CODE_CELLS = 6  # 4x4 code plus the one-cell black border
FACE_CELLS = 8  # plus the one-cell white quiet zone
MARKER_SHADE = 0.9  # white paper a little darker than full white, so fog/light never clips it
BODY_SHADE = 0.35  # the carrier's plain body (cube top, board edge)


SMALL_ROOF_ROWS_X = (-0.2, 0.1, 0.4, 0.7)  # the small roof markers' rows, for ``CarrierDesign``


@dataclass(frozen=True)
class CarrierDesign:
    """Carrier sizes. UAV cube: side ``uav_cube_m``, its top ``uav_hang_m`` below the body origin. UGV
    board: ``ugv_rows`` x 2 markers of face side ``ugv_face_m`` on the roof (``roof_z`` above the body
    origin), the two columns ``ugv_gap_m`` apart (the UAVs stand on the centre line), rows centred at
    ``ugv_rows_x`` along the body x axis; small roof markers of face ``ugv_small_face_m`` in rows at
    ``ugv_small_rows_x``, in the same two columns."""

    uav_cube_m: float = 0.30
    uav_hang_m: float = 0.05
    ugv_face_m: float = 0.55
    ugv_gap_m: float = 0.30
    ugv_rows_x: tuple[float, ...] = (-0.65,)
    roof_z: float = 0.5  # UGV_ROOF_HEIGHT - UGV_BODY_HEIGHT
    # small roof markers beside the UAVs' take-off spots, in front of the board (``SMALL_ROOF_ROWS_X``):
    # the board's and the panels' markers are bigger than the image of a camera 1-2 m from the UGV, these
    # fit it whole. Off by default: with the board under them they fill a climbing UAV's near view, and
    # masked they leave its tracker nothing for its first second off the roof (docs/decisions.md)
    ugv_small_face_m: float = 0.25
    ugv_small_rows_x: tuple[float, ...] = ()
    ugv_back: bool = True  # two panels of face ``ugv_panel_m`` on the back, facing -x
    ugv_sides: bool = True  # two panels on each side
    ugv_panel_m: float = 0.7
    ugv_half_length_m: float = 1.1
    ugv_half_width_m: float = 0.7
    dictionary: str = DICTIONARY


def _face(center: F64, normal: F64, up: F64, side: float) -> F64:
    """(4, 3) corners TL, TR, BR, BL of a square of ``side`` facing ``normal``, image top towards ``up``.
    Seen from the front the viewer's right is ``up x normal``."""
    n = normal / np.linalg.norm(normal)
    u = up / np.linalg.norm(up)
    r = np.cross(u, n)
    h = side / 2
    return np.array(
        [center - r * h + u * h, center + r * h + u * h, center + r * h - u * h, center - r * h - u * h]
    )


def _inset(face: F64) -> F64:
    """The marker's corners (black border) inside a face with the quiet zone around it."""
    c = face.mean(0)
    return np.asarray(c + (face - c) * (CODE_CELLS / FACE_CELLS), dtype=np.float64)


@dataclass(frozen=True)
class CarrierGeometry:
    """What is drawn for one carrier, in its agent's body frame: marker faces (F, 4, 3) with their ids
    (the whole face incl. quiet zone is textured) and plain body quads (P, 4, 3)."""

    faces: F64
    ids: tuple[int, ...]
    plain: F64
    kind: str = "uav"


def uav_faces(d: CarrierDesign) -> tuple[F64, F64]:
    """(marker faces (5, 4, 3): +x, -x, +y, -y, bottom; plain top (1, 4, 3)) of the UAV cube."""
    s = d.uav_cube_m
    c = np.array([0.0, 0.0, -d.uav_hang_m - s / 2])
    z = np.array([0.0, 0.0, 1.0])
    faces = [
        _face(c + n * s / 2, n, z, s) for n in (np.eye(3)[0], -np.eye(3)[0], np.eye(3)[1], -np.eye(3)[1])
    ]
    faces.append(_face(c - z * s / 2, -z, np.eye(3)[0], s))
    top = _face(c + z * s / 2, z, np.eye(3)[0], s)
    return np.array(faces), top[None]


def _roof_rows(
    d: CarrierDesign, rows_x: tuple[float, ...], s: float, back_m: float
) -> tuple[list[F64], list[F64]]:
    """Roof markers of face ``s`` (image top to the front) in rows at ``rows_x``, one each side of the UAVs'
    centre line, and the plain board under them (5 cm beyond the markers at the sides and the front,
    ``back_m`` behind them)."""
    z, x = np.array([0.0, 0.0, 1.0]), np.eye(3)[0]
    faces = [
        _face(np.array([rx, side * (d.ugv_gap_m / 2 + s / 2), d.roof_z + 0.002]), z, x, s)
        for rx in rows_x
        for side in (1.0, -1.0)
    ]
    if not rows_x:
        return faces, []
    half_y = d.ugv_gap_m / 2 + s + 0.05
    x0, x1 = min(rows_x) - s / 2 - back_m, max(rows_x) + s / 2 + 0.05
    return faces, [
        np.array(
            [[x1, half_y, d.roof_z], [x1, -half_y, d.roof_z], [x0, -half_y, d.roof_z], [x0, half_y, d.roof_z]]
        )
    ]


def ugv_faces(d: CarrierDesign) -> tuple[F64, F64]:
    """(marker faces (F, 4, 3), plain board quads) of the UGV: the roof board's markers, optionally panels
    on the back (facing -x) and the sides, then the small roof markers."""
    z = np.array([0.0, 0.0, 1.0])
    x, y = np.eye(3)[0], np.eye(3)[1]
    faces, plain = _roof_rows(d, d.ugv_rows_x, d.ugv_face_m, 0.05)
    p = d.ugv_panel_m
    zc = d.roof_z - p / 2
    if d.ugv_back:
        for side in (1.0, -1.0):
            faces.append(_face(np.array([-d.ugv_half_length_m - 0.002, side * p / 2, zc]), -x, z, p))
    if d.ugv_sides:
        for side in (1.0, -1.0):
            for rx in (-p / 2, p / 2):
                faces.append(_face(np.array([rx, side * (d.ugv_half_width_m + 0.002), zc]), side * y, z, p))
    # appended last, so the board's and the panels' ids stay what they were
    small, small_plain = _roof_rows(d, d.ugv_small_rows_x, d.ugv_small_face_m, 0.0)  # meets the board
    return np.array(faces + small), np.array(plain + small_plain, dtype=np.float64).reshape(-1, 4, 3)


def carrier_geometry(spec: AgentSpec, first_id: int, d: CarrierDesign) -> CarrierGeometry:
    faces, plain = uav_faces(d) if spec.kind == "uav" else ugv_faces(d)
    return CarrierGeometry(faces, tuple(range(first_id, first_id + len(faces))), plain, spec.kind)


def team_geometry(scenario: Scenario, d: CarrierDesign = CarrierDesign()) -> dict[str, CarrierGeometry]:
    """Every agent's carrier geometry; marker ids run through the agents in the scenario's order."""
    out: dict[str, CarrierGeometry] = {}
    nxt = 0
    for a in scenario.agents:
        g = carrier_geometry(a, nxt, d)
        out[a.agent_id] = g
        nxt += len(g.ids)
    n_ids = _dictionary(d.dictionary).bytesList.shape[0]
    if nxt > n_ids:
        raise ValueError(f"{nxt} markers do not fit in {d.dictionary} ({n_ids} ids)")
    return out


def team_carriers(
    scenario: Scenario, body_from_cam: dict[str, F64], d: CarrierDesign = CarrierDesign()
) -> dict[str, Carrier]:
    """The layout written to each dataset: markers' corners (black border) in each agent's body frame."""
    out = {}
    for aid, g in team_geometry(scenario, d).items():
        markers = tuple(
            Marker(i, float(np.linalg.norm(f[1] - f[0])) * CODE_CELLS / FACE_CELLS, _inset(f))
            for i, f in zip(g.ids, g.faces, strict=True)
        )
        out[aid] = Carrier(aid, d.dictionary, np.asarray(body_from_cam[aid], dtype=np.float64), markers)
    return out


def _dictionary(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def marker_texture(dictionary: str, marker_id: int, size_px: int) -> NDArray[np.uint8]:
    """(size_px, size_px) marker image with its one-cell white quiet zone (``size_px`` divisible by 8)."""
    cell = size_px // FACE_CELLS
    img = cv2.aruco.generateImageMarker(_dictionary(dictionary), marker_id, cell * CODE_CELLS, borderBits=1)
    out = np.full((size_px, size_px), 255, np.uint8)
    o = (size_px - cell * CODE_CELLS) // 2
    out[o : o + cell * CODE_CELLS, o : o + cell * CODE_CELLS] = img
    return out


class CarrierScene:
    """The team's carriers as the renderer draws them: one texture layer per marker (appended after the
    world's layers, starting at ``first_layer``) plus one plain layer, and per frame the quads of every
    carrier but the observer's own at the agents' true poses.

    A UAV's cube is drawn only once all of it is above ``dock_z`` (the UGV's roof): docked on the roof it
    hangs into the UGV's landing well. The UGV's body is not drawn, so without this rule the cube of the
    UAV ahead would fill the lower half of the next UAV's image 0.25 m away while they wait for take-off
    (and the tiny preset's uav1 never initialised)."""

    def __init__(
        self,
        geometry: dict[str, CarrierGeometry],
        first_layer: int,
        tex_px: int,
        dictionary: str,
        dock_z: float = UGV_ROOF_HEIGHT,
    ):
        self.geometry = geometry
        self.dock_z = dock_z
        ids = [i for g in geometry.values() for i in g.ids]
        self.layer_of = {i: first_layer + k for k, i in enumerate(ids)}
        self.plain_layer = first_layer + len(ids)
        textures = [marker_texture(dictionary, i, tex_px) for i in ids]
        self.layers = np.stack([*textures, np.full((tex_px, tex_px), 255, np.uint8)])

    def quads(self, world_from_body: dict[str, F64], observer: str) -> Quads:
        corners, layers, shades = [], [], []
        for aid, g in self.geometry.items():
            if aid == observer or aid not in world_from_body:
                continue
            T = world_from_body[aid]
            if (
                g.kind == "uav"
                and float((g.faces[..., :] @ T[:3, :3].T + T[:3, 3])[..., 2].min()) < self.dock_z
            ):
                continue
            for f, i in zip(g.faces, g.ids, strict=True):
                corners.append(f @ T[:3, :3].T + T[:3, 3])
                layers.append(self.layer_of[i])
                shades.append(MARKER_SHADE)
            for q in g.plain:
                corners.append(q @ T[:3, :3].T + T[:3, 3])
                layers.append(self.plain_layer)
                shades.append(BODY_SHADE)
        n = len(corners)
        uv = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), (n, 1, 1))
        return Quads(
            np.asarray(corners, dtype=np.float64).reshape(n, 4, 3),
            uv,
            np.asarray(layers, dtype=np.int32),
            np.asarray(shades, dtype=np.float64),
        )
