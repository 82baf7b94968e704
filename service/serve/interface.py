"""The narrow interface through which the API reads (and pokes) the running service.

``api/`` imports only this module from ``service/``. The running service (``service/shell/service.py``)
implements :class:`ChtcService`; the API tests serve it too (``service/sim/served.py``).

Contract for implementers:

- Every method is synchronous, thread-safe and cheap. ``chtc()``, ``chtc_map()``, ``condition()``,
  ``sensors()``, ``health()``, ``ready()`` and ``metrics()`` are called on every poll (10 Hz per client is
  expected): return prebuilt, immutable snapshots, never do I/O or numerical work in them.
  ``list_identifications()`` and ``get_identification()`` may read the database (the API calls them from a
  worker thread). ``field()`` may solve a steady state once per identification but should cache the result.
- Units: temperatures °C, H in W/(m²·K), lengths m, speed rpm, torque N·m, durations s. Every ``datetime`` is
  timezone-aware UTC.
- Snapshots are frozen; arrays inside them must not be mutated after construction (build new snapshots).
- Failures are typed (never ``None`` for "failed"); ``ServiceError`` is the root of the service's whole tree
  (``service.errors``), these are the ones the API maps to HTTP codes (``api/errors.py``; any other
  ``ServiceError`` is a 500)::

      ServiceError (service.errors)
      ├── NotFoundError(ServiceError, LookupError)        unknown identification id / job id      -> 404
      ├── NoDataYetError(ServiceError)                    nothing to show yet (no field, no data)  -> 503
      ├── BusyError(ServiceError)                         an identification is already running    -> 409
      └── NotReadyError(ServiceError)                     model not loaded / not enough good data -> 503

  ``chtc()`` returns ``None`` only with its documented meaning: no identification has finished yet;
  ``chtc_map()`` returns ``None`` in per-condition mode or before the first map fit.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from service.contracts.records import IdentificationData
from service.contracts.sensorfault import SensorFault
from service.errors import ServiceError
from service.estimate.locator import TriangleLocator, locator_for
from service.estimate.mechanics import MechanicsCalibration
from service.estimate.probe import ProbeError as ProbeError
from service.estimate.probe import ProbeMeasurement
from service.estimate.reference import CompensationReference
from service.identify.mode import IdentificationMode

# the policy's vocabulary, re-exported for api/ (which imports only this module of service/)
from service.serve.verdict import ACTIONS as ACTIONS
from service.serve.verdict import ChtcStatus as ChtcStatus
from service.serve.verdict import DataCode as DataCode
from service.serve.verdict import DataProblem as DataProblem
from service.serve.verdict import Reason as Reason
from service.serve.verdict import Verdict as Verdict

if TYPE_CHECKING:
    from service.estimate.growth import GrowthEstimate, PlcCompensation

H_UNIT = "W/(m²·K)"
FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
ZONE_NAMES: tuple[str, ...] = ("H1", "H2", "H3", "H4", "H5", "H6", "H7")


class NotFoundError(ServiceError, LookupError):
    """An identification or job id that does not exist."""


class NoDataYetError(ServiceError):
    """Nothing to show yet (no field before the first identification, no samples)."""


class BusyError(ServiceError):
    """An identification is already queued or running."""


class NotReadyError(ServiceError):
    """The service cannot do what was asked yet (model not loaded, too little good data)."""


class ConditionState(enum.StrEnum):
    STABLE = "stable"
    CHANGING = "changing"


@dataclass(frozen=True, kw_only=True)
class ConditionSnapshot:
    """One operating condition as seen by the change detector."""

    id: int
    speed_rpm: float
    torque_nm: float
    ambient_c: float
    since: datetime  # UTC start of this condition
    state: ConditionState


FieldAt = Literal["now", "steady"]


@dataclass(frozen=True, eq=False)
class FieldSnapshot:
    """A temperature field on the axisymmetric (r, z) section of the P1 mesh."""

    t: datetime  # UTC instant the field belongs to (for "steady": when it was computed)
    at: FieldAt
    nodes_rz: np.ndarray  # (N, 2) m
    triangles: np.ndarray  # (M, 3) node indices
    temps_c: np.ndarray  # (N,) °C
    identification_id: int | None = None
    # (N,) °C 1σ of temps_c: the filtered live state's uncertainty ("now"); None for "steady" (a model output)
    std_c: np.ndarray | None = None

    @property
    def bounds_rz(self) -> tuple[float, float, float, float]:
        """(r_min, r_max, z_min, z_max) of the mesh, m."""
        lo = self.nodes_rz.min(axis=0)
        hi = self.nodes_rz.max(axis=0)
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    @property
    def locator(self) -> TriangleLocator:
        """The mesh's point locator, shared by every snapshot on the same mesh arrays (built once)."""
        return locator_for(self.nodes_rz, self.triangles)

    def evaluate(self, points_rz: np.ndarray) -> np.ndarray:
        """Temperatures (°C) at (P, 2) points (r, z) in m, by P1 interpolation; NaN outside the section."""
        pts = np.asarray(points_rz, dtype=float).reshape(-1, 2)
        return self.locator.interpolate(self.temps_c, self.locator.locate(pts))

    def evaluate_std(self, points_rz: np.ndarray) -> np.ndarray | None:
        """1σ (°C) at (P, 2) points by P1 interpolation of the nodal 1σ (an upper bound of the interpolated
        temperature's 1σ: σ of a convex combination ≤ the combination of the σ); None without ``std_c``."""
        if self.std_c is None:
            return None
        pts = np.asarray(points_rz, dtype=float).reshape(-1, 2)
        return self.locator.interpolate(self.std_c, self.locator.locate(pts))


