"""The one mapping from an identification to what the API serves (pure functions).

An identification exists as ``service.contracts.records.IdentificationData``: built from the
``model.identify.IdentificationResult`` by ``IdentificationData.from_result``, stored as is (``values()``) and
read back after a restart or by the history endpoints (``IdentificationData.from_row``). ``data_to_record``
turns it, with the condition it was taken at, into the ``IdentificationRecord`` the API serves, and
``chtc_snapshot`` wraps the current record with what makes it trustworthy now (status, bounds, usability)::

    IdentificationResult --from_result--> IdentificationData --values()/from_row--> database row
                                                |
                                          data_to_record  (+ ConditionSnapshot)
                                                v
                            IdentificationRecord --chtc_snapshot--> ChtcSnapshot --api.schemas--> JSON

A value that should reach ``/chtc`` is a field of the result, set in the one mapper
``IdentificationData.from_result`` (stored in ``diagnostics`` it needs no column; a column needs a
migration), and a field of the schema (``api/schemas.py``), read as ``snapshot.record.data.<name>``: the
served record holds the stored one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Protocol

import numpy as np
import numpy.typing as npt

from model.defaults import BOUND_REL_TOL
from service.contracts.records import IdentificationData, IdentificationRow, JsonValue
from service.identify.speedmap import MAP_GRID_RPM, SpeedMap
from service.serve.interface import (
    ZONE_NAMES,
    ChtcMapSnapshot,
    ChtcSnapshot,
    ChtcStatus,
    ConditionSnapshot,
    ConditionState,
    IdentificationRecord,
)

__all__ = [
    "ConditionRow",
    "MapFreshness",
    "StoredIdentification",
    "Usability",
    "age_s",
    "at_bound",
    "chtc_map_snapshot",
    "chtc_snapshot",
    "condition_from_row",
    "data_to_record",
    "map_freshness",
    "map_record",
    "row_to_record",
    "usability",
]

N_ZONES = len(ZONE_NAMES)
BoolArray = npt.NDArray[np.bool_]
FloatArray = npt.NDArray[np.float64]


class ConditionRow(Protocol):
    """The columns of a stored condition (``service.store.models.Condition``)."""

    id: int
    speed_rpm: float
    torque_nm: float
    ambient_c: float
    started_at: datetime


class StoredIdentification(IdentificationRow, Protocol):
    """A stored identification with its condition loaded (the repository's list/get functions load it)."""

    @property
    def condition(self) -> ConditionRow: ...


def _floats(values: Sequence[float | None] | None) -> FloatArray:
    """Read-only (7,) float array, None -> NaN (None itself -> all NaN)."""
    out = np.full(N_ZONES, np.nan)
    if values is not None:
        out = np.array([np.nan if v is None else float(v) for v in values], dtype=float)
    out.setflags(write=False)
    return out


def _bools(values: Sequence[bool] | Sequence[JsonValue] | None) -> BoolArray:
    """Read-only (7,) bool array (None or a wrong length -> all False: records from before the field)."""
    out = np.zeros(N_ZONES, dtype=bool)
    if values is not None and len(values) == N_ZONES:
        out = np.array([bool(v) for v in values], dtype=bool)
    out.setflags(write=False)
    return out


def _ci_lo(values: Sequence[float | None] | None) -> FloatArray:
    """Lower CI bounds; a record stored before the CIs were computed in log H (docs/design/identification.md)
    may hold a negative one: H is positive, so it is served as 0."""
    with np.errstate(invalid="ignore"):
        out = np.where(_floats(values) < 0.0, 0.0, _floats(values))
    out.setflags(write=False)
    return out


def _flags(data: IdentificationData, name: str) -> BoolArray:
    """A (7,) flag stored in the diagnostics (``at_bound``, ``prior_dominated``); all False when absent."""
    diagnostics = data.diagnostics or {}
    flags = diagnostics.get(name)
    return _bools(flags if isinstance(flags, list) else None)


def data_to_record(data: IdentificationData, condition: ConditionSnapshot) -> IdentificationRecord:
    """The API view of an identification, just finished (or skipped, or failed) or read back from the
    database: the one mapping from the stored record to the served one."""
    return IdentificationRecord(
        data=data,
        condition=condition,
        h=_floats(data.h),
        ci95_lo=_ci_lo(data.ci95_lo),
        ci95_hi=_floats(data.ci95_hi),
        identified=_bools(data.identified),
        at_bound=_flags(data, "at_bound"),
        prior_dominated=_flags(data, "prior_dominated"),
    )


def condition_from_row(
    row: ConditionRow, *, state: ConditionState = ConditionState.STABLE
) -> ConditionSnapshot:
    """The API view of a stored condition (the detector's live state is not stored: STABLE by default)."""
    return ConditionSnapshot(
        id=int(row.id),
        speed_rpm=float(row.speed_rpm),
        torque_nm=float(row.torque_nm),
        ambient_c=float(row.ambient_c),
        since=row.started_at,
        state=state,
    )


def row_to_record(row: StoredIdentification) -> IdentificationRecord:
    """The API view of a stored identification (its condition loaded)."""
    return data_to_record(IdentificationData.from_row(row), condition_from_row(row.condition))


def age_s(then: datetime | None, now: datetime) -> float | None:
    """Seconds from ``then`` to ``now`` (None for None)."""
    return None if then is None else max(0.0, (now - then).total_seconds())


def at_bound(rec: IdentificationRecord, box: tuple[float, float] | None, rel_tol: float) -> BoolArray:
    """(7,) bool: the record's own flag, or H within ``rel_tol`` × box width of a bound of ``box``."""
    flags = np.asarray(rec.at_bound, dtype=bool)
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
    bound: BoolArray,
    condition: ConditionSnapshot | None,
    data_problems: tuple[str, ...],
    restored: bool,
    has_sample: bool = True,
    converging_since: datetime | None = None,
    not_fresh: str | None = None,
) -> Usability:
    """Whether a compensation controller may apply ``rec``'s H now, else the first reason why not.

    Codes, in this order: ``no_data`` (no sample acquired yet), ``stale`` (the data are not fresh:
    ``data_problems``), ``state_converging`` (the live state has not converged since ``converging_since``,
    a restart or a data gap: no identification window may start yet, the H are the last ones),
    ``condition_changed`` (identified at another condition, or the condition is changing), in speed-map
    mode ``not_fresh`` instead (the map's own reason, ``map_freshness``: ``map_old``, ``speed_not_visited``),
    ``at_bound`` (an H on a bound of the search box), ``not_identified`` (an H's 95 % CI wider than the
    threshold), ``restored`` (otherwise usable, but the last stored H, not re-identified since the
    restart)."""
    if not has_sample:
        return Usability(False, "no_data: no sample acquired yet")
    if data_problems:
        return Usability(False, "stale: " + ", ".join(data_problems) + " (see /readyz)")
    if converging_since is not None:
        since = converging_since.isoformat(timespec="seconds")
        return Usability(
            False,
            f"state_converging: the live temperature state has not converged since {since} (restart or data "
            "gap): no identification window starts before it has, the H are the last identified ones",
        )
    if not_fresh is not None:
        return Usability(False, not_fresh)
    if condition is None or condition.id != rec.condition.id or condition.state is not ConditionState.STABLE:
        now = "none" if condition is None else f"{condition.id} ({condition.state.value})"
        return Usability(False, f"condition_changed: identified at condition {rec.condition.id}, now {now}")
    if bool(np.any(bound)):
        names = ", ".join(n for n, b in zip(ZONE_NAMES, bound, strict=True) if b)
        return Usability(False, f"at_bound: {names} on a bound of the search box (not identified)")
    weak = [n for n, ok in zip(ZONE_NAMES, rec.identified, strict=True) if not ok]
    positive = len(rec.h) == N_ZONES and all(math.isfinite(float(x)) and x > 0 for x in rec.h)
    if weak or not positive:
        return Usability(False, f"not_identified: {', '.join(weak) or 'H'} (95 % CI too wide)")
    if restored:
        return Usability(False, "restored: the last stored H, not re-identified since the restart")
    return Usability(True, None)


