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
from hivemap.server.placerec.shipping import Shipper, run_shipped
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
    """Run once in each process at start: a pool spawns its process at the first job, and the process
    imports the back-end (the initializer's module) then, so the first query or solve does not wait."""
    return os.getpid()


def _exit_with_parent(parent: int, period_s: float) -> None:
    """Worker initializer: end this worker once the server that spawned it is gone. A killed server
    (SIGKILL, out of memory) cannot shut its pools down, and its spawned workers would otherwise wait
    on their queues for ever, holding their memory."""
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        os._exit(1)

    threading.Thread(target=watch, name="hive-parent-watch", daemon=True).start()


def spawn_pool(period_s: float = 1.0) -> concurrent.futures.ProcessPoolExecutor:
    """A one-process pool, spawned (the server's threads are not forked), whose worker ends when the
    server process does (:func:`_exit_with_parent`)."""
    return concurrent.futures.ProcessPoolExecutor(
        1,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_exit_with_parent,
        initargs=(os.getpid(), period_s),
    )


class SolverProcess:
    """One solver's process (a gtsam or pycolmap solve holds the GIL for its whole length, which would
    stop the event loop): a :func:`spawn_pool` started by :meth:`start` (or else by the first job) and
    replaced after its process died; :meth:`stop` ends a job still running, since 3.11 has no
    ``terminate_workers`` and a running job would hold the server's exit until it ends."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._running = 0  # jobs submitted and not ended (the pose graph and the covariances share one)

    def start(self) -> None:
        """Spawn the process now (with its imports), ahead of the first job."""
        if self._pool is None:
            self._pool = spawn_pool()
            self._pool.submit(_warm)

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        self.start()
        assert self._pool is not None
        self._running += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)
        except BrokenProcessPool:
            logger.error("%s process died: restarting it", self.name)
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            raise
        finally:
            self._running -= 1

    def stop(self) -> None:
        if self._pool is None:
            return
        for proc in list(getattr(self._pool, "_processes", {}).values()) if self._running else []:
            proc.terminate()
        self._pool.shutdown(wait=False, cancel_futures=True)


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
    """Jobs in ``workers`` processes (spawned: the server's threads are not forked), each its own
    single-process pool, so a job goes to a known worker: the one with the fewest jobs in flight. Each
    worker keeps the features of the last ``keyframe_cache`` keyframes it was sent
    (:mod:`~hivemap.server.placerec.shipping`); 0 ships every job whole."""

    def __init__(self, workers: int, keyframe_cache: int = 0) -> None:
        self.workers = workers
        self._cache = keyframe_cache
        self._pools = [self._start() for _ in range(workers)]
        self._shippers = [Shipper(keyframe_cache) for _ in range(workers)]
        self._inflight = [0] * workers

    @staticmethod
    def _start() -> concurrent.futures.ProcessPoolExecutor:
        pool = spawn_pool()
        pool.submit(_warm)
        return pool

    async def run(self, job: QueryJob) -> list[CandidateReport]:
        if self._cache <= 0:
            return await self.call(run_job, job)
        i = self._pick()
        # packed on the event loop right before the submit, so the worker sees jobs in packing order
        shipped = self._shippers[i].pack(job)
        try:
            return await self._submit(i, run_shipped, shipped, self._cache)
        except Exception:
            # a job that failed in the worker may have left its cache out of step with the mirror
            self._shippers[i].reset()
            raise

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        return await self._submit(self._pick(), fn, *args)

    def _pick(self) -> int:
        return min(range(self.workers), key=self._inflight.__getitem__)

    async def _submit(self, i: int, fn: Callable[..., T], *args: Any) -> T:
        self._inflight[i] += 1
        try:
            return await asyncio.wrap_future(self._pools[i].submit(fn, *args))
        except BrokenProcessPool:
            # a worker died (killed, out of memory): this job fails, the next ones get a new worker,
            # which holds no keyframes
            logger.error("verification worker %d died: restarting it", i)
            self._pools[i].shutdown(wait=False, cancel_futures=True)
            self._pools[i] = self._start()
            self._shippers[i].reset()
            raise
        finally:
            self._inflight[i] -= 1

    def shutdown(self) -> None:
        for pool in self._pools:
            pool.shutdown(wait=False, cancel_futures=True)


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
    executor: str,
    workers: int,
    ray_address: str,
    thread_pool: concurrent.futures.Executor,
    keyframe_cache: int = 0,
) -> Verifier:
    """The verifier for ``executor`` (one of :data:`EXECUTORS`); ``workers`` 0: :func:`default_workers`;
    ``keyframe_cache``: keyframes whose features each local worker keeps."""
    n = workers if workers > 0 else default_workers()
    if executor == "local":
        return ProcessVerifier(n, keyframe_cache)
    if executor == "thread":
        return ThreadVerifier(thread_pool)
    if executor == "ray":
        return RayVerifier(n, ray_address)
    raise ValueError(f"unknown executor {executor!r} (one of {', '.join(EXECUTORS)})")
