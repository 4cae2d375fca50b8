"""The calibration a ROS bag does not carry: from a EuRoC ``mav0`` folder (its ``sensor.yaml`` files) or
from Kalibr files (a camchain yaml, optionally an IMU yaml with the noise densities)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.dataset_files import (
    DatasetError,
    camera_from_sensor_yaml,
    gnss_from_sensor_yaml,
    imu_from_sensor_yaml,
    matrix_from_yaml,
    read_yaml,
)
from hivemap.maps.camera import PinholeCamera, StereoRig

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Calibration:
    """Sensor calibration in the EuRoC reader's terms (body = IMU frame)."""

    cameras: dict[str, PinholeCamera]
    T_BS: dict[str, F64]
    rates: dict[str, float]
    imu_noise: dict[str, float]
    gnss_origin: tuple[float, float, float] | None = None
    agent_id: str | None = None
    kind: str | None = None

    def stereo_rig(self) -> StereoRig | None:
        """The cam0-cam1 rig of this calibration, None without a cam1."""
        if "cam1" not in self.cameras:
            return None
        return StereoRig(self.cameras["cam0"], self.cameras["cam1"], self.T_BS["cam0"], self.T_BS["cam1"])


def load_calibration(paths: Sequence[Path]) -> Calibration:
    """A EuRoC agent/``mav0`` folder, or Kalibr yaml files (one camchain, optionally one IMU file)."""
    if not paths:
        raise DatasetError("a bag needs --calib (a EuRoC mav0 folder or a Kalibr camchain yaml)")
    if len(paths) == 1 and paths[0].is_dir():
        return _euroc_calibration(paths[0])
    camchain: Calibration | None = None
    imu_noise: dict[str, float] = {}
    imu_rate = 0.0
    for p in paths:
        if p.is_dir():
            raise DatasetError("give either one EuRoC mav0 folder or Kalibr yaml files", p)
        d = read_yaml(p)
        if "cam0" in d:
            camchain = _kalibr_camchain(d, p)
        else:
            imu_noise, imu_rate = _kalibr_imu(d, p)
    if camchain is None:
        raise DatasetError(
            "no camchain among the --calib files (a Kalibr yaml with a 'cam0' entry)", paths[0]
        )
    rates = dict(camchain.rates)
    if imu_rate:
        rates["imu0"] = imu_rate
    if not imu_noise:
        log.warning("no IMU noise in the calibration (Kalibr imu yaml): using the default noise model")
    return Calibration(camchain.cameras, camchain.T_BS, rates, imu_noise)


def _euroc_calibration(path: Path) -> Calibration:
    mav0 = path / "mav0" if (path / "mav0").is_dir() else path
    if not (mav0 / "cam0").is_dir():
        raise DatasetError("not a EuRoC calibration folder (expected mav0/cam0/sensor.yaml)", path)
    cameras: dict[str, PinholeCamera] = {}
    T_BS: dict[str, F64] = {}
    rates: dict[str, float] = {}
    for name in ("cam0", "cam1"):
        if name == "cam0" or (mav0 / name).is_dir():
            cameras[name], T_BS[name], rates[name] = camera_from_sensor_yaml(mav0 / name / "sensor.yaml")
    T_BS["imu0"], rates["imu0"], noise = imu_from_sensor_yaml(mav0 / "imu0" / "sensor.yaml")
    origin = None
    if (mav0 / "gnss0" / "sensor.yaml").is_file():
        T_BS["gnss0"], rates["gnss0"], origin = gnss_from_sensor_yaml(mav0 / "gnss0" / "sensor.yaml")
    agent_id = kind = None
    agent_yaml = mav0.parent / "agent.yaml"
    if agent_yaml.is_file():
        meta = read_yaml(agent_yaml)
        agent_id = str(meta["agent_id"]) if "agent_id" in meta else None
        kind = str(meta["kind"]) if "kind" in meta else None
    return Calibration(cameras, T_BS, rates, noise, origin, agent_id, kind)


def _kalibr_camchain(d: dict[str, Any], path: Path) -> Calibration:
    """Kalibr camchain(-imucam): ``T_cam_imu`` is imu -> cam, so body_from_cam = inv(T_cam_imu);
    cam1 may only give ``T_cn_cnm1`` (cam0 -> cam1)."""
    cameras: dict[str, PinholeCamera] = {}
    T_BS: dict[str, F64] = {}
    rates: dict[str, float] = {}
    cam_from_imu: dict[str, F64] = {}
    for name in ("cam0", "cam1"):
        if name not in d:
            continue
        c = d[name]
        where = f"{name}."
        try:
            model = str(c.get("camera_model", "pinhole"))
            dist = str(c.get("distortion_model", "radtan"))
            fu, fv, cu, cv = (float(x) for x in c["intrinsics"])
            w, h = (int(x) for x in c["resolution"])
            coeffs = [float(x) for x in c.get("distortion_coeffs", [0, 0, 0, 0])]
        except (KeyError, ValueError, TypeError, AttributeError) as e:
            raise DatasetError(f"missing or bad {where}{e}", path) from e
        if model != "pinhole":
            raise DatasetError(f"{where}camera_model {model!r} unsupported (pinhole only)", path)
        if dist not in ("radtan", "radial-tangential", "none"):
            raise DatasetError(f"{where}distortion_model {dist!r} unsupported (radtan only)", path)
        k = (coeffs + [0.0] * 4)[:4]
        cameras[name] = PinholeCamera(w, h, fu, fv, cu, cv, (k[0], k[1], k[2], k[3]))
        if "T_cam_imu" in c:
            cam_from_imu[name] = matrix_from_yaml(c["T_cam_imu"], path, f"{name}.T_cam_imu")
        elif name == "cam1" and "T_cn_cnm1" in c and "cam0" in cam_from_imu:
            cam_from_imu[name] = (
                matrix_from_yaml(c["T_cn_cnm1"], path, "cam1.T_cn_cnm1") @ cam_from_imu["cam0"]
            )
        elif name == "cam0":
            # a camera-only calibration: the body frame is cam0's, the IMU extrinsics are unknown
            log.warning("%s: no cam0.T_cam_imu, taking the IMU frame as cam0's", path)
            cam_from_imu[name] = np.eye(4)
        else:
            raise DatasetError("cam1 has neither T_cam_imu nor T_cn_cnm1", path)
        T_BS[name] = np.asarray(np.linalg.inv(cam_from_imu[name]), dtype=np.float64)
        rates[name] = float(c.get("rate_hz", 0.0) or 0.0)
    T_BS["imu0"] = np.eye(4)
    return Calibration(cameras, T_BS, rates, {})


def _kalibr_imu(d: dict[str, Any], path: Path) -> tuple[dict[str, float], float]:
    """Kalibr IMU yaml (noise densities and random walks, top level or under ``imu0``)."""
    node = d.get("imu0", d)
    keys = (
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "gyroscope_noise_density",
        "gyroscope_random_walk",
    )
    if not isinstance(node, dict) or not any(k in node for k in keys):
        raise DatasetError("neither a Kalibr camchain ('cam0') nor an IMU yaml (noise densities)", path)
    try:
        noise = {k: float(node[k]) for k in keys if k in node}
        rate = float(node.get("update_rate", 0.0))
    except (ValueError, TypeError) as e:
        raise DatasetError(f"bad IMU parameter: {e}", path) from e
    return noise, rate
