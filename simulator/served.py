"""The real soft sensor, served from a virtual-plant run: for the API tests, ``python -m benchmarks api`` and
the fuzzing server.

``served_service(database_url=..., plan=...)`` builds the service as ``service.host.runtime.Runtime`` does
(the real ``ServiceCore`` and ``SoftSensorService``, the model from the ROM cache, a real database through
``open_persistence``: SQLite in a temporary directory in the tests) and runs its asyncio shell on a loop in a
background thread. Only the devices differ: instead of the acquisition polling drivers, :func:`feed` hands it
the samples of a ``model.plant.VirtualPlant`` run (``simulator.plantsamples.samples_from_plant``), and the
identification worker is :class:`InlineWorker` (the shell's ``Worker`` protocol), the worker process's job
function ``service.identify.worker.run_job`` in a thread of this process (no second process, same seeded
result, the same job->outcome mapping), so a fed sample's identification is recorded before :func:`feed`
returns.

Every event enters the service through the shell's public API: :func:`feed` hands samples to ``on_sample``
on the service's loop, the API's requests go through the service's own methods (which hand them over to the
loop); what is served is read from the published ``view``. Everything else here is construction. Time is a
:class:`ManualClock`: :func:`feed` moves it to the sample's time (the acquisition stamps samples with the
service's clock), a test moves it further by hand (stale data) without sleeping.

Errors::

    ServedError(RuntimeError)     the service did not settle (a job held or hanging) or the loop is gone
"""

from __future__ import annotations

import asyncio
import functools
import signal
import sys
import threading
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import TypeVar

from drivers.ringbuffer import Sample
from model.geometry import load_spindle
from model.plant import Segment, VirtualPlant
from service.core.machine import ServiceCore
from service.host.persistence import Persistence, open_persistence
from service.host.runtime import CanDevice, DaqDevice, core_config, growth_server
from service.identify.worker import JobOutcome, JobRequest, run_job
from service.modelload import LoadedModel, ModelRef, load_model
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.errors import SimulatorError
from simulator.plantsamples import samples_from_plant

__all__ = [
    "DEMO_FED",
    "DEMO_PROFILE",
    "InlineWorker",
    "ManualClock",
    "Plan",
    "Served",
    "ServedError",
    "feed",
    "plant_samples",
    "served_service",
]

T = TypeVar("T")

# The paper's two conditions (SPEC §2, Tables 4 and 10) from a cold start. The first DEMO_FED samples (22 min)
# give one identification at each (the first window is identification.schedule_min[0] of the condition's data:
# 7 min by default, 10 min in the API tests); the 30 after them (5 min more at 4000 rpm, before the next
# scheduled identification) are there for a test to feed.
DEMO_PROFILE = (Segment(660.0, 3000.0, 12.0, 23.2), Segment(960.0, 4000.0, 14.0, 21.8))
DEMO_FED = 133
PLAN_T0 = datetime(2026, 11, 22, 7, 0, tzinfo=UTC)


class ServedError(SimulatorError, RuntimeError):
    """The served service did not settle in time, or its loop has stopped."""


class ManualClock:
    """A UTC clock moved by hand (``advance``) or by :func:`feed` (never backwards)."""

    def __init__(self, start: datetime) -> None:
        self.now = start

    def __call__(self) -> datetime:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += timedelta(seconds=seconds)

    def at_least(self, t: datetime) -> None:
        self.now = max(self.now, t)


@dataclass(frozen=True, kw_only=True)
class Plan:
    """A virtual-plant run: its operating profile, noise seed, mesh (m) and UTC start (the first sample)."""

    profile: tuple[Segment, ...] = DEMO_PROFILE
    seed: int = 1
    mesh_size_m: float = 0.004  # coarser than the plant's default, for speed; still finer than the service's
    t0: datetime = PLAN_T0


@functools.cache
def plant_samples(plan: Plan) -> tuple[Sample, ...]:
    """The plan's run as acquisition samples, one per 10 s (computed once per plan and process)."""
    if not plan.profile:
        return ()
    plant = VirtualPlant(load_spindle(), mesh_size_m=plan.mesh_size_m, seed=plan.seed)
    return tuple(samples_from_plant(plant.run(list(plan.profile)), t0_s=plan.t0.timestamp()))


@functools.cache
def _model(ref: ModelRef) -> LoadedModel:
    return load_model(ref)


