"""What the running service drives outside itself, as protocols: the database writer and the identification
worker (``service.shell.service.SoftSensorService`` takes them; ``service.shell.internal`` drives them)."""

from __future__ import annotations

from typing import Protocol

from service.contracts.records import Record
from service.identify.worker import JobOutcome, JobRequest
from service.shell.health import StatusSource

__all__ = ["RecordWriter", "Worker"]


class RecordWriter(StatusSource, Protocol):
    """The buffered database writer (``service.store.writer.DbWriter`` or ``persistence.GateSink``)."""

    def submit(self, record: Record) -> bool: ...


class Worker(Protocol):
    """The identification worker as the shell drives it: ``service.identify.worker.IdentificationWorker`` (a
    process) in the running service, ``simulator.served.InlineWorker`` (a thread) in the API tests.

    ``model_version`` is None until ``start()`` has loaded the model; ``run`` never raises for a failed job (a
    failure is an outcome); ``running_job`` is the job id ``run`` is busy with, ``restarts`` counts processes
    replaced after a crash or a hang.
    """

    model_version: str | None
    restarts: int
    running_job: int | None

    async def start(self) -> str: ...

    async def run(self, req: JobRequest) -> JobOutcome: ...

    def cancel(self, job_id: int) -> None: ...

    def close(self) -> None: ...
