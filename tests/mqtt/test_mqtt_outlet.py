"""The MQTT outlet against a real Mosquitto (started by the test on its own port) and an independent peer
(Node, Eclipse Tahu's ``sparkplug-payload`` decoder): births, data, death, rebirth, the buffer across a broker
outage, and the JSON mode's retained topics and Will. The served values come from a small reader with the
service's own snapshot types (the whole service is in test_mqtt_service.py)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import pytest

from service.contracts.errors import NoDataYetError
from service.contracts.health import DeviceHealth, DeviceStatus, HealthSnapshot
from service.contracts.snapshots import ChtcSnapshot, CompensationSnapshot, ConditionSnapshot
from service.mqttsettings import MqttSettings
from service.serve.mqtt.outlet import MqttOutlet
from service.serve.mqtt.points import CATALOGUE
from tests.mqtt.peers import Broker, broker, kind, make_certificates, metrics_by_name, need_peers, peer

T = TypeVar("T")
GROUP, NODE, DEVICE = "plant", "cell-7", "spindle1"


class Reader:
    """The served values before the first sample: no H, no growth, no condition; the DAQ ``status``."""

    def __init__(self) -> None:
        self.status = DeviceStatus.DOWN

    def chtc(self) -> ChtcSnapshot | None:
        return None

    def compensation(self) -> CompensationSnapshot | None:
        return None

    def condition(self) -> ConditionSnapshot:
        raise NoDataYetError("no operating condition yet")

    def health(self) -> HealthSnapshot:
        dev = DeviceHealth(name="modbus", status=self.status, last_ok_at=None, age_s=None)
        return HealthSnapshot(
            t=datetime.now(UTC), devices=[dev], model_loaded=True, model_version="x", uptime_s=1.0
        )


def settings(port: int, **kw: object) -> MqttSettings:
    base: dict[str, object] = dict(
        enabled=True,
        port=port,
        group_id=GROUP,
        edge_node_id=NODE,
        device_id=DEVICE,
        backoff_initial_s=0.2,
        backoff_max_s=1.0,
        tick_s=60.0,
    )
    return MqttSettings.model_validate(base | kw)


async def until(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        await asyncio.sleep(0.02)


def off_loop(fn: Callable[[], T]) -> Awaitable[T]:
    return asyncio.to_thread(fn)


@pytest.fixture
def mosquitto(tmp_path: Path):  # type: ignore[no-untyped-def]
    need_peers()
    with broker(tmp_path) as b:
        yield b


def test_sparkplug_birth_data_and_death_decoded_by_an_independent_peer(
    mosquitto: Broker, tmp_path: Path
) -> None:
    async def scenario() -> None:
        with peer(mosquitto.url, "sparkplug", GROUP, NODE) as p:
            outlet = MqttOutlet(settings(mosquitto.port), state_dir=tmp_path)
            reader = Reader()
            outlet.on_view(reader)
            await outlet.start()
            nb = await off_loop(lambda: p.wait_for(kind("NBIRTH"), what="NBIRTH"))
            db = await off_loop(lambda: p.wait_for(kind("DBIRTH"), what="DBIRTH"))
            bd = metrics_by_name(nb)["bdSeq"]["value"]
            assert bd == 0 and nb["payload"]["seq"] == 0 and db["payload"]["seq"] == 1
            assert metrics_by_name(nb)["Node Control/Rebirth"] | {"timestamp": 0} == {
                "name": "Node Control/Rebirth",
                "type": "Boolean",
                "value": False,
                "timestamp": 0,
            }
            born = metrics_by_name(db)
            assert len(born) == len(CATALOGUE)
            h1 = born["Chtc/H1"]
            assert h1["type"] == "Double" and h1["alias"] > 0 and h1["value"] is None
            assert h1["properties"]["engUnit"]["value"] == "W/(m²·K)"
            assert h1["properties"]["Quality"]["value"] == 0  # no identification yet: bad
            assert born["Growth/Axial"]["properties"]["engUnit"]["value"] == "µm"
            assert born["Controller/SD43900"]["properties"]["engLow"]["type"] == "Double"
            assert born["Status/Usable"]["value"] is False and born["Status/Code"]["value"] == "no-data"
            assert born["Health/modbus"]["value"] == "down"
            assert len({m["alias"] for m in born.values()}) == len(CATALOGUE)  # aliases unique
            await until(lambda: outlet.stats().sent >= 3)  # the first view's DDATA (values born as null)
            reader.status = DeviceStatus.OK
            outlet.on_view(reader)
            dd = await off_loop(
                lambda: p.wait_for(
                    lambda ln: (
                        ln.get("kind") == "DDATA"
                        and (born["Health/modbus"]["alias"], "ok")
                        in {(m.get("alias"), m.get("value")) for m in ln["payload"]["metrics"]}
                    ),
                    what="DDATA with the DAQ's health",
                )
            )
            sent = {m["alias"]: m for m in dd["payload"]["metrics"]}
            assert all("name" not in m for m in sent.values())  # aliases only
            assert sent[born["Health/modbus"]["alias"]]["value"] == "ok"
            assert born["Status/Heartbeat"]["alias"] in sent
            assert born["Chtc/H1"]["alias"] not in sent  # unchanged: not sent
            seqs = [ln["payload"]["seq"] for ln in p.lines if ln.get("kind") in ("NBIRTH", "DBIRTH", "DDATA")]
            assert seqs == list(range(len(seqs)))
            await outlet.close()
            nd = await off_loop(lambda: p.wait_for(kind("NDEATH"), what="NDEATH"))
            assert metrics_by_name(nd)["bdSeq"]["value"] == bd and "seq" not in nd["payload"]
            stale = await off_loop(lambda: p.wait_for(lambda ln: ln.get("event") == "stale", what="stale"))
            assert stale["device"] == f"{NODE}/{DEVICE}" and stale["metrics"] == len(CATALOGUE)

    asyncio.run(scenario())


def test_a_rebirth_request_gives_births_with_the_same_bdseq_and_seq_from_zero(
    mosquitto: Broker, tmp_path: Path
) -> None:
    async def scenario() -> None:
        (tmp_path / f"mqtt-bdseq-{GROUP}-{NODE}").write_text("41\n")  # a previous run's
        with peer(mosquitto.url, "sparkplug", GROUP, NODE) as p:
            outlet = MqttOutlet(settings(mosquitto.port, rebirth_min_interval_s=30.0), state_dir=tmp_path)
            outlet.on_view(Reader())
            await outlet.start()
            nb = await off_loop(lambda: p.wait_for(kind("NBIRTH")))
            assert metrics_by_name(nb)["bdSeq"]["value"] == 42
            await until(lambda: outlet.stats().sent >= 3)
            p.send("rebirth")
            nb2 = await off_loop(lambda: p.wait_for(kind("NBIRTH"), what="rebirth NBIRTH"))
            db2 = await off_loop(lambda: p.wait_for(kind("DBIRTH"), what="rebirth DBIRTH"))
            assert metrics_by_name(nb2)["bdSeq"]["value"] == 42
            assert (nb2["payload"]["seq"], db2["payload"]["seq"]) == (0, 1)
            p.send("rebirth")  # within the rate limit: counted, not honoured
            await until(lambda: outlet.stats().rebirth_requests == 2)
            outlet.on_view(Reader())
            dd = await off_loop(lambda: p.wait_for(kind("DDATA")))
            assert dd["payload"]["seq"] == 2  # no third birth in between
            assert outlet.stats().rebirths == 1 and outlet.stats().births == 2
            await outlet.close()

    asyncio.run(scenario())


OUTAGE_S = float(os.environ.get("CHTC_TEST_MQTT_OUTAGE_S", "4"))


def test_a_broker_outage_buffers_up_to_the_bound_and_reconnects_with_a_new_birth(
    mosquitto: Broker, tmp_path: Path
) -> None:
    """The broker stops for ``CHTC_TEST_MQTT_OUTAGE_S`` (4 s; docs/integration.md shows a 60 s run): views
    keep coming, the buffer keeps the newest 5 of 8 DDATA (3 dropped, counted), and the reconnect sends a new
    NBIRTH (bdSeq + 1) and DBIRTH, then the 5 as historical DDATA."""

    async def scenario() -> None:
        with peer(mosquitto.url, "sparkplug", GROUP, NODE) as p:
            outlet = MqttOutlet(settings(mosquitto.port, buffer_messages=5), state_dir=tmp_path)
            reader = Reader()
            outlet.on_view(reader)
            await outlet.start()
            await off_loop(lambda: p.wait_for(kind("DBIRTH")))
            await until(lambda: outlet.stats().sent >= 3)
            await off_loop(mosquitto.stop)
            await until(lambda: not outlet.stats().connected)
            t0 = time.monotonic()
            for _ in range(8):  # a view each: the heartbeat changes, one DDATA each
                before = outlet.buffered + outlet.stats().dropped
                outlet.on_view(reader)
                await until(lambda b=before: outlet.buffered + outlet.stats().dropped > b)
            await until(lambda: outlet.buffered + outlet.stats().dropped == 8)
            assert outlet.buffered == 5 and outlet.stats().dropped == 3
            await asyncio.sleep(max(0.0, OUTAGE_S - (time.monotonic() - t0)))
            failures = outlet.stats().connect_failures
            assert failures >= 1  # new clients tried, refused
            await off_loop(mosquitto.start)
            t_up = time.monotonic()
            nb = await off_loop(lambda: p.wait_for(kind("NBIRTH"), timeout_s=20, what="NBIRTH after restart"))
            back_s = time.monotonic() - t_up
            assert metrics_by_name(nb)["bdSeq"]["value"] == 1
            await off_loop(lambda: p.wait_for(kind("DBIRTH")))
            historical = []
            while len(historical) < 5:
                dd = await off_loop(lambda: p.wait_for(kind("DDATA"), what="buffered DDATA"))
                assert all(m.get("isHistorical") for m in dd["payload"]["metrics"])
                historical.append(dd["payload"]["seq"])
            assert historical == [2, 3, 4, 5, 6]
            assert outlet.stats().reconnects == 1 and outlet.buffered == 0
            print(
                f"outage {time.monotonic() - t0 - back_s:.1f} s: buffered 5, dropped 3, "
                f"{failures} refused connects (backoff 0.2 s doubling to 1 s), NBIRTH {back_s:.2f} s after "
                "the broker was back, bdSeq 0 -> 1, the 5 buffered DDATA after the DBIRTH as historical"
            )
            await outlet.close()

    asyncio.run(scenario())


CHILD = """
import asyncio, sys
from pathlib import Path
from service.mqttsettings import MqttSettings
from service.serve.mqtt.outlet import MqttOutlet
sys.path.insert(0, {tests!r})
from tests.mqtt.test_mqtt_outlet import Reader

