"""The marker layout model: file round trip, corner frames, and errors that name the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hivemap.maps.geometry import se3, so3_exp
from hivemap.maps.markers import Carrier, LayoutError, Marker, carrier_of_marker, load_layout, save_layout


def _square(center: np.ndarray, size: float) -> np.ndarray:
    h = size / 2
    return center + np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=float)


def _team() -> dict[str, Carrier]:
    body_from_cam = se3(so3_exp(np.array([0.3, -0.1, 0.2])), np.array([0.25, 0.1, 0.15]))
    ugv = Carrier(
        "ugv", "DICT_4X4_50", body_from_cam, (Marker(0, 0.5, _square(np.array([0.0, 0.0, 1.4]), 0.5)),)
    )
    uav = Carrier(
        "uav1", "DICT_4X4_50", np.eye(4), (Marker(1, 0.2, _square(np.array([0.0, 0.0, -0.2]), 0.2)),)
    )
    return {"ugv": ugv, "uav1": uav}


def test_layout_round_trips_and_maps_corners_into_cam0(tmp_path: Path) -> None:
    team = _team()
    save_layout(tmp_path / "markers.yaml", team)
    back = load_layout(tmp_path / "markers.yaml")
    assert set(back) == {"ugv", "uav1"}
    np.testing.assert_allclose(back["ugv"].body_from_cam, team["ugv"].body_from_cam, atol=1e-12)
    # corners in cam0, mapped back through body_from_cam, are the body-frame corners
    pc = back["ugv"].corners_cam([0])
    pb = pc @ team["ugv"].body_from_cam[:3, :3].T + team["ugv"].body_from_cam[:3, 3]
    np.testing.assert_allclose(pb, team["ugv"].markers[0].corners_body, atol=1e-8)
    found = carrier_of_marker(back, "DICT_4X4_50", 1)
    assert found is not None and found.agent_id == "uav1"
    assert carrier_of_marker(back, "DICT_4X4_50", 9) is None


def test_duplicate_ids_and_bad_files_are_refused(tmp_path: Path) -> None:
    team = _team()
    dup = Carrier("uav2", "DICT_4X4_50", np.eye(4), team["uav1"].markers)
    with pytest.raises(LayoutError, match="both uav1 and uav2"):
        save_layout(tmp_path / "m.yaml", {**team, "uav2": dup})
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "format_version: 1\ncarriers:\n- agent_id: ugv\n  dictionary: D\n  body_from_cam: [[1, 0]]\n"
    )
    with pytest.raises(LayoutError, match="bad.yaml.*body_from_cam"):
        load_layout(bad)
    with pytest.raises(LayoutError, match="cannot read"):
        load_layout(tmp_path / "missing.yaml")
