"""Response schemas (pydantic), separate from the service snapshots and the ORM rows.

Naming: every number carries its unit in its name (``h_w_m2k``, ``ambient_c``, ``speed_rpm``, ``r_m``,
``age_s``); every timestamp is UTC ISO-8601 and ends in ``_at`` (or is ``t``/``since``). Conversion functions
``*_out()`` build these from :mod:`service.serve.interface` snapshots.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, field_validator

from api.deps import ClockInfo
from service.contracts.command import CommandSnapshot
from service.contracts.health import DeviceHealth, HealthSnapshot
from service.contracts.mechanics import MECH_PARAMS, MechanicsCalibration
from service.contracts.probe import FixtureOffset, ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import (
    H_UNIT,
    ZONE_NAMES,
    ChtcMapSnapshot,
    ChtcSnapshot,
    CompensationSnapshot,
    ConditionSnapshot,
    IdentificationJob,
    IdentificationRecord,
    OffsetBaseline,
    SectionSnapshot,
    SensorReading,
)
from service.contracts.verdict import ChtcStatus, Reason, Verdict


def _enum(value: object) -> Any:
    """An enum member (or a plain string) as its string value; pydantic checks it against the Literal."""
    return str(value)


def _num(x: float | None, digits: int | None = None) -> float | None:
    """A JSON-safe float: NaN/inf become null."""
    if x is None:
        return None
    v = float(x)
    if not math.isfinite(v):
        return None
    return round(v, digits) if digits is not None else v


class ZoneOut(BaseModel):
    name: str = Field(description="H1..H7")
    h_w_m2k: float | None = Field(description="convective heat transfer coefficient, W/(m²·K)")
    ci95_lo_w_m2k: float | None
    ci95_hi_w_m2k: float | None
    identified: bool = Field(
        description="False: not identified from this window (95 % CI wider than the threshold, or at a bound)"
    )
    at_bound: bool = Field(
        False, description="H lies on a bound of the search box (the optimum may be outside): not identified"
    )
    prior_dominated: bool = Field(
        False,
        description="the data did not see this H: value and band are the prior's (physics correlations, "
        "σ(ln H) = ln 3, plus the speed map's information): not identified",
    )


def zones_out(
    h: np.ndarray,
    *,
    lo: np.ndarray,
    hi: np.ndarray,
    identified: np.ndarray,
    at_bound: np.ndarray | None = None,
    prior_dominated: np.ndarray | None = None,
) -> list[ZoneOut]:
    return [
        ZoneOut(
            name=n,
            h_w_m2k=_num(h[i], 4),
            ci95_lo_w_m2k=_num(lo[i], 4),
            ci95_hi_w_m2k=_num(hi[i], 4),
            identified=bool(identified[i]),
            at_bound=bool(at_bound[i]) if at_bound is not None else False,
            prior_dominated=bool(prior_dominated[i]) if prior_dominated is not None else False,
        )
        for i, n in enumerate(ZONE_NAMES)
    ]


class ConditionOut(BaseModel):
    id: int
    speed_rpm: float
    torque_nm: float
    ambient_c: float
    since: datetime = Field(description="UTC start of this condition")
    state: Literal["stable", "changing"]


def condition_out(c: ConditionSnapshot) -> ConditionOut:
    return ConditionOut(
        id=c.id,
        speed_rpm=c.speed_rpm,
        torque_nm=c.torque_nm,
        ambient_c=c.ambient_c,
        since=c.since,
        state=_enum(c.state),
    )


class SpindleAnswer(BaseModel):
    """A top-level answer: ``spindle_id`` first, so every body says which spindle it is about."""

    spindle_id: str = Field(
        description="which spindle answers: its id (settings spindle.id), as stored in the database"
    )


class SensorFaultOut(BaseModel):
    """A channel the live state leaves out: stuck or drifting without the DAQ flagging it."""

    channel: int = Field(description="sensor channel, 1..32")
    kind: Literal["stuck", "drift"] = Field(description="stuck: frozen reading; drift: walks off the model")
    since: datetime = Field(description="UTC instant it was found and left out")
    detail: str = Field(description="the evidence, for humans (never parse it)")


def sensor_faults_out(faults: Any) -> list[SensorFaultOut]:
    return [
        SensorFaultOut(
            channel=f.channel,
            kind=_enum(f.kind),
            since=datetime.fromtimestamp(f.since_t, tz=UTC),
            detail=f.detail,
        )
        for f in faults
    ]


SENSOR_FAULTS_DOC = (
    "channels left out of the live state as stuck or drifting (not flagged by the DAQ; the CI carries what "
    "they bent before they were found); empty when none"
)


class BlockerOut(BaseModel):
    """One reason a served value is not usable, and what the operator should do about it."""

    reason_code: Reason
    reason: str = Field(description="'code: detail' for humans (never parse it)")
    action: str


class VerdictOut(SpindleAnswer):
    """The served-value policy's verdict (service.serve.policy): one status, the usable flag, and when not
    usable the typed reason, a human detail and what the operator should do."""

    status: ChtcStatus = Field(description="freshness of the served value")
    usable_for_compensation: bool
    reason_code: Reason | None = Field(description="why not usable, one code of the enum (null when usable)")
    reason: str | None = Field(description="why not usable, for humans: 'code: detail' (never parse it)")
    action: str | None = Field(description="what the operator should do (null when usable)")
    blocking: list[BlockerOut] = Field(
        default_factory=list,
        description="every reason that blocks, in order, each with its action (the first is reason_code; "
        "empty when usable)",
    )


def _verdict(v: Verdict) -> dict[str, Any]:
    return {
        "status": _enum(v.status),
        "usable_for_compensation": v.usable,
        "reason_code": None if v.reason is None else _enum(v.reason),
        "reason": v.text,
        "action": v.action,
        "blocking": [
            BlockerOut(reason_code=_enum(b.reason), reason=b.text, action=b.action) for b in v.blocking
        ],
    }


class ChtcOut(VerdictOut):
    """``usable_for_compensation``: these H may be used by a model that needs them (fresh data, identified at
    the current stable condition, each H identified or prior-dominated, none on a bound of the search box)."""

    unit: str = Field(H_UNIT, description="unit of every h_w_m2k / ci95_*_w_m2k")
    zones: list[ZoneOut]
    prior_dominated: list[bool] = Field(
        default_factory=lambda: [False] * len(ZONE_NAMES),
        description="per H (H1..H7): the data did not see it, value and band are the prior's",
    )
    h_box_w_m2k: list[float] | None = Field(
        None, description="the search box of H [low, high], W/(m²·K): a CI bound beyond it means 'unknown'"
    )
    identified_at: datetime
    identification_id: int
    condition: ConditionOut
    f_c2: float | None = Field(description="objective: mean squared residual, °C²")
    fit: float | None = Field(description="1 / (1 + f), dimensionless")
    rmse_c: float | None
    method: str
    model_version: str
    newest_sample_at: datetime | None
    sample_age_s: float | None = Field(description="age of the newest sample at served_at, s")
    served_at: datetime
    sensor_faults: list[SensorFaultOut] = Field(default_factory=list, description=SENSOR_FAULTS_DOC)


def chtc_out(s: ChtcSnapshot, now: datetime, *, spindle_id: str) -> ChtcOut:
    age = None if s.newest_sample_at is None else round((now - s.newest_sample_at).total_seconds(), 3)
    return ChtcOut(
        spindle_id=spindle_id,
        **_verdict(s.verdict),
        unit=s.unit,
        zones=zones_out(
            s.h,
            lo=s.ci95_lo,
            hi=s.ci95_hi,
            identified=s.identified,
            at_bound=s.at_bound,
            prior_dominated=s.prior_dominated,
        ),
        prior_dominated=[bool(x) for x in s.prior_dominated],
        h_box_w_m2k=None if s.box is None else [float(s.box[0]), float(s.box[1])],
        identified_at=s.identified_at,
        identification_id=s.identification_id,
        condition=condition_out(s.condition),
        f_c2=_num(s.f),
        fit=_num(s.fit),
        rmse_c=_num(s.rmse_c),
        method=s.method,
        model_version=s.model_version,
        newest_sample_at=s.newest_sample_at,
        sample_age_s=age,
        served_at=now,
        sensor_faults=sensor_faults_out(s.sensor_faults),
    )


# --- /chtc/map (speed-map mode, docs/design/hmap.md, docs/api.md)


class MapZoneOut(BaseModel):
    name: str = Field(description="H1..H7")
    h_w_m2k: list[float | None] = Field(description="H at each of speeds_rpm, W/(m²·K)")
    ci95_lo_w_m2k: list[float | None] = Field(description="95 % band, lower edge at each speed, W/(m²·K)")
    ci95_hi_w_m2k: list[float | None] = Field(description="95 % band, upper edge at each speed, W/(m²·K)")
    identified: list[bool] = Field(
        description="per speed: the band narrower than identification.ci_rel_threshold (in ln H)"
    )


class VisitedOut(BaseModel):
    speed_rpm: float = Field(description="a speed bin the fitted data have covered, rpm")
    duration_s: float = Field(
        description="seconds of data at this speed bin, decayed like the map's information (forgetting), s"
    )


class ChtcMapOut(VerdictOut):
    """The verdict: how current the map is at the current speed (``usable_for_compensation``: fresh there)."""

    unit: str = Field(H_UNIT, description="unit of every h_w_m2k / ci95_*_w_m2k")
    family: str = Field(description="the map's model family: 'nodes' (ln H at speed nodes) or 'physics'")
    fitted_at: datetime = Field(description="UTC end of the window of the fit the map comes from")
    identification_id: int | None = Field(description="the stored identification of that fit")
    rmse_c: float | None = Field(description="the fit's RMS residual, °C")
    restored: bool = Field(description="the stored map, not re-fitted since the service restarted")
    ambient_c: float = Field(description="the ambient the map is evaluated at (the newest sample's), °C")
    speeds_rpm: list[float] = Field(description="the speed grid every zone's lists follow, rpm, ascending")
    zones: list[MapZoneOut]
    visited: list[VisitedOut] = Field(description="the speeds the fitted data have covered, ascending")
    visited_margin_rpm: float = Field(
        description="a speed within this of a visited one (with enough data) counts as covered, rpm"
    )
    current_speed_rpm: float | None = Field(description="the newest sample's speed, rpm (null before any)")
    newest_sample_at: datetime | None
    sample_age_s: float | None = Field(description="age of the newest sample at served_at, s")
    served_at: datetime


def _nums(a: np.ndarray, digits: int) -> list[float | None]:
    return [_num(x, digits) for x in a]


def chtc_map_out(s: ChtcMapSnapshot, now: datetime, *, spindle_id: str) -> ChtcMapOut:
    age = None if s.newest_sample_at is None else round((now - s.newest_sample_at).total_seconds(), 3)
    return ChtcMapOut(
        spindle_id=spindle_id,
        **_verdict(s.verdict),
        unit=s.unit,
        family=s.family,
        fitted_at=s.fitted_at,
        identification_id=s.identification_id,
        rmse_c=_num(s.rmse_c, 4),
        restored=bool(s.restored),
        ambient_c=round(float(s.ambient_c), 3),
        speeds_rpm=[float(x) for x in s.speeds_rpm],
        zones=[
            MapZoneOut(
                name=name,
                h_w_m2k=_nums(s.h_w_m2k[:, i], 4),
                ci95_lo_w_m2k=_nums(s.ci95_lo_w_m2k[:, i], 4),
                ci95_hi_w_m2k=_nums(s.ci95_hi_w_m2k[:, i], 4),
                identified=[bool(x) for x in s.identified[:, i]],
            )
            for i, name in enumerate(s.zones)
        ],
        visited=[
            VisitedOut(speed_rpm=float(r), duration_s=round(float(d), 1))
            for r, d in zip(s.visited_rpm, s.visited_s, strict=True)
        ],
        visited_margin_rpm=float(s.visited_margin_rpm),
        current_speed_rpm=_num(s.current_speed_rpm, 1),
        newest_sample_at=s.newest_sample_at,
        sample_age_s=age,
        served_at=now,
    )


class FieldMeta(SpindleAnswer):
    at: Literal["now", "steady"]
    t: datetime = Field(description="UTC instant the field belongs to")
    identification_id: int | None
    temperature_unit: str = "°C"
    length_unit: str = "m"
    t_min_c: float | None
    t_max_c: float | None
    std_max_c: float | None = Field(
        default=None,
        description="largest 1σ of the field, °C (at=now: the filtered state's; null for steady)",
    )


class FieldMeshOut(FieldMeta):
    format: Literal["mesh"] = "mesh"
    nodes_r_m: list[float]
    nodes_z_m: list[float]
    temps_c: list[float | None]
    std_c: list[float | None] | None = Field(
        default=None,
        description="1σ per node, °C (at=now: the filtered live state's; null for steady); 95 %: ±1.96σ",
    )
    triangles: list[list[int]]


class FieldGridOut(FieldMeta):
    format: Literal["grid"] = "grid"
    r_m: list[float] = Field(description="nr grid abscissae, m")
    z_m: list[float] = Field(description="nz grid ordinates, m")
    temps_c: list[list[float | None]] = Field(description="[i_r][i_z], null outside the section")
    std_c: list[list[float | None]] | None = Field(
        default=None, description="1σ [i_r][i_z], °C (P1-interpolated; null for steady); 95 %: ±1.96σ"
    )


class PointOut(BaseModel):
    r_m: float
    z_m: float
    temp_c: float | None = Field(description="null when the point is outside the section")
    inside: bool
    std_c: float | None = Field(default=None, description="1σ, °C (P1-interpolated; null for steady)")
    ci95_c: tuple[float, float] | None = Field(default=None, description="temp_c ± 1.96σ, °C")


class FieldPointsOut(FieldMeta):
    format: Literal["points"] = "points"
    points: list[PointOut]


class SensorOut(BaseModel):
    channel: int
    name: str
    role: str
    r_m: float
    z_m: float
    measured_c: float | None
    predicted_c: float | None
    residual_c: float | None = Field(description="measured - offset - predicted, °C")
    predicted_sd_c: float | None = Field(
        default=None, description="1σ of predicted_c (the filtered live state's and the model's error), °C"
    )
    predicted_ci95_c: tuple[float, float] | None = Field(default=None, description="predicted_c ± 1.96σ, °C")
    quality: str
    t: datetime
    offset_c: float | None = Field(
        default=None, description="sensor offset zeroed against the baseline (subtracted before the fit), °C"
    )
    offset_sd_c: float | None = Field(default=None, description="1σ of the offset still unknown, °C")
    offset_calibrated_at: datetime | None = Field(default=None, description="UTC end of the baseline")
    offset_source: Literal["auto", "manual", "commissioning"] | None = Field(
        default=None,
        description="how the baseline was taken: at rest (auto), asked for (manual) or the commissioning "
        "thermal test's rest, used until the spindle rests (commissioning); null: no baseline (unknown)",
    )


class BaselineOut(BaseModel):
    t_from: datetime
    t_to: datetime = Field(description="UTC calibration time (end of the rest window)")
    source: str = Field(description='"auto" (detected equilibrium), "manual" or "commissioning"')
    samples: int
    offsets_c: list[float | None] = Field(description="per channel 1..32, °C (null: no data at rest)")
    sd_c: list[float] = Field(description="per channel 1σ of the offset, °C")


def baseline_out(b: OffsetBaseline) -> BaselineOut:
    return BaselineOut(
        t_from=b.t_from,
        t_to=b.t_to,
        source=b.source,
        samples=b.samples,
        offsets_c=[_num(x, 4) for x in b.offsets_c],
        sd_c=[round(x, 4) for x in b.sd_c],
    )


def sensor_out(s: SensorReading) -> SensorOut:
    return SensorOut(
        channel=s.channel,
        name=s.name,
        role=s.role,
        r_m=s.r_m,
        z_m=s.z_m,
        measured_c=_num(s.measured_c, 4),
        predicted_c=_num(s.predicted_c, 4),
        residual_c=_num(s.residual_c, 4),
        predicted_sd_c=_num(s.predicted_sd_c, 4),
        predicted_ci95_c=_ci95(s.predicted_c, s.predicted_sd_c),
        quality=s.quality,
        t=s.t,
        offset_c=_num(s.offset_c, 4),
        offset_sd_c=_num(s.offset_sd_c, 4),
        offset_calibrated_at=s.offset_calibrated_at,
        offset_source=s.offset_source,  # type: ignore[arg-type]
    )


class SensorsOut(SpindleAnswer):
    t: datetime | None = Field(description="UTC of the newest sample")
    sample_age_s: float | None
    served_at: datetime
    channels: list[SensorOut]


class ConditionsOut(SpindleAnswer):
    current: ConditionOut
    recent: list[ConditionOut] = Field(description="newest first, the current one included")
    served_at: datetime


class IdentificationOut(BaseModel):
    id: int
    started_at: datetime
    finished_at: datetime
    reason: str
    outcome: str
    message: str
    condition: ConditionOut
    window_from: datetime
    window_to: datetime
    unit: str = H_UNIT
    zones: list[ZoneOut]
    f_c2: float | None
    fit: float | None
    rmse_c: float | None
    method: str
    model_version: str
    nfev: int
    wall_s: float
    n_sensors_used: int


def identification_out(r: IdentificationRecord) -> IdentificationOut:
    return IdentificationOut(
        id=r.id,
        started_at=r.started_at,
        finished_at=r.finished_at,
        reason=r.reason,
        outcome=r.outcome,
        message=r.message,
        condition=condition_out(r.condition),
        window_from=r.window_from,
        window_to=r.window_to,
        zones=zones_out(
            r.h,
            lo=r.ci95_lo,
            hi=r.ci95_hi,
            identified=r.identified,
            at_bound=r.at_bound,
            prior_dominated=r.prior_dominated,
        ),
        f_c2=_num(r.f),
        fit=_num(r.fit),
        rmse_c=_num(r.rmse_c),
        method=r.method,
        model_version=r.model_version,
        nfev=r.nfev,
        wall_s=r.wall_s,
        n_sensors_used=r.n_sensors_used,
    )


class IdentificationPageOut(SpindleAnswer):
    items: list[IdentificationOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None
    partial: bool = Field(False, description="true: the database could not be read; only records in memory")
    partial_reason: str | None = Field(None, description="why the page is partial (null when complete)")


class IdentificationRequest(BaseModel):
    model_config = {"extra": "forbid"}
    reason: str = Field("manual", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:\- ]+$")


class JobOut(SpindleAnswer):
    job_id: str
    reason: str
    state: Literal["queued", "running", "done", "failed"]
    requested_at: datetime
    finished_at: datetime | None
    identification_id: int | None
    message: str
    href: str = Field(description="poll this URL for the job's state")


def job_out(j: IdentificationJob, prefix: str, *, spindle_id: str) -> JobOut:
    return JobOut(
        spindle_id=spindle_id,
        job_id=j.job_id,
        reason=j.reason,
        state=_enum(j.state),
        requested_at=j.requested_at,
        finished_at=j.finished_at,
        identification_id=j.identification_id,
        message=j.message,
        href=f"{prefix}/identifications/jobs/{j.job_id}",
    )


class DeviceOut(BaseModel):
    name: str
    status: Literal["ok", "degraded", "down", "disabled"]
    last_ok_at: datetime | None
    age_s: float | None
    counters: dict[str, int]
    message: str


def device_out(d: DeviceHealth) -> DeviceOut:
    return DeviceOut(
        name=d.name,
        status=_enum(d.status),
        last_ok_at=d.last_ok_at,
        age_s=_num(d.age_s, 3),
        counters=dict(d.counters),
        message=d.message,
    )


class ClockOut(BaseModel):
    simulated: bool = Field(
        description="true: every timestamp of this API is simulated plant time (`chtc demo`, `chtc replay`), "
        "not the wall clock"
    )
    speedup: float = Field(description="plant seconds per wall second (1 on the wall clock)")


class HealthOut(SpindleAnswer):
    status: Literal["ok", "degraded"]
    t: datetime
    clock: ClockOut = Field(description="what the service's clock (every timestamp served) is")
    model_loaded: bool
    model_version: str | None
    uptime_s: float
    devices: list[DeviceOut]


def health_out(h: HealthSnapshot, clock: ClockInfo | None = None, *, spindle_id: str) -> HealthOut:
    bad = not h.model_loaded or any(str(d.status) in ("degraded", "down") for d in h.devices)
    c = clock or ClockInfo()
    return HealthOut(
        spindle_id=spindle_id,
        status="degraded" if bad else "ok",
        t=h.t,
        clock=ClockOut(simulated=c.simulated, speedup=c.speedup),
        model_loaded=h.model_loaded,
        model_version=h.model_version,
        uptime_s=round(h.uptime_s, 3),
        devices=[device_out(d) for d in h.devices],
    )


class ReadyOut(SpindleAnswer):
    ready: bool
    reasons: list[str]
    t: datetime


def _ci95(mean: float | None, sd: float | None) -> tuple[float, float] | None:
    """mean ± 1.96·sd rounded to 0.1 mK (None when either is missing or not finite)."""
    if mean is None or sd is None or not (math.isfinite(mean) and math.isfinite(sd)):
        return None
    return (round(mean - 1.96 * sd, 4), round(mean + 1.96 * sd, 4))


# --- /compensation (docs/design/growth.md, docs/api.md)


class GrowthValueOut(BaseModel):
    um: float = Field(description="growth, µm")
    plc_0p1um: int = Field(description="the growth in 0.1 µm, rounded (an integer for a PLC)")
    ci95_um: tuple[float, float] = Field(description="95 % CI, µm (field, H and mechanics parts combined)")
    std_um: float = Field(description="1σ, µm (root sum of squares of the parts)")
    std_field_um: float = Field(description="1σ from the live field's uncertainty, µm")
    std_h_um: float = Field(description="1σ from H's uncertainty, µm")
    std_mech_um: float = Field(
        0.0,
        description="1σ from the commissioned mechanics' posterior (mount restraint, α) and, on the axial "
        "growth, the fixture offset's (fixture_offset), µm; 0 without a commissioning (then the policy's "
        "mechanics_uncalibrated rule applies)",
    )


class GrowthHorizonOut(BaseModel):
    horizon_s: float = Field(description="ahead of `at`, s")
    at: datetime = Field(description="UTC instant the forecast is for")
    axial: GrowthValueOut
    radial: GrowthValueOut


class GrowthForecastOut(BaseModel):
    """If the condition and H hold."""

    steady_axial: GrowthValueOut
    steady_radial: GrowthValueOut
    tau_s: float = Field(description="time constant of the axial growth's remaining change, s")
    slowest_tau_s: float = Field(description="the thermal model's slowest time constant, s")
    horizons: list[GrowthHorizonOut] = Field(description="5, 15 and 30 min ahead")


class PlcOut(BaseModel):
    """Controller values for the axial growth (docs/design/growth.md, 'Controller mapping'); check the sign
    once at commissioning."""

    tool_dir: int = Field(description="-1: the tool points to -Z of the machine axis (ISO 841)")
    correction_um: float = Field(description="axis correction cancelling the growth, µm (-tool_dir·growth)")
    sd43900_temp_comp_abs_value_mm: float = Field(description="SINUMERIK SD43900, mm")
    sd43910_temp_comp_slope: float = Field(description="SINUMERIK SD43910 (0: position-independent)")
    sd43920_temp_comp_ref_position_mm: float = Field(description="SINUMERIK SD43920, mm")
    sd42960_tool_temp_comp_mm: float = Field(description="SINUMERIK SD42960 component along the spindle, mm")
    isg_temp_comp_offset_0_0p1um: int = Field(description="Beckhoff/ISG P-AXIS-00273, 0.1 µm")
    isg_temp_comp_coefficient_um_per_m: float = Field(description="Beckhoff/ISG P-AXIS-00274, µm/m")
    isg_temp_comp_position_0_0p1um: int = Field(description="Beckhoff/ISG P-AXIS-00272, 0.1 µm")


class ProfileOut(BaseModel):
    """The controller profile that bounds the command ([controller]; docs/design/policy.md)."""

    name: str = Field(description="generic, sinumerik, fanuc or heidenhain")
    max_step_um: float = Field(description="the largest change per update, µm")
    max_rate_um_s: float = Field(description="the largest rate of change, µm/s")
    limit_um: float = Field(description="the largest magnitude served, µm")


class CommandOut(BaseModel):
    """What the controller applies now (docs/design/policy.md, 'The command value'): the axial growth to
    compensate, µm (+ towards the tool), following the growth while usable, held for hold_s when the verdict
    drops, then moving towards the best estimate the service has, never faster than the profile allows. Apply
    it whatever usable_for_compensation says; its status says what it does."""

    value_um: float = Field(description="the growth the controller compensates now, µm")
    status: Literal["following", "rate_limited", "holding", "fading", "at_limit", "none"] = Field(
        description="following: the usable growth; rate_limited: moving towards it, cut by the profile; "
        "holding: the verdict dropped, the last applied value held; fading: past the hold, moving towards "
        "the best estimate; at_limit: clipped at the profile's limit; none: nothing known, 0 or towards it"
    )
    at: datetime = Field(description="UTC instant of the command (the service's clock)")
    hold_s: float = Field(description="how long the last applied value is held after the verdict drops, s")
    profile: ProfileOut
    correction_um: float = Field(description="axis correction cancelling the command, µm (-tool_dir·value)")
    sd43900_temp_comp_abs_value_mm: float = Field(description="SINUMERIK SD43900 for the command, mm")
    sd42960_tool_temp_comp_mm: float = Field(description="SINUMERIK SD42960 for the command, mm")
    isg_temp_comp_offset_0_0p1um: int = Field(description="Beckhoff/ISG P-AXIS-00273 for the command, 0.1 µm")
    fanuc_is_b_units: int = Field(description="FANUC detection units at IS-B (1 µm) of the correction")
    fanuc_is_c_units: int = Field(description="FANUC detection units at IS-C (0.1 µm) of the correction")


def command_out(c: CommandSnapshot) -> CommandOut:
    p = c.plc
    return CommandOut(
        value_um=round(c.value_um, 4),
        status=c.status.value,
        at=datetime.fromtimestamp(c.at, tz=UTC),
        hold_s=c.hold_s,
        profile=ProfileOut(
            name=c.profile.name,
            max_step_um=c.profile.max_step_um,
            max_rate_um_s=c.profile.max_rate_um_s,
            limit_um=c.profile.limit_um,
        ),
        correction_um=round(p.correction_um, 4),
        sd43900_temp_comp_abs_value_mm=round(p.sd43900_mm, 7),
        sd42960_tool_temp_comp_mm=round(p.sd42960_tool_axis_mm, 7),
        isg_temp_comp_offset_0_0p1um=p.isg_offset_0p1um,
        fanuc_is_b_units=round(p.correction_um),
        fanuc_is_c_units=round(10.0 * p.correction_um),
    )


class SensitivityOut(BaseModel):
    channel: int
    axial_um_per_c: float = Field(description="axial growth per °C error of this channel, µm/°C")
    radial_um_per_c: float = Field(description="radial growth per °C error of this channel, µm/°C")


class ReferenceIn(BaseModel):
    """``POST /compensation/reference``: every field optional."""

    model_config = {"extra": "forbid"}
    temperature_c: float | None = Field(
        None,
        ge=-50.0,
        le=200.0,
        allow_inf_nan=False,
        strict=True,  # a number: `false` is not 0 °C
        description="the uniform temperature of growth 0, °C (absent: the live field's, now)",
    )
    set_by: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.:@\- ]+$",
        description='who zeroed the controller (absent: "api")',
    )
    source: Literal["api", "cli"] = Field("api", description='"cli": sent by chtc commission zero')


class ReferenceOut(BaseModel):
    temperature_c: float = Field(description="uniform temperature at which the served growth is 0, °C")
    sd_c: float = Field(description="its 1σ, °C (carried in every served CI; 0: given by an operator)")
    at: datetime = Field(description="UTC instant the controller was zeroed")
    source: Literal["api", "cli", "first_start", "config"]
    set_by: str


def reference_out(r: CompensationReference) -> ReferenceOut:
    return ReferenceOut(
        temperature_c=round(r.temperature_c, 4),
        sd_c=round(r.sd_c, 4),
        at=r.at,
        source=r.source,  # type: ignore[arg-type]
        set_by=r.set_by,
    )


class MechanicsParameterOut(BaseModel):
    name: str = Field(description="restraint (0 free, 1 held radially), alpha_shaft, alpha_housing (factors)")
    value: float
    sd: float = Field(description="posterior 1σ")
    ci95: tuple[float, float] = Field(description="posterior 95 % CI")


class MechanicsOut(BaseModel):
    """A commissioning of the growth's mechanics (docs/commissioning.md): what ``/compensation`` uses."""

    at: datetime = Field(description="UTC instant the commissioning was made")
    set_by: str
    source: Literal["api", "cli", "prior"] = Field(
        description='"prior": not commissioned, the mechanics prior updated by probe readings alone'
    )
    parameters: list[MechanicsParameterOut]
    residual_rms_um: float | None = Field(description="the fit's axial residual RMS, µm")
    residual_max_um: float | None = Field(description="the fit's axial residual max |·|, µm")
    explained: bool = Field(description="the fit's verdict: the model explains the test")
    sources_sha256: dict[str, str] = Field(description="SHA-256 of the test's files by role")
    probe_readings_absorbed: int = Field(
        0,
        description="probe readings absorbed since (POST /compensation/measurements): the posterior "
        "includes them",
    )


