"""The outlets serve the point catalogue, and only it (issue 43, "One point catalogue"): the OPC UA address
space as built by the server (browsed, with each variable's DataType, ValueRank, EngineeringUnits and
EURange) and the Sparkplug DBIRTH as the outlet publishes it (each metric's datatype, engUnit, engLow and
engHigh) against ``service.serve.catalogue``. Before the catalogue, the two outlets disagreed on six ranges
(growth ±2000 against ±200 µm, H 0-1000 against 0-500, ...)."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime
from typing import Any

import pytest
from asyncua import Server, ua

from service.serve.catalogue import POINTS, UNITS, by_mqtt, by_opcua
from service.serve.mqtt import sparkplug_b_pb2 as pb
from service.serve.mqtt.points import ALIASES, CATALOGUE, DataType
from service.serve.mqtt.sparkplug import SparkplugSession, SparkplugTopics
from service.serve.opcua.nodes import unit_id, variables
from service.serve.opcua.server import build_address_space

N_SENSORS = 32
VT = {
    ua.ObjectIds.Double: "Double",
    ua.ObjectIds.Boolean: "Boolean",
    ua.ObjectIds.String: "String",
    ua.ObjectIds.UInt32: "UInt32",
    ua.ObjectIds.Int32: "Int32",
    ua.ObjectIds.Int64: "Int64",
    ua.ObjectIds.DateTime: "DateTime",
}
CODES = {unit_id(code): code for code in UNITS}


async def _served_opcua() -> dict[str, dict[str, Any]]:
    """Every variable below the spindle's object, as a client would read it: path -> attributes."""
    server = Server()
    await server.init()
    idx = await server.register_namespace("urn:spindle-chtc:opcua")
    _t, instance = await build_address_space(server, idx, variables(N_SENSORS), spindle="Spindle1")
    out: dict[str, dict[str, Any]] = {}
    for group in await instance.get_children(nodeclassmask=ua.NodeClass.Object):
        gname = (await group.read_browse_name()).Name
        for var in await group.get_children(nodeclassmask=ua.NodeClass.Variable):
            name = (await var.read_browse_name()).Name
            attrs: dict[str, Any] = {
                "vtype": VT[(await var.read_data_type()).Identifier],
                "rank": await var.read_value_rank(),
                "dims": await var.read_array_dimensions(),
                "unit": None,
                "range": None,
            }
            for prop in await var.get_properties():
                pname = (await prop.read_browse_name()).Name
                value = await prop.read_value()
                if pname == "EngineeringUnits":
                    attrs["unit"] = CODES[value.UnitId]
                    attrs["symbol"] = value.DisplayName.Text
                elif pname == "EURange":
                    attrs["range"] = (value.Low, value.High)
            out[f"{gname}.{name}"] = attrs
    return out


@pytest.fixture(scope="module")
def served_opcua() -> dict[str, dict[str, Any]]:
    return asyncio.run(_served_opcua())


def _served_sparkplug() -> dict[str, dict[str, Any]]:
    session = SparkplugSession(SparkplugTopics("chtc", "edge", "Spindle1"))
    (_n, _nb), (_d, dbirth) = session.births(0, {}, datetime(2026, 11, 29, tzinfo=UTC))
    payload = pb.Payload()
    payload.ParseFromString(dbirth)
    out = {}
    for m in payload.metrics:
        props = dict(zip(m.properties.keys, m.properties.values, strict=True))
        low, high = props.get("engLow"), props.get("engHigh")
        out[m.name] = {
            "datatype": DataType(m.datatype),
            "unit": props["engUnit"].string_value if "engUnit" in props else None,
            "range": None if low is None or high is None else (low.double_value, high.double_value),
        }
    return out


def test_every_point_is_declared_once() -> None:
    keys = [p.key for p in POINTS]
    assert len(keys) == len(set(keys))
    assert len(by_opcua()) == sum(p.opcua is not None for p in POINTS)
    assert len(by_mqtt()) == sum(p.mqtt is not None for p in POINTS)
    assert all(p.opcua or p.mqtt for p in POINTS)
    assert all((p.unit is None) == (p.range is None) for p in POINTS), "a unit goes with a range"


def test_the_opcua_address_space_serves_the_catalogue_and_only_it(served_opcua: dict) -> None:
    catalogue = by_opcua()
    assert set(served_opcua) - set(catalogue) == set(), "served, not in the catalogue"
    assert set(catalogue) - set(served_opcua) == set(), "in the catalogue, not served"
    diffs = []
    for path, got in served_opcua.items():
        p = catalogue[path]
        length = N_SENSORS if p.length == -2 else p.length
        want = {
            "vtype": p.vtype,
            "rank": 1 if length else -1,
            "dims": [max(length, 0)] if length else [],
            "unit": p.unit,
            "range": p.range,
        }
        if p.unit is not None:
            want["symbol"] = UNITS[p.unit][0]
        if got != want:
            diffs.append((path, got, want))
    assert diffs == []


def test_the_sparkplug_birth_serves_the_catalogue_and_only_it() -> None:
    served = _served_sparkplug()
    catalogue = by_mqtt()
    assert set(served) == set(catalogue) == set(ALIASES) == {m.name for m in CATALOGUE}
    diffs = []
    for name, got in served.items():
        p = catalogue[name]
        want = {"datatype": DataType[p.vtype.upper()], "unit": p.symbol, "range": p.range}
        if got != want:
            diffs.append((name, got, want))
    assert diffs == []


def test_a_value_both_outlets_serve_has_one_unit_and_range(served_opcua: dict) -> None:
    """0 differences between the outlets (the issue's bar), and the issue's six values as chosen."""
    sparkplug = _served_sparkplug()
    both = [p for p in POINTS if p.opcua and p.mqtt]
    assert len(both) == 41  # 36, and the command value's 5 (issue 42)
    diffs = [
        (p.key, served_opcua[p.opcua]["range"], sparkplug[p.mqtt]["range"])
        for p in both
        if served_opcua[p.opcua]["range"] != sparkplug[p.mqtt]["range"]
        or served_opcua[p.opcua].get("symbol") != sparkplug[p.mqtt]["unit"]
    ]
    assert diffs == []
    chosen = {
        "growth.axial": (-200.0, 200.0),
        "h.H1": (0.0, 500.0),
        "condition.speed": (0.0, 60000.0),
        "condition.torque": (-500.0, 500.0),
        "condition.ambient": (-20.0, 60.0),
        "controller.sd43900": (-0.2, 0.2),
    }
    assert {k: p.range for p in POINTS for k in chosen if p.key == k} == chosen