@dataclass(frozen=True)
class SensorReading:
    """One channel at the newest sample, with the model's prediction for it."""

    channel: int  # 1..32
    name: str
    role: str  # "bearing" | "housing"
    r_m: float
    z_m: float
    measured_c: float | None  # None when the channel has no usable value (see quality)
    predicted_c: (
        float | None
    )  # the filtered live state at the sensor, offset-corrected; None before it started
    residual_c: float | None  # measured - offset - predicted
    quality: str  # drivers.quality.Quality value: "ok", "stale", "open_circuit", ...
    t: datetime  # UTC of the sample
    offset_c: float | None = None  # zeroed sensor offset (subtracted before the fit); None: no baseline
    offset_sd_c: float | None = None  # 1σ of the offset still unknown, carried in the CIs
    offset_calibrated_at: datetime | None = None  # UTC end of the baseline (service.acquire.calibration)
    offset_source: str | None = None  # how the baseline was taken: "auto" | "manual"; None: no baseline
    predicted_sd_c: float | None = None  # 1σ of predicted_c (the filtered state's and the model's error)


@dataclass(frozen=True, kw_only=True)
class OffsetBaseline:
    """A sensor-offset baseline taken at thermal equilibrium (``service.acquire.calibration``): the window
    [t_from, t_to] (UTC), "auto" or "manual", and per channel the offset and its 1σ (°C; None: no data)."""

    t_from: datetime
    t_to: datetime
    source: str
    samples: int
    offsets_c: tuple[float | None, ...]
    sd_c: tuple[float, ...]


@dataclass(frozen=True, eq=False, kw_only=True)
class IdentificationRecord:
    """One finished (or failed, skipped, cancelled) identification as served: the stored ``data``, the
    condition it was taken at, and its per-zone values as read-only (7,) arrays.

    Built by ``service.serve.views.data_to_record`` only. Every other value is the stored record's, read
    through ``data`` (the properties below name the ones the service and the API use).
    """

    data: IdentificationData
    condition: ConditionSnapshot
    h: FloatArray  # (7,) W/(m²·K); NaN when not identified (failed, skipped)
    ci95_lo: FloatArray  # (7,) W/(m²·K), >= 0
    ci95_hi: FloatArray
    identified: BoolArray  # (7,) 95 % CI narrow enough and not at a bound
    at_bound: BoolArray  # (7,) H on a bound of the search box (then not identified)
    # (7,) H the data could not see: value and band are the prior's (a MAP fit; never identified)
    prior_dominated: BoolArray = field(default_factory=lambda: np.zeros(len(ZONE_NAMES), dtype=bool))

    @property
    def id(self) -> int:
        return self.data.id

    @property
    def started_at(self) -> datetime:
        return self.data.started_at

    @property
    def finished_at(self) -> datetime:
        return self.data.finished_at

    @property
    def reason(self) -> str:
        """Trigger: "condition-change" | "scheduled" | "manual" | ..."""
        return self.data.reason

    @property
    def outcome(self) -> str:
        """A ``service.contracts.outcome.Outcome`` value: "ok", "failed", "insufficient-data", ..."""
        return self.data.outcome

    @property
    def message(self) -> str:
        return self.data.message

    @property
    def window_from(self) -> datetime:
        return self.data.window_start

    @property
    def window_to(self) -> datetime:
        return self.data.window_end

    @property
    def f(self) -> float | None:
        """Objective: mean squared residual, °C²."""
        return self.data.f

    @property
    def fit(self) -> float | None:
        """1 / (1 + f)."""
        return self.data.fit

    @property
    def rmse_c(self) -> float | None:
        return self.data.rmse_c

    @property
    def method(self) -> str:
        return self.data.method

    @property
    def model_version(self) -> str:
        return self.data.model_version

    @property
    def nfev(self) -> int:
        return self.data.nfev

    @property
    def wall_s(self) -> float:
        return self.data.duration_s

    @property
    def n_sensors_used(self) -> int:
        """Channels the fit used (masked-out ones excluded)."""
        return self.data.n_sensors_used


