"""What goes into the service core and what comes out of it: frozen events and instructions.

``ServiceCore.handle(event) -> list[Instruction]`` (``service.core.machine``). Every event carries an
``event_id`` (a string the caller makes unique, e.g. ``"sample-1042"``, ``"outcome-3"``, ``"manual-1"``) and
every instruction the core emits while handling it carries the same id, as do the identification records it
stores (``IdentificationData.started_by_event``: the event that started the job, ``finished_by_event``: the
one that ended it), so a story can be followed from a sample to the stored row when debugging::

    SampleReceived        -> Store(sample row, condition rows, skipped jobs), Launch, Cancel, Log
    JobOutcomeReceived    -> Store(identification), Log, Launch (the next job that fell due)
    ManualRequested       -> ManualAccepted + Launch | Store (skipped at once) | Rejected(BUSY | NOT_READY)
    BaselineRequested     -> Calibrated + Log | Rejected(NOT_READY)
    BaselineAdopted       -> Calibrated + Store + Log (the calibrator had no baseline) | nothing
    IdsKnown              -> Log (ids continue from the database's: service.core.idcounter)

Refused requests are instructions (``Rejected`` with a :class:`RejectKind`), not exceptions: ``handle`` is
total for well-formed events. The shell turns ``Rejected`` into ``BusyError`` / ``NotReadyError`` for the API.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from datetime import datetime

from drivers.ringbuffer import Sample
from service.contracts.calibration import Calibration
from service.contracts.records import Record
from service.contracts.snapshots import IdentificationJob
from service.core.idcounter import IdsKnown
from service.identify.worker import JobOutcome, JobRequest

__all__ = [
    "BaselineAdopted",
    "BaselineRequested",
    "Calibrated",
    "Cancel",
    "Event",
    "IdsKnown",
    "Instruction",
    "JobOutcomeReceived",
    "Launch",
    "Log",
    "ManualAccepted",
    "ManualRequested",
    "RejectKind",
    "Rejected",
    "SampleReceived",
    "Store",
]


# --- events ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SampleReceived:
    """One acquisition sample (``drivers.ringbuffer.Sample``, UTC ``t``), in time order."""

    event_id: str
    sample: Sample


@dataclass(frozen=True, eq=False, kw_only=True)
class JobOutcomeReceived:
    """What the worker returned for a launched job."""

    event_id: str
    outcome: JobOutcome
    finished_at: datetime


@dataclass(frozen=True)
class ManualRequested:
    """An identification asked for through the API; ``reason`` is stored with it (up to 32 characters)."""

    event_id: str
    reason: str = "manual"


@dataclass(frozen=True)
class BaselineRequested:
    """An offset baseline asked for through the API at ``t`` (UTC; used only before the first sample)."""

    event_id: str
    t: datetime


@dataclass(frozen=True, eq=False)
class BaselineAdopted:
    """A baseline known from elsewhere (the stored commissioning's rest, ``service.contracts.
    commissionbaseline``), set while the service runs: used only when the calibrator has none (a rest
    baseline is never replaced)."""

    event_id: str
    calibration: Calibration


Event = SampleReceived | JobOutcomeReceived | ManualRequested | BaselineRequested | BaselineAdopted | IdsKnown


# --- instructions ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Store:
    """Hand ``record`` to the database writer."""

    event_id: str
    record: Record


@dataclass(frozen=True, eq=False, kw_only=True)
class Launch:
    """Run ``request`` in the worker process and send back its outcome (``JobOutcomeReceived``)."""

    event_id: str
    job_key: str  # "job-<id>", the API's job id
    request: JobRequest


@dataclass(frozen=True, kw_only=True)
class Cancel:
    """Cancel the worker's job ``job_id`` (its outcome, when it comes, is stored as cancelled)."""

    event_id: str
    job_id: int
    reason: str


@dataclass(frozen=True)
class Log:
    """A line for the operator (``chtc run`` prints it)."""

    event_id: str
    message: str


@dataclass(frozen=True)
class ManualAccepted:
    """The reply to ``ManualRequested``: the job it created (running, or already ended when skipped)."""

    event_id: str
    job: IdentificationJob


@dataclass(frozen=True, eq=False)
class Calibrated:
    """The reply to ``BaselineRequested`` (and the note of an automatic baseline): the new offsets."""

    event_id: str
    calibration: Calibration


class RejectKind(enum.StrEnum):
    BUSY = "busy"  # a job is running: try again later (HTTP 409)
    NOT_READY = "not_ready"  # no samples, no condition, too little data, calibration off or not at rest (503)


@dataclass(frozen=True, kw_only=True)
class Rejected:
    """A request the core refused, with the reason the API shows."""

    event_id: str
    kind: RejectKind
    reason: str


Instruction = Store | Launch | Cancel | Log | ManualAccepted | Calibrated | Rejected
