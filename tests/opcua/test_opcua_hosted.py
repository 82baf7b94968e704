"""One OPC UA server for a host's spindles (issue 43, "Hosted outlets", OPC UA part): with ``[[spindles]]``
and ``[opcua] enabled``, one server with one object per spindle, named by its id, of the one type, each
object fed by its own spindle: both read their own speed, and when spindle a's DAQ hangs a's measured
temperatures leave Good while b's stay Good. Before, ``[opcua]`` with ``[[spindles]]`` was refused at start.
Real drivers against simulated devices (as ``tests/service/test_host.py``). Slow: about a minute alone."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua

from drivers.sim.faults import FaultKind
from service.host.fleet import Host, HostError
from service.host.runtime import ScaledClock, free_port
from service.settings import Settings
from simulator.simrig import SimAddress, plant_rig
from tests.hostrig import host_plant_run, simulated_host

pytestmark = pytest.mark.slow
SPEEDUP = 40.0
NS = "urn:spindle-chtc:opcua"


async def _until(pred, timeout_s: float, every_s: float = 0.2) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if await pred():
            return True
        await asyncio.sleep(every_s)
    return False


async def scenario(db_url: str) -> dict[str, Any]:
    addresses = {sid: SimAddress.free(speedup=SPEEDUP) for sid in ("a", "b")}
    settings = Settings(
        spindles=[
            {"id": sid, "modbus": {"port": a.port}, "can": {"channel": a.channel}}
            for sid, a in addresses.items()
        ],
        api={"port": free_port()},
        database={"url": db_url},
        engine={"identification_workers": 1},
        opcua={"enabled": True, "port": free_port()},
    )
    host = simulated_host(settings, addresses, speedup=SPEEDUP)
    run = host_plant_run()
    rigs = []
    out: dict[str, Any] = {}
    try:
        await host.start(api=False)
        assert host.opcua is not None
        rigs = [await plant_rig(run, address=a) for a in addresses.values()]
        async with Client(host.opcua.server.endpoint) as c:
            idx = await c.get_namespace_index(NS)

            async def read(sid: str, path: str) -> ua.DataValue:
                node = c.get_node(f"ns={idx};s={sid}.{path}")
                return await node.read_data_value(raise_on_bad_status=False)

            async def both_measured() -> bool:
                paths = ("Temperatures.Measured", "Condition.SpeedRpm")
                dvs = [await read(sid, p) for sid in "ab" for p in paths]
                return all(dv.StatusCode_.is_good() for dv in dvs)

            out["both_good"] = await _until(both_measured, 150.0)
            out["objects"] = {
                sid: (await c.get_node(f"ns={idx};s={sid}").read_type_definition()).Identifier for sid in "ab"
            }
            out["speed"] = {sid: (await read(sid, "Condition.SpeedRpm")).Value.Value for sid in "ab"}
            fault = rigs[0].daq_server.faults.inject(FaultKind.HANG)

            async def a_left_good() -> bool:
                return not (await read("a", "Temperatures.Measured")).StatusCode_.is_good()

            out["a_left_good"] = await _until(a_left_good, 60.0)
            out["b_after"] = (await read("b", "Temperatures.Measured")).StatusCode_.is_good()
            rigs[0].daq_server.faults.clear(fault)
    finally:
        await host.stop()
        for rig in rigs:
            await rig.stop()
    return out


def test_one_server_one_object_per_spindle_each_fed_by_its_own(tmp_path: Path) -> None:
    out = asyncio.run(scenario(f"sqlite:///{tmp_path / 'fleet.db'}"))
    assert out["both_good"]
    assert out["objects"] == {"a": "SpindleThermalModelType", "b": "SpindleThermalModelType"}
    assert all(abs(v - 3000.0) < 50.0 for v in out["speed"].values()), out["speed"]
    assert out["a_left_good"] and out["b_after"], out


def test_one_object_name_for_every_spindle_is_refused() -> None:
    settings = Settings(
        spindles=[
            {"id": "a", "can": {"channel": "a"}},
            {"id": "b", "modbus": {"port": 5999}, "can": {"channel": "b"}},
        ],
        opcua={"enabled": True, "spindle": "Spindle1"},
    )
    with pytest.raises(HostError, match=r"opcua\.spindle"):
        Host(settings=settings, clock=ScaledClock(1.0), devices=lambda s: None, on_event=print)  # type: ignore[arg-type, return-value]
