"""The EuRoC/ASL files of an agent dataset, one reader each (``hivemap.client.dataset`` assembles them):
CSV series, image lists and the ``sensor.yaml`` calibrations. Every problem raises ``DatasetError``
naming the file (and line)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from hivemap.maps.camera import PinholeCamera

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class DatasetError(Exception):
    """Missing or corrupt dataset input; ``path`` (and ``line``, 1-based) say where."""

    def __init__(self, message: str, path: Path | str | None = None, line: int | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.line = line
        where = "" if path is None else (f"{path}:{line}: " if line is not None else f"{path}: ")
        super().__init__(f"{where}{message}")


# ---------------------------------------------------------------------------------------------
# Low-level parsing
# ---------------------------------------------------------------------------------------------


def read_yaml(path: Path) -> dict[str, Any]:
    """YAML mapping from ``path`` (tolerates OpenCV's ``%YAML:1.0`` first line)."""
    if not path.is_file():
        raise DatasetError("file not found", path)
    text = path.read_text(errors="replace")
    text = "\n".join(line for line in text.splitlines() if not line.startswith("%YAML"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        raise DatasetError(f"invalid YAML: {e}", path, None if mark is None else mark.line + 1) from e
    if not isinstance(data, dict):
        raise DatasetError("expected a YAML mapping", path)
    return data


def _csv_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(1-based line number, stripped comma-separated fields) of each line of a EuRoC csv that is neither
    blank nor a ``#`` comment; DatasetError if the file is missing."""
    if not path.is_file():
        raise DatasetError("file not found", path)
    with open(path, newline="") as f:
        for i, raw in enumerate(f, start=1):
            line = raw.strip()
            if line and not line.startswith("#"):
                yield i, [p.strip() for p in line.split(",")]


def read_csv_numeric(path: Path, n_cols: int | tuple[int, ...]) -> tuple[I64, F64]:
    """EuRoC csv: first column int timestamp [ns], then floats. Returns (t_ns (N,), values (N, C-1)).

    Lines starting with ``#`` and a header line are skipped; timestamps must increase strictly.
    """
    allowed = (n_cols,) if isinstance(n_cols, int) else n_cols
    ts: list[int] = []
    rows: list[list[float]] = []
    for i, parts in _csv_lines(path):
        if len(parts) not in allowed:
            if not ts and not _is_number(parts[0]):
                continue  # header without '#'
            want = " or ".join(map(str, allowed))
            raise DatasetError(f"expected {want} columns, got {len(parts)}", path, i)
        try:
            t = int(parts[0])
            vals = [float(p) for p in parts[1:]]
        except ValueError as e:
            raise DatasetError(f"not a number ({e})", path, i) from e
        if not all(np.isfinite(vals)):
            raise DatasetError("non-finite value", path, i)
        if ts and t <= ts[-1]:
            raise DatasetError(f"timestamp {t} not after previous {ts[-1]}", path, i)
        ts.append(t)
        rows.append(vals)
    width = len(rows[0]) if rows else min(allowed) - 1
    return np.asarray(ts, dtype=np.int64), np.asarray(rows, dtype=np.float64).reshape(len(rows), width)


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_image_list(path: Path) -> tuple[I64, list[str]]:
    """EuRoC camera csv ``#timestamp [ns],filename`` -> (t_ns, filenames)."""
    ts: list[int] = []
    names: list[str] = []
    for i, parts in _csv_lines(path):
        if len(parts) != 2:
            if not ts and not _is_number(parts[0]):
                continue
            raise DatasetError(f"expected 2 columns (timestamp, filename), got {len(parts)}", path, i)
        try:
            t = int(parts[0])
        except ValueError as e:
            raise DatasetError(f"bad timestamp {parts[0]!r}", path, i) from e
        if ts and t <= ts[-1]:
            raise DatasetError(f"timestamp {t} not after previous {ts[-1]}", path, i)
        ts.append(t)
        names.append(parts[1])
    return np.asarray(ts, dtype=np.int64), names


def matrix_from_yaml(node: Any, path: Path, key: str = "T_BS") -> F64:
    """EuRoC ``{cols, rows, data}`` (or a nested/flat list) -> (rows, cols) array."""
    try:
        if isinstance(node, dict):
            rows, cols = int(node.get("rows", 4)), int(node.get("cols", 4))
            arr = np.asarray(node["data"], dtype=np.float64).reshape(rows, cols)
        else:
            arr = np.asarray(node, dtype=np.float64).reshape(4, 4)
    except (KeyError, ValueError, TypeError) as e:
        raise DatasetError(f"bad matrix {key!r}: {e}", path) from e
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"non-finite values in {key!r}", path)
    return arr


def camera_from_sensor_yaml(path: Path) -> tuple[PinholeCamera, F64, float]:
    """EuRoC camera sensor.yaml -> (PinholeCamera, T_BS, rate_hz)."""
    d = read_yaml(path)
    try:
        w, h = (int(x) for x in d["resolution"])
        fu, fv, cu, cv = (float(x) for x in d["intrinsics"])
        model = str(d.get("camera_model", "pinhole"))
        dist_model = str(d.get("distortion_model", "radial-tangential"))
        coeffs = [float(x) for x in d.get("distortion_coefficients", [0, 0, 0, 0])]
        rate = float(d.get("rate_hz", 0.0))
    except (KeyError, ValueError, TypeError) as e:
        raise DatasetError(f"missing or bad camera key: {e}", path) from e
    if model != "pinhole":
        raise DatasetError(f"unsupported camera_model {model!r} (pinhole only)", path)
    if dist_model not in ("radial-tangential", "radtan", "plumb_bob", "none"):
        raise DatasetError(f"unsupported distortion_model {dist_model!r}", path)
    coeffs = (coeffs + [0.0] * 4)[:4]
    cam = PinholeCamera(w, h, fu, fv, cu, cv, (coeffs[0], coeffs[1], coeffs[2], coeffs[3]))
    return cam, matrix_from_yaml(d.get("T_BS", np.eye(4).tolist()), path), rate


IMU_NOISE_KEYS = (
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "gyroscope_bias_correlation_time",
    "accelerometer_bias_correlation_time",
    "gyroscope_turn_on_bias_sigma",
    "accelerometer_turn_on_bias_sigma",
)


def imu_from_sensor_yaml(path: Path) -> tuple[F64, float, dict[str, float]]:
    """EuRoC IMU sensor.yaml -> (T_BS, rate_hz, noise parameters by their EuRoC/Kalibr names)."""
    d = read_yaml(path)
    try:
        noise = {k: float(d[k]) for k in IMU_NOISE_KEYS if k in d}
        rate = float(d.get("rate_hz", 0.0))
    except (ValueError, TypeError) as e:
        raise DatasetError(f"bad IMU parameter: {e}", path) from e
    return matrix_from_yaml(d.get("T_BS", np.eye(4).tolist()), path), rate, noise


def gnss_from_sensor_yaml(path: Path) -> tuple[F64, float, tuple[float, float, float] | None]:
    """hivemap GNSS sensor.yaml -> (T_BS, rate_hz, ENU origin (lat, lon, alt) or None)."""
    d = read_yaml(path)
    origin = None
    o = d.get("origin")
    try:
        rate = float(d.get("rate_hz", 0.0))
        if isinstance(o, dict):
            origin = (float(o["lat"]), float(o["lon"]), float(o["alt"]))
    except (KeyError, ValueError, TypeError) as e:
        raise DatasetError(f"bad GNSS origin or rate: {e}", path) from e
    return matrix_from_yaml(d.get("T_BS", np.eye(4).tolist()), path), rate, origin
