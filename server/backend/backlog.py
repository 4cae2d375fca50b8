"""The place-recognition queue: which waiting keyframe is queried next, and which need not be.

Verification runs as fast as the CPU allows (no budget: a fixed rate made the server fall behind a team
it could have kept up with). While the queue is short, keyframes are queried oldest first. When it
builds up (more than ``backlog`` waiting), the newest is queried first, as the agents are there now and
a detection of a place they left long ago helps least, and the same agent's waiting keyframes that
share map points with it are skipped: their place is the one being queried.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator

KfKey = tuple[str, int]


class QueryQueue:
    """Waiting query keyframes with their arrival times; ``queue_max`` bounds it (oldest dropped)."""

    def __init__(self, queue_max: int, backlog: int) -> None:
        self._keys: deque[KfKey] = deque()
        self.arrived: dict[KfKey, float] = {}
        self.queue_max = max(1, int(queue_max))
        self.backlog = int(backlog)
        self.dropped = 0  # pushed out of the full queue
        self.skipped = 0  # not queried: the same agent's covisible keyframe was queried in a backlog

    def __len__(self) -> int:
        return len(self._keys)

    def __bool__(self) -> bool:
        return bool(self._keys)

    def __iter__(self) -> Iterator[KfKey]:
        return iter(self._keys)

    def push(self, key: KfKey) -> KfKey | None:
        """Queue ``key``; returns the keyframe dropped to make room, if any."""
        dropped = None
        if len(self._keys) >= self.queue_max:
            dropped = self._keys.popleft()
            self.arrived.pop(dropped, None)
            self.dropped += 1
        self._keys.append(key)
        self.arrived[key] = time.monotonic()
        return dropped

    def pop(self, covisible: Callable[[KfKey], Iterable[KfKey]]) -> tuple[KfKey, list[KfKey]]:
        """The next keyframe to query and the waiting ones skipped for it (``covisible(key)``: the
        keyframes sharing map points with ``key``)."""
        if self.backlog <= 0 or len(self._keys) <= self.backlog:
            return self._keys.popleft(), []
        key = self._keys.pop()
        near = set(covisible(key))
        skip = [k for k in self._keys if k[0] == key[0] and k in near]
        if skip:
            gone = set(skip)
            self._keys = deque(k for k in self._keys if k not in gone)
            for k in skip:
                self.arrived.pop(k, None)
            self.skipped += len(skip)
        return key, skip

    def done(self, key: KfKey) -> float:
        """Seconds from ``key``'s arrival to now (its query done)."""
        now = time.monotonic()
        return now - self.arrived.pop(key, now)
