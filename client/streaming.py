"""Streaming agent: a dataset replayed through ``hivemap.client.Agent`` connected to a server.

The replay is the offline one (``hivemap.client.replay.Replay``); the agent's link streams every
front-end event and applies the server's corrections (see :mod:`hivemap.client.agent`).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hivemap.client.outputs import write_outputs
from hivemap.client.replay import Replay
from hivemap.client.runner import RunnerOptions, RunSummary

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
    """Replay a dataset as an agent streaming to a server.

    Same processing and outputs as :func:`~hivemap.client.runner.run_offline`; in addition every
    front-end event becomes a protocol message (``map_points`` before the ``keyframe`` that references
    them, the fix used at that keyframe attached; ``pose_updates`` after local BA), durably queued in
    ``out/outbox.sqlite`` and streamed; server ``correction`` messages become co-location factors of the
    second stage. After the last frame the agent waits for the server's acks and last corrections.

    SIGTERM (docker stop, systemd) and SIGINT end the replay between frames: what was produced is in
    the outbox (durable) and goes out at the next start; the summary's ``stopped_by`` names the signal.
    Raises :class:`StreamFailed` when the server refused the agent or could not be reached.
    """
    import asyncio

    return asyncio.run(
        _stream(agent_dir, out_dir, server, agent_id, token, options, frontend_options, second_stage_options)
    )


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

    # The event loop only turns signals into ``stopping`` (installed first, so a signal during the set-up
    # is handled too); the replay runs in a worker thread, which copies this context's agent tag.
    stopping = threading.Event()
    stopped_by: list[str] = []
    loop = asyncio.get_running_loop()
    signals = _on_stop_signals(loop, stopping, stopped_by)
    try:
        return await asyncio.to_thread(
            _replay, agent_dir, Path(out_dir), server, agent_id, token, options or RunnerOptions(),
            frontend_options, second_stage_options, stopping, stopped_by,
        )  # fmt: skip
    finally:
        for sig in signals:
            loop.remove_signal_handler(sig)


def _replay(
    agent_dir: DatasetSource,
    out: Path,
    server: str,
    agent_id: str | None,
    token: str,
    options: RunnerOptions,
    frontend_options: object | None,
    second_stage_options: object | None,
    stopping: threading.Event,
    stopped_by: list[str],
) -> RunSummary:
    import time

    from hivemap.client.link import LinkFailed, LinkRefused
    from hivemap.client.logtags import tag_agent

    out.mkdir(parents=True, exist_ok=True)
    replay = Replay.open(agent_dir, options, frontend_options, second_stage_options, agent_id)
    live = replay.live
    aid = str(live.agent_id)
    tag_agent(aid)  # this thread's log lines (and the link's) say which agent speaks
    outbox = out / "outbox.sqlite"
    live.connect(server, token, out)
    wall0 = time.perf_counter()
    try:
        n_frames = replay.feed(stop=lambda: stopping.is_set() or live.link_failed)
        # a failed link ends the run at once: nothing more can be sent now
        unsent = live.close(stop=stopping if not live.link_failed else _set())
    except BaseException:
        unsent = live.close(stop=_set())
        log.error("agent %s failed; %d messages unsent in %s (kept for the next start)", aid, unsent, outbox)
        raise
    err = live.link_error
    if isinstance(err, LinkRefused | LinkFailed):
        raise StreamFailed(str(err), unsent, outbox) from err
    if err is not None:
        log.error("agent %s: link failed; %d messages unsent in %s (kept for the next start)", aid, unsent,
                  outbox)  # fmt: skip
        raise err
    summary = replay.summary()
    summary.stopped_by = stopped_by[0] if stopped_by else ""
    summary.unsent = unsent
    summary.wall_s = time.perf_counter() - wall0
    write_outputs(live.core, out, summary, n_frames)
    summary.outputs["outbox"] = str(outbox)
    (out / "run.json").write_text(summary.to_json())
    stats = live.link_stats
    log.info(
        "agent %s streamed: %d keyframes, %d corrections applied, up %d B, down %d B, %d poses refused",
        aid, summary.keyframes, live.core.corrections_applied, stats.bytes_up, stats.bytes_down,
        live.core.corrections_refused,
    )  # fmt: skip
    return summary


def _set() -> threading.Event:
    ev = threading.Event()
    ev.set()
    return ev


class StreamFailed(RuntimeError):
    """The link ended the run (refused, or gave up reconnecting); ``unsent`` messages stay in ``outbox``."""

    def __init__(self, message: str, unsent: int, outbox: Path) -> None:
        super().__init__(message)
        self.unsent = unsent
        self.outbox = outbox


def _on_stop_signals(loop: Any, stopping: threading.Event, stopped_by: list[str]) -> list[int]:
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
