"""The place-recognition queue: which waiting keyframe is queried next, and which need not be.

Verification runs as fast as the CPU allows (no budget: a fixed rate made the server fall behind a team
it could have kept up with). Keyframes are queried in arrival order, so each agent's queries come in
increasing keyframe ids, as the consistency check of detections needs (consecutive detections within
``consistency_max_gap`` ids). When the queue builds up (more than ``backlog`` waiting), a keyframe whose
place its agent has just queried is skipped: the agent's last queried keyframe is one of its
``NEIGHBOURS`` best covisible keyframes. That thins each agent's queries to about one in three keyframes,
which keeps consecutive detections of one place well inside the consistency gap.

Each keyframe also gets its arrival number, held until the back-end has finished with it (:meth:`finished`),
so that :meth:`done_through` can tell a finishing agent whether everything that reached the server
before its own last keyframe has been looked up.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator

KfKey = tuple[str, int]

# In a backlog, a keyframe is skipped when its agent's last queried keyframe is among its this many best
# covisible keyframes (ORB-SLAM's covisibility as "the same place").
NEIGHBOURS = 2


class QueryQueue:
    """Waiting query keyframes with their arrival times; ``queue_max`` bounds it (oldest dropped)."""

    def __init__(self, queue_max: int, backlog: int) -> None:
        self._keys: deque[KfKey] = deque()
        self.arrived: dict[KfKey, float] = {}
        self.queue_max = max(1, int(queue_max))
        self.backlog = int(backlog)
        self.dropped = 0  # pushed out of the full queue
        self.skipped = 0  # not queried in a backlog: their agent had just queried their place
        self._last: dict[str, KfKey] = {}  # per agent, its last keyframe taken for a query
        self.n_arrived = 0  # keyframes pushed so far; the n-th has arrival number n
        self._open: dict[KfKey, int] = {}  # arrival numbers of the keyframes not finished yet

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
            self._open.pop(dropped, None)
            self.dropped += 1
        self._keys.append(key)
        self.arrived[key] = time.monotonic()
        self.n_arrived += 1
        self._open.setdefault(key, self.n_arrived)
        return dropped

    def pop(self, best_covisible: Callable[[KfKey, int], Iterable[KfKey]]) -> tuple[KfKey, list[KfKey]]:
        """The next keyframe to query and those skipped before it (``best_covisible(key, n)``: the ``n``
        keyframes sharing most map points with ``key``). The queue must not be empty; the last keyframe
        is never skipped."""
        skipped: list[KfKey] = []
        while True:
            key = self._keys.popleft()
            last = self._last.get(key[0])
            backlog = 0 < self.backlog < len(self._keys) + 1
            if self._keys and backlog and last is not None and last in set(best_covisible(key, NEIGHBOURS)):
                self.arrived.pop(key, None)
                self._open.pop(key, None)
                self.skipped += 1
                skipped.append(key)
                continue
            self._last[key[0]] = key
            return key, skipped

    def done(self, key: KfKey) -> float:
        """Seconds from ``key``'s arrival to now (its query done)."""
        now = time.monotonic()
        return now - self.arrived.pop(key, now)

    def finished(self, key: KfKey) -> None:
        """The back-end is through with ``key``: queried, and what it found merged or added (an
        optimisation it asked for runs on: see ``Backend.optimising``)."""
        self._open.pop(key, None)

    def done_through(self) -> int:
        """The largest n such that the first n arrivals are all finished (skipped and dropped ones
        count as finished)."""
        return min(self._open.values()) - 1 if self._open else self.n_arrived
