"""Other agents' marker carriers masked out of tracking: they move, so features on them break the
static-world assumption of frame-to-map tracking (issues 25 and 28).

A carrier in view is found by the same ``cv2.aruco`` detector that makes rendezvous observations, run on
every raw cam0 frame before ORB. With an accepted carrier pose the whole carrier (every marker of its
layout, each grown by its white quiet zone) is projected into both cameras, so faces that are too small,
too oblique or hidden for the detector are masked too; without one, the detected marker quads, grown,
are masked in cam0 and shifted by their stereo disparity (from the marker's size in pixels) into cam1.
A carrier that the detector misses in a frame keeps its last mask for a few frames: detection flickers
at range and at the image border, and one frame of features on a moving carrier is enough to pull a
pose. Masks are dilated by a margin so ORB's descriptor patches near the edge see little of the carrier.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.markers import CarrierObservation, MarkerDetector, MarkerOptions
from hivemap.maps.camera import PinholeCamera, StereoRig
from hivemap.maps.markers import Carrier

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
Polys = tuple[list[NDArray[np.int32]], list[NDArray[np.int32]]]  # hulls in cam0, in cam1
# a printed marker's white quiet zone is one code cell each side (6 cells of code and black border in
# 8): growing a marker's corners about its centre by 8/6, plus slack, covers its whole face
QUIET_ZONE_GROW = 1.45
# between whole-image searches the detector looks this far (px) around the masked carriers: a carrier
# close and fast moves ~10 px a frame at 20 Hz
SEARCH_GROW_PX = 40


@dataclass
class _Held:
    polys_left: list[NDArray[np.int32]]
    polys_right: list[NDArray[np.int32]]
    age: int = 0


@dataclass
class MaskStats:
    frames: int = 0
    frames_masked: int = 0  # frames with at least one carrier masked
    by_pose: int = 0  # carriers masked from an accepted pose
    by_quads: int = 0  # carriers masked from their detected quads only
    held: int = 0  # carriers masked from an earlier frame
    masked_fraction: list[float] = field(default_factory=list)  # of cam0's pixels, per masked frame
    detect_s: float = 0.0  # CPU time in the detector


def _grown_corners(carrier: Carrier) -> F64:
    """(4 K, 3) every marker's corners grown by its quiet zone, in the carrier agent's cam0 frame."""
    pts = []
    ids = sorted(carrier.ids())
    corners = carrier.corners_cam(ids).reshape(-1, 4, 3)
    for c in corners:
        centre = c.mean(axis=0)
        pts.append(centre + QUIET_ZONE_GROW * (c - centre))
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def _project_hull(pts_cam: F64, cam: PinholeCamera) -> NDArray[np.int32] | None:
    """Convex hull (M, 1, 2) of ``pts_cam`` (in front of the camera) in distorted pixels, or None when
    some point is behind it (the hull of a projection across the image plane is meaningless)."""
    if len(pts_cam) == 0 or (pts_cam[:, 2] <= 0.05).any():
        return None
    uv, _ = cv2.projectPoints(pts_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if not np.isfinite(uv).all() or np.abs(uv).max() > 1e5:
        return None
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    return np.asarray(hull, np.int32)


class CarrierMask:
    """Per stereo frame: the other agents' carriers found in cam0, and masks (255 = use, 0 = carrier)."""

    def __init__(
        self,
        rig: StereoRig,
        carriers: Mapping[str, Carrier],
        own_agent_id: str,
        marker_options: MarkerOptions | None = None,
        margin_px: int = 6,
        hold_frames: int = 4,
        full_every: int = 2,
    ) -> None:
        """``margin_px``: dilation of every masked region; ``hold_frames``: frames a carrier the detector
        missed stays masked where it was last seen; ``full_every``: frames between searches of the whole
        image (``FrontendOptions.carrier_mask_*``)."""
        self.rig = rig
        self.margin_px, self.hold_frames, self.full_every = margin_px, hold_frames, max(full_every, 1)
        self.full_frame = False  # the last ``update`` searched the whole image
        self.detector = MarkerDetector(rig.left, carriers, own_agent_id, marker_options or MarkerOptions())
        self._grown = {a: _grown_corners(c) for a, c in carriers.items() if a != own_agent_id}
        self._held: dict[str, _Held] = {}
        self.stats = MaskStats()
        # the frame the last ``update`` ran on and its accepted poses, for the rendezvous stream
        self.frame_t: float | None = None
        self.observations: list[CarrierObservation] = []

    def update(self, t: float, left: U8) -> tuple[U8 | None, U8 | None]:
        """Detect in ``left`` (raw cam0) and return the (cam0, cam1) masks, None where nothing is masked.

        The whole image is searched on every ``full_every``-th frame; in between only around the carriers
        masked now (a carrier moves a few pixels a frame, a new one enters at most a frame late), which
        halves the detector's cost."""
        self.full_frame = self.stats.frames % self.full_every == 0
        self.stats.frames += 1
        self.frame_t = float(t)
        t0 = time.process_time()
        if self.full_frame:
            obs, quads = self.detector.sightings(left)
        elif self._held:
            x0, y0, x1, y1 = self._search_box(left.shape)
            obs, quads = self.detector.sightings(left[y0:y1, x0:x1], offset=(x0, y0))
        else:
            obs, quads = [], {}
        self.stats.detect_s += time.process_time() - t0
        self.observations = obs
        posed = {o.agent_id: o for o in obs}
        current: dict[str, _Held] = {}
        for aid in set(posed) | set(quads):
            polys = self._from_pose(posed[aid]) if aid in posed else None
            if polys is not None:
                self.stats.by_pose += 1
            else:
                polys = self._from_quads(aid, quads.get(aid, []))
                if polys is None:
                    continue
                self.stats.by_quads += 1
            current[aid] = _Held(*polys)
        for aid, held in self._held.items():
            if aid not in current and held.age + 1 <= self.hold_frames:
                current[aid] = _Held(held.polys_left, held.polys_right, held.age + 1)
                self.stats.held += 1
        self._held = current
        if not current:
            return None, None
        self.stats.frames_masked += 1
        left_mask = self._draw([p for h in current.values() for p in h.polys_left], self.rig.left)
        right_mask = self._draw([p for h in current.values() for p in h.polys_right], self.rig.right)
        self.stats.masked_fraction.append(float(np.mean(left_mask == 0)))
        return left_mask, right_mask

    def _search_box(self, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
        """Bounding box of the masked carriers in cam0, grown by ``SEARCH_GROW_PX``, inside the image."""
        pts = np.concatenate([p.reshape(-1, 2) for h in self._held.values() for p in h.polys_left])
        h, w = shape[:2]
        x0, y0 = (np.maximum(pts.min(axis=0) - SEARCH_GROW_PX, 0)).astype(int)
        x1, y1 = pts.max(axis=0) + SEARCH_GROW_PX
        return int(x0), int(y0), int(min(x1, w)), int(min(y1, h))

    def _from_pose(self, o: CarrierObservation) -> Polys | None:
        pts = self._grown.get(o.agent_id)
        if pts is None:
            return None
        T_l = o.cam_from_observed
        in_left = pts @ T_l[:3, :3].T + T_l[:3, 3]
        T_r = self.rig.right_from_left @ T_l
        in_right = pts @ T_r[:3, :3].T + T_r[:3, 3]
        hl, hr = _project_hull(in_left, self.rig.left), _project_hull(in_right, self.rig.right)
        if hl is None or hr is None:
            return None
        return [hl], [hr]

    def _from_quads(self, aid: str, quads: list[F64]) -> Polys | None:
        """Grown quads in cam0; in cam1 the same shifted by the disparity their size in pixels implies."""
        if not quads:
            return None
        size_m = min((m.size_m for m in self.detector.carriers[aid].markers), default=0.0)
        cam = self.rig.left
        left, right = [], []
        for q in quads:
            centre = q.mean(axis=0)
            grown = centre + QUIET_ZONE_GROW * (q - centre)
            side_px = float(np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1)))
            # the smallest marker of the layout gives the nearest distance, i.e. the largest disparity;
            # the mask in cam1 spans from no shift to that shift, so it holds for any of the markers
            dist = cam.fx * size_m / max(side_px, 1.0) if size_m > 0 else math.inf
            disp = cam.fx * self.rig.baseline / max(dist, 0.05)
            shifted = np.concatenate([grown, grown - [disp, 0.0]])
            left.append(np.asarray(cv2.convexHull(np.round(grown).astype(np.int32)), np.int32))
            right.append(np.asarray(cv2.convexHull(np.round(shifted).astype(np.int32)), np.int32))
        return left, right

    def _draw(self, polys: list[NDArray[np.int32]], cam: PinholeCamera) -> U8:
        mask = np.full((cam.height, cam.width), 255, np.uint8)
        for p in polys:
            cv2.fillConvexPoly(mask, p, 0)
            if self.margin_px > 0:
                cv2.polylines(mask, [p], True, 0, thickness=2 * self.margin_px + 1)
        return mask
