"""ORM rows → the frozen snapshots of ``service/serve/interface.py`` (what the API serves)."""

from __future__ import annotations

import numpy as np

from service.serve.interface import (
    ConditionSnapshot,
    ConditionState,
    IdentificationPage,
    IdentificationRecord,
)
from service.store.models import Condition, Identification
from service.store.repository import Page


def _array(values: object, n: int = 7) -> np.ndarray:
    if values is None:
        return np.full(n, np.nan)
    return np.array([np.nan if v is None else v for v in values], dtype=float)  # type: ignore[attr-defined]


def condition_snapshot(row: Condition) -> ConditionSnapshot:
    """A stored condition; ``state`` is STABLE (the detector's live state is not stored)."""
    return ConditionSnapshot(
        id=row.id,
        speed_rpm=row.speed_rpm,
        torque_nm=row.torque_nm,
        ambient_c=row.ambient_c,
        since=row.started_at,
        state=ConditionState.STABLE,
    )


def identification_record(row: Identification) -> IdentificationRecord:
    """A stored identification (its condition must be loaded: the repository's list/get functions do)."""
    identified = np.array(row.identified if row.identified is not None else [False] * 7, dtype=bool)
    return IdentificationRecord(
        id=row.id,
        started_at=row.started_at,
        finished_at=row.finished_at,
        reason=row.reason,
        outcome=row.outcome,
        message=row.message,
        condition=condition_snapshot(row.condition),
        window_from=row.window_start,
        window_to=row.window_end,
        h=_array(row.h),
        ci95_lo=_array(row.ci95_lo),
        ci95_hi=_array(row.ci95_hi),
        identified=identified,
        f=row.f,
        fit=row.fit,
        rmse_c=row.rmse_c,
        method=row.method,
        model_version=row.model_version,
        nfev=row.nfev,
        wall_s=row.duration_s,
        n_sensors_used=row.n_sensors_used,
    )


def identification_page(page: Page[Identification]) -> IdentificationPage:
    return IdentificationPage(
        items=[identification_record(r) for r in page.items],
        total=page.total,
        limit=page.limit,
        offset=page.offset,
    )
