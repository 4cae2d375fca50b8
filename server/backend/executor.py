"""Where verification jobs run: worker processes on this machine, the place-recognition thread, or Ray.

A query's verification (:class:`~hivemap.server.placerec.job.QueryJob`, its slices of the maps as arrays)
is the back-end's heavy work and pure Python + NumPy, so threads would share one core (the GIL): it runs
in a pool of processes (``local``, sized by ``workers``: default the cores less one for the event loop,
at least one), as a Ray task on a Ray cluster (``ray``, the optional ``hivemap[cluster]`` extra), or in
the place-recognition thread itself (``thread``: no processes, one core). The results come back to the
event loop, which applies them as before. Other pure jobs of the back-end (a loop's weld,
:mod:`.weld`) go the same way through :meth:`Verifier.call`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol, TypeVar

from hivemap.server.placerec.job import QueryJob
from hivemap.server.placerec.types import CandidateReport
from hivemap.server.placerec.verify import run_job

logger = logging.getLogger(__name__)

EXECUTORS = ("local", "thread", "ray")

T = TypeVar("T")


def default_workers() -> int:
    """The cores this process may use, less one for the event loop; at least one."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, n - 1)


class Verifier(Protocol):
    workers: int

    async def run(self, job: QueryJob) -> list[CandidateReport]: ...

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` where the verification jobs run (``fn`` a module-level function, picklable)."""
        ...

    def shutdown(self) -> None: ...


def _warm() -> int:
    """Run once in each worker at start, so that the first query does not pay for the imports."""
    return os.getpid()


class ThreadVerifier:
    """Jobs in the given thread pool (the place-recognition thread): one at a time, no processes."""

    def __init__(self, pool: concurrent.futures.Executor) -> None:
        self.workers = 1
        self._pool = pool

    async def run(self, job: QueryJob) -> list[CandidateReport]:
        return await self.call(run_job, job)

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def shutdown(self) -> None:  # the pool is the back-end's
        pass


class ProcessVerifier:
    """Jobs in a pool of ``workers`` processes (spawned: the server's threads are not forked)."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool = self._start()

    def _start(self) -> concurrent.futures.ProcessPoolExecutor:
        ctx = multiprocessing.get_context("spawn")
        pool = concurrent.futures.ProcessPoolExecutor(self.workers, mp_context=ctx)
        for _ in range(self.workers):
            pool.submit(_warm)
        return pool

    async def run(self, job: QueryJob) -> list[CandidateReport]:
        return await self.call(run_job, job)

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        try:
            return await asyncio.wrap_future(self._pool.submit(fn, *args))
        except BrokenProcessPool:
            # a worker died (killed, out of memory): this job fails, the next ones get a new pool
            logger.error("a verification worker died: restarting the pool")
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._start()
            raise

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


class RayVerifier:
    """Jobs as Ray tasks: on the cluster at ``address`` (``""``: start a local Ray instance), up to
    ``workers`` at once."""

    def __init__(self, workers: int, address: str = "") -> None:
        try:
            import ray
        except ImportError as exc:
            raise RuntimeError("executor 'ray' needs Ray: pip install 'hivemap[cluster]'") from exc
        self._ray = ray
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"address": address} if address else {"num_cpus": workers}
            ray.init(**kwargs, include_dashboard=False, logging_level=logging.WARNING)
        self.workers = workers
        self._tasks: dict[Callable[..., Any], Any] = {}

    async def run(self, job: QueryJob) -> list[CandidateReport]:
        return await self.call(run_job, job)

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        task = self._tasks.get(fn)
        if task is None:
            task = self._tasks[fn] = self._ray.remote(num_cpus=1)(fn)
        result: T = await task.remote(*args)
        return result

    def shutdown(self) -> None:
        pass  # Ray stays up for the process (tests share one instance); ray.shutdown() ends it


def make_verifier(
    executor: str, workers: int, ray_address: str, thread_pool: concurrent.futures.Executor
) -> Verifier:
    """The verifier for ``executor`` (one of :data:`EXECUTORS`); ``workers`` 0: :func:`default_workers`."""
    n = workers if workers > 0 else default_workers()
    if executor == "local":
        return ProcessVerifier(n)
    if executor == "thread":
        return ThreadVerifier(thread_pool)
    if executor == "ray":
        return RayVerifier(n, ray_address)
    raise ValueError(f"unknown executor {executor!r} (one of {', '.join(EXECUTORS)})")
