"""Streaming agent: dataset replay as an agent that streams to a server over ``AgentLink``.

Split out of ``hivemap.client.runner`` (which keeps the offline replay and re-exports
:func:`run_streaming` and :func:`health_url`); the processing is the runner's ``OfflineAgent``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hivemap.client.runner import (
    RunnerOptions,
    RunSummary,
    _frame_times,
    _gnss_table,
    _imu,
    _load_pair,
    _make_agent,
    _write_outputs,
)

if TYPE_CHECKING:
    from hivemap.client.dataset import DatasetSource

log = logging.getLogger(__name__)


def run_streaming(
    agent_dir: DatasetSource,
    out_dir: str | Path,
    server: str,
    agent_id: str | None,
    token: str,
    options: RunnerOptions | None = None,
    frontend_options: object | None = None,
    second_stage_options: object | None = None,
) -> RunSummary:
    """Replay a dataset as an agent streaming to a server (``hivemap.client.link.AgentLink``).

    Same processing and outputs as :func:`run_offline`; in addition every front-end event becomes a
    protocol message (``map_points`` before the ``keyframe`` that references them, the fix used at
    that keyframe attached; ``pose_updates`` after local BA), durably queued in ``out/outbox.sqlite``
    and streamed; server ``correction`` messages become co-location factors of the second stage.
    """
    import asyncio

    return asyncio.run(
        _stream(agent_dir, out_dir, server, agent_id, token, options, frontend_options, second_stage_options)
    )


def health_url(server: str) -> str:
    """The server's ``/health`` address from its WebSocket address (``ws://HOST:PORT/ws``)."""
    from urllib.parse import urlsplit, urlunsplit

    u = urlsplit(server)
    scheme = {"ws": "http", "wss": "https", "http": "http", "https": "https"}.get(u.scheme)
    if scheme is None or not u.netloc:
        raise ValueError(f"server address {server!r} is not ws://HOST:PORT/ws")
    path = u.path[: -len("/ws")] if u.path.endswith("/ws") else u.path.rstrip("/")
    return urlunsplit((scheme, u.netloc, path + "/health", "", ""))


def _backend_idle(url: str) -> bool | None:
    """The server's ``backend_idle`` (None: the server reports none, i.e. no back-end or an older server).

    Raises ``OSError`` when the server does not answer (the caller retries)."""
    import urllib.request

    with urllib.request.urlopen(url, timeout=5.0) as r:  # noqa: S310 (http(s) only, see health_url)
        try:
            value = json.loads(r.read()).get("backend_idle")
        except (ValueError, AttributeError) as exc:
            log.warning("server health %s unreadable: %s", url, exc)
            return None
    return value if isinstance(value, bool) else None


async def _wait_for_server(
    server: str, options: RunnerOptions, last_correction: list[float], apply_pending: Callable[[], None]
) -> None:
    """After the last frame: wait for the corrections the server still owes (see RunnerOptions)."""
    import asyncio
    import time

    t_end = time.monotonic()
    url = health_url(server)
    idle_polls, use_health, failures = 0, True, 0
    if options.corrections_max_wait_s <= 0:
        apply_pending()
        return
    while time.monotonic() - t_end < options.corrections_max_wait_s:
        await asyncio.sleep(0.5)
        apply_pending()
        quiet = time.monotonic() - max(last_correction[0], t_end)
        if use_health:
            try:
                idle = await asyncio.to_thread(_backend_idle, url)
            except OSError as exc:
                # a busy server can miss one poll's 5 s timeout: retry; the quiet timer only after several
                failures += 1
                log.warning("server health %s: no answer (%s), %d in a row", url, exc, failures)
                if failures >= options.health_max_failures:
                    log.warning("server health unreachable: waiting until %.0f s without corrections",
                                options.corrections_quiet_s)  # fmt: skip
                    use_health = False
                continue
            failures = 0
            if idle is None:
                log.warning("server reports no back-end state: waiting until %.0f s without corrections",
                            options.corrections_quiet_s)  # fmt: skip
                use_health = False
                continue
            idle_polls = idle_polls + 1 if idle else 0
            # idle twice in a row, and the last correction has had time to arrive
            if idle_polls >= 2 and quiet >= options.corrections_grace_s:
                break
        elif quiet >= options.corrections_quiet_s:
            break
    else:
        log.warning("server still busy %.0f s after the last frame: stopping", options.corrections_max_wait_s)
    apply_pending()


