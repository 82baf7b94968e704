"""Conversions between the service's records, the database rows and the API snapshots (pure functions).

One identification exists in three shapes: ``service.db.records.IdentificationData`` (what the writer
stores; built from ``model.identify.IdentificationResult`` by ``IdentificationData.from_result``), the ORM
row ``service.db.models.Identification`` (what comes back after a restart or from the history endpoints) and
``service.interface.IdentificationRecord`` (what the API serves). The functions here map the first two to
the third so that the live answer and the stored answer are the same numbers.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any

import numpy as np

from service.db.records import IdentificationData
from service.interface import ConditionSnapshot, ConditionState, IdentificationRecord

__all__ = ["condition_from_row", "data_to_record", "nan_array", "row_to_record"]

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
        ci95_lo=nan_array(data.ci95_lo),
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
    )


def condition_from_row(row: Any, *, state: ConditionState = ConditionState.STABLE) -> ConditionSnapshot:
    """The API view of a stored ``service.db.models.Condition`` row."""
    return ConditionSnapshot(
        id=int(row.id),
        speed_rpm=float(row.speed_rpm),
        torque_nm=float(row.torque_nm),
        ambient_c=float(row.ambient_c),
        since=row.started_at,
        state=state,
    )


def row_to_record(row: Any) -> IdentificationRecord:
    """The API view of a stored ``service.db.models.Identification`` row (its condition loaded)."""
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
        ci95_lo=nan_array(row.ci95_lo),
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
    )


def age_s(then: datetime | None, now: datetime) -> float | None:
    """Seconds from ``then`` to ``now`` (None for None)."""
    return None if then is None else max(0.0, (now - then).total_seconds())


def is_usable_h(h: np.ndarray) -> bool:
    return bool(len(h) == N_ZONES and all(math.isfinite(float(x)) and x > 0 for x in h))
