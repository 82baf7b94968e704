"""The core's per-condition track (modes ``per_condition`` and ``combined``): it drives the identification
scheduler (``service.identify.scheduler``) with the conditions the detector confirms and the samples' time,
launches the jobs it starts, records their outcomes and takes manual requests in per-condition mode.
``Unscheduled`` stands in for it in speed-map mode (no per-condition schedule; a stray outcome is still
recorded). Pure: no I/O, no clock; the serving strategy (``service.core.serving``) builds one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Protocol

from model.identify import IdentificationResult
from model.identify_prior import HPrior
from service.contracts.snapshots import IdentificationRecord
from service.core.events import Cancel, JobOutcomeReceived, Launch, ManualAccepted, RejectKind
from service.core.jobbook import Job, job_key
from service.core.jobs import converging_reason, job_request, job_window
from service.core.parts import CoreParts, Out, utc
from service.core.view import NewestSample
from service.estimate.live import LiveStateError
from service.identify import scheduler as sched
from service.identify.window import InsufficientWindowError
from service.identify.worker import JobOutcome, JobStatus

__all__ = ["ManualTrack", "ScheduleTrack", "Unscheduled"]


class ManualTrack(Protocol):
    """The track that takes identifications requested through the API."""

    def manual(self, reason: str, newest: NewestSample, out: Out) -> None:
        """``ManualAccepted`` or ``Rejected`` into ``out``."""
        ...


class ScheduleTrack:
    """See the module docstring."""

    def __init__(self, parts: CoreParts, *, prior: Callable[[float, float], HPrior] | None = None) -> None:
        self.p = parts
        # the jobs' prior at (speed rpm, ambient °C): a MAP fit (combined mode); None: unregularised
        self.prior = prior
        # a condition that started while the live state converges: its schedule counts from the convergence
        self.held: sched.ConditionStarted | None = None

    def condition_started(self, ev: sched.ConditionStarted) -> list[sched.Instruction]:
        """Tell the scheduler, counting the condition's schedule from max(its start, the live state's
        convergence): while the state converges after a (re)start the start is held (the newest wins)."""
        ready = self.p.live.ready_at()
        if ready is None:
            self.held = ev
            return []
        return self.p.scheduler.handle(replace(ev, t_start=max(ev.t_start, ready)))

    def converged(self, ts: float, out: Out) -> list[sched.Instruction]:
        """A held condition's schedule counts from the live state's convergence, once it converged."""
        ready = self.p.live.ready_at()
        if self.held is None or ready is None:
            return []
        held, self.held = self.held, None
        out.log(f"live state converged: condition {held.condition_id}'s schedule counts from now")
        return self.p.scheduler.handle(replace(held, t=ts, t_start=max(held.t_start, ready)))

    def tick(self, todo: list[sched.Instruction], ts: float, out: Out) -> None:
        """The sample's time: carry out ``todo`` (this sample's instructions) and what the scheduler wants."""
        todo = [*todo, *self.p.scheduler.handle(sched.Tick(ts))]
        self._execute(todo, ts, out)

    # --- scheduler instructions -----------------------------------------------------------------------------
    def _execute(
        self, instructions: Sequence[sched.Instruction], ts: float, out: Out, manual_reason: str = ""
    ) -> None:
        queue = list(instructions)
        while queue:
            ins = queue.pop(0)
            if isinstance(ins, sched.StartJob):
                queue += self._start(ins, ts, out, manual_reason)
            elif isinstance(ins, sched.CancelJob):
                self._cancel(ins, out)

    def _start(
        self, start: sched.StartJob, ts: float, out: Out, manual_reason: str
    ) -> list[sched.Instruction]:
        """Build the job's window and launch it, or end it at once (idle spindle, too few data)."""
        p = self.p
        now = utc(ts)
        if p.live.ready_at() is None:
            # no job and no stored outcome: the scheduler retries at its next time (/chtc says why meanwhile)
            why = converging_reason(p.live)
            out.log(f"identification for condition {start.condition_id} deferred: {why}")
            return p.scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=why))
        if start.trigger == "manual":
            reason = manual_reason or "manual"
        else:
            reason = "condition-change" if p.jobs.first_of(start.condition_id) else "scheduled"
        job = p.jobs.open(start, reason=reason, now=now, event_id=out.event_id)
        min_rpm = p.config.min_speed_rpm
        if abs(start.point.speed_rpm) < min_rpm:
            msg = (
                f"spindle idle ({start.point.speed_rpm:.0f} rpm < {min_rpm:.0f} rpm): "
                "no bearing heat, H1-H7 are not identifiable"
            )
            p.store_outcome(job, outcome="skipped", message=msg, finished_at=now, out=out)
            return p.scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=msg))
        try:
            window = job_window(start, p.live, p.history, p.config)
        except (InsufficientWindowError, LiveStateError) as err:
            msg = err.reason if isinstance(err, InsufficientWindowError) else str(err)
            p.store_outcome(job, outcome="insufficient-data", message=msg, finished_at=now, out=out)
            return p.scheduler.handle(sched.JobSkipped(t=ts, job_id=start.job_id, reason=msg))
        request = job_request(start, window, config=p.config, offsets=p.offsets())
        if self.prior is not None:
            request = replace(request, prior=self.prior(start.point.speed_rpm, start.point.ambient_c))
        snap, arrays = window.start, window.arrays
        job = p.jobs.launched(job, window_from=utc(snap.t), window_to=utc(float(arrays.times_s[-1])))
        out.instructions.append(Launch(event_id=out.event_id, job_key=job.key, request=request))
        out.log(
            f"identification {job.key}: condition {start.condition_id}, "
            f"window {arrays.n_steps * arrays.dt_s / 60:.0f} min, "
            f"{int(arrays.mask.sum())} sensors, warm start from {start.warm_source}"
        )
        return []

    def _cancel(self, ins: sched.CancelJob, out: Out) -> None:
        out.instructions.append(Cancel(event_id=out.event_id, job_id=ins.job_id, reason=ins.reason))
        job = self.p.jobs.waiting(ins.job_id)
        self.p.jobs.cancelling(ins.job_id, ins.reason)
        if job is not None:
            out.log(f"identification {job.key} cancelling: {ins.reason}")

    # --- outcomes -------------------------------------------------------------------------------------------
    def outcome(self, job: Job, ev: JobOutcomeReceived, ts: float, out: Out) -> None:
        """Record a worker outcome; launch what the scheduler wants next."""
        p = self.p
        outcome = ev.outcome
        running = p.scheduler.running
        if outcome.status is JobStatus.CANCELLED or running is None or running.job_id != outcome.job_id:
            p.store_outcome(
                job,
                outcome="cancelled",
                message=outcome.message or "cancelled",
                finished_at=ev.finished_at,
                out=out,
            )
            return
        if outcome.status is JobStatus.INSUFFICIENT_DATA:
            p.store_outcome(
                job, outcome="insufficient-data", message=outcome.message, finished_at=ev.finished_at, out=out
            )
            more = p.scheduler.handle(sched.JobSkipped(t=ts, job_id=outcome.job_id, reason=outcome.message))
        elif outcome.status is JobStatus.FAILED or outcome.result is None:
            p.store_outcome(
                job, outcome="failed", message=outcome.message, finished_at=ev.finished_at, out=out
            )
            more = p.scheduler.handle(sched.JobFailed(t=ts, job_id=outcome.job_id, reason=outcome.message))
        else:
            rec = self._store_result(job, outcome=outcome, result=outcome.result, ev=ev, out=out)
            h = tuple(float(x) for x in rec.h)
            more = p.scheduler.handle(sched.JobFinished(t=ts, job_id=outcome.job_id, h=h))
        self._execute(more, ts, out)

    def _store_result(
        self,
        job: Job,
        *,
        outcome: JobOutcome,
        result: IdentificationResult,
        ev: JobOutcomeReceived,
        out: Out,
    ) -> IdentificationRecord:
        p = self.p
        data, rec = p.jobs.identified(
            job, result, finished_at=ev.finished_at, event_id=out.event_id, condition=p.condition_of(job)
        )
        out.store(data)
        ls = result.load_scale
        load = None if ls is None else (float(ls[0]), float(ls[1]))
        p.serve(p.serving.identified(rec, load, p.condition))
        h_txt = ", ".join(f"{x:.1f}" for x in rec.h)
        out.log(
            f"identification {job.key} ok: H = [{h_txt}] W/(m²·K), fit {rec.fit:.4f}, "
            f"RMSE {rec.rmse_c:.3f} °C, {outcome.wall_s:.2f} s"
        )
        return rec

    # --- manual requests ------------------------------------------------------------------------------------
    def manual(self, reason: str, newest: NewestSample, out: Out) -> None:
        """An identification requested through the API (per-condition mode)."""
        p = self.p
        running = p.scheduler.running
        if running is not None:
            out.reject(RejectKind.BUSY, f"identification {job_key(running.job_id)} is already running")
            return
        ts = newest.t.timestamp()
        todo = p.scheduler.handle(sched.ManualRequest(ts, requested_by=reason))
        for ins in todo:
            if isinstance(ins, sched.ManualRejected | sched.ManualQueued):
                kind = RejectKind.NOT_READY if isinstance(ins, sched.ManualRejected) else RejectKind.BUSY
                out.reject(kind, ins.reason)
                return
        self._execute(todo, ts, out, manual_reason=(reason or "manual")[:32])
        start = next(i for i in todo if isinstance(i, sched.StartJob))
        job = p.jobs.jobs_view[job_key(start.job_id)]
        out.instructions.append(ManualAccepted(out.event_id, job))


class Unscheduled(ScheduleTrack):
    """No per-condition schedule (speed-map mode): confirmed conditions and the samples' time are not handed
    to the scheduler; an outcome that is not the running map fit's is recorded as cancelled."""

    def condition_started(self, ev: sched.ConditionStarted) -> list[sched.Instruction]:
        return []

    def tick(self, todo: list[sched.Instruction], ts: float, out: Out) -> None:
        return None