def chtc_snapshot(
    rec: IdentificationRecord,
    *,
    status: ChtcStatus,
    newest_sample_at: datetime | None,
    condition: ConditionSnapshot | None,
    data_problems: tuple[str, ...],
    restored: bool,
    box: tuple[float, float] | None,
    converging_since: datetime | None = None,
    not_fresh: str | None = None,
) -> ChtcSnapshot:
    """What ``/chtc`` serves: the current identification ``rec`` and whether a controller may use it now.

    ``data_problems``: codes of ``core.data_problems`` (empty: fresh); ``restored``: ``rec`` is the last
    stored one, not re-identified since the restart; ``box``: the search box of H (an H within
    ``BOUND_REL_TOL`` of a bound is not identified); ``converging_since``: the live state's (re)start while
    it has not converged (``usability``); ``not_fresh``: in speed-map mode, why the map is not fresh at the
    current speed (``map_freshness``; ``rec`` is then ``map_record``'s: H from the map at the current
    condition)."""
    bound = at_bound(rec, box, BOUND_REL_TOL)
    use = usability(
        rec,
        bound=bound,
        condition=condition,
        data_problems=data_problems,
        restored=restored,
        has_sample=newest_sample_at is not None,
        converging_since=converging_since,
        not_fresh=not_fresh,
    )
    identified = rec.identified & ~bound & ~rec.prior_dominated
    identified.setflags(write=False)
    return ChtcSnapshot(
        record=rec,
        status=status,
        newest_sample_at=newest_sample_at,
        identified=identified,
        at_bound=bound,
        usable_for_compensation=use.usable,
        reason=use.reason,
        box=None if box is None else (float(box[0]), float(box[1])),
    )


