"""The modbus and can settings reach the drivers that ``chtc run`` builds (``make_device_drivers``), and the
drivers work with them against the simulated devices on loopback / a python-can virtual bus."""

from __future__ import annotations

import asyncio
import uuid

import can
import pytest

from drivers.base import utc_now
from drivers.errors import DeviceTimeoutError
from drivers.registers import default_register_map
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, TimelineSource
from service.commands.run import make_device_drivers
from service.settings import Settings


def test_modbus_unit_setting_is_the_unit_the_driver_asks() -> None:
    async def main() -> None:
        source = TimelineSource(ArrayTimeline.constant(temps_c=24.0))
        async with SimulatedDaq(source, port=0, register_map=default_register_map(unit_id=17)) as sim:
            settings = Settings(modbus={"port": sim.port, "unit": 17, "timeout_s": 0.5})
            daq, _can = make_device_drivers(settings, clock=utc_now)
            async with daq:
                assert daq.unit_id == 17
                assert (await daq.read()).temps_c[0] == pytest.approx(24.0)

    asyncio.run(main())


def test_modbus_unit_unset_means_the_register_map_unit() -> None:
    daq, _can = make_device_drivers(Settings(), clock=utc_now)
    assert daq.unit_id == default_register_map().unit_id == 1


def test_can_interface_options_and_filters_reach_the_bus() -> None:
    channel = f"settings-{uuid.uuid4().hex}"
    settings = Settings(
        can={
            "interface": "virtual",
            "channel": channel,
            "filters": [{"can_id": 0x200, "can_mask": 0x7FF}],
            "options": {"receive_own_messages": False},
            "stale_after_s": 0.3,
        }
    )

    async def main() -> None:
        _daq, sensor = make_device_drivers(settings, clock=utc_now)
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        try:
            async with sensor:
                await sensor.connect()
                tx.send(can.Message(arbitration_id=0x181, data=bytes(6), is_extended_id=False))
                with pytest.raises(DeviceTimeoutError):
                    await sensor.read()  # filtered out by the bus: only 0x200 passes
        finally:
            tx.shutdown()

    asyncio.run(main())
