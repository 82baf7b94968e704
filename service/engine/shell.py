"""The running soft sensor: the asyncio shell around the pure :class:`service.engine.core.ServiceCore`.

Data flow::

    acquisition (drivers) --Sample--> on_sample --SampleReceived--> core.handle --> instructions
    instructions: Store -> database writer, Launch -> worker process --JobOutcome--> JobOutcomeReceived,
                  Cancel -> worker, Log -> on_event
    after each event: core.view() --published--> readers (service.serve.reader.ViewReader, no lock)
                                                 --subscribe()--> outlets' on_view (service.serve.outlet)

The shell owns every side effect; the core only decides. Each event gets an id (``"sample-1042"``,
``"outcome-3"``, ``"manual-1"``, ...) that the instructions and the stored identification records keep.
When started, events are handled on the event loop: an API thread's request (``request_identification``,
``request_baseline``) is handed over to the loop and waited for; before ``start()`` the caller's thread
handles it (one thread at a time). After each event the shell publishes the core's immutable snapshot
(``service.serve.view.CoreView``) by swapping one reference, which the API threads read without a lock, and
hands it to the subscribed outlets (REST, OPC UA, MQTT; ``subscribe``, coalesced, at most every
``outlet_interval_s``).
Jobs run in the worker process; with ``run_job`` (offline use, tests) they run inline, synchronously, and
their outcome is handled right after the event that launched them.

:class:`SoftSensorService` implements ``service.serve.interface.ChtcService`` for the API: the reads are
answered by ``reader()`` (a ``ViewReader`` of the newest view: the same values every outlet serves), the
writes and the database history here. Device health is
sampled once a second and transitions are stored as device events. Time comes from an injected ``clock``
(UTC ``datetime``), the same clock the acquisition stamps samples with, so ``chtc demo`` can run the whole
service at a speed-up.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import contextlib
import functools
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Coroutine, Mapping, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from drivers.ringbuffer import Sample
from service.acquire.devicewatch import DeviceWatch
from service.contracts.errors import BusyError, NotReadyError
from service.contracts.health import DeviceHealth, DeviceStatus, HealthSnapshot, Readiness
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.metrics import CoreMetrics, FilterMetrics, HistogramData, MetricsSnapshot
from service.contracts.mode import IdentificationMode
from service.contracts.probe import ProbeError, ProbeMeasurement
from service.contracts.records import DeviceEventData, Record
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    ChtcMapSnapshot,
    ChtcSnapshot,
    CompensationSnapshot,
    ConditionSnapshot,
    FieldAt,
    FieldSnapshot,
    IdentificationJob,
    IdentificationPage,
    IdentificationRecord,
    OffsetBaseline,
    SectionSnapshot,
    SensorHistory,
    SensorReading,
    SpindleLayout,
)
from service.engine.archive import IdentificationArchive
from service.engine.core import ServiceCore
from service.engine.corethread import CoreRunner, InlineRunner
from service.engine.events import (
    BaselineRequested,
    Calibrated,
    Cancel,
    Event,
    IdsKnown,
    Instruction,
    JobOutcomeReceived,
    Launch,
    Log,
    ManualAccepted,
    ManualRequested,
    Rejected,
    RejectKind,
    SampleReceived,
    Store,
)
from service.engine.growthserve import GrowthServer
from service.engine.health import (
    HealthSource,
    StatusSource,
    core_health,
    db_health,
    filter_health,
    frame_events,
    frame_outcomes,
    loop_health,
    poll_events,
    poll_outcomes,
    source_health,
)
from service.engine.looplag import LoopLagMonitor
from service.identify.worker import JobOutcome, JobRequest, JobStatus
from service.serve.histogram import LATENCY_BUCKETS_S, Histogram
from service.serve.interface import CountedOutlet
from service.serve.reader import MAP_H_BOX, ReadContext, ViewReader
from service.serve.sensorhistory import SensorHistoryBuffer
from service.serve.view import CoreView
from service.store.mechanics import mechanics_record
from service.store.probes import probe_record
from service.store.references import reference_record

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from service.engine.commissioning import CommissionReport
    from service.serve.outlet import Outlet
    from service.store.reads import DbReads

__all__ = ["MAP_H_BOX", "RecordWriter", "SoftSensorService", "Worker"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]
HANDOVER_TIMEOUT_S = 30.0  # an API thread waits this long for the event loop to handle its request


class RecordWriter(StatusSource, Protocol):
    """The buffered database writer (``service.store.writer.DbWriter`` or ``persistence.GateSink``)."""

    def submit(self, record: Record) -> bool: ...


class Worker(Protocol):
    """The identification worker as the shell drives it: ``service.identify.worker.IdentificationWorker`` (a
    process) in the running service, ``service.sim.served.InlineWorker`` (a thread) in the API tests.

    ``model_version`` is None until ``start()`` has loaded the model; ``run`` never raises for a failed job (a
    failure is an outcome); ``running_job`` is the job id ``run`` is busy with, ``restarts`` counts processes
    replaced after a crash or a hang.
    """

    model_version: str | None
    restarts: int
    running_job: int | None

    async def start(self) -> str: ...

    async def run(self, req: JobRequest) -> JobOutcome: ...

    def cancel(self, job_id: int) -> None: ...

    def close(self) -> None: ...


def utc_now() -> datetime:
    return datetime.now(UTC)


def _write_latency(writer: object) -> HistogramData | None:
    """The database writer's batch latencies, if it keeps them (``persistence.GateSink`` does)."""
    hist = getattr(writer, "write_latency", None)
    return None if hist is None else hist.snapshot()


