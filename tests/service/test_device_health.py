"""A CAN fault or warning status reaches /healthz: the real CAN driver listens to the simulated sensor node
on a python-can virtual bus, and the service's health view (served by the API) shows ``can`` degraded with
the reason within a couple of seconds, and ok again once the sensor reports ok."""

from __future__ import annotations

import asyncio
import time
import uuid

import can
import httpx

from api.app import create_app
from drivers.can_sensor import CanSpindleSensor
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.source import ArrayTimeline, TimelineSource
from service.core.machine import ServiceCore
from service.host.runtime import core_config
from service.settings import Settings
from service.shell.service import SoftSensorService


async def _can_health(client: httpx.AsyncClient) -> dict:
    body = (await client.get("/api/v1/healthz")).json()
    return next(d for d in body["devices"] if d["name"] == "can")


async def _wait_status(client: httpx.AsyncClient, status: str, timeout_s: float = 2.0) -> tuple[dict, float]:
    started = time.monotonic()
    while True:
        dev = await _can_health(client)
        if dev["status"] == status:
            return dev, time.monotonic() - started
        assert time.monotonic() - started < timeout_s, f"can still {dev['status']}: {dev}"
        await asyncio.sleep(0.05)


def test_can_fault_status_shows_as_degraded_with_the_reason(loaded_model) -> None:
    settings = Settings()
    core = ServiceCore(core_config(settings), model=loaded_model)
    channel = f"health-{uuid.uuid4().hex}"

    async def main() -> None:
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        faults = FaultController()
        source = TimelineSource(ArrayTimeline.constant(speed_rpm=3000.0, torque_nm=5.0))
        sensor = CanSpindleSensor(interface="virtual", channel=channel, stale_after_s=1.0)
        svc = SoftSensorService(core, worker=None, sources={"can": sensor})
        app = create_app(settings, svc)
        transport = httpx.ASGITransport(app=app)
        reader = asyncio.create_task(sensor.run(interval_s=0.0))
        try:
            async with (
                SimulatedCanNode(source, bus=tx, faults=faults),
                httpx.AsyncClient(transport=transport, base_url="http://chtc") as client,
            ):
                await _wait_status(client, "ok")
                fault = faults.inject(FaultKind.FAULT_STATUS, value=2)
                dev, took_s = await _wait_status(client, "degraded")
                assert "sensor reports fault (status byte 2)" in dev["message"]
                assert took_s < 2.0
                faults.clear(fault)
                await _wait_status(client, "ok")
                faults.inject(FaultKind.FAULT_STATUS, value=1)
                dev, _ = await _wait_status(client, "degraded")
                assert "sensor reports warning (status byte 1)" in dev["message"]
        finally:
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)
            await sensor.close()
            tx.shutdown()

    asyncio.run(main())
