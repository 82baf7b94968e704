"""The running service's machinery behind the facade ``service.shell.service.SoftSensorService`` (as asyncua's
``Server`` wraps its ``InternalServer``): the event loop's side of the pure core.

Data flow::

    acquisition (drivers) --Sample--> on_sample --SampleReceived--> core.handle --> instructions
    instructions: Store -> database writer, Launch -> worker process --JobOutcome--> JobOutcomeReceived,
                  Cancel -> worker, Log -> on_event
    after each event: core.view() --published--> readers (service.serve.reader.ViewReader, no lock)
                                                 --subscribe()--> outlets' on_view (service.shell.outlets)

Each event gets an id (``"sample-1042"``, ``"outcome-3"``, ``"manual-1"``, ...) that the instructions and the
stored identification records keep. When started, events are handled on the event loop: an API thread's
request is handed over to the loop and waited for; before ``start()`` the caller's thread handles it (one
thread at a time). After each event the core's immutable snapshot (``service.serve.view.CoreView``) is
published by swapping one reference, which the API threads read without a lock, and handed to the subscribed
outlets. Jobs run in the worker process; with ``run_job`` (offline use, tests) they run inline, synchronously,
and their outcome is handled right after the event that launched them. Device health is sampled once a
second and transitions are stored as device events.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import functools
import itertools
import logging
import threading
from collections.abc import Callable, Coroutine, Mapping, Sequence
from dataclasses import replace
from datetime import datetime
from typing import TYPE_CHECKING

import numpy as np

from drivers.ringbuffer import Sample
from service.acquire.devicewatch import DeviceWatch
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.errors import NotReadyError
from service.contracts.health import DeviceHealth
from service.contracts.records import DeviceEventData, Record
from service.core.events import (
    Cancel,
    Event,
    IdsKnown,
    Instruction,
    JobOutcomeReceived,
    Launch,
    Log,
    SampleReceived,
    Store,
)
from service.core.machine import ServiceCore
from service.identify.worker import JobOutcome, JobRequest, JobStatus
from service.serve.compensation import GrowthServer
from service.serve.reader import ReadContext, ViewReader
from service.serve.sensorhistory import SensorHistoryBuffer
from service.serve.view import CoreView
from service.shell.corethread import CoreRunner, InlineRunner
from service.shell.gauges import Gauges
from service.shell.growthserve import TermsRefresher
from service.shell.health import HealthSource
from service.shell.looplag import LoopLagMonitor
from service.shell.outlets import OutletHub

if TYPE_CHECKING:
    from service.shell.ports import RecordWriter, Worker

__all__ = ["HANDOVER_TIMEOUT_S", "InternalService"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]
HANDOVER_TIMEOUT_S = 30.0  # an API thread waits this long for the event loop to handle its request


def with_control(record: Record, growth: GrowthServer) -> Record:
    """A live-state checkpoint with the CI gate's and the command's state added (they survive a restart with
    the live state, ``GrowthServer(control_state=...)``); any other record as it is."""
    ctl = growth.controller
    state = None if ctl is None else ctl.state
    if not isinstance(record, LiveCheckpoint) or state is None:
        return record
    return replace(record, control=state.to_array())


class InternalService:
    """See the module docstring. Built by ``SoftSensorService`` with its parts."""

    def __init__(
        self,
        core: ServiceCore,
        *,
        worker: Worker | None,
        writer: RecordWriter | None,
        sources: Mapping[str, HealthSource],
        clock: Clock,
        on_event: Callable[[str], None],
        history_capacity: int,
        run_job: Callable[[JobRequest], JobOutcome] | None,
        growth: GrowthServer,
        runner: CoreRunner | None,
        max_core_lag_s: float,
        loop_lag: LoopLagMonitor | None,
        own_loop_lag: bool,
        outlet_interval_s: float,
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
        self.clock = clock
        self.on_event = on_event
        self.run_job = run_job
        self._core_view: CoreView = core.view()
        self.view: CoreView = self._core_view  # the published one (replaced, never changed)
        self._event_ids: dict[str, itertools.count[int]] = {}
        self._deferred: list[Event] = []
        self.loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._device_watch = DeviceWatch()
        self.gauges = Gauges(
            sources=sources, writer=writer, worker=worker, runner=self.runner, loop_lag=loop_lag, clock=clock
        )
        self.model_loaded = worker is None or worker.model_version is not None
        self.closed = False
        sensors = [(sp.channel, sp.name, sp.role) for sp in core.model.spec.sensors]
        self.history = SensorHistoryBuffer(history_capacity, sensors)
        self.growth = growth
        self.terms = TermsRefresher(growth, self.spawn)
        self.read_ctx = ReadContext(
            core.model,
            clock=clock,
            mode=core.config.mode,
            growth=growth,
            devices=self.devices,
            model_loaded=lambda: self.model_loaded,
        )
        self.outlets = OutletHub(self.reader, lambda: self.loop, lambda: self.closed, outlet_interval_s)
        self.runner.start(self._handle_here, self._publish)

    def reader(self) -> ViewReader:
        """The read side of the newest published view (cheap; what every outlet reads)."""
        return ViewReader(self.view, self.read_ctx)

    def devices(self, view: CoreView | None = None, now: datetime | None = None) -> list[DeviceHealth]:
        """The device health at ``now`` (default: the clock's) with ``view`` (default: the newest)."""
        return self.gauges.devices(self.view if view is None else view, now)

    # --- lifecycle ------------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Remember the loop, start the worker process (loads the model there) and the health watcher."""
        self.loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self.outlets.schedule()  # outlets subscribed before start() get the current view
        try:
            await asyncio.to_thread(self.growth.prepare)  # the growth model: once, off the loop
        except NotReadyError as err:  # /compensation answers 503 with the cause; H is served as before
            self.record_event("growth", "unavailable", str(err))
        if self.worker is not None:
            version = await self.worker.start()
            self.model_loaded = True
            self.record_event("worker", "started", f"model {version}")
        self.spawn(self._watch_health())
        if self.loop_lag is not None and self._own_loop_lag:
            self.spawn(self.loop_lag.run())

    async def close(self) -> None:
        self.closed = True
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await asyncio.to_thread(self.runner.close)
        if self.worker is not None:
            self.worker.close()

    def spawn(self, coro: Coroutine[object, object, None]) -> asyncio.Task[None]:
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
        loop = self.loop
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

    def next_id(self, kind: str) -> str:
        counter = self._event_ids.setdefault(kind, itertools.count(1))
        return f"{kind}-{next(counter)}"

    def on_sample(self, sample: Sample) -> None:
        """Feed one acquisition sample (called on the event loop by the acquisition)."""
        self.post(SampleReceived(self.next_id("sample"), sample))

    def ids_known(self, next_condition_id: int, next_identification_id: int) -> None:
        """The database answered after start-up: ids continue from its, if none was issued yet."""
        self.post(IdsKnown(self.next_id("ids"), next_condition_id, next_identification_id))

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
        if isinstance(event, SampleReceived):
            self._step_command()
        if isinstance(self.runner, InlineRunner):
            for ins in instructions:
                self._execute(ins)
            return instructions
        if instructions:
            self._on_loop(functools.partial(self._execute_all, instructions))
        self._prepare_answers()
        return instructions

    def _step_command(self) -> None:
        """Each published sample steps the CI gate and the command value (``GrowthServer.snapshot``; a read
        steps them too), so that they move on the service's clock whether or not anything reads them."""
        if self.growth.controller is None:
            return
        try:
            self.reader().compensation()
        except Exception as err:  # the request raises it to its caller; never stop the core for it
            log.debug("command not stepped: %s: %s", type(err).__name__, err)

    def _prepare_answers(self) -> None:
        """With the core thread: build ``/chtc``'s snapshot of the new view here, so that a request on the
        loop finds it cached (the map's H and prior at the new sample's speed cost a few ms of CPU)."""
        try:
            self.reader().chtc()
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
            self.view = v
        self.outlets.schedule()

    def _on_loop(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the event loop (now, when called there or when there is none running)."""
        loop = self.loop
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
        view = self.view
        self.growth.observe(view)
        loop = self.loop
        if loop is not None and loop.is_running() and self.growth.wants_refresh(view):
            self._on_loop(functools.partial(self.terms.want, view))

    def _execute(self, ins: Instruction) -> None:
        if isinstance(ins, Store):
            if self.writer is not None:
                self.writer.submit(with_control(ins.record, self.growth))
        elif isinstance(ins, Launch):
            self._launch(ins)
        elif isinstance(ins, Cancel):
            if self.worker is not None:
                self.worker.cancel(ins.job_id)
        elif isinstance(ins, Log):
            log.debug("[%s] %s", ins.event_id, ins.message)
            self.on_event(ins.message)
        # ManualAccepted, Calibrated, Rejected: replies, read by the caller of handle()

    def _remember_history(self) -> None:
        """Measured (usable channels only) and predicted temperatures of the newest sample, for the API."""
        v = self.view
        s = v.newest
        if s is None:
            return
        ok = np.array([q == "ok" for q in s.quality], dtype=bool)
        measured = np.where(ok & np.isfinite(s.temps_c), s.temps_c, np.nan)
        predicted = None if v.live is None else v.live.sensors_c
        self.history.append(s.t, measured, predicted)

    # --- jobs -----------------------------------------------------------------------------------------------
    def _launch(self, launch: Launch) -> None:
        """Run a job: inline with ``run_job``, else on the event loop in the worker process (without a loop
        and a worker, its failed outcome comes at once)."""
        if self.run_job is not None:
            self._deferred.append(self._outcome_event(self.run_job(launch.request)))
            return
        if self.loop is None and self.worker is None:
            self._deferred.append(self._outcome_event(_no_worker(launch)))
            return
        self.spawn(self._run_job(launch))

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
        return JobOutcomeReceived(event_id=self.next_id("outcome"), outcome=outcome, finished_at=self.clock())

    # --- device health (event-loop thread) --------------------------------------------------------------
    async def _watch_health(self, period_s: float = 1.0) -> None:
        while not self.closed:
            for event in self._device_watch.observe(self.devices()):
                self.record_event(event.device, event.kind, event.detail)
            await asyncio.sleep(period_s)

    def record_event(self, device: str, kind: str, detail: str = "") -> None:
        if self.writer is not None:
            self.writer.submit(DeviceEventData(t=self.clock(), device=device, kind=kind, detail=detail))
        self.on_event(f"{device}: {kind} {detail}".rstrip())


def _no_worker(launch: Launch) -> JobOutcome:
    return JobOutcome(
        job_id=launch.request.job_id, status=JobStatus.FAILED, message="no identification worker"
    )