async def main():
    s = MqttSettings(enabled=True, mode="json", port={port}, topic_prefix="shop/chtc", device_id="spindle1",
                     keepalive_s=5)
    outlet = MqttOutlet(s, state_dir=Path({state!r}))
    outlet.on_view(Reader())
    await outlet.start()
    await asyncio.sleep(3600)

asyncio.run(main())
"""


def test_json_mode_publishes_retained_topics_and_its_will_says_offline_after_kill_9(
    mosquitto: Broker, tmp_path: Path
) -> None:
    root = Path(__file__).resolve().parents[2]
    code = CHILD.format(tests=str(root), port=mosquitto.port, state=str(tmp_path))
    env = os.environ | {"PYTHONPATH": str(root)}
    child = subprocess.Popen([sys.executable, "-c", code], env=env, start_new_session=True)
    try:
        with peer(mosquitto.url, "json", "shop/chtc") as p:
            p.wait_for(lambda ln: ln.get("topic", "").endswith("/Status/Heartbeat"), what="values")
        # a subscriber that comes later gets the retained values
        with peer(mosquitto.url, "json", "shop/chtc") as late:
            avail = late.wait_for(lambda ln: ln.get("topic") == "shop/chtc/spindle1/availability")
            assert avail["retain"] is True and avail["text"] == "online"
            usable = late.wait_for(lambda ln: ln.get("topic") == "shop/chtc/spindle1/Status/Usable")
            assert usable["retain"] is True
            body = __import__("json").loads(usable["text"])
            assert body["v"] is False and body["q"] == "good" and body["t"].endswith("Z")
            h1 = late.wait_for(lambda ln: ln.get("topic") == "shop/chtc/spindle1/Chtc/H1")
            assert __import__("json").loads(h1["text"]) | {"t": None} == {"v": None, "q": "bad", "t": None}
            os.killpg(child.pid, signal.SIGKILL)
            child.wait(timeout=10)
            gone = late.wait_for(
                lambda ln: ln.get("topic") == "shop/chtc/spindle1/availability" and ln["text"] == "offline",
                timeout_s=15,  # the broker sees the socket closed at once; at the latest after 1.5 × 5 s
                what="the Will",
            )
            assert gone["text"] == "offline"
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()


def test_tls_to_the_broker_verifies_its_certificate(tmp_path: Path) -> None:
    """With ``tls.ca`` the outlet connects over TLS (the peer, on the plain listener, sees the births);
    without it the broker's certificate (not signed by a system CA) is refused and nothing is published."""
    need_peers()
    ca, cert, key = make_certificates(tmp_path)

    async def scenario(b: Broker) -> None:
        assert b.tls_port is not None
        with peer(b.url, "sparkplug", GROUP, NODE) as p:
            untrusted = MqttOutlet(
                settings(b.tls_port, tls={"enabled": True}, edge_node_id="other"), state_dir=tmp_path
            )
            untrusted.on_view(Reader())
            await untrusted.start()
            await until(lambda: untrusted.stats().connect_failures >= 1)
            assert untrusted.stats().sent == 0
            await untrusted.close()
            outlet = MqttOutlet(settings(b.tls_port, tls={"ca": ca}), state_dir=tmp_path)
            outlet.on_view(Reader())
            await outlet.start()
            nb = await off_loop(lambda: p.wait_for(kind("NBIRTH"), what="NBIRTH over TLS"))
            assert nb["node"] == NODE
            await outlet.close()

    with broker(tmp_path, tls=(ca, cert, key)) as b:
        asyncio.run(scenario(b))
