"""When a replayed dataset's frames reach the front-end: as fast as it takes them (``asap``), at the
camera's clock (``camera``), or at the camera's clock with a one-frame buffer (``live``).

``asap`` is what the offline baselines use: every frame, reproducible whatever the machine. ``camera``
never runs ahead of the recording but processes every frame, however late. ``live`` is what a robot's
camera driver does when its consumer falls behind: the front-end takes the newest frame that is due
and the older ones are gone (ORB-SLAM3's ROS nodes keep one image in their buffer the same way); the
IMU samples of the dropped frames still reach the agent with the next frame it takes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

PACES = ("asap", "camera", "live")


def check_pace(pace: str) -> None:
    """Raises ValueError naming the paces when ``pace`` is none of them."""
    if pace not in PACES:
        raise ValueError(f"unknown pace {pace!r} (one of {', '.join(PACES)})")


@dataclass
class Pacer:
    """Chooses the next frame to process and waits for it. ``times`` are the frames' timestamps [s]; the
    first frame is due when the pacer is first asked."""

    times: NDArray[np.float64]
    pace: str = "asap"
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    dropped: int = 0  # frames skipped (live)
    late_max_s: float = 0.0  # how far behind the camera's clock a processed frame was taken, at most
    _start: float | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        check_pace(self.pace)

    def take(self, i: int) -> int:
        """The index of the frame to process now, given that frame ``i`` is the next one not yet
        processed (``i`` itself except in ``live`` when later frames are already due); waits until it
        is due."""
        if self.pace == "asap":
            return i
        now = self.clock()
        if self._start is None:
            self._start = now - float(self.times[i] - self.times[0])
        if self.pace == "live":
            # the newest frame due by now; never beyond the last
            j = int(np.searchsorted(self.times, self.times[0] + (now - self._start), side="right")) - 1
            if j > i:
                self.dropped += j - i
                i = j
        due = self._start + float(self.times[i] - self.times[0])
        if now < due:
            self.sleep(due - now)
        else:
            self.late_max_s = max(self.late_max_s, now - due)
        return i
