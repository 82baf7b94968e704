"""Plain, immutable records the service hands to the writer (or to ``repository.write_records``).

They carry no session state, so a batch that failed can be retried as is. Validation happens at
construction and raises ``RecordError`` naming the field (naive datetime, wrong length, unknown outcome).
Non-finite floats (NaN, ±inf) are stored as NULL. ``SampleData.from_sample`` and
``IdentificationData.from_result`` adapt a ``drivers`` ``Sample`` and a ``model.identify`` result.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime
from typing import Any

from service.store.errors import RecordError
from service.store.models import OUTCOMES

N_ZONES = 7


def finite(value: Any) -> float | None:
    """``float(value)``, or None for None/NaN/±inf (JSON and SQL have no NaN)."""
    if value is None:
        return None
    x = float(value)
    return x if math.isfinite(x) else None


def finite_list(values: Any) -> list[float | None]:
    return [finite(v) for v in values]


def _check_times(record: object) -> None:
    for f in fields(record):  # type: ignore[arg-type]
        value = getattr(record, f.name)
        if isinstance(value, datetime) and (value.tzinfo is None or value.utcoffset() is None):
            raise RecordError(
                f"{type(record).__name__}.{f.name}: naive datetime {value.isoformat()}; need UTC"
            )


def _check_len(record: object, name: str, value: Sequence[Any] | None, n: int) -> None:
    if value is not None and len(value) != n:
        raise RecordError(f"{type(record).__name__}.{name}: expected {n} values, got {len(value)}")


@dataclass(frozen=True)
class ConditionStart:
    """A new operating condition (id assigned by the service)."""

    id: int
    started_at: datetime
    speed_rpm: float
    torque_nm: float
    ambient_c: float

    def __post_init__(self) -> None:
        _check_times(self)

    def values(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class ConditionEnd:
    """Condition ``id`` ended at ``ended_at`` (the next one started)."""

    id: int
    ended_at: datetime

    def __post_init__(self) -> None:
        _check_times(self)


@dataclass(frozen=True)
class DeviceEventData:
    t: datetime
    device: str  # "modbus" | "can" | "db" | "worker" | ...
    kind: str  # "connected", "timeout", "unavailable", ...
    detail: str = ""

    def __post_init__(self) -> None:
        _check_times(self)

    def values(self) -> dict[str, Any]:
        return {"t": self.t, "device": self.device[:16], "kind": self.kind[:64], "detail": self.detail}


@dataclass(frozen=True)
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

    @classmethod
    def from_sample(cls, sample: Any) -> SampleData:
        """From a ``drivers`` ``Sample`` (t, temps_c, ambient_c, speed_rpm, torque_nm, quality, *_ok)."""
        quality = [str(getattr(q, "value", q)) for q in sample.quality]
        return cls(
            t=sample.t,
            temps_c=tuple(finite_list(sample.temps_c)),
            ambient_c=finite(sample.ambient_c),
            speed_rpm=finite(sample.speed_rpm),
            torque_nm=finite(sample.torque_nm),
            quality=tuple(quality),
            can_ok=bool(getattr(sample, "can_ok", True)),
            daq_ok=bool(getattr(sample, "daq_ok", True)),
        )

    def values(self) -> dict[str, Any]:
        bad = {str(i + 1): q for i, q in enumerate(self.quality) if q != "ok"}
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


@dataclass(frozen=True)
class IdentificationData:
    """One identification outcome (ids from the service). H, CIs in W/(m²·K); f in °C²; rmse in °C."""

    id: int
    condition_id: int
    started_at: datetime
    finished_at: datetime
    window_start: datetime
    window_end: datetime
    reason: str  # trigger: "schedule" | "manual" | ...
    outcome: str  # one of models.OUTCOMES
    method: str
    model_version: str
    h: Sequence[float | None] | None = None  # 7; None when nothing was identified
    ci95_lo: Sequence[float | None] | None = None
    ci95_hi: Sequence[float | None] | None = None
    identified: Sequence[bool] | None = None
    load_scale: Sequence[float] | None = None  # (front, rear)
    f: float | None = None
    fit: float | None = None
    rmse_c: float | None = None
    nfev: int = 0
    duration_s: float = 0.0
    n_sensors_used: int = 0
    warm_start_source: str | None = None
    warm_start_id: int | None = None
    message: str = ""
    diagnostics: Mapping[str, Any] | None = field(default=None)

    def __post_init__(self) -> None:
        _check_times(self)
        if self.outcome not in OUTCOMES:
            raise RecordError(f"IdentificationData.outcome: {self.outcome!r} is not one of {OUTCOMES}")
        for name in ("h", "ci95_lo", "ci95_hi", "identified"):
            _check_len(self, name, getattr(self, name), N_ZONES)
        _check_len(self, "load_scale", self.load_scale, 2)

    @classmethod
    def from_result(cls, result: Any, **meta: Any) -> IdentificationData:
        """From a ``model.identify.IdentificationResult``; ``meta`` gives ids, times, reason, model_version...

        ``outcome`` defaults to "ok"; ``rmse_c`` is √f, the RMSE over the entries the fit used (masked-out
        channels excluded); ``n_sensors_used`` counts the channels with a per-sensor RMSE (the identification
        gives NaN for a masked-out one, whatever value it showed, e.g. −327.68 °C open circuit).
        """
        ci = [[finite(v) for v in row] for row in result.h_ci95]
        per_sensor = [finite(v) for v in getattr(result, "rmse_per_sensor", ())]
        used = [v for v in per_sensor if v is not None]
        load = getattr(result, "load_scale", None)
        f = finite(result.f)
        at_bound = getattr(result, "at_bound", None)
        diagnostics = {
            "test_points": _plain(getattr(result, "test_points", None)),
            "rmse_per_sensor": per_sensor,
            "at_bound": None if at_bound is None else [bool(v) for v in at_bound],
        }
        values: dict[str, Any] = {
            "outcome": "ok",
            "method": str(result.method),
            "h": finite_list(result.h),
            "ci95_lo": [row[0] for row in ci],
            "ci95_hi": [row[1] for row in ci],
            "identified": [bool(v) for v in result.identified],
            "load_scale": None if load is None else [float(v) for v in load],
            "f": finite(result.f),
            "fit": finite(result.fit),
            "rmse_c": math.sqrt(f) if f is not None and f >= 0 else None,
            "nfev": int(result.nfev),
            "duration_s": float(result.wall_s),
            "n_sensors_used": len(used),
            "message": str(getattr(result, "message", "")),
            "diagnostics": diagnostics,
        }
        values.update(meta)
        return cls(**values)

    def values(self) -> dict[str, Any]:
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
            "diagnostics": None if self.diagnostics is None else _plain(self.diagnostics),
        }


class SampleDecimator:
    """Keep one sample per ``period_s`` (``database.sample_store_period_s``) of sample time, on a grid.

    The grid is ``k * period_s`` (epoch seconds); a sample belongs to the grid instant nearest to it
    (tolerance ``period_s / 2``), and ``keep(t)`` is True for the first sample of each grid slot after the
    last kept one. Jittered stamps (a 10 s acquisition arriving at 9.7 s, 10.4 s, ...) therefore keep
    every sample, where "at least ``period_s`` after the last kept one" dropped about a third of them. A
    sample in an earlier slot than the last kept one (the clock stepped back) restarts the grid there.
    """

    def __init__(self, period_s: float) -> None:
        if not period_s > 0:
            raise ValueError(f"database.sample_store_period_s must be > 0, got {period_s!r}")
        self.period_s = period_s
        self._last_slot: int | None = None

    def slot(self, t: datetime | float) -> int:
        """The grid slot of ``t`` (a UTC ``datetime`` or epoch seconds)."""
        ts = t.timestamp() if isinstance(t, datetime) else float(t)
        return math.floor(ts / self.period_s + 0.5)

    def keep(self, t: datetime | float) -> bool:
        k = self.slot(t)
        if self._last_slot is not None and k == self._last_slot:
            return False
        self._last_slot = k
        return True


@dataclass(frozen=True)
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

    def values(self) -> dict[str, Any]:
        return {
            "t_from": self.t_from,
            "t_to": self.t_to,
            "source": self.source,
            "samples": int(self.samples),
            "offsets_c": finite_list(self.offsets_c),
            "sd_c": finite_list(self.sd_c),
        }


CALIBRATION_SOURCES = ("auto", "manual")

Record = (
    ConditionStart | ConditionEnd | IdentificationData | DeviceEventData | SampleData | OffsetCalibrationData
)
RECORD_TYPES = (
    ConditionStart,
    ConditionEnd,
    IdentificationData,
    DeviceEventData,
    SampleData,
    OffsetCalibrationData,
)


def _plain(value: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None, keys to str."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, float):
        return finite(value)
    return value
