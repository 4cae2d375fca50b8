"""IMU and GNSS sensor models driven by a true ``Trajectory``; NMEA GPGGA formatting and parsing.

IMU (paper Table 2, the RotorS/Gazebo IMU model): measurement = truth + bias + white noise, where the
white noise of continuous density ``sigma_c`` is drawn per sample with ``sigma_c * sqrt(rate)`` and the
bias is a first-order Gauss-Markov process with correlation time ``tau`` and random-walk density
``sigma_rw`` (discrete: ``b_k+1 = exp(-dt/tau) b_k + sqrt(sigma_rw^2 tau / 2 (1 - exp(-2 dt/tau))) n``)
plus a constant turn-on bias. Truth: gyroscope = body angular rate, accelerometer = body specific force
``R^T (a - g)`` with ``g = [0, 0, -9.81]`` (z up), both exact from the trajectory splines.

GNSS (paper Table 3): the antenna sits at the body origin; each fix = true ENU position + N(0, sigma_h)
on east/north and N(0, sigma_v) on up. Geodetic conversion uses pymap3d (WGS84); GPGGA altitude is the
ellipsoidal height (geoid separation written as 0.0).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import numpy as np
import pymap3d
from numpy.typing import NDArray

from hivemap.maps.geometry import so3_exp
from hivemap.sim.scenarios import GnssNoise, ImuNoise
from hivemap.sim.trajectories import G_WORLD, Trajectory

F64 = NDArray[np.float64]


def sample_times(duration: float, rate_hz: float) -> F64:
    """Times 0, 1/rate, ... <= duration (exact multiples; computed from integer indices)."""
    n = int(np.floor(duration * rate_hz + 1e-9)) + 1
    return np.arange(n, dtype=np.float64) / rate_hz


@dataclass(frozen=True)
class ImuData:
    """IMU samples: t (N,) s, gyro (N, 3) rad/s, accel (N, 3) m/s^2, and the true biases added."""

    t: F64
    gyro: F64
    accel: F64
    bias_gyro: F64
    bias_accel: F64


def _gauss_markov(
    n: int, dt: float, sigma_rw: float, tau: float, turn_on: float, rng: np.random.Generator
) -> F64:
    phi = np.exp(-dt / tau)
    sd = np.sqrt(sigma_rw**2 * tau / 2.0 * (1.0 - np.exp(-2.0 * dt / tau)))
    b = np.zeros((n, 3))
    b0 = rng.normal(0.0, turn_on, 3) if turn_on > 0 else np.zeros(3)
    if sd > 0:
        w = rng.normal(0.0, sd, (n, 3))
        cur = np.zeros(3)
        for k in range(1, n):
            cur = phi * cur + w[k]
            b[k] = cur
    return b + b0


def simulate_imu(
    traj: Trajectory, rate_hz: float, noise: ImuNoise, rng: np.random.Generator, duration: float | None = None
) -> ImuData:
    """IMU samples at ``rate_hz`` from t = 0 to ``duration`` (default: the trajectory's)."""
    t = sample_times(traj.duration if duration is None else min(duration, traj.duration), rate_hz)
    dt = 1.0 / rate_hz
    n = len(t)
    gyro_true = traj.angular_velocity(t)
    acc_true = traj.specific_force(t)
    bg = _gauss_markov(
        n, dt, noise.gyroscope_random_walk, noise.gyroscope_bias_correlation_time,
        noise.gyroscope_turn_on_bias_sigma, rng,
    )  # fmt: skip
    ba = _gauss_markov(
        n, dt, noise.accelerometer_random_walk, noise.accelerometer_bias_correlation_time,
        noise.accelerometer_turn_on_bias_sigma, rng,
    )  # fmt: skip
    sg = noise.gyroscope_noise_density * np.sqrt(rate_hz)
    sa = noise.accelerometer_noise_density * np.sqrt(rate_hz)
    gyro = gyro_true + bg + (rng.normal(0.0, sg, (n, 3)) if sg > 0 else 0.0)
    accel = acc_true + ba + (rng.normal(0.0, sa, (n, 3)) if sa > 0 else 0.0)
    return ImuData(t, gyro, accel, bg, ba)


def integrate_imu(
    t: F64, gyro: F64, accel: F64, R0: F64, p0: F64, v0: F64, gravity: F64 = G_WORLD
) -> tuple[F64, F64, F64]:
    """Dead-reckon IMU samples (strapdown, z-up world) -> (R (N,3,3), p (N,3), v (N,3)).

    Between samples the rates are taken linear in time: rotation by the 4th-order Magnus expansion
    (exp map), velocity/position by Simpson's rule with the attitude at the mid-point.
    """
    n = len(t)
    R = np.zeros((n, 3, 3))
    p = np.zeros((n, 3))
    v = np.zeros((n, 3))
    R[0], p[0], v[0] = R0, p0, v0
    for k in range(n - 1):
        h = t[k + 1] - t[k]
        w0, w1 = gyro[k], gyro[k + 1]
        wm = 0.5 * (w0 + w1)
        # rotation over the half step (linear rate from w0 to wm) and the full step
        Rh = R[k] @ so3_exp(h / 4 * (w0 + wm) + h * h / 48 * np.cross(w0, wm))
        R1 = R[k] @ so3_exp(h / 2 * (w0 + w1) + h * h / 12 * np.cross(w0, w1))
        a0 = R[k] @ accel[k] + gravity
        am = Rh @ (0.5 * (accel[k] + accel[k + 1])) + gravity
        a1 = R1 @ accel[k + 1] + gravity
        v[k + 1] = v[k] + h / 6 * (a0 + 4 * am + a1)
        p[k + 1] = p[k] + h * v[k] + h * h / 6 * (a0 + 2 * am)
        R[k + 1] = R1
    return R, p, v


# ---------------------------------------------------------------------------------------------
# GNSS
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GeodeticOrigin:
    lat: float  # degrees, WGS84
    lon: float
    alt: float  # ellipsoidal height, m


@dataclass(frozen=True)
class GnssData:
    """GNSS fixes: t (N,) s, enu (N, 3) measured, enu_true (N, 3), sigma_h, sigma_v (m)."""

    t: F64
    enu: F64
    enu_true: F64
    sigma_h: float
    sigma_v: float


def simulate_gnss(
    traj: Trajectory,
    rate_hz: float,
    noise: GnssNoise,
    rng: np.random.Generator,
    duration: float | None = None,
) -> GnssData:
    t = sample_times(traj.duration if duration is None else min(duration, traj.duration), rate_hz)
    truth = traj.position(t)
    n = len(t)
    err = np.concatenate(
        [rng.normal(0.0, noise.sigma_horizontal, (n, 2)), rng.normal(0.0, noise.sigma_vertical, (n, 1))],
        axis=1,
    )
    return GnssData(t, truth + err, truth, noise.sigma_horizontal, noise.sigma_vertical)


def enu_to_geodetic(enu: F64, origin: GeodeticOrigin) -> F64:
    """(N, 3) ENU metres -> (N, 3) lat, lon (deg), ellipsoidal height (m), via pymap3d."""
    enu = np.asarray(enu, dtype=np.float64).reshape(-1, 3)
    lat, lon, alt = pymap3d.enu2geodetic(enu[:, 0], enu[:, 1], enu[:, 2], origin.lat, origin.lon, origin.alt)
    return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=1)


