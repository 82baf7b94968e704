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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Protocol

from service.contracts.calibration import Calibration
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.columns import Column, JsonValue, check_times, finite, finite_list, plain, plain_dict
from service.contracts.errors import RecordError
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.outcome import OUTCOMES
from service.contracts.probe import ProbeMeasurement
from service.contracts.reference import CompensationReference

if TYPE_CHECKING:
    from model.identify import IdentificationResult

N_ZONES = 7


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
        check_times(self)

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
        check_times(self)


@dataclass(frozen=True, kw_only=True)
class DeviceEventData:
    t: datetime
    device: str  # "modbus" | "can" | "db" | "worker" | ...
    kind: str  # "connected", "timeout", "unavailable", ...
    detail: str = ""

    def __post_init__(self) -> None:
        check_times(self)

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
        check_times(self)
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
        check_times(self)
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
        check_times(self)
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
            "test_points": plain(result.test_points),
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
            return None if self.diagnostics is None else plain_dict(self.diagnostics)
        return plain_dict({**(self.diagnostics or {}), "events": events})


Record = (
    ConditionStart
    | ConditionEnd
    | IdentificationData
    | DeviceEventData
    | SampleData
    | SampleMinuteData
    | Calibration
    | CompensationReference
    | LiveCheckpoint
    | MechanicsCalibration
    | ProbeMeasurement
)
RECORD_TYPES = (
    ConditionStart,
    ConditionEnd,
    IdentificationData,
    DeviceEventData,
    SampleData,
    SampleMinuteData,
    Calibration,
    CompensationReference,
    LiveCheckpoint,
    MechanicsCalibration,
    ProbeMeasurement,
)
