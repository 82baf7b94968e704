"""The OPC UA address space as data, and the values of one reader (pure: no asyncua here).

Every variable is a :class:`Var`: its path below the spindle object (``Growth.Axial`` -> NodeId
``ns=<ours>;s=<spindle>.Growth.Axial``; ``<spindle>``: ``opcua.spindle``, unset: ``spindle.id``), its OPC UA
data type, scalar or 1-D array (S7-1500 clients resolve no structures), its UNECE unit and its EURange.
:func:`render` evaluates a ``ViewReader`` at ``now`` into one :class:`Reading` per variable: the value, its
StatusCode (``service.serve.opcua.status``) and its SourceTimestamp (the data's time: the sample's, the
growth's instant, the identification's end; the evaluation's for the status and device nodes, which describe
the service now).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from service.contracts.command import CommandSnapshot
from service.contracts.errors import NoDataYetError
from service.contracts.snapshots import ZONE_NAMES, ChtcSnapshot, CompensationSnapshot, SensorReading
from service.contracts.verdict import ChtcStatus, DataCode, Reason, Verdict
from service.errors import ServiceError
from service.serve.catalogue import PER_SENSOR, POINTS, UNITS, VType
from service.serve.opcua.status import UaStatus, lost_since, status_of, worst

if TYPE_CHECKING:
    from service.serve.reader import ViewReader

__all__ = [
    "MODEL_PUBLISHED",
    "MODEL_VERSION",
    "UNECE",
    "UNITS_NAMESPACE",
    "VARS",
    "Reading",
    "Var",
    "render",
    "unit_id",
]

UNITS_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"
UNECE = UNITS  # UNECE Rec. 20 code -> (display name, description) (SPEC §7; service.serve.catalogue)
NAN = float("nan")
EPOCH = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's "no time" (DateTime 0)
# The address space's model version (the NodeSet2's <Models>): raise it, and the date, whenever a variable,
# a method, a unit or a range changes, so an engineering tool sees that its import is out of date.
MODEL_VERSION = "2.0.0"
MODEL_PUBLISHED = datetime(2026, 11, 29, tzinfo=UTC)


def unit_id(code: str) -> int:
    """The EUInformation UnitId of a UNECE code: its ASCII bytes as one big-endian integer ("CEL" ->
    0x43454C)."""
    out = 0
    for ch in code.strip():
        out = (out << 8) | ord(ch)
    return out


@dataclass(frozen=True, kw_only=True)
class Var:
    """One variable: ``path`` below the spindle object (``Group.Name``), type, shape (``length`` > 0: a 1-D
    array of that many, -1: a 1-D array of any length; 0: a scalar), unit, range, description."""

    path: str
    vtype: VType
    length: int = 0
    unit: str | None = None
    range: tuple[float, float] | None = None
    description: str = ""

    @property
    def group(self) -> str:
        return self.path.split(".", 1)[0]

    @property
    def name(self) -> str:
        return self.path.split(".", 1)[1]

    @property
    def analog(self) -> bool:
        return self.unit is not None


@dataclass(frozen=True)
class Reading:
    """One variable's value (a scalar or a list), StatusCode and SourceTimestamp (None: the server's now)."""

    value: object
    status: UaStatus
    source_time: datetime | None


GROUPS: dict[str, str] = {
    "Status": "Whether the compensation may be applied now, why not, and liveness (Heartbeat, SampleAge)",
    "H": "Convective heat transfer coefficients H1-H7 of the spindle's zones, their 95 % CIs and flags",
    "Condition": "The operating condition as the change detector sees it",
    "Temperatures": "The sensor channels at the newest sample: measured and predicted by the live state",
    "Growth": "Thermal growth at the spindle nose (axial + towards the tool), 95 % CIs and forecast",
    "Controller": "Values a PLC writes to the CNC's temperature compensation (docs/integration.md)",
    "Devices": "Health of the service's devices (Modbus DAQ, CAN, database, worker, filter, ...)",
}


def _vars(n_sensors: int) -> tuple[Var, ...]:
    """The address space's variables, rendered from the point catalogue (``service.serve.catalogue``)."""
    return tuple(
        Var(
            path=p.opcua,
            vtype=p.vtype,
            length=n_sensors if p.length == PER_SENSOR else p.length,
            unit=p.unit,
            range=p.range,
            description=p.description,
        )
        for p in POINTS
        if p.opcua is not None
    )


VARS: tuple[Var, ...] = _vars(32)


def variables(n_sensors: int = 32) -> tuple[Var, ...]:
    """The variables for a spindle with ``n_sensors`` channels (32: ``VARS``)."""
    return VARS if n_sensors == 32 else _vars(n_sensors)