async def _stream(
    agent_dir: DatasetSource,
    out_dir: str | Path,
    server: str,
    agent_id: str | None,
    token: str,
    options: RunnerOptions | None,
    frontend_options: object | None,
    second_stage_options: object | None,
) -> RunSummary:
    import asyncio

    options = options or RunnerOptions()
    # SIGTERM (docker stop, systemd) and SIGINT end the replay between frames: what was produced is in
    # the outbox (durable) and goes out at the next start; the agent then exits normally. Installed
    # first, so a signal during the set-up below is handled too (the replay then stops at once).
    stopping = asyncio.Event()
    stopped_by: list[str] = []
    signals = _on_stop_signals(asyncio.get_running_loop(), stopping, stopped_by)
    try:
        return await _stream_until(
            agent_dir, out_dir, server, agent_id, token, options, frontend_options, second_stage_options,
            stopping, stopped_by,
        )  # fmt: skip
    finally:
        for sig in signals:
            asyncio.get_running_loop().remove_signal_handler(sig)


async def _stream_until(
    agent_dir: DatasetSource,
    out_dir: str | Path,
    server: str,
    agent_id: str | None,
    token: str,
    options: RunnerOptions,
    frontend_options: object | None,
    second_stage_options: object | None,
    stopping: Any,
    stopped_by: list[str],
) -> RunSummary:
    import asyncio
    import threading
    import time

    from tqdm import tqdm

    from hivemap.client.dataset import open_dataset
    from hivemap.client.frontend.tracker import KeyframeEvent, PoseUpdateEvent
    from hivemap.client.link import AgentLink, LinkOptions
    from hivemap.client.logtags import CorrectionSummary, tag_agent
    from hivemap.client.outbox import open_mission_outbox
    from hivemap.protocol import Correction, Keyframe, MapPoints, PoseUpdates

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ds = open_dataset(agent_dir)  # a EuRoC folder or a BagSource
    aid = agent_id or str(ds.agent_id)
    tag_agent(aid)  # this task's log lines (and its threads') say which agent speaks
    times = _frame_times(ds)
    if options.max_frames is not None:
        times = times[: options.max_frames]
    imu = _imu(ds)
    gnss = _gnss_table(ds)
    agent = _make_agent(ds, gnss, options, frontend_options, second_stage_options)
    agent.select(times)

    pending: list[Correction] = []
    lock = threading.Lock()

    last_correction = [time.monotonic()]

    def on_correction(msg: Correction) -> None:  # called in the event loop; applied between frames
        with lock:
            pending.append(msg)
            last_correction[0] = time.monotonic()

    T_BS = getattr(ds, "T_BS", {}) or {}
    cam_from_antenna = None
    if "gnss0" in T_BS and "cam0" in T_BS:
        cam_from_antenna = (np.linalg.inv(np.asarray(T_BS["cam0"])) @ np.asarray(T_BS["gnss0"]))[:3, 3].copy()
    # One outbox is one mission: an unfinished one is resumed (this front-end then starts in a session
    # the earlier process never used), a finished one is archived and a new mission begins.
    box = open_mission_outbox(out, aid)
    first = box.start_session()
    if first:
        log.info("agent %s resumes mission %s in session %d", aid, box.mission, first)
    link = AgentLink(
        server, aid, str(getattr(ds, "kind", "uav")), ds.camera.to_dict(), token, box,
        on_correction=on_correction, cam_from_antenna=cam_from_antenna, session=first,
        options=LinkOptions(max_connect_attempts=options.max_connect_attempts),
    )  # fmt: skip
    outgoing: list[object] = []

    def on_event(ev: object) -> None:
        # the wire carries the mission's session numbers: this process's front-end sessions shifted by
        # the first one it was given
        session = first + int(getattr(ev, "session", 0))
        box.reserve_sessions(session)  # writes only when a tracking loss started a new session
        if isinstance(ev, KeyframeEvent):
            if len(ev.new_point_ids):
                outgoing.append(
                    MapPoints(ev.new_point_ids, ev.new_point_xyz, ev.new_point_descriptors, session)
                )
            fix = agent.kf_fix.get((ev.session, ev.kf_id))
            outgoing.append(
                Keyframe(
                    ev.kf_id,
                    ev.timestamp,
                    ev.world_from_cam,
                    ev.keypoints,
                    ev.octaves,
                    ev.descriptors,
                    ev.point_ids,
                    None if fix is None else gnss.enu[fix],
                    None if fix is None else gnss.cov[fix],
                    session,
                    agent.up_in_cam(ev.session, ev.kf_id),
                )  # fmt: skip
            )
        elif isinstance(ev, PoseUpdateEvent):
            outgoing.append(PoseUpdates(ev.kf_ids, ev.world_from_cam, ev.point_ids, ev.xyz, session))

    agent.on_event = on_event

    corrections_log = CorrectionSummary(log)

    def apply_pending() -> None:
        with lock:
            todo = list(pending)
            pending.clear()
        for c in todo:
            if c.session < first:  # a session of the process that ran this mission before
                log.debug("correction for session %d of an earlier process: not this front-end's", c.session)
                continue
            enu = c.global_frame == "enu"
            n = agent.apply_correction(
                c.session - first, c.kf_ids, c.world_from_cam, c.global_from_local, enu=enu
            )
            corrections_log.add(c.map_id, c.global_frame, n)  # DEBUG each, INFO every 10 s

    def step(i: int, prev_t: float) -> None:
        apply_pending()
        t = float(times[i])
        left, right = _load_pair(ds, i)
        sel = (imu[:, 0] > prev_t) & (imu[:, 0] <= t) if len(imu) else None
        agent.step(t, left, right, imu[sel] if sel is not None else None)

    link_task = asyncio.create_task(link.run())
    summary = RunSummary(agent_id=aid, gnss_mode=str(options.gnss))
    summary.gnss_available = int(gnss.valid.sum())
    summary.gnss_selected = int(agent.selected.sum())
    wall0 = time.perf_counter()
    prev_t = -math.inf
    link_task.add_done_callback(lambda _: stopping.set())  # the link gave up (or was refused)
    n_frames = 0
    failure: Exception | None = None
    try:
        for i in tqdm(range(len(times)), desc=f"agent {aid}", unit="frame", disable=not options.progress):
            if stopping.is_set():
                break
            await asyncio.to_thread(step, i, prev_t)
            n_frames = i + 1
            prev_t = float(times[i])
            for msg in outgoing:
                link.submit_nowait(msg)  # type: ignore[arg-type]
            outgoing.clear()
            if link_task.done():
                link_task.result()  # raises LinkRefused / LinkFailed
        if not stopping.is_set():
            await asyncio.to_thread(agent.finish)
            for msg in outgoing:
                link.submit_nowait(msg)  # type: ignore[arg-type]
            outgoing.clear()
        try:
            await _unless(link.flush(timeout=options.flush_timeout_s), stopping)
        except TimeoutError:
            log.warning("server did not acknowledge everything within %.0f s", options.flush_timeout_s)
        await _unless(_wait_for_server(server, options, last_correction, apply_pending), stopping)
        if link_task.done() and not link_task.cancelled():
            link_task.result()  # the link failed during the flush
        if not stopping.is_set() and box.finish():  # all acknowledged: the next run is a new mission
            log.info("agent %s: mission %s complete", aid, box.mission)
    except Exception as exc:
        failure = exc
    finally:
        await link.close()
        link_task.cancel()
        with contextlib_suppress():
            await link_task
    summary.stopped_by = stopped_by[0] if stopped_by else ""
    corrections_log.flush()
    if failure is not None:
        from hivemap.client.link import LinkFailed, LinkRefused

        if isinstance(failure, LinkRefused | LinkFailed):
            raise StreamFailed(str(failure), link.unsent, out / "outbox.sqlite") from failure
        log.error("agent %s failed; %d messages unsent in %s (kept for the next start)",
                  aid, link.unsent, out / "outbox.sqlite")  # fmt: skip
        raise failure
    summary.unsent = link.unsent
    summary.wall_s = time.perf_counter() - wall0
    _write_outputs(agent, out, summary, n_frames)
    summary.outputs["outbox"] = str(out / "outbox.sqlite")
    (out / "run.json").write_text(summary.to_json())
    log.info(
        "agent %s streamed: %d keyframes, %d corrections applied, up %d B, down %d B, %d poses refused",
        aid, summary.keyframes, agent.corrections_applied, link.stats.bytes_up, link.stats.bytes_down,
        agent.corrections_refused,
    )  # fmt: skip
    return summary