def mechanics_out(c: MechanicsCalibration) -> MechanicsOut:
    sd = c.sd
    return MechanicsOut(
        at=c.at,
        set_by=c.set_by,
        source=c.source,  # type: ignore[arg-type]
        parameters=[
            MechanicsParameterOut(
                name=n,
                value=round(float(v), 6),
                sd=round(float(s), 6),
                ci95=(round(float(v - 1.959963984540054 * s), 6), round(float(v + 1.959963984540054 * s), 6)),
            )
            for n, v, s in zip(MECH_PARAMS, c.x, sd, strict=True)
        ],
        residual_rms_um=None if not math.isfinite(c.residual_rms_um) else round(c.residual_rms_um, 4),
        residual_max_um=None if not math.isfinite(c.residual_max_um) else round(c.residual_max_um, 4),
        explained=c.explained,
        sources_sha256=dict(c.sources),
        probe_readings_absorbed=int(c.report.get("probe_readings_absorbed", 0)),
    )


class MeasurementIn(BaseModel):
    """``POST /compensation/measurements``: a probe reading (a tool setter, a probe on an artefact) of the
    tool's axial position relative to the commissioned zero (docs/commissioning.md, "Probe measurements")."""

    model_config = {"extra": "forbid"}
    at: datetime = Field(description="UTC ISO-8601 instant of the reading (Z or +00:00), not in the future")
    axial_um: float = Field(
        ge=-10_000.0,
        le=10_000.0,
        allow_inf_nan=False,
        description="axial growth measured, µm, + towards the tool",
    )
    sd_um: float = Field(gt=0.0, le=1000.0, allow_inf_nan=False, description="the reading's 1σ, µm")
    set_by: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.:@\- ]+$",
        description='who sent it (absent: "api")',
    )

    @field_validator("at")
    @classmethod
    def _utc(cls, v: datetime) -> datetime:
        off = v.utcoffset()
        if off is None or off.total_seconds() != 0.0:
            raise ValueError("must be UTC (end it with Z or +00:00)")
        return v


