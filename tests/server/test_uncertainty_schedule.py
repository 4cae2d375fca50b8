"""When the back-end solves every keyframe's covariance of a map: at most ``max_duty`` of a core, and
``max_duty_behind`` while place recognition has a backlog (real queue, real scheduler; the solve itself is
a timed stand-in, since what is tested is when it runs, not what it computes)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from types import SimpleNamespace
from typing import Any

from hivemap.server.backend.backlog import QueryQueue
from hivemap.server.backend.options import SchedulerOptions, UncertaintyOptions
from hivemap.server.backend.uncertainty import Uncertainty

SOLVE_CPU_S = 0.05


class _Timed(Uncertainty):
    """Records when each full solve starts; each reports ``SOLVE_CPU_S`` of CPU."""

    def __init__(self, bk: Any, options: UncertaintyOptions) -> None:
        super().__init__(bk, options)
        self.starts: list[float] = []

    async def _solve(self, map_id: int, full: bool) -> Any:
        self.starts.append(time.monotonic())
        return SimpleNamespace(cpu_s=SOLVE_CPU_S)


def _starts(backlog: bool, seconds: float) -> list[float]:
    """Solve starts of one map asked again continuously for ``seconds``, with or without a backlog."""
    queue = QueryQueue(100, backlog=3)
    for i in range(5 if backlog else 2):
        queue.push(("uav1", i))
    bk = SimpleNamespace(queue=queue, options=SimpleNamespace(scheduler=SchedulerOptions(backlog=3)),
                         server=SimpleNamespace(stack=SimpleNamespace(maps={0: object()})))  # fmt: skip
    u = _Timed(bk, UncertaintyOptions(min_interval_s=0.1, max_duty=0.5, max_duty_behind=0.025))

    async def run() -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            u.request(0)  # new keyframes keep asking
            await asyncio.sleep(0.02)
        for t in u.stop():
            with contextlib.suppress(asyncio.CancelledError):
                await t

    asyncio.run(run())
    return u.starts


def test_a_backlog_slows_the_covariances_to_their_behind_duty() -> None:
    """0.05 s of CPU a solve: 0.1 s apart at duty 0.5, 2 s apart at duty 0.025 behind a backlog."""
    free = _starts(False, 1.5)
    behind = _starts(True, 3.5)
    assert 6 <= len(free) <= 16, free
    assert len(behind) == 2, behind  # the first at once, the next 2 s later
    assert 1.9 <= behind[1] - behind[0] <= 2.6