# --- values ---------------------------------------------------------------------------------------------
_NO_DATA = Verdict(ChtcStatus.NO_DATA, False, Reason.NO_DATA, "no sample acquired yet")
_REFERENCE_ONLY = frozenset(
    {
        Reason.NO_REFERENCE,
        Reason.MECHANICS_UNCALIBRATED,
        Reason.NO_OFFSET_BASELINE,
        Reason.IDENTIFICATION_OLD,
        Reason.CI_TOO_WIDE,
        Reason.NO_IDENTIFICATION,
    }
)


def render(
    reader: ViewReader, *, now: datetime, bad_after_s: float, heartbeat: int, n_sensors: int = 32
) -> dict[str, Reading]:
    """Every variable's reading for ``reader`` at ``now`` (see the module docstring)."""
    v = reader.view
    try:
        comp = reader.compensation()
    except ServiceError:  # the growth model is unavailable (NotReadyError): as REST's 503, no values
        comp = None
    chtc = reader.chtc()
    newest = None if v.newest is None else v.newest.t
    problems = {p.code for p in v.data_problems(now)} if newest is not None else set()
    lost = lost_since(v.last_good_daq_t, v.last_good_can_t, newest, now=now)
    comp_verdict = _NO_DATA if comp is None or newest is None else comp.verdict
    comp_code = status_of(comp_verdict, lost_s=lost, bad_after_s=bad_after_s)
    out: dict[str, Reading] = {}
    out.update(_status(comp, chtc, comp_verdict, comp_code, newest=newest, now=now, heartbeat=heartbeat))
    out.update(_h(chtc, newest=newest, lost_s=lost, bad_after_s=bad_after_s))
    out.update(_condition(reader, problems, now=now, bad_after_s=bad_after_s))
    out.update(_temperatures(reader, comp_verdict, problems, now=now, bad_after_s=bad_after_s, n=n_sensors))
    out.update(_growth(comp, comp_code))
    out.update(_devices(reader, now=now))
    return out


def _status(
    comp: CompensationSnapshot | None,
    chtc: ChtcSnapshot | None,
    verdict: Verdict,
    code: UaStatus,
    *,
    newest: datetime | None,
    now: datetime,
    heartbeat: int,
) -> dict[str, Reading]:
    good = UaStatus.GOOD
    hv = None if chtc is None else chtc.verdict
    waiting = UaStatus.BAD_WAITING_FOR_INITIAL_DATA

    def now_(x: object) -> Reading:
        return Reading(x, good, now)

    return {
        "Status.Usable": now_(bool(verdict.usable) and comp is not None),
        "Status.Code": now_(int(code)),
        "Status.Text": now_(verdict.status.value),
        "Status.Reason": now_("" if verdict.reason is None else verdict.reason.value),
        "Status.Detail": now_(verdict.text or ""),
        "Status.Action": now_(verdict.action or ""),
        "Status.HUsable": now_(hv is not None and bool(hv.usable)),
        "Status.HText": now_(ChtcStatus.NO_DATA.value if hv is None else hv.status.value),
        "Status.HReason": now_(
            Reason.NO_IDENTIFICATION.value if hv is None else ("" if hv.reason is None else hv.reason.value)
        ),
        "Status.NewestSampleTime": Reading(newest or EPOCH, good if newest else waiting, newest or now),
        "Status.SampleAge": Reading(
            NAN if newest is None else max(0.0, (now - newest).total_seconds()),
            good if newest else waiting,
            now,
        ),
        "Status.Heartbeat": now_(heartbeat & 0xFFFFFFFF),
    }


def _h(chtc: ChtcSnapshot | None, *, newest: datetime | None, lost_s: float, bad_after_s: float) -> dict:
    if chtc is None:
        code = UaStatus.BAD_WAITING_FOR_INITIAL_DATA
        out = {f"H.{z}": Reading(NAN, code, None) for z in ZONE_NAMES}
        for name, val in (("Values", NAN), ("CiLow95", NAN), ("CiHigh95", NAN)):
            out[f"H.{name}"] = Reading([val] * 7, code, None)
        for name in ("Identified", "PriorDominated", "AtBound"):
            out[f"H.{name}"] = Reading([False] * 7, code, None)
        out["H.IdentifiedAt"] = Reading(EPOCH, code, None)
        out["H.IdentificationId"] = Reading(0, code, None)
        return out
    verdict = chtc.verdict if newest is not None else _NO_DATA
    code = status_of(verdict, lost_s=lost_s, bad_after_s=bad_after_s)
    at = chtc.identified_at
    h, lo, hi = _floats(chtc.h), _floats(chtc.ci95_lo), _floats(chtc.ci95_hi)
    ident, prior, bound = _bools(chtc.identified), _bools(chtc.prior_dominated), _bools(chtc.at_bound)
    out = {}
    for i, z in enumerate(ZONE_NAMES):
        weak = bound[i] or prior[i] or not ident[i]
        out[f"H.{z}"] = Reading(
            h[i], worst(code, UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE) if weak else code, at
        )
    out["H.Values"] = Reading(h, code, at)
    out["H.CiLow95"] = Reading(lo, code, at)
    out["H.CiHigh95"] = Reading(hi, code, at)
    good = UaStatus.GOOD
    out["H.Identified"] = Reading(ident, good, at)
    out["H.PriorDominated"] = Reading(prior, good, at)
    out["H.AtBound"] = Reading(bound, good, at)
    out["H.IdentifiedAt"] = Reading(at, good, at)
    out["H.IdentificationId"] = Reading(int(chtc.identification_id), good, at)
    return out