class MeasurementOut(BaseModel):
    id: int | None = Field(description="stored row (null: not stored yet: the writer is asynchronous)")
    at: datetime
    axial_um: float
    sd_um: float
    predicted_um: float = Field(description="the served growth at `at` before the reading, µm")
    sigma_um: float = Field(description="1σ of the predicted reading (growth CI and the reading's sd), µm")
    innovation_um: float = Field(description="reading − predicted, µm")
    sigma_ratio: float = Field(description="|innovation| / sigma_um")
    accepted: bool = Field(
        description="absorbed into the mechanics and the fixture offset; false: beyond "
        "compensation.probe_gate_sigma"
    )
    offset_step: bool = Field(
        False,
        description="absorbed as a step of the fixture offset: beyond the gate, like the reading before it "
        'with a consistent innovation (docs/commissioning.md, "Probe measurements")',
    )
    message: str
    set_by: str
    source: str


class MeasurementPostOut(MeasurementOut):
    mechanics: MechanicsOut | None = Field(description="the mechanics in use after the reading")


def measurement_out(m: ProbeMeasurement) -> MeasurementOut:
    return MeasurementOut(**_measurement_fields(m))


def _measurement_fields(m: ProbeMeasurement) -> dict[str, Any]:
    msg = (
        f"absorbed as a STEP of the fixture offset: innovation {m.innovation_um:+.2f} µm is "
        f"{m.sigma_ratio:.1f} σ, like the reading before it; the offset was re-estimated"
        if m.offset_step
        else "absorbed: the mechanical posterior, the fixture offset and the served CI updated"
        if m.accepted
        else f"flagged, NOT absorbed: innovation {m.innovation_um:+.2f} µm is {m.sigma_ratio:.1f} σ "
        f"(σ {m.sigma_um:.2f} µm), beyond the gate compensation.probe_gate_sigma: a crash or a tool "
        "change since the last reading? Check the machine; re-commission if its mechanics changed"
    )
    return {
        "id": m.id,
        "at": m.at,
        "axial_um": round(m.axial_um, 4),
        "sd_um": round(m.sd_um, 4),
        "predicted_um": round(m.predicted_um, 4),
        "sigma_um": round(m.sigma_um, 4),
        "innovation_um": round(m.innovation_um, 4),
        "sigma_ratio": round(m.sigma_ratio, 3) if math.isfinite(m.sigma_ratio) else 1e9,
        "accepted": m.accepted,
        "offset_step": m.offset_step,
        "message": msg,
        "set_by": m.set_by,
        "source": m.source,
    }


