"""Marker carriers in a camera image: the carrier agent's cam0 in the observer's cam0 (seed 000).

Markers are detected with ``cv2.aruco`` (sub-pixel corners) in the distorted image, their corners then
taken from lines fitted along the black border's four edges (``marker_corners``); every visible corner
of one carrier goes into ONE PnP (as seed 000 does on its RhOct), initialised by SQPnP (IPPE on a planar
carrier, such as a roof board, to see both of its solutions), then refined by Levenberg-Marquardt under
the camera's distortion. The covariance is the Gauss-Newton one, ``sigma^2 (J^T J)^-1``, with ``J`` the
corners' Jacobian in gtsam's Pose3 right perturbation ``[rot, trans]`` of ``cam_from_observed`` and
``sigma`` (per pixel coordinate) the larger of ``MarkerOptions.pixel_sigma_px`` and the solve's residual.

A solution is refused (not reported) when its residual or its covariance is implausible, or when the
carrier is planar and its two IPPE solutions explain the corners about equally well (their squared
residuals closer than ``ambiguity_min_chi2`` sigma^2) (the planar
ambiguity of a single marker seen small or face-on): a wrong pose is worse than none, since the server
can merge maps from it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from hivemap.client.frontend.marker_corners import refine_quad
from hivemap.maps.camera import PinholeCamera
from hivemap.maps.geometry import se3
from hivemap.maps.markers import Carrier, carrier_of_marker

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


@dataclass(frozen=True)
class MarkerOptions:
    """Detection and acceptance of carrier poses. ``from_table`` reads a TOML ``[markers]`` table."""

    enabled: bool = True
    # the agent runs the detector on every k-th cam0 frame: 10 Hz of 20 Hz frames keeps its CPU near a
    # tenth of the front-end's (docs/decisions.md, issue 25), plenty for the server's consistency check
    every_k_frames: int = 2
    # corner noise of the covariance (px per coordinate, 1 sigma): sub-pixel refined corners of a
    # rendered or printed marker; the solve's own residual is used when larger
    pixel_sigma_px: float = 0.5
    corner_refine_win: int = 5  # cv2 sub-pixel refinement window (half size, px)
    # then each corner from lines fitted along the marker's four border edges (``marker_corners``): a
    # small marker's corners from its whole edges, not from a few pixels around each corner
    edge_refine: bool = True
    # adaptive-threshold windows (px) cv2.aruco tries, min to max by step: 5 and 15 found as many markers
    # as cv2's 3, 13 and 23 in half the time (one pass less; docs/decisions.md, issue 25), which counts
    # now that the carrier mask runs the detector on every frame
    adaptive_thresh_win_min: int = 5
    adaptive_thresh_win_max: int = 15
    adaptive_thresh_win_step: int = 10
    max_reproj_rms_px: float = 2.0  # a larger residual: the corners do not fit the carrier's geometry
    max_rot_sigma_deg: float = 5.0  # covariance plausibility: 1-sigma rotation bound
    max_pos_sigma_rel: float = 0.1  # 1-sigma position bound as a fraction of the distance
    # planar carrier: the other IPPE solution's squared residual must exceed the best one's by this many
    # sigma^2 (a likelihood-ratio test, chi2 of 1 DoF: 16 is 4 sigma), else the pose is ambiguous
    ambiguity_min_chi2: float = 16.0
    min_distance_m: float = 0.2

    @staticmethod
    def from_table(table: Mapping[str, Any] | None) -> MarkerOptions:
        """The defaults with the table's fields replaced; unknown keys or wrong types raise ValueError."""
        base = MarkerOptions()
        if not table:
            return base
        hints = typing.get_type_hints(MarkerOptions)
        names = {f.name for f in dataclasses.fields(MarkerOptions)}
        changes: dict[str, Any] = {}
        for key, value in table.items():
            if key not in names:
                raise ValueError(f"unknown key markers.{key}")
            hint = hints[key]
            if hint is bool and not isinstance(value, bool):
                raise ValueError(f"markers.{key}: expected true/false, got {value!r}")
            if hint is int and (isinstance(value, bool) or not isinstance(value, int)):
                raise ValueError(f"markers.{key}: expected an integer, got {value!r}")
            if hint is float:
                if isinstance(value, bool) or not isinstance(value, int | float):
                    raise ValueError(f"markers.{key}: expected a number, got {value!r}")
                value = float(value)
            changes[key] = value
        return dataclasses.replace(base, **changes)


