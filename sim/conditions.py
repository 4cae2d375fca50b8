"""Lighting and weather applied to rendered frames (paper Table 4: bright/somber, clear/mist/fog).

Fog is defined once, by the meteorological visibility V (Koschmieder): the transmission of a
surface at distance d is ``exp(-3.912 d / V)`` (3.912 = -ln 0.02, the 2% contrast threshold), and
the pixel blends towards the fog's own brightness (airlight) by ``1 - transmission``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
KOSCHMIEDER = 3.912


def fog_transmission(distance_m: NDArray[np.floating], visibility_m: float) -> F32:
    """exp(-3.912 d / V); 0 for infinite distance (sky), 1 for a clear sky (V = inf)."""
    d = np.asarray(distance_m, dtype=np.float64)
    if not np.isfinite(visibility_m):
        return np.ones(d.shape, np.float32)
    with np.errstate(invalid="ignore"):
        t = np.exp(-KOSCHMIEDER * d / visibility_m)
    return np.where(np.isfinite(d), t, 0.0).astype(np.float32)


@dataclass(frozen=True)
class Lighting:
    """Exposure model: gain, gamma, black level and sensor noise (std in grey levels at gain 1)."""

    name: str
    gain: float
    gamma: float
    black: float
    noise_std: float

    @staticmethod
    def preset(name: str) -> Lighting:
        try:
            return LIGHTING[name]
        except KeyError:
            raise ValueError(f"unknown lighting {name!r}: choose one of {sorted(LIGHTING)}") from None


@dataclass(frozen=True)
class Weather:
    name: str
    visibility_m: float  # inf = clear
    airlight: float  # fog brightness, grey levels

    @staticmethod
    def preset(name: str) -> Weather:
        try:
            return WEATHER[name]
        except KeyError:
            raise ValueError(f"unknown weather {name!r}: choose one of {sorted(WEATHER)}") from None


LIGHTING = {
    "bright": Lighting("bright", gain=1.0, gamma=1.0, black=0.0, noise_std=1.5),
    # Low sun: a third of the light, crushed shadows, and more sensor noise after the gain.
    "somber": Lighting("somber", gain=0.35, gamma=1.35, black=4.0, noise_std=3.0),
}
WEATHER = {
    "clear": Weather("clear", float("inf"), 200.0),
    "mist": Weather("mist", 150.0, 190.0),
    "fog": Weather("fog", 50.0, 185.0),
}


def apply_conditions(
    gray: NDArray[np.uint8],
    depth: NDArray[np.floating],
    lighting: Lighting | str,
    weather: Weather | str,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """Apply weather (by depth) then lighting and sensor noise to a rendered frame."""
    light = Lighting.preset(lighting) if isinstance(lighting, str) else lighting
    wx = Weather.preset(weather) if isinstance(weather, str) else weather
    img = gray.astype(np.float32)
    if np.isfinite(wx.visibility_m):
        t = fog_transmission(depth, wx.visibility_m)
        img = img * t + wx.airlight * (1.0 - t)
    img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** light.gamma * light.gain + light.black
    img += rng.normal(0.0, light.noise_std, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
