"""The service's core run offline over a recorded sample sequence: deterministic identifications.

Used by ``chtc identify`` (recorded log files), the benches and tests. The samples go through exactly the
same ``ServiceCore`` (sample history, live state, detector, scheduler, window building) and the same events
as in the running service (``service.shell.service``); the only difference is that each ``Launch`` runs
synchronously in this process (``service.identify.worker.run_job``, the worker process's own function, with
the same seeded rng) instead of in the worker process, so the same log always gives the same H.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Protocol

from drivers.ringbuffer import Sample
from model.identify import IdentificationResult
from service.contracts.calibration import Calibration
from service.contracts.records import Record
from service.contracts.snapshots import ConditionSnapshot, IdentificationRecord
from service.core.config import CoreConfig, Restored
from service.core.events import (
    Event,
    Instruction,
    JobOutcomeReceived,
    Launch,
    Log,
    SampleReceived,
    Store,
)
from service.core.machine import ServiceCore
from service.identify.worker import JobStatus, run_job
from service.modelload import LoadedModel

__all__ = ["OfflineResult", "RecordSink", "run_job", "run_offline"]


class RecordSink(Protocol):
    def submit(self, record: Record) -> bool: ...


@dataclass(kw_only=True)
class OfflineResult:
    records: list[IdentificationRecord]  # oldest first
    stored: list[Record] = field(default_factory=list)  # the records the database writer would have got
    samples: int = 0
    conditions: list[ConditionSnapshot] = field(default_factory=list)  # oldest first
    first: datetime | None = None  # time of the first and the last sample
    last: datetime | None = None
    calibration: Calibration | None = None  # the newest offset baseline (None: none)
    instructions: list[Instruction] = field(default_factory=list)  # every instruction, in order


def run_offline(
    samples: Iterable[Sample],
    *,
    model: LoadedModel,
    config: CoreConfig,
    ring_capacity: int = 100_000,
    on_event: Callable[[str], None] | None = None,
    restored: Restored | None = None,
    sink: RecordSink | None = None,
    on_sample: Callable[[ServiceCore, int, IdentificationResult | None], None] | None = None,
) -> OfflineResult:
    """Feed ``samples`` (time-ordered) through the core; identify inline.

    Event ids: ``sample-<n>`` (1-based sample number) and ``outcome-<job id>``. An identification finishes
    at the sample that triggered it (no wall time passes offline). ``on_sample(core, k, last_ok)``, if given,
    is called after sample k (0-based) and the identifications it started, with the newest successful
    result so far (None: none yet), so that a bench can read the live state as the service would serve it.
    """
    core = ServiceCore(config, model=model, restored=restored, history_capacity=ring_capacity)
    res = OfflineResult(records=[])
    last_ok: IdentificationResult | None = None
    for n, sample in enumerate(samples, start=1):
        res.samples = n
        res.first, res.last = res.first or sample.t, sample.t
        pending: list[Event] = [SampleReceived(f"sample-{n}", sample)]
        while pending:
            for ins in core.handle(pending.pop(0)):
                res.instructions.append(ins)
                if isinstance(ins, Store):
                    res.stored.append(ins.record)
                    if sink is not None:
                        sink.submit(ins.record)
                elif isinstance(ins, Log) and on_event is not None:
                    on_event(ins.message)
                elif isinstance(ins, Launch):
                    done = _outcome(core, model, ins, sample.t)
                    if done.outcome.status is JobStatus.OK and done.outcome.result is not None:
                        last_ok = done.outcome.result
                    pending.append(done)
        if on_sample is not None:
            on_sample(core, n - 1, last_ok)
    view = core.view()
    res.records = list(reversed(view.records))
    res.conditions = list(reversed(view.conditions))
    res.calibration = view.calibration
    return res


def _outcome(core: ServiceCore, model: LoadedModel, launch: Launch, t: datetime) -> JobOutcomeReceived:
    outcome = run_job(model, launch.request)
    return JobOutcomeReceived(event_id=f"outcome-{launch.request.job_id}", outcome=outcome, finished_at=t)
