"""The MQTT outlet's pure parts: deadbands, the quality mapping, bdSeq across restarts, the bounded buffer,
the Sparkplug sequence and payloads, the JSON payload (no broker)."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.contracts.verdict import ChtcStatus
from service.mqttsettings import MqttSettings
from service.serve.mqtt import sparkplug_b_pb2 as pb
from service.serve.mqtt.bdseq import BdSeqStore
from service.serve.mqtt.buffer import OutBuffer
from service.serve.mqtt.plainjson import payload
from service.serve.mqtt.points import CATALOGUE, Point, Quality, changed, quality_of
from service.serve.mqtt.sparkplug import (
    PayloadError,
    SparkplugSession,
    SparkplugTopics,
    is_rebirth_request,
)

T0 = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
BANDS = MqttSettings().deadbands.model_dump()
H1 = [m for m in CATALOGUE if m.name == "Chtc/H1"]


def test_a_number_is_sent_again_only_beyond_its_deadband_or_on_a_quality_change() -> None:
    last = {"Chtc/H1": Point(40.0, Quality.GOOD, T0)}
    assert changed(H1, {"Chtc/H1": Point(40.4, Quality.GOOD, T0)}, last, BANDS) == []
    assert changed(H1, {"Chtc/H1": Point(40.6, Quality.GOOD, T0)}, last, BANDS) == ["Chtc/H1"]
    assert changed(H1, {"Chtc/H1": Point(40.0, Quality.STALE, T0)}, last, BANDS) == ["Chtc/H1"]
    assert changed(H1, {"Chtc/H1": Point(None, Quality.BAD, T0)}, last, BANDS) == ["Chtc/H1"]
    assert changed(H1, {"Chtc/H1": Point(40.0, Quality.GOOD, T0)}, {}, BANDS) == ["Chtc/H1"]
    flags = [m for m in CATALOGUE if m.name == "Status/Usable"]
    was = {"Status/Usable": Point(True, Quality.GOOD, T0)}
    assert changed(flags, {"Status/Usable": Point(False, Quality.GOOD, T0)}, was, BANDS) == ["Status/Usable"]


def test_quality_follows_the_served_status() -> None:
    got = {s: quality_of(s) for s in ChtcStatus}
    assert got[ChtcStatus.FRESH] is Quality.GOOD
    assert got[ChtcStatus.STALE] is Quality.STALE and Quality.STALE.sparkplug == 500
    assert got[ChtcStatus.NO_DATA] is Quality.BAD and Quality.BAD.json == "bad"
    for s in (ChtcStatus.IDENTIFYING, ChtcStatus.PREDICTED, ChtcStatus.AT_BOUND):
        assert got[s].sparkplug == 192 and got[s].json == "uncertain"


def test_bdseq_continues_after_a_restart_and_wraps_at_255(tmp_path: Path) -> None:
    store = BdSeqStore(tmp_path / "sub" / "bdseq")
    assert store.upcoming() == 0
    store.commit(store.upcoming())
    assert BdSeqStore(tmp_path / "sub" / "bdseq").upcoming() == 1  # a new process reads it
    store.commit(255)
    assert store.upcoming() == 0
    (tmp_path / "sub" / "bdseq").write_text("garbage")
    assert store.upcoming() == 0


def test_the_buffer_drops_the_oldest_and_counts() -> None:
    buf: OutBuffer[int] = OutBuffer(3)
    for i in range(5):
        buf.put(i)
    assert (len(buf), buf.dropped) == (3, 2)
    assert [buf.take(), buf.take()] == [2, 3]
    buf.put_back(3)
    assert [buf.take(), buf.take(), buf.take()] == [3, 4, None]


def _decode(body: bytes) -> pb.Payload:
    p = pb.Payload()
    p.ParseFromString(body)
    return p


def test_seq_runs_0_to_255_and_a_birth_restarts_it() -> None:
    s = SparkplugSession(SparkplugTopics("g", "n", "d"))
    (_, nb), (_, db) = s.births(7, {}, T0)
    assert (_decode(nb).seq, _decode(db).seq) == (0, 1)
    seqs = [_decode(s.data({}, T0)).seq for _ in range(256)]
    assert seqs[:3] == [2, 3, 4] and seqs[253] == 255 and seqs[254] == 0
    (_, nb), _ = s.births(7, {}, T0)
    assert _decode(nb).seq == 0 and _decode(nb).metrics[0].long_value == 7


def test_ddata_carries_aliases_timestamps_quality_and_signed_ints() -> None:
    s = SparkplugSession(SparkplugTopics("g", "n", "d"))
    t = T0 - timedelta(seconds=10)
    body = s.data(
        {"Controller/IsgOffset": Point(-123, Quality.STALE, t), "Chtc/H1": Point(41.5, Quality.GOOD, t)},
        T0,
        historical=True,
    )
    isg, h1 = _decode(body).metrics
    assert not isg.name and isg.alias == s.alias["Controller/IsgOffset"] and isg.is_historical
    assert isg.int_value == 2**32 - 123 and isg.timestamp == int(t.timestamp() * 1000)
    assert list(isg.properties.keys) == ["Quality"] and isg.properties.values[0].int_value == 500
    assert h1.double_value == 41.5 and not h1.HasField("properties")  # good: no Quality property


def test_a_rebirth_request_is_recognised_and_garbage_is_a_typed_error() -> None:
    p = pb.Payload()
    m = p.metrics.add()
    m.name, m.datatype, m.boolean_value = "Node Control/Rebirth", 11, True
    assert is_rebirth_request(p.SerializeToString())
    m.boolean_value = False
    assert not is_rebirth_request(p.SerializeToString())
    with pytest.raises(PayloadError):
        is_rebirth_request(b"\xff\xff\xff")


def test_json_payload_is_v_q_t() -> None:
    body = json.loads(payload(Point(T0, Quality.GOOD, T0 + timedelta(milliseconds=5))))
    assert body == {"v": "2026-11-27T12:00:00.000Z", "q": "good", "t": "2026-11-27T12:00:00.005Z"}


def test_settings_refuse_ids_that_are_not_one_topic_level() -> None:
    with pytest.raises(ValidationError, match="edge_node_id"):
        MqttSettings(edge_node_id="a/b")
    with pytest.raises(ValidationError, match="topic_prefix"):
        MqttSettings(topic_prefix="plant/#")
    assert MqttSettings(topic_prefix="plant/hall2").topic_prefix == "plant/hall2"


def test_relative_mqtt_paths_in_a_config_file_are_relative_to_it(tmp_path: Path) -> None:
    from service.settings import load_settings

    path = tmp_path / "etc" / "chtc.toml"
    path.parent.mkdir()
    path.write_text('[mqtt]\nstate_dir = "state"\n[mqtt.tls]\nca = "certs/ca.pem"\n', encoding="utf-8")
    s = load_settings(path).mqtt
    assert s.state_dir == tmp_path / "etc" / "state"
    assert s.tls.ca == tmp_path / "etc" / "certs" / "ca.pem" and s.tls.active


@pytest.mark.parametrize(
    ("mqtt", "device"),
    [
        ({}, "cell3-sp07"),  # unset: the spindle's id
        ({"device_id": "press-2"}, "press-2"),  # set: kept
    ],
)
def test_the_outlet_names_its_sparkplug_device_and_json_level_after_the_spindle(
    tmp_path: Path, mqtt: dict[str, str], device: str
) -> None:
    """The factory the runtime calls (nothing connects before ``start()``)."""
    from service.serve.mqtt.outlet import mqtt_outlet
    from service.serve.outlet import OutletContext
    from service.settings import Settings

    section = {"enabled": True, "state_dir": str(tmp_path), **mqtt}
    settings = Settings(spindle={"id": "cell3-sp07"}, mqtt=section)  # type: ignore[arg-type]
    outlet = mqtt_outlet(OutletContext(settings=settings, service=None, clock=lambda: datetime.now(UTC)))
    assert outlet.session.topics.device == device
    assert outlet.session.topics.ddata == f"spBv1.0/chtc/DDATA/chtc-1/{device}"
    assert outlet.json_topics.availability == f"chtc/{device}/availability"