@dataclass(frozen=True)
class CarrierObservation:
    """One carrier seen in one image."""

    agent_id: str  # whose carrier
    marker_ids: NDArray[np.int64]
    cam_from_observed: F64  # (4,4) the carrier agent's cam0 in the observer's cam0
    covariance: F64  # (6,6) gtsam Pose3 right perturbation [rot rad, trans m], as in ``Rendezvous``
    reproj_rms_px: float
    n_corners: int


def _skew(p: F64) -> F64:
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


def _residuals(obj: F64, img: F64, rvec: F64, tvec: F64, cam: PinholeCamera) -> F64:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist_coeffs)
    return np.asarray(proj.reshape(-1, 2) - img, dtype=np.float64)


def _rms(r: F64) -> float:
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else math.inf


def pose_information(obj: F64, rvec: F64, tvec: F64, cam: PinholeCamera) -> F64:
    """``J^T J`` (6, 6) of the corners' pixels in the right perturbation ``T Exp([w, v])`` of the pose
    ``T`` = (rvec, tvec), ``obj`` (N, 3) in the observed frame: ``d p_cam = R (-[P]x w + v)``."""
    _, jac = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist_coeffs)
    du_dpc = np.asarray(jac[:, 3:6], dtype=np.float64).reshape(-1, 2, 3)  # d uv / d tvec = d uv / d p_cam
    R, _ = cv2.Rodrigues(rvec)
    H = np.zeros((6, 6))
    for i, P in enumerate(obj):
        dpc = np.hstack([-R @ _skew(P), R])  # (3, 6)
        J = du_dpc[i] @ dpc
        H += J.T @ J
    return H


def solve_carrier_pose(
    obj: F64, img: F64, cam: PinholeCamera, options: MarkerOptions
) -> tuple[F64, F64, float] | None:
    """One PnP over all corners ``obj`` (N, 3) in the carrier's cam0 frame against distorted pixels
    ``img`` (N, 2): (cam_from_observed, covariance, rms) or None when refused (module docstring)."""
    obj = np.ascontiguousarray(obj, dtype=np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(img, dtype=np.float64).reshape(-1, 2)
    if len(obj) < 4:
        return None
    centred = obj - obj.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    planar = sv[2] <= 1e-6 * max(sv[0], 1e-12)
    method = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, cam.K, cam.dist_coeffs, flags=method)
    except cv2.error:
        return None
    if n == 0:
        return None
    # candidates compared unrefined: refined, IPPE's second solution can slide into the first
    sols = []
    for rv, tv in zip(rvecs[:n], tvecs[:n], strict=True):
        rv, tv = np.asarray(rv, np.float64).reshape(3, 1), np.asarray(tv, np.float64).reshape(3, 1)
        sols.append((_rms(_residuals(obj, img, rv, tv, cam)), rv, tv))
    sols.sort(key=lambda s: s[0])
    _, rvec, tvec = sols[0]
    refined = cv2.solvePnPRefineLM(obj, img, cam.K, cam.dist_coeffs, rvec.copy(), tvec.copy(), _LM_CRITERIA)
    rvec, tvec = (np.asarray(v, np.float64).reshape(3, 1) for v in refined)
    rms = _rms(_residuals(obj, img, rvec, tvec, cam))
    if not math.isfinite(rms) or rms > options.max_reproj_rms_px:
        return None
    # the residual's per-coordinate sigma (rms is per corner, over 2N - 6 degrees of freedom)
    sigma = max(options.pixel_sigma_px, rms * math.sqrt(len(obj) / max(2 * len(obj) - 6, 1)))
    if (
        planar
        and len(sols) > 1
        and len(obj) * (sols[1][0] ** 2 - rms**2) < options.ambiguity_min_chi2 * sigma**2
    ):
        return None
    R, _ = cv2.Rodrigues(rvec)
    T = se3(R, tvec.reshape(3))
    pts_cam = obj @ R.T + tvec.reshape(3)
    dist = float(np.linalg.norm(T[:3, 3]))
    if (pts_cam[:, 2] <= 0).any() or dist < options.min_distance_m:
        return None
    H = pose_information(obj, rvec, tvec, cam)
    try:
        cov = sigma**2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    cov = 0.5 * (cov + cov.T)
    ev = np.linalg.eigvalsh(cov)
    if not np.isfinite(cov).all() or ev[0] <= 0:
        return None
    rot_sigma = math.degrees(math.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]))
    # the position's uncertainty in the observer's frame: R times the right-perturbation translation
    pos_sigma = math.sqrt(np.linalg.eigvalsh(R @ cov[3:, 3:] @ R.T)[-1])
    if rot_sigma > options.max_rot_sigma_deg or pos_sigma > options.max_pos_sigma_rel * dist:
        return None
    return T, cov, rms


