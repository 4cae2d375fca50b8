"""EuRoC/ASL reader on a sequence written byte-for-byte in EuRoC's own format (headers, sensor.yaml keys,
CRLF line ends as in the MH/V1 zips), and its error reporting on corrupt or missing input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hivemap.client.dataset import DatasetError, load_dataset, load_scenario

CAM0_YAML = """# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
CAM1_YAML = """# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam1 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
         0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
        -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [457.587, 456.134, 379.999, 255.238] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28368365,  0.07451284, -0.00010473, -3.55590700e-05]
"""
IMU_YAML = """#Default imu sensor yaml file
sensor_type: imu
comment: VI-Sensor IMU (ADIS16448)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 200

# inertial sensor noise model parameters (static)
gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )
gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )
accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]   ( accel "white noise" )
accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )
"""
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
T0 = 1403636579763555584  # first cam0 stamp of MH_01_easy
N_FRAMES = 5


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.replace("\n", "\r\n").encode())


@pytest.fixture
def euroc(tmp_path: Path) -> Path:
    root = tmp_path / "MH_01_easy"
    mav0 = root / "mav0"
    rng = np.random.default_rng(0)
    stamps = [T0 + i * 50_000_000 for i in range(N_FRAMES)]
    for cam, yml in (("cam0", CAM0_YAML), ("cam1", CAM1_YAML)):
        _write(mav0 / cam / "sensor.yaml", yml)
        _write(
            mav0 / cam / "data.csv", "#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in stamps)
        )
        (mav0 / cam / "data").mkdir(parents=True)
        for t in stamps:
            cv2.imwrite(
                str(mav0 / cam / "data" / f"{t}.png"), rng.integers(0, 255, (480, 752), dtype=np.uint8)
            )
    _write(mav0 / "imu0" / "sensor.yaml", IMU_YAML)
    imu_t = [T0 - 5_000_000 + i * 5_000_000 for i in range(60)]
    rows = [f"{t},-0.0991347015132779,0.14730578886832138,0.02722713633111154,8.147691708333333,"
            f"-0.3759215833333333,-2.40262925" for t in imu_t]  # fmt: skip
    _write(mav0 / "imu0" / "data.csv", IMU_HEADER + "\n" + "\n".join(rows) + "\n")
    gt = [
        f"{t},4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,-0.027876,0.033207,"
        f"0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593"
        for t in imu_t
    ]
    _write(mav0 / "state_groundtruth_estimate0" / "data.csv", GT_HEADER + "\n" + "\n".join(gt) + "\n")
    return root


def test_loads_a_euroc_sequence(euroc: Path):
    ds = load_dataset(euroc)
    assert ds.agent_id == "MH_01_easy" and ds.kind == "uav"
    assert len(ds.frames) == N_FRAMES
    assert ds.frames.t_ns[0] == T0
    assert ds.frames.timestamps[1] - ds.frames.timestamps[0] == pytest.approx(0.05)
    cam = ds.cameras["cam0"]
    assert (cam.width, cam.height, cam.fx, cam.cy) == (752, 480, 458.654, 248.375)
    assert cam.dist[0] == pytest.approx(-0.28340811)
    assert ds.rig is not None
    assert ds.rig.baseline == pytest.approx(0.1101, abs=1e-3)  # EuRoC's stereo baseline is ~11 cm
    assert ds.rates["cam0"] == 20 and ds.rates["imu0"] == 200
    assert ds.imu.shape == (60, 7)
    assert ds.imu[0, 0] == pytest.approx((T0 - 5_000_000) * 1e-9)
    assert ds.imu[0, 4] == pytest.approx(8.147691708333333)
    assert ds.imu_noise["gyroscope_noise_density"] == pytest.approx(1.6968e-4)
    gt = ds.groundtruth
    assert gt is not None and len(gt) == 60
    R = Rotation.from_quat([-0.153029, -0.827383, -0.082152, 0.534108]).as_matrix()
    assert np.allclose(gt.world_from_body[0, :3, :3], R, atol=1e-5)
    assert np.allclose(gt.world_from_body[0, :3, 3], [4.688319, -1.786938, 0.783338])
    assert np.allclose(gt.velocity[0], [-0.027876, 0.033207, 0.800006])
    assert np.allclose(gt.bias_gyro[0], [-0.003172, 0.021267, 0.078502])
    assert np.allclose(gt.bias_accel[0], [-0.025266, 0.136696, 0.075593])
    assert ds.gnss is None
    g0, g1 = ds.frames.load(2)
    assert g0.shape == (480, 752) and g0.dtype == np.uint8 and g1 is not None
    poses = ds.groundtruth_at_frames()
    assert poses.shape == (N_FRAMES, 4, 4)