def _lost_code(lost: bool, last_good: datetime | None, *, now: datetime, bad_after_s: float) -> UaStatus:
    if not lost:
        return UaStatus.GOOD
    if lost_since(last_good, now=now) > bad_after_s:
        return UaStatus.BAD_NO_COMMUNICATION
    return UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE


def _condition(reader: ViewReader, problems: set[DataCode], *, now: datetime, bad_after_s: float) -> dict:
    v = reader.view
    cond = v.condition
    at = None if v.newest is None else v.newest.t
    if cond is None:
        code = UaStatus.BAD_WAITING_FOR_INITIAL_DATA
        vals: tuple[object, ...] = (NAN, NAN, NAN, "", EPOCH, 0)
    else:
        lost = bool(problems & {DataCode.CAN_NO_GOOD_DATA, DataCode.NO_SAMPLE, DataCode.CORE_BEHIND})
        code = _lost_code(lost, v.last_good_can_t, now=now, bad_after_s=bad_after_s)
        vals = (
            float(cond.speed_rpm),
            float(cond.torque_nm),
            float(cond.ambient_c),
            cond.state.value,
            cond.since,
            int(cond.id),
        )
    names = ("SpeedRpm", "TorqueNm", "AmbientC", "State", "Since", "Id")
    return {f"Condition.{n}": Reading(x, code, at) for n, x in zip(names, vals, strict=True)}


def _temperatures(
    reader: ViewReader,
    comp_verdict: Verdict,
    problems: set[DataCode],
    *,
    now: datetime,
    bad_after_s: float,
    n: int,
) -> dict:
    v = reader.view
    try:
        sensors: Sequence[SensorReading] = reader.sensors()
    except NoDataYetError:
        sensors = ()
    if not sensors:
        code = UaStatus.BAD_WAITING_FOR_INITIAL_DATA
        nan = [NAN] * n
        return {
            "Temperatures.Measured": Reading(nan, code, None),
            "Temperatures.Predicted": Reading(nan, code, None),
            "Temperatures.PredictedSd": Reading(nan, code, None),
            "Temperatures.ChannelOk": Reading([False] * n, code, None),
            "Temperatures.Quality": Reading(["no_data"] * n, code, None),
            "Temperatures.Names": Reading([""] * n, code, None),
        }
    at = sensors[0].t
    lost = bool(problems & {DataCode.DAQ_NO_GOOD_DATA, DataCode.NO_SAMPLE, DataCode.CORE_BEHIND})
    measured_code = _lost_code(lost, v.last_good_daq_t, now=now, bad_after_s=bad_after_s)
    live = v.live
    if live is None:
        pred_code = UaStatus.BAD_WAITING_FOR_INITIAL_DATA
    elif comp_verdict.reason in _REFERENCE_ONLY:  # about the growth's zero and H, not the live state
        pred_code = (
            UaStatus.UNCERTAIN_SUB_NORMAL if comp_verdict.status is ChtcStatus.PREDICTED else UaStatus.GOOD
        )
    else:
        pred_code = status_of(
            comp_verdict, lost_s=lost_since(v.last_good_daq_t, now=now), bad_after_s=bad_after_s
        )
    good = UaStatus.GOOD
    return {
        "Temperatures.Measured": Reading([_f(s.measured_c) for s in sensors], measured_code, at),
        "Temperatures.Predicted": Reading([_f(s.predicted_c) for s in sensors], pred_code, at),
        "Temperatures.PredictedSd": Reading([_f(s.predicted_sd_c) for s in sensors], pred_code, at),
        "Temperatures.ChannelOk": Reading(
            [s.quality == "ok" and s.measured_c is not None for s in sensors], good, at
        ),
        "Temperatures.Quality": Reading([s.quality for s in sensors], good, at),
        "Temperatures.Names": Reading([s.name for s in sensors], good, at),
    }