class InlineWorker:
    """The shell's ``Worker`` (as ``service.identify.worker.IdentificationWorker``), running each job with
    ``run_job`` in a thread of this process.

    ``hold()`` keeps the next jobs waiting before they start (a job "running" for as long as a test needs),
    ``release()`` lets them go; ``loading=True`` keeps the model "loading" (``start()`` waits, and so do jobs,
    as they queue behind the model in the worker process) until ``release_model()``.
    """

    def __init__(self, model: LoadedModel, *, loading: bool = False) -> None:
        self.model = model
        self.model_version: str | None = None
        self.restarts = 0
        self.running_job: int | None = None
        self._go = threading.Event()
        self._go.set()
        self._loaded = threading.Event()
        if not loading:
            self._loaded.set()
        self._cancel = -1

    @property
    def loading(self) -> bool:
        return not self._loaded.is_set()

    def hold(self) -> None:
        self._go.clear()

    def release(self) -> None:
        self._go.set()

    def release_model(self) -> None:
        self._loaded.set()

    async def start(self) -> str:
        await asyncio.to_thread(self._loaded.wait)
        self.model_version = self.model.version
        return self.model_version

    async def run(self, req: JobRequest) -> JobOutcome:
        self.running_job = req.job_id
        try:
            await asyncio.to_thread(self._loaded.wait)
            await asyncio.to_thread(self._go.wait)
            stop = functools.partial(self._cancelled, req.job_id)
            return await asyncio.to_thread(run_job, self.model, req, should_stop=stop)
        finally:
            self.running_job = None

    def _cancelled(self, job_id: int) -> bool:
        return self._cancel == job_id

    def cancel(self, job_id: int) -> None:
        self._cancel = job_id

    def close(self) -> None:
        self._go.set()
        self._loaded.set()


class Served:
    """A running served service: ``service`` (the shell, a ``ChtcService``), its ``clock``, the plan's
    ``samples`` (``fed`` of them so far), the ``worker`` and the database's ``persistence``. ``close()`` at
    the end."""

    def __init__(
        self,
        *,
        service: SoftSensorService,
        clock: ManualClock,
        worker: InlineWorker,
        persistence: Persistence,
        samples: tuple[Sample, ...],
        sources: Mapping[str, DaqDevice | CanDevice] | None = None,
    ) -> None:
        self.service = service
        self.sources = dict(sources or {})
        self.clock = clock
        self.worker = worker
        self.persistence = persistence
        self.samples = samples
        self.fed = 0
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="served-loop", daemon=True)
        self._thread.start()
        self._resident: set[asyncio.Task[object]] = set()  # tasks that live as long as the service
        self._starting: asyncio.Future[None] | None = None
        self._feeders: list[tuple[threading.Event, threading.Thread]] = []

    def call(self, fn: Callable[[], Awaitable[T]], timeout_s: float = 60.0) -> T:
        """Run ``fn()`` (a coroutine) on the service's loop and wait for its result."""

        async def run() -> T:
            return await fn()

        if not self._thread.is_alive():
            raise ServedError("the served service's loop has stopped")
        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(timeout_s)

    def start(self) -> None:
        """Start the shell (worker, health watch) and the database's background retry, as ``Runtime`` does."""

        async def begin() -> None:
            self.persistence.start_background()
            self._starting = asyncio.ensure_future(self.service.start())
            await asyncio.sleep(0)
            self._resident = asyncio.all_tasks() - {asyncio.current_task()}  # settle() ignores the start

        self.call(begin)
        if not self.worker.loading:
            self.started()

    def started(self, timeout_s: float = 60.0) -> None:
        """Wait for ``service.start()`` (after ``worker.release_model()`` when the model was loading)."""

        async def wait() -> None:
            assert self._starting is not None, "start() first"
            await self._starting
            self._resident = asyncio.all_tasks() - {asyncio.current_task()}

        self.worker.release_model()
        self.call(wait, timeout_s)

    def settle(self, timeout_s: float = 60.0) -> None:
        """Wait until every job the service has started is recorded (jobs a finished job starts, too)."""

        async def quiet() -> None:
            me = asyncio.current_task()
            while pending := asyncio.all_tasks() - self._resident - {me}:
                await asyncio.wait(pending)

        try:
            self.call(quiet, timeout_s)
        except TimeoutError as err:
            raise ServedError(f"the service did not settle within {timeout_s:.0f} s (a job held?)") from err

    def feed_next(self, n: int | None = None) -> None:
        """Feed the plan's next ``n`` samples (None: all the rest)."""
        end = len(self.samples) if n is None else min(len(self.samples), self.fed + n)
        for s in self.samples[self.fed : end]:
            feed(self, s)

    def feed_every(self, period_s: float) -> threading.Event:
        """Feed the plan's next sample every ``period_s`` wall seconds from a thread, until the plan runs out
        or the returned event is set (a live-like service for a browser or a load test)."""
        stop = threading.Event()

        def run() -> None:
            while self.fed < len(self.samples) and not stop.wait(period_s):
                self.feed_next(1)

        thread = threading.Thread(target=run, name="served-feeder", daemon=True)
        self._feeders.append((stop, thread))
        thread.start()
        return stop

    def close(self) -> None:
        """Stop the shell, then the database (flushing the writer), as ``Runtime.stop`` does."""
        if self.loop.is_closed():
            return
        for stop_feeding, feeder in self._feeders:
            stop_feeding.set()
            feeder.join(30.0)

        async def stop() -> None:
            for src in self.sources.values():
                await src.close()
            await self.service.close()
            await asyncio.to_thread(self.persistence.close, 10.0)

        self.worker.close()
        self.call(stop, 30.0)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10.0)
        self.loop.close()

    def __enter__(self) -> Served:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def feed(served: Served, sample: Sample) -> None:
    """The one way samples enter the served service: as the acquisition hands them over (the shell's
    ``on_sample`` on its loop), then wait until the identifications the sample started are recorded."""
    if served.fed < len(served.samples) and sample is served.samples[served.fed]:
        served.fed += 1
    served.clock.at_least(sample.t)

    async def deliver() -> None:
        served.service.on_sample(sample)

    served.call(deliver)
    served.settle()


