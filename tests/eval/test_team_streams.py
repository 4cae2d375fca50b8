"""bench/team_streams.py: a copy of the team is a separate team (shifted, re-textured, seeing its own
team's carriers), and the original stays as recorded."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from hivemap.protocol import Keyframe, PoseUpdates, Rendezvous, decode, encode


def _rendezvous(observed: str) -> Rendezvous:
    T = np.eye(4)
    T[:3, 3] = (0.5, -0.2, 3.0)
    return Rendezvous(
        timestamp=12.5, observed_agent=observed, marker_ids=np.array([3, 4], dtype=np.int64), ref_kf_id=7,
        ref_from_cam=np.eye(4), cam_from_observed=T, covariance=np.eye(6) * 1e-4, reproj_rms_px=0.3,
    )  # fmt: skip


def test_a_copys_rendezvous_names_its_own_teams_agent_and_keeps_the_relative_pose(
    bench_module: Callable[[str], ModuleType],
) -> None:
    ts = bench_module("team_streams")
    msg = _rendezvous("ugv")
    mask = np.random.default_rng(1).integers(0, 256, 32, dtype=np.uint8)
    copy = ts.copy_message(msg, np.array([ts.KM, 0.0, 0.0]), mask, "c1")
    assert copy.observed_agent == "ugvc1"
    assert np.array_equal(copy.cam_from_observed, msg.cam_from_observed)
    assert np.array_equal(copy.ref_from_cam, msg.ref_from_cam) and copy.ref_kf_id == 7
    assert ts.copy_message(msg, np.zeros(3), None).observed_agent == "ugv"


def test_a_copys_keyframe_is_shifted_and_re_textured(bench_module: Callable[[str], ModuleType]) -> None:
    ts = bench_module("team_streams")
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    kf = Keyframe(
        kf_id=5, timestamp=1.0, world_from_cam=T, keypoints=np.zeros((2, 2), dtype=np.float32),
        octaves=np.zeros(2, dtype=np.uint8), descriptors=rng.integers(0, 256, (2, 32), dtype=np.uint8),
        point_ids=np.array([-1, -1], dtype=np.int64),
    )  # fmt: skip
    mask = rng.integers(0, 256, 32, dtype=np.uint8)
    copy = ts.copy_message(kf, np.array([ts.KM, 0.0, 0.0]), mask, "c1")
    assert np.allclose(copy.world_from_cam[:3, 3], (1001.0, 2.0, 3.0))
    assert np.array_equal(copy.descriptors ^ mask, kf.descriptors)
    # distances within the copy are the original's
    d = np.unpackbits(copy.descriptors[0] ^ copy.descriptors[1]).sum()
    assert d == np.unpackbits(kf.descriptors[0] ^ kf.descriptors[1]).sum()


def test_every_message_of_a_stream_has_its_own_seq(
    tmp_path: Path, bench_module: Callable[[str], ModuleType]
) -> None:
    """Messages after an agent's last keyframe (pose updates of its last local BA) each get a seq."""
    ts = bench_module("team_streams")
    rng = np.random.default_rng(0)
    kf = Keyframe(
        kf_id=1, timestamp=5.0, world_from_cam=np.eye(4), keypoints=np.zeros((1, 2), dtype=np.float32),
        octaves=np.zeros(1, dtype=np.uint8), descriptors=rng.integers(0, 256, (1, 32), dtype=np.uint8),
        point_ids=np.array([-1], dtype=np.int64),
    )  # fmt: skip
    upd = PoseUpdates(
        kf_ids=np.array([1], dtype=np.int64), world_from_cam=np.eye(4)[None],
        point_ids=np.zeros(0, dtype=np.int64), xyz=np.zeros((0, 3)),
    )  # fmt: skip
    db = sqlite3.connect(tmp_path / "uav1.sqlite")
    db.execute("CREATE TABLE outbox (seq INTEGER PRIMARY KEY, frame BLOB NOT NULL, acked INTEGER)")
    for i, m in enumerate([kf, upd, upd, upd], start=1):
        db.execute("INSERT INTO outbox VALUES (?, ?, 1)", (i, encode(m, i)))
    db.commit()
    db.close()
    meta = {"agents": [{"agent_id": "uav1", "kind": "uav", "camera": {}, "cam_from_antenna": None,
                        "stereo_baseline": 0.11}],
            "start_poses": {"uav1": np.eye(4).tolist()}}  # fmt: skip
    (tmp_path / "team.json").write_text(json.dumps(meta))
    (stream,) = ts.make_streams(tmp_path, 1, 1.0, None)
    assert [decode(f)[0] for _, f, _ in stream.frames] == [1, 2, 3, 4]
    # the hello says the stereo baseline, so the server keeps the keyframes' stereo observations
    assert stream.hello.stereo_baseline == 0.11

    # a recording from before the baseline was kept, whose scenario is gone: a clear error, no replay
    # without stereo
    del meta["agents"][0]["stereo_baseline"]
    meta["scenario_dir"] = str(tmp_path / "gone")
    (tmp_path / "team.json").write_text(json.dumps(meta))
    with pytest.raises(SystemExit, match="no stereo baseline for uav1"):
        ts.make_streams(tmp_path, 1, 1.0, None)