# --- speed-map mode (docs/design/hmap.md) -------------------------------------------------------------------


def _ro(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


def _ro_bool(a: BoolArray) -> BoolArray:
    a.setflags(write=False)
    return a


def map_record(
    rec: IdentificationRecord,
    speed_map: SpeedMap,
    *,
    speed_rpm: float,
    ambient_c: float,
    condition: ConditionSnapshot,
    ci_threshold: float,
) -> IdentificationRecord:
    """The record ``/chtc`` serves in speed-map mode: the stored map fit ``rec`` (provenance, fit) with H1-H7
    and their 95 % bands from the map at ``speed_rpm`` and ``ambient_c`` (the newest sample's), taken at the
    current ``condition``; ``identified`` where the band's half-width in ln H is <= ``ci_threshold``."""
    h, lo, hi = speed_map.h_at([speed_rpm], ambient_c)
    half = 0.5 * np.log(hi[0] / lo[0])
    return replace(
        rec,
        condition=condition,
        h=_ro(np.array(h[0], dtype=float)),
        ci95_lo=_ro(np.array(lo[0], dtype=float)),
        ci95_hi=_ro(np.array(hi[0], dtype=float)),
        identified=_ro_bool(np.asarray(half <= ci_threshold, dtype=bool)),
        at_bound=_ro_bool(np.zeros(N_ZONES, dtype=bool)),
    )


@dataclass(frozen=True)
class MapFreshness:
    status: ChtcStatus
    reason: str | None  # why not fresh, "code: detail" (None: fresh)


def map_freshness(
    speed_map: SpeedMap,
    *,
    newest_t: datetime | None,
    speed_rpm: float | None,
    data_problems: tuple[str, ...],
    converging_since: datetime | None,
    fresh_s: float,
    margin_rpm: float,
    min_visit_s: float,
) -> MapFreshness:
    """How current the map is at the current speed. In this order: ``no-data`` (no sample), ``stale``
    (``data_problems``; or no speed known at all: ``speed_rpm`` None with a sample; or ``restored``: the
    stored map, not re-fitted since the restart; or ``state_converging``), then ``identifying`` with
    ``map_old`` (the fit's window ended more than ``fresh_s`` before the newest sample) or
    ``speed_not_visited`` (the current speed is not within ``margin_rpm`` of a speed with >= ``min_visit_s``
    of fitted data), else ``fresh``."""
    if newest_t is None:
        if speed_map.restored:
            return MapFreshness(ChtcStatus.STALE, "restored: the stored map, no sample since the restart")
        return MapFreshness(ChtcStatus.NO_DATA, "no_data: no sample acquired yet")
    if data_problems:
        return MapFreshness(ChtcStatus.STALE, "stale: " + ", ".join(data_problems) + " (see /readyz)")
    if speed_rpm is None:
        return MapFreshness(ChtcStatus.STALE, "stale: no speed value known yet (see /readyz)")
    if speed_map.restored:
        return MapFreshness(ChtcStatus.STALE, "restored: the stored map, not re-fitted since the restart")
    if converging_since is not None:
        since = converging_since.isoformat(timespec="seconds")
        return MapFreshness(
            ChtcStatus.STALE, f"state_converging: the live temperature state has not converged since {since}"
        )
    age = (newest_t - speed_map.fitted_at).total_seconds()
    if age > fresh_s:
        return MapFreshness(
            ChtcStatus.IDENTIFYING,
            f"map_old: the map's data end {age / 60:.1f} min before the newest sample "
            f"(limit {fresh_s / 60:.0f} min)",
        )
    if not speed_map.covered(speed_rpm, margin_rpm=margin_rpm, min_visit_s=min_visit_s):
        return MapFreshness(
            ChtcStatus.IDENTIFYING,
            f"speed_not_visited: {abs(speed_rpm):.0f} rpm is not within {margin_rpm:.0f} rpm of a speed "
            f"with >= {min_visit_s:.0f} s of fitted data",
        )
    return MapFreshness(ChtcStatus.FRESH, None)


def chtc_map_snapshot(
    speed_map: SpeedMap,
    *,
    ambient_c: float,
    freshness: MapFreshness,
    newest_sample_at: datetime | None,
    current_speed_rpm: float | None,
    ci_threshold: float,
    margin_rpm: float,
) -> ChtcMapSnapshot:
    """What ``chtc_map()`` serves: the map on ``MAP_GRID_RPM`` at ``ambient_c`` with its bands, ``identified``
    where the band's half-width in ln H is <= ``ci_threshold``, the visited speeds and the freshness."""
    h, lo, hi = speed_map.h_at(MAP_GRID_RPM, ambient_c)
    half = 0.5 * np.log(hi / lo)
    return ChtcMapSnapshot(
        fitted_at=speed_map.fitted_at,
        identification_id=speed_map.identification_id,
        family=speed_map.family,
        ambient_c=float(ambient_c),
        speeds_rpm=MAP_GRID_RPM,
        h_w_m2k=_ro(np.asarray(h, dtype=float)),
        ci95_lo_w_m2k=_ro(np.asarray(lo, dtype=float)),
        ci95_hi_w_m2k=_ro(np.asarray(hi, dtype=float)),
        identified=_ro_bool(np.asarray(half <= ci_threshold, dtype=bool)),
        visited_rpm=speed_map.visited_rpm,
        visited_s=speed_map.visited_s,
        status=freshness.status,
        newest_sample_at=newest_sample_at,
        current_speed_rpm=current_speed_rpm,
        visited_margin_rpm=float(margin_rpm),
        rmse_c=speed_map.rmse_c,
        restored=speed_map.restored,
        reason=freshness.reason,
    )
