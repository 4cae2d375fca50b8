"""Ground truth in the viewer: a server given a ground-truth folder (``groundtruth``) aligns each agent's
ground truth to its map (REST ``/maps/ID/groundtruth``) and the viewer draws it with a toggle; a server
without one says so and the viewer hides the toggle."""

from __future__ import annotations

import io
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))
from agent_client import SyncAgent  # noqa: E402
from srv_helpers import TOKENS, ServerProcess, write_config  # noqa: E402

from hivemap.maps.geometry import quat_wxyz_from_rotmat, se3, so3_exp  # noqa: E402
from hivemap.server.loadgen import StreamTruth, synthetic_stream  # noqa: E402

# the ground truth's world: the map frame turned by 40 degrees and moved (the alignment must undo it)
WORLD_FROM_MAP = se3(so3_exp(np.array([0.0, 0.0, np.radians(40.0)])), np.array([100.0, -20.0, 3.0]))


def _write_tum(path: Path, truth: StreamTruth, scale: float = 1.0) -> None:
    """Camera poses of ``truth`` in the ground truth's world; ``scale`` != 1 makes it disagree with the
    estimate in shape (no rigid alignment absorbs it)."""
    ks = sorted(truth.kf_poses)
    c = np.mean([truth.kf_poses[k][:3, 3] for k in ks], axis=0)
    lines = []
    for k in ks:
        T = truth.kf_poses[k].copy()
        T[:3, 3] = c + scale * (T[:3, 3] - c)
        W = WORLD_FROM_MAP @ T
        w, x, y, z = quat_wxyz_from_rotmat(W[:3, :3])
        lines.append(f"{truth.kf_timestamps[k]:.6f} {W[0, 3]} {W[1, 3]} {W[2, 3]} {x} {y} {z} {w}")
    path.write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def mission(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("gt")
    gt = tmp / "groundtruth"
    gt.mkdir()
    server = ServerProcess(tmp / "data", write_config(tmp / "server.toml", groundtruth=str(gt))).start()
    truths = {}
    try:
        # no back-end: one map per agent, so each has its own alignment
        for agent_id, seed, offset in (("uav1", 1, (0.0, 0.0, 0.0)), ("ugv1", 2, (5.0, 30.0, 0.0)),
                                       ("uav2", 3, (-20.0, 0.0, 0.0))):  # fmt: skip
            msgs, truth = synthetic_stream(agent_id, 15, features=150, seed=seed, offset=offset)
            with SyncAgent(server.ws_url, agent_id, TOKENS[agent_id]) as ag:
                ag.welcome()
                assert ag.send_all(msgs)[1] == []
            truths[agent_id] = truth
        _write_tum(gt / "uav1.tum", truths["uav1"])
        _write_tum(gt / "ugv1.tum", truths["ugv1"], scale=1.6)
        # uav2 has none
        yield server, truths
    finally:
        server.stop()


def _map_of(server: ServerProcess, agent_id: str) -> int:
    return int(server.json(f"/agents/{agent_id}")["map_id"])


def test_groundtruth_is_aligned_to_each_map(mission: Any) -> None:
    server, truths = mission
    gt = server.json(f"/maps/{_map_of(server, 'uav1')}/groundtruth")
    assert gt["configured"] and gt["aligned"] and [a["agent_id"] for a in gt["agents"]] == ["uav1"]
    (a,) = gt["agents"]
    truth = truths["uav1"]
    centres = np.array([truth.kf_poses[k][:3, 3] for k in sorted(truth.kf_poses)])
    # the ground truth is the estimate in another frame: aligned, it lies on the keyframes (within 1 mm)
    assert a["matched"] == len(centres) and a["rmse_m"] < 1e-3
    np.testing.assert_allclose(np.array(a["positions"]), centres, atol=1e-3)
    bad = server.json(f"/maps/{_map_of(server, 'ugv1')}/groundtruth")["agents"][0]
    assert bad["agent_id"] == "ugv1" and bad["rmse_m"] > 0.5  # a shape no rigid alignment absorbs
    none = server.json(f"/maps/{_map_of(server, 'uav2')}/groundtruth")
    assert none["configured"] and not none["aligned"] and none["agents"] == []
    assert server.get("/maps/999/groundtruth").status_code == 404


def test_viewer_draws_groundtruth_with_a_toggle(mission: Any) -> None:
    from PIL import Image
    from test_viewer import open_viewer

    server, _ = mission
    driver, body = open_viewer(server.url, "data-groundtruth", "2")
    try:
        assert body.get_attribute("data-groundtruth") == "2"  # uav1 and ugv1; uav2 has none
        assert driver.find_element("id", "gt-toggle").is_displayed()
        assert body.get_attribute("data-groundtruth-shown") == "2"
        time.sleep(1.0)
        shown = driver.get_screenshot_as_png()
        driver.find_element("id", "show-gt").click()
        assert body.get_attribute("data-groundtruth-shown") == "0"
        time.sleep(1.0)
        hidden = driver.get_screenshot_as_png()
    finally:
        driver.quit()

    def view(png: bytes) -> np.ndarray:
        img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
        return img[:, : img.shape[1] - 440]  # without the side panel

    # ugv1's ground truth departs from its trajectory: hiding it changes the picture
    changed = int((np.abs(view(shown) - view(hidden)).max(axis=2) > 40).sum())
    assert changed > 100, changed


def test_without_groundtruth_the_toggle_is_hidden(tmp_path: Path) -> None:
    from test_viewer import open_viewer

    server = ServerProcess(tmp_path / "data", write_config(tmp_path / "server.toml")).start()
    try:
        msgs, _ = synthetic_stream("uav1", 5, features=100, seed=1)
        with SyncAgent(server.ws_url, "uav1", TOKENS["uav1"]) as ag:
            ag.welcome()
            assert ag.send_all(msgs)[1] == []
        gt = server.json(f"/maps/{_map_of(server, 'uav1')}/groundtruth")
        assert gt == {"map_id": gt["map_id"], "configured": False, "aligned": False, "agents": []}
        driver, body = open_viewer(server.url, "data-groundtruth", None)
        try:
            assert body.get_attribute("data-groundtruth") == "0"
            assert not driver.find_element("id", "gt-toggle").is_displayed()
        finally:
            driver.quit()
    finally:
        server.stop()


def test_a_groundtruth_folder_that_does_not_exist_is_one_line(tmp_path: Path) -> None:
    import subprocess

    cmd = [sys.executable, "-m", "hivemap.cli.main", "server", "--port", "0", "--data-dir", str(tmp_path),
           "--groundtruth", str(tmp_path / "nope")]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        f"hivemap: error: field 'groundtruth': {tmp_path / 'nope'} is not a folder"
    ], res.stderr
