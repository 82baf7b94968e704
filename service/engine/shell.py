"""The running soft sensor: the asyncio shell around :class:`service.engine.core.ServiceCore`.

Data flow::

    acquisition (drivers) --Sample--> ring buffer --> core.ingest: live state, detector, scheduler
         --Launch--> worker process (identification) --JobOutcome--> core.job_done --> records
    records --> DbWriter (buffers while the database is down) ;  API threads --> ChtcService methods

:class:`SoftSensorService` implements ``service.serve.interface.ChtcService`` for the API. Everything the API
polls
is prebuilt under the core's lock; nothing here blocks the event loop for long (the worker is a separate
process, the writer a thread). Device health is sampled once a second and transitions are stored as device
events. Time comes from an injected ``clock`` (UTC ``datetime``), the same clock the acquisition stamps
samples with, so ``chtc demo`` can run the whole service at a speed-up.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from typing import Any

import numpy as np

from model.defaults import BOUND_REL_TOL
from service.acquire.devicewatch import DeviceWatch, transition_detail
from service.engine.core import Launch, ServiceCore
from service.identify.worker import IdentificationWorker, JobOutcome, JobStatus
from service.serve.interface import (
    LATENCY_BUCKETS_S,
    ChtcSnapshot,
    ChtcStatus,
    ConditionSnapshot,
    DeviceHealth,
    DeviceStatus,
    FieldAt,
    FieldSnapshot,
    HealthSnapshot,
    Histogram,
    IdentificationJob,
    IdentificationPage,
    IdentificationRecord,
    MetricsSnapshot,
    NoDataError,
    NotFoundError,
    NotReadyError,
    OffsetBaseline,
    Readiness,
    SectionPart,
    SensorHistory,
    SensorHistoryBuffer,
    SensorReading,
    SpindleLayout,
    ZoneInfo,
)
from service.serve.views import Usability, age_s, at_bound, row_to_record, usability
from service.store.records import DeviceEventData

__all__ = ["SoftSensorService", "transition_detail"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]


def utc_now() -> datetime:
    return datetime.now(UTC)


class SoftSensorService:
    """See the module docstring. Construct with the parts, ``start()`` on the loop, ``close()`` at the end."""

    def __init__(
        self,
        core: ServiceCore,
        *,
        worker: IdentificationWorker | None,
        writer: Any = None,  # service.store.writer.DbWriter (submit/status) or None
        session_factory: Any = None,  # sessionmaker for the history endpoints, or None
        # service.store.reads.DbReads: history reads bounded and with a deadline, or None
        db_reads: Any = None,
        sources: Mapping[str, Any] | None = None,  # "modbus"/"can" -> drivers Source (metrics, connected)
        clock: Clock = utc_now,
        on_event: Callable[[str], None] | None = None,
        history_capacity: int = 2160,  # samples of measured vs predicted kept for the API (6 h at 10 s)
    ) -> None:
        self.core = core
        self.worker = worker
        self.writer = writer
        self.session_factory = session_factory
        self.db_reads = db_reads
        self.sources = dict(sources or {})
        self.clock = clock
        self.on_event = on_event or (lambda msg: log.info("%s", msg))
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._started_mono = time.monotonic()
        self._device_watch = DeviceWatch()
        self._snap_cache: tuple[tuple[Any, ...], ChtcSnapshot] | None = None
        self._steady_cache: tuple[tuple[Any, ...], FieldSnapshot] | None = None
        self._poll_latency = Histogram(LATENCY_BUCKETS_S)
        modbus = self.sources.get("modbus")
        if modbus is not None and hasattr(modbus, "on_read_s"):
            modbus.on_read_s = self._poll_latency.observe  # the driver's own poll timing (drivers.base)
        self.model_loaded = worker is None or worker.model_version is not None
        self.closed = False
        sensors = [(sp.channel, sp.name, sp.role) for sp in core.model.spec.sensors]
        self._history = SensorHistoryBuffer(history_capacity, sensors)

    # --- lifecycle ------------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Remember the loop, start the worker process (loads the model there) and the health watcher."""
        self._loop = asyncio.get_running_loop()
        live = self.core.live
        live.set_h(live.h, stepper=await asyncio.to_thread(live.prepare, live.h))
        if self.worker is not None:
            version = await self.worker.start()
            self.model_loaded = True
            self.record_event("worker", "started", f"model {version}")
        self._spawn(self._watch_health())

    async def close(self) -> None:
        self.closed = True
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.worker is not None:
            self.worker.close()

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # --- samples and jobs (event-loop thread) -----------------------------------------------------------
    def on_sample(self, sample: Any) -> None:
        """Feed one acquisition sample (called on the event loop by the acquisition)."""
        for launch in self.core.ingest(sample):
            self._launch(launch)
        self._remember_history()

    def _remember_history(self) -> None:
        """Measured (usable channels only) and predicted temperatures of the newest sample, for the API."""
        core = self.core
        with core.lock:
            s = core.newest
            if s is None:
                return
            ok = np.array([q == "ok" for q in s.quality], dtype=bool)
            measured = np.where(ok & np.isfinite(s.temps_c), s.temps_c, np.nan)
            live = core.current is not None and core.live.initialized
            predicted = core.live.sensors_now() if live else None
        self._history.append(s.t, measured, predicted)

    def on_cancel(self, job_id: int) -> None:
        if self.worker is not None:
            self.worker.cancel(job_id)

    def _launch(self, launch: Launch) -> None:
        """Run a job on the event loop (API threads hand their manual jobs over thread-safely)."""
        try:
            running: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if self._loop is not None and running is not self._loop:
            self._loop.call_soon_threadsafe(self._launch, launch)
            return
        self._spawn(self._run_job(launch))

    async def _run_job(self, launch: Launch) -> None:
        assert launch.request is not None
        if self.worker is None:
            outcome = JobOutcome(launch.start.job_id, JobStatus.FAILED, None, "no identification worker", 0.0)
        else:
            try:
                outcome = await self.worker.run(launch.request)
            except asyncio.CancelledError:
                raise
            except Exception as err:  # the worker façade should not raise; never lose the job silently
                outcome = JobOutcome(
                    launch.start.job_id, JobStatus.FAILED, None, f"{type(err).__name__}: {err}", 0.0
                )
        if self.worker is not None and self.worker.restarts:
            self.record_event("worker", "restarted", f"{self.worker.restarts} restart(s) so far")
        stepper = None
        if outcome.status is JobStatus.OK and outcome.result is not None:
            # factorise the live model's step for the new H in a thread, not on the event loop
            stepper = await asyncio.to_thread(
                self.core.live.prepare, np.asarray(outcome.result.h, dtype=float)
            )
        for more in self.core.job_done(outcome, finished_at=self.clock(), stepper=stepper):
            self._launch(more)

    # --- device health (event-loop thread) --------------------------------------------------------------
    async def _watch_health(self, period_s: float = 1.0) -> None:
        while not self.closed:
            for event in self._device_watch.observe(self._devices()):
                self.record_event(event.device, event.kind, event.detail)
            await asyncio.sleep(period_s)

    def record_event(self, device: str, kind: str, detail: str = "") -> None:
        if self.writer is not None:
            self.writer.submit(DeviceEventData(self.clock(), device, kind, detail))
        self.on_event(f"{device}: {kind} {detail}".rstrip())

    # --- ChtcService: current values ------------------------------------------------------------------------
    def chtc(self) -> ChtcSnapshot | None:
        core = self.core
        with core.lock:
            rec = core.current
            if rec is None:
                return None
            newest = core.newest.t if core.newest is not None else None
            # codes only ("daq_no_good_data"): the snapshot and its ETag stay put while stale (ages: /readyz)
            problems = tuple(p.split(":")[0] for p in core.data_problems(self.clock())) if newest else ()
            status = self._status(rec, newest, problems)
            cond = core.condition
            key = (rec.id, status, newest, cond.id if cond else None, cond.state if cond else None, problems)
            if self._snap_cache is not None and self._snap_cache[0] == key:
                return self._snap_cache[1]
            bound = at_bound(rec, getattr(core.model.rom, "h_box", None), BOUND_REL_TOL)
            use = (
                usability(rec, bound=bound, condition=cond, data_problems=problems, restored=False)
                if newest is not None
                else Usability(False, "no_data: no sample acquired yet")
            )
            if use.usable and core.current_from_restore:
                use = Usability(False, "restored: the last stored H, not re-identified since the restart")
            snap = ChtcSnapshot(
                h=rec.h,
                ci95_lo=rec.ci95_lo,
                ci95_hi=rec.ci95_hi,
                identified=rec.identified & ~bound,
                identified_at=rec.finished_at,
                condition=rec.condition,
                f=float(rec.f if rec.f is not None else np.nan),
                fit=float(rec.fit if rec.fit is not None else np.nan),
                rmse_c=float(rec.rmse_c if rec.rmse_c is not None else np.nan),
                method=rec.method,
                model_version=rec.model_version,
                identification_id=rec.id,
                status=status,
                newest_sample_at=newest,
                at_bound=bound,
                usable_for_compensation=use.usable,
                reason=use.reason,
            )
            self._snap_cache = (key, snap)
            return snap

    def _status(
        self, rec: IdentificationRecord, newest: datetime | None, problems: tuple[str, ...]
    ) -> ChtcStatus:
        core = self.core
        if newest is None:
            return ChtcStatus.STALE if core.current_from_restore else ChtcStatus.NO_DATA
        if problems or core.current_from_restore:
            return ChtcStatus.STALE
        cond = core.condition
        if core.scheduler.running is not None or cond is None or cond.id != rec.condition.id:
            return ChtcStatus.IDENTIFYING
        if cond.state.value != "stable":
            return ChtcStatus.IDENTIFYING
        return ChtcStatus.FRESH

    def field(self, at: FieldAt) -> FieldSnapshot:
        core = self.core
        with core.lock:
            rec = core.current
            if rec is None:
                raise NoDataError("no identification yet: no temperature field")
            if not core.live.initialized:
                raise NoDataError("no sample yet: the live temperature field has not started")
            fe = core.model.fe
            if at == "now":
                snap = core.live.field_now()
                return FieldSnapshot(_utc(snap.t), "now", fe.nodes_rz, fe.triangles, snap.field_c, rec.id)
            key = (rec.id, core.condition.id if core.condition else None)
            if self._steady_cache is not None and self._steady_cache[0] == key:
                return self._steady_cache[1]
            steady = core.live.steady()
            out = FieldSnapshot(self.clock(), "steady", fe.nodes_rz, fe.triangles, steady, rec.id)
            self._steady_cache = (key, out)
            return out

    def sensors(self) -> Sequence[SensorReading]:
        core = self.core
        with core.lock:
            s = core.newest
            if s is None:
                raise NoDataError("no sample yet")
            pred = core.live.sensors_now() if core.current is not None and core.live.initialized else None
            cal = core.calibrator.current if core.calibrator is not None else None
            sd = core.calibrator.offset_sd() if core.calibrator is not None else None
            out = []
            for i, spec in enumerate(core.model.spec.sensors):
                q = s.quality[i] if i < len(s.quality) else "no_data"
                m = float(s.temps_c[i]) if q == "ok" and np.isfinite(s.temps_c[i]) else None
                p = float(pred[i]) if pred is not None else None
                off = float(cal.applied()[i]) if cal is not None else None
                res = m - (off or 0.0) - p if m is not None and p is not None else None  # offset-corrected
                out.append(
                    SensorReading(
                        *(spec.channel, spec.name, spec.role, spec.r_m, spec.z_m, m, p, res, q, s.t),
                        offset_c=off,
                        offset_sd_c=None if sd is None else float(sd[i]),
                        offset_calibrated_at=None if cal is None else cal.t_to,
                        offset_source=None if cal is None else cal.source,
                    )
                )
            return out

    def request_baseline(self) -> OffsetBaseline:
        c = self.core.request_baseline()
        return OffsetBaseline(
            c.t_from,
            c.t_to,
            c.source,
            c.samples,
            tuple(float(x) if np.isfinite(x) else None for x in c.offsets_c),
            tuple(float(x) for x in c.sd_c),
        )

    def condition(self) -> ConditionSnapshot:
        cond = self.core.condition
        if cond is None:
            raise NoDataError("no operating condition yet")
        return cond

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        with self.core.lock:
            return list(self.core.conditions)[: max(0, limit)]

    def sensor_history(self, since: datetime | None) -> SensorHistory:
        return self._history.since(since)

    def layout(self) -> SpindleLayout:
        spec = self.core.model.spec
        parts = tuple(SectionPart(r.name, r.material, r.r0_m, r.r1_m, r.z0_m, r.z1_m) for r in spec.regions)
        zones = tuple(ZoneInfo(z.name, z.description) for z in spec.zones)
        return SpindleLayout(spec.name, parts, zones)

    # --- ChtcService: history ---------------------------------------------------------------------------
    def list_identifications(
        self, *, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        partial = None
        if self.session_factory is not None:
            try:
                return self._db_page(since, until, limit, offset)
            except NotReadyError:  # the database is hung (read timed out or every read slot taken): 503
                raise
            except Exception as err:  # database down: serve what this process remembers, marked partial
                log.warning("identification history from memory (database: %s)", err)
                partial = f"database not readable, only the records in memory: {err}"
        with self.core.lock:
            rows = [
                r
                for r in self.core.records
                if (since is None or r.finished_at >= since) and (until is None or r.finished_at < until)
            ]
        rows.sort(key=lambda r: (r.finished_at, r.id), reverse=True)
        return IdentificationPage(rows[offset : offset + limit], len(rows), limit, offset, partial)

    def _db_page(
        self, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        from service.store.repository import list_identifications

        def read(session: Any) -> IdentificationPage:
            page = list_identifications(session, since=since, until=until, limit=limit, offset=offset)
            return IdentificationPage([row_to_record(r) for r in page.items], page.total, limit, offset)

        return self._merge_pending(self._db_read(read, "list identifications"), since, until)

    def _db_read(self, fn: Callable[[Any], Any], what: str) -> Any:
        """``fn(session)`` through the bounded read pool (503 when the database hangs), else inline."""
        if self.db_reads is not None:
            return self.db_reads.run(fn, what)
        from service.store.repository import session_scope

        with session_scope(self.session_factory, what) as session:
            return fn(session)

    def _merge_pending(
        self, page: IdentificationPage, since: datetime | None, until: datetime | None
    ) -> IdentificationPage:
        """Records still in the writer's buffer are not in the database yet: show them on the first page."""
        if page.offset != 0:
            return page
        stored = {r.id for r in page.items}
        newest_stored = max((r.id for r in page.items), default=0)
        with self.core.lock:
            extra = [
                r
                for r in self.core.records
                if r.id not in stored
                and r.id > newest_stored
                and (since is None or r.finished_at >= since)
                and (until is None or r.finished_at < until)
            ]
        if not extra:
            return page
        items = sorted([*extra, *page.items], key=lambda r: (r.finished_at, r.id), reverse=True)
        return IdentificationPage(items[: page.limit], page.total + len(extra), page.limit, page.offset)

    def get_identification(self, identification_id: int) -> IdentificationRecord:
        with self.core.lock:
            for r in self.core.records:
                if r.id == identification_id:
                    return r
        if self.session_factory is not None:
            from service.store.errors import DatabaseError, RecordNotFoundError
            from service.store.repository import get_identification

            try:
                return self._db_read(
                    lambda session: row_to_record(get_identification(session, identification_id)),
                    "get identification",
                )
            except RecordNotFoundError:
                pass
            except DatabaseError as err:  # down or refusing: a 503 naming the reason, not a 500
                raise NotReadyError(f"identification {identification_id}: {err}") from err
        raise NotFoundError(f"identification {identification_id} not found")

    # --- ChtcService: requests --------------------------------------------------------------------------
    def request_identification(self, reason: str) -> IdentificationJob:
        job, launches = self.core.request(reason)
        for launch in launches:
            self._launch(launch)
        return job

    def job(self, job_id: str) -> IdentificationJob:
        with self.core.lock:
            job = self.core.jobs.get(job_id)
        if job is None:
            raise NotFoundError(f"job {job_id!r} not found")
        return job

    # --- ChtcService: health and metrics ----------------------------------------------------------------
    def _devices(self) -> list[DeviceHealth]:
        now = self.clock()
        out = [self._source_health(name, src, now) for name, src in self.sources.items()]
        out.append(self._db_health(now))
        out.append(self._worker_health())
        return out

    def _source_health(self, name: str, src: Any, now: datetime) -> DeviceHealth:
        m = src.metrics
        last_ok = m.last_ok_t
        if not src.connected:
            status = DeviceStatus.DOWN
        elif src.is_stale() or m.errors:
            status = DeviceStatus.DEGRADED if not src.is_stale() else DeviceStatus.DOWN
        else:
            status = DeviceStatus.OK
        recent_error = m.last_error_t is not None and (now - m.last_error_t).total_seconds() <= 60.0
        if status is DeviceStatus.DEGRADED and not recent_error:
            status = DeviceStatus.OK  # old errors only: healthy again
        condition = src.condition() if hasattr(src, "condition") else ""  # e.g. CAN fault status
        if condition and status is DeviceStatus.OK:
            status = DeviceStatus.DEGRADED
        counters = {
            "polls": m.polls,
            "reads_ok": m.reads_ok,
            "reconnects": m.reconnects,
            **m.errors,
            **m.events,
        }
        # a recovered device's error is history; a CAN warning/fault status is the reason while it lasts
        message = condition or (m.last_error if status is not DeviceStatus.OK else "")
        return DeviceHealth(name, status, last_ok, age_s(last_ok, now), counters, message)

    def _db_health(self, now: datetime) -> DeviceHealth:
        if self.writer is None:
            return DeviceHealth("db", DeviceStatus.DISABLED, None, None, {}, "no database configured")
        st = self.writer.status()
        status = DeviceStatus.OK if st.connected else DeviceStatus.DOWN
        busy_s = getattr(st, "busy_s", None)
        hung = busy_s is not None and busy_s > getattr(st, "stall_s", 3.0)
        if st.connected and (st.pending > 1000 or hung):
            status = DeviceStatus.DEGRADED
        counters = {
            "pending": st.pending,
            "written": st.written,
            "dropped": st.dropped,
            "rejected": st.rejected,
            "errors": st.errors,
        }
        msg = (
            "" if st.connected else f"buffering {st.pending} records: {st.last_error or 'not connected yet'}"
        )
        if hung:
            msg = f"database not answering for {busy_s:.0f} s; buffering {st.pending} records"
        return DeviceHealth("db", status, st.last_ok_at, age_s(st.last_ok_at, now), counters, msg)

    def _worker_health(self) -> DeviceHealth:
        if self.worker is None:
            return DeviceHealth("worker", DeviceStatus.DISABLED, None, None, {}, "no identification worker")
        status = DeviceStatus.OK if self.worker.model_version is not None else DeviceStatus.DOWN
        counters = {"restarts": self.worker.restarts, **self.core.counts}
        running = self.worker.running_job
        msg = f"running job-{running}" if running is not None else "idle"
        return DeviceHealth("worker", status, None, None, counters, msg)

    def health(self) -> HealthSnapshot:
        return HealthSnapshot(
            t=self.clock(),
            devices=self._devices(),
            model_loaded=self.model_loaded,
            model_version=self.core.model.version if self.model_loaded else None,
            uptime_s=time.monotonic() - self._started_mono,
        )

    def ready(self) -> Readiness:
        reasons = []
        if not self.model_loaded:
            reasons.append("model not loaded")
        reasons.extend(self.core.data_problems(self.clock()))
        return Readiness(not reasons, tuple(reasons))

    def metrics(self) -> MetricsSnapshot:
        core = self.core
        now = self.clock()
        modbus = self.sources.get("modbus")
        can = self.sources.get("can")
        with core.lock:
            ages = core.channel_ages(now)
            quality = list(core.newest.quality) if core.newest is not None else ["no_data"] * len(ages)
            last = core.current
            counts = dict(core.counts)
            durations = core.durations.snapshot()
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
            model_version=core.model.version if self.model_loaded else None,
            channel_age_s=ages,
            channel_quality=quality,
            identifications_total=counts,
            identification_duration_s=durations,
            last_fit=None if last is None else last.fit,
            last_rmse_c=None if last is None else last.rmse_c,
            db_pending_rows=0 if st is None else int(st.pending),
            db_errors_total=0 if st is None else int(st.errors),
            reconnects_total=reconnects,
        )


def poll_outcomes(src: Any) -> dict[str, int]:
    """Modbus polls by outcome, one per poll: "ok", each failure by error class ("device_timeout",
    "short_reply", "modbus_exception", ...) and "link_down" (refused while a reconnect was not yet due)."""
    if src is None:
        return {}
    m = src.metrics
    out = {"ok": int(m.reads_ok), "link_down": int(m.events.get("polls_while_down", 0))}
    for name, n in m.errors.items():
        out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


def poll_events(src: Any) -> dict[str, int]:
    """Modbus events (not outcomes): "new_samples", "stale_polls", "restarts", ..."""
    if src is None:
        return {}
    return {_snake(k): int(n) for k, n in src.metrics.events.items() if k != "polls_while_down"}


def _frame_error(name: str) -> bool:
    """Whether an error class name (drivers.errors) is a rejected frame (not a counter gap on a good one)."""
    from drivers import errors

    cls = getattr(errors, name, None)
    return (
        isinstance(cls, type)
        and issubclass(cls, errors.FrameError)
        and not issubclass(cls, errors.CounterGapError)
    )


def frame_outcomes(src: Any) -> dict[str, int]:
    """CAN frames by outcome, one per frame read: "ok" or the reason it was rejected ("unknown_frame_id",
    "wrong_dlc", "bad_signal", ...)."""
    if src is None:
        return {}
    m = src.metrics
    out = {"ok": int(m.reads_ok)}
    for name, n in m.errors.items():
        if _frame_error(name):
            out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


def frame_events(src: Any) -> dict[str, int]:
    """CAN events: the driver's counters ("counter_gaps", "frames_lost", "faults", "warnings", ...) and the
    errors that are no frame ("device_timeout": silence, "device_unavailable": bus down)."""
    from drivers import errors

    if src is None:
        return {}
    m = src.metrics
    out = {_snake(k): int(n) for k, n in m.events.items()}
    for name, n in m.errors.items():
        cls = getattr(errors, name, None)
        if not _frame_error(name) and not (isinstance(cls, type) and issubclass(cls, errors.CounterGapError)):
            out[_snake(name)] = out.get(_snake(name), 0) + int(n)
    return out


@functools.cache
def _build_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spindle-chtc")
    except PackageNotFoundError:
        return "unknown"


def _snake(name: str) -> str:
    out = "".join("_" + c.lower() if c.isupper() else c for c in name).lstrip("_")
    return out.removesuffix("_error") or out


def _utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)
