"""A job's life in a process pool (``supervise_job``, the one copy that ``IdentificationWorker`` and
``WorkerPool`` run): the timeout, a caller's cancel, the grace after either and a broken pool, driven with
plain asyncio futures in place of the pool's (no process, no model)."""

from __future__ import annotations

import asyncio
from concurrent.futures.process import BrokenProcessPool

import pytest

from service.contracts.outcome import Outcome
from service.identify.worker import JobOutcome, supervise_job


class Pool:
    """What ``supervise_job`` sees of a pool: a submit, a cancel and a discard, each counted."""

    def __init__(self, *, stops_when_cancelled: bool, broken: bool = False) -> None:
        self.stops_when_cancelled = stops_when_cancelled
        self.broken = broken
        self.fut: asyncio.Future[JobOutcome] | None = None
        self.cancels = 0
        self.discards = 0

    def submit(self) -> asyncio.Future[JobOutcome]:
        if self.broken:
            raise BrokenProcessPool("a process died")
        self.fut = asyncio.get_running_loop().create_future()
        return self.fut

    def cancel(self) -> None:
        self.cancels += 1
        if self.stops_when_cancelled and self.fut is not None:  # the job stops at its next evaluation
            self.fut.set_result(JobOutcome(job_id=7, status=Outcome.CANCELLED, message="cancelled"))

    def discard(self) -> None:
        self.discards += 1

    async def run(self, *, timeout_s: float = 0.05, grace_s: float = 0.05) -> JobOutcome:
        return await supervise_job(
            self.submit,
            7,
            timeout_s=timeout_s,
            cancel_grace_s=grace_s,
            cancel=self.cancel,
            discard=self.discard,
        )


def test_a_job_done_in_time_is_its_outcome() -> None:
    async def scenario() -> tuple[JobOutcome, Pool]:
        pool = Pool(stops_when_cancelled=True)
        task = asyncio.ensure_future(pool.run(timeout_s=10.0))
        while pool.fut is None:
            await asyncio.sleep(0)
        done = JobOutcome(job_id=7, status=Outcome.OK, message="fit")
        pool.fut.set_result(done)
        assert await task is done
        return done, pool

    _, pool = asyncio.run(scenario())
    assert (pool.cancels, pool.discards) == (0, 0)


@pytest.mark.parametrize("stops", [True, False])
def test_a_job_past_its_timeout_fails_and_one_that_does_not_stop_is_discarded(stops: bool) -> None:
    pool = Pool(stops_when_cancelled=stops)
    out = asyncio.run(pool.run(timeout_s=0.05, grace_s=0.05))
    assert (out.job_id, out.status) == (7, Outcome.FAILED)
    assert out.message == "identification exceeded timeout_s=0 s"
    assert out.wall_s >= 0.05
    assert (pool.cancels, pool.discards) == (1, 0 if stops else 1)


@pytest.mark.parametrize("stops", [True, False])
def test_a_cancelled_caller_stops_the_job_and_is_cancelled(stops: bool) -> None:
    async def scenario(pool: Pool) -> None:
        task = asyncio.ensure_future(pool.run(timeout_s=10.0, grace_s=0.05))
        while pool.fut is None:
            await asyncio.sleep(0)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    pool = Pool(stops_when_cancelled=stops)
    asyncio.run(scenario(pool))
    assert (pool.cancels, pool.discards) == (1, 0 if stops else 1)


def test_a_broken_pool_is_discarded_and_its_job_failed() -> None:
    pool = Pool(stops_when_cancelled=True, broken=True)
    out = asyncio.run(pool.run())
    assert (out.status, out.message) == (Outcome.FAILED, "worker process died: a process died")
    assert (pool.cancels, pool.discards) == (0, 1)


def test_a_pool_that_breaks_after_a_cancel_leaves_no_unretrieved_exception(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Issue 41 (``chtc demo`` stopped during a job): the job's task is cancelled, the worker's pool is then
    terminated and the job's future ends in ``BrokenProcessPool`` with nobody waiting for it; asyncio logged
    ``ERROR Future exception was never retrieved``."""
    import gc

    async def scenario() -> None:
        pool = Pool(stops_when_cancelled=False)
        task = asyncio.ensure_future(pool.run(timeout_s=10.0, grace_s=0.01))
        while pool.fut is None:
            await asyncio.sleep(0)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert pool.fut is not None
        pool.fut.set_exception(BrokenProcessPool("terminated at close"))  # the pool's close
        pool.fut = None
        await asyncio.sleep(0)

    with caplog.at_level("ERROR", logger="asyncio"):
        asyncio.run(scenario())
        gc.collect()
    assert not [r for r in caplog.records if "never retrieved" in r.getMessage()], caplog.text