class Judged:
    """A snapshot carrying the served-value policy's ``verdict`` (``service.serve.policy``), read through
    these properties: its status, the usable flag a consumer acts on, and the reason for humans."""

    verdict: Verdict

    @property
    def status(self) -> ChtcStatus:
        return self.verdict.status

    @property
    def usable_for_compensation(self) -> bool:
        """The flag a consumer acts on (the policy's verdict)."""
        return self.verdict.usable

    @property
    def reason(self) -> str | None:
        """Why not usable, for humans ("code: detail"; ``verdict.reason`` is the typed code)."""
        return self.verdict.text


@dataclass(frozen=True, eq=False, kw_only=True)
class ChtcSnapshot(Judged):
    """The current H1-H7 (the identification ``record``) and whether a controller may use them now.

    Built by ``service.serve.views.chtc_snapshot`` only; the record's values are read through it.
    """

    record: IdentificationRecord  # the identification served: H, CIs, fit, provenance
    newest_sample_at: datetime | None  # UTC of the newest sample in the ring buffer
    identified: BoolArray  # (7,) the record's flag and not at a bound of the search box
    at_bound: BoolArray  # (7,) H on a bound of the search box (not identified)
    verdict: Verdict  # the policy's (service.serve.policy.chtc_verdict): status, usable, reason
    unit: str = H_UNIT
    zones: tuple[str, ...] = ZONE_NAMES
    box: tuple[float, float] | None = None  # the search box of H, W/(m²·K) (bounds beyond it print "> box")
    # channels the live state leaves out as stuck or drifting (service.estimate.sensorfaults), by channel
    sensor_faults: tuple[SensorFault, ...] = ()

    @property
    def h(self) -> FloatArray:
        """(7,) W/(m²·K)."""
        return self.record.h

    @property
    def prior_dominated(self) -> BoolArray:
        """(7,) H the data did not see: the prior's value and band (a MAP fit; never identified)."""
        return self.record.prior_dominated

    @property
    def ci95_lo(self) -> FloatArray:
        return self.record.ci95_lo

    @property
    def ci95_hi(self) -> FloatArray:
        return self.record.ci95_hi

    @property
    def identified_at(self) -> datetime:
        """UTC end of the identification."""
        return self.record.finished_at

    @property
    def condition(self) -> ConditionSnapshot:
        """The condition the window was taken at."""
        return self.record.condition

    @property
    def identification_id(self) -> int:
        return self.record.id

    @property
    def f(self) -> float | None:
        """Objective: mean squared residual, °C²."""
        return self.record.f

    @property
    def fit(self) -> float | None:
        return self.record.fit

    @property
    def rmse_c(self) -> float | None:
        return self.record.rmse_c

    @property
    def method(self) -> str:
        return self.record.method

    @property
    def model_version(self) -> str:
        return self.record.model_version


