"""The one mapping from an identification to what the API serves (pure functions).

An identification exists as ``service.contracts.records.IdentificationData``: built from the
``model.identify.IdentificationResult`` by ``IdentificationData.from_result``, stored as is (``values()``) and
read back after a restart or by the history endpoints (``IdentificationData.from_row``). ``data_to_record``
turns it, with the condition it was taken at, into the ``IdentificationRecord`` the API serves, and
``chtc_snapshot`` wraps the current record with the policy's verdict on it now (``service.serve.policy``)::

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

from collections.abc import Sequence
from dataclasses import replace
from datetime import datetime
from typing import Protocol

import numpy as np
import numpy.typing as npt

from model.hmap import Z95
from model.identify_prior import HPrior
from service.contracts.columns import JsonValue
from service.contracts.records import IdentificationData, IdentificationRow
from service.contracts.sensorfault import SensorFault
from service.contracts.snapshots import (
    ZONE_NAMES,
    ChtcMapSnapshot,
    ChtcSnapshot,
    ConditionSnapshot,
    ConditionState,
    IdentificationRecord,
)
from service.contracts.verdict import Verdict
from service.identify.speedmap import MAP_GRID_RPM, SpeedMap, beyond_box

__all__ = [
    "ConditionRow",
    "StoredIdentification",
    "age_s",
    "at_bound",
    "chtc_map_snapshot",
    "chtc_snapshot",
    "condition_from_row",
    "data_to_record",
    "map_record",
    "row_to_record",
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


def _diagnostic_flags(data: IdentificationData, name: str) -> BoolArray:
    """(7,) bool flags stored in the record's diagnostics under ``name`` (all False when absent)."""
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
        at_bound=_diagnostic_flags(data, "at_bound"),
        prior_dominated=_diagnostic_flags(data, "prior_dominated"),
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


def chtc_snapshot(
    rec: IdentificationRecord,
    *,
    newest_sample_at: datetime | None,
    verdict: Verdict,
    bound: BoolArray,
    box: tuple[float, float] | None = None,
    sensor_faults: tuple[SensorFault, ...] = (),
) -> ChtcSnapshot:
    """What ``/chtc`` serves: the current identification ``rec`` and the policy's ``verdict`` on it now
    (``service.serve.policy.chtc_verdict``); ``bound``: ``at_bound(rec, ...)`` (an H there is not
    identified); ``box``: the search box of H, W/(m²·K), served for readable bounds (``> box``)."""
    identified = rec.identified & ~bound & ~rec.prior_dominated
    identified.setflags(write=False)
    return ChtcSnapshot(
        record=rec,
        newest_sample_at=newest_sample_at,
        identified=identified,
        at_bound=bound,
        verdict=verdict,
        box=None if box is None else (float(box[0]), float(box[1])),
        sensor_faults=sensor_faults,
    )