def measurement_post_out(m: ProbeMeasurement, cal: MechanicsCalibration | None) -> MeasurementPostOut:
    return MeasurementPostOut(**_measurement_fields(m), mechanics=None if cal is None else mechanics_out(cal))


class MechanicsCommissionIn(BaseModel):
    """``POST /compensation/mechanics``: a thermal test, its files' contents (docs/commissioning.md)."""

    model_config = {"extra": "forbid"}
    temperatures_csv: str = Field(
        min_length=1, max_length=64_000_000, description="the temperature CSV (chtc record format), text"
    )
    can_log_base64: str = Field(
        min_length=1, max_length=64_000_000, description="the CAN log, base64 of the file's bytes"
    )
    can_log_format: Literal["blf", "asc", "log", "csv", "trc", "mf4"] = Field(
        "blf", description="the CAN log's format (its file suffix)"
    )
    displacements_csv: str = Field(
        min_length=1,
        max_length=16_000_000,
        description="time (UTC ISO-8601), axial_um, optionally radial_um; empty cells: missing",
    )
    set_by: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.:@\- ]+$",
        description='who ran the test (absent: "api")',
    )
    source: Literal["api", "cli"] = Field("api", description='"cli": sent by chtc commission growth')
    force: bool = Field(
        False, description="store and use the calibration even when the model does not explain the test"
    )


