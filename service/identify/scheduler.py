"""Identification scheduler: a pure state machine (no I/O, no clock, no asyncio).

It decides *when* to identify H1–H7 and from which warm start; the worker does the work. Times are seconds on
the sample time axis (UTC epoch seconds in the service, plant seconds in tests), so a simulated speed-up needs
nothing special. Events in, instructions out::

    ConditionStarted  -> [CancelJob]            a newer condition cancels the running job
    Tick(t)           -> [StartJob]             the first request once ``min_data_s`` of the condition exist,
                                                then one per entry of ``schedule_s`` (s after the change)
    ManualRequest     -> [StartJob] | [ManualQueued] | [ManualRejected]
    JobFinished       -> [StartJob]?            stores H as this condition's latest result; starts a request
    JobFailed/Skipped -> [StartJob]?            that fell due while the job ran, else waits for the next one

Only one job runs at a time (the worker has one process). A schedule entry that falls due while a job runs is
served once when it finishes; entries missed by then are merged into that one request. The warm start is the
last result of this condition, else the stored result of the nearest earlier condition (distance in
operating-point space scaled by ``distance_scales``), else none (cold start).

Errors::

    SchedulerError(ValueError)     a bad configuration field (named) or an unknown event
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass, field

from service.errors import ServiceError
from service.identify.detector import OperatingPoint

__all__ = [
    "CancelJob",
    "ConditionStarted",
    "IdentificationScheduler",
    "JobFailed",
    "JobFinished",
    "JobSkipped",
    "ManualQueued",
    "ManualRejected",
    "ManualRequest",
    "PastResult",
    "SchedulerConfig",
    "SchedulerError",
    "SchedulerStatus",
    "StartJob",
    "Tick",
]


class SchedulerError(ServiceError, ValueError):
    """A bad scheduler configuration field or an event the scheduler does not know."""


class SchedulerStatus(enum.Enum):
    IDLE = "idle"  # no operating condition yet
    COLLECTING = "collecting"  # condition known, not enough data of it yet
    RUNNING = "running"  # a job is running
    WAITING = "waiting"  # between two scheduled identifications
    DONE = "done"  # schedule of this condition exhausted (manual requests still served)


@dataclass(frozen=True, kw_only=True)
class SchedulerConfig:
    """Timing in s after the condition change; ``distance_scales`` (rpm, N·m, °C) for the nearest one. From
    the settings' ``[identification]`` (no defaults here: ``service.core.config.core_config`` builds it)."""

    min_data_s: float
    schedule_s: tuple[float, ...]
    max_window_s: float
    distance_scales: tuple[float, float, float]
    tolerance_s: float  # an entry is due this much early (sample-time jitter: half the sample period)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_data_s) and self.min_data_s > 0):
            raise SchedulerError(f"identification.min_data_s must be > 0, got {self.min_data_s!r}")
        if not (math.isfinite(self.max_window_s) and self.max_window_s >= self.min_data_s):
            raise SchedulerError(
                f"identification.max_window_s must be >= min_data_s ({self.min_data_s}), "
                f"got {self.max_window_s!r}"
            )
        sched = tuple(self.schedule_s)
        if not sched or any(b <= a for a, b in itertools.pairwise(sched)) or sched[0] < self.min_data_s:
            raise SchedulerError(
                f"identification.schedule_s must be increasing and start at >= min_data_s, got {sched!r}"
            )
        if len(self.distance_scales) != 3 or any(s <= 0 for s in self.distance_scales):
            raise SchedulerError(
                f"experimental.distance_scales must be 3 positive numbers, got {self.distance_scales!r}"
            )


# --- events ---------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class ConditionStarted:
    t: float
    condition_id: int
    point: OperatingPoint
    t_start: float


@dataclass(frozen=True)
class Tick:
    t: float


@dataclass(frozen=True)
class ManualRequest:
    t: float
    requested_by: str = "api"


@dataclass(frozen=True, kw_only=True)
class JobFinished:
    t: float
    job_id: int
    h: tuple[float, ...]


@dataclass(frozen=True, kw_only=True)
class JobFailed:
    t: float
    job_id: int
    reason: str


@dataclass(frozen=True, kw_only=True)
class JobSkipped:
    t: float
    job_id: int
    reason: str


Event = ConditionStarted | Tick | ManualRequest | JobFinished | JobFailed | JobSkipped


# --- instructions ---------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class StartJob:
    job_id: int
    condition_id: int
    point: OperatingPoint
    t_from: float
    t_to: float
    warm_start: tuple[float, ...] | None
    warm_source: str  # "this condition", "condition <id>" or "none"
    trigger: str  # "schedule" or "manual"


@dataclass(frozen=True)
class CancelJob:
    job_id: int
    reason: str


@dataclass(frozen=True)
class ManualQueued:
    reason: str


@dataclass(frozen=True)
class ManualRejected:
    reason: str


Instruction = StartJob | CancelJob | ManualQueued | ManualRejected


@dataclass(frozen=True, kw_only=True)
class PastResult:
    """A stored identification result of a condition (restored from the database on restart)."""

    condition_id: int
    point: OperatingPoint
    h: tuple[float, ...]


@dataclass(kw_only=True)
class _Current:
    condition_id: int
    point: OperatingPoint
    t_start: float
    next_entry: int = 0
    due: str | None = None  # "schedule" / "manual": a request waiting for the running job to end
    last_h: tuple[float, ...] | None = None


