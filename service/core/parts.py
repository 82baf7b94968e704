"""What the core and its identification tracks share (``service.core.machine`` owns one ``CoreParts``; the
per-condition track ``service.core.schedtrack`` and the speed map's ``service.core.maptrack`` work on
it): the configuration, the live state, the sample history, the job book, the condition and the serving
strategy (as ``Decides``: what the tracks ask of it; ``service.core.serving`` implements it, and imports
this module, never the reverse); and ``Out``, the instructions of one ``handle`` call. Pure: no I/O, no
clock, no lock.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Protocol

import numpy as np

from service.acquire.calibration import OffsetCalibrator
from service.acquire.history import RingHistory
from service.contracts.records import Record
from service.contracts.snapshots import ConditionSnapshot, ConditionState, IdentificationRecord
from service.core.config import CoreConfig
from service.core.events import Instruction, Log, Rejected, RejectKind, Store
from service.core.jobbook import Job, JobBook
from service.core.jobs import Offsets
from service.core.samples import SampleBook
from service.estimate.state import GUESSED_H_REL, FilteredState
from service.estimate.state import h_rel_from_ci as h_rel
from service.identify import scheduler as sched
from service.identify.detector import ConditionDetector, DetectorStatus
from service.modelload import LoadedModel

__all__ = [
    "CONDITIONS_KEPT",
    "CoreParts",
    "Decides",
    "Load",
    "Out",
    "Served",
    "considered_h_rel",
    "h_rel",
    "live_h_rel",
    "no_baseline_sd",
    "utc",
]

CONDITIONS_KEPT = 200
Load = tuple[float, float] | None  # a per-condition fit's bearing-heat load scales
Served = tuple[IdentificationRecord, Load]  # an identification whose H the live state takes, with its load


class Decides(Protocol):
    """What the core and its tracks ask of the serving strategy (``service.core.serving.Serving``): which
    identification serves, and which one the live state takes when one finishes or the condition moves."""

    current: IdentificationRecord | None
    from_restore: bool
    map_serves: bool
    generation: int

    def identified(
        self, rec: IdentificationRecord, load: Load, condition: ConditionSnapshot | None
    ) -> Served | None: ...

    def mapped(self, rec: IdentificationRecord, condition: ConditionSnapshot | None) -> Served | None: ...

    def follow(self, condition: ConditionSnapshot | None) -> Served | None: ...


def utc(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, tz=UTC)


@dataclass
class Out:
    """The instructions of one ``handle`` call, each stamped with the event's id."""

    event_id: str
    instructions: list[Instruction] = field(default_factory=list)

    def store(self, record: Record) -> None:
        self.instructions.append(Store(self.event_id, record))

    def log(self, message: str) -> None:
        self.instructions.append(Log(self.event_id, message))

    def reject(self, kind: RejectKind, reason: str) -> None:
        self.instructions.append(Rejected(event_id=self.event_id, kind=kind, reason=reason))


