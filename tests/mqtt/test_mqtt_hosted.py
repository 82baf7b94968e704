"""One Sparkplug B edge node for a host's spindles (issue 43, "Hosted outlets", the Sparkplug part): with
``[[spindles]]`` and ``[mqtt] enabled``, one NBIRTH, a DBIRTH per spindle (named by its id, or its
``spindles[i].mqtt.device_id``), DDATA per spindle from its own views, one sequence number for the node; a
spindle whose DAQ stops shows it in its own metrics' quality while the others' DDATA go on; NCMD rebirth
gives the NBIRTH and every DBIRTH again; a stopped spindle's feed gives its DDEATH. Before, ``[mqtt]`` with
``[[spindles]]`` was refused at start.

A real Mosquitto of the test's own (``tests.mqtt.peers.broker``) and a subscriber decoding with the repo's
``sparkplug_b_pb2``; the host test runs real drivers against simulated devices (as
``tests/opcua/test_opcua_hosted.py``)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from prometheus_client import generate_latest

from api.fleet import MergedMetrics
from service.host.fleet import Host, HostError
from service.host.runtime import ScaledClock
from service.host.runtime import free_port as free_api_port
from service.mqttsettings import MqttSettings
from service.serve.mqtt import sparkplug_b_pb2 as pb
from service.serve.mqtt.devices import Devices
from service.serve.mqtt.outlet import MqttOutlet
from service.serve.mqtt.points import CATALOGUE, Point, Quality
from service.serve.mqtt.sparkplug import SparkplugNode
from service.settings import Settings
from simulator.simrig import SimAddress, plant_rig
from tests.hostrig import host_plant_run, simulated_host
from tests.mqtt.peers import MOSQUITTO, Broker, broker
from tests.mqtt.test_mqtt_outlet import Reader

T0 = datetime(2026, 11, 29, 12, 0, tzinfo=UTC)
SPEEDUP = 40.0
BANDS = MqttSettings().deadbands.model_dump()


# --- the pure parts ----------------------------------------------------------------------------------------
def _decode(body: bytes) -> pb.Payload:
    p = pb.Payload()
    p.ParseFromString(body)
    return p


def test_one_sequence_for_the_node_across_its_devices_and_a_ddeath_takes_the_next() -> None:
    node = SparkplugNode()
    bodies = [node.nbirth(3, T0), node.dbirth({}, T0), node.dbirth({}, T0), node.ddata({}, T0)]
    bodies.append(node.ddeath(T0))
    assert [_decode(b).seq for b in bodies] == [0, 1, 2, 3, 4]
    death = _decode(bodies[-1])
    assert len(death.metrics) == 0 and death.timestamp == int(T0.timestamp() * 1000)
    assert _decode(node.nbirth(3, T0)).seq == 0  # a rebirth restarts it


def test_devices_keep_their_own_buffers_and_the_sender_takes_the_oldest_of_any() -> None:
    devs = Devices(["a", "b"], buffer_messages=2, deadbands=BANDS)
    h = {"Chtc/H1": Point(40.0, Quality.GOOD, T0)}
    assert devs.offer("a", h) and devs.offer("b", h)
    assert not devs.offer("a", h)  # unchanged: nothing queued
    for v in (41.0, 42.0, 43.0):  # a's buffer keeps its newest 2; b's is untouched
        devs.offer("a", {"Chtc/H1": Point(v, Quality.GOOD, T0)})
    assert (devs.buffered, devs.dropped) == (3, 2)
    taken = [devs.take() for _ in range(3)]
    assert [(i.device, i.points["Chtc/H1"].value) for i in taken if i] == [
        ("b", 40.0),
        ("a", 42.0),
        ("a", 43.0),
    ]
    devs.offer("b", {"Chtc/H1": Point(50.0, Quality.GOOD, T0)})
    devs.born("a")  # a's birth: b's queued item is not history ...
    item = devs.take()
    assert item is not None and item.device == "b" and not devs.historical(item)
    devs.born("b")  # ... until b's own birth, after which it goes out flagged historical
    assert devs.historical(item)
    devs.put_back(item)
    assert devs.stop("b") and not devs.stop("b")  # its DDEATH once; its buffer gone
    assert devs.take() is None and devs.live == [devs["a"]]


def test_a_spindle_may_name_its_own_device_and_nothing_else_of_the_connection() -> None:
    def hosted(mqtt: dict[str, Any], **top: Any) -> Settings:
        return Settings(
            spindles=[
                {"id": "a", "can": {"channel": "a"}},
                {"id": "b", "modbus": {"port": 5999}, "can": {"channel": "b"}, "mqtt": mqtt},
            ],
            mqtt={"enabled": True, **top},
        )

    got = [s.mqtt.for_spindle(s.spindle.id).device for s in hosted({"device_id": "press-2"}).per_spindle()]
    assert got == ["a", "press-2"]
    with pytest.raises(ValueError, match=r"spindles\[1\]\.mqtt\.group_id: not per spindle"):
        hosted({"group_id": "other"})
    with pytest.raises(ValueError, match=r"spindles\[1\]\.mqtt\.device_id"):
        hosted({"device_id": "a/b"})
    with pytest.raises(ValueError, match="share the mqtt device id a"):
        hosted({"device_id": "a"})
    with pytest.raises(ValueError, match="share the mqtt device id x"):  # one name for every device
        hosted({}, device_id="x")
    with pytest.raises(HostError, match=r"mqtt\.device_id"):  # [mqtt] device_id names one spindle's: refused
        settings = hosted({"device_id": "press-2"}, device_id="x")
        Host(settings=settings, clock=ScaledClock(1.0), devices=None, on_event=print)  # type: ignore[arg-type]
    Host(settings=hosted({}), clock=ScaledClock(1.0), devices=None, on_event=print)  # type: ignore[arg-type]


# --- against a broker --------------------------------------------------------------------------------------
@dataclass
class Seen:
    """Every Sparkplug message of one group, decoded: (monotonic time, kind, device or "", payload)."""

    msgs: list[tuple[float, str, str, pb.Payload]] = field(default_factory=list)

    def of(self, kind: str, device: str | None = None, after: float = 0.0) -> list[pb.Payload]:
        return [p for t, k, d, p in self.msgs if k == kind and (device is None or d == device) and t >= after]

    def devices(self, kind: str, after: float = 0.0) -> set[str]:
        return {d for t, k, d, _ in self.msgs if k == kind and t >= after}


@contextlib.asynccontextmanager
async def subscriber(port: int, group: str) -> AsyncIterator[tuple[Seen, aiomqtt.Client]]:
    seen = Seen()
    async with aiomqtt.Client("127.0.0.1", port, identifier=f"test-host-{os.getpid()}-{group}") as client:
        await client.subscribe(f"spBv1.0/{group}/#", qos=1)

        async def collect() -> None:
            async for m in client.messages:
                levels = str(m.topic).split("/")
                device = levels[4] if len(levels) > 4 else ""
                assert isinstance(m.payload, bytes)
                seen.msgs.append((time.monotonic(), levels[2], device, _decode(m.payload)))

        task = asyncio.create_task(collect())
        try:
            yield seen, client
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


async def until(pred: Callable[[], bool], timeout_s: float, every_s: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        await asyncio.sleep(every_s)
    return pred()


def rebirth_request() -> bytes:
    p = pb.Payload()
    p.timestamp = int(time.time() * 1000)
    m = p.metrics.add()
    m.name, m.datatype, m.boolean_value = "Node Control/Rebirth", 11, True
    return p.SerializeToString()


@pytest.fixture
def mosquitto(tmp_path: Path):  # type: ignore[no-untyped-def]
    if not Path(MOSQUITTO).exists():
        pytest.skip("mosquitto not installed (.ci/run installs it)")
    with broker(tmp_path) as b:
        yield b


def test_a_stopped_device_gets_its_ddeath_and_the_others_go_on(mosquitto: Broker, tmp_path: Path) -> None:
    """The outlet with two devices: births for both, then d1's feed closes (its spindle stopped): a DDEATH on
    d1's topic with the next seq, and d2's DDATA after it."""
    group = f"dd{os.getpid()}"

    async def scenario() -> None:
        s = MqttSettings(enabled=True, port=mosquitto.port, group_id=group, edge_node_id="n", tick_s=60.0)
        outlet = MqttOutlet(s, state_dir=tmp_path, devices=["d1", "d2"])
        async with subscriber(mosquitto.port, group) as (seen, _):
            for feed in outlet.feeds.values():
                feed.on_view(Reader())
            await outlet.start()
            assert await until(lambda: seen.devices("DBIRTH") == {"d1", "d2"}, 30.0)
            assert len(seen.of("NBIRTH")) == 1
            await outlet.feeds["d1"].close()
            assert await until(lambda: bool(seen.of("DDEATH", "d1")), 30.0)
            t_death = seen.msgs[-1][0]
            outlet.feeds["d2"].on_view(Reader())  # the heartbeat moves: a DDATA
            outlet.feeds["d1"].on_view(Reader())  # stopped: nothing
            assert await until(lambda: bool(seen.of("DDATA", "d2", after=t_death)), 30.0)
            await asyncio.sleep(0.3)
            assert not seen.of("DDATA", "d1", after=t_death)
            await outlet.close()
            assert await until(lambda: bool(seen.of("NDEATH")), 30.0)
            seqs = [p.seq for _, k, _, p in seen.msgs if k != "NDEATH"]
            assert seqs == list(range(len(seqs)))  # one sequence for the node, DDEATH included

    asyncio.run(scenario())


def say(msg: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} {msg}", flush=True)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_one_edge_node_one_device_per_spindle_each_fed_by_its_own(mosquitto: Broker, tmp_path: Path) -> None:
    group = f"cell{os.getpid()}"
    out = asyncio.run(host_scenario(mosquitto, tmp_path, group))
    print(out["timing"])


async def host_scenario(mosquitto: Broker, tmp_path: Path, group: str) -> dict[str, Any]:
    ids = ("a", "b", "c")
    devices = {"a": "a", "b": "b", "c": "press-3"}  # c names its own device
    addresses = {sid: SimAddress.free(speedup=SPEEDUP) for sid in ids}
    settings = Settings(
        spindles=[
            {"id": sid, "modbus": {"port": a.port}, "can": {"channel": a.channel}}
            | ({"mqtt": {"device_id": devices[sid]}} if devices[sid] != sid else {})
            for sid, a in addresses.items()
        ],
        api={"port": free_api_port()},
        database={"url": f"sqlite:///{tmp_path / 'fleet.db'}"},
        engine={"identification_workers": 1},
        mqtt={
            "enabled": True,
            "port": mosquitto.port,
            "group_id": group,
            "edge_node_id": "host-1",
            "state_dir": str(tmp_path / "state"),
            "tick_s": 1.0,
            "rebirth_min_interval_s": 0.0,
            "backoff_initial_s": 0.2,
            "backoff_max_s": 1.0,
        },
    )
    host = simulated_host(settings, addresses, speedup=SPEEDUP)
    run = host_plant_run()
    rigs = []
    out: dict[str, Any] = {}
    alias = {m.name: i for i, m in enumerate(CATALOGUE, start=1)}
    want = set(devices.values())
    async with subscriber(mosquitto.port, group) as (seen, client):
        try:
            await host.start(api=False)
            assert host.mqtt is not None
            rigs = [await plant_rig(run, address=a) for a in addresses.values()]
            t0 = time.monotonic()
            say("host started")
            assert await until(lambda: seen.devices("DBIRTH") == want, 60.0), seen.devices("DBIRTH")
            say(f"births ({time.monotonic() - t0:.1f} s)")
            assert len(seen.of("NBIRTH")) == 1
            born = {d: seen.of("DBIRTH", d)[0] for d in want}
            assert all({m.name for m in b.metrics} == {m.name for m in CATALOGUE} for b in born.values())

            def speed_good(device: str, after: float = 0.0) -> bool:
                return any(
                    m.alias == alias["Condition/Speed"] and abs(m.double_value - 3000.0) < 50.0
                    for p in seen.of("DDATA", device, after=after)
                    for m in p.metrics
                )

            assert await until(lambda: all(speed_good(d) for d in want), 150.0), seen.devices("DDATA")
            t_data = time.monotonic()
            say(f"every spindle's speed in its DDATA ({t_data - t0:.1f} s)")

            def values(device: str, name: str, after: float) -> list[tuple[Any, int]]:
                """(value, Sparkplug quality) of ``name`` in ``device``'s DDATA after ``after``."""
                out = []
                for p in seen.of("DDATA", device, after=after):
                    for m in p.metrics:
                        if m.alias == alias[name]:
                            q = dict(zip(m.properties.keys, m.properties.values, strict=True)).get("Quality")
                            value = getattr(m, m.WhichOneof("value") or "is_null")
                            out.append((value, 192 if q is None else q.int_value))
                return out

            def lost(after: float) -> bool:
                """a's device dead, or its own metrics saying its DAQ is gone: a measured value's quality bad
                or stale, or its DAQ's health down with the compensation no longer fresh."""
                if seen.of("DDEATH", "a", after=after):
                    return True
                bad = any(
                    q in (0, 500)
                    for p in seen.of("DDATA", "a", after=after)
                    for m in p.metrics
                    if m.alias != alias["Status/SampleAge"]
                    for q in [
                        v.int_value for k, v in zip(m.properties.keys, m.properties.values, strict=True)
                    ]
                )
                down = any(v in ("down", "degraded") for v, _ in values("a", "Health/modbus", after))
                code = [v for v, _ in values("a", "Status/Code", after)]
                return bad or (down and bool(code) and code[-1] != "fresh")

            await rigs[0].daq_server.stop()  # a's DAQ gone; b's and c's go on
            t_stop = time.monotonic()
            say(f"a's DAQ stopped ({t_stop - t0:.1f} s)")
            out["a_lost"] = await until(lambda: lost(t_stop), 60.0)
            t_lost = time.monotonic()
            trail = {n: values("a", n, t_stop)[-3:] for n in ("Health/modbus", "Status/Code", "Chtc/H1")}
            say(f"a's DAQ loss in its metrics after {t_lost - t_stop:.1f} s: {trail}")
            assert out["a_lost"], f"a's metrics did not show the lost DAQ within 60 s: {trail}"
            assert await until(
                lambda: all(len(seen.of("DDATA", d, after=t_lost)) >= 2 for d in ("b", "press-3")), 30.0
            ), "b's and press-3's DDATA stopped"
            assert all(v == "ok" for d in ("b", "press-3") for v, _ in values(d, "Health/modbus", t_stop))

            t_ask = time.monotonic()
            await client.publish(f"spBv1.0/{group}/NCMD/host-1", rebirth_request(), qos=1)
            assert await until(lambda: seen.devices("DBIRTH", after=t_ask) == want, 20.0)
            nb = seen.of("NBIRTH", after=t_ask)
            assert len(nb) == 1 and nb[0].seq == 0
            first_bd = next(m.long_value for m in seen.of("NBIRTH")[0].metrics if m.name == "bdSeq")
            assert next(m.long_value for m in nb[0].metrics if m.name == "bdSeq") == first_bd
            assert sorted(p.seq for p in seen.of("DBIRTH", after=t_ask)) == [1, 2, 3]
            say("rebirth")
            exposed = generate_latest(MergedMetrics({}, host.outlet_metrics)).decode()  # the host's /metrics
            line = r'^chtc_outlet_messages_total\{outlet="mqtt",result="sent"\} (\S+)$'
            sent = re.search(line, exposed, re.M)
            assert sent is not None and float(sent.group(1)) >= len(seen.of("DDATA")) > 0, exposed
            assert 'chtc_outlet_connected{outlet="mqtt"} 1.0' in exposed
            out["timing"] = (
                f"{t_data - t0:.1f} s from the births to every spindle's speed in DDATA; a's DAQ stopped -> "
                f"shown in its metrics after {t_lost - t_stop:.1f} s ({trail})"
            )
        finally:
            await host.stop()
            for rig in rigs:
                with contextlib.suppress(Exception):
                    await rig.stop()
        assert await until(lambda: bool(seen.of("NDEATH")), 30.0)
        nd = seen.of("NDEATH")[-1]
        assert next(m.long_value for m in nd.metrics if m.name == "bdSeq") == first_bd
    return out


