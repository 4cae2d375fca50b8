"""The single SQLite writer thread: group commit, then acknowledge.

Every store operation runs in this one thread (SQLite connections are single-threaded), in submission order.
Operations submitted while a commit is in progress are committed together in the next batch, so under load
one commit (one fsync) covers many messages. ``done`` callbacks run on the event loop only AFTER the commit
that made their operation durable: that is where the server sends its acks.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

logger = logging.getLogger(__name__)

S = TypeVar("S")
T = TypeVar("T")

Op = Callable[[S], Any]
Done = Callable[[BaseException | None], None]

_STOP = object()


class StoreWriter(Generic[S]):
    """Runs ``op(store)`` calls in a dedicated thread; commits in batches; reports back on the loop.

    ``open_store`` runs in the thread and returns the store; the store needs ``commit()``, ``rollback()`` and
    ``close()``. ``min_commit_interval`` spaces commits (seconds) so a steady trickle still batches.
    """

    def __init__(
        self,
        open_store: Callable[[], S],
        loop: asyncio.AbstractEventLoop,
        min_commit_interval: float = 0.005,
        max_batch: int = 2000,
    ) -> None:
        self._open_store = open_store
        self._loop = loop
        self._interval = min_commit_interval
        self._max_batch = max_batch
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="hivemap-store-writer", daemon=True)
        self._opened: asyncio.Future[None] = loop.create_future()
        self.store: S | None = None
        self.commits = 0
        self.ops = 0
        self.commit_seconds = 0.0
        self.failed = False

    async def start(self) -> S:
        self._thread.start()
        await self._opened
        assert self.store is not None
        return self.store

    def submit(self, op: Op[S] | None, done: Done | None = None) -> None:
        """Queue ``op`` (None = nothing to write); ``done(exc)`` runs on the loop after the commit."""
        self._queue.put((op, done))

    async def call(self, fn: Callable[[S], T]) -> T:
        """Run ``fn(store)`` in the writer thread and return its result once it is committed."""
        fut: asyncio.Future[T] = self._loop.create_future()
        box: list[T] = []

        def op(store: S) -> None:
            box.append(fn(store))

        def done(exc: BaseException | None) -> None:
            if fut.done():
                return
            if exc is not None:
                fut.set_exception(exc)
            elif box:
                fut.set_result(box[0])
            else:  # the op never ran (the commit failed first)
                fut.set_exception(RuntimeError("store operation did not run"))

        self.submit(op, done)
        return await fut

    async def flush(self) -> None:
        """Wait until everything submitted so far is committed."""
        await self.call(lambda store: None)

    async def stop(self) -> None:
        self._queue.put(_STOP)
        await asyncio.to_thread(self._thread.join)

    # -- thread side -------------------------------------------------------------------------------
    def _notify(self, dones: list[tuple[Done, BaseException | None]]) -> None:
        for done, exc in dones:
            try:
                done(exc)
            except Exception:  # a callback must never kill the loop
                logger.exception("store callback failed")

    def _run(self) -> None:
        try:
            self.store = self._open_store()
        except BaseException as exc:  # report the failure to start()
            self._loop.call_soon_threadsafe(self._opened.set_exception, exc)
            return
        self._loop.call_soon_threadsafe(self._opened.set_result, None)
        store = self.store
        last_commit = 0.0
        stopping = False
        while not stopping:
            item = self._queue.get()
            if item is _STOP:
                break
            batch: list[tuple[Done | None, BaseException | None]] = []
            self._execute(store, item, batch)
            deadline = last_commit + self._interval
            while len(batch) < self._max_batch:
                try:
                    timeout = deadline - time.monotonic()
                    item = self._queue.get(timeout=timeout) if timeout > 0 else self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is _STOP:
                    stopping = True
                    break
                self._execute(store, item, batch)
            t0 = time.monotonic()
            commit_exc: BaseException | None = None
            try:
                if self.failed:  # an operation of this batch failed: none of the batch is kept
                    raise next((e for _, e in batch if e is not None), RuntimeError("store failed"))
                store.commit()  # type: ignore[attr-defined]
            except Exception as exc:  # disk full, I/O error: nothing in this batch is durable
                logger.exception("commit failed")
                commit_exc = exc
                self.failed = True
                try:
                    store.rollback()  # type: ignore[attr-defined]
                except Exception:
                    logger.exception("rollback failed")
            last_commit = time.monotonic()
            self.commit_seconds += last_commit - t0
            self.commits += 1
            dones = [(d, commit_exc or e) for d, e in batch if d is not None]
            if dones:
                # RuntimeError: the loop is gone (shutdown): nobody is waiting any more.
                with contextlib.suppress(RuntimeError):
                    self._loop.call_soon_threadsafe(self._notify, dones)
        try:
            store.commit()  # type: ignore[attr-defined]
            store.close()  # type: ignore[attr-defined]
        except Exception:
            logger.exception("closing the store failed")

    def _execute(self, store: S, item: tuple[Op[S] | None, Done | None], batch: list[Any]) -> None:
        op, done = item
        exc: BaseException | None = None
        if self.failed:
            # Fail-stop: after any failure nothing more is written, so the stored last seq of an agent can
            # never move past a message that is not on disk. Agents keep their messages (the error is
            # transient for them) and resend after the server restarts and reloads the consistent store.
            batch.append((done, RuntimeError("the store failed earlier; restart the server")))
            return
        if op is not None:
            try:
                op(store)
            except Exception as e:
                logger.exception("store operation failed: the batch is rolled back and the store stops")
                exc = e
                self.failed = True
            self.ops += 1
        batch.append((done, exc))