class MechanicsCommissionOut(BaseModel):
    stored: bool = Field(description="the calibration is stored and used by /compensation now")
    mechanics: MechanicsOut
    report: dict[str, Any] = Field(description="the fit's report: parameters with prior/posterior, residuals")


class CompensationOut(VerdictOut):
    """``usable_for_compensation``: the one flag a controller acts on. True when the data are fresh (or the
    DAQ alone is down, status ``predicted``, for at most compensation.max_open_loop_min), the live state has
    converged and is consistent, a reference is stored, the H in use are not older than
    compensation.max_identification_age_min, and the axial growth's 95 % CI half-width is within
    compensation.max_ci95_um. A condition change does not clear it."""

    unit: str = Field("µm", description="unit of every *_um value")
    at: datetime = Field(description="UTC instant of the live field the growth is computed from")
    t_ref_c: float = Field(description="reference temperature (uniform) at which the growth is 0, °C")
    t_ref_at: datetime | None = Field(
        description="UTC instant the compensation zero was set (reference.at); null: none set, the growth is "
        "provisional (the uniform equivalent of the first converged live field) and not usable"
    )
    reference: ReferenceOut | None = Field(
        None, description="the compensation zero in use (GET /compensation/reference); null: none set"
    )
    mechanics: MechanicsOut | None = Field(
        None,
        description="the commissioned mechanics in use (GET /compensation/mechanics); null: the spindle "
        "description's, uncalibrated",
    )
    fixture_offset: FixtureOffsetOut | None = Field(
        None,
        description="the fixture or tool-holder offset the probe readings measured, included in `axial`; "
        "null: no reading absorbed since the commissioning (the growth is over the commissioned zero)",
    )
    axial: GrowthValueOut = Field(description="spindle nose on the axis, + towards the tool")
    radial: GrowthValueOut = Field(description="nose outer diameter, + outwards")
    forecast: GrowthForecastOut
    plc: PlcOut
    command: CommandOut | None = Field(
        None, description="what the controller applies now (docs/design/policy.md); null: not stepped yet"
    )
    sensitivity: list[SensitivityOut] = Field(description="growth per unit temperature error of each sensor")
    identification_id: int | None = Field(
        description="the identification whose H the growth uses (null before the first one: the live state's "
        "guessed H with the widest band; then never usable, reason no_identification)"
    )
    h_w_m2k: list[float] = Field(description="H1-H7 the growth uses (the live state's), W/(m²·K)")
    ambient_c: float = Field(description="the held ambient of the forecast, °C")
    newest_sample_at: datetime | None
    sample_age_s: float | None = Field(description="age of the newest sample at served_at, s")
    served_at: datetime
    sensor_faults: list[SensorFaultOut] = Field(default_factory=list, description=SENSOR_FAULTS_DOC)