@dataclass(eq=False, kw_only=True)
class CoreParts:
    """The core's shared state (see the module docstring); ``condition`` is the current one, ``conditions``
    the newest ``CONDITIONS_KEPT``, newest first."""

    config: CoreConfig
    model: LoadedModel
    live: FilteredState
    history: RingHistory
    detector: ConditionDetector
    scheduler: sched.IdentificationScheduler  # the per-condition schedule; also the job ids' source
    jobs: JobBook
    samples: SampleBook
    calibrator: OffsetCalibrator | None
    serving: Decides
    condition: ConditionSnapshot | None = None
    conditions: tuple[ConditionSnapshot, ...] = ()

    def set_condition(self, snap: ConditionSnapshot, *, new: bool = False) -> None:
        self.condition = snap
        if new or not self.conditions:
            self.conditions = (snap, *self.conditions[: CONDITIONS_KEPT - 1])
        else:
            self.conditions = (snap, *self.conditions[1:])

    def follow_condition(self) -> None:
        """The current condition is CHANGING while the detector holds a candidate, else STABLE."""
        cond = self.condition
        if cond is not None and self.detector.status is DetectorStatus.PENDING:
            if cond.state is not ConditionState.CHANGING:
                self.set_condition(replace(cond, state=ConditionState.CHANGING))
        elif cond is not None and cond.state is not ConditionState.STABLE:
            self.set_condition(replace(cond, state=ConditionState.STABLE))

    def condition_of(self, job: Job) -> ConditionSnapshot:
        cid = job.start.condition_id
        cond = next((c for c in self.conditions if c.id == cid), self.condition)
        assert cond is not None
        return cond

    def no_baseline_sd(self) -> float:
        """``no_baseline_sd`` of this core's configuration and calibrator."""
        return no_baseline_sd(self.config, self.calibrator)

    def h_rel_for(self, h: Any, hi: Any, guessed: Any = None) -> np.ndarray:
        """The live state's considered H error (relative 1σ, 7) for H ``h`` with 95 % upper bound ``hi``:
        the fit's σ(ln H) (``h_rel``), the model-form term ``live_h_form_sd`` (the served band's
        ``h_form_sd``) and ``no_baseline_sd`` in quadrature, as the served band (``/chtc``) has them: the
        growth's CI takes its H error from here (issue 40; docs/design/policy.md, "The served H band").
        ``guessed`` (7,) marks H that are no estimate (a fit's H on its search box's bound, a map's whose band
        lies wholly outside the box): theirs is ``GUESSED_H_REL``, whatever their band says."""
        return live_h_rel(self.config, self.calibrator, h, hi, guessed)

    def offsets(self) -> Offsets | None:
        cal = self.calibrator
        return None if cal is None else Offsets(cal.offsets(), cal.offset_sd())

    def serve(self, served: tuple[IdentificationRecord, tuple[float, float] | None] | None) -> None:
        """Give the live state the H (and bearing-heat load scales) of an identification the serving strategy
        has just started to serve (None: the live state's H stays, or comes from the map)."""
        if served is not None:
            rec, load = served
            self.live.set_h(rec.h, load, h_rel=self.h_rel_for(rec.h, rec.ci95_hi, rec.at_bound))

    def store_outcome(self, job: Job, *, outcome: str, message: str, finished_at: datetime, out: Out) -> None:
        data, _ = self.jobs.ended(
            job,
            outcome=outcome,
            message=message,
            finished_at=finished_at,
            event_id=out.event_id,
            condition=self.condition_of(job),
        )
        out.store(data)
        out.log(f"identification {job.key} {outcome}: {message}")


def no_baseline_sd(config: CoreConfig, calibrator: OffsetCalibrator | None) -> float:
    """1σ in ln H (``config.h_no_baseline_sd``) the H bands carry while offset calibration is on and has
    no baseline (the offsets unknown, 0.17 °C per channel: a warm start with an empty database), else 0
    (docs/design/estimator.md, "Warm restart with no stored state")."""
    return config.h_no_baseline_sd if calibrator is not None and calibrator.current is None else 0.0


def live_h_rel(
    config: CoreConfig, calibrator: OffsetCalibrator | None, h: Any, hi: Any, guessed: Any = None
) -> np.ndarray:
    """``considered_h_rel`` with the live state's terms: ``config.live_h_form_sd`` and ``no_baseline_sd``
    (``CoreParts.h_rel_for``; a restart's stored H before the parts exist)."""
    return considered_h_rel(
        h,
        hi,
        guessed,
        form_sd=config.live_h_form_sd,
        no_baseline_sd=no_baseline_sd(config, calibrator),
    )


def considered_h_rel(
    h: Any, hi: Any, guessed: Any = None, *, form_sd: float, no_baseline_sd: float
) -> np.ndarray:
    """``CoreParts.h_rel_for`` before the parts exist (a restart's stored H): the fit's σ(ln H) from its
    95 % upper bound ``hi``, ``form_sd`` and ``no_baseline_sd`` in quadrature; ``GUESSED_H_REL`` where
    ``guessed``."""
    rel = np.hypot(np.hypot(h_rel(h, hi), form_sd), no_baseline_sd)
    if guessed is not None:
        rel = np.where(np.asarray(guessed, dtype=bool), GUESSED_H_REL, rel)
    return np.asarray(rel)