@dataclass(frozen=True, eq=False, kw_only=True)
class ChtcMapSnapshot(Judged):
    """The identified H map H = F(n, Ti) over the speed range (``identification.mode = "speed_map"``,
    docs/design/hmap.md): H1-H7 and their 95 % bands on a speed grid at the current ambient, the speeds the
    data have covered, and how current the map is.

    Built by ``service.serve.views.chtc_map_snapshot`` only. Arrays are read-only; speeds in rpm, H in
    W/(m²·K), durations in s, times UTC. Between and beyond the visited speeds the map is the prior's
    interpolation (its band says so: wide there).
    """

    fitted_at: datetime  # UTC end of the window of the fit the map comes from
    identification_id: int | None  # the stored identification of that fit (None: not stored)
    family: str  # "nodes" (ln H at speed nodes, the default) | "physics" (model.hmap)
    ambient_c: float  # the ambient the grid is evaluated at (the newest sample's; 20 °C before any)
    speeds_rpm: FloatArray  # (k,) grid, 0..7000 rpm
    h_w_m2k: FloatArray  # (k, 7)
    ci95_lo_w_m2k: FloatArray  # (k, 7), > 0
    ci95_hi_w_m2k: FloatArray  # (k, 7)
    identified: BoolArray  # (k, 7) 95 % band narrower than identification.ci_rel_threshold
    visited_rpm: FloatArray  # (m,) speeds the data covered (binned), ascending
    visited_s: FloatArray  # (m,) seconds of data at each visited speed (decayed like the map's information)
    verdict: Verdict  # how current the map is at the current speed (service.serve.policy.map_verdict)
    newest_sample_at: datetime | None  # UTC of the newest sample
    current_speed_rpm: float | None = None  # the newest sample's speed (None before any)
    visited_margin_rpm: float = 0.0  # a speed within this of a visited one counts as covered
    rmse_c: float | None = None  # the fit's RMS residual, °C
    restored: bool = False  # the stored map, not re-fitted since the restart
    unit: str = H_UNIT
    zones: tuple[str, ...] = ZONE_NAMES


@dataclass(frozen=True, kw_only=True)
class IdentificationPage:
    items: Sequence[IdentificationRecord]  # newest first
    total: int  # matching the filter, over all pages
    limit: int
    offset: int
    partial_reason: str | None = None  # set when the database could not be read: only records in memory


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


@dataclass(frozen=True, kw_only=True)
class IdentificationJob:
    job_id: str
    reason: str
    state: JobState
    requested_at: datetime
    finished_at: datetime | None = None
    identification_id: int | None = None  # set when state is DONE (or FAILED with a stored record)
    message: str = ""


class DeviceStatus(enum.StrEnum):
    OK = "ok"
    DEGRADED = "degraded"  # reachable, but faults/bad channels/retries
    DOWN = "down"
    DISABLED = "disabled"


@dataclass(frozen=True, kw_only=True)
class DeviceHealth:
    name: str  # "modbus" | "can" | "db" | "worker" | "filter"
    status: DeviceStatus
    last_ok_at: datetime | None  # UTC of the last good read/frame/write
    age_s: float | None  # seconds since last_ok_at, at the time of health()
    counters: Mapping[str, int] = field(default_factory=dict)  # e.g. {"polls": 10, "timeouts": 1}
    message: str = ""


@dataclass(frozen=True, kw_only=True)
class HealthSnapshot:
    t: datetime
    devices: Sequence[DeviceHealth]
    model_loaded: bool
    model_version: str | None
    uptime_s: float


@dataclass(frozen=True)
class Readiness:
    ready: bool  # model loaded and data fresh
    reasons: Sequence[str] = ()  # why not, e.g. ("model not loaded", "no sample for 35 s")


@dataclass(frozen=True, kw_only=True)
class HistogramData:
    """A cumulative histogram as Prometheus wants it: counts[i] = observations <= upper_bounds[i]."""

    upper_bounds: tuple[float, ...]  # ascending, without +Inf
    counts: tuple[int, ...]  # cumulative, same length as upper_bounds
    count: int  # total (the +Inf bucket)
    sum: float


@dataclass(frozen=True, kw_only=True)
class FilterMetrics:
    """The live state's Kalman filter (docs/design/estimator.md): the last sample's normalised innovation
    squared ``nis`` over ``dof`` used channels (E[nis] = dof under a consistent filter), the NIS window's Σ
    NIS / Σ dof (``window_ratio``, ≈ 1 when consistent), its verdict ("filling", "ok", "high", "low"), whether
    the state has ``converged`` since the (re)start and whether the NIS has been above its band long enough to
    be reported (``inconsistent``)."""

    nis: float
    dof: int
    window_ratio: float | None
    verdict: str
    converged: bool
    inconsistent: bool


@dataclass(frozen=True, kw_only=True)
class CoreMetrics:
    """The core thread: ``wait_s`` each event's wait in its queue [s]; ``queued`` events now; ``lag_s`` how
    long the oldest waiting sample has waited [s]; ``dropped`` samples (queue full) and ``handled`` events."""

    wait_s: HistogramData
    queued: int
    lag_s: float
    dropped: int
    handled: int


