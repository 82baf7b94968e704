"""The service's core: a pure state machine, ``handle(event) -> list[Instruction]``.

Events and instructions are defined in ``service.core.events``. The core owns the condition detector, the
identification scheduler, the offset calibrator, the sample history (a ring buffer of its own) and the live
state, and keeps what the API reads. The live state is closed loop (``service.estimate.state.FilteredState``:
a Kalman filter on the reduced model, corrected by each sample's usable, offset-corrected channels); an
identification window starts from it (mean and covariance) and is not scheduled before it has
converged since the (re)start (``state_converging``). It does no I/O, takes no lock and imports no
database code: records to store, jobs to launch or cancel and lines to log come out as instructions, which
the asyncio shell (``service.shell.service``) or the offline runner (``service.core.offline``)
executes. After each event ``view()`` gives an immutable snapshot (``service.core.view.CoreView``) that
the shell publishes for the API threads.

The identification mode (``CoreConfig.mode``) is one serving strategy (``service.core.serving``): it
builds the tracks that run, the per-condition schedule (``service.core.schedtrack``) and the speed map
(``service.core.maptrack``), each a stand-in when the mode does not run it, and decides which
identification serves. The core hands each sample to both tracks and each outcome to the track that owns
its job; it tests no mode. The state the core and its tracks share is a ``service.core.parts.CoreParts``.

One caller drives a core, from one thread. The same events on a fresh core give the same instructions.

Time: the detector, the scheduler and the live state run on the sample time axis (UTC epoch seconds of the
samples' timestamps), so a simulated speed-up only has to scale the acquisition clock.

Errors::

    CoreError(ServiceError, ValueError)      an event the core does not know
    (drivers.ringbuffer.SampleOrderError: a sample older than the newest one; the state is unchanged)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from datetime import datetime
from types import MappingProxyType

import numpy as np

from drivers.ringbuffer import RingBuffer, Sample
from service.acquire.calibration import (
    BaselineRefined,
    BaselineRejected,
    BaselineRequest,
    BaselineTaken,
    OffsetCalibrator,
    Reading,
)
from service.acquire.history import RingHistory
from service.contracts.calibration import Calibration
from service.contracts.checkpoint import CheckpointError
from service.contracts.commissionbaseline import COMMISSIONING, commissioning_baseline
from service.contracts.errors import RecordError
from service.contracts.records import ConditionEnd, ConditionStart
from service.contracts.snapshots import ConditionSnapshot, ConditionState
from service.core.baselinecheck import MAX_SLOPE, BaselineCheck, needs_check
from service.core.config import CoreConfig, Restored
from service.core.events import (
    BaselineAdopted,
    BaselineRequested,
    Calibrated,
    Event,
    IdsKnown,
    Instruction,
    JobOutcomeReceived,
    ManualRequested,
    RejectKind,
    SampleReceived,
)
from service.core.idcounter import IdCounter, rebase_ids
from service.core.jobbook import JobBook, job_key
from service.core.parts import CONDITIONS_KEPT, CoreParts, Out, live_h_rel, utc
from service.core.restorecut import cut_future
from service.core.samples import SampleBook
from service.core.serving import serving_for
from service.core.view import CoreView, NewestSample
from service.errors import ServiceError
from service.estimate.sensorfaults import fault_lines
from service.estimate.state import FilteredState
from service.identify import scheduler as sched
from service.identify.detector import ConditionChanged, ConditionDetector, OperatingPoint, SampleEvent
from service.modelload import LoadedModel

__all__ = ["CoreConfig", "CoreError", "Restored", "ServiceCore"]


class CoreError(ServiceError, ValueError):
    """An event the core does not know."""


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
        self._capacity = history_capacity
        self._restored: Restored | None = restored or Restored()  # until the first sample (``cut_future``)
        self._build(self._restored)

    def _build(self, restored: Restored) -> None:
        """The parts from what the database knew (again at the first sample when some of it was dated after
        that sample: ``service.core.restorecut``)."""
        config, model = self.config, self.model
        serving = serving_for(config.mode, restored)
        n_sensors = len(model.spec.sensors)
        self._ring = RingBuffer(self._capacity, n_sensors)
        last_point = None
        if restored.conditions:
            c = restored.conditions[0]
            last_point = OperatingPoint(speed_rpm=c.speed_rpm, torque_nm=c.torque_nm, ambient_c=c.ambient_c)
        last = restored.last
        h0 = np.asarray(last.h if last is not None else config.initial_h, dtype=float)
        live = FilteredState(
            model.rom,
            model.spec,
            h=h0,
            dt_s=config.rules.dt_s,
            settings=replace(config.filter, keep_s=3 * serving.longest_window_s(config)),
        )
        cal = config.calibration
        self._notes: list[str] = []  # said with the first event (the constructor has no ``Out``)
        calibrator = (
            None
            if cal is None
            else OffsetCalibrator(
                config=cal, sample_period_s=config.rules.dt_s, current=self._start_baseline(restored)
            )
        )
        if calibrator is not None:  # a restored baseline's offsets go to the filter at once
            live.set_offsets(calibrator.offsets(), calibrator.offset_sd())
        # the considered H error (before ``resume``, which rescales to it): the stored result's as a served
        # one's (``CoreParts.h_rel_for``: its band, the form term, no baseline yet, guessed where at a bound);
        # 100 % for the guessed initial H
        live.set_h(
            h0,
            h_rel=1.0
            if last is None
            else live_h_rel(config, calibrator, last.h, last.ci95_hi, last.at_bound),
        )
        self._check = _check_of(None if calibrator is None else calibrator.current)
        if restored.live is not None:  # the stored checkpoint: the filter resumes instead of restarting
            try:
                live.resume(restored.live, model.version)
                at = utc(restored.live.t).isoformat(timespec="seconds")
                self._notes.append(f"live state resumed from its checkpoint of {at}")
            except CheckpointError as err:
                self._notes.append(f"live state not resumed ({err}); it starts from its prior")
        self._checkpoint_t = -math.inf  # sample time [s] of the last checkpoint handed to the writer
        self._p = CoreParts(
            config=config,
            model=model,
            live=live,
            history=RingHistory(self._ring, suspect=live.suspect_channels),
            detector=ConditionDetector(config.detector, reference=last_point),
            scheduler=sched.IdentificationScheduler(config=config.scheduler, history=list(restored.history)),
            jobs=JobBook(
                next_identification_id=restored.next_identification_id,
                model_version=model.version,
                method=config.method,
            ),
            samples=SampleBook(
                n_sensors,
                min_good_channels=config.rules.min_good_channels,
                store_period_s=config.sample_store_period_s,
            ),
            calibrator=calibrator,
            serving=serving,
            condition=restored.conditions[0] if restored.conditions else None,
            conditions=tuple(restored.conditions[:CONDITIONS_KEPT]),
        )
        self._cond_ids = IdCounter(restored.next_condition_id)
        self._resumed = self._p.condition is not None
        self._tracks = serving.tracks(self._p, restored)
        self._p.serve(serving.follow(self._p.condition))

    def _start_baseline(self, restored: Restored) -> Calibration | None:
        """The stored baseline; without one, the stored commissioning's (its test's rest), said in a note."""
        if restored.calibration is not None or self.config.calibration is None:
            return restored.calibration
        try:
            c = commissioning_baseline(restored.mechanics)
        except RecordError as err:
            self._notes.append(f"the commissioning's offset baseline is not used: {err}")
            return None
        if c is not None:
            self._notes.append(_adopted_line(c))
        return c

    # --- the state machine ----------------------------------------------------------------------------------
    def handle(self, event: Event) -> list[Instruction]:
        """One event in, what to do out (see ``service.core.events``)."""
        out = Out(event.event_id)
        match event:
            case SampleReceived():
                self._on_sample(event.sample, out)
            case JobOutcomeReceived():
                self._on_outcome(event, out)
            case ManualRequested():
                self._on_manual(event.reason, out)
            case BaselineRequested():
                self._on_baseline(event.t, out)
            case BaselineAdopted():
                if self._p.calibrator is not None:
                    self._calibrated(self._p.calibrator.adopt(event.calibration), out)
            case IdsKnown():
                rebase_ids(event, self._cond_ids, self._p.jobs.id_counter, out.log)
            case _:
                raise CoreError(f"unknown core event {type(event).__name__}")
        return out.instructions

    def view(self) -> CoreView:
        """The immutable snapshot of the state now (cheap: the large parts are shared, not copied)."""
        p = self._p
        running = p.scheduler.running
        cal = p.calibrator
        sd = None
        if cal is not None:
            sd = np.array(cal.offset_sd(), dtype=float)
            sd.setflags(write=False)
        book = p.samples
        return CoreView(
            newest=book.newest,
            condition=p.condition,
            conditions=p.conditions,
            current=p.serving.current,
            current_from_restore=p.serving.from_restore,
            records=p.jobs.records,
            jobs=p.jobs.jobs_view,
            running_job=None if running is None else job_key(running.job_id),
            counts=MappingProxyType(dict(p.jobs.counts)),
            durations=p.jobs.durations,
            last_ok_t=tuple(float(x) for x in book.last_ok_t),
            last_good_daq_t=book.last_good_daq_t,
            last_good_can_t=book.last_good_can_t,
            calibration=None if cal is None else cal.current,
            offset_sd_c=sd,
            live=p.live.view() if p.live.initialized else None,
            stale_after_s=self.config.stale_after_s,
            min_good_channels=self.config.rules.min_good_channels,
            map_config=self._tracks.maps.config,
            speed_map=self._tracks.maps.speed_map,
            map_serves=p.serving.map_serves,
            ci_threshold=self.config.ci_threshold,
            offsets_unchecked=self._check is not None,
            h_form_sd=float(np.hypot(self.config.h_form_sd, p.no_baseline_sd())),
        )

    @property
    def live_h(self) -> np.ndarray:
        """The live state's current H (7,) W/(m²·K) (a copy)."""
        return np.array(self._p.live.h, dtype=float)

    # --- samples --------------------------------------------------------------------------------------------
    def _on_sample(self, sample: Sample, out: Out) -> None:
        """Store, advance the live state, detect; then the tracks (the map's first, as it reserves job ids
        before this sample's per-condition jobs)."""
        if self._restored is not None:
            self._restore_until(sample.t.timestamp())
        p = self._p
        self._ring.append(sample)  # first: an out-of-order sample raises before anything changed
        ts = sample.t.timestamp()
        newest = p.samples.observe(sample)
        p.follow_condition()
        self._calibrate(newest, out)
        row = p.samples.to_store(newest)
        if row is not None:
            out.store(row)
        self._advance_live(newest, ts, out)
        if self._check is not None:
            self._judge_baseline(newest, ts, out)
        self._checkpoint(ts, out)
        todo: list[sched.Instruction] = []
        if self._resumed:
            todo += self._resume(ts, out)
        todo += self._tracks.schedule.converged(ts, out)
        for change in p.detector.handle(
            SampleEvent(
                t=ts,
                speed_rpm=float(sample.speed_rpm),
                torque_nm=float(sample.torque_nm),
                ambient_c=float(sample.ambient_c),
            )
        ):
            todo += self._on_change(change, out)
        self._tracks.maps.sample(newest, ts, out)
        self._tracks.schedule.tick(todo, ts, out)

    def _restore_until(self, ts: float) -> None:
        """At the first sample: what was restored dated after it is not resumed (the parts are built again
        without it; the next ids, possibly re-based by ``IdsKnown`` meanwhile, are kept)."""
        restored, self._restored = self._restored, None
        assert restored is not None
        kept, notes = cut_future(restored, ts)
        if not notes:
            return
        next_ids = self._cond_ids.next_id, self._p.jobs.id_counter.next_id
        self._build(replace(kept, next_condition_id=next_ids[0], next_identification_id=next_ids[1]))
        self._notes[:0] = notes

    def _checkpoint(self, ts: float, out: Out) -> None:
        """Hand the live state to the writer every ``live_checkpoint_s`` of sample time, the first
        ``live_checkpoint_phase_s`` after the live state starts; log start notes."""
        for note in self._notes:
            out.log(note)
        self._notes.clear()
        every = self.config.live_checkpoint_s
        live = self._p.live
        if every <= 0.0 or not live.initialized:
            return
        if self._checkpoint_t == -math.inf:  # the first one ``live_checkpoint_phase_s`` from now
            self._checkpoint_t = ts - every + self.config.live_checkpoint_phase_s
        if ts - self._checkpoint_t < every:
            return
        self._checkpoint_t = ts
        out.store(live.checkpoint(self.model.version))

    def _calibrate(self, s: NewestSample, out: Out) -> None:
        cal = self._p.calibrator
        if cal is None:
            return
        ok = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        reading = Reading(t=s.t, temps_c=s.temps_c, ok=ok, ambient_c=s.ambient_c, speed_rpm=s.speed_rpm)
        self._calibrated(cal.handle(reading), out)

    def _calibrated(
        self, instructions: Sequence[BaselineTaken | BaselineRefined | BaselineRejected], out: Out
    ) -> Calibration | None:
        live = self._p.live
        for ins in instructions:
            if isinstance(ins, BaselineRefined):  # the same rest, a longer average: stored, no message
                out.store(ins.calibration)
                live.set_offsets(ins.calibration.applied(), ins.calibration.sd_c)
            if isinstance(ins, BaselineTaken):
                c = ins.calibration
                out.store(c)
                out.log(
                    _adopted_line(c)
                    if c.source == COMMISSIONING
                    else f"sensor offsets zeroed ({c.source} baseline, {c.samples} samples at rest until "
                    f"{c.t_to.isoformat(timespec='seconds')}): {np.nanmin(c.offsets_c):+.2f}.."
                    f"{np.nanmax(c.offsets_c):+.2f} °C"
                )
                out.instructions.append(Calibrated(out.event_id, c))
                live.set_offsets(c.applied(), c.sd_c)
                self._check = _check_of(c)
                return c
        return None

    def _judge_baseline(self, s: NewestSample, ts: float, out: Out) -> None:
        """The commissioning's offsets against the live field's residuals (``service.core.
        baselinecheck``): kept, or dropped (back to no baseline) when zero offsets fit the sensors better."""
        live, cal, check = self._p.live, self._p.calibrator, self._check
        if check is None or cal is None or not live.initialized:
            return
        usable = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        beta = check.add(ts, np.asarray(s.temps_c, dtype=float), usable, live.view().sensors_c)
        if beta is None:
            return
        self._check = None
        if beta >= MAX_SLOPE:
            out.log(f"the commissioning's sensor offsets fit the sensors (residual slope {beta:+.2f}): kept")
            return
        cal.forget()
        live.set_offsets(cal.offsets(), cal.offset_sd())
        out.log(
            f"the commissioning's sensor offsets do NOT fit the sensors (residual slope {beta:+.2f}: a "
            "sensor exchanged or the DAQ re-zeroed since?): not used; no offset baseline until the spindle "
            "rests (or POST /api/v1/sensors/baseline at rest)"
        )

    def _on_baseline(self, t: datetime, out: Out) -> None:
        """Take a baseline now from the newest samples at rest; ``Rejected`` naming why not."""
        cal = self._p.calibrator
        if cal is None:
            out.reject(RejectKind.NOT_READY, "sensor calibration is disabled")
            return
        newest = self._p.samples.newest
        at = newest.t if newest is not None else t
        result = cal.handle(BaselineRequest(at))
        if self._calibrated(result, out) is None:
            why = next((r.reason for r in result if isinstance(r, BaselineRejected)), "no baseline")
            out.reject(RejectKind.NOT_READY, why)

    def _advance_live(self, s: NewestSample, ts: float, out: Out) -> None:
        """Predict to the sample and correct with its usable channels (quality OK, finite; the calibration's
        offsets are subtracted inside the filter)."""
        inputs = (s.ambient_c, s.speed_rpm, s.torque_nm)
        usable = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        temps = np.where(usable, s.temps_c, 0.0)
        if self._p.live.initialized:
            upd = self._p.live.push(
                ts,
                ambient_c=inputs[0],
                speed_rpm=inputs[1],
                torque_nm=inputs[2],
                temps_c=temps,
                usable=usable,
            )
            for line in fault_lines(upd.faults):
                out.log(line)
            return
        if not np.isfinite(inputs).all():
            return  # wait for ambient, speed and torque (CAN may come up after the DAQ) before starting
        self._p.live.initialize(ts, inputs, temps, usable)

    def _resume(self, ts: float, out: Out) -> list[sched.Instruction]:
        """After a restart the stored condition continues; its data start now (the ring buffer is empty)."""
        self._resumed = False
        cond = self._p.condition
        assert cond is not None
        point = OperatingPoint(speed_rpm=cond.speed_rpm, torque_nm=cond.torque_nm, ambient_c=cond.ambient_c)
        out.log(f"resumed condition {cond.id} ({cond.speed_rpm:.0f} rpm) from the database")
        return self._condition_started(
            sched.ConditionStarted(t=ts, condition_id=cond.id, point=point, t_start=ts)
        )

    def _on_change(self, change: ConditionChanged, out: Out) -> list[sched.Instruction]:
        cid = next(self._cond_ids)
        started = utc(change.t_start)
        if self._p.condition is not None:
            out.store(ConditionEnd(id=self._p.condition.id, ended_at=started))
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
        self._p.set_condition(snap, new=True)
        if self._p.live.initialized:
            self._p.live.mark(change.t_start)
        out.log(
            f"condition {cid}: {p.speed_rpm:.0f} rpm, {p.torque_nm:.2f} N·m, {p.ambient_c:.2f} °C "
            f"since {started.isoformat(timespec='seconds')} ({change.reason})"
        )
        return self._condition_started(
            sched.ConditionStarted(t=change.t_confirmed, condition_id=cid, point=p, t_start=change.t_start)
        )

    def _condition_started(self, ev: sched.ConditionStarted) -> list[sched.Instruction]:
        """A change triggers a map fit (debounced) and starts the condition's per-condition schedule."""
        self._tracks.maps.condition_started(ev.t)
        return self._tracks.schedule.condition_started(ev)

    # --- outcomes and manual requests -----------------------------------------------------------------------
    def _on_outcome(self, ev: JobOutcomeReceived, out: Out) -> None:
        """Record a worker outcome (the track that owns its job)."""
        outcome = ev.outcome
        job = self._p.jobs.take(outcome.job_id, outcome.wall_s)
        if job is None:
            return
        newest = self._p.samples.newest
        ts = (newest.t if newest is not None else ev.finished_at).timestamp()
        maps = self._tracks.maps
        track = maps if maps.owns(outcome.job_id) else self._tracks.schedule
        track.outcome(job, ev, ts, out)

    def _on_manual(self, reason: str, out: Out) -> None:
        """An identification requested through the API: ``ManualAccepted`` or ``Rejected``."""
        newest = self._p.samples.newest
        if newest is None:
            out.reject(RejectKind.NOT_READY, "no samples yet: nothing to identify from")
            return
        self._tracks.manual.manual(reason, newest, out)


def _adopted_line(c: Calibration) -> str:
    return (
        f"sensor offsets from the commissioning's rest ({c.samples} samples until "
        f"{c.t_to.isoformat(timespec='seconds')}): {np.nanmin(c.offsets_c):+.2f}.."
        f"{np.nanmax(c.offsets_c):+.2f} °C, 1σ {float(np.nanmedian(c.sd_c)):.3f} °C, until the spindle rests"
    )


def _check_of(c: Calibration | None) -> BaselineCheck | None:
    """A commissioning's baseline in use is checked against the sensors (any other is not), unless its offsets
    are within the 1σ added for their age of zero (``needs_check``): then either answer is covered."""
    if c is None or c.source != COMMISSIONING or not needs_check(c.applied()):
        return None
    return BaselineCheck(c.applied())
