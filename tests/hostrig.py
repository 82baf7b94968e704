"""A host of simulated spindles as the hosted-outlet tests start it (tests/mqtt/test_mqtt_hosted.py,
tests/opcua/test_opcua_hosted.py): each spindle's real drivers against its own simulated DAQ and CAN bus
(``simulator.simrig``), at a speed-up, on one scaled clock; and the plant run every spindle's devices play."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from model.plant import PlantRun, Segment
from service.host.fleet import Host
from service.host.runtime import ScaledClock
from service.settings import Settings
from simulator.simrig import SimAddress, make_drivers
from tests.service.conftest import plant_run

__all__ = ["host_plant_run", "simulated_host"]


def simulated_host(
    settings: Settings,
    addresses: Mapping[str, SimAddress],
    *,
    speedup: float,
    on_event: Callable[[str], None] = lambda _m: None,
) -> Host:
    """The host of ``settings``; the spindle on Modbus port p gets the drivers of the device on p."""
    clock = ScaledClock(speedup)
    by_port = {a.port: a for a in addresses.values()}
    return Host(
        settings=settings,
        clock=clock,
        devices=lambda s: make_drivers(s, by_port[s.modbus.port], clock=clock),
        on_event=on_event,
        simulated_time=True,
    )


def host_plant_run() -> PlantRun:
    """2 h at 3000 rpm and 5 N·m in a 22-°C shop (seed 11): what each simulated spindle here plays."""
    return plant_run([Segment(7200.0, 3000.0, 5.0, 22.0)], seed=11)
