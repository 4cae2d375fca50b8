"""After the last frame: wait for the corrections the server still owes, watching its ``/health``.

The server's loop closures can come long after an agent's last keyframe, so a finishing agent waits
until the server says its back-end is idle (see ``RunnerOptions.corrections_*``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hivemap.client.runner import RunnerOptions

log = logging.getLogger(__name__)


def health_url(server: str) -> str:
    """The server's ``/health`` address from its WebSocket address (``ws://HOST:PORT/ws``)."""
    from urllib.parse import urlsplit, urlunsplit

    u = urlsplit(server)
    scheme = {"ws": "http", "wss": "https", "http": "http", "https": "https"}.get(u.scheme)
    if scheme is None or not u.netloc:
        raise ValueError(f"server address {server!r} is not ws://HOST:PORT/ws")
    path = u.path[: -len("/ws")] if u.path.endswith("/ws") else u.path.rstrip("/")
    return urlunsplit((scheme, u.netloc, path + "/health", "", ""))


def backend_idle(url: str) -> bool | None:
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


def wait_for_server(
    server: str,
    options: RunnerOptions,
    last_correction: Callable[[], float],
    apply_pending: Callable[[], object],
    stop: threading.Event | None = None,
) -> None:
    """Poll the server's health until its back-end is idle twice in a row and ``corrections_grace_s``
    passed since the last correction (``last_correction()``: its ``time.monotonic()``), applying the
    corrections that arrive meanwhile; at most ``corrections_max_wait_s``. A server that reports no
    back-end state, or does not answer ``health_max_failures`` polls in a row: until no correction came
    for ``corrections_quiet_s``. ``stop`` (set by a signal) ends the wait at once."""
    stop = stop or threading.Event()
    t_end = time.monotonic()
    url = health_url(server)
    idle_polls, use_health, failures = 0, True, 0
    if options.corrections_max_wait_s <= 0:
        apply_pending()
        return
    while time.monotonic() - t_end < options.corrections_max_wait_s:
        if stop.wait(0.5):
            return
        apply_pending()
        quiet = time.monotonic() - max(last_correction(), t_end)
        if use_health:
            try:
                idle = backend_idle(url)
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