@dataclass(kw_only=True)
class _Running:
    job_id: int
    condition_id: int
    trigger: str


@dataclass(kw_only=True)
class IdentificationScheduler:
    """Pure scheduler: ``handle(event) -> list[instruction]``; ``history`` seeds the warm-start memory."""

    config: SchedulerConfig
    history: list[PastResult] = field(default_factory=list)
    status: SchedulerStatus = SchedulerStatus.IDLE
    current: _Current | None = None
    running: _Running | None = None
    _next_job_id: int = 1

    def reserve_job_id(self) -> int:
        """A job id that no scheduled job will take, for a job launched outside the schedule (a speed-map
        fit): both kinds share the worker and the job book, keyed by id."""
        job_id = self._next_job_id
        self._next_job_id += 1
        return job_id

    def handle(self, event: Event) -> list[Instruction]:
        match event:
            case ConditionStarted():
                return self._on_condition(event)
            case Tick():
                return self._on_tick(event.t)
            case ManualRequest():
                return self._on_manual(event)
            case JobFinished() | JobFailed() | JobSkipped():
                return self._on_job_end(event)
        raise SchedulerError(f"unknown scheduler event {type(event).__name__}")

    # --- handlers -------------------------------------------------------------------------------------
    def _on_condition(self, ev: ConditionStarted) -> list[Instruction]:
        out: list[Instruction] = []
        if self.running is not None:
            out.append(CancelJob(self.running.job_id, f"superseded by condition {ev.condition_id}"))
            self.running = None
        self.current = _Current(condition_id=ev.condition_id, point=ev.point, t_start=ev.t_start)
        own = [p for p in self.history if p.condition_id == ev.condition_id]
        if own:
            self.current.last_h = own[-1].h
        self.status = SchedulerStatus.COLLECTING
        return out + self._on_tick(ev.t)

    def _on_tick(self, t: float) -> list[Instruction]:
        cur = self.current
        if cur is None or self.running is not None or cur.next_entry >= len(self.config.schedule_s):
            return []
        if t - cur.t_start < self.config.schedule_s[cur.next_entry] - self.config.tolerance_s:
            return []
        return [self._start(t, "schedule")]

    def _on_manual(self, ev: ManualRequest) -> list[Instruction]:
        cur = self.current
        if cur is None:
            return [ManualRejected("no operating condition detected yet")]
        have = ev.t - cur.t_start
        if have < self.config.min_data_s - self.config.tolerance_s:
            return [
                ManualRejected(
                    f"too little data of the current condition: {have:.0f} s < min_data_s "
                    f"{self.config.min_data_s:.0f} s"
                )
            ]
        if self.running is not None:
            cur.due = "manual"
            return [ManualQueued(f"job {self.running.job_id} is running; the request runs when it ends")]
        return [self._start(ev.t, "manual")]

    def _on_job_end(self, ev: JobFinished | JobFailed | JobSkipped) -> list[Instruction]:
        run = self.running
        if run is None or run.job_id != ev.job_id:
            return []  # a cancelled or unknown job: nothing to do
        self.running = None
        cur = self.current
        assert cur is not None and cur.condition_id == run.condition_id
        if isinstance(ev, JobFinished):
            cur.last_h = tuple(ev.h)
            self.history.append(PastResult(condition_id=cur.condition_id, point=cur.point, h=tuple(ev.h)))
        self.status = self._idle_status()
        due, cur.due = cur.due, None
        if due == "manual":
            return [self._start(ev.t, "manual")]
        return self._on_tick(ev.t)

    # --- helpers --------------------------------------------------------------------------------------
    def _idle_status(self) -> SchedulerStatus:
        cur = self.current
        if cur is None:
            return SchedulerStatus.IDLE
        if cur.next_entry >= len(self.config.schedule_s):
            return SchedulerStatus.DONE
        return SchedulerStatus.WAITING if cur.last_h is not None else SchedulerStatus.COLLECTING

    def _start(self, t: float, trigger: str) -> StartJob:
        cur = self.current
        assert cur is not None
        elapsed = t - cur.t_start
        sched = self.config.schedule_s
        while cur.next_entry < len(sched) and sched[cur.next_entry] <= elapsed + self.config.tolerance_s:
            cur.next_entry += 1
        warm, source = self._warm_start(cur)
        job = StartJob(
            job_id=self._next_job_id,
            condition_id=cur.condition_id,
            point=cur.point,
            t_from=max(cur.t_start, t - self.config.max_window_s),
            t_to=t,
            warm_start=warm,
            warm_source=source,
            trigger=trigger,
        )
        self._next_job_id += 1
        self.running = _Running(job_id=job.job_id, condition_id=cur.condition_id, trigger=trigger)
        self.status = SchedulerStatus.RUNNING
        return job

    def _warm_start(self, cur: _Current) -> tuple[tuple[float, ...] | None, str]:
        if cur.last_h is not None:
            return cur.last_h, "this condition"
        others = [p for p in self.history if p.condition_id != cur.condition_id]
        if not others:
            return None, "none"
        best = min(enumerate(others), key=lambda kp: (self._distance(kp[1].point, cur.point), -kp[0]))[1]
        return best.h, f"condition {best.condition_id}"

    def _distance(self, a: OperatingPoint, b: OperatingPoint) -> float:
        return math.sqrt(
            sum(
                ((x - y) / s) ** 2
                for x, y, s in zip(a.as_tuple(), b.as_tuple(), self.config.distance_scales, strict=True)
            )
        )
