"""The service's synchronous core: one sample or one job outcome in, jobs to launch and records out.

It owns the condition detector, the identification scheduler and the live FE state, and keeps what the API
reads (newest sample, current condition, current identification, job table). It does no I/O of its own:
records go to an injected ``sink`` (the buffered database writer), jobs are returned as :class:`Launch`
objects that the asyncio shell (``service.engine.shell``) hands to the worker process. Every public method
takes
the lock, so the API threads may read while the event loop writes.

Time: the detector, the scheduler and the live state run on the sample time axis (UTC epoch seconds of the
samples' timestamps), so a simulated speed-up only has to scale the acquisition clock.
"""

from __future__ import annotations

import itertools
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Protocol

import numpy as np

from drivers.quality import Quality
from model.carry import StateCovariance
from service.acquire.calibration import (
    BaselineRefined,
    BaselineRequest,
    BaselineTaken,
    Calibration,
    CalibrationConfig,
    OffsetCalibrator,
    Reading,
)
from service.defaults import CARRY_START_ERROR, CI_REL_THRESHOLD, ESTIMATE_T0_SHIFT
from service.estimate.live import LiveModel, LiveStateError
from service.identify.detector import (
    ConditionChanged,
    ConditionDetector,
    DetectorConfig,
    DetectorStatus,
    OperatingPoint,
    SampleEvent,
)
from service.identify.scheduler import (
    CancelJob,
    ConditionStarted,
    IdentificationScheduler,
    Instruction,
    JobFailed,
    JobFinished,
    JobSkipped,
    ManualQueued,
    ManualRejected,
    ManualRequest,
    PastResult,
    SchedulerConfig,
    StartJob,
    Tick,
)
from service.identify.window import (
    InsufficientDataError,
    RawWindow,
    WindowArrays,
    WindowRules,
    resample_window,
)
from service.identify.worker import JobOutcome, JobRequest, JobStatus
from service.modelload import LoadedModel
from service.serve.interface import (
    DURATION_BUCKETS_S,
    BusyError,
    ConditionSnapshot,
    ConditionState,
    Histogram,
    IdentificationJob,
    IdentificationRecord,
    JobState,
    NotReadyError,
)
from service.serve.views import data_to_record
from service.store.calibrations import calibration_record
from service.store.records import (
    ConditionEnd,
    ConditionStart,
    IdentificationData,
    Record,
    SampleData,
    SampleDecimator,
    finite,
    finite_list,
)

__all__ = ["CoreConfig", "Launch", "Restored", "SampleHistory", "ServiceCore"]

Clock = Callable[[], datetime]


class SampleHistory(Protocol):
    """Read access to the ring buffer: the samples with t in [t_from, t_to] (epoch s) as arrays."""

    def raw_window(self, t_from: float, t_to: float) -> RawWindow: ...


class RecordSink(Protocol):
    def submit(self, record: Record) -> bool: ...


@dataclass(frozen=True)
class CoreConfig:
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    rules: WindowRules = field(default_factory=WindowRules)
    method: str = "hybrid"
    seed: int = 0
    estimate_loads: bool = False
    estimate_t0_shift: str = ESTIMATE_T0_SHIFT  # "never" | "initial" (start from the first guess) | "always"
    carry_start_error: bool = CARRY_START_ERROR  # CIs carry the start field's error (the live state's)
    time_budget_s: float | None = None
    ci_threshold: float = CI_REL_THRESHOLD
    # sample time without good data (a sample, >= rules.min_good_channels usable channels and the ambient,
    # speed and torque from CAN) before H is reported stale
    stale_after_s: float = 60.0
    sample_store_period_s: float = 10.0
    min_speed_rpm: float = 100.0  # below: spindle idle, no bearing heat, H not identifiable -> skipped
    initial_h: tuple[float, ...] = (50.0,) * 7  # live-state H before the first identification (no data yet)
    # sensor offsets zeroed against a baseline at thermal equilibrium (service.acquire.calibration); None: the
    # measurements are taken as they come and no offset uncertainty is carried in the CIs
    calibration: CalibrationConfig | None = field(default_factory=CalibrationConfig)


