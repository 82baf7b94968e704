"""The running soft sensor: :class:`SoftSensorService`, the asyncio shell around the pure
:class:`service.core.machine.ServiceCore`, and the ``service.serve.interface.ChtcService`` the API reads.

A thin facade (as asyncua's ``Server`` wraps its ``InternalServer``) over its parts, exposed as they are:

- ``internal`` (``service.shell.internal.InternalService``): the event loop's side of the core: events in
  (``on_sample``, ``post``, ``handle``), the published view, instructions executed (database writer, worker
  process), outlets (``subscribe``), device health;
- ``growth`` (``service.serve.compensation.GrowthServer``): what ``/compensation`` serves;
- the reads: ``reader()``, a ``service.serve.reader.ViewReader`` of the newest published view (the same values
  every outlet serves; ``chtc()``, ``compensation()``, ... are ``NewestViewReads``'s, in ``service.serve``).

What stays here is what the service does for its callers beyond the core: the requests that become events and
whose replies become answers or errors, the compensation's commissioning writes (stored through the writer),
the history from the database, the metrics. Time comes from an injected ``clock`` (UTC ``datetime``), the same
clock the acquisition stamps samples with, so ``chtc demo`` can run the whole service at a speed-up.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Coroutine, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivers.ringbuffer import Sample
from service.contracts.commissionbaseline import commissioning_baseline
from service.contracts.errors import BusyError, NotReadyError, RecordError
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.metrics import MetricsSnapshot
from service.contracts.probe import ProbeError, ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    IdentificationJob,
    IdentificationPage,
    IdentificationRecord,
    OffsetBaseline,
    SensorHistory,
)
from service.core.events import (
    BaselineAdopted,
    BaselineRequested,
    Calibrated,
    Event,
    Instruction,
    ManualAccepted,
    ManualRequested,
    Rejected,
    RejectKind,
)
from service.core.machine import ServiceCore
from service.identify.worker import JobOutcome, JobRequest
from service.serve.compensation import GrowthServer
from service.serve.reader import MAP_H_BOX, NewestViewReads, ViewReader
from service.serve.view import CoreView
from service.shell.archive import IdentificationArchive
from service.shell.corethread import CoreRunner
from service.shell.health import HealthSource
from service.shell.internal import InternalService
from service.shell.looplag import LoopLagMonitor
from service.shell.ports import RecordWriter, Worker
from service.store.mechanics import mechanics_record
from service.store.probes import probe_record
from service.store.references import reference_record

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from service.serve.outlet import Outlet
    from service.shell.commissioning import CommissionReport
    from service.store.reads import DbReads

__all__ = ["MAP_H_BOX", "RecordWriter", "SoftSensorService", "Worker"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]


def utc_now() -> datetime:
    return datetime.now(UTC)


class SoftSensorService(NewestViewReads):
    """See the module docstring. Construct with the parts, ``start()`` on the loop, ``close()`` at the end."""

    # the internal service's parts, exposed as they are (bound in __init__)
    start: Callable[[], Coroutine[object, object, None]]
    close: Callable[[], Coroutine[object, object, None]]
    handle: Callable[[Event], list[Instruction]]
    post: Callable[[Event], None]
    on_sample: Callable[[Sample], None]
    ids_known: Callable[[int, int], None]
    subscribe: Callable[[Outlet], None]
    unsubscribe: Callable[[Outlet], None]
    record_event: Callable[..., None]
    reader: Callable[[], ViewReader]

    def __init__(
        self,
        core: ServiceCore,
        *,
        worker: Worker | None,
        writer: RecordWriter | None = None,
        session_factory: sessionmaker[Session] | None = None,  # for the history endpoints
        db_reads: DbReads | None = None,  # history reads bounded and with a deadline
        sources: Mapping[str, HealthSource] | None = None,  # "modbus"/"can" -> drivers Source
        clock: Clock = utc_now,
        on_event: Callable[[str], None] | None = None,
        history_capacity: int = 2160,  # samples of measured vs predicted kept for the API (6 h at 10 s)
        run_job: Callable[[JobRequest], JobOutcome] | None = None,
        growth: GrowthServer | None = None,  # /compensation; default: referred to the live state's start
        runner: CoreRunner | None = None,  # where the core's work runs (default inline; runtime: CoreThread)
        max_core_lag_s: float = math.inf,  # a sample waiting longer for the core: served as core_behind
        loop_lag: LoopLagMonitor | None = None,  # measured on the loop from start(); /healthz, /metrics
        own_loop_lag: bool = True,  # run loop_lag's measuring task (False: its owner runs it, e.g. a Host)
        outlet_interval_s: float = 0.1,  # subscribed outlets get a new view at most this often (coalesced)
    ) -> None:
        self.core = core
        self.worker = worker
        self.writer = writer
        self.clock = clock
        self.on_event = on_event or (lambda msg: log.info("%s", msg))
        self.growth = growth if growth is not None else GrowthServer(core.model)  # /compensation
        if self.growth.on_reference is None:  # every zero taken is stored (restored at the next start)
            self.growth.on_reference = self._store_reference
        self._archive = IdentificationArchive(session_factory, db_reads)
        self.internal = i = InternalService(
            core,
            worker=worker,
            writer=writer,
            sources=sources or {},
            clock=clock,
            on_event=self.on_event,
            history_capacity=history_capacity,
            run_job=run_job,
            growth=self.growth,
            runner=runner,
            max_core_lag_s=max_core_lag_s,
            loop_lag=loop_lag,
            own_loop_lag=own_loop_lag,
            outlet_interval_s=outlet_interval_s,
        )
        self.runner = i.runner
        self.loop_lag = loop_lag
        self.start, self.close, self.handle, self.post = i.start, i.close, i.handle, i.post
        self.on_sample, self.ids_known, self.record_event = i.on_sample, i.ids_known, i.record_event
        self.subscribe, self.unsubscribe = i.outlets.subscribe, i.outlets.unsubscribe
        self.reader = i.reader

    @property
    def model_loaded(self) -> bool:
        """The identification worker has loaded its model (a host's ``/readyz`` waits for it)."""
        return bool(self.internal.model_loaded)

    @property
    def view(self) -> CoreView:
        """The core's state after the last event (immutable; replaced, never changed)."""
        return self.internal.view

    # --- ChtcService: requests ------------------------------------------------------------------------------
    def request_baseline(self) -> OffsetBaseline:
        for ins in self.handle(BaselineRequested(self.internal.next_id("baseline"), self.clock())):
            if isinstance(ins, Rejected):
                raise NotReadyError(ins.reason)
            if isinstance(ins, Calibrated):
                c = ins.calibration
                return OffsetBaseline(
                    t_from=c.t_from,
                    t_to=c.t_to,
                    source=c.source,
                    samples=c.samples,
                    offsets_c=tuple(float(x) if np.isfinite(x) else None for x in c.offsets_c),
                    sd_c=tuple(float(x) for x in c.sd_c),
                )
        raise NotReadyError("no baseline")

    def set_compensation_reference(
        self, *, temperature_c: float | None, source: str, set_by: str
    ) -> CompensationReference:
        ref = self.growth.take_reference(
            self.view, source=source, set_by=set_by, temperature_c=temperature_c, at=self.clock()
        )
        self.on_event(
            f"compensation zero set: {ref.temperature_c:.3f} °C ± {ref.sd_c:.3f} "
            f"({ref.source}, by {ref.set_by})"
        )
        return ref

    def commission_mechanics(
        self,
        *,
        temperatures: Path,
        canlog: Path | None,
        displacements: Path,
        set_by: str,
        source: str,
        force: bool = False,
    ) -> tuple[CommissionReport, bool]:
        """Fit the mechanics to a measured thermal test with this service's own core and model
        (``service.shell.commissioning``; blocking, seconds to a minute: call it off the event loop);
        store and use the calibration when the model explains the test (or ``force``). (report, stored)."""
        from service.shell.commissioning import commission_growth

        rep = commission_growth(
            self.core.model,
            self.core.config,
            temperatures,
            canlog,
            displacements,
            set_by=set_by,
            source=source,
            basis=self.growth.mechanics_basis(),
            now=self.clock(),
        )
        stored = rep.explained or force
        if stored:
            self.set_mechanics(rep.calibration)
        return rep, stored

    def set_mechanics(self, cal: MechanicsCalibration) -> None:
        """Serve with ``cal`` from now on and store it (restored at every start); blocking (~2 s the first
        time: the mount/α operators). The offset baseline of its test's rest is used when the core has none
        (``service.contracts.commissionbaseline``: a start without the stored baseline)."""
        self.growth.set_mechanics(cal)
        if self.writer is not None:
            self.writer.submit(mechanics_record(cal))
        try:
            baseline = commissioning_baseline(cal)
        except RecordError as err:
            self.on_event(f"the commissioning's offset baseline is not used: {err}")
            baseline = None
        if baseline is not None:
            self.post(BaselineAdopted(self.internal.next_id("baseline"), baseline))
        x = cal.x
        self.on_event(
            f"mechanics commissioned: restraint {x[0]:.3f}, α shaft {x[1]:.3f}, α housing {x[2]:.3f} "
            f"({cal.source}, by {cal.set_by}; the model "
            f"{'explains' if cal.explained else 'does NOT explain'} "
            "the test)"
        )

    def add_measurement(
        self, *, at: datetime, axial_um: float, sd_um: float, set_by: str, source: str
    ) -> ProbeMeasurement:
        """Take a probe reading (``GrowthServer.measure``; blocking, ~2 s the first time: call it off the
        event loop) and store it, absorbed or not. ``ProbeError`` naming the field: ``at`` in the future
        (beyond the live state's newest instant) or outside the kept history, a bad value."""
        now = self.clock()
        if at > now:
            raise ProbeError(f"at: {at.isoformat()} is in the future (now {now.isoformat()})")
        m = self.growth.measure(
            self.view, at=at, axial_um=axial_um, sd_um=sd_um, set_by=set_by, source=source
        )
        if self.writer is not None:
            self.writer.submit(probe_record(m, now))
        verdict = (
            f"absorbed as a STEP of the fixture offset ({m.sigma_ratio:.1f} σ off, like the one before)"
            if m.offset_step
            else "absorbed"
            if m.accepted
            else f"NOT absorbed: {m.sigma_ratio:.1f} σ off (a crash or a tool change since the last one?)"
        )
        off = self.growth.fixture_offset
        self.on_event(
            f"probe reading {m.axial_um:+.2f} ± {m.sd_um:.2f} µm at {m.at.isoformat()} (predicted "
            f"{m.predicted_um:+.2f} ± {m.sigma_um:.2f} µm): {verdict}"
            + ("" if off is None else f"; fixture offset {off.um:+.2f} ± {off.sd_um:.2f} µm")
        )
        return m

    def _store_reference(self, ref: CompensationReference) -> None:
        if self.writer is not None:
            self.writer.submit(reference_record(ref))

    def sensor_history(self, since: datetime | None) -> SensorHistory:
        return self.internal.history.since(since)

    # --- ChtcService: history ---------------------------------------------------------------------------
    def list_identifications(
        self, *, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        records = self.view.records
        return self._archive.page(records, since=since, until=until, limit=limit, offset=offset)

    def get_identification(self, identification_id: int) -> IdentificationRecord:
        return self._archive.get(self.view.records, identification_id)

    # --- ChtcService: requests --------------------------------------------------------------------------
    def request_identification(self, reason: str) -> IdentificationJob:
        if (
            not self.internal.model_loaded
        ):  # the core does not know the worker; no job can run before its model
            raise NotReadyError("the model is still loading in the identification worker; retry when ready")
        for ins in self.handle(ManualRequested(self.internal.next_id("manual"), reason)):
            if isinstance(ins, Rejected):
                raise (BusyError if ins.kind is RejectKind.BUSY else NotReadyError)(ins.reason)
            if isinstance(ins, ManualAccepted):
                return ins.job
        raise NotReadyError("the identification request was not answered")

    # --- ChtcService: metrics -------------------------------------------------------------------------------
    def metrics(self) -> MetricsSnapshot:
        i = self.internal
        return i.gauges.metrics(
            i.view,
            chtc=self.chtc(),
            model_version=self.core.model.version if i.model_loaded else None,
            growth_terms=(self.growth.computed, self.growth.compute_cpu_s),
            outlets=i.outlets.metrics(),
        )