def served_service(
    *,
    database_url: str,
    plan: Plan | None = Plan(),
    settings: Settings | None = None,
    feed_samples: int | None = None,
    sources: Mapping[str, DaqDevice | CanDevice] | None = None,
    clock: ManualClock | None = None,
    loading: bool = False,
    on_event: Callable[[str], None] | None = None,
) -> Served:
    """The real service on ``database_url`` (migrated), fed the first ``feed_samples`` samples of ``plan``
    (None: all; ``plan=None``: no samples at all).

    ``settings``: the service's settings (the database URL is replaced); ``sources``: drivers whose health
    the service reports ("modbus", "can"; none by default: no device runs); ``loading``: the model is still
    loading (``served.started()`` finishes it); nothing is fed then, samples fed by hand are taken, their jobs
    wait for the model.
    """
    s = settings if settings is not None else Settings()
    s = s.model_copy(update={"database": s.database.model_copy(update={"url": database_url})})
    if "require_mechanics_calibration" not in s.compensation.model_fields_set:
        # the plan's plant has the spindle description's own mechanics: nothing to commission unless the
        # settings ask for the rule explicitly (issue 27)
        comp = s.compensation.model_copy(update={"require_mechanics_calibration": False})
        s = s.model_copy(update={"compensation": comp})
    if "require_offset_baseline" not in s.compensation.model_fields_set:
        # nor offsets on its sensors (``VirtualPlant``'s default): nothing for a baseline to remove
        comp = s.compensation.model_copy(update={"require_offset_baseline": False})
        s = s.model_copy(update={"compensation": comp})
    samples = plant_samples(plan) if plan is not None else ()
    clock = clock if clock is not None else ManualClock(samples[0].t if samples else PLAN_T0)
    say = on_event or (lambda _msg: None)
    model = _model(ModelRef.from_settings(s))
    persistence = open_persistence(s.database, migrate=True, on_event=say, clock=clock, spindle=s.spindle)
    core = ServiceCore(
        core_config(s),
        model=model,
        restored=persistence.restored,
        history_capacity=s.acquisition.ring_capacity,
    )
    worker = InlineWorker(model, loading=loading)
    service = SoftSensorService(
        core,
        worker=worker,
        writer=persistence.sink,
        session_factory=persistence.session_factory,
        db_reads=persistence.reads,
        sources=sources,
        clock=clock,
        on_event=say,
        growth=growth_server(model, s, persistence.restored),
    )
    served = Served(
        service=service,
        clock=clock,
        worker=worker,
        persistence=persistence,
        samples=samples,
        sources=sources,
    )
    try:
        served.start()
        if not loading:
            served.feed_next(feed_samples)
    except BaseException:
        served.close()
        raise
    return served


def exit_on_sigterm() -> None:
    """Make SIGTERM raise ``SystemExit`` in the main thread, so that a served service run by uvicorn in a
    server process is closed and its temporary database removed (uvicorn shuts down gracefully on SIGTERM,
    then re-raises the signal to the handler that was installed before it)."""
    signal.signal(signal.SIGTERM, lambda _sig, _frame: sys.exit(0))