def _growth_value(v: Any) -> GrowthValueOut:
    return GrowthValueOut(
        um=round(float(v.um), 4),
        plc_0p1um=int(v.plc_0p1um),
        ci95_um=(round(float(v.ci95_um[0]), 4), round(float(v.ci95_um[1]), 4)),
        std_um=round(float(v.std_um), 4),
        std_field_um=round(float(v.std_field_um), 4),
        std_h_um=round(float(v.std_h_um), 4),
        std_mech_um=round(float(getattr(v, "std_mech_um", 0.0)), 4),
    )


class FixtureOffsetOut(BaseModel):
    """The fixture or tool-holder offset the probe readings measured (docs/commissioning.md, "Probe
    measurements"): included in ``axial`` (its value, and its 1σ in ``axial.std_mech_um``)."""

    um: float = Field(description="the offset, µm, + towards the tool (added to the axial growth)")
    sd_um: float = Field(description="its 1σ, µm")
    ci95_um: tuple[float, float] = Field(description="its 95 % CI, µm")
    readings: int = Field(description="probe readings absorbed since the commissioning")
    steps: int = Field(description="of them absorbed as a step of the offset (two consistent gated readings)")
    at: datetime = Field(description="UTC instant of the last reading absorbed")


def fixture_offset_out(o: FixtureOffset) -> FixtureOffsetOut:
    z = 1.959963984540054
    return FixtureOffsetOut(
        um=round(o.um, 4),
        sd_um=round(o.sd_um, 4),
        ci95_um=(round(o.um - z * o.sd_um, 4), round(o.um + z * o.sd_um, 4)),
        readings=o.readings,
        steps=o.steps,
        at=o.at,
    )


