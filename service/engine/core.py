"""The service's core: a pure state machine, ``handle(event) -> list[Instruction]``.

Events and instructions are defined in ``service.engine.events``. The core owns the condition detector, the
identification scheduler, the offset calibrator, the sample history (a ring buffer of its own) and the live
state, and keeps what the API reads. The live state is closed loop (``service.estimate.state.FilteredState``:
a Kalman filter on the reduced model, corrected by each sample's usable, offset-corrected channels); an
identification window starts from it (mean and covariance) and is not scheduled before it has
converged since the (re)start (``state_converging``). It does no I/O, takes no lock and imports no
database code: records to store, jobs to launch or cancel and lines to log come out as instructions, which
the asyncio shell (``service.engine.shell``) or the offline runner (``service.engine.offline``)
executes. After each event ``view()`` gives an immutable snapshot (``service.engine.view.CoreView``) that
the shell publishes for the API threads.

One caller drives a core, from one thread. The same events on a fresh core give the same instructions.

Time: the detector, the scheduler and the live state run on the sample time axis (UTC epoch seconds of the
samples' timestamps), so a simulated speed-up only has to scale the acquisition clock.

Errors::

    CoreError(ValueError)      an event the core does not know
    (drivers.ringbuffer.SampleOrderError: a sample older than the newest one; the state is unchanged)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from types import MappingProxyType

import numpy as np

from drivers.ringbuffer import RingBuffer, Sample
from model.identify import IdentificationResult
from service.acquire.calibration import (
    BaselineRefined,
    BaselineRejected,
    BaselineRequest,
    BaselineTaken,
    Calibration,
    OffsetCalibrator,
    Reading,
)
from service.acquire.history import RingHistory
from service.contracts.records import (
    ConditionEnd,
    ConditionStart,
    Record,
)
from service.engine.config import CoreConfig, Restored
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
from service.engine.idcounter import IdCounter, rebase_ids
from service.engine.jobbook import Job, JobBook, MapValues, job_key
from service.engine.jobs import Offsets, converging_reason, job_request, job_window
from service.engine.mapbook import MapBook
from service.engine.samples import SampleBook
from service.engine.view import CoreView, NewestSample
from service.errors import ServiceError
from service.estimate.live import LiveStateError
from service.estimate.state import FilteredState
from service.estimate.state import h_rel_from_ci as _h_rel
from service.identify import scheduler as sched
from service.identify.detector import (
    ConditionChanged,
    ConditionDetector,
    DetectorStatus,
    OperatingPoint,
    SampleEvent,
)
from service.identify.mapjob import MapJob
from service.identify.speedmap import SpeedMap
from service.identify.window import InsufficientWindowError
from service.identify.worker import JobOutcome, JobStatus
from service.modelload import LoadedModel
from service.serve.interface import (
    ConditionSnapshot,
    ConditionState,
    IdentificationRecord,
)
from service.store.calibrations import calibration_record

__all__ = ["CoreConfig", "CoreError", "Restored", "ServiceCore"]

CONDITIONS_KEPT = 200


class CoreError(ServiceError, ValueError):
    """An event the core does not know."""


@dataclass
class _Out:
    """The instructions of one ``handle`` call, each stamped with the event's id."""

    event_id: str
    instructions: list[Instruction] = field(default_factory=list)

    def store(self, record: Record) -> None:
        self.instructions.append(Store(self.event_id, record))

    def log(self, message: str) -> None:
        self.instructions.append(Log(self.event_id, message))

    def reject(self, kind: RejectKind, reason: str) -> None:
        self.instructions.append(Rejected(event_id=self.event_id, kind=kind, reason=reason))


def utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)


