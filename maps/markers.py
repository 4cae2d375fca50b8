"""Fiducial marker carriers: which agent carries which markers where (seed 000's RhOct, a UGV roof board).

One model shared by the renderer (draws the carriers on the agents), the front-end (detects them and
solves the carrier's pose) and the evaluation. A carrier's corners are in its agent's body frame, as the
dataset's calibration gives every sensor (EuRoC ``T_BS``), and ``body_from_cam`` is the carrier agent's
cam0 extrinsic, so an observer can turn "carrier in my camera" into "its cam0 in my cam0", the frame of
the keyframe poses the server holds.

Corner order per marker is OpenCV's (``cv2.aruco``): top-left, top-right, bottom-right, bottom-left of the
marker image as printed, seen from the side it faces.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

F64 = NDArray[np.float64]
LAYOUT_FILE = "markers.yaml"  # per agent dataset folder: the whole team's carriers
FORMAT_VERSION = 1


class LayoutError(ValueError):
    """A marker layout file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class Marker:
    """One square marker: its dictionary id, side length (m, black border included) and 4 corners (4, 3)
    in the carrier agent's body frame, OpenCV's corner order."""

    marker_id: int
    size_m: float
    corners_body: F64


@dataclass(frozen=True)
class Carrier:
    """The markers one agent carries, all from one ``cv2.aruco`` dictionary (e.g. ``DICT_4X4_50``)."""

    agent_id: str
    dictionary: str
    body_from_cam: F64
    markers: tuple[Marker, ...]

    def ids(self) -> set[int]:
        return {m.marker_id for m in self.markers}

    def corners_cam(self, marker_ids: Iterable[int]) -> F64:
        """(4 * K, 3) corners of the given markers in the carrier agent's cam0 frame, in the given order."""
        by_id = {m.marker_id: m for m in self.markers}
        cam_from_body = np.linalg.inv(self.body_from_cam)
        pts = np.concatenate([by_id[i].corners_body for i in marker_ids]) if marker_ids else np.zeros((0, 3))
        return np.asarray(pts @ cam_from_body[:3, :3].T + cam_from_body[:3, 3], dtype=np.float64)


def carrier_of_marker(carriers: Mapping[str, Carrier], dictionary: str, marker_id: int) -> Carrier | None:
    """The carrier that holds ``marker_id`` of ``dictionary`` (ids are unique per dictionary in a team)."""
    for c in carriers.values():
        if c.dictionary == dictionary and marker_id in c.ids():
            return c
    return None


def check_unique_ids(carriers: Mapping[str, Carrier]) -> None:
    seen: dict[tuple[str, int], str] = {}
    for c in carriers.values():
        for m in c.markers:
            key = (c.dictionary, m.marker_id)
            if key in seen:
                raise LayoutError(
                    f"marker {m.marker_id} of {c.dictionary} is on both {seen[key]} and {c.agent_id}"
                )
            seen[key] = c.agent_id


def save_layout(path: Path, carriers: Mapping[str, Carrier]) -> None:
    check_unique_ids(carriers)
    doc = {
        "format_version": FORMAT_VERSION,
        "carriers": [
            {
                "agent_id": c.agent_id,
                "dictionary": c.dictionary,
                "body_from_cam": np.asarray(c.body_from_cam, dtype=float).round(12).tolist(),
                "markers": [
                    {"id": m.marker_id, "size_m": m.size_m, "corners_body": m.corners_body.round(9).tolist()}
                    for m in c.markers
                ],
            }
            for c in carriers.values()
        ],
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def load_layout(path: Path) -> dict[str, Carrier]:
    """Read a team's carriers; raises :class:`LayoutError` naming the file and what is wrong."""
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise LayoutError(f"{path}: cannot read marker layout ({e})") from None
    if not isinstance(doc, dict) or doc.get("format_version") != FORMAT_VERSION:
        raise LayoutError(f"{path}: not a marker layout of format_version {FORMAT_VERSION}")
    out: dict[str, Carrier] = {}
    try:
        for i, c in enumerate(doc["carriers"]):
            b = np.asarray(c["body_from_cam"], dtype=np.float64)
            if b.shape != (4, 4) or not np.isfinite(b).all():
                raise LayoutError(f"{path}: carriers[{i}].body_from_cam must be a finite 4x4 matrix")
            markers = []
            for j, m in enumerate(c["markers"]):
                corners = np.asarray(m["corners_body"], dtype=np.float64)
                if corners.shape != (4, 3) or not np.isfinite(corners).all():
                    raise LayoutError(f"{path}: carriers[{i}].markers[{j}].corners_body must be 4x3")
                markers.append(Marker(int(m["id"]), float(m["size_m"]), corners))
            out[str(c["agent_id"])] = Carrier(str(c["agent_id"]), str(c["dictionary"]), b, tuple(markers))
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, LayoutError):
            raise
        raise LayoutError(f"{path}: malformed marker layout ({type(e).__name__}: {e})") from None
    check_unique_ids(out)
    return out
