"""Driving the service core with events in tests: samples in, instructions out, jobs run inline."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime

from drivers.ringbuffer import Sample
from service.contracts.records import Record
from service.core.events import Event, Instruction, JobOutcomeReceived, Launch, SampleReceived, Store
from service.core.machine import ServiceCore
from service.identify.worker import JobOutcome, run_job
from service.modelload import LoadedModel


def feed(core: ServiceCore, samples: Iterable[Sample], *, first: int = 1) -> list[Instruction]:
    """Hand each sample to ``core`` as ``SampleReceived("sample-<n>")``; every instruction, in order."""
    out: list[Instruction] = []
    for n, s in enumerate(samples, start=first):
        out += core.handle(SampleReceived(f"sample-{n}", s))
    return out


def feed_and_run(
    core: ServiceCore, model: LoadedModel, samples: Iterable[Sample], *, first: int = 1
) -> list[Instruction]:
    """``feed``, running each launched job at once (``run_job``) and handing its outcome back."""
    out: list[Instruction] = []
    for n, s in enumerate(samples, start=first):
        pending: list[Event] = [SampleReceived(f"sample-{n}", s)]
        while pending:
            for ins in core.handle(pending.pop(0)):
                out.append(ins)
                if isinstance(ins, Launch):
                    pending.append(outcome_event(core, run_job(model, ins.request), s.t))
    return out


def outcome_event(core: ServiceCore, outcome: JobOutcome, t: datetime) -> JobOutcomeReceived:
    return JobOutcomeReceived(event_id=f"outcome-{outcome.job_id}", outcome=outcome, finished_at=t)


def launches(instructions: Iterable[Instruction]) -> list[Launch]:
    return [i for i in instructions if isinstance(i, Launch)]


def stored(instructions: Iterable[Instruction]) -> list[Record]:
    return [i.record for i in instructions if isinstance(i, Store)]
