"""Sparkplug B topics and payloads (Eclipse Sparkplug 3.0; pure: bytes in, bytes out).

Edge node = this instance (``group_id``/``edge_node_id``), device = a spindle (``device_id``; with
``[[spindles]]`` one device per spindle, all under the one edge node)::

    spBv1.0/{group}/NBIRTH/{node}            bdSeq, Node Control/Rebirth          seq 0
    spBv1.0/{group}/DBIRTH/{node}/{device}   every metric: name, alias, datatype,  seq 1 (2, 3, ... one per
                                             properties engUnit/engLow/engHigh     device)
                                             (/Quality)
    spBv1.0/{group}/DDATA/{node}/{device}    changed metrics by alias only         the next seq (mod 256)
    spBv1.0/{group}/DDEATH/{node}/{device}   a device that stopped (no metrics)    the next seq
    spBv1.0/{group}/NDEATH/{node}            bdSeq (the MQTT Will; no seq)
    spBv1.0/{group}/NCMD/{node}              Node Control/Rebirth = true -> births again (NBIRTH and every
                                             device's DBIRTH), same bdSeq

``SparkplugNode`` holds the edge node's one sequence number (shared by all its devices, as Sparkplug says)
and the aliases (the same for every device); ``SparkplugSession`` is the node with one device (a single
spindle). The outlet (``service.serve.mqtt.outlet``) owns the connection. Payloads are the generated
``sparkplug_b_pb2`` (Eclipse Tahu's ``sparkplug_b.proto``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

from service.errors import ServiceError
from service.serve.mqtt import sparkplug_b_pb2 as pb
from service.serve.mqtt.points import CATALOGUE, DataType, MetricDef, Point, Quality, Value

__all__ = [
    "NAMESPACE",
    "REBIRTH",
    "PayloadError",
    "SparkplugNode",
    "SparkplugSession",
    "SparkplugTopics",
    "ms",
]

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"


class PayloadError(ServiceError, ValueError):
    """A received Sparkplug payload that cannot be decoded."""


def ms(t: datetime) -> int:
    """Epoch milliseconds of an aware UTC datetime (Sparkplug timestamps)."""
    return round(t.timestamp() * 1000.0)


@dataclass(frozen=True)
class SparkplugTopics:
    """The edge node's topics; ``device`` names the device of a single spindle (``dbirth``, ``ddata``), and
    :meth:`of` gives any device's."""

    group: str
    node: str
    device: str = ""

    def _node(self, kind: str) -> str:
        return f"{NAMESPACE}/{self.group}/{kind}/{self.node}"

    @property
    def nbirth(self) -> str:
        return self._node("NBIRTH")

    @property
    def ndeath(self) -> str:
        return self._node("NDEATH")

    @property
    def ncmd(self) -> str:
        return self._node("NCMD")

    @property
    def dbirth(self) -> str:
        return f"{self._node('DBIRTH')}/{self.device}"

    @property
    def ddata(self) -> str:
        return f"{self._node('DDATA')}/{self.device}"

    def of(self, kind: str, device: str) -> str:
        """``kind`` (``DBIRTH``, ``DDATA``, ``DDEATH``) of ``device``."""
        return f"{self._node(kind)}/{device}"


def _set_value(m: pb.Payload.Metric, datatype: DataType, value: Value) -> None:
    if value is None:
        m.is_null = True
    elif datatype is DataType.BOOLEAN:
        m.boolean_value = bool(value)
    elif datatype is DataType.STRING:
        m.string_value = str(value)
    elif datatype is DataType.DOUBLE:
        m.double_value = float(value)  # type: ignore[arg-type]
    elif datatype is DataType.DATETIME:
        m.long_value = ms(value) if isinstance(value, datetime) else int(value)
    elif datatype in (DataType.INT64, DataType.UINT64):
        m.long_value = int(value) % 2**64  # type: ignore[arg-type]  # two's complement for Int64
    else:
        m.int_value = int(value) % 2**32  # type: ignore[arg-type]  # two's complement for Int32


def _prop(ps: pb.Payload.PropertySet, key: str, datatype: DataType, value: Value) -> None:
    ps.keys.append(key)
    v = ps.values.add()
    v.type = int(datatype)
    if isinstance(value, str):
        v.string_value = value
    elif datatype is DataType.DOUBLE:
        v.double_value = float(value)  # type: ignore[arg-type]
    else:
        v.int_value = int(value) % 2**32  # type: ignore[arg-type]


def _quality(m: pb.Payload.Metric, q: Quality) -> None:
    if q.sparkplug != Quality.GOOD:
        _prop(m.properties, "Quality", DataType.INT32, q.sparkplug)


