"""Nominal start configuration (paper 2.4: UAVs take off from the UGV's roof; issue 27): ``[start_poses]``
is a prior known to ``sigma_m`` / ``sigma_deg``, never a merge by itself. Synthetic agents of
test_backend's world stream to a real server: a place-recognition merge that agrees with the prior is
taken at its first detection with the measured (not the nominal) transform; one that contradicts it
is not taken from one place, however often it is detected; agents that never see the same place stay
apart."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_backend import UAV_FROM_WORLD, Server, agent_transform, check_transform, stream  # noqa: E402

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3, so3_exp  # noqa: E402
from hivemap.server.backend_synth import UGV_FROM_WORLD, agent_stream, make_world  # noqa: E402
from hivemap.server.settings import ServerSettings  # noqa: E402


def _nominal(local_from_world: Sim3, first_local: np.ndarray, off_m: float, off_deg: float) -> list[Any]:
    """An agent's cam0 start pose in the world (the common frame), off by ``off_m`` / ``off_deg``."""
    T = local_from_world.inverse().transform_pose(first_local)
    err = se3(so3_exp(np.radians(off_deg) * np.array([0.0, 0.6, 0.8])), off_m * np.array([0.6, -0.8, 0.0]))
    return (T @ err).tolist()  # type: ignore[no-any-return]


def _streams(seed: int) -> tuple[list[Any], np.ndarray, list[Any], np.ndarray]:
    rng = np.random.default_rng(seed)
    pts, desc = make_world(rng, 2500, (-20, 30))
    ugv_msgs, ugv_true, _ = agent_stream(rng, pts, desc, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    uav_msgs, uav_true, _ = agent_stream(rng, pts, desc, np.linspace(-2, 12, 10), UAV_FROM_WORLD)
    return ugv_msgs, ugv_true, uav_msgs, uav_true


def _run(tmp_path: Path, off_m: float, off_deg: float) -> tuple[Server, np.ndarray]:
    ugv_msgs, ugv_true, uav_msgs, uav_true = _streams(1)
    starts = {
        "sigma_m": 0.2,
        "sigma_deg": 5.0,
        "ugv1": _nominal(UGV_FROM_WORLD, ugv_true[0], 0.0, 0.0),
        "uav1": _nominal(UAV_FROM_WORLD, uav_true[0], off_m, off_deg),
    }
    srv = Server(tmp_path / "data", start_poses=starts)
    with stream(srv, "ugv1", "ugv", ugv_msgs), stream(srv, "uav1", "uav", uav_msgs):
        srv.wait_idle()
    return srv, uav_true


@pytest.fixture
def stopped() -> Iterator[list[Server]]:
    servers: list[Server] = []
    yield servers
    for s in servers:
        s.stop()


def _merges(srv: Server) -> list[dict[str, Any]]:
    return srv.call(lambda: list(srv.backend.merges))  # type: ignore[no-any-return]


def _merge_checks(srv: Server) -> list[Any]:
    """The consistency checks of merge detections (loops are checked too, after the merge)."""
    evs = srv.call(lambda: srv.hive.events.since(0, kind="consistency"))
    return [e for e in evs if e.message.startswith("merge")]


def test_agreeing_prior_merges_at_first_detection_with_the_measured_transform(
    tmp_path: Path, stopped: list[Server]
) -> None:
    srv, uav_true = _run(tmp_path, 0.15, 4.0)  # within the stated 0.2 m / 5 deg
    stopped.append(srv)
    (rec,) = _merges(srv)
    assert rec["by"] == "place_recognition+prior" and rec["prior"]["agrees"], rec
    assert rec["prior"]["diff_deg"] > 2.0  # the measurement differs from the nominal mounting ...
    true = UGV_FROM_WORLD @ UAV_FROM_WORLD.inverse()
    est = agent_transform(srv, "uav1")
    assert rotation_angle_deg(est.R @ true.R.T) < 1.0  # ... and the merge takes the measurement
    check_transform(est, true, uav_true[:, :3, 3])
    assert len(_merge_checks(srv)) == 1, "an agreeing prior stands in for the consecutive confirmations"
    # the map's self-check on the REST API: the two agents agree with their measured relative poses
    (map_id,) = srv.call(lambda: list(srv.hive.stack.maps))
    sc = httpx.get(f"http://127.0.0.1:{srv.port}/maps/{map_id}", timeout=10).json()["selfcheck"]
    (pair,) = sc["pairs"]
    assert pair["agents"] == ["uav1", "ugv1"] and pair["n"] >= 1 and pair["max_m"] < 0.2, sc
    assert sc["alarms"] == []


def test_contradicting_prior_is_not_overridden_from_one_place(tmp_path: Path, stopped: list[Server]) -> None:
    """Every keyframe of this world sees most of its points: however many of them detect the merge, they are
    one place, so a wrong prior stands (independent places override it: test_prior_places.py)."""
    srv, _ = _run(tmp_path, 3.0, 30.0)  # a wrong mounting
    stopped.append(srv)
    assert _merges(srv) == []
    evs = srv.call(lambda: srv.hive.events.since(0, kind="start_prior"))
    assert len({e.data["query"][1] for e in evs}) >= 3, [e.message for e in evs]  # detected again and again
    assert all(not e.data["agrees"] and len(e.data["places"]) == 1 for e in evs), [e.data for e in evs]
    assert srv.call(lambda: len(srv.hive.stack.maps)) == 2


def test_prior_alone_never_merges(tmp_path: Path, stopped: list[Server]) -> None:
    rng = np.random.default_rng(3)
    pts_a, desc_a = make_world(rng, 2000, (-20, 30))
    pts_b, desc_b = make_world(rng, 2000, (200, 250))
    a_msgs, a_true, _ = agent_stream(rng, pts_a, desc_a, np.linspace(-6, 8, 10), UGV_FROM_WORLD)
    b_msgs, b_true, _ = agent_stream(rng, pts_b, desc_b, np.linspace(205, 220, 10), UAV_FROM_WORLD)
    starts = {
        "ugv1": _nominal(UGV_FROM_WORLD, a_true[0], 0, 0),
        "uav1": _nominal(UAV_FROM_WORLD, b_true[0], 0, 0),
    }
    srv = Server(tmp_path / "data", start_poses=starts)
    stopped.append(srv)
    with stream(srv, "ugv1", "ugv", a_msgs), stream(srv, "uav1", "uav", b_msgs):
        srv.wait_idle()
    assert srv.call(lambda: len(srv.hive.stack.maps)) == 2
    assert srv.call(lambda: srv.hive.events.counts.get("start_anchor", 0)) == 2


def test_start_poses_table() -> None:
    s = ServerSettings(start_poses={"sigma_m": 0.5, "uav1": np.eye(4).tolist()})
    assert s.start_poses.sigma_m == 0.5 and s.start_poses.sigma_deg == 5.0
    assert list(s.start_poses.poses) == ["uav1"]
    with pytest.raises(ValueError, match="start_poses.uav1"):
        ServerSettings(start_poses={"uav1": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
