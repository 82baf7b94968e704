"""Plain, immutable records the service hands to the writer (or to ``repository.write_records``).

They carry no session state, so a batch that failed can be retried as is. Validation happens at
construction and raises ``RecordError`` naming the field (naive datetime, wrong length, unknown outcome).
Non-finite floats (NaN, ±inf) are stored as NULL. ``IdentificationData.from_result`` adapts a
``model.identify`` result and ``IdentificationData.from_row`` reads a stored row back (the inverse of
``values()``); ``service.serve.views`` maps an ``IdentificationData`` to what the API serves. This module
imports neither SQLAlchemy nor the model.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime
from typing import TYPE_CHECKING, Protocol, SupportsFloat, TypeVar

import numpy as np

from service.contracts.errors import RecordError
from service.contracts.outcome import OUTCOMES

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    from model.identify import IdentificationResult

N_ZONES = 7
K = TypeVar("K")

# What a JSON column holds (``diagnostics``): built by ``_plain`` from numpy values.
JsonValue = None | bool | int | float | str | list["JsonValue"] | dict[str, "JsonValue"]
ColumnScalar = datetime | int | float | str | bool | bytes | None
Column = ColumnScalar | list[float | None] | list[bool] | dict[str, JsonValue]


def finite(value: SupportsFloat | None) -> float | None:
    """``float(value)``, or None for None/NaN/±inf (JSON and SQL have no NaN)."""
    if value is None:
        return None
    x = float(value)
    return x if math.isfinite(x) else None


def finite_list(values: Iterable[SupportsFloat | None]) -> list[float | None]:
    return [finite(v) for v in values]


def _check_times(record: DataclassInstance) -> None:
    for f in fields(record):
        value = getattr(record, f.name)
        if isinstance(value, datetime) and (value.tzinfo is None or value.utcoffset() is None):
            raise RecordError(
                f"{type(record).__name__}.{f.name}: naive datetime {value.isoformat()}; need UTC"
            )


def _check_len(record: object, name: str, value: Sequence[object] | None, n: int) -> None:
    if value is not None and len(value) != n:
        raise RecordError(f"{type(record).__name__}.{name}: expected {n} values, got {len(value)}")


@dataclass(frozen=True, kw_only=True)
class ConditionStart:
    """A new operating condition (id assigned by the service)."""

    id: int
    started_at: datetime
    speed_rpm: float
    torque_nm: float
    ambient_c: float

    def __post_init__(self) -> None:
        _check_times(self)

    def values(self) -> dict[str, Column]:
        return {
            "id": self.id,
            "started_at": self.started_at,
            "speed_rpm": self.speed_rpm,
            "torque_nm": self.torque_nm,
            "ambient_c": self.ambient_c,
        }


@dataclass(frozen=True)
class ConditionEnd:
    """Condition ``id`` ended at ``ended_at`` (the next one started)."""

    id: int
    ended_at: datetime

    def __post_init__(self) -> None:
        _check_times(self)


@dataclass(frozen=True, kw_only=True)
class DeviceEventData:
    t: datetime
    device: str  # "modbus" | "can" | "db" | "worker" | ...
    kind: str  # "connected", "timeout", "unavailable", ...
    detail: str = ""

    def __post_init__(self) -> None:
        _check_times(self)

    def values(self) -> dict[str, Column]:
        return {"t": self.t, "device": self.device[:16], "kind": self.kind[:64], "detail": self.detail}


@dataclass(frozen=True, kw_only=True)
class SampleData:
    """One acquisition instant: temperatures °C per channel, ambient °C, speed rpm, torque N·m."""

    t: datetime
    temps_c: Sequence[float | None]
    ambient_c: float | None
    speed_rpm: float | None
    torque_nm: float | None
    quality: Sequence[str]  # per channel, drivers.quality.Quality values ("ok", "open_circuit", ...)
    can_ok: bool = True
    daq_ok: bool = True

    def __post_init__(self) -> None:
        _check_times(self)
        _check_len(self, "quality", self.quality, len(self.temps_c))

    def values(self) -> dict[str, Column]:
        bad: dict[str, JsonValue] = {str(i + 1): q for i, q in enumerate(self.quality) if q != "ok"}
        return {
            "t": self.t,
            "temps_c": finite_list(self.temps_c),
            "ambient_c": finite(self.ambient_c),
            "speed_rpm": finite(self.speed_rpm),
            "torque_nm": finite(self.torque_nm),
            "n_good": len(self.quality) - len(bad),
            "bad_channels": bad,
            "can_ok": bool(self.can_ok),
            "daq_ok": bool(self.daq_ok),
        }


@dataclass(frozen=True, kw_only=True)
class SampleMinuteData:
    """The means of the stored samples of one minute ``[t, t + 60 s)`` (``service.store.downsample``):
    °C per channel (a channel's mean over its non-null values; None: none), ambient °C, speed rpm (mean and
    max), torque N·m; ``n`` samples; the fewest good channels; whether CAN and the DAQ were ok throughout."""

    t: datetime
    n: int
    temps_c: Sequence[float | None]
    ambient_c: float | None
    speed_rpm: float | None
    speed_max_rpm: float | None
    torque_nm: float | None
    n_good_min: int
    can_ok: bool
    daq_ok: bool

    def __post_init__(self) -> None:
        _check_times(self)
        if self.n < 1:
            raise RecordError(f"SampleMinuteData.n: need >= 1, got {self.n}")

    def values(self) -> dict[str, Column]:
        return {
            "t": self.t,
            "n": int(self.n),
            "temps_c": finite_list(self.temps_c),
            "ambient_c": finite(self.ambient_c),
            "speed_rpm": finite(self.speed_rpm),
            "speed_max_rpm": finite(self.speed_max_rpm),
            "torque_nm": finite(self.torque_nm),
            "n_good_min": int(self.n_good_min),
            "can_ok": bool(self.can_ok),
            "daq_ok": bool(self.daq_ok),
        }


class IdentificationRow(Protocol):
    """The columns of a stored identification (``service.store.models.Identification``) that are read back."""

    id: int
    condition_id: int
    started_at: datetime
    finished_at: datetime
    window_start: datetime
    window_end: datetime
    reason: str
    outcome: str
    message: str
    method: str
    model_version: str
    ci95_lo: list[float | None] | None
    ci95_hi: list[float | None] | None
    identified: list[bool] | None
    load_scale_front: float | None
    load_scale_rear: float | None
    f: float | None
    fit: float | None
    rmse_c: float | None
    nfev: int
    duration_s: float
    n_sensors_used: int
    warm_start_source: str | None
    warm_start_id: int | None
    diagnostics: dict[str, JsonValue] | None

    @property
    def h(self) -> tuple[float | None, ...]: ...


@dataclass(frozen=True, kw_only=True)
class IdentificationData:
    """One identification outcome (ids from the service). H, CIs in W/(m²·K); f in °C²; rmse in °C.

    What is stored and, with its condition, what is served (``service.serve.views.data_to_record``): a value
    that should reach ``/chtc`` and ``/identifications`` is a field here, set in ``from_result``.
    """

    id: int
    condition_id: int
    started_at: datetime
    finished_at: datetime
    window_start: datetime
    window_end: datetime
    reason: str  # trigger: "condition-change" | "scheduled" | "manual" | ...
    outcome: str  # a service.contracts.outcome.Outcome value
    method: str
    model_version: str
    h: Sequence[float | None] | None = None  # 7; None when nothing was identified
    ci95_lo: Sequence[float | None] | None = None
    ci95_hi: Sequence[float | None] | None = None
    identified: Sequence[bool] | None = None
    load_scale: Sequence[float | None] | None = None  # (front, rear)
    f: float | None = None
    fit: float | None = None
    rmse_c: float | None = None
    nfev: int = 0
    duration_s: float = 0.0
    n_sensors_used: int = 0
    warm_start_source: str | None = None
    warm_start_id: int | None = None
    message: str = ""
    # test_points, rmse_per_sensor, at_bound: JSON, so a new diagnostic needs no column
    diagnostics: Mapping[str, JsonValue] | None = field(default=None)
    # ids of the service core's events that started and ended the job (service.core.events), stored in
    # the diagnostics as {"events": {"started_by": ..., "finished_by": ...}}: a story to follow when debugging
    started_by_event: str | None = None
    finished_by_event: str | None = None

    def __post_init__(self) -> None:
        _check_times(self)
        if self.outcome not in OUTCOMES:
            raise RecordError(f"IdentificationData.outcome: {self.outcome!r} is not one of {OUTCOMES}")
        for name, value in (
            ("h", self.h),
            ("ci95_lo", self.ci95_lo),
            ("ci95_hi", self.ci95_hi),
            ("identified", self.identified),
        ):
            _check_len(self, name, value, N_ZONES)
        _check_len(self, "load_scale", self.load_scale, 2)

    @classmethod
    def from_result(
        cls,
        result: IdentificationResult,
        *,
        id: int,
        condition_id: int,
        started_at: datetime,
        finished_at: datetime,
        window_start: datetime,
        window_end: datetime,
        reason: str,
        model_version: str,
        warm_start_source: str | None = None,
        warm_start_id: int | None = None,
        started_by_event: str | None = None,
        finished_by_event: str | None = None,
    ) -> IdentificationData:
        """A successful identification from its ``model.identify.IdentificationResult`` and the job's ids,
        times and provenance.

        ``rmse_c`` is √f, the RMSE over the entries the fit used (masked-out channels excluded);
        ``n_sensors_used`` counts the channels with a per-sensor RMSE (the identification gives NaN for a
        masked-out one, whatever value it showed, e.g. −327.68 °C open circuit).
        """
        ci = [[finite(v) for v in row] for row in result.h_ci95]
        per_sensor = finite_list(result.rmse_per_sensor)
        f = finite(result.f)
        diagnostics: dict[str, JsonValue] = {
            "test_points": _plain(result.test_points),
            "rmse_per_sensor": list(per_sensor),
            "at_bound": [bool(v) for v in result.at_bound],
            # a MAP fit (served modes): H the data did not see, kept at the prior (never identified)
            "prior_dominated": [bool(v) for v in result.prior_dominated],
        }
        if result.prior_source is not None:
            diagnostics["prior"] = str(result.prior_source)
        return cls(
            id=id,
            condition_id=condition_id,
            started_at=started_at,
            finished_at=finished_at,
            window_start=window_start,
            window_end=window_end,
            reason=reason,
            outcome="ok",
            method=str(result.method),
            model_version=model_version,
            h=finite_list(result.h),
            ci95_lo=[row[0] for row in ci],
            ci95_hi=[row[1] for row in ci],
            identified=[bool(v) for v in result.identified],
            load_scale=None if result.load_scale is None else [float(v) for v in result.load_scale],
            f=f,
            fit=finite(result.fit),
            rmse_c=math.sqrt(f) if f is not None and f >= 0 else None,
            nfev=int(result.nfev),
            duration_s=float(result.wall_s),
            n_sensors_used=sum(v is not None for v in per_sensor),
            warm_start_source=warm_start_source,
            warm_start_id=warm_start_id,
            message=str(result.message),
            diagnostics=diagnostics,
            started_by_event=started_by_event,
            finished_by_event=finished_by_event,
        )

    @classmethod
    def from_row(cls, row: IdentificationRow) -> IdentificationData:
        """A stored identification read back: the inverse of ``values()`` (NULL stays None)."""
        scales = (row.load_scale_front, row.load_scale_rear)
        return cls(
            id=int(row.id),
            condition_id=int(row.condition_id),
            started_at=row.started_at,
            finished_at=row.finished_at,
            window_start=row.window_start,
            window_end=row.window_end,
            reason=row.reason,
            outcome=row.outcome,
            method=row.method,
            model_version=row.model_version,
            h=None if all(v is None for v in row.h) else list(row.h),
            ci95_lo=row.ci95_lo,
            ci95_hi=row.ci95_hi,
            identified=row.identified,
            load_scale=None if all(v is None for v in scales) else list(scales),
            f=row.f,
            fit=row.fit,
            rmse_c=row.rmse_c,
            nfev=int(row.nfev or 0),
            duration_s=float(row.duration_s or 0.0),
            n_sensors_used=int(row.n_sensors_used or 0),
            warm_start_source=row.warm_start_source,
            warm_start_id=row.warm_start_id,
            message=row.message or "",
            diagnostics=row.diagnostics,
        )

    def values(self) -> dict[str, Column]:
        h = list(self.h) if self.h is not None else [None] * N_ZONES
        load = list(self.load_scale) if self.load_scale is not None else [None, None]
        return {
            "id": self.id,
            "condition_id": self.condition_id,
            "started_at": self.started_at,
            "finished_at": self.finished_at,
            "window_start": self.window_start,
            "window_end": self.window_end,
            "reason": self.reason[:32],
            "outcome": self.outcome,
            "message": self.message,
            "method": self.method[:32],
            "model_version": self.model_version[:128],
            **{f"h{i + 1}": finite(v) for i, v in enumerate(h)},
            "ci95_lo": None if self.ci95_lo is None else finite_list(self.ci95_lo),
            "ci95_hi": None if self.ci95_hi is None else finite_list(self.ci95_hi),
            "identified": None if self.identified is None else [bool(v) for v in self.identified],
            "load_scale_front": finite(load[0]),
            "load_scale_rear": finite(load[1]),
            "f": finite(self.f),
            "fit": finite(self.fit),
            "rmse_c": finite(self.rmse_c),
            "nfev": int(self.nfev),
            "duration_s": float(self.duration_s),
            "n_sensors_used": int(self.n_sensors_used),
            "warm_start_source": None if self.warm_start_source is None else self.warm_start_source[:64],
            "warm_start_id": self.warm_start_id,
            "diagnostics": self._stored_diagnostics(),
        }

    def _stored_diagnostics(self) -> dict[str, JsonValue] | None:
        events = {"started_by": self.started_by_event, "finished_by": self.finished_by_event}
        if all(v is None for v in events.values()):
            return None if self.diagnostics is None else _plain_dict(self.diagnostics)
        return _plain_dict({**(self.diagnostics or {}), "events": events})


@dataclass(frozen=True, kw_only=True)
class OffsetCalibrationData:
    """A sensor offset baseline (``service.acquire.calibration.Calibration``): offsets and their 1σ per
    channel [°C] (None: the channel had no data at rest, not corrected), the rest window [t_from, t_to]
    (UTC), the number of samples averaged and how it was taken ("auto" | "manual")."""

    t_from: datetime
    t_to: datetime
    source: str
    samples: int
    offsets_c: tuple[float | None, ...]
    sd_c: tuple[float | None, ...]

    def __post_init__(self) -> None:
        _check_times(self)
        _check_len(self, "sd_c", self.sd_c, len(self.offsets_c))
        if self.source not in CALIBRATION_SOURCES:
            raise RecordError(f"OffsetCalibrationData.source: {self.source!r} not in {CALIBRATION_SOURCES}")
        if self.samples < 1:
            raise RecordError(f"OffsetCalibrationData.samples: need >= 1, got {self.samples}")
        if self.t_to < self.t_from:
            raise RecordError("OffsetCalibrationData.t_to: before t_from")

    def values(self) -> dict[str, Column]:
        return {
            "t_from": self.t_from,
            "t_to": self.t_to,
            "source": self.source,
            "samples": int(self.samples),
            "offsets_c": finite_list(self.offsets_c),
            "sd_c": finite_list(self.sd_c),
        }


CALIBRATION_SOURCES = ("auto", "manual")


@dataclass(frozen=True, kw_only=True)
class CompensationReferenceData:
    """A compensation zero (``service.estimate.reference.CompensationReference``): the uniform temperature
    [°C] at which the growth is 0 and its 1σ [°C], when (UTC), how (``source``) and by whom (``set_by``)."""

    at: datetime
    temperature_c: float
    sd_c: float
    source: str
    set_by: str

    def __post_init__(self) -> None:
        _check_times(self)
        if not (math.isfinite(self.temperature_c) and math.isfinite(self.sd_c) and self.sd_c >= 0.0):
            raise RecordError("CompensationReferenceData: temperature_c and sd_c (>= 0) must be finite")

    def values(self) -> dict[str, Column]:
        return {
            "at": self.at,
            "temperature_c": float(self.temperature_c),
            "sd_c": float(self.sd_c),
            "source": self.source[:16],
            "set_by": self.set_by[:64],
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class LiveStateData:
    """The live state's checkpoint (``service.estimate.checkpoint.LiveCheckpoint``): its time ``at`` (UTC),
    the reduced model it belongs to, whether it had converged, the held inputs (ambient °C, speed rpm,
    torque N·m) and the arrays as an ``.npz`` ``payload``. The writer keeps only the newest row."""

    at: datetime
    model_version: str
    converged: bool
    ambient_c: float
    speed_rpm: float
    torque_nm: float
    payload: bytes

    def __post_init__(self) -> None:
        _check_times(self)
        if not all(math.isfinite(x) for x in (self.ambient_c, self.speed_rpm, self.torque_nm)):
            raise RecordError("LiveStateData: ambient_c, speed_rpm and torque_nm must be finite")
        if not self.payload:
            raise RecordError("LiveStateData.payload: empty")

    def values(self) -> dict[str, Column]:
        return {
            "at": self.at,
            "model_version": self.model_version[:64],
            "converged": bool(self.converged),
            "ambient_c": float(self.ambient_c),
            "speed_rpm": float(self.speed_rpm),
            "torque_nm": float(self.torque_nm),
            "payload": self.payload,
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class MechanicsCalibrationData:
    """A commissioning of the growth's mechanics (``service.estimate.mechanics.MechanicsCalibration``): when
    (UTC), how (``source``) and by whom, θ = (restraint, α shaft, α housing) and its covariance (3×3, row
    major), the fit's residual RMS and max [µm], its verdict, the SHA-256 of the test's files and its
    report."""

    at: datetime
    set_by: str
    source: str
    restraint: float
    alpha_shaft: float
    alpha_housing: float
    cov: list[list[float]]
    residual_rms_um: float
    residual_max_um: float
    explained: bool
    temperatures_sha256: str
    canlog_sha256: str | None
    displacements_sha256: str
    report: dict[str, JsonValue]

    def __post_init__(self) -> None:
        _check_times(self)
        vals = (self.restraint, self.alpha_shaft, self.alpha_housing, *(v for r in self.cov for v in r))
        if not all(math.isfinite(v) for v in vals) or len(self.cov) != 3:
            raise RecordError("MechanicsCalibrationData: θ and its 3×3 covariance must be finite")

    def values(self) -> dict[str, Column]:
        return {
            "at": self.at,
            "set_by": self.set_by[:64],
            "source": self.source[:16],
            "restraint": float(self.restraint),
            "alpha_shaft": float(self.alpha_shaft),
            "alpha_housing": float(self.alpha_housing),
            "cov": [finite(v) for r in self.cov for v in r],  # row major
            "residual_rms_um": finite(self.residual_rms_um),
            "residual_max_um": finite(self.residual_max_um),
            "explained": bool(self.explained),
            "temperatures_sha256": self.temperatures_sha256[:64],
            "canlog_sha256": None if self.canlog_sha256 is None else self.canlog_sha256[:64],
            "displacements_sha256": self.displacements_sha256[:64],
            "report": _plain_dict(self.report),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class ProbeMeasurementData:
    """A probe reading in service (``service.estimate.probe.ProbeMeasurement``): its instant (UTC), the axial
    reading and its 1σ [µm], the field's feature row (2×3, row major) [µm] and growth variance [µm²] then,
    the prediction, its 1σ and the innovation [µm], whether it was absorbed, who sent it."""

    at: datetime
    recorded_at: datetime
    axial_um: float
    sd_um: float
    features: list[list[float]]
    field_var_um2: float
    predicted_um: float
    sigma_um: float
    innovation_um: float
    accepted: bool
    set_by: str
    source: str

    def __post_init__(self) -> None:
        _check_times(self)
        vals = (
            self.axial_um,
            self.sd_um,
            self.field_var_um2,
            self.predicted_um,
            self.sigma_um,
            self.innovation_um,
        )
        flat = [v for r in self.features for v in r]
        if not all(math.isfinite(v) for v in (*vals, *flat)) or len(flat) != 6:
            raise RecordError("ProbeMeasurementData: finite values and a 2×3 feature row needed")

    def values(self) -> dict[str, Column]:
        return {
            "at": self.at,
            "recorded_at": self.recorded_at,
            "axial_um": float(self.axial_um),
            "sd_um": float(self.sd_um),
            "features": [finite(v) for r in self.features for v in r],  # row major
            "field_var_um2": float(self.field_var_um2),
            "predicted_um": float(self.predicted_um),
            "sigma_um": float(self.sigma_um),
            "innovation_um": float(self.innovation_um),
            "accepted": bool(self.accepted),
            "set_by": self.set_by[:64],
            "source": self.source[:16],
        }


Record = (
    ConditionStart
    | ConditionEnd
    | IdentificationData
    | DeviceEventData
    | SampleData
    | SampleMinuteData
    | OffsetCalibrationData
    | CompensationReferenceData
    | LiveStateData
    | MechanicsCalibrationData
    | ProbeMeasurementData
)
RECORD_TYPES = (
    ConditionStart,
    ConditionEnd,
    IdentificationData,
    DeviceEventData,
    SampleData,
    SampleMinuteData,
    OffsetCalibrationData,
    CompensationReferenceData,
    LiveStateData,
    MechanicsCalibrationData,
    ProbeMeasurementData,
)


def _plain(value: object) -> JsonValue:
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None, keys to str."""
    if isinstance(value, Mapping):
        return _plain_dict(value)
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, float):
        return finite(value)
    if value is None or isinstance(value, bool | int | str):
        return value
    raise RecordError(f"diagnostics: {type(value).__name__} is not JSON")


def _plain_dict(value: Mapping[K, object]) -> dict[str, JsonValue]:
    return {str(k): _plain(v) for k, v in value.items()}