def compensation_out(s: CompensationSnapshot, now: datetime, *, spindle_id: str) -> CompensationOut:
    g, f, p = s.growth, s.growth.forecast, s.plc
    age = None if s.newest_sample_at is None else round((now - s.newest_sample_at).total_seconds(), 3)
    return CompensationOut(
        spindle_id=spindle_id,
        **_verdict(s.verdict),
        unit="µm",
        at=g.at,
        t_ref_c=round(g.t_ref_c, 4),
        t_ref_at=s.reference_at,
        reference=None if s.reference is None else reference_out(s.reference),
        mechanics=None if getattr(s, "mechanics", None) is None else mechanics_out(s.mechanics),  # type: ignore[arg-type]
        fixture_offset=None if s.fixture_offset is None else fixture_offset_out(s.fixture_offset),
        axial=_growth_value(g.axial),
        radial=_growth_value(g.radial),
        forecast=GrowthForecastOut(
            steady_axial=_growth_value(f.steady_axial),
            steady_radial=_growth_value(f.steady_radial),
            tau_s=round(f.tau_s, 1),
            slowest_tau_s=round(f.slowest_tau_s, 1),
            horizons=[
                GrowthHorizonOut(
                    horizon_s=hz,
                    at=g.at + timedelta(seconds=hz),
                    axial=_growth_value(a),
                    radial=_growth_value(r),
                )
                for hz, a, r in zip(f.horizons_s, f.axial, f.radial, strict=True)
            ],
        ),
        plc=PlcOut(
            tool_dir=s.tool_dir,
            correction_um=round(p.correction_um, 4),
            sd43900_temp_comp_abs_value_mm=round(p.sd43900_mm, 7),
            sd43910_temp_comp_slope=p.sd43910_slope,
            sd43920_temp_comp_ref_position_mm=p.sd43920_ref_mm,
            sd42960_tool_temp_comp_mm=round(p.sd42960_tool_axis_mm, 7),
            isg_temp_comp_offset_0_0p1um=p.isg_offset_0p1um,
            isg_temp_comp_coefficient_um_per_m=p.isg_coefficient_um_per_m,
            isg_temp_comp_position_0_0p1um=p.isg_position_0p1um,
        ),
        command=None if s.command is None else command_out(s.command),
        sensitivity=[
            SensitivityOut(channel=c, axial_um_per_c=round(a, 5), radial_um_per_c=round(r, 5))
            for c, a, r in zip(
                s.channels, g.sensitivity_axial_um_per_k, g.sensitivity_radial_um_per_k, strict=True
            )
        ],
        identification_id=s.identification_id,
        h_w_m2k=[round(float(x), 4) for x in g.h],
        ambient_c=round(g.ambient_c, 3),
        newest_sample_at=s.newest_sample_at,
        sample_age_s=age,
        served_at=now,
        sensor_faults=sensor_faults_out(getattr(s, "sensor_faults", ())),
    )