@dataclass(frozen=True, kw_only=True)
class OutletMetrics:
    """An outlet's delivery counters since start (``chtc_outlet_*``): messages ``sent``, ``dropped`` (its
    buffer full), ``buffered`` now, ``reconnects`` (connections after the first), ``connect_failures``
    (refused tries), ``connected`` now (None: an outlet without a connection of its own, a server) and the
    requests a server ``refused``, by reason (OPC UA: ``Write``, ``Call``, ``BadTooManySessions``, ...)."""

    sent: int = 0
    dropped: int = 0
    buffered: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    connected: bool | None = None
    refused: Mapping[str, int] = field(default_factory=dict)


@runtime_checkable
class CountedOutlet(Protocol):
    """An outlet (``service.serve.outlet.Outlet``) that counts its deliveries for ``/metrics``."""

    name: str

    def outlet_metrics(self) -> OutletMetrics: ...


@dataclass(frozen=True, kw_only=True)
class MetricsSnapshot:
    """Numbers the service exposes; the API turns them into Prometheus metrics (``chtc_*``)."""

    modbus_poll_latency_s: HistogramData  # successful polls' round trips (the driver's own timing)
    # outcomes (every poll / frame has exactly one); events are counted separately below
    modbus_polls_total: Mapping[str, int]  # "ok", "device_timeout", "short_reply", "link_down", ...
    can_frames_total: Mapping[str, int]  # "ok", "unknown_frame_id", "wrong_dlc", ...
    channel_age_s: Sequence[float | None]  # 32; seconds since the channel's last good value, None = never
    channel_quality: Sequence[str]  # 32; current Quality value per channel
    identifications_total: Mapping[str, int]  # by outcome: "ok", "failed", "insufficient-data"
    identification_duration_s: HistogramData
    last_fit: float | None
    last_rmse_c: float | None
    db_pending_rows: int = 0
    db_errors_total: int = 0
    db_write_s: HistogramData | None = None  # each batch's write and commit (None: no database writer)
    reconnects_total: Mapping[str, int] = field(default_factory=dict)  # by device
    modbus_events_total: Mapping[str, int] = field(default_factory=dict)  # "new_samples", "restarts", ...
    can_events_total: Mapping[str, int] = field(default_factory=dict)  # "counter_gaps", "faults", silence...
    chtc: ChtcSnapshot | None = None  # the current H, CIs, status, usable_for_compensation (None: none yet)
    build_version: str = ""  # package version (chtc_build_info)
    model_version: str | None = None
    filter: FilterMetrics | None = None  # None before the live state started
    # docs/design/threading.md: the event loop's lag (None: not measured), its largest of the last window [s];
    # the core thread (None: the core runs inline): how long events waited for it, its backlog now
    loop_lag_s: HistogramData | None = None
    loop_lag_recent_max_s: float | None = None
    core: CoreMetrics | None = None
    growth_terms_computed: int = 0  # /compensation's condition terms computed (cache misses) and their CPU
    growth_terms_cpu_s: float = 0.0
    outlets: Mapping[str, OutletMetrics] = field(default_factory=dict)  # by outlet name (those counting)


@dataclass(frozen=True, eq=False, kw_only=True)
class CompensationSnapshot(Judged):
    """What ``/compensation`` serves (docs/design/growth.md): the thermal growth at the spindle nose from the
    live field (``growth``: µm, 0.1-µm integers, 95 % CIs, forecast, sensor sensitivity; frozen) with the
    policy's verdict on it at the same instant (``service.serve.policy.compensation_verdict``: judged on the
    growth itself, not on the H), and the controller values of the axial growth (``plc``, for a tool pointing
    along ``tool_dir`` of the machine axis)."""

    growth: GrowthEstimate
    verdict: Verdict  # the policy's (service.serve.policy.compensation_verdict): status, usable, reason
    newest_sample_at: datetime | None
    identification_id: int | None  # the identification whose H the growth uses (None: none yet, H guessed)
    plc: PlcCompensation
    tool_dir: int  # -1: the tool points to -Z
    channels: tuple[int, ...]  # sensor channel numbers of the sensitivity entries
    reference: CompensationReference | None = None  # the zero in use (None: none set, not usable)
    mechanics: MechanicsCalibration | None = None  # the commissioned mechanics (None: the description's)
    # channels the live state leaves out as stuck or drifting (service.estimate.sensorfaults), by channel:
    # the growth's CI carries what they bent before they were found
    sensor_faults: tuple[SensorFault, ...] = ()

    @property
    def reference_at(self) -> datetime | None:
        """When the compensation reference was set; None: none set (the growth is provisional)."""
        return None if self.reference is None else self.reference.at


