"""After the last frame: wait for the corrections the server still owes, watching its ``/health``, then
take the server's final estimate of every keyframe.

The server's loop closures can come long after an agent's last keyframe (a server behind its team
looks them up minutes later), so a finishing agent waits until the server's back-end has caught up with
what the team had sent when the agent finished (see ``RunnerOptions.corrections_*``). A correction
carries only every ``stride``-th keyframe and the moved ones (it bounds the downlink), so at the end the
agent reads all of them once (``/agents/{id}/trajectory``) and fuses them as its last correction.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from hivemap.client.agent import Agent
    from hivemap.client.runner import RunnerOptions

F64 = NDArray[np.float64]

log = logging.getLogger(__name__)


def health_url(server: str) -> str:
    """The server's ``/health`` address from its WebSocket address (``ws://HOST:PORT/ws``)."""
    return rest_url(server, "/health")


def rest_url(server: str, route: str, query: str = "") -> str:
    """The address of the server's REST ``route`` (e.g. ``/health``) from its WebSocket address."""
    from urllib.parse import urlsplit, urlunsplit

    u = urlsplit(server)
    scheme = {"ws": "http", "wss": "https", "http": "http", "https": "https"}.get(u.scheme)
    if scheme is None or not u.netloc:
        raise ValueError(f"server address {server!r} is not ws://HOST:PORT/ws")
    path = u.path[: -len("/ws")] if u.path.endswith("/ws") else u.path.rstrip("/")
    return urlunsplit((scheme, u.netloc, path + route, query, ""))


def fetch_trajectory(server: str, agent_id: str, session: int, frame: str) -> tuple[NDArray[np.int64], F64]:
    """The server's current pose of every keyframe of the agent's ``session`` (``frame``: "local" or
    "global"): keyframe ids and world_from_cam (K, 4, 4). Raises ``OSError`` when the server does not
    answer, ``ValueError`` when the answer is not a trajectory."""
    import urllib.request
    from urllib.parse import quote, urlencode

    from hivemap.maps.geometry import rotmat_from_quat_wxyz, se3

    url = rest_url(server, f"/agents/{quote(agent_id, safe='')}/trajectory",
                   urlencode({"frame": frame, "format": "json", "session": session}))  # fmt: skip
    with urllib.request.urlopen(url, timeout=30.0) as r:  # noqa: S310 (http(s) only, see rest_url)
        body = json.loads(r.read())
    try:
        poses = body["poses"]
        ids = np.array([int(p["kf_id"]) for p in poses], dtype=np.int64)
        T = np.array([se3(rotmat_from_quat_wxyz(np.asarray(p["quat_wxyz"], dtype=np.float64)), p["position"])
                      for p in poses]).reshape(-1, 4, 4)  # fmt: skip
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{url}: not a trajectory ({exc})") from exc
    return ids, T


def adopt_final_estimate(server: str, agent: Agent) -> int:
    """Fuse the server's pose of every keyframe of each session it corrected as that session's last
    correction (:meth:`Agent.apply_snapshot`); returns the keyframes fused. A server that does not answer
    leaves the agent with its last corrections, and says so."""
    total = 0
    for session in sorted(agent.corrected_sessions()):
        frame = agent.snapshot_frame(session)
        try:
            ids, poses = fetch_trajectory(server, agent.agent_id, session, frame)
        except (OSError, ValueError) as exc:
            log.warning("server's final estimate of session %d not read (%s): the last corrections stand",
                        session, exc)  # fmt: skip
            continue
        n = agent.apply_snapshot(session, ids, poses)
        log.info("server's final estimate of session %d: %d of %d keyframes fused", session, n, len(ids))
        total += n
    return total


def backend_state(url: str) -> dict[str, Any] | None:
    """The server's back-end fields of ``/health``: ``idle`` (bool), and from servers that report them
    ``arrived``, ``done`` (ints) and ``optimising`` (bool). None: the server reports no back-end state
    (no back-end, or an older server).

    Raises ``OSError`` when the server does not answer (the caller retries)."""
    import urllib.request

    with urllib.request.urlopen(url, timeout=5.0) as r:  # noqa: S310 (http(s) only, see health_url)
        try:
            h = json.loads(r.read())
            idle = h.get("backend_idle")
        except (ValueError, AttributeError) as exc:
            log.warning("server health %s unreadable: %s", url, exc)
            return None
    if not isinstance(idle, bool):
        return None
    state: dict[str, Any] = {"idle": idle}
    arrived, done, busy = h.get("backend_arrived"), h.get("backend_done"), h.get("backend_optimising")
    if isinstance(arrived, int) and isinstance(done, int) and isinstance(busy, bool):
        state.update(arrived=arrived, done=done, optimising=busy)
    return state


def wait_for_server(
    server: str,
    options: RunnerOptions,
    last_correction: Callable[[], float],
    apply_pending: Callable[[], object],
    stop: threading.Event | None = None,
) -> bool:
    """Poll the server's health until it has caught up with this agent's end, applying the corrections
    that arrive meanwhile, then ``corrections_grace_s`` more after the last correction. True when the
    wait ended because the back-end said it was through (not by a timer, a stall or ``stop``).

    Caught up: the back-end is through with every keyframe that had reached it when the wait began (this
    agent's last ones and the team's up to then) and runs no optimisation, or it is idle, twice in a row.
    The team's later keyframes may correct this agent too, but that is the team's next information, not
    what this agent's mission saw. The wait ends early when the server makes no progress (no keyframe
    done, no correction) for ``corrections_stall_s``, and after ``corrections_max_wait_s`` in any case.
    A server that reports no back-end state, or does not answer ``health_max_failures`` polls in a row:
    until no correction came for ``corrections_quiet_s``. ``stop`` (set by a signal) ends the wait."""
    stop = stop or threading.Event()
    t_end = time.monotonic()
    url = health_url(server)
    ready_polls, use_health, failures = 0, True, 0
    mark: int | None = None  # the back-end's arrivals when the wait began
    done_seen, t_progress = -1, t_end
    if options.corrections_max_wait_s <= 0:
        apply_pending()
        return False
    through = False
    while time.monotonic() - t_end < options.corrections_max_wait_s:
        if stop.wait(0.5):
            return False
        apply_pending()
        now = time.monotonic()
        quiet = now - max(last_correction(), t_end)
        if use_health:
            try:
                state = backend_state(url)
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
            if state is None:
                log.warning("server reports no back-end state: waiting until %.0f s without corrections",
                            options.corrections_quiet_s)  # fmt: skip
                use_health = False
                continue
            ready = state["idle"]
            if "done" in state:
                if mark is None:
                    mark = state["arrived"]
                ready = ready or (state["done"] >= mark and not state["optimising"])
                if state["done"] > done_seen:
                    done_seen, t_progress = state["done"], now
            ready_polls = ready_polls + 1 if ready else 0
            # ready twice in a row, and the last correction has had time to arrive
            if ready_polls >= 2 and quiet >= options.corrections_grace_s:
                through = True
                break
            if now - max(t_progress, last_correction()) >= options.corrections_stall_s:
                log.warning("server made no progress for %.0f s: stopping", options.corrections_stall_s)
                break
        elif quiet >= options.corrections_quiet_s:
            break
    else:
        log.warning("server still busy %.0f s after the last frame: stopping", options.corrections_max_wait_s)
    apply_pending()
    return through
