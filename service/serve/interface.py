"""The service protocol: what the API (and every reader of the running service) needs, ``ChtcService``.

``api/`` imports from ``service/`` only this package (``service.serve``) and the value types it hands out
(``service.contracts``: the snapshots, the errors, the verdict). The running service
(``service/shell/service.py``) implements :class:`ChtcService`; the API tests serve it too
(``simulator/served.py``).

Contract for implementers:

- Every method is synchronous, thread-safe and cheap. ``chtc()``, ``chtc_map()``, ``condition()``,
  ``sensors()``, ``health()``, ``ready()`` and ``metrics()`` are called on every poll (10 Hz per client is
  expected): return prebuilt, immutable snapshots, never do I/O or numerical work in them.
  ``list_identifications()`` and ``get_identification()`` may read the database (the API calls them from a
  worker thread). ``field()`` may solve a steady state once per identification but should cache the result.
- Units: temperatures °C, H in W/(m²·K), lengths m, speed rpm, torque N·m, durations s. Every ``datetime`` is
  timezone-aware UTC.
- Snapshots are frozen (``service.contracts.snapshots``); arrays inside them must not be mutated after
  construction (build new snapshots).
- Failures are typed (never ``None`` for "failed"): ``NotFoundError``, ``NoDataYetError``, ``BusyError``,
  ``NotReadyError`` (``service.contracts.errors``, whose docstring draws the tree and the HTTP codes).

  ``chtc()`` returns ``None`` only with its documented meaning: no identification has finished yet;
  ``chtc_map()`` returns ``None`` in per-condition mode or before the first map fit.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from service.contracts.health import HealthSnapshot, Readiness
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.metrics import MetricsSnapshot, OutletMetrics
from service.contracts.mode import IdentificationMode
from service.contracts.probe import ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    ChtcMapSnapshot,
    ChtcSnapshot,
    CompensationSnapshot,
    ConditionSnapshot,
    FieldAt,
    FieldSnapshot,
    IdentificationJob,
    IdentificationPage,
    IdentificationRecord,
    OffsetBaseline,
    SectionSnapshot,
    SensorHistory,
    SensorReading,
    SpindleLayout,
)

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = ["ChtcService", "CountedOutlet", "FleetHost", "HostedRuntime", "HostedSpindle"]


@runtime_checkable
class CountedOutlet(Protocol):
    """An outlet (``service.serve.outlet.Outlet``) that counts its deliveries for ``/metrics``."""

    name: str

    def outlet_metrics(self) -> OutletMetrics: ...


@runtime_checkable
class ChtcService(Protocol):
    """What the API needs from the running service (see the module docstring for the contract)."""

    def chtc(self) -> ChtcSnapshot | None:
        """The current H1-H7; None only if no identification has finished yet."""
        ...

    def chtc_map(self) -> ChtcMapSnapshot | None:
        """The H map over the speed range with its bands and the visited speeds; None when the service runs
        per condition (``identification.mode = "per_condition"``) or no map has been fitted yet. Cheap (a
        prebuilt snapshot per map fit and ambient)."""
        ...

    def identification_mode(self) -> IdentificationMode:
        """``PER_CONDITION`` (the paper's protocol: one H per held condition), ``SPEED_MAP`` (H = F(n, Ti)
        over the speed range, ``chtc_map()``) or ``COMBINED`` (both: the per-condition H at a held condition,
        the map's elsewhere); fixed for the service's life (``identification.mode``; a ``str`` enum whose
        values are the settings' spelling)."""
        ...

    def field(self, at: FieldAt) -> FieldSnapshot:
        """Temperature field now (state estimate) or at steady state for the current H and condition.

        Raises NoDataYetError before the first identification.
        """
        ...

    def sensors(self) -> Sequence[SensorReading]:
        """The 32 channels at the newest sample; raises NoDataYetError before the first sample."""
        ...

    def condition(self) -> ConditionSnapshot:
        """The current operating condition; raises NoDataYetError before the first CAN frame."""
        ...

    def request_baseline(self) -> OffsetBaseline:
        """Take a sensor-offset baseline now (spindle at rest, at the ambient); NotReadyError says why not."""
        ...

    def compensation_reference(self) -> CompensationReference | None:
        """The compensation zero in use (None: none set: ``/compensation`` is then not usable)."""
        ...

    def set_compensation_reference(
        self, *, temperature_c: float | None, source: str, set_by: str
    ) -> CompensationReference:
        """Store the compensation zero now: ``temperature_c`` [°C] as given, else the uniform equivalent of
        the live field (NotReadyError while the live state has not converged); persisted, restored at
        start."""
        ...

    def compensation_mechanics(self) -> MechanicsCalibration | None:
        """The mechanics in use: the commissioning updated by the probe readings absorbed since, or the
        prior updated by them (source "prior") when not commissioned (None: the spindle description's,
        uncalibrated, and no reading absorbed)."""
        ...

    def commission_mechanics(
        self,
        *,
        temperatures: Path,
        canlog: Path | None,
        displacements: Path,
        set_by: str,
        source: str,
        force: bool = False,
    ) -> tuple[Any, bool]:
        """Fit the mechanics to a measured thermal test (``service.shell.commissioning``; blocking); store
        and use it when the model explains the test or ``force``: (report, stored). ``CommissioningError``
        (and ``drivers.logs.LogFormatError``) for unusable files, naming the line."""
        ...

    def compensation_measurements(self) -> list[ProbeMeasurement]:
        """The probe readings kept (restored and new, absorbed or not), newest first."""
        ...

    def add_measurement(
        self, *, at: datetime, axial_um: float, sd_um: float, set_by: str, source: str
    ) -> ProbeMeasurement:
        """Take a probe reading of the axial growth at ``at`` (``service.estimate.probe``; blocking), absorb
        it into the mechanical posterior unless it lies beyond the gate, and store it. ``ProbeError`` naming
        the field for one that cannot be used (``at`` in the future or outside the kept history)."""
        ...

    def recent_conditions(self, limit: int) -> Sequence[ConditionSnapshot]:
        """Up to ``limit`` most recent conditions, newest first (the current one included)."""
        ...

    def list_identifications(
        self, *, since: datetime | None, until: datetime | None, limit: int, offset: int
    ) -> IdentificationPage:
        """Stored identifications finished in [since, until), newest first."""
        ...

    def get_identification(self, identification_id: int) -> IdentificationRecord:
        """One stored identification; raises NotFoundError."""
        ...

    def request_identification(self, reason: str) -> IdentificationJob:
        """Queue an identification now; BusyError if one is queued/running, NotReadyError if it can't run."""
        ...

    def job(self, job_id: str) -> IdentificationJob:
        """State of a requested identification; raises NotFoundError."""
        ...

    def health(self) -> HealthSnapshot: ...

    def ready(self) -> Readiness: ...

    def metrics(self) -> MetricsSnapshot: ...

    def sensor_history(self, since: datetime | None) -> SensorHistory:
        """Measured and predicted temperatures of the samples after ``since`` (all kept ones if None), oldest
        first; empty before the first sample. Cheap: a copy out of a bounded in-memory buffer."""
        ...

    def layout(self) -> SpindleLayout:
        """The spindle's solid parts and convective zones (static, for labelling the section)."""
        ...

    def compensation(self) -> CompensationSnapshot | None:
        """The thermal growth at the tool now; None only if there is nothing yet (no identification or no
        live field). May build the growth model (once) and its per-condition terms (per identification and
        condition, ~0.3 s): the API calls it from a worker thread."""
        ...

    def compensation_section(self) -> SectionSnapshot | None:
        """The section deformed by the live field (displacement in µm on the outline's nodes); None as for
        ``compensation()``, which it calls for the status (from a worker thread)."""
        ...


class HostedRuntime(Protocol):
    """A hosted spindle's running instance: its service (None until it has started)."""

    @property
    def service(self) -> ChtcService | None: ...


class HostedSpindle(Protocol):
    """One spindle of a host (``service.host.fleet.HostedSpindle``): its id, description, settings and
    running instance, or the ``error`` that stopped it."""

    @property
    def id(self) -> str: ...

    @property
    def description(self) -> str: ...

    @property
    def settings(self) -> Settings: ...

    @property
    def runtime(self) -> HostedRuntime | None: ...

    @property
    def error(self) -> str | None: ...

    @property
    def service(self) -> object | None: ...


class FleetHost(Protocol):
    """What the fleet's REST API (``api/fleet.py``) reads of an instance hosting several spindles
    (``service.host.fleet.Host``; docs/design/fleet.md)."""

    @property
    def settings(self) -> Settings: ...

    @property
    def spindles(self) -> Mapping[str, HostedSpindle]: ...

    @property
    def clock(self) -> Callable[[], datetime]: ...

    @property
    def failed(self) -> dict[str, str]: ...

    def outlet_metrics(self) -> Mapping[str, OutletMetrics]: ...
