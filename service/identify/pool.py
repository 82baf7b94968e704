"""One pool of identification processes shared by the spindles of one instance (docs/design/fleet.md).

``IdentificationWorker`` (``service.identify.worker``) is one process per spindle: 105–170 MiB each, the
largest part of a spindle's memory. An instance hosting many spindles instead starts ``WorkerPool(workers=K)``
(K = the cores it may use) and gives each spindle a ``lease()``: a ``PooledWorker`` with the interface the
shell drives (``service.shell.service.Worker``), so the shell does not know which it has.

- **Models.** Each process loads a reduced model the first time a job needs it, keyed by its ``ModelRef``
  (spindles of the same geometry share one), and keeps it.
- **Fairness.** A job waits for a free process on an ``asyncio.Semaphore``, which wakes waiters in arrival
  order; each spindle runs at most one job at a time (its shell awaits each), so when a whole cell changes
  speed at once the spindles' jobs run in the order they asked, none twice before another once.
- **Cancellation.** A shared array has one slot per lease holding the job id to cancel; a job checks its own
  slot at every batch evaluation of the reduced model (``CancellableModel``).
- **A hung job** (no stop within the grace after a cancel or its timeout) has the pool's processes
  terminated and the pool recreated: the jobs then in flight on the other processes (at most K − 1, of
  other spindles) end as failed ("worker process died") and run again at their next trigger; the spindles
  themselves go on. Each lease counts the restarts it caused or met.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from service.identify.worker import (
    WORKER_NICE,
    JobOutcome,
    JobRequest,
    WorkerError,
    run_job,
    single_threaded_children,
    supervise_job,
    terminate_pool,
    watch_parent,
)
from service.modelload import LoadedModel, ModelRef, load_model

if TYPE_CHECKING:
    from multiprocessing.sharedctypes import SynchronizedArray

__all__ = ["PooledWorker", "WorkerPool"]

MAX_LEASES = 4096  # slots of the shared cancel array (spindles of one instance)

# --- inside a pool process --------------------------------------------------------------------------
_MODELS: dict[ModelRef, LoadedModel] = {}
_CANCELS: SynchronizedArray[int] | None = None


def _init_pool_process(cancels: SynchronizedArray[int], parent_pid: int, nice: int) -> None:
    global _CANCELS
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    watch_parent(parent_pid)
    if nice > 0:
        with contextlib.suppress(OSError):
            os.nice(nice)
    _CANCELS = cancels


def _model(ref: ModelRef) -> LoadedModel:
    model = _MODELS.get(ref)
    if model is None:
        model = _MODELS[ref] = load_model(ref)
    return model


def _load(ref: ModelRef) -> str:
    return _model(ref).version


def _run_pooled(ref: ModelRef, slot: int, req: JobRequest) -> JobOutcome:
    cancels = _CANCELS

    def should_stop() -> bool:
        return cancels is not None and cancels[slot] == req.job_id

    return run_job(_model(ref), req, should_stop=should_stop)


# --- in the service process -------------------------------------------------------------------------
@dataclass(eq=False, kw_only=True)
class PooledWorker:
    """One spindle's share of a ``WorkerPool``: the ``Worker`` interface of the shell."""

    pool: WorkerPool
    ref: ModelRef
    slot: int
    timeout_s: float
    model_version: str | None = None
    restarts: int = 0
    running_job: int | None = None
    _closed: bool = field(default=False, repr=False)

    async def start(self) -> str:
        """Load this spindle's model in a pool process (once per process and geometry)."""
        self.model_version = await self.pool.load(self.ref)
        return self.model_version

    async def run(self, req: JobRequest) -> JobOutcome:
        if self._closed:
            raise WorkerError("this spindle's identification worker is closed")
        self.running_job = req.job_id
        try:
            return await self.pool.run(self, req)
        finally:
            self.running_job = None

    def cancel(self, job_id: int) -> None:
        self.pool.cancel(self.slot, job_id)

    def close(self) -> None:
        """This spindle stops using the pool (the pool itself is closed by its owner)."""
        self._closed = True

    def pids(self) -> list[int]:
        return self.pool.pids()