def test_mav0_folder_itself_is_accepted(euroc: Path):
    assert len(load_dataset(euroc / "mav0").frames) == N_FRAMES


def _corrupt_line(path: Path, lineno: int, new: str) -> None:
    lines = path.read_bytes().decode().split("\r\n")
    lines[lineno - 1] = new
    path.write_bytes("\r\n".join(lines).encode())


def test_wrong_column_count_names_file_and_line(euroc: Path):
    p = euroc / "mav0" / "imu0" / "data.csv"
    _corrupt_line(p, 4, "1403636579763555584,0.1,0.2")
    with pytest.raises(DatasetError) as e:
        load_dataset(euroc)
    assert e.value.path == p and e.value.line == 4
    assert "imu0/data.csv:4:" in str(e.value) and "columns" in str(e.value)


def test_non_numeric_value_names_line(euroc: Path):
    p = euroc / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = p.read_bytes().decode().split("\r\n")
    _corrupt_line(p, 3, lines[2].replace("4.688319", "4.68x319"))
    with pytest.raises(DatasetError, match=r"state_groundtruth_estimate0/data.csv:3: not a number"):
        load_dataset(euroc)


def test_non_increasing_timestamps(euroc: Path):
    p = euroc / "mav0" / "cam0" / "data.csv"
    _corrupt_line(p, 3, f"{T0},{T0}.png")
    with pytest.raises(DatasetError, match=r"cam0/data.csv:3: timestamp"):
        load_dataset(euroc)


def test_missing_files_are_named(euroc: Path):
    (euroc / "mav0" / "imu0" / "sensor.yaml").unlink()
    with pytest.raises(DatasetError, match=r"imu0/sensor.yaml: file not found"):
        load_dataset(euroc)


def test_missing_image_is_skipped_and_no_images_is_named(euroc: Path):
    # a listed frame missing on disk is skipped with its stereo partner (issue 24: partial copies of
    # real recordings); a camera with none of its images is an error naming its data folder
    img = euroc / "mav0" / "cam1" / "data" / f"{T0 + 100_000_000}.png"
    n = len(load_dataset(euroc).frames)
    img.unlink()
    ds = load_dataset(euroc)
    assert len(ds.frames) == n - 1 and T0 + 100_000_000 not in ds.frames.t_ns
    for p in (euroc / "mav0" / "cam1" / "data").glob("*.png"):
        p.unlink()
    with pytest.raises(DatasetError, match="none of the 5 listed images exist") as e:
        load_dataset(euroc)
    assert e.value.path == euroc / "mav0" / "cam1" / "data"


def test_corrupt_image_is_named_on_load(euroc: Path):
    img = euroc / "mav0" / "cam0" / "data" / f"{T0}.png"
    img.write_bytes(b"not a png")
    ds = load_dataset(euroc)
    with pytest.raises(DatasetError) as e:
        ds.frames.load(0)
    assert e.value.path == img


def test_bad_quaternion_and_bad_yaml(euroc: Path):
    p = euroc / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = p.read_bytes().decode().split("\r\n")
    _corrupt_line(p, 2, lines[1].replace("0.534108", "5.34108"))
    with pytest.raises(DatasetError, match="quaternion not unit"):
        load_dataset(euroc)
    (euroc / "mav0" / "cam0" / "sensor.yaml").write_text("intrinsics: [1, 2\nresolution: {")
    with pytest.raises(DatasetError, match=r"cam0/sensor.yaml"):
        load_dataset(euroc)


def test_not_a_dataset(tmp_path: Path):
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="mav0"):
        load_dataset(tmp_path)


def test_scenario_manifest(euroc: Path):
    (euroc.parent / "manifest.yaml").write_text(
        "scenario: mine\nseed: 5\norigin: {lat: 47.0, lon: 8.5, alt: 400.0}\n"
        "agents:\n  - {id: mav, kind: ugv, path: MH_01_easy}\n"
    )
    man = load_scenario(euroc.parent)
    assert man.name == "mine" and man.seed == 5 and man.origin == (47.0, 8.5, 400.0)
    ds = man.load_agent("mav")
    # kind and id come from the manifest when the agent folder has no agent.yaml
    assert (ds.agent_id, ds.kind) == ("mav", "ugv")
    (euroc.parent / "manifest.yaml").write_text("scenario: x\nagents:\n  - {kind: uav}\n")
    with pytest.raises(DatasetError, match="manifest"):
        load_scenario(euroc.parent)
