"""What the MQTT outlet publishes: the metric catalogue and the values of one instant (pure).

Every value comes from the reader the REST API reads (``/api/v1/chtc``, ``/api/v1/compensation``, the
health), so MQTT serves the same numbers with the same verdict. A value's quality follows the verdict of the
snapshot it belongs to (``quality_of``); its time is the data's time (the newest sample's, the growth's
``at``), not the publishing time.

Quality (docs/integration.md, "MQTT"): Sparkplug B has three codes (0 bad, 192 good, 500 stale) where
OPC UA has Good/Uncertain/Bad with sub-codes, so Sparkplug's ``Quality`` says only whether the value is
there, and the served ``Status/Usable`` and ``Status/Code`` say whether to act on it:

=============================================  ===========  ================  ===========================
served status (``ChtcStatus``)                  JSON ``q``   Sparkplug Quality OPC UA (for comparison)
=============================================  ===========  ================  ===========================
fresh                                           good         192 (no property) Good
identifying, predicted, at-bound                uncertain    192 (no property) Uncertain_*
stale (data lost)                               uncertain    500 stale         Uncertain_NoCommunication…
no-data                                         bad          0 bad             Bad_WaitingForInitialData
value absent (NaN, none yet)                    bad          0 bad (is_null)   Bad_WaitingForInitialData
=============================================  ===========  ================  ===========================

An H that is prior-dominated or at a bound of the search box is ``uncertain`` in JSON (192 in Sparkplug;
its ``Identified`` and ``PriorDominated`` flags say so).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Protocol

from service.contracts.errors import NoDataYetError
from service.contracts.health import HealthSnapshot
from service.contracts.snapshots import ZONE_NAMES, ChtcSnapshot, CompensationSnapshot, ConditionSnapshot
from service.contracts.verdict import ChtcStatus
from service.errors import ServiceError
from service.serve.catalogue import DEVICES, PointDef, by_mqtt

__all__ = [
    "ALIASES",
    "CATALOGUE",
    "DEVICES",
    "DataType",
    "MetricDef",
    "Point",
    "Quality",
    "ServedReader",
    "Value",
    "catalogue_index",
    "quality_of",
    "read_points",
]

Value = float | int | bool | str | datetime | None


class DataType(enum.IntEnum):
    """Sparkplug B datatype ids (Eclipse Sparkplug 3.0, "Data Types")."""

    INT32 = 3
    INT64 = 4
    UINT32 = 7
    UINT64 = 8
    DOUBLE = 10
    BOOLEAN = 11
    STRING = 12
    DATETIME = 13


class Quality(enum.IntEnum):
    """A value's quality; the numbers are Sparkplug's ``Quality`` property."""

    BAD = 0
    GOOD = 192
    UNCERTAIN = 193  # never sent as a Sparkplug code (sent as GOOD: Sparkplug has no "uncertain")
    STALE = 500

    @property
    def sparkplug(self) -> int:
        return int(Quality.GOOD) if self is Quality.UNCERTAIN else int(self)

    @property
    def json(self) -> str:
        return {Quality.GOOD: "good", Quality.UNCERTAIN: "uncertain", Quality.STALE: "uncertain"}.get(
            self, "bad"
        )


@dataclass(frozen=True)
class MetricDef:
    """One published metric: its name (Sparkplug metric name; JSON topic levels), datatype, unit (engUnit;
    None: none), range (engLow/engHigh; None: none) and the deadband it changes by (``MqttDeadbands``'s
    field name; None: any change)."""

    name: str
    datatype: DataType
    unit: str | None = None
    low: float | None = None
    high: float | None = None
    deadband: str | None = None
    doc: str = ""


@dataclass(frozen=True)
class Point:
    """A metric's value at an instant: ``value`` None when absent; ``t`` the data's time (UTC)."""

    value: Value
    quality: Quality
    t: datetime


class ServedReader(Protocol):
    """What the outlet reads: the served-value reader of ``service.serve`` (the methods REST serves)."""

    def chtc(self) -> ChtcSnapshot | None: ...

    def compensation(self) -> CompensationSnapshot | None: ...

    def condition(self) -> ConditionSnapshot: ...

    def health(self) -> HealthSnapshot: ...


# the deadband (``MqttDeadbands``'s field) of a number, by its unit (UNECE code)
DEADBANDS: dict[str, str] = {
    "D55": "h_w_m2k",
    "4H": "growth_um",
    "MMT": "mm",
    "C94": "speed_rpm",
    "NU": "torque_nm",
    "CEL": "temperature_c",
    "SEC": "age_s",
}


def _metric(p: PointDef) -> MetricDef:
    lo, hi = (None, None) if p.range is None else p.range
    return MetricDef(
        name=str(p.mqtt),
        datatype=DataType[p.vtype.upper()],
        unit=p.symbol,
        low=lo,
        high=hi,
        deadband=None if p.unit is None else DEADBANDS[p.unit],
        doc=p.description,
    )


# The Sparkplug aliases: the metric names in alias order (1-based; ``SparkplugSession``). Append only, so
# an alias keeps its metric across versions; the catalogue declares what each one is.
ALIASES: tuple[str, ...] = (
    "Status/Code",
    "Status/Usable",
    "Status/Reason",
    "Status/NewestSampleTime",
    "Status/SampleAge",
    "Status/Heartbeat",
    "Chtc/Status",
    "Chtc/Usable",
    "Chtc/Reason",
    "Chtc/IdentificationId",
    *(
        f"Chtc/{z}{leaf}"
        for z in ZONE_NAMES
        for leaf in ("", "/CiLow", "/CiHigh", "/Identified", "/PriorDominated")
    ),
    "Condition/Id",
    "Condition/State",
    "Condition/Speed",
    "Condition/Torque",
    "Condition/Ambient",
    *(f"Growth/{g}{leaf}" for g in ("Axial", "Radial", "SteadyAxial") for leaf in ("", "/CiLow", "/CiHigh")),
    "Controller/CorrectionUm",
    "Controller/SD43900",
    "Controller/SD42960",
    "Controller/IsgOffset",
    "Controller/ToolDir",
    *(f"Health/{d}" for d in DEVICES),
    # the command value (issue 42), after the rest: earlier aliases keep their numbers
    "Controller/Command",
    "Controller/CommandStatus",
    "Controller/CommandSD43900",
    "Controller/CommandIsgOffset",
    "Controller/CommandFanucUnits",
)
# the metrics in alias order, rendered from the point catalogue (``service.serve.catalogue``)
CATALOGUE: tuple[MetricDef, ...] = tuple(_metric(by_mqtt()[name]) for name in ALIASES)


def catalogue_index() -> dict[str, MetricDef]:
    return {m.name: m for m in CATALOGUE}


def quality_of(status: ChtcStatus) -> Quality:
    """The quality of a value served with ``status`` (module docstring's table)."""
    if status is ChtcStatus.FRESH:
        return Quality.GOOD
    if status is ChtcStatus.STALE:
        return Quality.STALE
    if status is ChtcStatus.NO_DATA:
        return Quality.BAD
    return Quality.UNCERTAIN


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _verdict_points(
    prefix: str, status: ChtcStatus, usable: bool, reason: str | None, t: datetime
) -> dict[str, Point]:
    q = Quality.GOOD  # the status itself is always known
    return {
        f"{prefix}/Code" if prefix == "Status" else f"{prefix}/Status": Point(status.value, q, t),
        f"{prefix}/Usable": Point(bool(usable), q, t),
        f"{prefix}/Reason": Point(reason or "", q, t),
    }


def _chtc_points(snap: ChtcSnapshot | None, now: datetime) -> dict[str, Point]:
    if snap is None:
        t = now
        out = _verdict_points("Chtc", ChtcStatus.NO_DATA, False, "no_identification", t)
        out["Chtc/IdentificationId"] = Point(None, Quality.BAD, t)
        for z in ZONE_NAMES:
            for leaf in ("", "/CiLow", "/CiHigh", "/Identified", "/PriorDominated"):
                out[f"Chtc/{z}{leaf}"] = Point(None, Quality.BAD, t)
        return out
    t = snap.newest_sample_at or snap.identified_at
    reason = None if snap.verdict.reason is None else snap.verdict.reason.value
    out = _verdict_points("Chtc", snap.status, snap.usable_for_compensation, reason, t)
    base = quality_of(snap.status)
    out["Chtc/IdentificationId"] = Point(int(snap.identification_id), base, t)
    for i, z in enumerate(snap.zones):
        doubtful = bool(snap.prior_dominated[i]) or bool(snap.at_bound[i])
        q = Quality.UNCERTAIN if base is Quality.GOOD and doubtful else base
        for leaf, v in (("", snap.h[i]), ("/CiLow", snap.ci95_lo[i]), ("/CiHigh", snap.ci95_hi[i])):
            value = _num(v)
            out[f"Chtc/{z}{leaf}"] = Point(value, q if value is not None else Quality.BAD, t)
        out[f"Chtc/{z}/Identified"] = Point(bool(snap.identified[i]), base, t)
        out[f"Chtc/{z}/PriorDominated"] = Point(bool(snap.prior_dominated[i]), base, t)
    return out


def _growth_points(snap: CompensationSnapshot | None, now: datetime) -> dict[str, Point]:
    names = [m.name for m in CATALOGUE if m.name.startswith(("Growth/", "Controller/"))]
    if snap is None:
        out = {n: Point(None, Quality.BAD, now) for n in names}
        out |= _verdict_points("Status", ChtcStatus.NO_DATA, False, "no_data", now)
        out["Status/NewestSampleTime"] = Point(None, Quality.BAD, now)
        out["Status/SampleAge"] = Point(None, Quality.BAD, now)
        return out
    g, p = snap.growth, snap.plc
    t = g.at
    q = quality_of(snap.status)
    reason = None if snap.verdict.reason is None else snap.verdict.reason.value
    out = _verdict_points("Status", snap.status, snap.usable_for_compensation, reason, t)
    newest = snap.newest_sample_at
    out["Status/NewestSampleTime"] = Point(newest, Quality.GOOD if newest else Quality.BAD, t)
    age = None if newest is None else max(0.0, (now - newest).total_seconds())
    out["Status/SampleAge"] = Point(age, Quality.GOOD if age is not None else Quality.BAD, now)
    for name, v in (("Axial", g.axial), ("Radial", g.radial), ("SteadyAxial", g.forecast.steady_axial)):
        out[f"Growth/{name}"] = Point(_num(v.um), q, t)
        out[f"Growth/{name}/CiLow"] = Point(_num(v.ci95_um[0]), q, t)
        out[f"Growth/{name}/CiHigh"] = Point(_num(v.ci95_um[1]), q, t)
    out["Controller/CorrectionUm"] = Point(_num(p.correction_um), q, t)
    out["Controller/SD43900"] = Point(_num(p.sd43900_mm), q, t)
    out["Controller/SD42960"] = Point(_num(p.sd42960_tool_axis_mm), q, t)
    out["Controller/IsgOffset"] = Point(int(p.isg_offset_0p1um), q, t)
    out["Controller/ToolDir"] = Point(int(snap.tool_dir), Quality.GOOD, t)
    cmd = snap.command
    if cmd is not None:  # always the value to apply: good; its status says what it does
        at, c = datetime.fromtimestamp(cmd.at, tz=UTC), cmd.plc
        out["Controller/Command"] = Point(_num(cmd.value_um), Quality.GOOD, at)
        out["Controller/CommandStatus"] = Point(str(cmd.status.value), Quality.GOOD, at)
        out["Controller/CommandSD43900"] = Point(_num(c.sd43900_mm), Quality.GOOD, at)
        out["Controller/CommandIsgOffset"] = Point(int(c.isg_offset_0p1um), Quality.GOOD, at)
        out["Controller/CommandFanucUnits"] = Point(round(c.correction_um), Quality.GOOD, at)
    else:
        for n in ("Command", "CommandStatus", "CommandSD43900", "CommandIsgOffset", "CommandFanucUnits"):
            out[f"Controller/{n}"] = Point(None, Quality.BAD, t)
    return out


def _condition_points(reader: ServedReader, now: datetime) -> dict[str, Point]:
    try:
        c = reader.condition()
    except NoDataYetError:
        return {
            n: Point(None, Quality.BAD, now)
            for n in ("Condition/Id", "Condition/State", "Condition/Speed", "Condition/Torque")
        } | {"Condition/Ambient": Point(None, Quality.BAD, now)}
    q, t = Quality.GOOD, c.since
    return {
        "Condition/Id": Point(int(c.id), q, t),
        "Condition/State": Point(c.state.value, q, t),
        "Condition/Speed": Point(_num(c.speed_rpm), q, t),
        "Condition/Torque": Point(_num(c.torque_nm), q, t),
        "Condition/Ambient": Point(_num(c.ambient_c), q, t),
    }


def _health_points(health: HealthSnapshot) -> dict[str, Point]:
    seen = {d.name: d for d in health.devices}
    out = {}
    for name in DEVICES:
        d = seen.get(name)
        out[f"Health/{name}"] = Point(
            None if d is None else d.status.value, Quality.GOOD if d else Quality.BAD, health.t
        )
    return out


def read_points(reader: ServedReader, *, now: datetime, heartbeat: int) -> dict[str, Point]:
    """Every catalogue metric's value now, read from ``reader`` (may block: ``compensation()`` can build the
    growth's condition terms, ~0.3 s; call it off the event loop)."""
    try:
        comp = reader.compensation()
    except ServiceError:  # no growth model (REST answers 503 with the cause): served as none
        comp = None
    out = _growth_points(comp, now)
    out |= _chtc_points(reader.chtc(), now)
    out |= _condition_points(reader, now)
    out |= _health_points(reader.health())
    out["Status/Heartbeat"] = Point(heartbeat % 2**32, Quality.GOOD, now)
    return out


def changed(
    defs: Sequence[MetricDef],
    new: Mapping[str, Point],
    last: Mapping[str, Point],
    deadbands: Mapping[str, float],
) -> list[str]:
    """Names (in catalogue order) whose point differs from ``last`` beyond its deadband: a number moved by
    more than its deadband, anything else changed, or its quality changed."""
    out = []
    for m in defs:
        p = new.get(m.name)
        if p is None:
            continue
        old = last.get(m.name)
        if old is None or old.quality != p.quality or _moved(old.value, p.value, deadbands, m.deadband):
            out.append(m.name)
    return out


def _moved(old: Value, new: Value, deadbands: Mapping[str, float], key: str | None) -> bool:
    numbers = (int, float)
    if isinstance(old, numbers) and isinstance(new, numbers) and not isinstance(old, bool):
        if isinstance(new, bool):
            return old != new
        band = deadbands.get(key or "other", 0.0)
        return abs(float(new) - float(old)) > band or (band == 0.0 and new != old)
    return old != new