def test_json_mode_gives_each_spindle_its_own_connection_topics_and_availability(
    mosquitto: Broker, tmp_path: Path
) -> None:
    """JSON with ``[[spindles]]``: one connection per spindle (each its own Will on its own availability
    topic), ``{topic_prefix}/{device}/...``; a set client_id is made unique per spindle."""
    from service.serve.mqtt.hosted import HostedMqtt

    prefix = f"shop{os.getpid()}"
    settings = Settings(
        spindles=[
            {"id": "a", "can": {"channel": "a"}},
            {"id": "b", "modbus": {"port": 5999}, "can": {"channel": "b"}, "mqtt": {"device_id": "press-2"}},
        ],
        mqtt={
            "enabled": True,
            "mode": "json",
            "port": mosquitto.port,
            "topic_prefix": prefix,
            "client_id": "cell",
            "state_dir": str(tmp_path),
            "tick_s": 1.0,
        },
    )

    async def scenario() -> None:
        spindles = {s.spindle.id: s for s in settings.per_spindle()}
        hosted = HostedMqtt(settings, spindles, clock=lambda: datetime.now(UTC), on_event=lambda _m: None)
        assert [o.settings.effective_client_id for o in hosted.outlets] == ["cell-a", "cell-press-2"]
        topics: dict[str, bytes] = {}
        async with aiomqtt.Client("127.0.0.1", mosquitto.port, identifier=f"t-json-{os.getpid()}") as c:
            await c.subscribe(f"{prefix}/#", qos=1)

            async def collect() -> None:
                async for m in c.messages:
                    assert isinstance(m.payload, bytes)
                    topics[str(m.topic)] = m.payload

            task = asyncio.create_task(collect())
            for feed in hosted.feeds.values():
                feed.on_view(Reader())
            await hosted.start()
            want = {
                f"{prefix}/{d}/{leaf}" for d in ("a", "press-2") for leaf in ("availability", "Status/Usable")
            }
            assert await until(lambda: want <= set(topics), 30.0), sorted(topics)[:5]
            assert topics[f"{prefix}/a/availability"] == b"online"
            await hosted.close()
            assert await until(lambda: topics[f"{prefix}/press-2/availability"] == b"offline", 30.0)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    asyncio.run(scenario())
