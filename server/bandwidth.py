"""Per-agent bandwidth accounting: bytes up/down, average and peak rate over 1 s windows."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class RateMeter:
    """Counts bytes in one direction. Peak = the largest number of bytes seen in any whole 1 s window
    (windows aligned on the clock's integer seconds); average = total bytes / number of 1 s windows from the
    first byte's window to the last byte's (so average <= peak always)."""

    total: int = 0
    peak: float = 0.0
    first: float | None = None
    last: float | None = None
    _window_start: float = 0.0
    _window_bytes: int = 0

    def add(self, nbytes: int, now: float) -> None:
        window = float(int(now))
        if self.first is None:
            self.first = now
            self._window_start = window
        if window != self._window_start:
            self.peak = max(self.peak, float(self._window_bytes))
            self._window_start = window
            self._window_bytes = 0
        self._window_bytes += nbytes
        self.total += nbytes
        self.last = now

    def average(self) -> float:
        if self.first is None or self.last is None:
            return 0.0
        return self.total / (int(self.last) - int(self.first) + 1)

    def peak_rate(self) -> float:
        """Peak bytes/s, including the window in progress."""
        return max(self.peak, float(self._window_bytes))


class Bandwidth:
    """Bytes received from (up) and sent to (down) one agent."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.up = RateMeter()
        self.down = RateMeter()

    def received(self, nbytes: int) -> None:
        self.up.add(nbytes, self._clock())

    def sent(self, nbytes: int) -> None:
        self.down.add(nbytes, self._clock())

    def summary(self) -> dict[str, float]:
        return {
            "up_total": float(self.up.total),
            "up_avg": self.up.average(),
            "up_peak": self.up.peak_rate(),
            "down_total": float(self.down.total),
            "down_avg": self.down.average(),
            "down_peak": self.down.peak_rate(),
        }