@dataclass(frozen=True)
class Restored:
    """What the database knew at start-up (``service.restore``)."""

    last: IdentificationRecord | None = None
    history: tuple[PastResult, ...] = ()
    conditions: tuple[ConditionSnapshot, ...] = ()  # newest first
    next_condition_id: int = 1
    next_identification_id: int = 1
    calibration: Calibration | None = None  # the newest stored sensor offset baseline


@dataclass(frozen=True, eq=False)
class Launch:
    """A job to run in the worker process, with what is needed to record its outcome."""

    start: StartJob
    request: JobRequest | None  # None for a job that never ran (insufficient data)
    job_key: str
    requested_at: datetime
    window_from: datetime
    window_to: datetime


@dataclass(frozen=True, eq=False)
class NewestSample:
    t: datetime
    temps_c: np.ndarray
    quality: tuple[str, ...]
    ambient_c: float
    speed_rpm: float
    torque_nm: float
    can_ok: bool
    daq_ok: bool


def utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)


def _quality_names(quality: Any) -> tuple[str, ...]:
    """``drivers.quality.Quality`` codes (uint8 or enum) -> "ok", "stale", "open_circuit", ..."""
    names = []
    for q in quality:
        try:
            names.append(Quality(int(q)).name.lower())
        except ValueError:
            names.append(f"unknown_{int(q)}")
    return tuple(names)


