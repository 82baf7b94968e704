"""The MQTT outlet stops when a publish swallowed its cancellation (Python 3.11's ``wait_for``, gh-86296;
``service/serve/tasks.py``). A CI run hung 300 s in ``HostedMqtt.close()`` that way. The client here is a
stand-in for aiomqtt's at the one place that matters: a publish whose acknowledgement arrives in the step the
cancel does, so the cancel is consumed and the publish returns normally."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime
from pathlib import Path

import pytest

from service.mqttsettings import MqttSettings
from service.serve.mqtt.outlet import MqttOutlet
from service.serve.mqtt.points import read_points
from service.serve.tasks import stop_tasks
from tests.mqtt.test_mqtt_outlet import Reader


class SwallowingClient:
    """``publish`` number ``swallow_at`` waits until cancelled and then returns as if acknowledged."""

    def __init__(self, swallow_at: int) -> None:
        self.swallow_at = swallow_at
        self.calls = 0
        self.waiting = asyncio.Event()

    async def publish(self, topic: str, payload: object = None, qos: int = 0, retain: bool = False) -> None:
        self.calls += 1
        if self.calls != self.swallow_at:
            return
        self.waiting.set()
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            return  # the acknowledgement won the race: the cancel is gone


@pytest.mark.parametrize("swallow_at", [1, 2], ids=["availability", "value"])
def test_a_cancel_swallowed_by_a_publish_still_stops_the_connection(tmp_path: Path, swallow_at: int) -> None:
    """Publish 1 is the JSON availability (``_serve``'s own task), 2 the first value (the sender task)."""

    async def scenario() -> tuple[bool, int]:
        cfg = MqttSettings.model_validate({"enabled": True, "mode": "json", "port": 1, "device_id": "d"})
        outlet = MqttOutlet(cfg, state_dir=tmp_path)
        outlet.offer("d", read_points(Reader(), now=datetime.now(UTC), heartbeat=1))
        client = SwallowingClient(swallow_at)
        serving = asyncio.create_task(outlet._serve(client))  # type: ignore[arg-type]
        await asyncio.wait_for(client.waiting.wait(), timeout=5.0)
        serving.cancel()
        done, _ = await asyncio.wait({serving}, timeout=5.0)
        if not done:  # the hang: leave nothing running behind the test
            await stop_tasks([serving], timeout_s=5.0)
        return bool(done), client.calls

    stopped, calls = asyncio.run(scenario())
    assert stopped, "the outlet's connection task went on after its cancel"
    assert calls >= swallow_at


def test_stop_tasks_cancels_again_a_task_that_swallowed_the_first_cancel() -> None:
    async def stubborn(swallowed: list[int]) -> None:
        while True:
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                if swallowed:
                    raise
                swallowed.append(1)

    async def until(released: asyncio.Event) -> None:
        while not released.is_set():
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                continue

    async def scenario() -> tuple[bool, bool, int]:
        swallowed: list[int] = []
        one = asyncio.create_task(stubborn(swallowed))
        released = asyncio.Event()
        never = asyncio.create_task(until(released))
        await asyncio.sleep(0)
        left = await stop_tasks([one], timeout_s=5.0, again_every_s=0.05)
        abandoned = await stop_tasks([never], timeout_s=0.3, again_every_s=0.05)
        stuck = abandoned == {never} and not never.done()
        released.set()
        never.cancel()
        await asyncio.wait({never}, timeout=5.0)
        return one.cancelled() and not left, stuck, len(swallowed)

    ended, stuck, swallowed = asyncio.run(scenario())
    assert ended and swallowed == 1
    assert stuck  # bounded: a task that never ends is given up after timeout_s, not waited for
