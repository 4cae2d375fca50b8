"""A bounded ring buffer of server events (merges, loops, corrections, errors) for ``/events``."""

from __future__ import annotations

import itertools
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

logger = logging.getLogger(__name__)

EVENT_KINDS = ("connect", "disconnect", "refused", "error", "merge", "loop", "correction", "session", "info")


@dataclass(frozen=True)
class Event:
    """One event. ``id`` increases strictly; clients poll ``/events?since=<last id seen>``."""

    id: int
    time: float
    kind: str
    message: str
    agent_id: str | None = None
    map_id: int | None = None
    data: dict[str, Any] = field(default_factory=dict)


class EventLog:
    """Thread-safe enough for the GIL: appends and reads are single deque operations."""

    def __init__(self, capacity: int = 10000) -> None:
        self._events: deque[Event] = deque(maxlen=capacity)
        self._ids = itertools.count(1)
        self.counts: dict[str, int] = {}

    def add(
        self,
        kind: str,
        message: str,
        *,
        agent_id: str | None = None,
        map_id: int | None = None,
        data: dict[str, Any] | None = None,
    ) -> Event:
        event = Event(next(self._ids), time.time(), kind, message, agent_id, map_id, dict(data or {}))
        self._events.append(event)
        self.counts[kind] = self.counts.get(kind, 0) + 1
        logger.debug("event %s: %s", kind, message)
        return event

    def since(self, since: int = 0, kind: str | None = None, limit: int | None = None) -> list[Event]:
        """Events with id > ``since`` (oldest first), optionally of one kind, at most ``limit`` (newest)."""
        out = [e for e in list(self._events) if e.id > since and (kind is None or e.kind == kind)]
        if limit is not None:
            out = out[-limit:] if limit > 0 else []
        return out

    @property
    def last_id(self) -> int:
        return self._events[-1].id if self._events else 0