class ServiceCore:
    """See the module docstring."""

    def __init__(
        self,
        config: CoreConfig,
        *,
        model: LoadedModel,
        history: SampleHistory,
        sink: RecordSink,
        restored: Restored | None = None,
        on_event: Callable[[str], None] | None = None,
        on_cancel: Callable[[int], None] | None = None,
    ) -> None:
        self.config = config
        self.on_cancel = on_cancel or (lambda _job_id: None)
        self.model = model
        self.history = history
        self.sink = sink
        self.on_event = on_event or (lambda _msg: None)
        self.lock = threading.RLock()
        restored = restored or Restored()
        self.restored = restored
        last_point = None
        if restored.conditions:
            c = restored.conditions[0]
            last_point = OperatingPoint(c.speed_rpm, c.torque_nm, c.ambient_c)
        self.detector = ConditionDetector(config.detector, reference=last_point)
        self.scheduler = IdentificationScheduler(config.scheduler, history=list(restored.history))
        h0 = restored.last.h if restored.last is not None else np.asarray(config.initial_h, dtype=float)
        self.live = LiveModel(
            model.fe,
            model.spec,
            h=np.asarray(h0, dtype=float),
            dt_s=config.rules.dt_s,
            keep_s=3 * config.scheduler.max_window_s,
        )
        self.condition: ConditionSnapshot | None = restored.conditions[0] if restored.conditions else None
        self.conditions: deque[ConditionSnapshot] = deque(restored.conditions, maxlen=200)
        self.current: IdentificationRecord | None = restored.last
        self.current_from_restore = restored.last is not None
        self.records: deque[IdentificationRecord] = deque(maxlen=500)
        self.jobs: dict[str, IdentificationJob] = {}
        self._job_keys: dict[int, str] = {}
        self._launches: dict[int, Launch] = {}
        self._cancel_reasons: dict[int, str] = {}
        self._cond_ids = itertools.count(restored.next_condition_id)
        self._ident_ids = itertools.count(restored.next_identification_id)
        self._resumed = self.condition is not None
        self.newest: NewestSample | None = None
        self._decimator = SampleDecimator(config.sample_store_period_s)
        self.counts: dict[str, int] = {"ok": 0, "failed": 0, "insufficient-data": 0, "cancelled": 0}
        self.durations = Histogram(DURATION_BUCKETS_S)
        self.samples_total = 0
        self._last_ok_t = np.full(len(model.spec.sensors), np.nan)
        self.last_good_daq_t: datetime | None = None  # newest sample with enough usable temperatures
        self.last_good_can_t: datetime | None = None  # newest sample with speed and torque from CAN
        cal = config.calibration
        self.calibrator = (
            None
            if cal is None
            else OffsetCalibrator(cal, sample_period_s=config.rules.dt_s, current=restored.calibration)
        )

    # --- samples ------------------------------------------------------------------------------------------
    def ingest(self, sample: Any) -> list[Launch]:
        """One acquisition ``Sample`` (drivers): store, advance the live state, detect, schedule."""
        with self.lock:
            ts = sample.t.timestamp()
            self._remember(sample)
            self._calibrate(sample)
            self._store_sample(sample, ts)
            self._advance_live(sample, ts)
            out: list[Instruction] = []
            if self._resumed:
                out += self._resume(ts)
            for change in self.detector.handle(
                SampleEvent(ts, float(sample.speed_rpm), float(sample.torque_nm), float(sample.ambient_c))
            ):
                out += self._on_change(change)
            out += self.scheduler.handle(Tick(ts))
            return self._execute(out, ts)

    def _remember(self, sample: Any) -> None:
        temps = np.asarray(sample.temps_c, dtype=float).copy()
        temps.setflags(write=False)
        self.newest = NewestSample(
            t=sample.t,
            temps_c=temps,
            quality=_quality_names(sample.quality),
            ambient_c=float(sample.ambient_c),
            speed_rpm=float(sample.speed_rpm),
            torque_nm=float(sample.torque_nm),
            can_ok=bool(getattr(sample, "can_ok", True)),
            daq_ok=bool(getattr(sample, "daq_ok", True)),
        )
        self.samples_total += 1
        ok = np.array([q == "ok" for q in self.newest.quality], dtype=bool)[: len(self._last_ok_t)]
        self._last_ok_t[: len(ok)][ok] = sample.t.timestamp()
        self._track_good_data(self.newest, ok)
        if self.condition is not None and self.detector.status is DetectorStatus.PENDING:
            if self.condition.state is not ConditionState.CHANGING:
                self._set_condition(replace(self.condition, state=ConditionState.CHANGING))
        elif self.condition is not None and self.condition.state is not ConditionState.STABLE:
            self._set_condition(replace(self.condition, state=ConditionState.STABLE))

    def _track_good_data(self, s: NewestSample, ok: np.ndarray) -> None:
        """Remember when the data were last good enough to identify from (``data_problems``)."""
        usable = int(np.sum(ok & np.isfinite(s.temps_c[: len(ok)])))
        if s.daq_ok and usable >= self.config.rules.min_good_channels and np.isfinite(s.ambient_c):
            self.last_good_daq_t = s.t
        if s.can_ok and np.isfinite(s.speed_rpm) and np.isfinite(s.torque_nm):
            self.last_good_can_t = s.t

    def data_problems(self, now: datetime) -> tuple[str, ...]:
        """Why the data are not fresh at ``now`` (empty: fresh), each "code: detail". Codes: ``no_sample``
        (nothing acquired for ``stale_after_s``: acquisition stalled), ``daq_no_good_data`` (no sample with
        ``rules.min_good_channels`` usable channels and the ambient for that long: DAQ unreachable, hung,
        garbled, frozen or channels broken), ``can_no_good_data`` (no speed/torque from CAN: silent, fault).
        """
        with self.lock:
            limit = self.config.stale_after_s
            if self.newest is None:
                return ("no_sample: no sample acquired yet",)
            out = []
            age = (now - self.newest.t).total_seconds()
            if age > limit:
                out.append(f"no_sample: newest sample {age:.0f} s old (limit {limit:.0f} s)")
            n = self.config.rules.min_good_channels
            what = f"sample with >= {n} usable temperature channels and the ambient"
            out += _age_problem("daq_no_good_data", what, self.last_good_daq_t, now, limit)
            can = "speed and torque from CAN"
            out += _age_problem("can_no_good_data", can, self.last_good_can_t, now, limit)
            return tuple(out)

    def _calibrate(self, sample: Any) -> None:
        if self.calibrator is None or self.newest is None:
            return
        s = self.newest
        ok = np.array([q == "ok" for q in s.quality], dtype=bool) & np.isfinite(s.temps_c)
        reading = Reading(s.t, s.temps_c, ok, s.ambient_c, s.speed_rpm)
        self._calibrated(self.calibrator.handle(reading))

    def _calibrated(self, instructions: Sequence[Any]) -> Calibration | None:
        for ins in instructions:
            if isinstance(ins, BaselineRefined):  # the same rest, a longer average: stored, no message
                self.sink.submit(calibration_record(ins.calibration))
            if isinstance(ins, BaselineTaken):
                c = ins.calibration
                self.sink.submit(calibration_record(c))
                self.on_event(
                    f"sensor offsets zeroed ({c.source} baseline, {c.samples} samples at rest until "
                    f"{c.t_to.isoformat(timespec='seconds')}): {np.nanmin(c.offsets_c):+.2f}.."
                    f"{np.nanmax(c.offsets_c):+.2f} °C"
                )
                return c
        return None

    def request_baseline(self) -> Calibration:
        """Take a baseline now from the newest samples at rest; ``NotReadyError`` naming why not."""
        with self.lock:
            if self.calibrator is None:
                raise NotReadyError("sensor calibration is disabled")
            t = self.newest.t if self.newest is not None else datetime.now(UTC)
            out = self.calibrator.handle(BaselineRequest(t))
            taken = self._calibrated(out)
            if taken is None:
                raise NotReadyError(getattr(out[0], "reason", "no baseline") if out else "no baseline")
            return taken

    def _store_sample(self, sample: Any, ts: float) -> None:
        if not self._decimator.keep(ts):
            return
        assert self.newest is not None
        s = self.newest
        self.sink.submit(
            SampleData(
                t=s.t,
                temps_c=tuple(finite_list(s.temps_c)),
                ambient_c=finite(s.ambient_c),
                speed_rpm=finite(s.speed_rpm),
                torque_nm=finite(s.torque_nm),
                quality=s.quality,
                can_ok=s.can_ok,
                daq_ok=s.daq_ok,
            )
        )

    def _advance_live(self, sample: Any, ts: float) -> None:
        inputs = (float(sample.ambient_c), float(sample.speed_rpm), float(sample.torque_nm))
        if self.live.initialized:
            self.live.push(ts, ambient_c=inputs[0], speed_rpm=inputs[1], torque_nm=inputs[2])
            return
        if not np.isfinite(inputs).all():
            return  # wait for ambient, speed and torque (CAN may come up after the DAQ) before starting
        temps = np.asarray(sample.temps_c, dtype=float)
        good = np.array([q == "ok" for q in _quality_names(sample.quality)]) & np.isfinite(temps)
        start = float(np.mean(temps[good])) if good.any() else inputs[0]
        self.live.initialize(ts, start, inputs)

    def _resume(self, ts: float) -> list[Instruction]:
        """After a restart the stored condition continues; its data start now (the ring buffer is empty)."""
        self._resumed = False
        cond = self.condition
        assert cond is not None
        point = OperatingPoint(cond.speed_rpm, cond.torque_nm, cond.ambient_c)
        self.on_event(f"resumed condition {cond.id} ({cond.speed_rpm:.0f} rpm) from the database")
        return self.scheduler.handle(ConditionStarted(ts, cond.id, point, ts))

    def _on_change(self, change: ConditionChanged) -> list[Instruction]:
        cid = next(self._cond_ids)
        started = utc(change.t_start)
        if self.condition is not None:
            self.sink.submit(ConditionEnd(id=self.condition.id, ended_at=started))
        p = change.point
        self.sink.submit(ConditionStart(cid, started, p.speed_rpm, p.torque_nm, p.ambient_c))
        snap = ConditionSnapshot(cid, p.speed_rpm, p.torque_nm, p.ambient_c, started, ConditionState.STABLE)
        self._set_condition(snap, new=True)
        if self.live.initialized:
            self.live.mark(change.t_start)
        self.on_event(
            f"condition {cid}: {p.speed_rpm:.0f} rpm, {p.torque_nm:.2f} N·m, {p.ambient_c:.2f} °C "
            f"since {started.isoformat(timespec='seconds')} ({change.reason})"
        )
        return self.scheduler.handle(ConditionStarted(change.t_confirmed, cid, p, change.t_start))

    def _set_condition(self, snap: ConditionSnapshot, *, new: bool = False) -> None:
        self.condition = snap
        if new or not self.conditions:
            self.conditions.appendleft(snap)
        else:
            self.conditions[0] = snap

    # --- instructions ---------------------------------------------------------------------------------------
    def _execute(self, instructions: Sequence[Instruction], ts: float) -> list[Launch]:
        launches: list[Launch] = []
        queue = list(instructions)
        while queue:
            ins = queue.pop(0)
            if isinstance(ins, StartJob):
                launch, more = self._prepare(ins, ts)
                queue += more
                if launch is not None:
                    launches.append(launch)
            elif isinstance(ins, CancelJob):
                self._cancelled(ins)
        return launches

    def _job_key(self, job_id: int, reason: str, requested_at: datetime) -> str:
        key = self._job_keys.get(job_id)
        if key is None:
            key = self._job_keys[job_id] = f"job-{job_id}"
            self.jobs[key] = IdentificationJob(key, reason, JobState.QUEUED, requested_at)
        return key

    def _prepare(self, job: StartJob, ts: float) -> tuple[Launch | None, list[Instruction]]:
        reason = self._reason(job)
        now = utc(ts)
        key = self._job_key(job.job_id, reason, now)
        if abs(job.point.speed_rpm) < self.config.min_speed_rpm:
            msg = (
                f"spindle idle ({job.point.speed_rpm:.0f} rpm < {self.config.min_speed_rpm:.0f} rpm): "
                "no bearing heat, H1-H7 are not identifiable"
            )
            self._finish_without_result(job, key, reason, now, "skipped", msg, utc(job.t_from))
            return None, self.scheduler.handle(JobSkipped(ts, job.job_id, msg))
        try:
            snap = self.live.field_at(job.t_from)
            start_cov = self.live.covariance_at(snap.t) if self.config.carry_start_error else None
            raw = self._raw(snap.t, job.t_to)
            arrays = resample_window(raw, snap.t, job.t_to, self.config.rules)
        except (InsufficientDataError, LiveStateError) as err:
            msg = getattr(err, "reason", str(err))
            self._finish_without_result(job, key, reason, now, "insufficient-data", msg, utc(job.t_from))
            return None, self.scheduler.handle(JobSkipped(ts, job.job_id, msg))
        request = JobRequest(
            job_id=job.job_id,
            window=arrays,
            t0_c=snap.field_c,
            warm_start=job.warm_start,
            method=self.config.method,
            seed=self.config.seed,
            estimate_loads=self.config.estimate_loads,
            estimate_t0_shift=self._fit_start_offset(snap),
            carry_start_error=self.config.carry_start_error,
            start_cov=start_cov,
            gap=self._gap(start_cov, snap.t),
            time_budget_s=self.config.time_budget_s,
            ci_threshold=self.config.ci_threshold,
            offsets_c=None if self.calibrator is None else self.calibrator.offsets(),
            offset_sd_c=None if self.calibrator is None else self.calibrator.offset_sd(),
        )
        launch = Launch(job, request, key, now, utc(snap.t), utc(float(arrays.times_s[-1])))
        self._launches[job.job_id] = launch
        self.jobs[key] = replace(self.jobs[key], state=JobState.RUNNING)
        self.on_event(
            f"identification {key}: condition {job.condition_id}, "
            f"window {arrays.n_steps * arrays.dt_s / 60:.0f} min, "
            f"{int(arrays.mask.sum())} sensors, warm start from {job.warm_source}"
        )
        return launch, []

    def _gap(self, start_cov: StateCovariance | None, t_start: float) -> WindowArrays | None:
        """The inputs from the rebase that ``start_cov`` belongs to up to the window start (None: no gap,
        or the history no longer has it; the worker then only decays the covariance)."""
        if start_cov is None or t_start - start_cov.t_s < 0.5 * self.config.rules.dt_s:
            return None
        rules = replace(self.config.rules, min_window_s=0.0, min_good_channels=0)
        try:
            raw = self._raw(start_cov.t_s, t_start)
            return resample_window(raw, start_cov.t_s, t_start, rules)
        except (InsufficientDataError, LiveStateError, ValueError):
            return None

    def _raw(self, t_from: float, t_to: float) -> RawWindow:
        """The history's samples for the grid [t_from, t_to] (s): sample times jitter around the grid, so
        the samples within half a step outside it belong to its end points (``resample_window``,
        ``LiveModel.push``) and are included."""
        half = 0.5 * self.config.rules.dt_s
        return self.history.raw_window(t_from - half, t_to + half)

    def _fit_start_offset(self, snap: Any) -> bool:
        """Whether the window's start field gets a fitted uniform offset (``estimate_t0_shift``): "initial"
        only while it still descends from the live state's initial guess (no rebase since), whose error is
        uniform (the first sample's noise)."""
        mode = self.config.estimate_t0_shift
        return mode == "always" or (mode == "initial" and bool(getattr(snap, "initial", False)))

    def _reason(self, job: StartJob) -> str:
        if job.trigger == "manual":
            return self._manual_reason or "manual"
        first = all(r.condition.id != job.condition_id for r in self.records)
        return "condition-change" if first else "scheduled"

    _manual_reason: str | None = None

    def channel_ages(self, now: datetime) -> list[float | None]:
        """Seconds since each channel's last OK value (None: never)."""
        ts = now.timestamp()
        return [None if not np.isfinite(t) else max(0.0, ts - float(t)) for t in self._last_ok_t]

    def _cancelled(self, ins: CancelJob) -> None:
        self.on_cancel(ins.job_id)
        self._cancel_reasons[ins.job_id] = ins.reason
        launch = self._launches.get(ins.job_id)
        key = self._job_keys.get(ins.job_id)
        if key is not None and self.jobs[key].state in (JobState.QUEUED, JobState.RUNNING):
            self.jobs[key] = replace(self.jobs[key], state=JobState.FAILED, message=ins.reason)
        if launch is not None:
            self.on_event(f"identification {launch.job_key} cancelling: {ins.reason}")

    # --- outcomes -------------------------------------------------------------------------------------------
    def job_done(self, outcome: JobOutcome, *, finished_at: datetime, stepper: Any = None) -> list[Launch]:
        """Record a worker outcome; returns further jobs the scheduler wants now.

        ``stepper``: ``live.prepare(result.h)`` computed off the event loop (else the next step factorises).
        """
        with self.lock:
            launch = self._launches.pop(outcome.job_id, None)
            if launch is None:
                return []
            ts = self.newest.t.timestamp() if self.newest is not None else finished_at.timestamp()
            self.durations.observe(outcome.wall_s)
            if (
                outcome.status is JobStatus.CANCELLED
                or self.scheduler.running is None
                or (self.scheduler.running.job_id != outcome.job_id)
            ):
                self._store_outcome(launch, "cancelled", outcome.message or "cancelled", finished_at)
                return []
            if outcome.status is JobStatus.INSUFFICIENT_DATA:
                self._store_outcome(launch, "insufficient-data", outcome.message, finished_at)
                return self._execute(
                    self.scheduler.handle(JobSkipped(ts, outcome.job_id, outcome.message)), ts
                )
            if outcome.status is JobStatus.FAILED:
                self._store_outcome(launch, "failed", outcome.message, finished_at)
                return self._execute(
                    self.scheduler.handle(JobFailed(ts, outcome.job_id, outcome.message)), ts
                )
            rec = self._store_result(launch, outcome, finished_at, stepper)
            self._rebase_live(outcome, launch)
            h = tuple(float(x) for x in rec.h)
            return self._execute(self.scheduler.handle(JobFinished(ts, outcome.job_id, h)), ts)

    def _meta(self, launch: Launch, finished_at: datetime) -> dict[str, Any]:
        job = launch.start
        return {
            "id": next(self._ident_ids),
            "condition_id": job.condition_id,
            "started_at": launch.requested_at,
            "finished_at": finished_at,
            "window_start": launch.window_from,
            "window_end": launch.window_to,
            "reason": self.jobs[launch.job_key].reason,
            "model_version": self.model.version,
            "warm_start_source": job.warm_source,
        }

    def _store_result(
        self, launch: Launch, outcome: JobOutcome, finished_at: datetime, stepper: Any = None
    ) -> IdentificationRecord:
        data = IdentificationData.from_result(outcome.result, **self._meta(launch, finished_at))
        rec = self._record(data, launch)
        self.current = rec
        self.current_from_restore = False
        self.live.set_h(rec.h, _load_scale(outcome.result), stepper=stepper)
        self.counts["ok"] += 1
        h_txt = ", ".join(f"{x:.1f}" for x in rec.h)
        self.on_event(
            f"identification {launch.job_key} ok: H = [{h_txt}] W/(m²·K), fit {rec.fit:.4f}, "
            f"RMSE {rec.rmse_c:.3f} °C, {outcome.wall_s:.2f} s"
        )
        return rec

    def _store_outcome(self, launch: Launch, outcome: str, message: str, finished_at: datetime) -> None:
        meta = self._meta(launch, finished_at)
        data = IdentificationData(outcome=outcome, method=self.config.method, message=message, **meta)
        self._record(data, launch)
        self.counts[outcome] = self.counts.get(outcome, 0) + 1
        self.on_event(f"identification {launch.job_key} {outcome}: {message}")

    def _finish_without_result(
        self,
        job: StartJob,
        key: str,
        reason: str,
        now: datetime,
        outcome: str,
        message: str,
        t_from: datetime,
    ) -> None:
        launch = Launch(job, None, key, now, t_from, utc(job.t_to))
        self._store_outcome(launch, outcome, message, now)

    def _record(self, data: IdentificationData, launch: Launch) -> IdentificationRecord:
        self.sink.submit(data)
        cond = next((c for c in self.conditions if c.id == data.condition_id), self.condition)
        assert cond is not None
        rec = data_to_record(data, cond)
        self.records.appendleft(rec)
        job = self.jobs[launch.job_key]
        state = JobState.DONE if data.outcome == "ok" else JobState.FAILED
        self.jobs[launch.job_key] = replace(
            job, state=state, finished_at=data.finished_at, identification_id=data.id, message=data.message
        )
        return rec

    def _rebase_live(self, outcome: JobOutcome, launch: Launch) -> None:
        """Restart the live state from the fitted model's field at the window end, then catch up."""
        final = getattr(outcome, "final_field_c", None)
        if final is None or not self.live.initialized:
            return
        t_end = launch.window_to.timestamp()
        t_now = self.live.t if self.newest is None else max(self.live.t, self.newest.t.timestamp())
        try:
            raw = self._raw(t_end, t_now)
        except Exception:  # the history cannot replay: keep the current state (it has the new H already)
            return
        self.live.rebase(t_end, final, raw, covariance=_state_covariance(outcome.result, t_end))

    # --- manual requests ------------------------------------------------------------------------------------
    def request(self, reason: str) -> tuple[IdentificationJob, list[Launch]]:
        """An identification requested through the API; raises BusyError / NotReadyError."""
        with self.lock:
            if self.newest is None:
                raise NotReadyError("no samples yet: nothing to identify from")
            if self.scheduler.running is not None:
                key = self._job_keys.get(self.scheduler.running.job_id, "?")
                raise BusyError(f"identification {key} is already running")
            ts = self.newest.t.timestamp()
            out = self.scheduler.handle(ManualRequest(ts, requested_by=reason))
            for ins in out:
                if isinstance(ins, ManualRejected):
                    raise NotReadyError(ins.reason)
                if isinstance(ins, ManualQueued):
                    raise BusyError(ins.reason)
            self._manual_reason = (reason or "manual")[:32]
            try:
                launches = self._execute(out, ts)
            finally:
                self._manual_reason = None
            start = next(i for i in out if isinstance(i, StartJob))
            return self.jobs[self._job_keys[start.job_id]], launches


def _age_problem(code: str, what: str, last: datetime | None, now: datetime, limit_s: float) -> list[str]:
    if last is None:
        return [f"{code}: no {what} yet"]
    age = (now - last).total_seconds()
    return [f"{code}: newest {what} is {age:.1f} s old (limit {limit_s:.0f} s)"] if age > limit_s else []


def _state_covariance(result: Any, t_end: float) -> StateCovariance | None:
    """The rebased state's error (the result's end ensemble), or None when the window did not carry it."""
    ens = getattr(result, "end_ensemble", None)
    if ens is None:
        return None
    ls = getattr(result, "load_scale", None)
    return StateCovariance(
        t_end, ens, np.asarray(result.h, np.float64), None if ls is None else np.asarray(ls, np.float64)
    )


def _load_scale(result: Any) -> tuple[float, float] | None:
    ls = getattr(result, "load_scale", None)
    return None if ls is None else (float(ls[0]), float(ls[1]))
