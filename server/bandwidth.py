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
    # seconds counted by earlier server runs (restored from the store): their bytes are in ``total``
    carried_s: int = 0

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
        seconds = self.carried_s
        if self.first is not None and self.last is not None:
            seconds += int(self.last) - int(self.first) + 1
        return self.total / seconds if seconds else 0.0

    def seconds(self) -> int:
        """The 1 s windows the average divides by (this run's and earlier runs')."""
        if self.first is None or self.last is None:
            return self.carried_s
        return self.carried_s + int(self.last) - int(self.first) + 1

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

    def to_record(self) -> dict[str, float]:
        """What survives a restart (the store's ``server_counters``): totals, peaks, seconds."""
        return {
            "up_total": self.up.total,
            "up_peak": self.up.peak_rate(),
            "up_seconds": self.up.seconds(),
            "down_total": self.down.total,
            "down_peak": self.down.peak_rate(),
            "down_seconds": self.down.seconds(),
        }

    def restore(self, rec: dict[str, float]) -> None:
        """Continue the counts of an earlier run (this run's clock starts afresh)."""
        for name, meter in (("up", self.up), ("down", self.down)):
            meter.total += int(rec.get(f"{name}_total", 0))
            meter.peak = max(meter.peak, float(rec.get(f"{name}_peak", 0.0)))
            meter.carried_s += int(rec.get(f"{name}_seconds", 0))

    def summary(self) -> dict[str, float]:
        return {
            "up_total": float(self.up.total),
            "up_avg": self.up.average(),
            "up_peak": self.up.peak_rate(),
            "down_total": float(self.down.total),
            "down_avg": self.down.average(),
            "down_peak": self.down.peak_rate(),
        }