def widen_band(
    h: FloatArray, lo: FloatArray, hi: FloatArray, *, form_sd: float, box: tuple[float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The 95 % band served for H (7,) [W/(m²·K)] with the fit's band [lo, hi]: its σ in ln H and ``form_sd``
    (the model-form error no statistical band sees) in quadrature, truncated to ``box`` (the support of H:
    the fit searches only there, the map's levels are bounded by it; a Gaussian band past it is the
    approximation's, not the data's). Returns (lo, hi, the widened half-width in ln H before truncation)."""
    h = np.asarray(h, dtype=float)
    # a lower bound of 0 (clamped) or one so small that hi/lo overflows: an unbounded band, σ = inf
    with np.errstate(divide="ignore", over="ignore"):
        sd = np.log(np.asarray(hi, dtype=float) / np.asarray(lo, dtype=float)) / (2.0 * Z95)
    sd = np.sqrt(sd**2 + float(form_sd) ** 2)
    half = Z95 * sd
    wlo = np.maximum(h * np.exp(-half), np.minimum(float(box[0]), h))
    whi = np.minimum(h * np.exp(half), np.maximum(float(box[1]), h))
    return wlo, whi, half


def served_record(
    rec: IdentificationRecord, *, form_sd: float, ci_threshold: float, box: tuple[float, float]
) -> IdentificationRecord:
    """The record ``/chtc`` serves of ``rec``: each band widened and truncated (``widen_band``), and an H
    ``identified`` only where the widened band's half-width in ln H is at most ``ci_threshold``."""
    lo, hi, half = widen_band(rec.h, rec.ci95_lo, rec.ci95_hi, form_sd=form_sd, box=box)
    return replace(
        rec,
        ci95_lo=_ro(lo),
        ci95_hi=_ro(hi),
        identified=_ro_bool(np.asarray(rec.identified & (half <= ci_threshold), dtype=bool)),
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
    prior: HPrior | None = None,
    model_box: tuple[float, float] | None = None,
) -> IdentificationRecord:
    """The record ``/chtc`` serves in speed-map mode: the stored map fit ``rec`` (provenance, fit) with H1-H7
    and their 95 % bands from the map at ``speed_rpm`` and ``ambient_c`` (the newest sample's), taken at the
    current ``condition``; ``identified`` where the band's half-width in ln H is <= ``ci_threshold``.

    With ``prior`` (``service.identify.prior.ServedMapPrior``: the map's information there on the cold
    physics prior) H and the band are its instead, and ``prior_dominated`` where the data did not see an H
    (never identified).

    With ``model_box`` (the reduced model's H box): an H whose band lies wholly outside it is a guess the map
    extrapolated, never identified (``service.identify.speedmap.beyond_box``)."""
    dominated = np.zeros(N_ZONES, dtype=bool)
    if prior is None:
        h3, lo3, hi3 = speed_map.h_at([speed_rpm], ambient_c)
        h, lo, hi = h3[0], lo3[0], hi3[0]
    else:
        sd = np.sqrt(np.diag(prior.log_cov))
        h = np.exp(prior.log_mean)
        lo, hi = h * np.exp(-Z95 * sd), h * np.exp(Z95 * sd)
        dominated = prior.dominated(sd**2)
    half = 0.5 * np.log(hi / lo)
    known = (half <= ci_threshold) & ~dominated
    if model_box is not None:
        known &= ~beyond_box(lo, hi, model_box)
    return replace(
        rec,
        condition=condition,
        h=_ro(np.array(h, dtype=float)),
        ci95_lo=_ro(np.array(lo, dtype=float)),
        ci95_hi=_ro(np.array(hi, dtype=float)),
        identified=_ro_bool(np.asarray(known, dtype=bool)),
        at_bound=_ro_bool(np.zeros(N_ZONES, dtype=bool)),
        prior_dominated=_ro_bool(np.array(dominated, dtype=bool)),
    )


def chtc_map_snapshot(
    speed_map: SpeedMap,
    *,
    ambient_c: float,
    verdict: Verdict,
    newest_sample_at: datetime | None,
    current_speed_rpm: float | None,
    ci_threshold: float,
    margin_rpm: float,
    form_sd: float = 0.0,
    box: tuple[float, float] = (0.0, np.inf),
    model_box: tuple[float, float] | None = None,
) -> ChtcMapSnapshot:
    """What ``chtc_map()`` serves: the map on ``MAP_GRID_RPM`` at ``ambient_c`` with its bands, ``identified``
    where the band's half-width in ln H is <= ``ci_threshold``, the visited speeds and the policy's
    ``verdict`` (``service.serve.policy.map_verdict``); the bands widened by ``form_sd`` and truncated to
    ``box`` as ``/chtc``'s (``widen_band``); with ``model_box`` never where the band lies wholly outside the
    reduced model's H box (as ``map_record``)."""
    h, lo, hi = speed_map.h_at(MAP_GRID_RPM, ambient_c)
    lo, hi, half = widen_band(h, lo, hi, form_sd=form_sd, box=box)
    known = half <= ci_threshold
    if model_box is not None:
        known &= ~beyond_box(lo, hi, model_box)
    return ChtcMapSnapshot(
        fitted_at=speed_map.fitted_at,
        identification_id=speed_map.identification_id,
        family=speed_map.family,
        ambient_c=float(ambient_c),
        speeds_rpm=MAP_GRID_RPM,
        h_w_m2k=_ro(np.asarray(h, dtype=float)),
        ci95_lo_w_m2k=_ro(np.asarray(lo, dtype=float)),
        ci95_hi_w_m2k=_ro(np.asarray(hi, dtype=float)),
        identified=_ro_bool(np.asarray(known, dtype=bool)),
        visited_rpm=speed_map.visited_rpm,
        visited_s=speed_map.visited_s,
        verdict=verdict,
        newest_sample_at=newest_sample_at,
        current_speed_rpm=current_speed_rpm,
        visited_margin_rpm=float(margin_rpm),
        rmse_c=speed_map.rmse_c,
        restored=speed_map.restored,
    )