class WorkerPool:
    """``workers`` identification processes for the spindles of an instance; ``lease(ref)`` per spindle."""

    def __init__(
        self,
        *,
        workers: int,
        context: str = "spawn",
        cancel_grace_s: float = 5.0,
        nice: int = WORKER_NICE,
    ) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self.cancel_grace_s = cancel_grace_s
        self.nice = nice
        self._ctx = multiprocessing.get_context(context)
        self._cancels: SynchronizedArray[int] = self._ctx.Array("q", [-1] * MAX_LEASES)
        self._pool: cf.ProcessPoolExecutor | None = None
        self._free: asyncio.Semaphore | None = None
        self._leases: list[PooledWorker] = []
        self._closed = False
        self.restarts = 0
        self.jobs_run = 0
        self.waited_s = 0.0  # summed time jobs waited for a free process

    def lease(self, ref: ModelRef, *, timeout_s: float = 120.0) -> PooledWorker:
        """A spindle's worker on this pool (``WorkerError`` when closed or out of slots)."""
        if self._closed:
            raise WorkerError("the identification pool is closed")
        if len(self._leases) >= MAX_LEASES:
            raise WorkerError(f"the identification pool serves at most {MAX_LEASES} spindles")
        lease = PooledWorker(pool=self, ref=ref, slot=len(self._leases), timeout_s=timeout_s)
        self._leases.append(lease)
        return lease

    def _executor(self) -> cf.ProcessPoolExecutor:
        if self._closed:
            raise WorkerError("the identification pool is closed")
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=self._ctx,
                initializer=_init_pool_process,
                initargs=(self._cancels, os.getpid(), self.nice),
            )
        return self._pool

    def _semaphore(self) -> asyncio.Semaphore:
        if self._free is None:
            self._free = asyncio.Semaphore(self.workers)
        return self._free

    async def warm(self, refs: list[ModelRef]) -> None:
        """Start every process and load ``refs`` in each (concurrent loads spread over the processes), so no
        spindle's first identification pays a model load and the memory is taken at start, not mid-shift."""
        loop = asyncio.get_running_loop()
        with single_threaded_children():
            futs = [
                loop.run_in_executor(self._executor(), _load, ref)
                for ref in refs
                for _ in range(self.workers)
            ]
        await asyncio.gather(*futs)

    async def load(self, ref: ModelRef) -> str:
        """Load ``ref`` in a pool process (the others load it at their first job of that geometry)."""
        loop = asyncio.get_running_loop()
        async with self._semaphore():
            with single_threaded_children():
                fut = loop.run_in_executor(self._executor(), _load, ref)
            return await fut

    async def run(self, lease: PooledWorker, req: JobRequest) -> JobOutcome:
        loop = asyncio.get_running_loop()
        asked = time.perf_counter()
        async with self._semaphore():  # FIFO: in the order the spindles asked
            self.waited_s += time.perf_counter() - asked
            try:
                return await supervise_job(
                    lambda: loop.run_in_executor(self._executor(), _run_pooled, lease.ref, lease.slot, req),
                    req.job_id,
                    timeout_s=lease.timeout_s,
                    cancel_grace_s=self.cancel_grace_s,
                    cancel=lambda: self.cancel(lease.slot, req.job_id),
                    discard=lambda: self._discard(lease),
                )
            finally:
                self.jobs_run += 1

    def cancel(self, slot: int, job_id: int) -> None:
        self._cancels[slot] = job_id

    def _discard(self, lease: PooledWorker) -> None:
        """Terminate the pool's processes (a hung job holds one; there is no way to kill only it)."""
        lease.restarts += 1
        pool, self._pool = self._pool, None
        if pool is None:
            return
        self.restarts += 1
        terminate_pool(pool, wait=False)

    def pids(self) -> list[int]:
        procs = getattr(self._pool, "_processes", None) or {}
        return [p.pid for p in list(procs.values()) if p.pid is not None and p.is_alive()]

    def close(self) -> None:
        self._closed = True
        pool, self._pool = self._pool, None
        if pool is not None:
            terminate_pool(pool, wait=True)
