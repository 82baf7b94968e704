"""The core's book of identification jobs: the API's job table, the jobs waiting for their outcome, the
identification records this process made and their counts (owned and driven by ``service.core.machine``).

Ids: identification ids continue from ``next_identification_id`` (the database's, after a restart); a job's
key is ``"job-<scheduler job id>"``. Every record keeps the id of the event that started its job and of the
one that ended it (``IdentificationData.started_by_event`` / ``finished_by_event``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import UTC, datetime
from types import MappingProxyType
from typing import TypedDict

from model.identify import IdentificationResult
from service.contracts.columns import JsonValue
from service.contracts.metrics import HistogramData
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, IdentificationJob, IdentificationRecord, JobState
from service.core.idcounter import IdCounter
from service.identify.scheduler import StartJob
from service.serve.histogram import DURATION_BUCKETS_S
from service.serve.views import data_to_record

__all__ = ["MAP_METHOD", "Job", "JobBook", "MapValues", "job_key"]

RECORDS_KEPT = 500  # identifications this process remembers for the API (the database has them all)


def job_key(job_id: int) -> str:
    return f"job-{job_id}"


@dataclass(frozen=True, kw_only=True)
class Job:
    """A job the scheduler started, with what is needed to record its outcome."""

    start: StartJob
    key: str
    reason: str
    requested_at: datetime
    window_from: datetime
    window_to: datetime
    started_by: str  # id of the event that started it


MAP_METHOD = "speed-map"  # the method stored with a speed-map fit (identification.mode = "speed_map")


@dataclass(frozen=True, eq=False, kw_only=True)
class MapValues:
    """What a speed-map fit stores: H1-H7 and the 95 % band at the window's last condition (W/(m²·K)),
    ``identified`` flags, the RMS residual (°C), model runs, worker wall time (s), channels used, the
    fit's message and the map itself (``SpeedMap.to_json()``)."""

    h: tuple[float, ...]
    ci95_lo: tuple[float, ...]
    ci95_hi: tuple[float, ...]
    identified: tuple[bool, ...]
    rmse_c: float
    nfev: int
    wall_s: float
    n_sensors_used: int
    message: str
    speed_map: dict[str, JsonValue]


class _Meta(TypedDict):
    """The fields of an ``IdentificationData`` that the book knows whatever the outcome."""

    id: int
    condition_id: int
    started_at: datetime
    finished_at: datetime
    window_start: datetime
    window_end: datetime
    reason: str
    model_version: str
    warm_start_source: str | None
    started_by_event: str | None
    finished_by_event: str | None


