"""Log lines that say which agent speaks, and summaries instead of one INFO line per correction.

Several agents often share one terminal (``make demo``, a compose log) or one process (the experiment
runner's threads): ``tag_agent(agent_id)`` marks the current context (and the tasks and ``to_thread`` calls
started from it, which copy it) so that :class:`AgentTag`, installed on the log handlers by the ``hivemap``
command, prefixes its lines with ``[agent_id]``.
"""

from __future__ import annotations

import contextvars
import logging
import time
from dataclasses import dataclass, field

_AGENT: contextvars.ContextVar[str | None] = contextvars.ContextVar("hivemap_agent", default=None)


def tag_agent(agent_id: str | None) -> None:
    """Log lines from this context on carry ``[agent_id]`` (``None`` removes the tag)."""
    _AGENT.set(agent_id)


class AgentTag(logging.Filter):
    """Sets ``record.agent`` to ``"[id] "`` (or ``""``) for a format with ``%(agent)s``."""

    def filter(self, record: logging.LogRecord) -> bool:
        tag = _AGENT.get()
        record.agent = f"[{tag}] " if tag else ""
        return True


@dataclass
class CorrectionSummary:
    """Counts the corrections an agent applies and logs them at INFO once per ``interval_s`` (each one at
    DEBUG): a mission gets hundreds, most of them without a keyframe of the current session."""

    logger: logging.Logger
    interval_s: float = 10.0
    corrections: int = 0
    keyframes: int = 0
    empty: int = 0
    maps: set[int] = field(default_factory=set)
    _since: float = field(default_factory=time.monotonic)

    def add(self, map_id: int, frame: str, n_keyframes: int) -> None:
        self.logger.debug(
            "correction from map %d (%s frame): %d keyframes fused as co-location factors", map_id, frame,
            n_keyframes,
        )  # fmt: skip
        self.corrections += 1
        self.keyframes += n_keyframes
        self.empty += n_keyframes == 0
        self.maps.add(map_id)
        if time.monotonic() - self._since >= self.interval_s:
            self.flush()

    def flush(self) -> None:
        """Log the counts since the last summary (nothing when there were none)."""
        if self.corrections:
            maps = ", ".join(str(m) for m in sorted(self.maps))
            self.logger.info(
                "%d corrections in %.0f s from map %s: %d keyframes fused as co-location factors "
                "(%d corrections had none of this session's)",
                self.corrections, time.monotonic() - self._since, maps, self.keyframes, self.empty,
            )  # fmt: skip
        self.corrections = self.keyframes = self.empty = 0
        self.maps = set()
        self._since = time.monotonic()
