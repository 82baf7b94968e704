"""The service's core run offline over a recorded sample sequence: deterministic identifications.

Used by ``chtc identify`` (recorded log files) and by tests. The samples go through exactly the same
``ServiceCore`` (ring buffer, live state, detector, scheduler, window building) as in the running service;
the only difference is that each identification runs synchronously in this process (``run_job``, the
worker process's function, with the same seeded rng), so the same log always gives the same H.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np

from service.acquire.history import RingHistory
from service.engine.core import CoreConfig, Restored, ServiceCore
from service.identify.worker import JobOutcome, JobStatus, run_job
from service.modelload import LoadedModel
from service.serve.interface import IdentificationRecord

__all__ = ["OfflineResult", "run_offline"]


@dataclass
class OfflineResult:
    records: list[IdentificationRecord]  # oldest first
    stored: list[Any] = field(default_factory=list)  # the records the database writer would have got
    samples: int = 0
    conditions: list[Any] = field(default_factory=list)  # ConditionSnapshot, oldest first
    first: datetime | None = None  # time of the first and the last sample
    last: datetime | None = None
    calibration: Any = (
        None  # service.acquire.calibration.Calibration of the newest offset baseline (None: none)
    )


class _ListSink:
    def __init__(self) -> None:
        self.records: list[Any] = []

    def submit(self, record: Any) -> bool:
        self.records.append(record)
        return True


class _Tee:
    def __init__(self, first: _ListSink, second: Any) -> None:
        self.first, self.second = first, second

    def submit(self, record: Any) -> bool:
        self.first.submit(record)
        return True if self.second is None else bool(self.second.submit(record))


def run_offline(
    samples: Iterable[Any],
    *,
    model: LoadedModel,
    config: CoreConfig,
    ring_capacity: int = 100_000,
    on_event: Callable[[str], None] | None = None,
    restored: Restored | None = None,
    sink: Any = None,
) -> OfflineResult:
    """Feed ``samples`` (``drivers.ringbuffer.Sample``, time-ordered) through the core; identify inline."""
    from drivers.ringbuffer import RingBuffer

    ring = RingBuffer(ring_capacity, len(model.spec.sensors))
    listed = _ListSink()
    core = ServiceCore(
        config,
        model=model,
        history=RingHistory(ring),
        sink=_Tee(listed, sink),
        restored=restored,
        on_event=on_event,
    )
    n, first, last = 0, None, None
    for sample in samples:
        ring.append(sample)
        n += 1
        first, last = first or sample.t, sample.t
        pending = core.ingest(sample)
        while pending:
            launch = pending.pop(0)
            assert launch.request is not None
            outcome = run_job(model, launch.request)  # the worker process's own function, in this process
            finished = _finished_at(sample.t, outcome)
            stepper = None
            if outcome.status is JobStatus.OK and outcome.result is not None:
                stepper = core.live.prepare(np.asarray(outcome.result.h, dtype=float))
            pending += core.job_done(outcome, finished_at=finished, stepper=stepper)
    cal = core.calibrator.current if core.calibrator is not None else None
    return OfflineResult(
        records=list(reversed(core.records)),
        stored=listed.records,
        samples=n,
        conditions=list(reversed(core.conditions)),
        first=first,
        last=last,
        calibration=cal,
    )


def _finished_at(t: datetime, outcome: JobOutcome) -> datetime:
    """Offline, an identification finishes at the sample that triggered it (no wall time passes)."""
    del outcome
    return t
