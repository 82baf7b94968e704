"""The same driver checks against real devices, only when the environment says where they are.

``CHTC_TEST_MODBUS=host:port`` (a DAQ serving the device contract's register map, docs/drivers.md, read-only)
and/or
``CHTC_TEST_CAN=interface:channel`` (a bus carrying ``SpindleStatus`` frames). Skipped otherwise.
"""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest

from drivers.can_sensor import CanSpindleSensor
from drivers.modbus_daq import ModbusDaq
from drivers.quality import Quality

MODBUS = os.environ.get("CHTC_TEST_MODBUS", "")
CAN = os.environ.get("CHTC_TEST_CAN", "")


@pytest.mark.skipif(not MODBUS, reason="set CHTC_TEST_MODBUS=host:port to test a real DAQ")
def test_real_daq_poll() -> None:
    host, port = MODBUS.rsplit(":", 1)

    async def main() -> None:
        async with ModbusDaq(host, int(port), timeout_s=2.0) as daq:
            first = await daq.read()
            assert first.temps_c.shape == (32,) and first.quality.dtype == np.uint8
            assert set(first.quality.tolist()) <= {int(q) for q in Quality}
            assert np.all(np.isnan(first.temps_c) | ((first.temps_c > -60) & (first.temps_c < 400)))

    asyncio.run(main())


@pytest.mark.skipif(not CAN, reason="set CHTC_TEST_CAN=interface:channel to test a real CAN bus")
def test_real_can_frames() -> None:
    interface, channel = CAN.split(":", 1)

    async def main() -> None:
        async with CanSpindleSensor(interface=interface, channel=channel, stale_after_s=1.0) as sensor:
            readings = [await sensor.read() for _ in range(20)]
            assert all(0 <= r.speed_rpm <= 65535 for r in readings)
            assert sensor.metrics.events.get("frames_lost", 0) == 0

    asyncio.run(main())