class SparkplugNode:
    """Sequence number and aliases of one edge node with any number of devices (module docstring); pure:
    payloads out, no I/O.

    Not thread-safe: the outlet's publisher task is its only user. Aliases are the catalogue's positions
    (1-based; 0 is ``bdSeq``'s place and unused), stable across births and versions that only append, and
    the same for every device.
    """

    def __init__(self, *, catalogue: Sequence[MetricDef] = CATALOGUE) -> None:
        self.catalogue = tuple(catalogue)
        self.alias = {m.name: i for i, m in enumerate(self.catalogue, start=1)}
        self._seq = 0

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (self._seq + 1) % 256
        return seq

    def death(self, bd_seq: int, now: datetime) -> bytes:
        """NDEATH: the Will registered at connect; carries ``bdSeq`` and no ``seq``."""
        p = pb.Payload()
        p.timestamp = ms(now)
        m = p.metrics.add()
        m.name, m.timestamp, m.datatype, m.long_value = BDSEQ, ms(now), DataType.INT64, bd_seq
        return p.SerializeToString()

    def nbirth(self, bd_seq: int, now: datetime) -> bytes:
        """NBIRTH (seq 0, ``bdSeq``, ``Node Control/Rebirth``): restarts the sequence; the devices' DBIRTHs
        follow it (after each connect and each honoured rebirth)."""
        self._seq = 0
        nb = pb.Payload()
        nb.timestamp, nb.seq = ms(now), self._next_seq()
        m = nb.metrics.add()
        m.name, m.timestamp, m.datatype, m.long_value = BDSEQ, ms(now), DataType.INT64, bd_seq
        m = nb.metrics.add()
        m.name, m.timestamp, m.datatype, m.boolean_value = REBIRTH, ms(now), DataType.BOOLEAN, False
        return nb.SerializeToString()

    def dbirth(self, points: Mapping[str, Point], now: datetime) -> bytes:
        """DBIRTH of one device: every metric with its alias, datatype, properties and current value (an
        absent one null and bad)."""
        db = pb.Payload()
        db.timestamp, db.seq = ms(now), self._next_seq()
        for d in self.catalogue:
            m = db.metrics.add()
            m.name, m.alias, m.datatype = d.name, self.alias[d.name], int(d.datatype)
            p = points.get(d.name) or Point(None, Quality.BAD, now)
            m.timestamp = ms(p.t)
            _set_value(m, d.datatype, p.value)
            if d.unit is not None:
                _prop(m.properties, "engUnit", DataType.STRING, d.unit)
            if d.low is not None and d.high is not None:
                _prop(m.properties, "engLow", DataType.DOUBLE, d.low)
                _prop(m.properties, "engHigh", DataType.DOUBLE, d.high)
            _quality(m, p.quality)
        return db.SerializeToString()

    def ddata(self, points: Mapping[str, Point], now: datetime, *, historical: bool = False) -> bytes:
        """DDATA with ``points`` (name -> point) by alias only; ``historical``: values from before the
        current birth (sent after a reconnect), which a host must not take as the current value."""
        p = pb.Payload()
        p.timestamp, p.seq = ms(now), self._next_seq()
        for name, point in points.items():
            d = self.catalogue[self.alias[name] - 1]
            m = p.metrics.add()
            m.alias, m.datatype, m.timestamp = self.alias[name], int(d.datatype), ms(point.t)
            if historical:
                m.is_historical = True
            _set_value(m, d.datatype, point.value)
            _quality(m, point.quality)
        return p.SerializeToString()

    def ddeath(self, now: datetime) -> bytes:
        """DDEATH of one device (its spindle stopped): a timestamp and the next ``seq``, no metrics; a host
        marks the device's metrics stale until its next DBIRTH."""
        p = pb.Payload()
        p.timestamp, p.seq = ms(now), self._next_seq()
        return p.SerializeToString()


class SparkplugSession(SparkplugNode):
    """The edge node with one device, ``topics.device`` (a single spindle: today's names)."""

    def __init__(self, topics: SparkplugTopics, *, catalogue: Sequence[MetricDef] = CATALOGUE) -> None:
        super().__init__(catalogue=catalogue)
        self.topics = topics

    def births(
        self, bd_seq: int, points: Mapping[str, Point], now: datetime
    ) -> tuple[tuple[str, bytes], tuple[str, bytes]]:
        """NBIRTH (seq 0) and the device's DBIRTH (seq 1)."""
        nb = self.nbirth(bd_seq, now)
        return (self.topics.nbirth, nb), (self.topics.dbirth, self.dbirth(points, now))

    def data(self, points: Mapping[str, Point], now: datetime, *, historical: bool = False) -> bytes:
        """The device's DDATA (:meth:`SparkplugNode.ddata`)."""
        return self.ddata(points, now, historical=historical)


def is_rebirth_request(payload: bytes) -> bool:
    """An NCMD asking for a rebirth (``Node Control/Rebirth`` = true); ``PayloadError`` if undecodable."""
    p = pb.Payload()
    try:
        p.ParseFromString(payload)
    except Exception as err:  # protobuf's DecodeError
        raise PayloadError(f"NCMD payload: {err}") from err
    return any(m.name == REBIRTH and m.HasField("boolean_value") and m.boolean_value for m in p.metrics)


def now_utc() -> datetime:
    return datetime.now(UTC)