class JobBook:
    """See the module docstring; ``model_version`` and ``method`` are stored with every record."""

    def __init__(self, *, next_identification_id: int, model_version: str, method: str) -> None:
        self.model_version = model_version
        self.method = method
        self.records: tuple[IdentificationRecord, ...] = ()  # newest first
        self.counts: dict[str, int] = {"ok": 0, "failed": 0, "insufficient-data": 0, "cancelled": 0}
        self.durations = HistogramData(
            upper_bounds=DURATION_BUCKETS_S, counts=(0,) * len(DURATION_BUCKETS_S), count=0, sum=0.0
        )
        self.jobs_view: MappingProxyType[str, IdentificationJob] = MappingProxyType({})
        self._jobs: dict[str, IdentificationJob] = {}
        self._waiting: dict[int, Job] = {}
        self._ids = IdCounter(next_identification_id)

    @property
    def id_counter(self) -> IdCounter:
        """The identification ids (``service.core.idcounter``)."""
        return self._ids

    def first_of(self, condition_id: int) -> bool:
        """Whether no record of this process belongs to ``condition_id`` yet."""
        return all(r.condition.id != condition_id for r in self.records)

    def open(self, start: StartJob, *, reason: str, now: datetime, event_id: str) -> Job:
        """A new job, queued: its window is the scheduler's until ``launched`` narrows it."""
        job = Job(
            start=start,
            key=job_key(start.job_id),
            reason=reason,
            requested_at=now,
            window_from=_utc(start.t_from),
            window_to=_utc(start.t_to),
            started_by=event_id,
        )
        self._set(IdentificationJob(job_id=job.key, reason=reason, state=JobState.QUEUED, requested_at=now))
        return job

    def launched(self, job: Job, *, window_from: datetime, window_to: datetime) -> Job:
        """``job`` runs in the worker on this window; its outcome is awaited."""
        job = replace(job, window_from=window_from, window_to=window_to)
        self._waiting[job.start.job_id] = job
        self._set(replace(self._jobs[job.key], state=JobState.RUNNING))
        return job

    def waiting(self, job_id: int) -> Job | None:
        return self._waiting.get(job_id)

    def take(self, job_id: int, wall_s: float) -> Job | None:
        """The awaited job whose outcome came (None: unknown), its worker time counted."""
        job = self._waiting.pop(job_id, None)
        if job is not None:
            self.durations = _observed(self.durations, wall_s)
        return job

    def cancelling(self, job_id: int, reason: str) -> None:
        """The job is being cancelled: failed for the API at once (its record comes with the outcome)."""
        key = job_key(job_id)
        if key in self._jobs and self._jobs[key].state in (JobState.QUEUED, JobState.RUNNING):
            self._set(replace(self._jobs[key], state=JobState.FAILED, message=reason))

    def ended(
        self,
        job: Job,
        *,
        outcome: str,
        message: str,
        finished_at: datetime,
        event_id: str,
        condition: ConditionSnapshot,
    ) -> tuple[IdentificationData, IdentificationRecord]:
        """``job`` ended without a result (failed, skipped, cancelled, ...): its record."""
        meta = self._meta(job, finished_at, event_id)
        data = IdentificationData(outcome=outcome, method=self.method, message=message, **meta)
        return data, self._record(data, job, condition)

    def identified(
        self,
        job: Job,
        result: IdentificationResult,
        *,
        finished_at: datetime,
        event_id: str,
        condition: ConditionSnapshot,
    ) -> tuple[IdentificationData, IdentificationRecord]:
        """``job`` ended with ``result``: its record."""
        data = IdentificationData.from_result(result, **self._meta(job, finished_at, event_id))
        return data, self._record(data, job, condition)

    def mapped(
        self,
        job: Job,
        *,
        values: MapValues,
        finished_at: datetime,
        event_id: str,
        condition: ConditionSnapshot,
    ) -> tuple[IdentificationData, IdentificationRecord]:
        """A speed-map ``job`` ended with a map fit: its record (H at the window's last speed, the map in
        the diagnostics, method ``MAP_METHOD``)."""
        f = values.rmse_c**2
        data = IdentificationData(
            outcome="ok",
            method=MAP_METHOD,
            h=[float(x) for x in values.h],
            ci95_lo=[float(x) for x in values.ci95_lo],
            ci95_hi=[float(x) for x in values.ci95_hi],
            identified=[bool(x) for x in values.identified],
            f=f,
            fit=1.0 / (1.0 + f),
            rmse_c=values.rmse_c,
            nfev=values.nfev,
            duration_s=values.wall_s,
            n_sensors_used=values.n_sensors_used,
            message=values.message,
            diagnostics={"speed_map": values.speed_map, "at_bound": [False] * len(values.h)},
            **self._meta(job, finished_at, event_id),
        )
        return data, self._record(data, job, condition)

    def _meta(self, job: Job, finished_at: datetime, event_id: str) -> _Meta:
        return {
            "id": next(self._ids),
            "condition_id": job.start.condition_id,
            "started_at": job.requested_at,
            "finished_at": finished_at,
            "window_start": job.window_from,
            "window_end": job.window_to,
            "reason": job.reason,
            "model_version": self.model_version,
            "warm_start_source": job.start.warm_source,
            "started_by_event": job.started_by,
            "finished_by_event": event_id,
        }

    def _record(
        self, data: IdentificationData, job: Job, condition: ConditionSnapshot
    ) -> IdentificationRecord:
        rec = data_to_record(data, condition)
        self.records = (rec, *self.records[: RECORDS_KEPT - 1])
        self.counts[data.outcome] = self.counts.get(data.outcome, 0) + 1
        state = JobState.DONE if data.outcome == "ok" else JobState.FAILED
        self._set(
            replace(
                self._jobs[job.key],
                state=state,
                finished_at=data.finished_at,
                identification_id=data.id,
                message=data.message,
            )
        )
        return rec

    def _set(self, job: IdentificationJob) -> None:
        self._jobs[job.job_id] = job
        self.jobs_view = MappingProxyType(dict(self._jobs))


def _utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)


def _observed(h: HistogramData, value: float) -> HistogramData:
    """``h`` with one more observation (a cumulative histogram, as ``Histogram.observe`` keeps it)."""
    counts = tuple(c + 1 if value <= ub else c for c, ub in zip(h.counts, h.upper_bounds, strict=True))
    return HistogramData(
        upper_bounds=h.upper_bounds, counts=counts, count=h.count + 1, sum=h.sum + float(value)
    )
