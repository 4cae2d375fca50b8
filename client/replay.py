"""A dataset fed through the live-input API (``hivemap.client.Agent``), for the offline and the streaming
replay (``hivemap.client.runner.run_offline``, ``hivemap.client.streaming.run_streaming``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hivemap.client.pacing import Pacer
from hivemap.client.replay_io import _frame_times, _Gnss, _gnss_table, _imu, _load_pair, select_gnss
from hivemap.client.runner import RunnerOptions, RunSummary

if TYPE_CHECKING:
    from hivemap.client.dataset import DatasetSource

F64 = NDArray[np.float64]


@dataclass
class Replay:
    """A dataset fed through the live-input API (``hivemap.client.Agent``) as a camera driver would:
    IMU samples up to each frame, the GNSS mode's fixes before the frame they belong to, then the pair.
    Used by the offline and the streaming replay."""

    ds: Any
    live: Any  # hivemap.client.agent.Agent
    times: F64
    imu: F64
    gnss: _Gnss
    selected: NDArray[np.int64]
    options: RunnerOptions
    pacer: Pacer

    @classmethod
    def open(
        cls,
        source: DatasetSource,
        options: RunnerOptions,
        frontend_options: object | None = None,
        second_stage_options: object | None = None,
        agent_id: str | None = None,
    ) -> Replay:
        from hivemap.client.agent import Agent, AgentOptions
        from hivemap.client.dataset import open_dataset

        ds = open_dataset(source)  # a EuRoC folder or a BagSource
        times = _frame_times(ds)
        if options.max_frames is not None:
            times = times[: options.max_frames]
        gnss = _gnss_table(ds)
        selected = np.flatnonzero(select_gnss(gnss.t, gnss.valid, options.gnss, options.seed))
        live = Agent.from_dataset(
            ds, agent_id=agent_id or str(ds.agent_id),
            options=AgentOptions(options, frontend_options, second_stage_options),
        )  # fmt: skip
        return cls(ds, live, times, _imu(ds), gnss, selected, options, Pacer(times, options.pace))

    def feed(self, stop: Callable[[], bool] | None = None) -> int:
        """Feed the frames at the options' pace (with a progress bar if they ask for one) until the last
        or until ``stop()`` says so before a frame; returns the number of frames fed."""
        from tqdm import tqdm

        imu, gnss, selected, max_dt = self.imu, self.gnss, self.selected, self.options.gnss_max_dt_s
        prev_t, next_fix, n, i = -math.inf, 0, 0, 0
        bar = tqdm(total=len(self.times), desc=f"agent {self.live.agent_id}", unit="frame",
                   disable=not self.options.progress)  # fmt: skip
        while i < len(self.times):
            if stop is not None and stop():
                break
            j = self.pacer.take(i)
            bar.update(j + 1 - i)
            i = j
            t = float(self.times[i])
            left, right = _load_pair(self.ds, i)
            if len(imu):
                self.live.feed_imu_batch(imu[(imu[:, 0] > prev_t) & (imu[:, 0] <= t)])
            while next_fix < len(selected) and gnss.t[selected[next_fix]] <= t + max_dt:
                k = selected[next_fix]
                self.live.feed_gnss_cov(float(gnss.t[k]), gnss.enu[k], gnss.cov[k])
                next_fix += 1
            self.live.feed_stereo(t, left, right)
            prev_t, n, i = t, n + 1, i + 1
        bar.close()
        return n

    def summary(self) -> RunSummary:
        s = RunSummary(agent_id=str(self.live.agent_id), gnss_mode=str(self.options.gnss))
        s.gnss_available = int(self.gnss.valid.sum())
        s.gnss_selected = len(self.selected)
        s.pace, s.frames_dropped, s.late_max_s = self.options.pace, self.pacer.dropped, self.pacer.late_max_s
        rv = self.live.rendezvous
        if rv is not None:
            s.rendezvous_sent, s.marker_frames = rv.observations, rv.frames_run
            s.marker_cpu_ms_mean = 1e3 * rv.cpu_s / rv.frames_run if rv.frames_run else 0.0
        return s
