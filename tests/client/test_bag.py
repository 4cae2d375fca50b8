"""ROS bags in, without ROS: bags written from a rendered dataset (ROS 2 MCAP and sqlite3, ROS 1) replay to
the folder's trajectory; calibration from EuRoC or Kalibr files; readable errors for a wrong topic."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from hivemap.cli.main import app
from hivemap.client.bag import BagSource, BagTopics, decode_image, load_bag
from hivemap.client.bag_calib import load_calibration
from hivemap.client.bag_write import write_bag
from hivemap.client.dataset import DatasetError, load_dataset
from hivemap.eval.trajectory import ate, groundtruth_trajectory, read_tum

BAGS = {"mcap": "ros2_mcap", "sqlite3": "ros2_sqlite", "ros1": "mission.bag"}


@pytest.fixture(scope="module")
def bags(tiny_agent: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    ds = load_dataset(tiny_agent)
    root = tmp_path_factory.mktemp("bags")
    return {fmt: write_bag(ds, root / name, fmt, BagTopics(gnss="/gnss0")) for fmt, name in BAGS.items()}  # type: ignore[arg-type]


def _run(dataset: Path, out: Path, *extra: str) -> dict:
    args = ["agent", "--dataset", str(dataset), "--offline", "--out", str(out), "--no-progress", *extra]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return json.loads((out / "run.json").read_text())


def test_bag_reader_gives_the_folder_reader_data(tiny_agent: Path, bags: dict[str, Path]) -> None:
    folder = load_dataset(tiny_agent)
    for fmt, path in bags.items():
        ds = load_bag(BagSource(path, (tiny_agent,), BagTopics(gnss="/gnss0")))
        assert ds.agent_id == folder.agent_id and ds.kind == folder.kind, fmt
        np.testing.assert_array_equal(ds.frames.t_ns, folder.frames.t_ns)
        np.testing.assert_array_equal(ds.imu, folder.imu)  # float64 round trip: exact
        for name in ("cam0", "cam1", "imu0"):
            np.testing.assert_array_equal(ds.T_BS[name], folder.T_BS[name])
        assert ds.imu_noise == folder.imu_noise
        # out of order and back again: a second pass over the bag
        for i in (0, 7, 3, len(folder.frames) - 1):
            (l0, r0), (l1, r1) = ds.frames.load(i), folder.frames.load(i)
            np.testing.assert_array_equal(l0, l1)
            assert r0 is not None and r1 is not None
            np.testing.assert_array_equal(r0, r1)
        # NavSatFix lat/lon/alt back to ENU around the same origin: sub-millimetre
        assert ds.gnss is not None and folder.gnss is not None
        np.testing.assert_allclose(ds.gnss.enu, folder.gnss.enu, atol=1e-6)
        np.testing.assert_allclose(ds.gnss.sigma, folder.gnss.sigma, rtol=1e-9)


def test_agent_on_bags_gives_the_folder_trajectory(tiny_agent: Path, bags: dict[str, Path], tmp_path) -> None:
    # With every GNSS fix the local frame is ENU, so ATE needs no alignment (the tiny UAV hovers during
    # these 2 s, which leaves an SE(3) fit degenerate); GNSS then comes from the bag's NavSatFix too.
    ref = _run(tiny_agent, tmp_path / "folder", "--gnss", "all")
    gt = groundtruth_trajectory(tiny_agent)
    ref_local = read_tum(tmp_path / "folder" / "local.tum")
    ref_ate = ate(ref_local, gt, "none").stats.rmse
    assert ref["gnss_used"] > 5
    for fmt, path in bags.items():
        out = tmp_path / fmt
        summary = _run(
            path, out, "--calib", str(tiny_agent / "mav0"), "--gnss", "all", "--gnss-topic", "/gnss0"
        )
        assert summary["frames"] == ref["frames"] and summary["keyframes"] == ref["keyframes"], fmt
        assert summary["gnss_used"] == ref["gnss_used"], fmt
        local = read_tum(out / "local.tum")
        assert abs(ate(local, gt, "none").stats.rmse - ref_ate) < 1e-3, fmt
        assert ate(local, ref_local, "none").stats.rmse < 1e-3, fmt


def test_missing_topic_is_one_line_naming_it(tiny_agent: Path, bags: dict[str, Path], tmp_path) -> None:
    cmd = [sys.executable, "-m", "hivemap.cli.main", "agent", "--dataset", str(bags["mcap"]), "--offline",
           "--calib", str(tiny_agent), "--cam1-topic", "/stereo/right", "--out", str(tmp_path)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "'/stereo/right' not in the bag" in lines[0] and "--cam1-topic" in lines[0]


def test_kalibr_camchain_matches_euroc_calibration(tiny_agent: Path, tmp_path) -> None:
    euroc = load_calibration([tiny_agent])
    cam = {}
    for name in ("cam0", "cam1"):
        c = euroc.cameras[name]
        cam[name] = {
            "camera_model": "pinhole", "distortion_model": "radtan",
            "intrinsics": [c.fx, c.fy, c.cx, c.cy], "resolution": [c.width, c.height],
            "distortion_coeffs": list(c.dist), "rostopic": f"/{name}/image_raw",
        }  # fmt: skip
    cam0_from_imu = np.linalg.inv(euroc.T_BS["cam0"])
    cam1_from_imu = np.linalg.inv(euroc.T_BS["cam1"])
    cam["cam0"]["T_cam_imu"] = cam0_from_imu.tolist()
    # cam1 only relative to cam0, as Kalibr's camera-only calibration writes it
    cam["cam1"]["T_cn_cnm1"] = (cam1_from_imu @ np.linalg.inv(cam0_from_imu)).tolist()
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(cam))
    noise = {k: v for k, v in euroc.imu_noise.items() if "density" in k or "random_walk" in k}
    (tmp_path / "imu.yaml").write_text(yaml.safe_dump({"imu0": {**noise, "update_rate": 200.0}}))
    kal = load_calibration([tmp_path / "camchain.yaml", tmp_path / "imu.yaml"])
    for name in ("cam0", "cam1"):
        assert kal.cameras[name] == euroc.cameras[name]
        np.testing.assert_allclose(kal.T_BS[name], euroc.T_BS[name], atol=1e-12)
    assert kal.imu_noise == noise and kal.rates["imu0"] == 200.0
    with pytest.raises(DatasetError, match="cam0.camera_model 'omni' unsupported"):
        cam["cam0"]["camera_model"] = "omni"
        (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(cam))
        load_calibration([tmp_path / "camchain.yaml"])


def test_decode_image_encodings() -> None:
    import cv2
    from rosbags.typesys import Stores, get_typestore

    T = get_typestore(Stores.ROS2_HUMBLE).types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    hdr = Header(stamp=Time(sec=1, nanosec=0), frame_id="cam0")
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    Image = T["sensor_msgs/msg/Image"]
    # a padded row (step > width * channels), as some drivers send
    padded = np.zeros((6, 16), np.uint8)
    padded[:, :15] = bgr.reshape(6, 15)
    msg = Image(
        header=hdr, height=6, width=5, encoding="bgr8", is_bigendian=0, step=16, data=padded.reshape(-1)
    )
    np.testing.assert_array_equal(decode_image(msg, Image.__msgtype__, "/c"), gray)
    g16 = (gray.astype(np.uint16) * 256).astype(">u2")
    msg = Image(header=hdr, height=6, width=5, encoding="mono16", is_bigendian=1, step=10,
                data=np.frombuffer(g16.tobytes(), np.uint8))  # fmt: skip
    np.testing.assert_array_equal(decode_image(msg, Image.__msgtype__, "/c"), gray)
    Compressed = T["sensor_msgs/msg/CompressedImage"]
    png = np.frombuffer(cv2.imencode(".png", gray)[1].tobytes(), np.uint8)
    msg = Compressed(header=hdr, format="png", data=png)
    np.testing.assert_array_equal(decode_image(msg, Compressed.__msgtype__, "/c"), gray)
    msg = Image(header=hdr, height=6, width=5, encoding="bayer_rggb8", is_bigendian=0, step=5,
                data=np.zeros(30, np.uint8))  # fmt: skip
    with pytest.raises(DatasetError, match="bayer_rggb8"):
        decode_image(msg, Image.__msgtype__, "/c")
