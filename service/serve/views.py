"""Conversions between the service's records, the database rows and the API snapshots (pure functions).

One identification exists in three shapes: ``service.store.records.IdentificationData`` (what the writer
stores; built from ``model.identify.IdentificationResult`` by ``IdentificationData.from_result``), the ORM
row ``service.store.models.Identification`` (what comes back after a restart or from the history endpoints)
and
``service.serve.interface.IdentificationRecord`` (what the API serves). The functions here map the first two
to
the third so that the live answer and the stored answer are the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from service.serve.interface import ZONE_NAMES, ConditionSnapshot, ConditionState, IdentificationRecord
from service.store.records import IdentificationData

__all__ = ["Usability", "condition_from_row", "data_to_record", "nan_array", "row_to_record", "usability"]

N_ZONES = 7


def nan_array(values: Any, n: int = N_ZONES) -> np.ndarray:
    """Float array of length ``n`` with None -> NaN (None itself -> all NaN)."""
    if values is None:
        return np.full(n, np.nan)
    out = np.array([np.nan if v is None else float(v) for v in values], dtype=float)
    out.setflags(write=False)
    return out


def _bool_array(values: Any) -> np.ndarray:
    out = np.zeros(N_ZONES, dtype=bool) if values is None else np.array([bool(v) for v in values], dtype=bool)
    out.setflags(write=False)
    return out


def data_to_record(data: IdentificationData, condition: ConditionSnapshot) -> IdentificationRecord:
    """The API view of an identification the service just finished (or skipped, or failed)."""
    return IdentificationRecord(
        id=data.id,
        started_at=data.started_at,
        finished_at=data.finished_at,
        reason=data.reason,
        outcome=data.outcome,
        message=data.message,
        condition=condition,
        window_from=data.window_start,
        window_to=data.window_end,
        h=nan_array(data.h),
        ci95_lo=_ci_lo(data.ci95_lo),
        ci95_hi=nan_array(data.ci95_hi),
        identified=_bool_array(data.identified),
        f=data.f,
        fit=data.fit,
        rmse_c=data.rmse_c,
        method=data.method,
        model_version=data.model_version,
        nfev=int(data.nfev),
        wall_s=float(data.duration_s),
        n_sensors_used=int(data.n_sensors_used),
        at_bound=_at_bound(data.diagnostics),
    )


def _ci_lo(values: Any) -> np.ndarray:
    """Lower CI bounds; a record stored before the CIs were computed in log H (docs/identification.md) may
    hold a negative one: H is positive, so it is served as 0."""
    lo = nan_array(values)
    with np.errstate(invalid="ignore"):
        out = np.where(lo < 0.0, 0.0, lo)
    out.setflags(write=False)
    return out


def _at_bound(diagnostics: Any) -> np.ndarray:
    """(7,) bool from the stored diagnostics (records before the flag existed: all False)."""
    values = diagnostics.get("at_bound") if isinstance(diagnostics, dict) else None
    return _bool_array(values if values is not None and len(values) == N_ZONES else None)


def condition_from_row(row: Any, *, state: ConditionState = ConditionState.STABLE) -> ConditionSnapshot:
    """The API view of a stored ``service.store.models.Condition`` row."""
    return ConditionSnapshot(
        id=int(row.id),
        speed_rpm=float(row.speed_rpm),
        torque_nm=float(row.torque_nm),
        ambient_c=float(row.ambient_c),
        since=row.started_at,
        state=state,
    )


def row_to_record(row: Any) -> IdentificationRecord:
    """The API view of a stored ``service.store.models.Identification`` row (its condition loaded)."""
    return IdentificationRecord(
        id=int(row.id),
        started_at=row.started_at,
        finished_at=row.finished_at,
        reason=row.reason,
        outcome=row.outcome,
        message=row.message or "",
        condition=condition_from_row(row.condition),
        window_from=row.window_start,
        window_to=row.window_end,
        h=nan_array(row.h),
        ci95_lo=_ci_lo(row.ci95_lo),
        ci95_hi=nan_array(row.ci95_hi),
        identified=_bool_array(row.identified),
        f=row.f,
        fit=row.fit,
        rmse_c=row.rmse_c,
        method=row.method,
        model_version=row.model_version,
        nfev=int(row.nfev or 0),
        wall_s=float(row.duration_s or 0.0),
        n_sensors_used=int(row.n_sensors_used or 0),
        at_bound=_at_bound(row.diagnostics),
    )


def age_s(then: datetime | None, now: datetime) -> float | None:
    """Seconds from ``then`` to ``now`` (None for None)."""
    return None if then is None else max(0.0, (now - then).total_seconds())


def is_usable_h(h: np.ndarray) -> bool:
    return bool(len(h) == N_ZONES and all(math.isfinite(float(x)) and x > 0 for x in h))


def at_bound(rec: IdentificationRecord, box: tuple[float, float] | None, rel_tol: float) -> np.ndarray:
    """(7,) bool: the record's own flag, or H within ``rel_tol`` × box width of a bound of ``box``."""
    flags = np.zeros(N_ZONES, dtype=bool) if rec.at_bound is None else np.asarray(rec.at_bound, dtype=bool)
    if box is not None:
        lo, hi = float(box[0]), float(box[1])
        tol = rel_tol * (hi - lo)
        with np.errstate(invalid="ignore"):
            flags = flags | (rec.h <= lo + tol) | (rec.h >= hi - tol)
    flags.setflags(write=False)
    return flags


@dataclass(frozen=True)
class Usability:
    usable: bool
    reason: str | None  # "code: detail" when not usable


def usability(
    rec: IdentificationRecord,
    *,
    bound: np.ndarray,
    condition: ConditionSnapshot | None,
    data_problems: tuple[str, ...],
    restored: bool,
) -> Usability:
    """Whether a compensation controller may apply ``rec``'s H now, else the first reason why not.

    Codes, in this order: ``stale`` (the data are not fresh: ``data_problems``), ``restored`` (the last stored
    H, not re-identified since the restart), ``condition_changed`` (identified at another condition, or the
    condition is changing), ``at_bound`` (an H on a bound of the search box), ``not_identified`` (an H's
    95 % CI wider than the threshold)."""
    if data_problems:
        return Usability(False, "stale: " + ", ".join(data_problems) + " (see /readyz)")
    if restored:
        return Usability(False, "restored: the last stored H, not re-identified since the restart")
    if condition is None or condition.id != rec.condition.id or condition.state is not ConditionState.STABLE:
        now = "none" if condition is None else f"{condition.id} ({condition.state.value})"
        return Usability(False, f"condition_changed: identified at condition {rec.condition.id}, now {now}")
    if bool(np.any(bound)):
        names = ", ".join(n for n, b in zip(ZONE_NAMES, bound, strict=True) if b)
        return Usability(False, f"at_bound: {names} on a bound of the search box (not identified)")
    weak = [n for n, ok in zip(ZONE_NAMES, rec.identified, strict=True) if not ok]
    if weak or not is_usable_h(rec.h):
        return Usability(False, f"not_identified: {', '.join(weak) or 'H'} (95 % CI too wide)")
    return Usability(True, None)