def _growth(comp: CompensationSnapshot | None, code: UaStatus) -> dict:
    names = (
        "Axial",
        "AxialSd",
        "AxialCiLow95",
        "AxialCiHigh95",
        "Radial",
        "RadialCiLow95",
        "RadialCiHigh95",
        "SteadyAxial",
        "SteadyAxialCiLow95",
        "SteadyAxialCiHigh95",
        "TauS",
        "ReferenceC",
    )
    ctrl = ("CorrectionUm", "SD43900Mm", "SD42960Mm")
    if comp is None:
        out = {f"Growth.{n}": Reading(NAN, code, None) for n in names}
        out["Growth.ForecastHorizons"] = Reading([], code, None)
        out["Growth.ForecastAxial"] = Reading([], code, None)
        out.update({f"Controller.{n}": Reading(NAN, code, None) for n in ctrl})
        out["Controller.IsgOffset0p1um"] = Reading(0, code, None)
        out["Controller.ToolDir"] = Reading(-1, UaStatus.GOOD, None)
        out.update(_command(None, code))
        return out
    g = comp.growth
    ax, rad, steady = g.axial, g.radial, g.forecast.steady_axial
    vals = (
        ax.um,
        ax.std_um,
        ax.ci95_um[0],
        ax.ci95_um[1],
        rad.um,
        rad.ci95_um[0],
        rad.ci95_um[1],
        steady.um,
        steady.ci95_um[0],
        steady.ci95_um[1],
        g.forecast.tau_s,
        g.t_ref_c,
    )
    at = g.at
    out = {f"Growth.{n}": Reading(_f(x), code, at) for n, x in zip(names, vals, strict=True)}
    out["Growth.ForecastHorizons"] = Reading(_floats(g.forecast.horizons_s), code, at)
    out["Growth.ForecastAxial"] = Reading([_f(x.um) for x in g.forecast.axial], code, at)
    plc = comp.plc
    out["Controller.CorrectionUm"] = Reading(_f(plc.correction_um), code, at)
    out["Controller.SD43900Mm"] = Reading(_f(plc.sd43900_mm), code, at)
    out["Controller.SD42960Mm"] = Reading(_f(plc.sd42960_tool_axis_mm), code, at)
    out["Controller.IsgOffset0p1um"] = Reading(int(plc.isg_offset_0p1um), code, at)
    out["Controller.ToolDir"] = Reading(int(comp.tool_dir), UaStatus.GOOD, at)
    out.update(_command(comp.command, code))
    return out


def _command(cmd: CommandSnapshot | None, code: UaStatus) -> dict:
    """The command value's nodes: Good whenever a command was stepped (it is always the value to apply; its
    status says what it does), ``code`` (the growth's) when there is none."""
    names = ("CommandUm", "CommandCorrectionUm", "CommandSD43900Mm")
    if cmd is None:
        out = {f"Controller.{n}": Reading(NAN, code, None) for n in names}
        out["Controller.CommandStatus"] = Reading("none", code, None)
        out["Controller.CommandIsgOffset0p1um"] = Reading(0, code, None)
        out["Controller.CommandFanucUnits"] = Reading(0, code, None)
        return out
    at = datetime.fromtimestamp(cmd.at, tz=UTC)
    good, p = UaStatus.GOOD, cmd.plc
    vals = (cmd.value_um, p.correction_um, p.sd43900_mm)
    out = {f"Controller.{n}": Reading(_f(x), good, at) for n, x in zip(names, vals, strict=True)}
    out["Controller.CommandStatus"] = Reading(str(cmd.status.value), good, at)
    out["Controller.CommandIsgOffset0p1um"] = Reading(int(p.isg_offset_0p1um), good, at)
    out["Controller.CommandFanucUnits"] = Reading(round(p.correction_um), good, at)
    return out


def _devices(reader: ViewReader, *, now: datetime) -> dict:
    health = reader.health()
    devs = list(health.devices)
    good = UaStatus.GOOD
    return {
        "Devices.Names": Reading([d.name for d in devs], good, now),
        "Devices.Status": Reading([d.status.value for d in devs], good, now),
        "Devices.Ok": Reading([d.status.value == "ok" for d in devs], good, now),
        "Devices.AgeS": Reading([_f(d.age_s) for d in devs], good, now),
        "Devices.ModelLoaded": Reading(bool(health.model_loaded), good, now),
    }


def _f(x: float | None) -> float:
    return NAN if x is None or not math.isfinite(float(x)) else float(x)


def _floats(xs: object) -> list[float]:
    return [_f(float(x)) for x in xs]  # type: ignore[attr-defined]


def _bools(xs: object) -> list[bool]:
    return [bool(x) for x in xs]  # type: ignore[attr-defined]
