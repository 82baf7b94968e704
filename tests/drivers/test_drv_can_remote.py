"""CAN driver over python-can-remote (the cross-process interface) against the simulator's hub."""

from __future__ import annotations

import asyncio
import uuid

import can
import pytest

from drivers.base import Backoff
from drivers.can_codec import encode_status
from drivers.can_sensor import CanSpindleSensor
from drivers.errors import DeviceUnavailableError
from drivers.sim.can_hub import CanHub

from .drvhelpers import free_port, poll_until


def test_remote_bus_refused_then_hub_appears_and_frames_flow() -> None:
    channel = f"drv-{uuid.uuid4().hex}"
    port = free_port()
    url = f"ws://127.0.0.1:{port}/"

    async def main() -> None:
        sensor = CanSpindleSensor(
            interface="remote", channel=url, stale_after_s=0.5, backoff=Backoff(initial_s=0.05, max_s=0.2)
        )
        with pytest.raises(DeviceUnavailableError, match="cannot open bus"):
            await sensor.connect()
        hub = CanHub(url, channel=channel)
        hub.start()
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        task = asyncio.create_task(sensor.run(interval_s=0.0))
        try:
            await poll_until(lambda: sensor.connected, timeout_s=5)
            k = 0

            def received() -> bool:
                nonlocal k
                tx.send(
                    can.Message(
                        arbitration_id=0x181,
                        data=encode_status(2500 + k, 4.5, k % 16, 0),
                        is_extended_id=False,
                    )
                )
                k += 1
                return sensor.metrics.reads_ok >= 10

            await poll_until(received, timeout_s=10)
            r = sensor.latest()
            assert r.torque_nm == 4.5 and 2500 <= r.speed_rpm < 2500 + k
            assert sensor.metrics.connect_failures == 1 and sensor.metrics.connects == 1
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await sensor.close()
            tx.shutdown()
            hub.stop()

    asyncio.run(main())