@dataclass(frozen=True, eq=False, kw_only=True)
class SectionSnapshot:
    """What ``/compensation/section`` serves (docs/design/growth.md, "The deformed section"): the outline of
    the spindle's axisymmetric section (``nodes_rz`` (M, 2) [m], ``edges`` (E, 2) node indices: every region's
    boundary) and its displacement ``u_um`` (2, M) [µm] (u_r, u_z) by the live field over the reference
    ``t_ref_c``, at ``at`` (UTC, the live field's instant), with the status of ``/compensation``."""

    at: datetime
    t_ref_c: float
    nodes_rz: FloatArray
    edges: npt.NDArray[np.int64]
    u_um: FloatArray
    status: ChtcStatus
    identification_id: int | None
    newest_sample_at: datetime | None


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


@dataclass(frozen=True, eq=False, kw_only=True)
class SensorHistory:
    """Per-sample measured and predicted temperatures, oldest first (measured vs predicted over time)."""

    t: tuple[datetime, ...]  # (n,) UTC sample times
    measured_c: np.ndarray  # (n, C) °C; NaN where the channel had no usable value (quality not "ok")
    predicted_c: np.ndarray  # (n, C) °C; NaN before the first identification
    channels: tuple[int, ...]  # (C,) channel numbers of the columns
    names: tuple[str, ...]  # (C,) sensor names (the spindle description's)
    roles: tuple[str, ...]  # (C,) "bearing" | "housing"
    capacity: int  # samples the buffer keeps; older ones are gone


class SensorHistoryBuffer:
    """A thread-safe ring of the last ``capacity`` samples (measured, predicted, °C) for ``sensor_history``.

    Kept in memory by the service, so it survives a dashboard reload but not a service restart.
    """

    def __init__(self, capacity: int, sensors: Sequence[tuple[int, str, str]]) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        self._lock = threading.Lock()
        self._channels = tuple(int(c) for c, _, _ in sensors)
        self._names = tuple(n for _, n, _ in sensors)
        self._roles = tuple(r for _, _, r in sensors)
        self._cap = int(capacity)
        self._t: list[datetime | None] = [None] * self._cap
        self._m = np.full((self._cap, len(self._channels)), np.nan)
        self._p = np.full((self._cap, len(self._channels)), np.nan)
        self._n = 0  # samples appended so far; slot of sample k is k % capacity

    def append(self, t: datetime, measured_c: np.ndarray, predicted_c: np.ndarray | None) -> None:
        """Add one sample; ``measured_c`` with NaN for unusable channels, ``predicted_c`` None if none yet."""
        with self._lock:
            i = self._n % self._cap
            self._t[i] = t
            self._m[i] = measured_c
            self._p[i] = np.nan if predicted_c is None else predicted_c
            self._n += 1

    def since(self, since: datetime | None) -> SensorHistory:
        """The kept samples later than ``since`` (UTC), oldest first."""
        with self._lock:
            n = min(self._n, self._cap)
            rows = [(self._n - n + k) % self._cap for k in range(n)]
            rows = [i for i in rows if since is None or _after(self._t[i], since)]
            ts = tuple(t for t in (self._t[i] for i in rows) if t is not None)
            m, p = self._m[rows], self._p[rows]  # fancy indexing copies
        return SensorHistory(
            t=ts,
            measured_c=m,
            predicted_c=p,
            channels=self._channels,
            names=self._names,
            roles=self._roles,
            capacity=self._cap,
        )


def _after(t: datetime | None, since: datetime) -> bool:
    return t is not None and t > since


@dataclass(frozen=True, kw_only=True)
class SectionPart:
    """A solid part of the (r, z) section: a rectangle in m (``[[regions]]`` of the spindle TOML)."""

    name: str  # e.g. "housing", "front_end_cap", "rear_bearing"
    material: str
    r0_m: float
    r1_m: float
    z0_m: float
    z1_m: float


@dataclass(frozen=True)
class ZoneInfo:
    name: str  # "H1" .. "H7"
    description: str  # e.g. "rear shaft pulley <-> ambient"


@dataclass(frozen=True, kw_only=True)
class SpindleLayout:
    name: str  # the spindle description's name
    parts: tuple[SectionPart, ...]
    zones: tuple[ZoneInfo, ...]