class SoftSensorService:
    """See the module docstring. Construct with the parts, ``start()`` on the loop, ``close()`` at the end."""

    def __init__(
        self,
        core: ServiceCore,
        *,
        worker: Worker | None,
        writer: RecordWriter | None = None,
        session_factory: sessionmaker[Session] | None = None,  # for the history endpoints
        db_reads: DbReads | None = None,  # history reads bounded and with a deadline
        sources: Mapping[str, HealthSource] | None = None,  # "modbus"/"can" -> drivers Source
        clock: Clock = utc_now,
        on_event: Callable[[str], None] | None = None,
        history_capacity: int = 2160,  # samples of measured vs predicted kept for the API (6 h at 10 s)
        run_job: Callable[[JobRequest], JobOutcome] | None = None,
        growth: GrowthServer | None = None,  # /compensation; default: referred to the live state's start
        runner: CoreRunner | None = None,  # where the core's work runs (default inline; runtime: CoreThread)
        max_core_lag_s: float = math.inf,  # a sample waiting longer for the core: served as core_behind
        loop_lag: LoopLagMonitor | None = None,  # measured on the loop from start(); /healthz, /metrics
        own_loop_lag: bool = True,  # run loop_lag's measuring task (False: its owner runs it, e.g. a Host)
        outlet_interval_s: float = 0.1,  # subscribed outlets get a new view at most this often (coalesced)
    ) -> None:
        self.core = core
        self.runner: CoreRunner = runner if runner is not None else InlineRunner()
        if run_job is not None and not isinstance(self.runner, InlineRunner):
            raise ValueError("run_job (jobs inline) needs the inline runner")
        self.max_core_lag_s = float(max_core_lag_s)
        self.loop_lag = loop_lag
        self._own_loop_lag = own_loop_lag
        self._pub_lock = threading.Lock()
        self.worker = worker
        self.writer = writer
        self._archive = IdentificationArchive(session_factory, db_reads)
        self.sources = dict(sources or {})
        self.clock = clock
        self.on_event = on_event or (lambda msg: log.info("%s", msg))
        self.run_job = run_job
        self._core_view: CoreView = core.view()
        self._view: CoreView = self._core_view
        self._event_ids: dict[str, itertools.count[int]] = {}
        self._deferred: list[Event] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._device_watch = DeviceWatch()
        self._poll_latency = Histogram(LATENCY_BUCKETS_S)
        self._terms_view: CoreView | None = None  # the newest view whose growth terms are wanted
        self._terms_task: asyncio.Task[None] | None = None
        modbus = self.sources.get("modbus")
        if modbus is not None and hasattr(modbus, "on_read_s"):
            modbus.on_read_s = self._poll_latency.observe  # the driver's own poll timing (drivers.base)
        self.model_loaded = worker is None or worker.model_version is not None
        self.closed = False
        sensors = [(sp.channel, sp.name, sp.role) for sp in core.model.spec.sensors]
        self._history = SensorHistoryBuffer(history_capacity, sensors)
        self._growth = growth if growth is not None else GrowthServer(core.model)  # /compensation
        if self._growth.on_reference is None:  # every zero taken is stored (restored at the next start)
            self._growth.on_reference = self._store_reference
        self._read_ctx = ReadContext(
            core.model,
            clock=clock,
            mode=core.config.mode,
            growth=self._growth,
            devices=self._devices,
            model_loaded=lambda: self.model_loaded,
        )
        self._outlets: list[Outlet] = []
        self.outlet_interval_s = float(outlet_interval_s)
        self._notify_pending = False
        self._notified_mono = -math.inf
        self.runner.start(self._handle_here, self._publish)

    @property
    def growth(self) -> GrowthServer:
        """The thermal growth's server (``compensation()``; docs/design/growth.md)."""
        return self._growth

    @property
    def view(self) -> CoreView:
        """The core's state after the last event (immutable; replaced, never changed)."""
        return self._view

    # --- lifecycle ------------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Remember the loop, start the worker process (loads the model there) and the health watcher."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._schedule_outlets()  # outlets subscribed before start() get the current view
        try:
            await asyncio.to_thread(self._growth.prepare)  # the growth model: once, off the loop
        except NotReadyError as err:  # /compensation answers 503 with the cause; H is served as before
            self.record_event("growth", "unavailable", str(err))
        if self.worker is not None:
            version = await self.worker.start()
            self.model_loaded = True
            self.record_event("worker", "started", f"model {version}")
        self._spawn(self._watch_health())
        if self.loop_lag is not None and self._own_loop_lag:
            self._spawn(self.loop_lag.run())

    async def close(self) -> None:
        self.closed = True
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await asyncio.to_thread(self.runner.close)
        if self.worker is not None:
            self.worker.close()

    def _spawn(self, coro: Coroutine[object, object, None]) -> asyncio.Task[None]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # --- events ---------------------------------------------------------------------------------------------
    def handle(self, event: Event) -> list[Instruction]:
        """Hand ``event`` to the core, execute its instructions, publish the new view; returns them.

        With the inline runner, from a thread other than the running loop's, the event is handled on the loop
        and waited for; with the core thread, it is queued behind the events before it and waited for (never
        call this on the loop then: ``post``).
        """
        if not isinstance(self.runner, InlineRunner):
            try:
                return self.runner.call(event, HANDOVER_TIMEOUT_S)
            except cf.TimeoutError as err:
                raise NotReadyError(
                    f"the service did not handle the request within {HANDOVER_TIMEOUT_S:.0f} s"
                ) from err
        loop = self._loop
        if loop is None or threading.get_ident() == self._loop_thread or not loop.is_running():
            return self._handle_here(event)
        done: cf.Future[list[Instruction]] = cf.Future()

        def run() -> None:
            try:
                done.set_result(self._handle_here(event))
            except Exception as err:  # the API thread raises it
                done.set_exception(err)

        loop.call_soon_threadsafe(run)
        try:
            return done.result(timeout=HANDOVER_TIMEOUT_S)
        except cf.TimeoutError as err:
            raise NotReadyError(
                f"the service did not take the request within {HANDOVER_TIMEOUT_S:.0f} s"
            ) from err

    def post(self, event: Event) -> None:
        """Hand ``event`` to the core without waiting for it (the event loop's events: samples, outcomes)."""
        if isinstance(self.runner, InlineRunner):
            self.handle(event)
        else:
            self.runner.post(event)

    def _handle_here(self, event: Event) -> list[Instruction]:
        instructions = self._step(event)
        while self._deferred:  # outcomes known at once (no worker, no loop): handled after, not inside
            self._step(self._deferred.pop(0))
        return instructions

    def _step(self, event: Event) -> list[Instruction]:
        """The per-event work, in the runner's thread: the core decides, the view is published; the
        instructions' side effects run on the loop (in order), or here with the inline runner."""
        instructions = self.core.handle(event)
        self._core_view = self.core.view()
        self._publish()
        if isinstance(event, SampleReceived):
            self._remember_history()
        self._refresh_growth()
        if isinstance(self.runner, InlineRunner):
            for ins in instructions:
                self._execute(ins)
            return instructions
        if instructions:
            self._on_loop(functools.partial(self._execute_all, instructions))
        self._prepare_answers()
        return instructions

    def _prepare_answers(self) -> None:
        """With the core thread: build ``/chtc``'s snapshot of the new view here, so that a request on the
        loop finds it cached (the map's H and prior at the new sample's speed cost a few ms of CPU)."""
        try:
            self.chtc()
        except Exception as err:  # the request raises it to its caller; never stop the core for it
            log.debug("chtc snapshot not prepared: %s: %s", type(err).__name__, err)

    def _publish(self) -> None:
        """Swap the published view: the core's last one with the core thread's backlog (``pending_since``);
        called by the core thread after each event and by the loop when a sample starts a backlog."""
        with self._pub_lock:
            v = self._core_view
            pending = self.runner.pending_since
            if pending is not None or v.max_core_lag_s != self.max_core_lag_s or v.pending_since is not None:
                v = replace(v, pending_since=pending, max_core_lag_s=self.max_core_lag_s)
            self._view = v
        self._schedule_outlets()

    # --- outlets (service.serve.outlet) ---------------------------------------------------------------------
    def subscribe(self, outlet: Outlet) -> None:
        """Hand every newly published view to ``outlet.on_view`` from now on: on the event loop, coalesced and
        at most every ``outlet_interval_s`` (the newest view; see ``service.serve.outlet``). The current view
        is delivered at once (with a running loop; else from ``start()``)."""
        self._outlets.append(outlet)
        self._schedule_outlets()

    def unsubscribe(self, outlet: Outlet) -> None:
        with contextlib.suppress(ValueError):
            self._outlets.remove(outlet)

    def _schedule_outlets(self) -> None:
        """Called by whichever thread published: one delivery pending at a time (a later publish finds it and
        is delivered by it, since the delivery reads the newest view when it runs)."""
        loop = self._loop
        if not self._outlets or self._notify_pending or loop is None or not loop.is_running():
            return
        self._notify_pending = True
        loop.call_soon_threadsafe(self._notify_outlets)

    def _notify_outlets(self) -> None:
        loop = self._loop
        wait = self.outlet_interval_s - (time.monotonic() - self._notified_mono)
        if wait > 0 and loop is not None:
            loop.call_later(wait, self._notify_outlets)  # still pending: publishes meanwhile coalesce here
            return
        self._notify_pending = False  # before reading the view: a publish from now on schedules anew
        self._notified_mono = time.monotonic()
        if self.closed:
            return
        reader = self.reader()
        for outlet in list(self._outlets):
            try:
                outlet.on_view(reader)
            except Exception as err:  # one outlet's bug must not stop the others nor the service
                log.warning("outlet %s: on_view failed: %s: %s", outlet.name, type(err).__name__, err)

    def _on_loop(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the event loop (now, when called there or when there is none running)."""
        loop = self._loop
        if loop is None or not loop.is_running() or threading.get_ident() == self._loop_thread:
            fn()
        else:
            loop.call_soon_threadsafe(fn)

    def _execute_all(self, instructions: Sequence[Instruction]) -> None:
        for ins in instructions:
            self._execute(ins)

    def _refresh_growth(self) -> None:
        """New identification or condition: the growth's condition terms in a thread (with a loop; without,
        the first ``compensation()`` computes them in its caller's thread)."""
        view = self._view
        self._growth.observe(view)
        loop = self._loop
        if loop is not None and loop.is_running() and self._growth.wants_refresh(view):
            self._on_loop(functools.partial(self._spawn_terms, view))

    def _spawn_terms(self, view: CoreView) -> None:
        """One refresh at a time, for the newest view wanting one: keys that change while a refresh runs
        (a condition change, then the live H at its speed, then an identification) coalesce into one."""
        self._terms_view = view
        if self._terms_task is None or self._terms_task.done():
            self._terms_task = self._spawn(self._growth_terms())

    async def _growth_terms(self) -> None:
        while (view := self._terms_view) is not None:
            self._terms_view = None
            try:
                await asyncio.to_thread(self._growth.refresh, view)
            except Exception as err:  # a request retries it and raises to its caller; say it here too
                log.warning("growth terms failed: %s: %s", type(err).__name__, err)

    def _execute(self, ins: Instruction) -> None:
        if isinstance(ins, Store):
            if self.writer is not None:
                self.writer.submit(ins.record)
        elif isinstance(ins, Launch):
            self._launch(ins)
        elif isinstance(ins, Cancel):
            if self.worker is not None:
                self.worker.cancel(ins.job_id)
        elif isinstance(ins, Log):
            log.debug("[%s] %s", ins.event_id, ins.message)
            self.on_event(ins.message)
        # ManualAccepted, Calibrated, Rejected: replies, read by the caller of handle()

    def _next_id(self, kind: str) -> str:
        counter = self._event_ids.setdefault(kind, itertools.count(1))
        return f"{kind}-{next(counter)}"

    def on_sample(self, sample: Sample) -> None:
        """Feed one acquisition sample (called on the event loop by the acquisition)."""
        self.post(SampleReceived(self._next_id("sample"), sample))

    def ids_known(self, next_condition_id: int, next_identification_id: int) -> None:
        """The database answered after start-up: ids continue from its, if none was issued yet."""
        self.post(IdsKnown(self._next_id("ids"), next_condition_id, next_identification_id))

    def _remember_history(self) -> None:
        """Measured (usable channels only) and predicted temperatures of the newest sample, for the API."""
        v = self._view
        s = v.newest
        if s is None:
            return
        ok = np.array([q == "ok" for q in s.quality], dtype=bool)
        measured = np.where(ok & np.isfinite(s.temps_c), s.temps_c, np.nan)
        predicted = None if v.live is None else v.live.sensors_c
        self._history.append(s.t, measured, predicted)

    def _launch(self, launch: Launch) -> None:
        """Run a job: inline with ``run_job``, else on the event loop in the worker process (without a loop
        and a worker, its failed outcome comes at once)."""
        if self.run_job is not None:
            self._deferred.append(self._outcome_event(self.run_job(launch.request)))
            return
        if self._loop is None and self.worker is None:
            self._deferred.append(self._outcome_event(_no_worker(launch)))
            return
        self._spawn(self._run_job(launch))

    async def _run_job(self, launch: Launch) -> None:
        if self.worker is None:
            outcome = _no_worker(launch)
        else:
            try:
                outcome = await self.worker.run(launch.request)
            except asyncio.CancelledError:
                raise
            except Exception as err:  # the worker façade should not raise; never lose the job silently
                outcome = JobOutcome(
                    job_id=launch.request.job_id,
                    status=JobStatus.FAILED,
                    message=f"{type(err).__name__}: {err}",
                )
        if self.worker is not None and self.worker.restarts:
            self.record_event("worker", "restarted", f"{self.worker.restarts} restart(s) so far")
        self.post(self._outcome_event(outcome))

    def _outcome_event(self, outcome: JobOutcome) -> JobOutcomeReceived:
        return JobOutcomeReceived(
            event_id=self._next_id("outcome"), outcome=outcome, finished_at=self.clock()
        )

    # --- device health (event-loop thread) --------------------------------------------------------------
    async def _watch_health(self, period_s: float = 1.0) -> None:
        while not self.closed:
            for event in self._device_watch.observe(self._devices()):
                self.record_event(event.device, event.kind, event.detail)
            await asyncio.sleep(period_s)

    def record_event(self, device: str, kind: str, detail: str = "") -> None:
        if self.writer is not None:
            self.writer.submit(DeviceEventData(t=self.clock(), device=device, kind=kind, detail=detail))
        self.on_event(f"{device}: {kind} {detail}".rstrip())

    # --- ChtcService: current values (service.serve.reader.ViewReader of the published view) ----------------
    def reader(self) -> ViewReader:
        """The read side of the newest published view (cheap; what every outlet reads)."""
        return ViewReader(self._view, self._read_ctx)

    def chtc(self) -> ChtcSnapshot | None:
        return self.reader().chtc()

    def identification_mode(self) -> IdentificationMode:
        return self.core.config.mode

    def chtc_map(self) -> ChtcMapSnapshot | None:
        return self.reader().chtc_map()

    def field(self, at: FieldAt) -> FieldSnapshot:
        return self.reader().field(at)

    def compensation(self) -> CompensationSnapshot | None:
        return self.reader().compensation()

    def compensation_section(self) -> SectionSnapshot | None:
        return self.reader().compensation_section()

    def sensors(self) -> Sequence[SensorReading]:
        return self.reader().sensors()

    def condition(self) -> ConditionSnapshot:
        return self.reader().condition()

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        return self.reader().recent_conditions(limit)

    def layout(self) -> SpindleLayout:
        return self.reader().layout()

    def request_baseline(self) -> OffsetBaseline:
        for ins in self.handle(BaselineRequested(self._next_id("baseline"), self.clock())):
            if isinstance(ins, Rejected):
                raise NotReadyError(ins.reason)
            if isinstance(ins, Calibrated):
                c = ins.calibration
                return OffsetBaseline(
                    t_from=c.t_from,
                    t_to=c.t_to,
                    source=c.source,
                    samples=c.samples,
                    offsets_c=tuple(float(x) if np.isfinite(x) else None for x in c.offsets_c),
                    sd_c=tuple(float(x) for x in c.sd_c),
                )
        raise NotReadyError("no baseline")

    def compensation_reference(self) -> CompensationReference | None:
        return self._growth.reference

    def set_compensation_reference(
        self, *, temperature_c: float | None, source: str, set_by: str
    ) -> CompensationReference:
        ref = self._growth.take_reference(
            self._view, source=source, set_by=set_by, temperature_c=temperature_c, at=self.clock()
        )
        self.on_event(
            f"compensation zero set: {ref.temperature_c:.3f} °C ± {ref.sd_c:.3f} "
            f"({ref.source}, by {ref.set_by})"
        )
        return ref

    def compensation_mechanics(self) -> MechanicsCalibration | None:
        return self._growth.mechanics

    def commission_mechanics(
        self,
        *,
        temperatures: Path,
        canlog: Path | None,
        displacements: Path,
        set_by: str,
        source: str,
        force: bool = False,
    ) -> tuple[CommissionReport, bool]:
        """Fit the mechanics to a measured thermal test with this service's own core and model
        (``service.engine.commissioning``; blocking, seconds to a minute: call it off the event loop);
        store and use the calibration when the model explains the test (or ``force``). (report, stored)."""
        from service.engine.commissioning import commission_growth

        rep = commission_growth(
            self.core.model,
            self.core.config,
            temperatures,
            canlog,
            displacements,
            set_by=set_by,
            source=source,
            basis=self._growth.mechanics_basis(),
            now=self.clock(),
        )
        stored = rep.explained or force
        if stored:
            self.set_mechanics(rep.calibration)
        return rep, stored

    def set_mechanics(self, cal: MechanicsCalibration) -> None:
        """Serve with ``cal`` from now on and store it (restored at every start); blocking (~2 s the first
        time: the mount/α operators)."""
        self._growth.set_mechanics(cal)
        if self.writer is not None:
            self.writer.submit(mechanics_record(cal))
        x = cal.x
        self.on_event(
            f"mechanics commissioned: restraint {x[0]:.3f}, α shaft {x[1]:.3f}, α housing {x[2]:.3f} "
            f"({cal.source}, by {cal.set_by}; the model "
            f"{'explains' if cal.explained else 'does NOT explain'} "
            "the test)"
        )

    def compensation_measurements(self) -> list[ProbeMeasurement]:
        """The probe readings kept (restored and new), newest first."""
        return self._growth.probes()

    def add_measurement(
        self, *, at: datetime, axial_um: float, sd_um: float, set_by: str, source: str
    ) -> ProbeMeasurement:
        """Take a probe reading (``GrowthServer.measure``; blocking, ~2 s the first time: call it off the
        event loop) and store it, absorbed or not. ``ProbeError`` naming the field: ``at`` in the future
        (beyond the live state's newest instant) or outside the kept history, a bad value."""
        now = self.clock()
        if at > now:
            raise ProbeError(f"at: {at.isoformat()} is in the future (now {now.isoformat()})")
        m = self._growth.measure(
            self._view, at=at, axial_um=axial_um, sd_um=sd_um, set_by=set_by, source=source
        )
        if self.writer is not None:
            self.writer.submit(probe_record(m, now))
        verdict = (
            "absorbed"
            if m.accepted
            else f"NOT absorbed: {m.sigma_ratio:.1f} σ off (a crash or a tool change since the last one?)"
        )
        self.on_event(
            f"probe reading {m.axial_um:+.2f} ± {m.sd_um:.2f} µm at {m.at.isoformat()} (predicted "
            f"{m.predicted_um:+.2f} ± {m.sigma_um:.2f} µm): {verdict}"
        )
        return m

    def _store_reference(self, ref: CompensationReference) -> None:
        if self.writer is not None:
            self.writer.submit(reference_record(ref))

    def sensor_history(self, since: datetime | None) -> SensorHistory:
        return self._history.since(since)

    # --- ChtcService: history ---------------------------------------------------------------------------
    def list_identifications(
        self, *, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        records = self._view.records
        return self._archive.page(records, since=since, until=until, limit=limit, offset=offset)

    def get_identification(self, identification_id: int) -> IdentificationRecord:
        return self._archive.get(self._view.records, identification_id)

    # --- ChtcService: requests --------------------------------------------------------------------------
    def request_identification(self, reason: str) -> IdentificationJob:
        if not self.model_loaded:  # the core does not know the worker; no job can run before its model
            raise NotReadyError("the model is still loading in the identification worker; retry when ready")
        for ins in self.handle(ManualRequested(self._next_id("manual"), reason)):
            if isinstance(ins, Rejected):
                raise (BusyError if ins.kind is RejectKind.BUSY else NotReadyError)(ins.reason)
            if isinstance(ins, ManualAccepted):
                return ins.job
        raise NotReadyError("the identification request was not answered")

    def job(self, job_id: str) -> IdentificationJob:
        return self.reader().job(job_id)

    # --- ChtcService: health and metrics ----------------------------------------------------------------
    def _devices(self, view: CoreView | None = None, now: datetime | None = None) -> list[DeviceHealth]:
        """The device health at ``now`` (default: the clock's) with ``view`` (default: the newest)."""
        view = self._view if view is None else view
        now = self.clock() if now is None else now
        out = [source_health(name, src, now) for name, src in self.sources.items()]
        out.append(db_health(self.writer, now))
        out.append(self._worker_health(view))
        out.append(filter_health(view, now))
        if self.runner.load().threaded:
            out.append(core_health(self.runner.load(), view, now))
        if self.loop_lag is not None:
            out.append(loop_health(self.loop_lag.lag()))
        return out

    def _worker_health(self, view: CoreView) -> DeviceHealth:
        if self.worker is None:
            return DeviceHealth(
                name="worker",
                status=DeviceStatus.DISABLED,
                last_ok_at=None,
                age_s=None,
                counters={},
                message="no identification worker",
            )
        status = DeviceStatus.OK if self.worker.model_version is not None else DeviceStatus.DOWN
        counters = {"restarts": self.worker.restarts, **view.counts}
        running = self.worker.running_job
        msg = f"running job-{running}" if running is not None else "idle"
        return DeviceHealth(
            name="worker", status=status, last_ok_at=None, age_s=None, counters=counters, message=msg
        )

    def health(self) -> HealthSnapshot:
        return self.reader().health()

    def ready(self) -> Readiness:
        return self.reader().ready()

    def metrics(self) -> MetricsSnapshot:
        v = self._view
        now = self.clock()
        modbus = self.sources.get("modbus")
        can = self.sources.get("can")
        ages = v.channel_ages(now)
        quality = list(v.newest.quality) if v.newest is not None else ["no_data"] * len(ages)
        last = v.current
        st = self.writer.status() if self.writer is not None else None
        reconnects = {n: int(s.metrics.reconnects) for n, s in self.sources.items()}
        if self.worker is not None:
            reconnects["worker"] = self.worker.restarts
        return MetricsSnapshot(
            modbus_poll_latency_s=self._poll_latency.snapshot(),
            modbus_polls_total=poll_outcomes(modbus),
            can_frames_total=frame_outcomes(can),
            modbus_events_total=poll_events(modbus),
            can_events_total=frame_events(can),
            chtc=self.chtc(),
            build_version=_build_version(),
            model_version=self.core.model.version if self.model_loaded else None,
            channel_age_s=ages,
            channel_quality=quality,
            identifications_total=dict(v.counts),
            identification_duration_s=v.durations,
            last_fit=None if last is None else last.fit,
            last_rmse_c=None if last is None else last.rmse_c,
            db_pending_rows=0 if st is None else int(st.pending),
            db_errors_total=0 if st is None else int(st.errors),
            db_write_s=_write_latency(self.writer),
            reconnects_total=reconnects,
            filter=_filter_metrics(v),
            loop_lag_s=None if self.loop_lag is None else self.loop_lag.histogram.snapshot(),
            loop_lag_recent_max_s=None if self.loop_lag is None else self.loop_lag.lag().recent_max_s,
            core=self._core_metrics(v, now),
            growth_terms_computed=self._growth.computed,
            growth_terms_cpu_s=self._growth.compute_cpu_s,
            outlets={o.name: o.outlet_metrics() for o in self._outlets if isinstance(o, CountedOutlet)},
        )

    def _core_metrics(self, v: CoreView, now: datetime) -> CoreMetrics | None:
        wait = self.runner.wait_s()
        if wait is None:
            return None
        load = self.runner.load()
        return CoreMetrics(
            wait_s=wait.snapshot(),
            queued=load.queued,
            lag_s=v.core_lag_s(now),
            dropped=load.dropped,
            handled=load.handled,
        )


def _filter_metrics(v: CoreView) -> FilterMetrics | None:
    live = v.live
    if live is None:
        return None
    return FilterMetrics(
        nis=live.nis,
        dof=live.nis_dof,
        window_ratio=live.nis_sum / live.nis_sum_dof if live.nis_sum_dof else None,
        verdict=live.verdict,
        converged=live.converged,
        inconsistent=live.inconsistent(live.t),
    )


def _no_worker(launch: Launch) -> JobOutcome:
    return JobOutcome(
        job_id=launch.request.job_id, status=JobStatus.FAILED, message="no identification worker"
    )


@functools.cache
def _build_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spindle-chtc")
    except PackageNotFoundError:
        return "unknown"
