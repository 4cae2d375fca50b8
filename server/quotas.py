"""Per-agent quotas: stored map points and keyframes, in total and per second (``[quotas]`` settings).

A message over a quota is refused as a whole (nothing applied) with an ``error`` whose code is ``quota``
(a total: the server will not store more of this agent, so the agent drops the message) or ``rate``
(too fast: transient, the agent keeps the message and resends it after a reconnect backoff). Other
agents are not affected: every count here is per agent.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from hivemap.server.settings import QuotaSettings


@dataclass
class TokenBucket:
    """``rate`` tokens per second up to ``burst``; starts full."""

    rate: float
    burst: float
    tokens: float = 0.0
    stamp: float | None = None  # None: never used (the bucket starts full)

    def take(self, n: int, now: float) -> bool:
        """Take ``n`` tokens if there are that many (nothing taken otherwise)."""
        if self.stamp is None:
            self.tokens, self.stamp = self.burst, now
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        # a single message larger than the whole burst would never pass: it may when the bucket is full
        if n <= self.tokens or self.tokens >= self.burst:
            self.tokens -= n
            return True
        return False


@dataclass
class QuotaExceeded:
    code: str  # "quota" (a total) or "rate"
    limit: str  # the setting's name, e.g. "quotas.max_points"
    message: str


@dataclass
class AgentQuota:
    """The rate buckets of one agent (totals are counted from the agent's maps by the caller)."""

    points: TokenBucket
    keyframes: TokenBucket
    last_event: dict[str, float] = field(default_factory=dict)


class Quotas:
    def __init__(self, settings: QuotaSettings, clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings
        self._clock = clock
        self._agents: dict[str, AgentQuota] = {}
        self.exceeded: dict[str, int] = {}  # per limit, for /metrics-like inspection and tests

    def _of(self, agent_id: str) -> AgentQuota:
        q = self._agents.get(agent_id)
        if q is None:
            s = self.settings
            q = AgentQuota(
                TokenBucket(s.points_per_s, float(s.points_burst)),
                TokenBucket(s.keyframes_per_s, float(s.keyframes_burst)),
            )
            self._agents[agent_id] = q
        return q

    def check(self, agent_id: str, kind: str, n: int, stored: int) -> QuotaExceeded | None:
        """May ``agent_id`` store ``n`` more ``kind`` ("points" or "keyframes"), holding ``stored``?
        Takes the rate tokens when it may."""
        s = self.settings
        total = s.max_points if kind == "points" else s.max_keyframes
        if stored + n > total:
            name = f"quotas.max_{kind}"
            return self._exceeded(
                "quota", name, f"{agent_id} stores {stored} {kind}, {n} more would exceed {name} = {total}"
            )
        q = self._of(agent_id)
        bucket = q.points if kind == "points" else q.keyframes
        if not bucket.take(n, self._clock()):
            name = f"quotas.{kind}_per_s"
            return self._exceeded(
                "rate",
                name,
                f"{agent_id} sends {kind} faster than {name} = {bucket.rate:g} "
                f"(burst {bucket.burst:g}): {n} refused, resend later",
            )
        return None

    def _exceeded(self, code: str, limit: str, message: str) -> QuotaExceeded:
        self.exceeded[limit] = self.exceeded.get(limit, 0) + 1
        return QuotaExceeded(code, limit, message)

    def should_report(self, agent_id: str, limit: str, every_s: float = 1.0) -> bool:
        """At most one /events event per agent and limit per ``every_s``: a flood must not flood the log."""
        q = self._of(agent_id)
        now = self._clock()
        if now - q.last_event.get(limit, -1e18) < every_s:
            return False
        q.last_event[limit] = now
        return True
