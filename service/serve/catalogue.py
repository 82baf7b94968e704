"""Every value the outlets serve, declared once (pure data: no asyncua, no MQTT here).

A :class:`PointDef` is one served value: its key, its OPC UA path (``Growth.Axial`` below the spindle's
object; None: not in the address space) and its Sparkplug metric name / JSON topic levels
(``Growth/Axial``; None: not published over MQTT), its type (OPC UA's built-in type name; the Sparkplug
datatype is the same type), its unit (a UNECE Rec. 20 code, :data:`UNITS`), its engineering range, a
description, and which verdict its quality follows (:data:`VERDICTS`). The OPC UA address space
(``service.serve.opcua.nodes``) and the Sparkplug metrics (``service.serve.mqtt.points``) are rendered from
:data:`POINTS`; ``tests/serve/test_catalogue.py`` fails when an outlet serves a point the catalogue lacks or
renders it with another unit, range or type.

Ranges are engineering ranges (OPC UA ``EURange``, Sparkplug ``engLow``/``engHigh``): what a display scales
to, not a clamp (a value outside is served as it is). They are the physically meaningful ones
(docs/integration.md, "One point catalogue"):

- growth and its CIs, the axis correction: ±200 µm (a spindle nose grows some tens of µm; SD43900/SD42960
  ±0.2 mm and the ISG offset ±2000 × 0.1 µm are the same ±200 µm); its 1σ 0-200 µm;
- H: 0-500 W/(m²·K) (the search box is 5-200, ``model/data/spindle.toml``; headroom for a wider one);
- speed: 0-60000 min⁻¹ (motor spindles of high-speed machining; the CAN frame carries up to 65535);
- torque: ±500 N·m (the CAN frame carries ±327.67);
- ambient: −20…60 °C (a workshop); the sensors' temperatures −50…250 °C (the probes' span);
- ages, time constants, forecast horizons: 0-86400 s (a day).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from service.contracts.snapshots import ZONE_NAMES

__all__ = ["DEVICES", "POINTS", "UNITS", "VERDICTS", "PointDef", "VType", "by_mqtt", "by_opcua"]

VType = Literal["Double", "Boolean", "String", "UInt32", "Int32", "Int64", "DateTime"]
Verdict = Literal["compensation", "chtc", "h_zone", "condition", "measured", "predicted", "service"]
# which verdict a point's quality (OPC UA StatusCode, Sparkplug/JSON quality) follows
VERDICTS: dict[str, str] = {
    "compensation": "/compensation's verdict (growth, controller values)",
    "chtc": "/chtc's verdict (H1-H7 as a set)",
    "h_zone": "/chtc's verdict; Uncertain when this zone's H is at a bound, unidentified or prior-dominated",
    "condition": "the CAN data's freshness (speed, torque, ambient)",
    "measured": "the DAQ data's freshness (measured temperatures)",
    "predicted": "the live state's verdict (predicted temperatures)",
    "service": "always Good: the service describes itself now (status, heartbeat, devices)",
}
# UNECE Rec. 20 code -> (symbol, description); OPC UA EUInformation and Sparkplug engUnit (the symbol)
UNITS: dict[str, tuple[str, str]] = {
    "D55": ("W/(m²·K)", "watt per square metre kelvin"),
    "CEL": ("°C", "degree Celsius"),
    "KEL": ("K", "kelvin"),
    "4H": ("µm", "micrometre (micron)"),
    "MMT": ("mm", "millimetre"),
    "C94": ("min⁻¹", "reciprocal minute (revolutions per minute)"),
    "NU": ("N·m", "newton metre"),
    "SEC": ("s", "second [unit of time]"),
}
# the devices of the health report (service.shell.health); one MQTT String metric each
DEVICES: tuple[str, ...] = ("modbus", "can", "db", "worker", "filter", "core", "event_loop")

H = ("D55", (0.0, 500.0))
UM = ("4H", (-200.0, 200.0))
UM_SD = ("4H", (0.0, 200.0))
MM = ("MMT", (-0.2, 0.2))
SPEED = ("C94", (0.0, 60000.0))
TORQUE = ("NU", (-500.0, 500.0))
AMBIENT = ("CEL", (-20.0, 60.0))
PROBE = ("CEL", (-50.0, 250.0))
PROBE_SD = ("KEL", (0.0, 100.0))
SECONDS = ("SEC", (0.0, 86400.0))
PER_SENSOR = -2  # ``length``: one element per sensor channel


@dataclass(frozen=True, kw_only=True)
class PointDef:
    """One served value (module docstring). ``length``: 0 a scalar, n > 0 an array of n, -1 an array of
    any length, ``PER_SENSOR`` one element per sensor channel (OPC UA only: MQTT publishes scalars)."""

    key: str
    vtype: VType
    description: str
    verdict: Verdict
    opcua: str | None = None
    mqtt: str | None = None
    unit: str | None = None
    range: tuple[float, float] | None = None
    length: int = 0

    @property
    def symbol(self) -> str | None:
        return None if self.unit is None else UNITS[self.unit][0]


def _p(
    key: str,
    vtype: VType,
    description: str,
    verdict: Verdict,
    *,
    opcua: str | None = None,
    mqtt: str | None = None,
    q: tuple[str, tuple[float, float]] | None = None,
    length: int = 0,
) -> PointDef:
    unit, rng = (None, None) if q is None else q
    return PointDef(
        key=key,
        vtype=vtype,
        description=description,
        verdict=verdict,
        opcua=opcua,
        mqtt=mqtt,
        unit=unit,
        range=rng,
        length=length,
    )


def _status() -> list[PointDef]:
    s: Verdict = "service"
    return [
        _p("status.usable", "Boolean", "apply the compensation values only if true", s,
           opcua="Status.Usable", mqtt="Status/Usable"),
        _p("status.code", "UInt32", "the StatusCode of the compensation values", s, opcua="Status.Code"),
        _p("status.text", "String", "/compensation status: fresh, predicted, identifying, stale, ...", s,
           opcua="Status.Text", mqtt="Status/Code"),
        _p("status.reason", "String", "why not usable (a reason code; empty when usable)", s,
           opcua="Status.Reason", mqtt="Status/Reason"),
        _p("status.detail", "String", "the reason for humans (never parse it)", s, opcua="Status.Detail"),
        _p("status.action", "String", "what the operator should do", s, opcua="Status.Action"),
        _p("chtc.usable", "Boolean", "H1-H7 may be used by a model that needs them (/chtc usable)", s,
           opcua="Status.HUsable", mqtt="Chtc/Usable"),
        _p("chtc.status", "String", "/chtc status", s, opcua="Status.HText", mqtt="Chtc/Status"),
        _p("chtc.reason", "String", "why H1-H7 are not usable (a reason code; empty when usable)", s,
           opcua="Status.HReason", mqtt="Chtc/Reason"),
        _p("status.newest_sample_time", "DateTime", "UTC of the newest sample", s,
           opcua="Status.NewestSampleTime", mqtt="Status/NewestSampleTime"),
        _p("status.sample_age", "Double", "age of the newest sample", s, q=SECONDS,
           opcua="Status.SampleAge", mqtt="Status/SampleAge"),
        _p("status.heartbeat", "UInt32", "+1 at every update (wraps at 2³²)", s,
           opcua="Status.Heartbeat", mqtt="Status/Heartbeat"),
    ]  # fmt: skip


def _h() -> list[PointDef]:
    out = []
    for z in ZONE_NAMES:
        out += [
            _p(f"h.{z}", "Double", f"{z}: convective heat transfer coefficient", "h_zone", q=H,
               opcua=f"H.{z}", mqtt=f"Chtc/{z}"),
            _p(f"h.{z}.ci_low", "Double", f"{z}: 95 % CI, low", "h_zone", q=H, mqtt=f"Chtc/{z}/CiLow"),
            _p(f"h.{z}.ci_high", "Double", f"{z}: 95 % CI, high", "h_zone", q=H, mqtt=f"Chtc/{z}/CiHigh"),
            _p(f"h.{z}.identified", "Boolean", f"{z}: the data determine it", "chtc",
               mqtt=f"Chtc/{z}/Identified"),
            _p(f"h.{z}.prior_dominated", "Boolean", f"{z}: the prior's, not the data's", "chtc",
               mqtt=f"Chtc/{z}/PriorDominated"),
        ]  # fmt: skip
    n = len(ZONE_NAMES)
    return [
        *out,
        _p("h.values", "Double", "H1-H7", "chtc", q=H, length=n, opcua="H.Values"),
        _p("h.ci_low", "Double", "H1-H7: 95 % CI, low", "chtc", q=H, length=n, opcua="H.CiLow95"),
        _p("h.ci_high", "Double", "H1-H7: 95 % CI, high", "chtc", q=H, length=n, opcua="H.CiHigh95"),
        _p("h.identified", "Boolean", "the data determine this H", "service", length=n,
           opcua="H.Identified"),
        _p("h.prior_dominated", "Boolean", "this H is the prior's", "service", length=n,
           opcua="H.PriorDominated"),
        _p("h.at_bound", "Boolean", "this H is on a bound of the search box", "service", length=n,
           opcua="H.AtBound"),
        _p("h.identified_at", "DateTime", "UTC end of the identification served", "service",
           opcua="H.IdentifiedAt"),
        _p("h.identification_id", "Int64", "the identification served", "service",
           opcua="H.IdentificationId", mqtt="Chtc/IdentificationId"),
    ]  # fmt: skip


def _condition() -> list[PointDef]:
    c: Verdict = "condition"
    return [
        _p("condition.speed", "Double", "spindle speed", c, q=SPEED,
           opcua="Condition.SpeedRpm", mqtt="Condition/Speed"),
        _p("condition.torque", "Double", "spindle torque", c, q=TORQUE,
           opcua="Condition.TorqueNm", mqtt="Condition/Torque"),
        _p("condition.ambient", "Double", "ambient temperature", c, q=AMBIENT,
           opcua="Condition.AmbientC", mqtt="Condition/Ambient"),
        _p("condition.state", "String", "stable or changing", c,
           opcua="Condition.State", mqtt="Condition/State"),
        _p("condition.since", "DateTime", "UTC start of this condition", c, opcua="Condition.Since"),
        _p("condition.id", "Int64", "the operating condition's id", c,
           opcua="Condition.Id", mqtt="Condition/Id"),
    ]  # fmt: skip


def _temperatures() -> list[PointDef]:
    n = PER_SENSOR
    return [
        _p("t.measured", "Double", "measured, channel 1 first", "measured", q=PROBE, length=n,
           opcua="Temperatures.Measured"),
        _p("t.predicted", "Double", "predicted by the live state", "predicted", q=PROBE, length=n,
           opcua="Temperatures.Predicted"),
        _p("t.predicted_sd", "Double", "1σ of the prediction", "predicted", q=PROBE_SD, length=n,
           opcua="Temperatures.PredictedSd"),
        _p("t.channel_ok", "Boolean", "the channel's value is usable", "service", length=n,
           opcua="Temperatures.ChannelOk"),
        _p("t.quality", "String", "ok, stale, open_circuit, ...", "service", length=n,
           opcua="Temperatures.Quality"),
        _p("t.names", "String", "channel names, channel 1 first", "service", length=n,
           opcua="Temperatures.Names"),
    ]  # fmt: skip


def _growth_value(name: str, ua_name: str, doc: str) -> PointDef:
    opcua, mqtt = f"Growth.{ua_name}", f"Growth/{ua_name}"
    return _p(f"growth.{name}", "Double", doc, "compensation", q=UM, opcua=opcua, mqtt=mqtt)


def _growth_ci(name: str, ua_name: str) -> list[PointDef]:
    return [
        _p(f"growth.{name}.ci_low", "Double", "95 % CI, low", "compensation", q=UM,
           opcua=f"Growth.{ua_name}CiLow95", mqtt=f"Growth/{ua_name}/CiLow"),
        _p(f"growth.{name}.ci_high", "Double", "95 % CI, high", "compensation", q=UM,
           opcua=f"Growth.{ua_name}CiHigh95", mqtt=f"Growth/{ua_name}/CiHigh"),
    ]  # fmt: skip


def _growth() -> list[PointDef]:
    return [
        _growth_value("axial", "Axial", "axial growth at the spindle nose, + towards the tool"),
        _p("growth.axial_sd", "Double", "axial growth: 1σ", "compensation", q=UM_SD, opcua="Growth.AxialSd"),
        *_growth_ci("axial", "Axial"),
        _growth_value("radial", "Radial", "radial growth of the nose, + outwards"),
        *_growth_ci("radial", "Radial"),
        _growth_value("steady_axial", "SteadyAxial", "axial growth if the condition and H hold (forecast)"),
        *_growth_ci("steady_axial", "SteadyAxial"),
        _p("growth.tau", "Double", "time constant of the growth", "compensation", q=SECONDS,
           opcua="Growth.TauS"),
        _p("growth.forecast_horizons", "Double", "forecast horizons", "compensation", q=SECONDS, length=-1,
           opcua="Growth.ForecastHorizons"),
        _p("growth.forecast_axial", "Double", "axial growth at the horizons", "compensation", q=UM,
           length=-1, opcua="Growth.ForecastAxial"),
        _p("growth.reference", "Double", "the compensation zero's temperature", "compensation", q=PROBE,
           opcua="Growth.ReferenceC"),
    ]  # fmt: skip


def _controller() -> list[PointDef]:
    c: Verdict = "compensation"
    return [
        _p("controller.correction", "Double", "the axis correction that cancels the growth", c, q=UM,
           opcua="Controller.CorrectionUm", mqtt="Controller/CorrectionUm"),
        _p("controller.sd43900", "Double", "SINUMERIK SD43900 $SA_TEMP_COMP_ABS_VALUE", c, q=MM,
           opcua="Controller.SD43900Mm", mqtt="Controller/SD43900"),
        _p("controller.sd42960", "Double", "SINUMERIK SD42960 $SC_TOOL_TEMP_COMP, tool axis", c, q=MM,
           opcua="Controller.SD42960Mm", mqtt="Controller/SD42960"),
        _p("controller.isg_offset", "Int32",
           "Beckhoff/ISG P-AXIS-00273 temp_comp_offset_0 in 0.1 µm (±2000: ±200 µm)", c,
           opcua="Controller.IsgOffset0p1um", mqtt="Controller/IsgOffset"),
        _p("controller.tool_dir", "Int32", "-1: the tool points to -Z", "service",
           opcua="Controller.ToolDir", mqtt="Controller/ToolDir"),
    ]  # fmt: skip


def _devices() -> list[PointDef]:
    s: Verdict = "service"
    return [
        _p("devices.names", "String", "the devices of /healthz", s, length=-1, opcua="Devices.Names"),
        _p("devices.status", "String", "ok, degraded, down, disabled", s, length=-1, opcua="Devices.Status"),
        _p("devices.ok", "Boolean", "the device is ok", s, length=-1, opcua="Devices.Ok"),
        _p("devices.age", "Double", "age of the device's newest report", s, q=SECONDS, length=-1,
           opcua="Devices.AgeS"),
        _p("devices.model_loaded", "Boolean", "the model is loaded", s, opcua="Devices.ModelLoaded"),
        *(_p(f"devices.{d}", "String", f"{d}: ok, degraded, down, disabled", s, mqtt=f"Health/{d}")
          for d in DEVICES),
    ]  # fmt: skip


def _command() -> list[PointDef]:
    """The command value (issue 42; docs/design/policy.md "The command value"): always the value to apply,
    its status says what it does, so its quality is the service's. Last: earlier MQTT aliases keep theirs."""
    s: Verdict = "service"
    return [
        _p("controller.command", "Double", "the command value: the growth the controller compensates now", s,
           q=UM, opcua="Controller.CommandUm", mqtt="Controller/Command"),
        _p("controller.command_status", "String", "following, rate_limited, holding, fading, at_limit, none",
           s, opcua="Controller.CommandStatus", mqtt="Controller/CommandStatus"),
        _p("controller.command_correction", "Double", "the axis correction of the command", s, q=UM,
           opcua="Controller.CommandCorrectionUm"),
        _p("controller.command_sd43900", "Double", "SINUMERIK SD43900 of the command", s, q=MM,
           opcua="Controller.CommandSD43900Mm", mqtt="Controller/CommandSD43900"),
        _p("controller.command_isg_offset", "Int32", "Beckhoff/ISG P-AXIS-00273 of the command, 0.1 µm", s,
           opcua="Controller.CommandIsgOffset0p1um", mqtt="Controller/CommandIsgOffset"),
        _p("controller.command_fanuc", "Int32", "FANUC IS-B units (1 µm) of the command's correction",
           s, opcua="Controller.CommandFanucUnits", mqtt="Controller/CommandFanucUnits"),
    ]  # fmt: skip


POINTS: tuple[PointDef, ...] = (
    *_status(),
    *_h(),
    *_condition(),
    *_temperatures(),
    *_growth(),
    *_controller(),
    *_devices(),
    *_command(),
)


def by_opcua() -> dict[str, PointDef]:
    """The points in the OPC UA address space, by path."""
    return {p.opcua: p for p in POINTS if p.opcua is not None}


def by_mqtt() -> dict[str, PointDef]:
    """The points published over MQTT, by metric name."""
    return {p.mqtt: p for p in POINTS if p.mqtt is not None}
