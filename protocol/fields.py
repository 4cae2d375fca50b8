"""Field validators shared by the codec's message readers; each raises :class:`FieldError` naming it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hivemap.protocol.errors import FieldError

POSE_TOL = 1e-6
_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])


def as_int(v: Any, path: str, lo: int = -(2**63), hi: int = 2**63 - 1) -> int:
    if not isinstance(v, int) or isinstance(v, bool):
        raise FieldError(f"expected an integer, got {type(v).__name__}", path)
    if not lo <= v <= hi:
        raise FieldError(f"{v} outside [{lo}, {hi}]", path)
    return v


def as_bool(v: Any, path: str) -> bool:
    if not isinstance(v, bool):
        raise FieldError(f"expected true or false, got {type(v).__name__}", path)
    return v


def as_float(v: Any, path: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise FieldError(f"expected a number, got {type(v).__name__}", path)
    if not math.isfinite(v):
        raise FieldError("not finite", path)
    return float(v)


def as_str(v: Any, path: str, max_len: int, allow_empty: bool = True) -> str:
    if not isinstance(v, str):
        raise FieldError(f"expected a string, got {type(v).__name__}", path)
    if len(v) > max_len:
        raise FieldError(f"longer than {max_len} characters", path)
    if not allow_empty and not v:
        raise FieldError("must not be empty", path)
    return v


def as_opt_str(v: Any, path: str, max_len: int) -> str | None:
    return None if v is None else as_str(v, path, max_len)


def as_array(
    v: Any, path: str, dtype: str, shape: tuple[int | None, ...], max_rows: int | None = None
) -> np.ndarray:
    """Check an array: dtype, ndim, fixed dims (None = any), first dim <= max_rows, finite floats."""
    if not isinstance(v, np.ndarray):
        raise FieldError(f"expected an array, got {type(v).__name__}", path)
    if v.dtype != np.dtype(dtype):
        raise FieldError(f"dtype {v.dtype}, expected {np.dtype(dtype)}", path)
    if v.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, v.shape, strict=True)):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise FieldError(f"shape {v.shape}, expected ({want})", path)
    if max_rows is not None and v.ndim and v.shape[0] > max_rows:
        raise FieldError(f"{v.shape[0]} rows exceed the limit of {max_rows}", path)
    if v.dtype.kind == "f" and not np.isfinite(v).all():
        raise FieldError("contains NaN or inf", path)
    return v


def rotation_error(R: list[list[float]]) -> tuple[float, float]:
    """max |R^T R - I| and det(R) of a 3x3 matrix given as nested lists (cheaper than numpy at 3x3)."""
    err = 0.0
    for i in range(3):
        for j in range(i, 3):
            d = R[0][i] * R[0][j] + R[1][i] * R[1][j] + R[2][i] * R[2][j] - (1.0 if i == j else 0.0)
            err = max(err, abs(d))
    det = (
        R[0][0] * (R[1][1] * R[2][2] - R[1][2] * R[2][1])
        - R[0][1] * (R[1][0] * R[2][2] - R[1][2] * R[2][0])
        + R[0][2] * (R[1][0] * R[2][1] - R[1][1] * R[2][0])
    )
    return err, det


def check_rigid(m: np.ndarray, path: str) -> None:
    """(..., 4, 4) SE(3): last row [0, 0, 0, 1], rotation orthonormal to 1e-6 with det +1."""
    if m.ndim == 2:
        rows = m.tolist()
        if rows[3] != [0.0, 0.0, 0.0, 1.0]:
            raise FieldError("last row of a pose must be [0, 0, 0, 1]", path)
        err, det = rotation_error([r[:3] for r in rows[:3]])
        if err > POSE_TOL or det <= 0:
            raise FieldError("rotation block is not a proper orthonormal rotation", path)
        return
    bottom = m[..., 3, :]
    if not (bottom == _BOTTOM).all():
        raise FieldError("last row of a pose must be [0, 0, 0, 1]", path)
    R = m[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() if R.size else 0.0
    if err > POSE_TOL or (R.size and (np.linalg.det(R) <= 0).any()):
        raise FieldError("rotation block is not a proper orthonormal rotation", path)


def check_similarity(m: np.ndarray, path: str) -> None:
    if not (m[3] == _BOTTOM).all():
        raise FieldError("last row of a Sim(3) matrix must be [0, 0, 0, 1]", path)
    det = float(np.linalg.det(m[:3, :3]))
    if not det > 0:
        raise FieldError("Sim(3) scale must be positive", path)
    R = m[:3, :3] / np.cbrt(det)
    if np.abs(R.T @ R - np.eye(3)).max() > POSE_TOL:
        raise FieldError("Sim(3) rotation block is not a scaled rotation", path)


def is_spd3(c: list[list[float]]) -> bool:
    """Symmetric (to 1e-12 relative) and positive definite (Sylvester: leading minors > 0)."""
    scale = max(abs(x) for row in c for x in row)
    if any(abs(c[i][j] - c[j][i]) > 1e-12 * scale for i in range(3) for j in range(i + 1, 3)):
        return False
    m2 = c[0][0] * c[1][1] - c[0][1] * c[1][0]
    m3 = (
        c[0][0] * (c[1][1] * c[2][2] - c[1][2] * c[2][1])
        - c[0][1] * (c[1][0] * c[2][2] - c[1][2] * c[2][0])
        + c[0][2] * (c[1][0] * c[2][1] - c[1][1] * c[2][0])
    )
    return c[0][0] > 0 and m2 > 0 and m3 > 0


def check_psd(c: np.ndarray, path: str) -> None:
    """A covariance: symmetric (to 1e-9 relative) and positive semi-definite (its smallest eigenvalue not
    below -1e-9 times its largest; a held keyframe's is exactly zero)."""
    scale = float(np.abs(c).max()) if c.size else 0.0
    if np.abs(c - c.T).max(initial=0.0) > 1e-9 * scale:
        raise FieldError("covariance must be symmetric", path)
    if scale > 0 and float(np.linalg.eigvalsh(c).min()) < -1e-9 * scale:
        raise FieldError("covariance must be positive semi-definite", path)


def check_same_rows(path_a: str, a: np.ndarray, path_b: str, b: np.ndarray) -> None:
    if a.shape[0] != b.shape[0]:
        raise FieldError(f"{b.shape[0]} rows but {path_a} has {a.shape[0]}", path_b)


CAMERA_KEYS = {"width", "height", "fx", "fy", "cx", "cy", "dist"}


def as_camera(v: Any, path: str) -> dict[str, object]:
    if not isinstance(v, dict):
        raise FieldError(f"expected a map, got {type(v).__name__}", path)
    keys = set(v)
    if keys != CAMERA_KEYS:
        missing, extra = CAMERA_KEYS - keys, keys - CAMERA_KEYS
        raise FieldError(f"missing {sorted(missing)}, unknown {sorted(map(str, extra))}", path)
    out: dict[str, object] = {
        "width": as_int(v["width"], f"{path}.width", 1, 16384),
        "height": as_int(v["height"], f"{path}.height", 1, 16384),
    }
    for k in ("fx", "fy", "cx", "cy"):
        out[k] = as_float(v[k], f"{path}.{k}")
    if float(out["fx"]) <= 0 or float(out["fy"]) <= 0:  # type: ignore[arg-type]
        raise FieldError("focal lengths must be positive", f"{path}.fx")
    dist = v["dist"]
    if not isinstance(dist, list) or len(dist) != 4:
        raise FieldError("expected 4 coefficients (k1, k2, p1, p2)", f"{path}.dist")
    out["dist"] = [as_float(d, f"{path}.dist[{i}]") for i, d in enumerate(dist)]
    return out