class MarkerDetector:
    """Finds the team's carriers (other than the observer's own) in an observer's cam0 images."""

    def __init__(
        self,
        camera: PinholeCamera,
        carriers: Mapping[str, Carrier],
        own_agent_id: str,
        options: MarkerOptions = MarkerOptions(),
    ) -> None:
        self.camera = camera
        self.carriers = dict(carriers)
        self.own_agent_id = own_agent_id
        self.options = options
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = options.corner_refine_win
        params.adaptiveThreshWinSizeMin = options.adaptive_thresh_win_min
        params.adaptiveThreshWinSizeMax = options.adaptive_thresh_win_max
        params.adaptiveThreshWinSizeStep = options.adaptive_thresh_win_step
        self._detectors: dict[str, cv2.aruco.ArucoDetector] = {}
        for name in sorted({c.dictionary for c in carriers.values() if c.agent_id != own_agent_id}):
            code = getattr(cv2.aruco, name, None)
            if not isinstance(code, int):
                raise ValueError(f"unknown cv2.aruco dictionary {name!r} in the marker layout")
            self._detectors[name] = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(code), params)

    def detect(self, gray: NDArray[np.uint8]) -> list[CarrierObservation]:
        return self.sightings(gray)[0]

    def sightings(
        self, gray: NDArray[np.uint8], offset: tuple[int, int] = (0, 0)
    ) -> tuple[list[CarrierObservation], dict[str, list[F64]]]:
        """(accepted carrier poses, every detected marker quad (4, 2) by carrier, refused poses included):
        the quads let the front-end mask a carrier out of tracking even when its pose is refused.
        ``gray`` may be a crop of the image whose top-left pixel is at ``offset`` (x, y) in it."""
        out: list[CarrierObservation] = []
        quads: dict[str, list[F64]] = {}
        for name, det in self._detectors.items():
            corners, ids, _ = det.detectMarkers(gray)
            if ids is None or len(ids) == 0:
                continue
            ids_flat = np.asarray(ids, dtype=np.int64).reshape(-1)
            uniq, counts = np.unique(ids_flat, return_counts=True)
            twice = set(uniq[counts > 1].tolist())  # one id seen twice: a false detection among them
            by_carrier: dict[str, list[tuple[int, F64]]] = {}
            for mid, c in zip(ids_flat.tolist(), corners, strict=True):
                carrier = carrier_of_marker(self.carriers, name, mid)
                if carrier is None or carrier.agent_id == self.own_agent_id:
                    continue
                quad = np.asarray(c, np.float64).reshape(4, 2) + offset
                if self.options.edge_refine:
                    refined = refine_quad(gray, quad, self.camera, offset)
                    quad = quad if refined is None else refined
                quads.setdefault(carrier.agent_id, []).append(quad)
                if mid not in twice:
                    by_carrier.setdefault(carrier.agent_id, []).append((mid, quad))
            for aid, seen in by_carrier.items():
                seen.sort(key=lambda s: s[0])
                mids = [m for m, _ in seen]
                obj = self.carriers[aid].corners_cam(mids)
                img = np.concatenate([c for _, c in seen])
                sol = solve_carrier_pose(obj, img, self.camera, self.options)
                if sol is None:
                    log.debug("carrier %s (markers %s): pose refused", aid, mids)
                    continue
                T, cov, rms = sol
                out.append(CarrierObservation(aid, np.asarray(mids, np.int64), T, cov, rms, len(obj)))
        return out, quads