class CompensationSectionOut(SpindleAnswer):
    """The spindle's section deformed by the live field (docs/design/growth.md, 'The deformed section'): draw
    (r + k·u_r, z + k·u_z) for an exaggeration k of your choice next to the undeformed outline."""

    status: ChtcStatus = Field(description="the status of /compensation (its verdict, service.serve.policy)")
    unit: str = Field("µm", description="unit of u_r_um and u_z_um")
    at: datetime = Field(description="UTC instant of the live field the displacement is computed from")
    t_ref_c: float = Field(description="reference temperature (uniform) at which the displacement is 0, °C")
    identification_id: int | None = Field(
        description="the identification whose H the live state uses (null before the first one)"
    )
    nodes_r_m: list[float] = Field(description="outline nodes: radius, m")
    nodes_z_m: list[float] = Field(description="outline nodes: axial position, m")
    edges: list[tuple[int, int]] = Field(description="outline edges (every part's boundary): node indices")
    u_r_um: list[float] = Field(description="radial displacement of each outline node, µm")
    u_z_um: list[float] = Field(description="axial displacement of each outline node, µm (0 at the mount)")
    max_abs_um: float = Field(description="largest |u| over the outline, µm")
    newest_sample_at: datetime | None
    sample_age_s: float | None = Field(description="age of the newest sample at served_at, s")
    served_at: datetime


def compensation_section_out(s: SectionSnapshot, now: datetime, *, spindle_id: str) -> CompensationSectionOut:
    age = None if s.newest_sample_at is None else round((now - s.newest_sample_at).total_seconds(), 3)
    u = np.asarray(s.u_um, dtype=float)
    return CompensationSectionOut(
        spindle_id=spindle_id,
        status=s.status,
        unit="µm",
        at=s.at,
        t_ref_c=round(s.t_ref_c, 4),
        identification_id=s.identification_id,
        nodes_r_m=np.round(s.nodes_rz[:, 0], 7).tolist(),
        nodes_z_m=np.round(s.nodes_rz[:, 1], 7).tolist(),
        edges=[(int(a), int(b)) for a, b in s.edges],
        u_r_um=np.round(u[0], 4).tolist(),
        u_z_um=np.round(u[1], 4).tolist(),
        max_abs_um=round(float(np.hypot(u[0], u[1]).max()), 4) if u.size else 0.0,
        newest_sample_at=s.newest_sample_at,
        sample_age_s=age,
        served_at=now,
    )