def geodetic_to_enu(lla: F64, origin: GeodeticOrigin) -> F64:
    """(N, 3) lat, lon (deg), height (m) -> (N, 3) ENU metres, via pymap3d."""
    lla = np.asarray(lla, dtype=np.float64).reshape(-1, 3)
    e, n, u = pymap3d.geodetic2enu(lla[:, 0], lla[:, 1], lla[:, 2], origin.lat, origin.lon, origin.alt)
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=1)


def nmea_checksum(body: str) -> str:
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"{c:02X}"


def format_gpgga(
    t_ns: int, lat: float, lon: float, alt: float, quality: int = 4, n_sats: int = 14, hdop: float = 0.8
) -> str:
    """One ``$GPGGA`` sentence (UTC time from a Unix-epoch ns timestamp; minutes with 8 decimals).

    8 decimals of minutes resolve 2e-5 m; altitude has 4 decimals; quality 4 = RTK fixed (cm noise).
    """
    utc = _dt.datetime.fromtimestamp(t_ns // 1_000_000_000, tz=_dt.UTC)
    frac = (t_ns % 1_000_000_000) / 1e9
    hhmmss = f"{utc.hour:02d}{utc.minute:02d}{utc.second + frac:05.2f}"
    la = abs(lat)
    lo = abs(lon)
    lat_s = f"{int(la):02d}{(la - int(la)) * 60:011.8f}"
    lon_s = f"{int(lo):03d}{(lo - int(lo)) * 60:011.8f}"
    body = (
        f"GPGGA,{hhmmss},{lat_s},{'N' if lat >= 0 else 'S'},{lon_s},{'E' if lon >= 0 else 'W'},"
        f"{quality},{n_sats:02d},{hdop:.1f},{alt:.4f},M,0.0,M,,"
    )
    return f"${body}*{nmea_checksum(body)}"


@dataclass(frozen=True)
class GgaFix:
    time_of_day_s: float
    lat: float
    lon: float
    alt: float
    quality: int


def parse_gpgga(sentence: str) -> GgaFix:
    """Parse a ``$GPGGA``/``$GNGGA`` sentence (checksum verified). Raises ValueError when malformed."""
    s = sentence.strip()
    if not s.startswith("$") or "*" not in s:
        raise ValueError(f"not an NMEA sentence: {s[:40]!r}")
    body, cs = s[1:].split("*", 1)
    if nmea_checksum(body) != cs.strip().upper():
        raise ValueError(f"NMEA checksum mismatch: {s[:40]!r}")
    f = body.split(",")
    if len(f) < 10 or not f[0].endswith("GGA"):
        raise ValueError(f"not a GGA sentence: {s[:40]!r}")
    hh, mm, ss = int(f[1][0:2]), int(f[1][2:4]), float(f[1][4:])
    lat = int(f[2][:2]) + float(f[2][2:]) / 60.0
    if f[3] == "S":
        lat = -lat
    lon = int(f[4][:3]) + float(f[4][3:]) / 60.0
    if f[5] == "W":
        lon = -lon
    alt = float(f[9])
    if len(f) > 11 and f[11]:
        alt += float(f[11])  # MSL + geoid separation = ellipsoidal height
    return GgaFix(hh * 3600 + mm * 60 + ss, lat, lon, alt, int(f[6]))