class StreamFailed(RuntimeError):
    """The link ended the run (refused, or gave up reconnecting); ``unsent`` messages stay in ``outbox``."""

    def __init__(self, message: str, unsent: int, outbox: Path) -> None:
        super().__init__(message)
        self.unsent = unsent
        self.outbox = outbox


def _on_stop_signals(loop: Any, stopping: Any, stopped_by: list[str]) -> list[int]:
    """SIGTERM and SIGINT set ``stopping`` (and append the signal's name); returns those handled."""
    import signal

    handled = []
    for sig in (signal.SIGTERM, signal.SIGINT):

        def on_signal(sig: signal.Signals = sig) -> None:
            log.warning("%s: stopping the replay; unsent messages stay in the outbox", sig.name)
            stopped_by.append(sig.name)
            stopping.set()

        try:
            loop.add_signal_handler(sig, on_signal)
            handled.append(int(sig))
        except (NotImplementedError, RuntimeError, ValueError):  # not the main thread, or no such API
            pass
    return handled


async def _unless(aw: Any, stopping: Any) -> None:
    """Await ``aw`` unless ``stopping`` is set first (then ``aw`` is cancelled)."""
    import asyncio

    task = asyncio.ensure_future(aw)
    stop = asyncio.ensure_future(stopping.wait())
    done, _ = await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
    stop.cancel()
    if task in done:
        task.result()
        return
    task.cancel()
    with contextlib_suppress():
        await task


def contextlib_suppress() -> Any:
    import asyncio
    import contextlib

    return contextlib.suppress(asyncio.CancelledError, Exception)