class ServiceCore:
    """See the module docstring. ``history_capacity``: samples kept for identification windows."""

    def __init__(
        self,
        config: CoreConfig,
        *,
        model: LoadedModel,
        restored: Restored | None = None,
        history_capacity: int = 8640,
    ) -> None:
        self.config = config
        self.model = model
        restored = restored or Restored()
        n_sensors = len(model.spec.sensors)
        self._ring = RingBuffer(history_capacity, n_sensors)
        self._history = RingHistory(self._ring)
        last_point = None
        if restored.conditions:
            c = restored.conditions[0]
            last_point = OperatingPoint(speed_rpm=c.speed_rpm, torque_nm=c.torque_nm, ambient_c=c.ambient_c)
        self._detector = ConditionDetector(config.detector, reference=last_point)
        self._scheduler = sched.IdentificationScheduler(
            config=config.scheduler, history=list(restored.history)
        )
        last = restored.last
        h0 = np.asarray(last.h if last is not None else config.initial_h, dtype=float)
        self._live = FilteredState(
            model.rom,
            model.spec,
            h=h0,
            dt_s=config.rules.dt_s,
            settings=replace(config.filter, keep_s=3 * _longest_window_s(config)),
        )
        # the considered H error: the stored result's CI, 100 % for the guessed initial H
        self._live.set_h(h0, h_rel=1.0 if last is None else _h_rel(last.h, last.ci95_hi))
        self._condition: ConditionSnapshot | None = restored.conditions[0] if restored.conditions else None
        self._conditions: tuple[ConditionSnapshot, ...] = tuple(restored.conditions[:CONDITIONS_KEPT])
        self._current: IdentificationRecord | None = restored.last
        self._current_from_restore = restored.last is not None
        self._jobs = JobBook(
            next_identification_id=restored.next_identification_id,
            model_version=model.version,
            method=config.method,
        )
        self._cond_ids = IdCounter(restored.next_condition_id)
        self._resumed = self._condition is not None
        # a condition that started while the live state converges: its schedule counts from the convergence
        self._held: sched.ConditionStarted | None = None
        self._samples = SampleBook(
            n_sensors,
            min_good_channels=config.rules.min_good_channels,
            store_period_s=config.sample_store_period_s,
        )
        cal = config.calibration
        self._calibrator = (
            None
            if cal is None
            else OffsetCalibrator(config=cal, sample_period_s=config.rules.dt_s, current=restored.calibration)
        )
        if self._calibrator is not None:  # a restored baseline's offsets go to the filter at once
            self._live.set_offsets(self._calibrator.offsets(), self._calibrator.offset_sd())
        # speed-map mode (docs/design/hmap.md): the latest map fit (a restored one is stale until re-fitted)
        self._speed_map: SpeedMap | None = restored.speed_map if config.speed_map is not None else None
        self._map = None if config.speed_map is None else MapBook(config, model, self._speed_map)
        # combined mode: the newest map fit and per-condition identification; the held condition's
        # per-condition one serves (``current``) while the condition holds, the map's elsewhere (map_serves)
        self._combined = self._map is not None and config.combined
        map_last = None if self._speed_map is None else (restored.map_last or restored.last)
        self._restored_recs = tuple(r for r in (restored.last, map_last) if r is not None)
        self._map_rec: IdentificationRecord | None = map_last
        self._cond_rec: IdentificationRecord | None = None if restored.last is map_last else restored.last
        self._cond_load: tuple[float, float] | None = None  # the per-condition fit's bearing-heat scales
        self._map_serves = True
        if map_last is not None:  # the restored map serves (stale until re-fitted), whatever was last
            self._current = map_last
        self._serve_held()

    # --- the state machine ----------------------------------------------------------------------------------
    def handle(self, event: Event) -> list[Instruction]:
        """One event in, what to do out (see ``service.engine.events``)."""
        out = _Out(event.event_id)
        match event:
            case SampleReceived():
                self._on_sample(event.sample, out)
            case JobOutcomeReceived():
                self._on_outcome(event, out)
            case ManualRequested():
                self._on_manual(event.reason, out)
            case BaselineRequested():
                self._on_baseline(event.t, out)
            case IdsKnown():
                rebase_ids(event, self._cond_ids, self._jobs.id_counter, out.log)
            case _:
                raise CoreError(f"unknown core event {type(event).__name__}")
        return out.instructions

    def view(self) -> CoreView:
        """The immutable snapshot of the state now (cheap: the large parts are shared, not copied)."""
        running = self._scheduler.running
        cal = self._calibrator
        sd = None
        if cal is not None:
            sd = np.array(cal.offset_sd(), dtype=float)
            sd.setflags(write=False)
        book = self._samples
        return CoreView(
            newest=book.newest,
            condition=self._condition,
            conditions=self._conditions,
            current=self._current,
            current_from_restore=self._current_from_restore,
            records=self._jobs.records,
            jobs=self._jobs.jobs_view,
            running_job=None if running is None else job_key(running.job_id),
            counts=MappingProxyType(dict(self._jobs.counts)),
            durations=self._jobs.durations,
            last_ok_t=tuple(float(x) for x in book.last_ok_t),
            last_good_daq_t=book.last_good_daq_t,
            last_good_can_t=book.last_good_can_t,
            calibration=None if cal is None else cal.current,
            offset_sd_c=sd,
            live=self._live.view() if self._live.initialized else None,
            stale_after_s=self.config.stale_after_s,
            min_good_channels=self.config.rules.min_good_channels,
            map_config=self.config.speed_map,
            speed_map=self._speed_map,
            map_serves=self._map_serves,
            ci_threshold=self.config.ci_threshold,
        )

    @property
    def live_h(self) -> np.ndarray:
        """The live state's current H (7,) W/(m²·K) (a copy)."""
        return np.array(self._live.h, dtype=float)

    # --- samples --------------------------------------------------------------------------------------------
    def _on_sample(self, sample: Sample, out: _Out) -> None:
        """Store, advance the live state, detect, schedule."""
        self._ring.append(sample)  # first: an out-of-order sample raises before anything changed
        ts = sample.t.timestamp()
        newest = self._samples.observe(sample)
        self._follow_condition()
        self._calibrate(newest, out)
        row = self._samples.to_store(newest)
        if row is not None:
            out.store(row)
        self._advance_live(newest, ts)
        todo: list[sched.Instruction] = []
        if self._resumed:
            todo += self._resume(ts, out)
        ready = self._live.ready_at()
        if self._held is not None and ready is not None:
            held, self._held = self._held, None
            out.log(f"live state converged: condition {held.condition_id}'s schedule counts from now")
            todo += self._scheduler.handle(replace(held, t=ts, t_start=max(held.t_start, ready)))
        for change in self._detector.handle(
            SampleEvent(
                t=ts,
                speed_rpm=float(sample.speed_rpm),
                torque_nm=float(sample.torque_nm),
                ambient_c=float(sample.ambient_c),
            )
        ):
            todo += self._on_change(change, out)
        if self._map is not None:  # speed-map and combined mode: the map's own trigger
            self._follow_condition()  # combined mode: a change pending since this sample serves the map
            self._serve_held()
            self._map_sample(newest, ts, out)
            if not self._combined:  # speed-map mode: no per-condition schedule
                return
        todo += self._scheduler.handle(sched.Tick(ts))
        self._execute(todo, ts, out)

    def _follow_condition(self) -> None:
        """The current condition is CHANGING while the detector holds a candidate, else STABLE."""
        cond = self._condition
        if cond is not None and self._detector.status is DetectorStatus.PENDING:
            if cond.state is not ConditionState.CHANGING:
                self._set_condition(replace(cond, state=ConditionState.CHANGING))
        elif cond is not None and cond.state is not ConditionState.STABLE:
            self._set_condition(replace(cond, state=ConditionState.STABLE))

    def _calibrate(self, s: NewestSample, out: _Out) -> None:
        if self._calibrator is None:
            return
        ok = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        reading = Reading(t=s.t, temps_c=s.temps_c, ok=ok, ambient_c=s.ambient_c, speed_rpm=s.speed_rpm)
        self._calibrated(self._calibrator.handle(reading), out)

    def _calibrated(
        self, instructions: Sequence[BaselineTaken | BaselineRefined | BaselineRejected], out: _Out
    ) -> Calibration | None:
        for ins in instructions:
            if isinstance(ins, BaselineRefined):  # the same rest, a longer average: stored, no message
                out.store(calibration_record(ins.calibration))
                self._live.set_offsets(ins.calibration.applied(), ins.calibration.sd_c)
            if isinstance(ins, BaselineTaken):
                c = ins.calibration
                out.store(calibration_record(c))
                out.log(
                    f"sensor offsets zeroed ({c.source} baseline, {c.samples} samples at rest until "
                    f"{c.t_to.isoformat(timespec='seconds')}): {np.nanmin(c.offsets_c):+.2f}.."
                    f"{np.nanmax(c.offsets_c):+.2f} °C"
                )
                out.instructions.append(Calibrated(out.event_id, c))
                self._live.set_offsets(c.applied(), c.sd_c)
                return c
        return None

    def _on_baseline(self, t: datetime, out: _Out) -> None:
        """Take a baseline now from the newest samples at rest; ``Rejected`` naming why not."""
        if self._calibrator is None:
            out.reject(RejectKind.NOT_READY, "sensor calibration is disabled")
            return
        newest = self._samples.newest
        at = newest.t if newest is not None else t
        result = self._calibrator.handle(BaselineRequest(at))
        if self._calibrated(result, out) is None:
            why = next((r.reason for r in result if isinstance(r, BaselineRejected)), "no baseline")
            out.reject(RejectKind.NOT_READY, why)

    def _advance_live(self, s: NewestSample, ts: float) -> None:
        """Predict to the sample and correct with its usable channels (quality OK, finite; the calibration's
        offsets are subtracted inside the filter)."""
        inputs = (s.ambient_c, s.speed_rpm, s.torque_nm)
        usable = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        temps = np.where(usable, s.temps_c, 0.0)
        if self._live.initialized:
            self._live.push(
                ts,
                ambient_c=inputs[0],
                speed_rpm=inputs[1],
                torque_nm=inputs[2],
                temps_c=temps,
                usable=usable,
            )
            return
        if not np.isfinite(inputs).all():
            return  # wait for ambient, speed and torque (CAN may come up after the DAQ) before starting
        self._live.initialize(ts, inputs, temps, usable)

    def _resume(self, ts: float, out: _Out) -> list[sched.Instruction]:
        """After a restart the stored condition continues; its data start now (the ring buffer is empty)."""
        self._resumed = False
        cond = self._condition
        assert cond is not None
        point = OperatingPoint(speed_rpm=cond.speed_rpm, torque_nm=cond.torque_nm, ambient_c=cond.ambient_c)
        out.log(f"resumed condition {cond.id} ({cond.speed_rpm:.0f} rpm) from the database")
        return self._condition_started(
            sched.ConditionStarted(t=ts, condition_id=cond.id, point=point, t_start=ts)
        )

    def _on_change(self, change: ConditionChanged, out: _Out) -> list[sched.Instruction]:
        cid = next(self._cond_ids)
        started = utc(change.t_start)
        if self._condition is not None:
            out.store(ConditionEnd(id=self._condition.id, ended_at=started))
        p = change.point
        out.store(
            ConditionStart(
                id=cid,
                started_at=started,
                speed_rpm=p.speed_rpm,
                torque_nm=p.torque_nm,
                ambient_c=p.ambient_c,
            )
        )
        snap = ConditionSnapshot(
            id=cid,
            speed_rpm=p.speed_rpm,
            torque_nm=p.torque_nm,
            ambient_c=p.ambient_c,
            since=started,
            state=ConditionState.STABLE,
        )
        self._set_condition(snap, new=True)
        if self._live.initialized:
            self._live.mark(change.t_start)
        out.log(
            f"condition {cid}: {p.speed_rpm:.0f} rpm, {p.torque_nm:.2f} N·m, {p.ambient_c:.2f} °C "
            f"since {started.isoformat(timespec='seconds')} ({change.reason})"
        )
        return self._condition_started(
            sched.ConditionStarted(t=change.t_confirmed, condition_id=cid, point=p, t_start=change.t_start)
        )

    def _condition_started(self, ev: sched.ConditionStarted) -> list[sched.Instruction]:
        """Tell the scheduler, counting the condition's schedule from max(its start, the live state's
        convergence): while the state converges after a (re)start the start is held (the newest wins)."""
        if self._map is not None:  # speed-map and combined mode: a change triggers a map fit (debounced)
            self._map.changed_at = ev.t
            if not self._combined:
                return []
        ready = self._live.ready_at()
        if ready is None:
            self._held = ev
            return []
        return self._scheduler.handle(replace(ev, t_start=max(ev.t_start, ready)))

    def _set_condition(self, snap: ConditionSnapshot, *, new: bool = False) -> None:
        self._condition = snap
        if new or not self._conditions:
            self._conditions = (snap, *self._conditions[: CONDITIONS_KEPT - 1])
        else:
            self._conditions = (snap, *self._conditions[1:])

    # --- scheduler instructions -----------------------------------------------------------------------------
    def _execute(
        self, instructions: Sequence[sched.Instruction], ts: float, out: _Out, manual_reason: str = ""
    ) -> None:
        queue = list(instructions)
        while queue:
            ins = queue.pop(0)
            if isinstance(ins, sched.StartJob):
                queue += self._start(ins, ts, out, manual_reason)
            elif isinstance(ins, sched.CancelJob):
                self._cancel(ins, out)

    def _start(
        self, start: sched.StartJob, ts: float, out: _Out, manual_reason: str
    ) -> list[sched.Instruction]:
        """Build the job's window and launch it, or end it at once (idle spindle, too few data)."""
        now = utc(ts)
        if self._live.ready_at() is None:
            # no job and no stored outcome: the scheduler retries at its next time (/chtc says why meanwhile)
            why = converging_reason(self._live)
            out.log(f"identification for condition {start.condition_id} deferred: {why}")
            return self._scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=why))
        if start.trigger == "manual":
            reason = manual_reason or "manual"
        else:
            reason = "condition-change" if self._jobs.first_of(start.condition_id) else "scheduled"
        job = self._jobs.open(start, reason=reason, now=now, event_id=out.event_id)
        if abs(start.point.speed_rpm) < self.config.min_speed_rpm:
            msg = (
                f"spindle idle ({start.point.speed_rpm:.0f} rpm < {self.config.min_speed_rpm:.0f} rpm): "
                "no bearing heat, H1-H7 are not identifiable"
            )
            self._store_outcome(job, outcome="skipped", message=msg, finished_at=now, out=out)
            return self._scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=msg))
        try:
            window = job_window(start, self._live, self._history, self.config)
        except (InsufficientWindowError, LiveStateError) as err:
            msg = err.reason if isinstance(err, InsufficientWindowError) else str(err)
            self._store_outcome(job, outcome="insufficient-data", message=msg, finished_at=now, out=out)
            return self._scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=msg))
        cal = self._calibrator
        offsets = None if cal is None else Offsets(cal.offsets(), cal.offset_sd())
        request = job_request(start, window, config=self.config, offsets=offsets)
        snap, arrays = window.start, window.arrays
        job = self._jobs.launched(job, window_from=utc(snap.t), window_to=utc(float(arrays.times_s[-1])))
        out.instructions.append(Launch(event_id=out.event_id, job_key=job.key, request=request))
        out.log(
            f"identification {job.key}: condition {start.condition_id}, "
            f"window {arrays.n_steps * arrays.dt_s / 60:.0f} min, "
            f"{int(arrays.mask.sum())} sensors, warm start from {start.warm_source}"
        )
        return []

    def _cancel(self, ins: sched.CancelJob, out: _Out) -> None:
        out.instructions.append(Cancel(event_id=out.event_id, job_id=ins.job_id, reason=ins.reason))
        job = self._jobs.waiting(ins.job_id)
        self._jobs.cancelling(ins.job_id, ins.reason)
        if job is not None:
            out.log(f"identification {job.key} cancelling: {ins.reason}")

    # --- outcomes -------------------------------------------------------------------------------------------
    def _on_outcome(self, ev: JobOutcomeReceived, out: _Out) -> None:
        """Record a worker outcome; launch what the scheduler wants next."""
        outcome = ev.outcome
        job = self._jobs.take(outcome.job_id, outcome.wall_s)
        if job is None:
            return
        newest = self._samples.newest
        ts = (newest.t if newest is not None else ev.finished_at).timestamp()
        if self._map is not None and self._map.running == outcome.job_id:
            self._map_outcome(job, ev, ts, out)
            return
        running = self._scheduler.running
        if outcome.status is JobStatus.CANCELLED or running is None or running.job_id != outcome.job_id:
            self._store_outcome(
                job,
                outcome="cancelled",
                message=outcome.message or "cancelled",
                finished_at=ev.finished_at,
                out=out,
            )
            return
        if outcome.status is JobStatus.INSUFFICIENT_DATA:
            self._store_outcome(
                job, outcome="insufficient-data", message=outcome.message, finished_at=ev.finished_at, out=out
            )
            more = self._scheduler.handle(
                sched.JobSkipped(t=ts, job_id=outcome.job_id, reason=outcome.message)
            )
        elif outcome.status is JobStatus.FAILED or outcome.result is None:
            self._store_outcome(
                job, outcome="failed", message=outcome.message, finished_at=ev.finished_at, out=out
            )
            more = self._scheduler.handle(
                sched.JobFailed(t=ts, job_id=outcome.job_id, reason=outcome.message)
            )
        else:
            result: IdentificationResult = outcome.result
            rec = self._store_result(job, outcome=outcome, result=result, ev=ev, out=out)
            h = tuple(float(x) for x in rec.h)
            more = self._scheduler.handle(sched.JobFinished(t=ts, job_id=outcome.job_id, h=h))
        self._execute(more, ts, out)

    def _store_result(
        self,
        job: Job,
        *,
        outcome: JobOutcome,
        result: IdentificationResult,
        ev: JobOutcomeReceived,
        out: _Out,
    ) -> IdentificationRecord:
        data, rec = self._jobs.identified(
            job, result, finished_at=ev.finished_at, event_id=out.event_id, condition=self._condition_of(job)
        )
        out.store(data)
        ls = result.load_scale
        load = None if ls is None else (float(ls[0]), float(ls[1]))
        if self._combined:
            self._cond_rec, self._cond_load = rec, load
            self._serve_held()
        else:
            self._current = rec
            self._current_from_restore = False
            self._live.set_h(rec.h, load, h_rel=_h_rel(rec.h, rec.ci95_hi))
        h_txt = ", ".join(f"{x:.1f}" for x in rec.h)
        out.log(
            f"identification {job.key} ok: H = [{h_txt}] W/(m²·K), fit {rec.fit:.4f}, "
            f"RMSE {rec.rmse_c:.3f} °C, {outcome.wall_s:.2f} s"
        )
        return rec

    def _store_outcome(
        self, job: Job, *, outcome: str, message: str, finished_at: datetime, out: _Out
    ) -> None:
        data, _ = self._jobs.ended(
            job,
            outcome=outcome,
            message=message,
            finished_at=finished_at,
            event_id=out.event_id,
            condition=self._condition_of(job),
        )
        out.store(data)
        out.log(f"identification {job.key} {outcome}: {message}")

    def _condition_of(self, job: Job) -> ConditionSnapshot:
        cid = job.start.condition_id
        cond = next((c for c in self._conditions if c.id == cid), self._condition)
        assert cond is not None
        return cond

    # --- manual requests ------------------------------------------------------------------------------------
    def _on_manual(self, reason: str, out: _Out) -> None:
        """An identification requested through the API: ``ManualAccepted`` or ``Rejected``."""
        newest = self._samples.newest
        if newest is None:
            out.reject(RejectKind.NOT_READY, "no samples yet: nothing to identify from")
            return
        if self._map is not None:
            self._map_manual(reason, newest, out)
            return
        running = self._scheduler.running
        if running is not None:
            why = f"identification {job_key(running.job_id)} is already running"
            out.reject(RejectKind.BUSY, why)
            return
        ts = newest.t.timestamp()
        todo = self._scheduler.handle(sched.ManualRequest(ts, requested_by=reason))
        for ins in todo:
            if isinstance(ins, sched.ManualRejected | sched.ManualQueued):
                kind = RejectKind.NOT_READY if isinstance(ins, sched.ManualRejected) else RejectKind.BUSY
                out.reject(kind, ins.reason)
                return
        self._execute(todo, ts, out, manual_reason=(reason or "manual")[:32])
        start = next(i for i in todo if isinstance(i, sched.StartJob))
        job = self._jobs.jobs_view[job_key(start.job_id)]
        out.instructions.append(ManualAccepted(out.event_id, job))

    # --- speed-map mode (docs/design/hmap.md) ---------------------------------------------------------------
    def _map_sample(self, s: NewestSample, ts: float, out: _Out) -> None:
        """Count the sample's speed, give the live state H from the map at its speed, fit when due."""
        book = self._map
        assert book is not None
        book.tally.add(ts, s.speed_rpm, self.config.rules.dt_s)
        self._map_live_h(s)
        reason = book.due(ts)
        if reason is not None:
            self._map_launch(ts, reason, out)

    def _serve_held(self) -> None:
        """Combined mode: which identification serves (``current``, the live state's H). The per-condition one
        of the current condition while that condition is stable (not restored: a stored one waits for
        its re-identification, as in per-condition mode); else the newest map fit (the per-condition one
        when there is no map yet). Measured better at a held condition on the chain and after restarts,
        the map on a duty cycle (docs/design/hmap.md "Combined mode")."""
        if not self._combined:
            return
        pc, cond = self._cond_rec, self._condition
        held = (
            pc is not None
            and all(pc is not r for r in self._restored_recs)
            and cond is not None
            and pc.condition.id == cond.id
            and cond.state is ConditionState.STABLE
        )
        target = pc if held else (self._map_rec if self._map_rec is not None else pc)
        serves = not held and self._map_rec is not None
        if target is None or (target is self._current and serves == self._map_serves):
            return
        self._current = target
        self._current_from_restore = any(target is r for r in self._restored_recs)
        self._map_serves = serves
        book = self._map
        assert book is not None
        book.live_key = None  # the map's H is set again at the next sample when it serves
        if held and pc is not None:
            self._live.set_h(pc.h, self._cond_load, h_rel=_h_rel(pc.h, pc.ci95_hi))

    def _map_live_h(self, s: NewestSample) -> None:
        """The live state's H: the map's (the cold prior's before the first fit) at the sample's speed and
        ambient, with the band as its considered error (recomputed when the speed bin or the map changes);
        in combined mode not while the held condition's per-condition H serves."""
        book = self._map
        assert book is not None
        if not self._map_serves:
            return
        if not (np.isfinite(s.speed_rpm) and np.isfinite(s.ambient_c)):
            return
        mean, cov, which = book.live_theta(s.t.timestamp(), self._speed_map)
        key = (round(abs(s.speed_rpm) / book.cfg.bin_rpm), round(s.ambient_c), which)
        if key == book.live_key:
            return
        book.live_key = key
        h, _, hi = book.family.h_ci95_at(mean, cov, [abs(s.speed_rpm)], s.ambient_c)
        self._live.set_h(h[0], h_rel=_h_rel(h[0], hi[0]))

    def _map_launch(self, ts: float, reason: str, out: _Out) -> str | None:
        """Launch a map fit over the rolling window ending now; None, or why not (stored when it is a job
        that could not run)."""
        book = self._map
        assert book is not None
        cond = self._condition
        ready = self._live.ready_at()
        if ready is None:
            return converging_reason(self._live)
        if cond is None:
            return "no operating condition yet"
        cfg = book.cfg
        t_from = max(ts - cfg.window_s, ready)
        if ts - t_from < cfg.min_window_s - 0.5 * self.config.rules.dt_s:
            return (
                f"{ts - t_from:.0f} s of data since the live state converged (need {cfg.min_window_s:.0f} s)"
            )
        jid = self._scheduler.reserve_job_id()
        point = OperatingPoint(speed_rpm=cond.speed_rpm, torque_nm=cond.torque_nm, ambient_c=cond.ambient_c)
        prior, source = book.prior_for(t_from, ts)
        start = sched.StartJob(
            job_id=jid,
            condition_id=cond.id,
            point=point,
            t_from=t_from,
            t_to=ts,
            warm_start=None,
            warm_source=source,
            trigger="map",
        )
        now = utc(ts)
        job = self._jobs.open(start, reason=reason, now=now, event_id=out.event_id)
        rules = replace(self.config.rules, min_window_s=cfg.min_window_s)
        book.changed_at = None
        try:
            window = job_window(start, self._live, self._history, replace(self.config, rules=rules))
        except (InsufficientWindowError, LiveStateError) as err:
            msg = err.reason if isinstance(err, InsufficientWindowError) else str(err)
            self._store_outcome(job, outcome="insufficient-data", message=msg, finished_at=now, out=out)
            book.retry_after = ts + cfg.debounce_s + self.config.rules.dt_s
            return msg
        cal = self._calibrator
        offsets = None if cal is None else Offsets(cal.offsets(), cal.offset_sd())
        request = job_request(start, window, config=self.config, offsets=offsets)
        prior, start_cov = book.intersect(prior, np.array(window.start.cov))
        request = replace(
            request,
            speed_map=MapJob(
                family=cfg.family,
                prior_mean=prior.mean,
                prior_cov=prior.cov,
                start_mean=None if self._speed_map is None else np.array(self._speed_map.mean),
            ),
            start_cov=start_cov,
            carry_start_error=False,
            start_modes=self.config.start_modes,
        )
        snap, arrays = window.start, window.arrays
        job = self._jobs.launched(job, window_from=utc(snap.t), window_to=utc(float(arrays.times_s[-1])))
        book.launched(jid, t_end=float(arrays.times_s[-1]), mask_used=int(arrays.mask.sum()))
        out.instructions.append(Launch(event_id=out.event_id, job_key=job.key, request=request))
        out.log(
            f"map identification {job.key} ({reason}): window {arrays.n_steps * arrays.dt_s / 60:.0f} min, "
            f"{int(arrays.mask.sum())} sensors, prior from {source}"
        )
        return None

    def _map_outcome(self, job: Job, ev: JobOutcomeReceived, ts: float, out: _Out) -> None:
        """A map fit came back: keep its posterior (the map served from now on) and store it."""
        book = self._map
        assert book is not None
        outcome = ev.outcome
        t_end, used, visited = book.finished()
        fit = outcome.map_fit
        if outcome.status is not JobStatus.OK or fit is None:
            kind = "insufficient-data" if outcome.status is JobStatus.INSUFFICIENT_DATA else "failed"
            if outcome.status is JobStatus.CANCELLED:
                kind = "cancelled"
            self._store_outcome(
                job, outcome=kind, message=outcome.message, finished_at=ev.finished_at, out=out
            )
            return
        m = SpeedMap(
            family=book.cfg.family,
            mean=fit.posterior.mean,
            cov=fit.posterior.cov,
            visited_rpm=visited[0],
            visited_s=visited[1],
            fitted_at=utc(t_end),
            rmse_c=float(fit.rmse_c),
        )
        cond = self._condition_of(job)
        newest = self._samples.newest
        amb = newest.ambient_c if newest is not None and np.isfinite(newest.ambient_c) else cond.ambient_c
        h, lo, hi = m.h_at([job.start.point.speed_rpm], amb)
        half = 0.5 * np.log(hi[0] / lo[0])
        values = MapValues(
            h=tuple(float(x) for x in h[0]),
            ci95_lo=tuple(float(x) for x in lo[0]),
            ci95_hi=tuple(float(x) for x in hi[0]),
            identified=tuple(bool(x) for x in half <= self.config.ci_threshold),
            rmse_c=float(fit.rmse_c),
            nfev=int(fit.nfev),
            wall_s=float(outcome.wall_s),
            n_sensors_used=used,
            message=outcome.message,
            speed_map=m.to_json(),
        )
        data, rec = self._jobs.mapped(
            job, values=values, finished_at=ev.finished_at, event_id=out.event_id, condition=cond
        )
        out.store(data)
        self._speed_map = replace(m, identification_id=data.id)
        book.keep(t_end, fit.posterior)
        if self._combined:
            self._map_rec = rec
            self._serve_held()
        else:
            self._current = rec
            self._current_from_restore = False
        out.log(
            f"map identification {job.key} ok: {fit.nfev} model runs, RMSE {fit.rmse_c:.3f} °C, "
            f"{outcome.wall_s:.2f} s; visited {len(visited[0])} speed bins"
        )

    def _map_manual(self, reason: str, newest: NewestSample, out: _Out) -> None:
        book = self._map
        assert book is not None
        if book.running is not None:
            out.reject(RejectKind.BUSY, f"map identification {job_key(book.running)} is already running")
            return
        ts = newest.t.timestamp()
        why = self._map_launch(ts, (reason or "manual")[:32], out)
        launched = next((i for i in out.instructions if isinstance(i, Launch)), None)
        if launched is None:
            out.reject(RejectKind.NOT_READY, why or "no map identification possible now")
            return
        out.instructions.append(ManualAccepted(out.event_id, self._jobs.jobs_view[launched.job_key]))


def _longest_window_s(config: CoreConfig) -> float:
    """The longest window a job may start back in time [s]: the per-condition ``max_window_s`` or, in
    speed-map mode, the map's rolling window if longer (the live state keeps its snapshots 3× this long; a
    map window starting before the oldest kept snapshot could not start: found with a 90-s
    ``max_window_s`` and the map's 10-min first window, tests/service/test_speed_map.py)."""
    longest = config.scheduler.max_window_s
    return longest if config.speed_map is None else max(longest, config.speed_map.window_s)
